"""Bone mode on the user's own glTF avatar (visemeflow/animation/skinned_asset.py): the `.bones.glb` is the whole
avatar with the SSDR face bones added to its skeleton, checked by the programs that read it: the Khronos validator,
three.js (the skinned vertices it computes, with our clip alone and with the avatar's own clip turning the neck at
the same time) and Blender's importer (its evaluated mesh), with the lips measured in millimetres where the curves
close them.

Avatars: tests/skinned_head_glb.py (the demo head on a Mixamo-like skeleton: armature turned and scaled 0.01, the
neck blending into `Neck`, the chin shared with a `Jaw`, a body on `Spine`, an `idle` clip) and tests/avatar_glb.py
(Ready Player Me's layout: teeth on a node without a skin, eyes the visemes do not move, a texture)."""

import json
import subprocess
from pathlib import Path

import numpy as np
import pygltflib as gl
import pytest
from avatar_glb import make_avatar
from blender_check import BPY_PYTHON, PROBE, Y_UP_TO_Z_UP, probe
from browser import serve_folder
from factories import NODE_MODULES, node_or_fail, validate
from gltf_player import PAGE, play
from skinned_head_glb import JOINTS, joint_worlds, make_skinned_head, neck_turn

from visemeflow.animation.bones import bone_animation, solve_bones
from visemeflow.animation.lips import inner_lip_pairs, pair_gap_mm
from visemeflow.animation.load import load_bound_character
from visemeflow.animation.skinned_asset import asset_bone_notes, write_asset_bones_glb
from visemeflow.articulation import CLOSED_MM
from visemeflow.rig.character import CharacterError
from visemeflow.rig.gltf import GltfScene
from visemeflow.visemes import VISEMES

FPS = 30.0
N = 24
HEAD_NODE, BODY_NODE = 6, 7   # tests/skinned_head_glb.py's mesh nodes
SHUT = [10, 11, 12]          # MBP alone
OPEN = [4, 20]               # AHH high


def talk() -> np.ndarray:
    c = np.zeros((N, 16), np.float32)
    c[:, VISEMES.index("AHH")] = 0.5 + 0.5 * np.sin(np.arange(N) / 3.0)
    c[:, VISEMES.index("OHH")] = 0.3 * np.clip(np.cos(np.arange(N) / 2.0), 0, 1)
    c[SHUT] = 0.0
    c[SHUT, VISEMES.index("MBP")] = 1.0
    c[OPEN] = 0.0
    c[OPEN, VISEMES.index("AHH")] = 1.0
    return c


@pytest.fixture(scope="module")
def head(tmp_path_factory):
    """The skinned head, its character, bones (8, 5 iterations) and bone GLB of `talk()`."""
    root = tmp_path_factory.mktemp("bone-asset")
    arrays = make_skinned_head(root / "head.glb")
    character, binding = load_bound_character(root / "head.glb")
    rig = solve_bones(character, 8, binding=binding, iterations=5)
    out = write_asset_bones_glb(root / "head.bones.glb", character, rig, talk(), FPS, name="speech")
    return root, arrays, character, rig, out


def head_only(arrays) -> np.ndarray:
    """The head's vertices that its skin puts wholly on `Head` and the `Jaw` (posed as `Head`): the face bones carry
    the whole viseme motion of these."""
    w = arrays["weights"]
    return np.flatnonzero(w["Head"] + w["Jaw"] > 1 - 1e-6)


# ---- the file --------------------------------------------------------------------------------------------------
def test_the_bone_glb_is_the_whole_avatar_with_face_bones_under_the_head_that_the_validator_accepts(head):
    root, arrays, character, rig, out = head
    report = validate(out)
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, report["issues"]["messages"]
    before, after = gl.GLTF2.load(str(root / "head.glb")), gl.GLTF2.load(str(out))
    assert [m.name for m in after.meshes] == ["HeadMesh", "BodyMesh"]
    assert [a.name for a in after.animations] == ["speech", "idle"]          # ours first: Blender plays it
    assert after.animations[1].to_dict() == before.animations[0].to_dict()
    names = [n.name for n in after.nodes]
    assert names[:len(before.nodes)] == [n.name for n in before.nodes]
    head_joint = names.index("Head")                   # the joint, not the mesh node of the same name
    added = list(range(len(before.nodes), len(after.nodes)))
    assert sorted(after.nodes[head_joint].children) == sorted([names.index("Jaw")] + added)
    assert [names[i] for i in added] == [f"Head_{b}" for b in rig.bone_names if f"Head_{b}" in names[len(before.nodes):]]
    skin = after.skins[0]
    assert skin.joints == before.skins[0].joints + added
    # the body keeps its skinning; the head's moving vertices are now on the face bones
    assert after.meshes[1].primitives[0].attributes.JOINTS_0 == before.meshes[1].primitives[0].attributes.JOINTS_0
    channels = {(c.target.node, c.target.path) for c in after.animations[0].channels}
    assert channels and {node for node, _ in channels} <= set(added)
    notes = asset_bone_notes(character, rig)
    assert any("moving vertices of HeadMesh are shared by Head with other joints" in n for n in notes), notes


