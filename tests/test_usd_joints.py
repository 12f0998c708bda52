"""The avatar's own skeleton in its blendshape USD (visemeflow/animation/usd_joints.py): UsdSkel skins the avatar
as glTF does, at rest and when the user poses its joints (a body animation put on the skeleton), with our blend
shapes playing on the face it moves. Checked with usd-core's UsdSkel.BakeSkinning against glTF's skinning formula
computed here from the file's own nodes, skins and targets, and by usd-core's validators.

Avatars: tests/skinned_head_glb.py (the demo head on a Mixamo-like skeleton: armature turned 90 degrees and scaled
0.01, head, neck and jaw influences, a body on `Spine`) and tests/avatar_glb.py (Ready Player Me's layout: a head
whose inverse bind matrices do not cancel its joints' rest transforms, teeth and eyes on nodes without a skin)."""

import numpy as np
import pygltflib as gl
import pytest
from avatar_glb import make_avatar
from blender_check import Y_UP_TO_Z_UP, probe
from factories import usd_validation_errors
from skinned_head_glb import make_skinned_head

from visemeflow.animation.load import load_character
from visemeflow.animation.usd import read_usd_weights, write_usd
from visemeflow.rig.gltf import GltfScene, _local_matrix, _quaternion_matrix

pxr = pytest.importorskip("pxr")
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel  # noqa: E402

N = 6


def weights_of(character, seed: int = 2) -> np.ndarray:
    return (np.random.default_rng(seed).random((N, character.n_shapes)) * 0.8).astype(np.float32)


