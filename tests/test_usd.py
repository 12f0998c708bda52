"""USD export (visemeflow/animation/usd.py), read back through Pixar's own library: the stage's metadata, the
SkelAnimation's weights at each time code, the BlendShape offsets, UsdSkel's skeleton/skinning queries, UsdSkel's
own deformation (BakeSkinning: blend shapes applied by UsdSkel itself) and the UsdValidation validators that
`usdchecker` runs."""

import numpy as np
import pytest
from factories import usd_validation_errors as validation_errors
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, UsdSkel

from visemeflow.rig.character import character_from_rig, make_character
from visemeflow.animation.usd import prim_name, read_usd_weights, write_usd
from visemeflow.rig import load_demo_rig
from visemeflow.rig.gltf import srgb_to_linear

AWKWARD = ("jaw.open", "2nd shape", "jaw_open", "viseme_PP", "mouth-smile L", "jaw.open!")


def smooth_weights(n_frames: int, n_shapes: int, fps: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames)[:, None] / fps
    freq, phase = rng.uniform(0.2, 2.0, n_shapes), rng.uniform(0, 2 * np.pi, n_shapes)
    return (0.5 + 0.5 * np.sin(2 * np.pi * freq * t + phase)).astype(np.float32)


def small_character(names=AWKWARD):
    rng = np.random.default_rng(1)
    neutral = rng.normal(size=(12, 3)).astype(np.float32)
    faces = np.array([[0, 1, 2], [2, 3, 0], [4, 5, 6], [6, 7, 4], [8, 9, 10], [10, 11, 8]])
    deltas = np.zeros((len(names), 12, 3), np.float32)
    for s in range(len(names)):
        moving = rng.choice(12, size=2 + s % 9, replace=False)  # sparse shapes and, for s >= 7, dense ones
        deltas[s, moving] = rng.normal(size=(len(moving), 3))
    deltas[-1] = rng.normal(size=(12, 3))  # every vertex moves: offsets stored densely
    return make_character("test head", neutral, faces, names, deltas)


def stored_offsets(shape: UsdSkel.BlendShape, n_vertices: int) -> np.ndarray:
    """The (V, 3) offsets a BlendShape prim stores, scattering sparse ones (pointIndices) into a full array."""
    offsets = np.asarray(shape.GetOffsetsAttr().Get(), np.float32)
    indices = shape.GetPointIndicesAttr().Get()
    full = np.zeros((n_vertices, 3), np.float32)
    if indices is None:
        full[:] = offsets
    else:
        full[np.asarray(indices)] = offsets
    return full


def skinning_targets(stage):
    cache = UsdSkel.Cache()
    root = UsdSkel.Root(stage.GetDefaultPrim())
    assert cache.Populate(root, Usd.TraverseInstanceProxies())
    bindings = cache.ComputeSkelBindings(root, Usd.TraverseInstanceProxies())
    assert len(bindings) == 1
    skel_query = cache.GetSkelQuery(bindings[0].GetSkeleton())
    return skel_query, list(bindings[0].GetSkinningTargets())


