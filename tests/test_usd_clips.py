"""The avatar's own clips in its USD (`visemeflow.animation.usd_clips`): each glTF animation that moves the skeleton
becomes a SkelAnimation under `/<Root>/Clips`, sampled with glTF's interpolations; bound in place of ours, UsdSkel
poses the avatar as three.js plays the same clip of the GLB; what a skeleton cannot carry is named in the layer."""

from pathlib import Path

import numpy as np
import pygltflib as gl
import pytest
from avatar_glb import make_avatar
from browser import serve_folder
from factories import NODE_MODULES, node_or_fail, usd_validation_errors
from gltf_player import PAGE, play
from skinned_head_glb import make_skinned_head

from visemeflow.animation.load import load_bound_character
from visemeflow.animation.usd import write_usd
from visemeflow.animation.usd_clips import sample_channel

FPS = 30.0


def test_samplers_interpolate_as_gltf_says():
    times = np.array([0.0, 1.0, 3.0])
    values = np.array([[0.0, 0.0, 0.0], [2.0, 4.0, 6.0], [2.0, 0.0, 0.0]])
    at = np.array([-1.0, 0.0, 0.5, 1.0, 2.0, 3.0, 9.0])
    np.testing.assert_allclose(sample_channel(times, values, "LINEAR", at)[:, 1], [0, 0, 2, 4, 2, 0, 0])
    np.testing.assert_allclose(sample_channel(times, values, "STEP", at)[:, 0], [0, 0, 0, 2, 2, 2, 2])
    # rotations: the half-way point between 0 and 90 degrees about z is 45 degrees (slerp, not a normalised lerp of
    # a long way round: the second key is given on the far hemisphere)
    quarter = [0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)]
    rot = sample_channel(np.array([0.0, 1.0]), np.array([[0.0, 0.0, 0.0, 1.0], [-q for q in quarter]]), "LINEAR",
                         np.array([0.25, 0.5]), rotation=True)
    np.testing.assert_allclose(np.abs(rot), [[0, 0, np.sin(np.pi / 16), np.cos(np.pi / 16)],
                                             [0, 0, np.sin(np.pi / 8), np.cos(np.pi / 8)]], atol=1e-12)
    # cubic spline (in-tangent, value, out-tangent per key): the Hermite curve, here x(t) = t^3 on [0, 1]
    cubic = np.array([[0.0], [0.0], [0.0], [3.0], [1.0], [0.0]])
    np.testing.assert_allclose(sample_channel(np.array([0.0, 1.0]), cubic, "CUBICSPLINE", np.array([0.5]))[:, 0],
                               [0.125])
    # keys 2 s apart: glTF scales the tangents by the gap (Appendix C): 0 -> 1 with an out-tangent of 1 at the first
    # key is 0.75 half-way (0.625 without the scaling)
    cubic = np.array([[0.0], [0.0], [1.0], [0.0], [1.0], [0.0]])
    np.testing.assert_allclose(sample_channel(np.array([0.0, 2.0]), cubic, "CUBICSPLINE", np.array([1.0]))[:, 0],
                               [0.75])
    # times as glTF stores them (float32: 0.1 is 0.100000001): a frame at a key's time takes that key
    step = sample_channel(np.array([0.0, 0.1, 0.2], np.float32), np.array([[0.0], [0.3], [0.6]]), "STEP",
                          np.arange(7) / 30.0)
    np.testing.assert_allclose(step[:, 0], [0, 0, 0, 0.3, 0.3, 0.3, 0.6])