def gltf_worlds(gltf: gl.GLTF2, local: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """Every node's world transform with some nodes' local transforms replaced (`local`): glTF's scene graph."""
    parents = {c: i for i, n in enumerate(gltf.nodes) for c in n.children or []}
    worlds: dict[int, np.ndarray] = {}

    def world(i: int) -> np.ndarray:
        if i not in worlds:
            own = local.get(i, _local_matrix(gltf.nodes[i]))
            worlds[i] = (world(parents[i]) if i in parents else np.eye(4)) @ own
        return worlds[i]

    for i in range(len(gltf.nodes)):
        world(i)
    return worlds


def gltf_skinned(path, node: int, targets: np.ndarray | None, local: dict[int, np.ndarray]) -> np.ndarray:
    """glTF 2.0's vertices of the skinned mesh on `node` with morph weights `targets` (in its target order) and the
    nodes posed by `local`: sum_k w_k world(joint_k) IBM_k (p + sum_s t_s d_s)."""
    scene = GltfScene(path)
    gltf = scene.gltf
    info = next(i for i in scene.meshes if node in i.nodes)
    source = scene.placed_mesh(info.index)[0]     # the arrays as stored, with JOINTS_0 / WEIGHTS_0
    skin = gltf.skins[gltf.nodes[node].skin]
    ibm = scene.reader.matrices(skin.inverseBindMatrices, "ibm")
    worlds = gltf_worlds(gltf, local)
    per_joint = np.stack([worlds[j] @ ibm[k] for k, j in enumerate(skin.joints)])
    blend = np.einsum("vk,vkij->vij", source.weights.astype(np.float64), per_joint[source.joints])
    points = source.neutral.astype(np.float64)
    if targets is not None:
        points = points + np.einsum("s,svc->vc", targets, source.deltas)
    return np.einsum("vij,vj->vi", blend[:, :3, :3], points) + blend[:, :3, 3]


def rotation_about(axis: str, angle: float) -> np.ndarray:
    q = {"x": [np.sin(angle / 2), 0, 0], "y": [0, np.sin(angle / 2), 0], "z": [0, 0, np.sin(angle / 2)]}[axis]
    return np.asarray([*q, np.cos(angle / 2)])


def posed_local(node: gl.Node, q_xyzw) -> np.ndarray:
    """The node's rest local transform with its rotation replaced."""
    m = np.eye(4)
    m[:3, :3] = _quaternion_matrix(q_xyzw) * np.asarray(node.scale or (1, 1, 1))[None, :]
    m[:3, 3] = node.translation or (0, 0, 0)
    return m


def pose_in_usd(stage: Usd.Stage, joint_token: str, q_xyzw) -> None:
    """Pose one joint on the stage's SkelAnimation as a user's body animation would: the joint added to the
    animation's joints (the others keep the Skeleton's rest transforms) with its rest translation and scale and the
    rotation `q_xyzw`."""
    anim = next(UsdSkel.Animation(p) for p in stage.Traverse() if p.IsA(UsdSkel.Animation))
    skeleton = next(UsdSkel.Skeleton(p) for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    rest = skeleton.GetRestTransformsAttr().Get()[list(skeleton.GetJointsAttr().Get()).index(joint_token)]
    translation, _, scale = UsdSkel.DecomposeTransform(rest)
    x, y, z, w = (float(c) for c in q_xyzw)
    anim.GetJointsAttr().Set(list(anim.GetJointsAttr().Get()) + [joint_token])
    anim.GetTranslationsAttr().Set(list(anim.GetTranslationsAttr().Get()) + [Gf.Vec3f(translation)])
    anim.GetRotationsAttr().Set(list(anim.GetRotationsAttr().Get()) + [Gf.Quatf(w, x, y, z)])
    anim.GetScalesAttr().Set(list(anim.GetScalesAttr().Get()) + [Gf.Vec3h(scale)])


def meshes_of(stage: Usd.Stage) -> dict[str, UsdGeom.Mesh]:
    return {p.GetName(): UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)}


def opened(path) -> Usd.Stage:
    """The file as written (not a layer that an earlier test's BakeSkinning changed in memory)."""
    layer = Sdf.Layer.FindOrOpen(str(path))
    layer.Reload(True)
    return Usd.Stage.Open(layer)


def world_points(mesh: UsdGeom.Mesh, k: int) -> np.ndarray:
    """The mesh's points at time k in the stage's space (BakeSkinning keeps points in the skeleton's space and
    gives the mesh the skeleton's transform)."""
    points = np.asarray(mesh.GetPointsAttr().Get(k), np.float64)
    m = np.asarray(mesh.ComputeLocalToWorldTransform(Usd.TimeCode(k)), np.float64)   # row-vector convention
    return points @ m[:3, :3] + m[3, :3]


@pytest.fixture(scope="module")
def mixamo(tmp_path_factory):
    root = tmp_path_factory.mktemp("usd-joints")
    path = root / "head.glb"
    make_skinned_head(path)
    character = load_character(path)
    weights = weights_of(character)
    out = write_usd(root / "head.usda", character, weights, 30.0, name="speech")
    return path, character, weights, out


def test_the_usd_holds_the_avatars_skeleton_and_skins_its_meshes_as_the_file_does(mixamo):
    path, character, weights, out = mixamo
    stage = opened(out)
    assert usd_validation_errors(stage) == []
    skeleton = next(UsdSkel.Skeleton(p) for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    assert list(skeleton.GetJointsAttr().Get()) == ["Hips", "Hips/Spine", "Hips/Spine/Neck", "Hips/Spine/Neck/Head",
                                                     "Hips/Spine/Neck/Head/Jaw"]
    meshes = meshes_of(stage)
    head, body = meshes["Mesh"], meshes["Body"]
    for mesh in (head, body):         # both skinned by the file's skin, 4 influences a vertex
        binding = UsdSkel.BindingAPI(mesh.GetPrim())
        assert binding.GetSkeletonRel().GetTargets() == [skeleton.GetPath()]
        assert binding.GetJointIndicesPrimvar().GetElementSize() == 4
    names, read, _ = read_usd_weights(out)
    assert names == character.shape_names and np.array_equal(read, weights)
    # at rest, with the weights of each frame: the character we animate (the scene as the file shows it)
    assert UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetDefaultPrim()), Gf.Interval(0, N - 1))
    for k in (0, 3, N - 1):
        expected = character.neutral + np.einsum("s,svc->vc", weights[k], character.deltas)
        np.testing.assert_allclose(world_points(head, k), expected, atol=1e-6)
    placed_body = GltfScene(path).placed_mesh(1, morph_targets=False)[1]
    np.testing.assert_allclose(world_points(body, 2), placed_body, atol=1e-6)


