"""An avatar GLB whose head is on a skeleton, as exported from Blender or Mixamo, for tests/test_bone_asset.py: the
demo head (ICT, in metres) with the 16 viseme morph targets, skinned to `Head` (and, at the chin, to a `Jaw` child
posed as `Head` is), the neck blending `Head` into `Neck`; an `Armature` node turned 90 degrees about X and scaled
0.01 (joints in centimetres); a body box skinned to `Spine`; an `idle` clip of its own that turns the neck. Bind
pose = rest pose (each inverse bind matrix the inverse of its joint's world transform), as in Ready Player Me's
files."""

from pathlib import Path

import numpy as np
import pygltflib as gl
from avatar_glb import _Blob

from visemeflow.rig import load_demo_rig
from visemeflow.rig.character import character_from_rig

ARMATURE_TURN = [np.sin(np.pi / 4), 0.0, 0.0, np.cos(np.pi / 4)]     # x, y, z, w: 90 degrees about X
ARMATURE_SCALE = 0.01
# joint: (parent, translation in the parent's frame, centimetres of the armature)
JOINTS = {"Hips": (None, [0.0, 0.0, 80.0]), "Spine": ("Hips", [0.0, 0.0, -30.0]), "Neck": ("Spine", [0.0, 0.0, -32.0]),
          "Head": ("Neck", [0.0, 0.0, -8.0]), "Jaw": ("Head", [0.0, 2.0, -4.0])}
NECK_TURN = 0.25            # radians about the neck's own Z: what the idle clip holds
NECK_FROM, NECK_TO = -0.14, -0.09   # metres (scene Y): below NECK_FROM on the neck, above NECK_TO on the head


def _matrix(translation, rotation_xyzw=(0.0, 0.0, 0.0, 1.0), scale=1.0) -> np.ndarray:
    x, y, z, w = rotation_xyzw
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    m = np.eye(4)
    m[:3, :3] = r * scale
    m[:3, 3] = translation
    return m


def joint_worlds() -> dict[str, np.ndarray]:
    """Each joint's rest world transform (4, 4)."""
    worlds = {}
    armature = _matrix([0.0, 0.0, 0.0], ARMATURE_TURN, ARMATURE_SCALE)
    for name, (parent, translation) in JOINTS.items():
        worlds[name] = (worlds[parent] if parent else armature) @ _matrix(translation)
    return worlds


def neck_turn() -> list[float]:
    return [0.0, 0.0, float(np.sin(NECK_TURN / 2)), float(np.cos(NECK_TURN / 2))]


TEETH_AT = np.array([0.0, -0.035, 0.07])    # metres, scene: behind the demo head's lips
TEETH_DROP = 0.008                           # metres the lower teeth drop at AHH = 1