def test_at_rest_the_bone_glb_places_every_mesh_where_the_avatar_had_it(head):
    root, arrays, character, rig, out = head
    before, after = GltfScene(root / "head.glb"), GltfScene(out)
    for info in before.meshes:
        np.testing.assert_allclose(after.placed_mesh(info.index, morph_targets=False)[1],
                                   before.placed_mesh(info.index, morph_targets=False)[1], atol=1e-6)


def test_the_package_says_whether_the_bones_close_the_lips(head):
    """Bone mode's lip report: the gap of the bone mesh's MBP (what the viewer sees), and a warning where the bones
    leave it open (here a rig whose MBP pose is its AHH pose)."""
    from dataclasses import replace

    from visemeflow.tasks.animate import _bone_closure

    root, arrays, character, rig, out = head
    lips: dict = {}
    assert _bone_closure(character, rig, lips) == [] and lips["bones_mbp_gap_mm"] < CLOSED_MM
    mbp, ahh = VISEMES.index("MBP"), VISEMES.index("AHH")
    rotations, translations = rig.rotations.copy(), rig.translations.copy()
    rotations[mbp], translations[mbp] = rig.rotations[ahh], rig.translations[ahh]
    lips = {}
    (warning,) = _bone_closure(character, replace(rig, rotations=rotations, translations=translations), lips)
    assert lips["bones_mbp_gap_mm"] > 3 * CLOSED_MM
    assert f"head.glb): its {rig.n_bones} bones leave MBP's lips " in warning
    assert f"more bones (--bones {2 * rig.n_bones}) may close them; --mode blendshape does" in warning


def test_default_morph_weights_of_the_driven_meshes_are_zero_in_the_bone_glb(tmp_path, head):
    """A file storing 1.0 as every target's default weight: with the bones playing the visemes, those defaults would
    add each shape on top of them in every viewer; the bone GLB sets them to 0."""
    root, arrays, character, rig, out = head
    g = gl.GLTF2.load(str(root / "head.glb"))
    g.meshes[0].weights = [1.0] * len(g.meshes[0].weights)
    g.save_binary(str(tmp_path / "defaults.glb"))
    loaded, _ = load_bound_character(tmp_path / "defaults.glb")
    written = gl.GLTF2.load(str(write_asset_bones_glb(tmp_path / "out.glb", loaded, rig, talk(), FPS)))
    assert written.meshes[0].weights == [0.0] * 16


def test_a_parent_scaled_unevenly_is_refused_naming_it(tmp_path, head):
    root, arrays, character, rig, out = head
    g = gl.GLTF2.load(str(root / "head.glb"))
    g.nodes[0].scale = [0.01, 0.02, 0.01]
    g.save_binary(str(tmp_path / "stretched.glb"))
    stretched, binding = load_bound_character(tmp_path / "stretched.glb")
    with pytest.raises(CharacterError, match=r"stretched.glb: node \d+ \(Head\) is scaled unevenly or mirrored in "
                                             r"the scene, because its parent node 0 \(Armature\) is;"):
        write_asset_bones_glb(tmp_path / "out.glb", stretched, rig, talk(), FPS)
    assert not (tmp_path / "out.glb").exists()


def test_a_second_set_of_influences_is_refused_naming_the_mesh(tmp_path, head):
    root, arrays, character, rig, out = head
    g = gl.GLTF2.load(str(root / "head.glb"))
    attributes = g.meshes[0].primitives[0].attributes
    attributes.JOINTS_1, attributes.WEIGHTS_1 = attributes.JOINTS_0, attributes.WEIGHTS_0
    g.save_binary(str(tmp_path / "eight.glb"))
    eight, _ = load_bound_character(tmp_path / "eight.glb")
    with pytest.raises(CharacterError, match=r"eight.glb: mesh HeadMesh has a second set of skin influences"):
        write_asset_bones_glb(tmp_path / "out.glb", eight, rig, talk(), FPS)


# ---- three.js ---------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    node_or_fail()
    root = tmp_path_factory.mktemp("served-bone-asset")
    with serve_folder(root, PAGE, NODE_MODULES) as address:
        yield root, address