def test_posing_the_usd_skeleton_moves_the_avatar_as_gltf_skinning_does_with_the_face_still_speaking(mixamo):
    """A body animation on the USD's skeleton (the neck turned 0.4 rad, the spine bent): head, chin and body go
    where glTF's skinning of the same pose puts them, the blend shapes of each frame on top."""
    path, character, weights, out = mixamo
    stage = opened(out)
    gltf = GltfScene(path).gltf
    neck, spine = 3, 2                                   # tests/skinned_head_glb.py's joint nodes
    turn, bend = rotation_about("z", 0.4), rotation_about("x", 0.3)
    pose_in_usd(stage, "Hips/Spine/Neck", turn)
    pose_in_usd(stage, "Hips/Spine", bend)
    local = {neck: posed_local(gltf.nodes[neck], turn), spine: posed_local(gltf.nodes[spine], bend)}
    assert UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetDefaultPrim()), Gf.Interval(0, N - 1))
    meshes = meshes_of(stage)
    for k in (1, 4):
        expected = gltf_skinned(path, 6, weights[k], local)
        got = world_points(meshes["Mesh"], k)
        np.testing.assert_allclose(got, expected, atol=1e-6)
        assert np.abs(got - (character.neutral + np.einsum("s,svc->vc", weights[k], character.deltas))).max() > 0.02
    np.testing.assert_allclose(world_points(meshes["Body"], 2), gltf_skinned(path, 7, None, local),
                               atol=1e-6)


def test_a_head_whose_bind_pose_is_not_its_rest_pose_and_meshes_on_plain_nodes_lie_where_the_scene_shows_them(
        tmp_path):
    """Ready Player Me's layout: the head's inverse bind matrices shift it at rest (glTF skins it there, and so does
    UsdSkel now from the stored positions), teeth and eyes on nodes without a skin bound rigidly to the topmost joint,
    the body on a plain node left static; at rest every mesh is where the scene shows it, and a turned head joint
    moves the head as glTF's skinning does."""
    path = tmp_path / "avatar.glb"
    make_avatar(path)
    character = load_character(path)
    weights = weights_of(character, 7)
    out = write_usd(tmp_path / "avatar.usda", character, weights, 30.0, name="speech")
    stage = opened(out)
    assert usd_validation_errors(stage) == []
    skeleton = next(UsdSkel.Skeleton(p) for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    assert list(skeleton.GetJointsAttr().Get()) == ["Hips", "Hips/HeadJoint"]
    meshes = meshes_of(stage)
    assert not UsdSkel.BindingAPI(meshes["BodyNode"].GetPrim()).GetSkeletonRel().GetTargets()
    assert list(UsdSkel.BindingAPI(meshes["Wolf3D_Teeth"].GetPrim()).GetJointsAttr().Get()) == ["Hips"]
    assert UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetDefaultPrim()), Gf.Interval(0, N - 1))
    for k in (0, 5):
        expected = character.neutral + np.einsum("s,svc->vc", weights[k], character.deltas)
        for part in character.parts:
            np.testing.assert_allclose(world_points(meshes[part.name], k),
                                       expected[part.start:part.stop], atol=1e-6, err_msg=part.name)
    gltf = GltfScene(path).gltf
    turn = rotation_about("y", 0.5)
    stage = opened(out)                       # BakeSkinning turned the SkelRoot off: the file again
    meshes = meshes_of(stage)
    pose_in_usd(stage, "Hips/HeadJoint", turn)
    assert UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetDefaultPrim()), Gf.Interval(0, N - 1))
    head = next(p for p in character.parts if p.name == "Wolf3D_Head")
    order = [character.shape_names.index(n) for n in head.target_names]
    expected = gltf_skinned(path, 3, weights[2][order], {2: posed_local(gltf.nodes[2], turn)})
    np.testing.assert_allclose(world_points(meshes["Wolf3D_Head"], 2), expected, atol=1e-6)