def test_short_clip_reads_back_frame_by_frame_through_usdskel(tmp_path):
    character = small_character()
    fps = 24.0
    weights = smooth_weights(10, character.n_shapes, fps)
    path = write_usd(tmp_path / "clip.usda", character, weights, fps, meters_per_unit=0.01)
    assert path.read_text().startswith("#usda 1.0")

    stage = Usd.Stage.Open(str(path))
    assert stage.GetTimeCodesPerSecond() == fps and stage.GetFramesPerSecond() == fps
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, 9)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.01)
    assert stage.GetDefaultPrim().IsA(UsdSkel.Root) and stage.GetDefaultPrim().GetName() == "test_head"

    skel_query, targets = skinning_targets(stage)
    anim_query = skel_query.GetAnimQuery()
    assert list(anim_query.GetBlendShapeOrder()) == list(AWKWARD)  # the real names, dots and spaces included
    assert list(anim_query.GetBlendShapeWeightTimeSamples()) == list(range(10))
    for k in range(10):
        got = np.asarray(anim_query.ComputeBlendShapeWeights(Usd.TimeCode(k)), np.float32)
        np.testing.assert_array_equal(got, weights[k])  # float32 in, float32 out: exact

    (mesh_query,) = targets
    assert mesh_query.HasBlendShapes() and list(mesh_query.GetBlendShapeOrder()) == list(AWKWARD)
    binding = UsdSkel.BindingAPI(mesh_query.GetPrim())
    shape_paths = binding.GetBlendShapeTargetsRel().GetTargets()
    assert len(shape_paths) == len(AWKWARD)
    assert [p.name for p in shape_paths] == ["jaw_open_1", "_2nd_shape", "jaw_open", "viseme_PP", "mouth_smile_L",
                                             "jaw_open_"]
    for s, shape_path in enumerate(shape_paths):
        assert Sdf.Path.IsValidIdentifier(shape_path.name)
        shape = UsdSkel.BlendShape(stage.GetPrimAtPath(shape_path))
        np.testing.assert_array_equal(stored_offsets(shape, character.n_vertices), character.deltas[s])
    assert UsdSkel.BlendShape(stage.GetPrimAtPath(shape_paths[0])).GetPointIndicesAttr().HasAuthoredValue()
    assert not UsdSkel.BlendShape(stage.GetPrimAtPath(shape_paths[-1])).GetPointIndicesAttr().HasAuthoredValue()

    names, read, read_fps = read_usd_weights(path)
    assert names == AWKWARD and read_fps == fps
    np.testing.assert_array_equal(read, weights)
    assert validation_errors(stage) == []  # before baking: BakeSkinning edits the stage (SkelRoot -> Xform)

    # The blend shapes as UsdSkel applies them (BlendShapeQuery), then UsdSkel's own deformation of the mesh
    query = UsdSkel.BlendShapeQuery(binding)
    assert query.GetNumBlendShapes() == len(AWKWARD)
    mesh = UsdGeom.Mesh(mesh_query.GetPrim())
    np.testing.assert_array_equal(np.asarray(mesh.GetPointsAttr().Get()), character.neutral)
    assert UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetDefaultPrim()), Gf.Interval(0, 9))
    for k in range(10):
        expected = character.neutral + np.einsum("s,svc->vc", weights[k], character.deltas)
        np.testing.assert_allclose(np.asarray(mesh.GetPointsAttr().Get(k)), expected, atol=1e-5)


@pytest.fixture(scope="module")
def demo_character():
    return character_from_rig(load_demo_rig())


@pytest.mark.parametrize("suffix", [".usd", ".usdc"])
def test_demo_rig_as_binary_crate(tmp_path, demo_character, suffix):
    fps = 30.0
    weights = smooth_weights(90, demo_character.n_shapes, fps, seed=3)
    path = write_usd(tmp_path / f"ict{suffix}", demo_character, weights, fps)
    assert path.read_bytes()[:8] == b"PXR-USDC"

    stage = Usd.Stage.Open(str(path))
    assert stage.GetTimeCodesPerSecond() == 30 and stage.GetEndTimeCode() == 89
    skel_query, (mesh_query,) = skinning_targets(stage)
    anim_query = skel_query.GetAnimQuery()
    assert list(anim_query.GetBlendShapeOrder()) == list(demo_character.shape_names)
    for k in (0, 45, 89):
        got = np.asarray(anim_query.ComputeBlendShapeWeights(Usd.TimeCode(k)), np.float32)
        np.testing.assert_array_equal(got, weights[k])
    mesh = UsdGeom.Mesh(mesh_query.GetPrim())
    assert np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3).tolist() == demo_character.faces.tolist()
    assert set(np.asarray(mesh.GetFaceVertexCountsAttr().Get()).tolist()) == {3}
    binding = UsdSkel.BindingAPI(mesh_query.GetPrim())
    for s, shape_path in enumerate(binding.GetBlendShapeTargetsRel().GetTargets()):
        shape = UsdSkel.BlendShape(stage.GetPrimAtPath(shape_path))
        assert shape_path.name == demo_character.shape_names[s]  # valid names are kept as they are
        np.testing.assert_array_equal(stored_offsets(shape, demo_character.n_vertices), demo_character.deltas[s])

    assert validation_errors(stage) == []
    # its skin colours: displayColor (linear), read by the material bound to it
    colours = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("displayColor")
    assert colours.GetInterpolation() == UsdGeom.Tokens.vertex
    np.testing.assert_allclose(np.asarray(colours.Get()), srgb_to_linear(demo_character.vertex_colors), atol=1e-7)
    material = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()[0]
    diffuse = material.ComputeSurfaceSource()[0].GetInput("diffuseColor").GetConnectedSource()[0]
    assert UsdShade.Shader(diffuse.GetPrim()).GetInput("varname").Get() == "displayColor"
    assert UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetDefaultPrim()), Gf.Interval(45, 45))
    expected = demo_character.neutral + np.einsum("s,svc->vc", weights[45], demo_character.deltas)
    np.testing.assert_allclose(np.asarray(mesh.GetPointsAttr().Get(45)), expected, atol=1e-4)