def _turn_neck(stage) -> None:
    """Add the neck turned (`neck_turn`) to the stage's SkelAnimation at every frame: a body animation on the USD's
    skeleton."""
    from pxr import Gf, UsdSkel

    anim = next(UsdSkel.Animation(p) for p in stage.Traverse() if p.IsA(UsdSkel.Animation))
    skeleton = next(UsdSkel.Skeleton(p) for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    translation, _, scale = UsdSkel.DecomposeTransform(skeleton.GetRestTransformsAttr().Get()[2])
    x, y, z, w = neck_turn()
    anim.GetJointsAttr().Set(list(anim.GetJointsAttr().Get()) + ["Hips/Spine/Neck"])
    for k in range(N):
        anim.GetTranslationsAttr().Set(list(anim.GetTranslationsAttr().Get(k)) + [Gf.Vec3f(translation)], k)
        anim.GetRotationsAttr().Set(list(anim.GetRotationsAttr().Get(k)) + [Gf.Quatf(w, x, y, z)], k)
    anim.GetScalesAttr().Set(list(anim.GetScalesAttr().Get()) + [Gf.Vec3h(scale)])


def _rotation(q_xyzw) -> np.ndarray:
    x, y, z, w = q_xyzw
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    return m


def test_three_js_plays_the_bones_on_the_avatar_and_shuts_its_lips_also_while_its_own_clip_turns_the_neck(
        head, served, browser):
    root, arrays, character, rig, out = head
    curves = talk()
    ours = bone_animation(rig, curves)                                   # (N, V, 3) the rig, scene metres
    frames = [0, *OPEN, *SHUT, N - 1]
    times = [f / FPS for f in frames]
    pairs = inner_lip_pairs(character)
    assert pairs is not None                                             # lipfinder found the head's lips
    whole = head_only(arrays)
    assert np.isin(pairs.ravel(), whole).all()
    moving = np.linalg.norm(ours - character.neutral[None], axis=2).max(axis=0)
    ids = sorted({*pairs.ravel().tolist(), *whole[np.argsort(-moving[whole])[:20]].tolist(),
                  *np.random.default_rng(0).choice(whole, 30, replace=False).tolist()})
    got = play(browser, served, out, ["speech"], times, {HEAD_NODE: ids, BODY_NODE: list(range(8))})
    assert got["clips"] == ["speech", "idle"] and sorted(got["skinned"]) == [HEAD_NODE, BODY_NODE]
    three = got["positions"][str(HEAD_NODE)]
    face = float(np.ptp(character.neutral, axis=0).max())
    worst = float(np.abs(three - ours[frames][:, ids]).max())
    print(f"\nthree.js, our clip: worst {worst * 1e3:.4f} mm over {len(ids)} vertices x {len(frames)} frames")
    assert worst < 1e-5 * face * 10                                      # float32 of a 30-cm head: < 0.03 mm
    assert np.abs(ours[frames][:, ids] - character.neutral[ids]).max() > 2e-3   # the face moves: millimetres
    lips = {f: three[k][[ids.index(i) for i in pairs.ravel()]].reshape(3, 2, 3) for k, f in enumerate(frames)}
    gaps = {f: float(pair_gap_mm(lips[f], 1000.0)) for f in frames}
    print("lip gaps mm:", {f: round(g, 2) for f, g in gaps.items()})
    assert all(gaps[f] < CLOSED_MM for f in SHUT) and all(gaps[f] > 3 * CLOSED_MM for f in OPEN), gaps
    body = GltfScene(root / "head.glb").placed_mesh(1, morph_targets=False)[1]
    np.testing.assert_allclose(got["positions"][str(BODY_NODE)][0], body, atol=1e-6)

    # the avatar's idle clip turns the neck while ours speaks: the face follows the head, lips still shut
    both = play(browser, served, out, ["speech", "idle"], times, {HEAD_NODE: ids})["positions"][str(HEAD_NODE)]
    neck = joint_worlds()["Neck"]
    turned = neck @ _rotation(neck_turn()) @ np.linalg.inv(neck)
    expected = np.einsum("ij,fvj->fvi", turned[:3, :3], ours[frames][:, ids]) + turned[:3, 3]
    worst = float(np.abs(both - expected).max())
    print(f"three.js, ours with idle: worst {worst * 1e3:.4f} mm")
    assert worst < 1e-4 * face
    assert np.abs(expected - ours[frames][:, ids]).max() > 0.01          # the turn moves the face by centimetres
    shut = [pair_gap_mm(both[k][[ids.index(i) for i in pairs.ravel()]].reshape(3, 2, 3), 1000.0)
            for k, f in enumerate(frames) if f in SHUT]
    assert max(shut) < CLOSED_MM, shut
    assert set(JOINTS) <= set(n.name for n in gl.GLTF2.load(str(out)).nodes)


def test_three_js_plays_teeth_that_had_no_skin_and_leaves_the_eyes_and_texture_as_they_were(tmp_path, served, browser):
    """Ready Player Me's layout: the teeth on a node without a skin move to a root node of that name, skinned by
    bones under the old node (renamed `TeethNode_FaceBones`, keeping its transform); the eyes, which the visemes do
    not move, and the textured material stay as they were."""
    make_avatar(tmp_path / "avatar.glb")
    character, binding = load_bound_character(tmp_path / "avatar.glb")
    rig = solve_bones(character, 6, binding=binding, iterations=5)
    curves = np.random.default_rng(2).random((N, 16)).astype(np.float32) * 0.6
    out = write_asset_bones_glb(tmp_path / "avatar.bones.glb", character, rig, curves, FPS, name="speech")
    report = validate(out)
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, report["issues"]["messages"]
    g, before = gl.GLTF2.load(str(out)), gl.GLTF2.load(str(tmp_path / "avatar.glb"))
    names = [n.name for n in g.nodes]
    teeth_node = names.index("TeethNode")
    assert g.nodes[teeth_node].mesh == 1 and g.nodes[teeth_node].skin is not None and teeth_node in g.scenes[0].nodes
    old = names.index("TeethNode_FaceBones")
    assert g.nodes[old].mesh is None and g.nodes[old].translation == before.nodes[old].translation
    assert set(g.skins[g.nodes[teeth_node].skin].joints) == set(g.nodes[old].children)
    for eye in ("EyeLeftNode", "EyeRightNode"):
        assert g.nodes[names.index(eye)].to_dict() == before.nodes[names.index(eye)].to_dict()
    assert g.materials[0].to_dict() == before.materials[0].to_dict() and len(g.images) == 1
    teeth = next(p for p in character.parts if p.name == "Wolf3D_Teeth")
    ours = bone_animation(rig, curves)[:, teeth.start:teeth.stop]
    frames = [0, 7, 15, N - 1]
    got = play(browser, served, out, ["speech"], [f / FPS for f in frames],
               {teeth_node: list(range(teeth.n_vertices))})
    worst = float(np.abs(got["positions"][str(teeth_node)] - ours[frames]).max())
    print(f"\nthree.js, teeth: worst {worst * 1e3:.4f} mm")
    assert worst < 1e-5
    assert np.abs(ours[frames] - character.neutral[teeth.start:teeth.stop]).max() > 1e-3


# ---- USD ----------------------------------------------------------------------------------------------------------
def test_the_bone_usd_of_an_avatar_is_its_whole_scene_that_usdskel_skins_as_we_do(tmp_path):
    """`.bones.usd` of a glTF avatar: one skinned Mesh per driven mesh (head, teeth, eyes), the body placed as the
    file places it, the head's material and texture coordinates; UsdSkel's baked skinning equals our bones; the
    validators find no error."""
    from pxr import Gf, Usd, UsdGeom, UsdShade, UsdSkel, UsdValidation

    from visemeflow.animation.usd_skel import write_usd_skel

    make_avatar(tmp_path / "avatar.glb")
    character, binding = load_bound_character(tmp_path / "avatar.glb")
    rig = solve_bones(character, 6, binding=binding, iterations=5)
    curves = np.random.default_rng(4).random((N, 16)).astype(np.float32) * 0.6
    path = write_usd_skel(tmp_path / "avatar.bones.usda", rig, curves, FPS, name="speech", character=character)
    stage = Usd.Stage.Open(str(path))
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = [e.GetMessage() for e in UsdValidation.ValidationContext(validators).Validate(stage)
              if e.GetType() == UsdValidation.ValidationErrorType.Error]
    assert errors == []
    root = stage.GetDefaultPrim()
    # its head's skin blends every vertex from Hips to HeadJoint: on the avatar's skeleton the face bones would move
    # it by one joint's share only, so the flat skeleton plays our bones, and the layer says why
    assert "would move the face up to 20.0 mm less than ours" in stage.GetRootLayer().documentation
    meshes = {p.GetName(): UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)}
    assert {"Wolf3D_Head", "Wolf3D_Teeth", "EyeLeft", "EyeRight", "BodyNode"} <= set(meshes), sorted(meshes)
    body = GltfScene(tmp_path / "avatar.glb").placed_mesh(4, morph_targets=False)[1]
    np.testing.assert_allclose(np.asarray(meshes["BodyNode"].GetPointsAttr().Get()), body, atol=1e-6)
    head_material = UsdShade.MaterialBindingAPI(meshes["Wolf3D_Head"]).ComputeBoundMaterial()[0]
    assert head_material and UsdGeom.PrimvarsAPI(meshes["Wolf3D_Head"]).GetPrimvar("st").HasValue()
    ours = bone_animation(rig, curves)
    assert UsdSkel.BakeSkinning(UsdSkel.Root(root), Gf.Interval(0, N - 1))
    for part in character.parts:
        mesh = meshes[part.name]
        for k in (0, 9, N - 1):
            np.testing.assert_allclose(np.asarray(mesh.GetPointsAttr().Get(k)), ours[k, part.start:part.stop],
                                       atol=1e-6, err_msg=part.name)
    head = next(p for p in character.parts if p.name == "Wolf3D_Head")
    assert np.abs(ours[9, head.start:head.stop] - character.neutral[head.start:head.stop]).max() > 1e-3