def _append(g: gl.GLTF2, blob: bytearray, array: np.ndarray, kind: str, component: int) -> int:
    """`array` appended to the GLB's buffer as a new accessor; its index."""
    blob += bytes(-len(blob) % 4)
    g.bufferViews.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=array.nbytes))
    blob += array.tobytes()
    g.accessors.append(gl.Accessor(bufferView=len(g.bufferViews) - 1, componentType=component, count=len(array),
                                   type=kind))
    return len(g.accessors) - 1


def test_skins_that_disagree_on_a_joints_bind_leave_the_skeleton_out_and_say_so(tmp_path):
    """A body skinned by a second skin that binds the head joint elsewhere: the two cannot be one UsdSkel Skeleton,
    so the meshes lie where the scene shows them on the one-joint skeleton, and the layer's documentation says why."""
    path = tmp_path / "avatar.glb"
    make_avatar(path)
    g = gl.GLTF2().load(str(path))
    blob = bytearray(g.binary_blob())
    first = g.accessors[g.skins[0].inverseBindMatrices]
    ibm = np.frombuffer(bytes(blob), np.float32, 32, g.bufferViews[first.bufferView].byteOffset).reshape(2, 16).copy()
    ibm[1, 13] += 0.25                                    # the head joint's bind 0.25 m lower
    body = next(n for n in g.nodes if n.name == "BodyNode")
    n_body = g.accessors[g.meshes[body.mesh].primitives[0].attributes.POSITION].count
    attributes = g.meshes[body.mesh].primitives[0].attributes
    attributes.JOINTS_0 = _append(g, blob, np.tile(np.array([1, 0, 0, 0], np.uint8), (n_body, 1)), gl.VEC4,
                                  gl.UNSIGNED_BYTE)
    attributes.WEIGHTS_0 = _append(g, blob, np.tile(np.array([1, 0, 0, 0], np.float32), (n_body, 1)), gl.VEC4,
                                   gl.FLOAT)
    g.skins.append(gl.Skin(joints=[1, 2], inverseBindMatrices=_append(g, blob, ibm, gl.MAT4, gl.FLOAT)))
    body.skin = 1
    blob += bytes(-len(blob) % 4)
    g.buffers[0].byteLength = len(blob)
    g.set_binary_blob(bytes(blob))
    g.save_binary(str(path))
    character = load_character(path)
    out = write_usd(tmp_path / "avatar.usda", character, weights_of(character), 30.0)
    stage = opened(out)
    skeleton = next(UsdSkel.Skeleton(p) for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    assert list(skeleton.GetJointsAttr().Get()) == ["root"]
    assert "'HeadJoint' has different bind matrices in two skins" in stage.GetRootLayer().documentation


def test_blender_imports_the_avatars_armature_from_the_usd_and_plays_the_face_in_place(mixamo, tmp_path):
    """Blender's USD importer (the PyPI bpy module) makes the skeleton an armature of the avatar's joints, and the
    head it skins from the stored positions plays our weights where the scene shows it (armature turned and scaled
    0.01), the body along."""
    path, character, weights, out = mixamo
    frames = [0, 3, N - 1]
    report, meshes = probe(out, frames, tmp_path / "blender.npz", fps=30.0)
    assert list(report["bones"].values()) == [["Hips", "Spine", "Neck", "Head", "Jaw"]], report["bones"]
    ours = character.neutral[None] + np.einsum("fs,svc->fvc", weights[frames], character.deltas)
    ours = np.einsum("ij,fvj->fvi", Y_UP_TO_Z_UP, ours.astype(np.float64))
    worst = float(np.abs(meshes["Mesh"] - ours).max())
    print(f"\nBlender, head: worst {worst * 1e3:.4f} mm")
    assert worst < 1e-5
    assert np.abs(ours[1] - ours[0]).max() > 1e-3      # the face moves between the frames compared
    body = GltfScene(path).placed_mesh(1, morph_targets=False)[1]
    np.testing.assert_allclose(meshes["Body"][0], body @ Y_UP_TO_Z_UP.T, atol=1e-5)


def test_a_skeleton_deeper_than_a_usd_takes_keeps_the_meshes_at_rest_and_says_so(tmp_path):
    """A skin whose joints form a chain of 300 (a crafted file: names are whole paths, so 50,000 would spell
    gigabytes): the USD is written at once, its meshes posed at rest on the one-joint skeleton, and says why."""
    from visemeflow.animation.usd_joints import MAX_DEPTH

    path = tmp_path / "avatar.glb"
    make_avatar(path)
    g = gl.GLTF2().load(str(path))
    blob = bytearray(g.binary_blob())
    first = g.accessors[g.skins[0].inverseBindMatrices]
    ibm = np.frombuffer(bytes(blob), np.float32, 32, g.bufferViews[first.bufferView].byteOffset).reshape(2, 16)
    chain = list(range(len(g.nodes), len(g.nodes) + MAX_DEPTH + 44))
    for k, node in enumerate(chain):
        g.nodes.append(gl.Node(name=f"link{k}", translation=[0.0, 0.001, 0.0]))
        parent = g.nodes[chain[k - 1]] if k else g.nodes[2]
        parent.children = (parent.children or []) + [node]
    identity = np.tile(np.eye(4, dtype=np.float32).reshape(1, 16), (len(chain), 1))
    g.skins[0].joints = list(g.skins[0].joints) + chain
    g.skins[0].inverseBindMatrices = _append(g, blob, np.concatenate([ibm, identity]), gl.MAT4, gl.FLOAT)
    blob += bytes(-len(blob) % 4)
    g.buffers[0].byteLength = len(blob)
    g.set_binary_blob(bytes(blob))
    g.save_binary(str(path))
    character = load_character(path)
    weights = weights_of(character)
    out = write_usd(tmp_path / "avatar.usda", character, weights, 30.0)
    stage = opened(out)
    skeleton = next(UsdSkel.Skeleton(p) for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    assert list(skeleton.GetJointsAttr().Get()) == ["root"]
    assert f"deeper than the {MAX_DEPTH} a USD skeleton is made of" in stage.GetRootLayer().documentation
    meshes = meshes_of(stage)
    assert UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetDefaultPrim()), Gf.Interval(0, N - 1))
    expected = character.neutral + np.einsum("s,svc->vc", weights[3], character.deltas)
    head = next(p for p in character.parts if p.name == "Wolf3D_Head")
    np.testing.assert_allclose(world_points(meshes["Wolf3D_Head"], 3), expected[head.start:head.stop], atol=1e-6)