def _add_clip(path: Path, name: str, channels: list[tuple[int, str, np.ndarray, np.ndarray, str]]) -> None:
    """Append a clip of (node, path, times, values, interpolation) channels to the GLB at `path`."""
    g = gl.GLTF2.load(str(path))
    blob = bytearray(g.binary_blob())

    def accessor(array: np.ndarray, kind: str, bounds: bool = False) -> int:
        array = np.ascontiguousarray(array, np.float32)
        blob.extend(bytes(-len(blob) % 4))
        g.bufferViews.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=array.nbytes))
        blob.extend(array.tobytes())
        g.accessors.append(gl.Accessor(bufferView=len(g.bufferViews) - 1, componentType=gl.FLOAT, count=len(array),
                                       type=kind, min=[float(array.min())] if bounds else None,
                                       max=[float(array.max())] if bounds else None))
        return len(g.accessors) - 1

    samplers, targets = [], []
    for k, (node, target, times, values, interpolation) in enumerate(channels):
        kind = {1: gl.SCALAR, 3: gl.VEC3, 4: gl.VEC4}[values.shape[1]]
        samplers.append(gl.AnimationSampler(input=accessor(times, gl.SCALAR, bounds=True),
                                            output=accessor(values, kind), interpolation=interpolation))
        targets.append(gl.AnimationChannel(sampler=k, target=gl.AnimationChannelTarget(node=node, path=target)))
    g.animations.append(gl.Animation(name=name, samplers=samplers, channels=targets))
    blob.extend(bytes(-len(blob) % 4))
    g.buffers[0].byteLength = len(blob)
    g.set_binary_blob(bytes(blob))
    g.save_binary(str(path))


def _about(axis: int, angle: float) -> list[float]:
    q = [0.0, 0.0, 0.0, float(np.cos(angle / 2))]
    q[axis] = float(np.sin(angle / 2))
    return q


@pytest.fixture(scope="module")
def nodding(tmp_path_factory):
    """The skinned head with a second clip `nod`: the Head joint nods (LINEAR rotation keys), the Spine sways
    (CUBICSPLINE translation), the Neck turns in steps (STEP rotation), and a channel of morph weights."""
    root = tmp_path_factory.mktemp("usd-clips")
    path = root / "head.glb"
    make_skinned_head(path)
    n_targets = len(gl.GLTF2.load(str(path)).meshes[0].extras["targetNames"])
    spine = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -30.0], [0.0, 0.0, 0.0],      # in, value, out (centimetres)
                      [0.0, 0.0, 0.0], [2.0, 0.0, -30.0], [0.0, 0.0, 0.0]])
    _add_clip(path, "nod", [
        (4, "rotation", np.array([0.0, 0.5, 1.0]), np.array([_about(0, 0.0), _about(0, 0.35), _about(0, -0.1)]),
         "LINEAR"),
        (2, "translation", np.array([0.0, 1.0]), spine, "CUBICSPLINE"),
        (3, "rotation", np.array([0.0, 0.45]), np.array([_about(2, 0.0), _about(2, 0.2)]), "STEP"),   # between frames:
        # at a key's own time three.js still holds the key before (0.4 in float32 is 0.40000001), we take the key
        (6, "weights", np.array([0.0, 1.0]), np.zeros((2 * n_targets, 1)), "LINEAR"),
    ])
    character, _ = load_bound_character(path)
    usd = write_usd(root / "head.usda", character, np.zeros((12, character.n_shapes), np.float32), FPS,
                    name="speech")
    return root, path, character, usd


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    node_or_fail()
    root = tmp_path_factory.mktemp("served-usd-clips")
    with serve_folder(root, PAGE, NODE_MODULES) as address:
        yield root, address