# ---- Blender ----------------------------------------------------------------------------------------------------


def test_blender_imports_the_avatar_with_its_face_on_bones_and_shuts_the_lips(head):
    root, arrays, character, rig, out = head
    if not BPY_PYTHON.is_file():
        pytest.fail(f"{BPY_PYTHON} missing: `make blender-deps` builds it (Blender as the PyPI bpy module)")
    frames = [0, *OPEN, *SHUT, N - 1]
    request = {"path": str(out), "frames": frames, "out": str(root / "blender.npz"), "fps": FPS}
    done = subprocess.run([str(BPY_PYTHON), str(PROBE), json.dumps(request)], capture_output=True, text=True,
                          timeout=300)
    lines = [line for line in done.stdout.splitlines() if line.startswith("probe: ")]
    assert done.returncode == 0 and lines, (done.stdout + done.stderr)[-3000:]
    with np.load(root / "blender.npz") as arrays_:
        meshes = {k: arrays_[k] for k in arrays_.files if not k.endswith((".uv", ".color"))}
    ours = np.einsum("ij,fvj->fvi", Y_UP_TO_Z_UP, bone_animation(rig, talk())[frames])
    (name,) = [n for n, m in meshes.items() if m.shape[1] == character.n_vertices]
    whole = head_only(arrays)
    worst = float(np.abs(meshes[name][:, whole] - ours[:, whole]).max())
    print(f"\nBlender: {sorted(meshes)}; head worst {worst * 1e3:.4f} mm")
    assert worst < 1e-4                                                   # 0.1 mm
    assert any(m.shape[1] == 8 for m in meshes.values())                  # the body came along
    pairs = inner_lip_pairs(character)
    gaps = pair_gap_mm(meshes[name][:, pairs.ravel()].reshape(len(frames), 3, 2, 3), 1000.0)
    shut = [k for k, f in enumerate(frames) if f in SHUT]
    assert (gaps[shut] < CLOSED_MM).all() and (np.delete(gaps, shut) > CLOSED_MM).any(), gaps