def _edited_avatar(path, edit) -> None:
    """tests/avatar_glb.py's avatar at `path`, changed by `edit(g, blob)` (pygltflib document, its buffer)."""
    make_avatar(path)
    g = gl.GLTF2().load(str(path))
    blob = bytearray(g.binary_blob())
    edit(g, blob)
    blob += bytes(-len(blob) % 4)
    g.buffers[0].byteLength = len(blob)
    g.set_binary_blob(bytes(blob))
    g.save_binary(str(path))


def _at_rest_where_the_scene_shows(path, tmp_path) -> Usd.Stage:
    """Write the avatar's USD and check that, baked, every driven mesh is where the character has it."""
    character = load_character(path)
    weights = weights_of(character, 11)
    out = write_usd(tmp_path / "avatar.usda", character, weights, 30.0)
    stage = opened(out)
    assert usd_validation_errors(stage) == []
    meshes = meshes_of(stage)
    assert UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetDefaultPrim()), Gf.Interval(0, N - 1))
    expected = character.neutral + np.einsum("s,svc->vc", weights[4], character.deltas)
    for part in character.parts:
        np.testing.assert_allclose(world_points(meshes[part.name], 4), expected[part.start:part.stop], atol=1e-6,
                                   err_msg=part.name)
    return opened(out)