def test_the_validators_do_flag_a_broken_binding(tmp_path):
    """The validation check above is not vacuous: a mesh bound to its blend shapes without the BindingAPI is an
    error for the UsdSkel validator usdchecker runs."""
    path = write_usd(tmp_path / "broken.usda", small_character(), smooth_weights(3, len(AWKWARD), 30), 30)
    text = path.read_text()
    mesh_block = text.index('def Mesh "Mesh" (')
    path.write_text(text[:mesh_block] + text[mesh_block:].replace('prepend apiSchemas = ["SkelBindingAPI"]', "", 1))
    assert any("SkelBindingAPI" in e for e in validation_errors(Usd.Stage.Open(str(path))))


def test_prim_names():
    assert prim_name("viseme_PP") == "viseme_PP"
    assert prim_name("2nd shape") == "_2nd_shape"
    assert prim_name("jaw.open") == "jaw_open"
    assert all(Sdf.Path.IsValidIdentifier(prim_name(n)) for n in ("", "1", "ä", "a/b", "a:b"))


def test_bad_input_is_refused_and_leaves_the_old_file(tmp_path):
    character = small_character()
    good = smooth_weights(4, character.n_shapes, 30)
    path = write_usd(tmp_path / "keep.usda", character, good, 30)
    before = path.read_bytes()
    nan = good.copy()
    nan[1, 2] = np.nan
    for weights, fps, match in [(good[:, :3], 30, "weights must be"), (good[:0], 30, "weights must be"),
                                (nan, 30, "NaN"), (good * 2, 30, r"\[0, 1\]"), (good, 0, "fps"),
                                (good, float("nan"), "fps")]:
        with pytest.raises(ValueError, match=match):
            write_usd(path, character, weights, fps)
    with pytest.raises(ValueError, match="suffix"):
        write_usd(tmp_path / "x.usdz", character, good, 30)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.usda"]  # no temporary file left behind


def test_usd_calls_wait_for_each_other_across_threads(tmp_path):
    """USD's first use from two threads at once can deadlock for good (C++ static-init guards against the GIL: it
    hung an `animate` writing two packages' .usd files). Every USD call of ours takes one lock, whose wait releases
    the GIL: a write started while another thread holds it waits, then finishes."""
    import threading

    from visemeflow.animation import usd

    character = small_character()
    weights = smooth_weights(4, character.n_shapes, 30.0)
    done = threading.Event()
    with usd._USD_LOCK:
        writer = threading.Thread(target=lambda: (write_usd(tmp_path / "a.usda", character, weights, 30.0),
                                                  done.set()))
        writer.start()
        assert not done.wait(1.0)          # held off by the lock
    assert done.wait(60.0) and read_usd_weights(tmp_path / "a.usda")[1].shape == (4, character.n_shapes)
    writer.join()


def test_many_threads_writing_their_first_usd_stage_at_once_all_finish(tmp_path):
    """The race itself, in fresh processes (it is the first use that builds USD's singletons): 16 threads released
    together by a barrier each write a stage. Unlocked, such a process hung about 1 run in 10."""
    import subprocess
    import sys

    from factories import REPO

    script = f"""
import sys, threading
sys.path.insert(0, {str(REPO / 'tests')!r})
import numpy as np
from factories import tiny_character
from visemeflow.animation.usd import write_usd
c = tiny_character(["a", "b", "c"], name="t")
barrier = threading.Barrier(16)
def go(i):
    barrier.wait()
    write_usd({str(tmp_path)!r} + f"/{{i}}.usdc", c, np.zeros((3, 3), np.float32), 30.0)
threads = [threading.Thread(target=go, args=(i,)) for i in range(16)]
[t.start() for t in threads]
[t.join() for t in threads]
"""
    for _ in range(3):
        subprocess.run([sys.executable, "-c", script], cwd=REPO, timeout=120, check=True)
    assert len(list(tmp_path.glob("*.usdc"))) == 16