# ---- the flow ---------------------------------------------------------------------------------------------------
@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_animate_in_bone_mode_writes_the_whole_avatar_and_says_what_the_bones_leave_out(tmp_path):
    from factories import make_curve_store

    from visemeflow.animation.package import AnimateConfig
    from visemeflow.flows.animate import AnimateParams, animate_flow

    make_avatar(tmp_path / "avatar.glb")
    store = make_curve_store(tmp_path / "store", n=1)
    result = animate_flow(AnimateParams(store=store.root, characters=[tmp_path / "avatar.glb"], source="ground_truth",
                                        config=AnimateConfig(formats=("glb",), mode="bones", bones=6, fps=30.0)))
    (report,) = result["packages_written"]
    path = Path(report["files"]["glb"])
    assert path.name.endswith(".bones.glb")
    assert validate(path)["issues"]["numErrors"] == 0
    g = gl.GLTF2.load(str(path))
    assert {m.name for m in g.meshes} == {"Wolf3D_Head", "Wolf3D_Teeth", "EyeLeft", "EyeRight", "Wolf3D_Body"}
    assert [a.name for a in g.animations] == [path.name.removesuffix(".bones.glb"), "idle"]
    assert g.images and g.skins[0].joints[:2] == [1, 2] and len(g.skins[0].joints) > 2
    # the test avatar's head blends the hips into the head joint vertex by vertex: said, not hidden
    assert any("moving vertices of Wolf3D_Head are shared by" in w for w in report["warnings"]), report["warnings"]


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_an_avatar_its_bones_cannot_join_is_a_reject_naming_the_node_not_a_crash(tmp_path):
    """A skeleton scaled unevenly (the armature at 1, 1.5, 0.8): bone mode refuses it, as one reject row per
    utterance naming the file and the node at fault; the run goes on (it ended in a traceback)."""
    from factories import make_curve_store

    from visemeflow.animation.package import AnimateConfig
    from visemeflow.flows.animate import AnimateParams, animate_flow

    make_skinned_head(tmp_path / "head.glb")
    g = gl.GLTF2.load(str(tmp_path / "head.glb"))
    g.nodes[0].scale = [0.01, 0.015, 0.008]
    g.save_binary(str(tmp_path / "stretched.glb"))
    from visemeflow.flows.errors import StageFailed

    store = make_curve_store(tmp_path / "store", n=2)
    with pytest.raises(StageFailed, match="all 2 utterances failed"):      # nothing written: the run is Failed
        animate_flow(AnimateParams(store=store.root, characters=[tmp_path / "stretched.glb"], source="ground_truth",
                                   config=AnimateConfig(formats=("glb",), mode="bones", bones=8, fps=30.0)))
    rows = store.read_table("rejects", "animate").to_pylist()
    assert sorted(r["utterance_id"] for r in rows) == ["spk/u0", "spk/u1"]
    assert {r["error_type"] for r in rows} == {"CharacterError"}
    for row in rows:
        assert row["message"].startswith(f"{row['utterance_id']}: {tmp_path / 'stretched.glb'}: node 4 (Head) is "
                                         "scaled unevenly or mirrored in the scene, because its parent node 0 "
                                         "(Armature) is;"), row["message"]