def test_head_vertices_of_no_weight_stay_where_the_file_puts_them(tmp_path):
    """WEIGHTS_0 rows of 0 (glTF leaves such a vertex where its node puts it; UsdSkel's skinning would put it at the
    origin, 1.5 m away): the head is then bound rigidly, as placed, not skinned from its stored arrays."""
    def edit(g, blob):
        attributes = g.meshes[0].primitives[0].attributes
        accessor = g.accessors[attributes.WEIGHTS_0]
        weights = np.frombuffer(bytes(blob), np.float32, accessor.count * 4,
                                g.bufferViews[accessor.bufferView].byteOffset).reshape(-1, 4).copy()
        weights[:2] = 0.0
        attributes.WEIGHTS_0 = _append(g, blob, weights, gl.VEC4, gl.FLOAT)

    path = tmp_path / "avatar.glb"
    _edited_avatar(path, edit)
    stage = _at_rest_where_the_scene_shows(path, tmp_path)
    head = meshes_of(stage)["Wolf3D_Head"]
    # rigid, on the topmost joint (its node is under none); the body, on a plain node, stays unbound
    assert list(UsdSkel.BindingAPI(head.GetPrim()).GetJointsAttr().Get()) == ["Hips"]
    assert UsdSkel.BindingAPI(head.GetPrim()).GetJointIndicesPrimvar().GetElementSize() == 1


def test_a_joint_scaled_to_zero_at_rest_does_not_stop_the_usd(tmp_path):
    """A hidden hat: a joint scaled 0 at rest with a child joint (glTF allows it; its rest transform cannot be
    inverted): the USD is written with the whole skeleton, every mesh where the scene shows it."""
    def edit(g, blob):
        head_joint = 2
        hat, tip = len(g.nodes), len(g.nodes) + 1
        g.nodes.append(gl.Node(name="Hat", translation=[0.0, 0.2, 0.0], scale=[0.0, 0.0, 0.0], children=[tip]))
        g.nodes.append(gl.Node(name="HatTip", translation=[0.0, 0.05, 0.0]))
        g.nodes[head_joint].children = (g.nodes[head_joint].children or []) + [hat]
        first = g.accessors[g.skins[0].inverseBindMatrices]
        ibm = np.frombuffer(bytes(blob), np.float32, 32, g.bufferViews[first.bufferView].byteOffset).reshape(2, 16)
        world_head = np.linalg.inv(ibm[1].reshape(4, 4).T)     # the head joint's bind
        extra = []
        for offset in (0.2, 0.25):                              # the hat's bind as if it were scaled 1
            m = world_head.copy()
            m[:3, 3] += [0.0, offset, 0.0]
            extra.append(np.linalg.inv(m).T.reshape(16))
        g.skins[0].joints = list(g.skins[0].joints) + [hat, tip]
        g.skins[0].inverseBindMatrices = _append(g, blob, np.concatenate([ibm, np.asarray(extra, np.float32)]),
                                                 gl.MAT4, gl.FLOAT)

    path = tmp_path / "avatar.glb"
    _edited_avatar(path, edit)
    stage = _at_rest_where_the_scene_shows(path, tmp_path)
    skeleton = next(UsdSkel.Skeleton(p) for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    assert list(skeleton.GetJointsAttr().Get()) == ["Hips", "Hips/HeadJoint", "Hips/HeadJoint/Hat",
                                                     "Hips/HeadJoint/Hat/HatTip"]


def test_a_skin_without_joints_does_not_stop_the_usd(tmp_path):
    """The body's node names a skin with no joints (and the body has no JOINTS_0): the USD is written, the body
    static where the scene shows it, the head on the avatar's skeleton."""
    def edit(g, blob):
        g.skins.append(gl.Skin(name="empty", joints=[]))
        next(n for n in g.nodes if n.name == "BodyNode").skin = len(g.skins) - 1

    path = tmp_path / "avatar.glb"
    _edited_avatar(path, edit)
    stage = _at_rest_where_the_scene_shows(path, tmp_path)
    body = meshes_of(stage)["BodyNode"]
    assert not UsdSkel.BindingAPI(body.GetPrim()).GetSkeletonRel().GetTargets()
    np.testing.assert_allclose(world_points(body, 0), GltfScene(path).placed_mesh(4, morph_targets=False)[1],
                               atol=1e-6)