def make_skinned_head(path: Path, teeth: bool = False, lips_on_neck: float = 0.0) -> dict:
    """Write the avatar (see the module); returns {"head": neutral (V, 3) m, "weights": per joint name (V,) skin
    weights of the head}. `teeth`: also a teeth mesh on a node without a skin, a child of the `Head` joint (as
    many exports place teeth), whose lower row drops with the open visemes; "teeth" is then its scene positions.
    `lips_on_neck`: that share of the skin weight of the mouth (within 2 cm of its centre) on `Neck` instead of
    `Head`, as a careless weight paint leaves it."""
    demo = character_from_rig(load_demo_rig())
    head = (demo.neutral * 0.01).astype(np.float32)
    deltas = (demo.deltas * 0.01).astype(np.float32)
    names = list(demo.shape_names)
    order = list(JOINTS)
    y, z = head[:, 1], head[:, 2]
    on_head = np.clip((y - NECK_FROM) / (NECK_TO - NECK_FROM), 0.0, 1.0)
    chin = (y > NECK_TO) & (y < -0.03) & (z > 0.06)
    weights = {name: np.zeros(len(head), np.float32) for name in order}
    weights["Neck"] = (1 - on_head).astype(np.float32)
    weights["Head"] = np.where(chin, 0.5, on_head).astype(np.float32)
    weights["Jaw"] = np.where(chin, 0.5, 0.0).astype(np.float32)
    if lips_on_neck:
        from visemeflow.animation.lips import inner_lip_pairs

        centre = head[inner_lip_pairs(demo).ravel()].mean(axis=0)
        mouth = np.linalg.norm(head - centre, axis=1) < 0.02
        for name in order:
            weights[name][mouth] *= 1 - lips_on_neck
        weights["Neck"][mouth] += lips_on_neck
    stacked = np.stack([weights[n] for n in order], axis=1)
    top = np.argsort(-stacked, axis=1)[:, :4]
    joints = top.astype(np.uint8)
    skin_weights = np.take_along_axis(stacked, top, axis=1).astype(np.float32)
    joints[skin_weights == 0] = 0

    g = gl.GLTF2(asset=gl.Asset(version="2.0", generator="test skinned head"))
    b = _Blob(g)
    g.materials.append(gl.Material(name="skin", pbrMetallicRoughness=gl.PbrMetallicRoughness(
        baseColorFactor=[0.8, 0.6, 0.5, 1.0], metallicFactor=0.0)))
    targets = [{"POSITION": b.accessor(d, gl.VEC3, gl.ARRAY_BUFFER, bounds=True)} for d in deltas]
    g.meshes.append(gl.Mesh(name="HeadMesh", primitives=[gl.Primitive(
        attributes=gl.Attributes(POSITION=b.accessor(head, gl.VEC3, gl.ARRAY_BUFFER, bounds=True),
                                 JOINTS_0=b.accessor(joints, gl.VEC4, gl.ARRAY_BUFFER),
                                 WEIGHTS_0=b.accessor(skin_weights, gl.VEC4, gl.ARRAY_BUFFER)),
        indices=b.accessor(demo.faces.astype(np.uint16).ravel(), gl.SCALAR, gl.ELEMENT_ARRAY_BUFFER),
        material=0, targets=targets)], weights=[0.0] * len(names), extras={"targetNames": names}))
    box = np.array([[x, y0, z0] for x in (-0.2, 0.2) for y0 in (-0.8, -0.2) for z0 in (-0.1, 0.1)], np.float32)
    box_faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                          [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.uint16)
    spine = order.index("Spine")
    g.meshes.append(gl.Mesh(name="BodyMesh", primitives=[gl.Primitive(
        attributes=gl.Attributes(
            POSITION=b.accessor(box, gl.VEC3, gl.ARRAY_BUFFER, bounds=True),
            JOINTS_0=b.accessor(np.tile(np.array([spine, 0, 0, 0], np.uint8), (8, 1)), gl.VEC4, gl.ARRAY_BUFFER),
            WEIGHTS_0=b.accessor(np.tile(np.array([1, 0, 0, 0], np.float32), (8, 1)), gl.VEC4, gl.ARRAY_BUFFER)),
        indices=b.accessor(box_faces.ravel(), gl.SCALAR, gl.ELEMENT_ARRAY_BUFFER), material=0)]))

    worlds = joint_worlds()
    if teeth:
        # a 6 x 2 strip: the upper row stays, the lower drops with the open visemes; stored in the Head joint's frame
        u, v = np.meshgrid(np.linspace(-0.02, 0.02, 6), [0.004, -0.004])
        placed = (np.c_[u.ravel(), v.ravel(), np.zeros(u.size)] + TEETH_AT).astype(np.float32)
        strip = np.array([[i, i + 1, i + 6] for i in range(5)] + [[i + 1, i + 7, i + 6] for i in range(5)], np.uint16)
        to_head = np.linalg.inv(worlds["Head"])
        stored = (placed @ to_head[:3, :3].T + to_head[:3, 3]).astype(np.float32)
        lower = np.arange(12) >= 6
        openness = {"AHH": 1.0, "AAA": 0.8, "OHH": 0.7, "EH": 0.5}
        teeth_deltas = np.zeros((len(names), 12, 3), np.float32)
        for name, amount in openness.items():
            teeth_deltas[names.index(name), lower, 1] = -TEETH_DROP * amount
        teeth_deltas = (teeth_deltas @ to_head[:3, :3].T).astype(np.float32)
        g.meshes.append(gl.Mesh(name="TeethMesh", primitives=[gl.Primitive(
            attributes=gl.Attributes(POSITION=b.accessor(stored, gl.VEC3, gl.ARRAY_BUFFER, bounds=True)),
            indices=b.accessor(strip.ravel(), gl.SCALAR, gl.ELEMENT_ARRAY_BUFFER), material=0,
            targets=[{"POSITION": b.accessor(d, gl.VEC3, gl.ARRAY_BUFFER, bounds=True)} for d in teeth_deltas])],
            weights=[0.0] * len(names), extras={"targetNames": names}))
    g.nodes = [gl.Node(name="Armature", rotation=ARMATURE_TURN, scale=[ARMATURE_SCALE] * 3, children=[1])]
    for name in order:                                              # nodes 1 .. 5
        g.nodes.append(gl.Node(name=name, translation=JOINTS[name][1]))
    for name, (parent, _) in JOINTS.items():
        if parent:
            p = g.nodes[1 + order.index(parent)]
            p.children = (p.children or []) + [1 + order.index(name)]
    g.nodes.append(gl.Node(name="Head", mesh=0, skin=0))            # 6: the object Blender shows as the head
    g.nodes.append(gl.Node(name="Body", mesh=1, skin=0))            # 7
    if teeth:                                                       # 8: a plain node under the Head joint
        g.nodes.append(gl.Node(name="Teeth", mesh=2))
        head_joint = g.nodes[1 + order.index("Head")]
        head_joint.children = (head_joint.children or []) + [8]
    ibm = np.stack([np.linalg.inv(worlds[n]) for n in order]).transpose(0, 2, 1).reshape(-1, 16)
    g.skins.append(gl.Skin(name="Armature", joints=[1 + k for k in range(len(order))], skeleton=1,
                           inverseBindMatrices=b.accessor(ibm.astype(np.float32), gl.MAT4)))
    times = np.array([0.0, 1.0], np.float32)
    turn = np.array([neck_turn(), neck_turn()], np.float32)
    g.animations.append(gl.Animation(name="idle", samplers=[gl.AnimationSampler(
        input=b.accessor(times, gl.SCALAR, bounds=True), output=b.accessor(turn, gl.VEC4), interpolation="LINEAR")],
        channels=[gl.AnimationChannel(sampler=0, target=gl.AnimationChannelTarget(node=1 + order.index("Neck"),
                                                                                   path="rotation"))]))
    g.scenes = [gl.Scene(name="Scene", nodes=[0, 6, 7])]
    g.scene = 0
    b.data += bytes(-len(b.data) % 4)
    g.buffers = [gl.Buffer(byteLength=len(b.data))]
    g.set_binary_blob(bytes(b.data))
    g.save_binary(str(path))
    return {"head": head, "weights": weights, **({"teeth": placed} if teeth else {})}