def test_more_bones_than_a_small_mesh_supports_are_as_many_as_it_does_and_said_so(tmp_path):
    """`--mesh Wolf3D_Teeth` at the default 32 bones: the teeth's 6 vertices support 2; bone mode makes those (it
    stopped with an error) and the package says so."""
    from visemeflow.animation.package import bone_count_note, bone_rig

    make_avatar(tmp_path / "avatar.glb")
    teeth, binding = load_bound_character(tmp_path / "avatar.glb", convention="arkit52", meshes=["Wolf3D_Teeth"])
    rig = bone_rig(teeth, binding, 32)
    assert 1 <= rig.n_bones <= 2 and rig.n_vertices == 6
    assert bone_count_note(teeth, 32) == (f"{teeth.where()}: 32 bones asked, at most 2 made: its 6 vertices support "
                                          "no more (each bone moves at least 3)")
    assert bone_count_note(teeth, 2) is None


def test_the_bone_usd_of_a_skinned_avatar_puts_the_face_bones_in_its_own_skeleton(head, tmp_path):
    """`.bones.usd` of an avatar whose head is on a skin: the face bones are joints under `Head` in the avatar's own
    skeleton (as in the bone GLB), so UsdSkel's baked skinning plays our bones on the face at rest, and with the neck
    turned on that skeleton (a body animation) the face turns with the head and still speaks; the body stays on
    `Spine`; the validators find no error."""
    from factories import usd_validation_errors
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel

    from visemeflow.animation.usd_skel import write_usd_skel

    root, arrays, character, rig, _ = head
    path = write_usd_skel(tmp_path / "head.bones.usda", rig, talk(), FPS, name="speech", character=character)

    def opened() -> Usd.Stage:           # the file as written, not a layer an earlier bake changed in memory
        layer = Sdf.Layer.FindOrOpen(str(path))
        layer.Reload(True)
        return Usd.Stage.Open(layer)

    def baked(stage: Usd.Stage) -> dict:
        assert UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetDefaultPrim()), Gf.Interval(0, N - 1))
        return {p.GetName(): UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)}

    def world(mesh, k: int) -> np.ndarray:
        points = np.asarray(mesh.GetPointsAttr().Get(k), np.float64)
        m = np.asarray(mesh.ComputeLocalToWorldTransform(Usd.TimeCode(k)), np.float64)   # row vectors
        return points @ m[:3, :3] + m[3, :3]

    stage = opened()
    assert usd_validation_errors(stage) == []
    joints = list(next(UsdSkel.Skeleton(p) for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
                  .GetJointsAttr().Get())
    assert joints[:5] == ["Hips", "Hips/Spine", "Hips/Spine/Neck", "Hips/Spine/Neck/Head", "Hips/Spine/Neck/Head/Jaw"]
    face = joints[5:]                  # the rig's moving bones (`bone_NN`, `rigid_NN` for the lower teeth)
    assert all(j.startswith("Hips/Spine/Neck/Head/Head_") for j in face) and \
        sum("_bone_" in j for j in face) >= 4, joints
    ours = bone_animation(rig, talk())
    whole = head_only(arrays)
    meshes = baked(stage)
    for k in [0, *OPEN, *SHUT]:
        np.testing.assert_allclose(world(meshes["HeadMesh"], k)[whole], ours[k][whole], atol=1e-6)
    np.testing.assert_allclose(world(meshes["Body"], 0),
                               GltfScene(root / "head.glb").placed_mesh(1, morph_targets=False)[1], atol=1e-6)
    # a body animation on the same skeleton, the neck turned: the head-only vertices are our bones' vertices carried
    # by the neck's turn, world(Neck) posed times world(Neck) at rest inverted
    stage = opened()
    _turn_neck(stage)
    meshes = baked(stage)
    neck = joint_worlds()["Neck"]
    carry = neck @ _rotation(neck_turn()) @ np.linalg.inv(neck)
    for k in [*OPEN, *SHUT]:
        expected = ours[k][whole] @ carry[:3, :3].T + carry[:3, 3]
        got = world(meshes["HeadMesh"], k)[whole]
        np.testing.assert_allclose(got, expected, atol=1e-6)
        assert np.abs(got - ours[k][whole]).max() > 0.01         # the head turned: centimetres


def test_blender_imports_the_bone_usd_as_the_avatars_armature_with_the_face_bones_and_shuts_the_lips(head):
    """Blender's USD importer makes one armature of the avatar's joints and the face bones under `Head`, and plays
    the head as our bones do (the head-only vertices, 0.1 mm), the lips shut where the curves shut them."""
    from visemeflow.animation.usd_skel import write_usd_skel

    root, arrays, character, rig, _ = head
    out = write_usd_skel(root / "head.bones.usda", rig, talk(), FPS, name="speech", character=character)
    frames = [0, *OPEN, *SHUT, N - 1]
    report, meshes = probe(out, frames, root / "blender-usd.npz", fps=FPS)
    (bones,) = report["bones"].values()
    assert bones[:5] == ["Hips", "Spine", "Neck", "Head", "Jaw"] and len(bones) > 5, bones
    head_mesh = meshes["HeadMesh"]
    ours = np.einsum("ij,fvj->fvi", Y_UP_TO_Z_UP, bone_animation(rig, talk())[frames])
    whole = head_only(arrays)
    worst = float(np.abs(head_mesh[:, whole] - ours[:, whole]).max())
    print(f"\nBlender, bone USD: head worst {worst * 1e3:.4f} mm")
    assert worst < 1e-4
    pairs = inner_lip_pairs(character)
    gaps = pair_gap_mm(head_mesh[:, pairs.ravel()].reshape(len(frames), 3, 2, 3), 1000.0)
    shut = [k for k, f in enumerate(frames) if f in SHUT]
    assert (gaps[shut] < CLOSED_MM).all() and (np.delete(gaps, shut) > CLOSED_MM).any(), gaps


@pytest.fixture(scope="module")
def toothed(tmp_path_factory):
    """The skinned head with teeth on a node without a skin under the `Head` joint, its character and bones."""
    root = tmp_path_factory.mktemp("bone-teeth")
    arrays = make_skinned_head(root / "head.glb", teeth=True)
    character, binding = load_bound_character(root / "head.glb")
    rig = solve_bones(character, 8, binding=binding, iterations=5)
    return root, arrays, character, rig


def test_the_bone_usd_puts_the_bones_of_teeth_on_a_plain_node_under_the_joint_above_them(toothed):
    """Teeth on a node without a skin, a child of the `Head` joint: their face bones are joints under `Head` in the
    avatar's own skeleton (they kept the flat SSDR skeleton for the whole file before), the teeth bound where the
    scene shows them; UsdSkel plays them as our bones do, and with the neck turned they follow the head."""
    from factories import usd_validation_errors
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel

    from visemeflow.animation.usd_skel import write_usd_skel

    root, arrays, character, rig = toothed
    path = write_usd_skel(root / "teeth.bones.usda", rig, talk(), FPS, name="speech", character=character)
    stage = Usd.Stage.Open(str(path))
    assert usd_validation_errors(stage) == []
    skeleton = next(UsdSkel.Skeleton(p) for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    joints = list(skeleton.GetJointsAttr().Get())
    assert joints[:4] == ["Hips", "Hips/Spine", "Hips/Spine/Neck", "Hips/Spine/Neck/Head"]
    assert any(j.startswith("Hips/Spine/Neck/Head/Teeth_") for j in joints), joints
    assert "on a node without a skin" not in stage.GetRootLayer().documentation
    teeth = next(p for p in character.parts if p.name == "TeethMesh")
    np.testing.assert_allclose(character.neutral[teeth.start:teeth.stop], arrays["teeth"], atol=1e-6)
    ours = bone_animation(rig, talk())[:, teeth.start:teeth.stop]
    assert np.abs(ours[OPEN] - arrays["teeth"]).max() > 5e-3        # the lower teeth drop at AHH

    def world(mesh, k: int) -> np.ndarray:
        points = np.asarray(mesh.GetPointsAttr().Get(k), np.float64)
        m = np.asarray(mesh.ComputeLocalToWorldTransform(Usd.TimeCode(k)), np.float64)
        return points @ m[:3, :3] + m[3, :3]

    def baked_teeth(stage: Usd.Stage):
        assert UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetDefaultPrim()), Gf.Interval(0, N - 1))
        return next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.GetName() == "TeethMesh")

    mesh = baked_teeth(stage)
    for k in [0, *OPEN, *SHUT]:
        np.testing.assert_allclose(world(mesh, k), ours[k], atol=1e-6)
    # the neck turned on the USD's skeleton (a body animation): the teeth turn with the head and still move
    layer = Sdf.Layer.FindOrOpen(str(path))
    layer.Reload(True)
    stage = Usd.Stage.Open(layer)
    _turn_neck(stage)
    mesh = baked_teeth(stage)
    neck = joint_worlds()["Neck"]
    carry = neck @ _rotation(neck_turn()) @ np.linalg.inv(neck)
    for k in [*OPEN, *SHUT]:
        np.testing.assert_allclose(world(mesh, k), ours[k] @ carry[:3, :3].T + carry[:3, 3], atol=1e-6)