def _bake(usd: Path, clip: str, frames: list[int]) -> dict[str, np.ndarray]:
    """World positions of every mesh at `frames` with the Skeleton playing `/<Root>/Clips/<clip>` (a fresh read of
    the file: the bake writes into the layer)."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel

    layer = Sdf.Layer.FindOrOpen(str(usd))
    layer.Reload(True)
    stage = Usd.Stage.Open(layer)
    root = stage.GetDefaultPrim()
    skeleton = next(UsdSkel.Skeleton(p) for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    UsdSkel.BindingAPI(skeleton.GetPrim()).GetAnimationSourceRel().SetTargets([root.GetPath().AppendPath(
        Sdf.Path(f"Clips/{clip}"))])
    assert UsdSkel.BakeSkinning(UsdSkel.Root(root), Gf.Interval(min(frames), max(frames)))
    out = {}
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Mesh):
            mesh = UsdGeom.Mesh(prim)
            rows = []
            for k in frames:
                points = np.asarray(mesh.GetPointsAttr().Get(k), np.float64)
                m = np.asarray(mesh.ComputeLocalToWorldTransform(Usd.TimeCode(k)), np.float64)
                rows.append(points @ m[:3, :3] + m[3, :3])
            out[prim.GetName()] = np.stack(rows)
    return out


def test_the_avatars_clips_are_skel_animations_that_pose_it_as_three_js_plays_them(nodding, browser, served):
    from pxr import Usd, UsdSkel

    root, glb, character, usd = nodding
    stage = Usd.Stage.Open(str(usd))
    assert usd_validation_errors(stage) == []
    clips = {p.GetName(): UsdSkel.Animation(p) for p in stage.GetPrimAtPath("/speech/Clips").GetChildren()}
    assert sorted(clips) == ["idle", "nod"]
    assert list(clips["nod"].GetJointsAttr().Get()) == ["Hips/Spine", "Hips/Spine/Neck", "Hips/Spine/Neck/Head"]
    assert len(clips["nod"].GetTranslationsAttr().GetTimeSamples()) == 31          # 1 s at 30 fps, from 0
    skeleton = next(UsdSkel.Skeleton(p) for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    bound = UsdSkel.BindingAPI(skeleton.GetPrim()).GetAnimationSourceRel().GetTargets()
    assert [str(p) for p in bound] == ["/speech/Skeleton/Animation"]                 # ours still plays
    assert "clip 'nod': its morph target weights not carried" in stage.GetRootLayer().documentation

    frames = [0, 3, 7, 12, 15, 22, 30]
    head_ids = np.random.default_rng(0).choice(character.n_vertices, 300, replace=False).tolist()
    got = play(browser, served, glb, ["nod"], [f / FPS for f in frames], {6: head_ids, 7: list(range(8))})
    baked = _bake(usd, "nod", frames)
    assert sorted(baked) == ["Body", "Mesh"], sorted(baked)      # the driven head (the one part) and the body
    worst_head = float(np.abs(baked["Mesh"][:, head_ids] - got["positions"]["6"]).max())
    worst_body = float(np.abs(baked["Body"] - got["positions"]["7"]).max())
    print(f"\nUSD clip 'nod' against three.js: head {worst_head * 1e3:.4f} mm, body {worst_body * 1e3:.4f} mm")
    assert worst_head < 2e-5 and worst_body < 2e-5
    moved = np.abs(got["positions"]["6"][1:] - got["positions"]["6"][0]).max()
    assert moved > 0.01            # the nod and the sway move the head by centimetres
    # the idle clip (the neck turned, held): the same against three.js at its one time
    got = play(browser, served, glb, ["idle"], [0.5], {6: head_ids})
    baked = _bake(usd, "idle", [15])
    assert np.abs(baked["Mesh"][:, head_ids] - got["positions"]["6"]).max() < 2e-5


def test_clips_the_skeleton_cannot_carry_are_named_and_broken_keys_leave_only_their_clip_out(tmp_path):
    from pxr import Usd

    # the multi-mesh avatar's idle turns a group of eye meshes, a node no joint hangs from
    make_avatar(tmp_path / "avatar.glb")
    character, _ = load_bound_character(tmp_path / "avatar.glb")
    usd = write_usd(tmp_path / "avatar.usda", character, np.zeros((4, character.n_shapes), np.float32), FPS)
    stage = Usd.Stage.Open(str(usd))
    assert "clip 'idle': node 'Eyes', which no joint hangs from not carried" in stage.GetRootLayer().documentation
    assert not stage.GetPrimAtPath(f"{stage.GetDefaultPrim().GetPath()}/Clips")
    # the skinned head with a clip whose times go backwards beside its good idle
    make_skinned_head(tmp_path / "head.glb")
    _add_clip(tmp_path / "head.glb", "broken", [
        (4, "rotation", np.array([0.0, 1.0, 0.5]), np.array([_about(0, 0.0)] * 3), "LINEAR")])
    character, _ = load_bound_character(tmp_path / "head.glb")
    usd = write_usd(tmp_path / "head.usda", character, np.zeros((4, character.n_shapes), np.float32), FPS,
                    name="speech")
    stage = Usd.Stage.Open(str(usd))
    assert [p.GetName() for p in stage.GetPrimAtPath("/speech/Clips").GetChildren()] == ["idle"]
    assert "clip 'broken': the keys of its rotation channel of node 4 are broken" in \
        stage.GetRootLayer().documentation


def test_a_clip_whose_last_key_lies_a_year_away_is_left_out_without_sampling_it(tmp_path):
    from pxr import Usd

    make_skinned_head(tmp_path / "head.glb")
    _add_clip(tmp_path / "head.glb", "year", [
        (4, "rotation", np.array([0.0, 3.2e7]), np.array([_about(0, 0.0), _about(0, 0.1)]), "LINEAR")])
    character, _ = load_bound_character(tmp_path / "head.glb")
    usd = write_usd(tmp_path / "head.usda", character, np.zeros((4, character.n_shapes), np.float32), FPS,
                    name="speech")
    stage = Usd.Stage.Open(str(usd))
    assert [p.GetName() for p in stage.GetPrimAtPath("/speech/Clips").GetChildren()] == ["idle"]
    assert "clip 'year': 960,000,001 frames of 1 joint, more than the USD takes here: left out" in \
        stage.GetRootLayer().documentation


def test_a_clip_that_hides_a_joint_and_one_that_ends_on_a_float32_key_are_carried_whole(tmp_path):
    from pxr import Usd, UsdSkel

    make_skinned_head(tmp_path / "head.glb")
    _add_clip(tmp_path / "head.glb", "hide", [          # the Jaw scaled to 0 from 0.5 s (a part hidden), 0.7 s long
        (5, "scale", np.array([0.0, 0.5, 0.7]), np.array([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]),
         "STEP")])
    _add_clip(tmp_path / "head.glb", "flat", [          # the Jaw squashed along one axis only
        (5, "scale", np.array([0.0, 0.5]), np.array([[1.0, 1.0, 1.0], [1.0, 0.0, 1.0]]), "LINEAR")])
    _add_clip(tmp_path / "head.glb", "idle", [          # a second clip of the name the file's own has
        (5, "rotation", np.array([0.0]), np.array([_about(0, 0.1)]), "STEP")])
    _add_clip(tmp_path / "head.glb", "lost", [(5, "scale", np.array([0.0]), np.array([[1.0, 1.0, 1.0]]), "STEP")])
    g = gl.GLTF2.load(str(tmp_path / "head.glb"))
    g.animations[-1].channels[0].sampler = 7           # a channel naming a sampler the clip does not have
    g.save_binary(str(tmp_path / "head.glb"))
    character, _ = load_bound_character(tmp_path / "head.glb")
    usd = write_usd(tmp_path / "head.usda", character, np.zeros((4, character.n_shapes), np.float32), FPS,
                    name="speech")
    stage = Usd.Stage.Open(str(usd))
    assert usd_validation_errors(stage) == []
    clips = {p.GetName(): UsdSkel.Animation(p) for p in stage.GetPrimAtPath("/speech/Clips").GetChildren()}
    assert sorted(clips) == ["flat", "hide", "idle", "idle_1"]
    assert list(clips["idle_1"].GetJointsAttr().Get()) == ["Hips/Spine/Neck/Head/Jaw"]
    hide = clips["hide"]
    assert len(hide.GetScalesAttr().GetTimeSamples()) == 22            # 0.7 s (float32) at 30 fps: 0 .. 21
    assert [tuple(hide.GetScalesAttr().Get(k)[0]) for k in (14, 15, 21)] == [(1, 1, 1), (0, 0, 0), (0, 0, 0)]
    assert tuple(clips["flat"].GetScalesAttr().Get(15)[0]) == (1, 0, 1)
    assert "clip 'lost': a channel names sampler 7, which does not exist: left out" in \
        stage.GetRootLayer().documentation