def test_blender_imports_the_bone_usd_with_the_teeth_on_the_heads_bones(toothed):
    """Blender's USD importer: one armature with the teeth's face bones under `Head`, the teeth where ours are."""
    from visemeflow.animation.usd_skel import write_usd_skel

    root, arrays, character, rig = toothed
    out = write_usd_skel(root / "teeth.bones.usda", rig, talk(), FPS, name="speech", character=character)
    frames = [0, *OPEN, *SHUT]
    report, meshes = probe(out, frames, root / "blender-teeth.npz", fps=FPS)
    (bones,) = report["bones"].values()
    assert bones[:4] == ["Hips", "Spine", "Neck", "Head"] and any(b.startswith("Teeth_") for b in bones), bones
    teeth = next(p for p in character.parts if p.name == "TeethMesh")
    ours = np.einsum("ij,fvj->fvi", Y_UP_TO_Z_UP, bone_animation(rig, talk())[frames][:, teeth.start:teeth.stop])
    worst = float(np.abs(meshes["TeethMesh"] - ours).max())
    print(f"\nBlender, bone USD: teeth worst {worst * 1e3:.4f} mm")
    assert worst < 1e-4


def test_lips_that_the_avatars_skeleton_would_leave_behind_keep_the_flat_skeleton_in_the_bone_usd(tmp_path):
    """A head whose mouth is weighted 30% to `Neck`: on the avatar's skeleton the face bones under `Head` would move
    the lips by 70% of their motion, so the bone USD keeps the flat SSDR skeleton (our bones exactly) and says why."""
    from pxr import Gf, Usd, UsdGeom, UsdSkel

    from visemeflow.animation.usd_skel import LIP_LOSS_MM, write_usd_skel

    make_skinned_head(tmp_path / "head.glb", lips_on_neck=0.3)
    character, binding = load_bound_character(tmp_path / "head.glb")
    rig = solve_bones(character, 8, binding=binding, iterations=5)
    path = write_usd_skel(tmp_path / "head.bones.usda", rig, talk(), FPS, name="speech", character=character)
    stage = Usd.Stage.Open(str(path))
    skeleton = next(UsdSkel.Skeleton(p) for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    assert skeleton.GetJointsAttr().Get()[0] == "root"
    doc = stage.GetRootLayer().documentation
    lost = float(doc.split("would move the lips up to ")[1].split(" mm")[0])
    assert lost > LIP_LOSS_MM
    assert UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetDefaultPrim()), Gf.Interval(0, N - 1))
    mesh = next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) and p.GetName() == "HeadMesh")
    ours = bone_animation(rig, talk())
    for k in [*OPEN, *SHUT]:
        np.testing.assert_allclose(np.asarray(mesh.GetPointsAttr().Get(k)), ours[k], atol=1e-6)
