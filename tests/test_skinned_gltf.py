"""Bone animation exports checked by real clients: the skinned GLB (visemeflow/animation/skinned_gltf.py) by the
Khronos validator (0 errors, 0 warnings) and by three.js (GLTFLoader + AnimationMixer in headless chromium: the
skinned vertex positions it computes, `SkinnedMesh.getVertexPosition`, equal our own skinning within 1e-3 of the face
size at frame times and between frames), and the UsdSkel stage (visemeflow/animation/usd_skel.py) by Pixar's
library (UsdSkel queries, `UsdSkel.BakeSkinning` reproducing our skinned points, the UsdValidation validators).

The demo rig's bones are solved once per module (8 bones, 5 iterations)."""

import json

import numpy as np
import pygltflib as gl
import pytest
from browser import serve_folder
from factories import NODE_MODULES, glb_arrays, node_or_fail, validate
from pxr import Gf, Usd, UsdGeom, UsdSkel, UsdValidation

from visemeflow.animation.bones import BoneRig, blend_poses, skin_vertices, solve_bones
from visemeflow.rig.character import character_from_rig
from visemeflow.animation.skinned_gltf import write_skinned_glb
from visemeflow.animation.usd_skel import joint_paths, write_usd_skel
from visemeflow.rig import load_demo_rig

FPS = 30.0


@pytest.fixture(scope="module")
def demo():
    return character_from_rig(load_demo_rig())


@pytest.fixture(scope="module")
def bones(demo) -> BoneRig:
    return solve_bones(demo, 8, iterations=5)


def speech_like_curves(n: int, seed: int = 0) -> np.ndarray:
    """Curves in [0, 1] that change fast enough for a wrong frame or interpolation to show."""
    rng = np.random.default_rng(seed)
    t = np.arange(n)[:, None] / FPS
    c = np.sin(2 * np.pi * rng.uniform(1, 4, 16) * t + rng.uniform(0, 6, 16))
    return (np.clip(c, 0, 1) ** 2 * rng.uniform(0.3, 1, 16)).astype(np.float32)


def slerp(a: np.ndarray, b: np.ndarray, alpha: float) -> np.ndarray:
    """Spherical interpolation of (..., 4) unit quaternions along the shorter arc, written here."""
    dot = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(dot < 0, -b, b)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1, 1))
    s = np.sin(theta)
    safe = s > 1e-9
    wa = np.where(safe, np.sin((1 - alpha) * theta) / np.where(safe, s, 1), 1 - alpha)
    wb = np.where(safe, np.sin(alpha * theta) / np.where(safe, s, 1), alpha)
    out = wa * a + wb * b
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def expected_pose(q: np.ndarray, t: np.ndarray, times32: np.ndarray, time: float):
    """glTF LINEAR sampling of the keyed poses at `time`: slerp of rotations, lerp of translations, clamped."""
    k = int(np.searchsorted(times32.astype(np.float64), time, side="right")) - 1
    if k < 0:
        return q[0], t[0]
    if k >= len(times32) - 1:
        return q[-1], t[-1]
    alpha = (time - float(times32[k])) / (float(times32[k + 1]) - float(times32[k]))
    return slerp(q[k], q[k + 1], alpha), t[k] * (1 - alpha) + t[k + 1] * alpha


# ---- the GLB's structure and the validator ---------------------------------------------------------------------
def test_skinned_glb_layout(tmp_path, bones, demo):
    curves = speech_like_curves(20)
    path = write_skinned_glb(tmp_path / "face.glb", bones, curves, FPS, name="clip")
    assert bones.mm_per_unit == 10.0   # the demo rig's centimetres: the file holds metres, glTF's unit
    bones, demo = bones.in_metres(), demo.in_metres()
    g, read = glb_arrays(path)
    assert g.scene == 0 and g.scenes[0].nodes == [0, 1]
    mesh_node, root = g.nodes[0], g.nodes[1]
    assert mesh_node.mesh == 0 and mesh_node.skin == 0 and mesh_node.translation is None
    assert root.name == "root" and root.children == list(range(2, 2 + bones.n_bones))
    (skin,) = g.skins
    assert skin.joints == [1, *range(2, 2 + bones.n_bones)] and skin.skeleton == 1
    acc = g.accessors[skin.inverseBindMatrices]
    assert (acc.type, acc.componentType, acc.count) == ("MAT4", gl.FLOAT, bones.n_bones + 1)
    view = g.bufferViews[acc.bufferView]
    ibm = np.frombuffer(g.binary_blob(), "<f4", 16 * acc.count, view.byteOffset + acc.byteOffset)
    ibm = ibm.reshape(-1, 4, 4).transpose(0, 2, 1)                                   # column-major on disk
    assert np.array_equal(ibm[0], np.eye(4))
    for b in range(bones.n_bones):
        node = g.nodes[2 + b]
        assert node.name == bones.bone_names[b] and node.rotation is None
        np.testing.assert_allclose(node.translation, bones.bind_translations[b], atol=1e-5)
        assert np.allclose(ibm[1 + b][:3, 3], -np.array(node.translation, np.float32)) and \
            np.array_equal(ibm[1 + b][:3, :3], np.eye(3))
    prim = g.meshes[0].primitives[0]
    joints, weights = read(prim.attributes.JOINTS_0), read(prim.attributes.WEIGHTS_0)
    assert g.accessors[prim.attributes.JOINTS_0].componentType == gl.UNSIGNED_BYTE
    assert np.array_equal(weights, bones.weights)
    assert np.array_equal(joints, np.where(bones.weights > 0, bones.joints + 1, 0))      # joint 0 = the root
    assert np.array_equal(read(prim.attributes.POSITION), demo.neutral)
    (anim,) = g.animations
    assert anim.name == "clip" and len(anim.channels) == 2 * bones.n_bones
    q, t = blend_poses(bones, curves)
    for ch in anim.channels:
        sampler = anim.samplers[ch.sampler]
        assert sampler.interpolation == "LINEAR"
        assert np.array_equal(read(sampler.input)[:, 0], (np.arange(20) / FPS).astype(np.float32))
        b = ch.target.node - 2
        values = read(sampler.output)
        if ch.target.path == "rotation":
            np.testing.assert_allclose(values, q[:, b][:, [1, 2, 3, 0]], atol=1e-7)
        else:
            assert ch.target.path == "translation"
            np.testing.assert_allclose(values, t[:, b], atol=1e-5)


def test_the_validator_finds_no_error_or_warning(tmp_path, bones, demo):
    files = [write_skinned_glb(tmp_path / "demo.glb", bones, speech_like_curves(90), FPS),
             write_skinned_glb(tmp_path / "one-frame.glb", bones, np.full((1, 16), 0.2), FPS)]
    for path in files:
        report = validate(path)
        issues = report["issues"]
        assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]
        info = report["info"]
        assert info["hasSkins"] and info["animationCount"] == 1 and info["totalVertexCount"] == demo.n_vertices


def test_the_validator_sees_broken_skins(tmp_path, bones):
    """Weights that do not sum to 1 and a non-unit rotation key are errors the check above would catch."""
    path = write_skinned_glb(tmp_path / "good.glb", bones, speech_like_curves(5), FPS)
    g = gl.GLTF2.load(str(path))
    blob = bytearray(g.binary_blob())
    prim = g.meshes[0].primitives[0]
    view = g.bufferViews[g.accessors[prim.attributes.WEIGHTS_0].bufferView]
    blob[view.byteOffset: view.byteOffset + 4] = np.float32(0.5).tobytes()
    rotation = next(c for c in g.animations[0].channels if c.target.path == "rotation")
    out = g.bufferViews[g.accessors[g.animations[0].samplers[rotation.sampler].output].bufferView]
    blob[out.byteOffset: out.byteOffset + 16] = np.array([0.5, 0.5, 0.5, 0.9], np.float32).tobytes()
    g.set_binary_blob(bytes(blob))
    g.save_binary(str(tmp_path / "bad.glb"))
    codes = {m["code"] for m in validate(tmp_path / "bad.glb")["issues"]["messages"] if m["severity"] == 0}
    assert "ACCESSOR_WEIGHTS_NON_NORMALIZED" in codes, codes
    assert "ACCESSOR_ANIMATION_SAMPLER_OUTPUT_NON_NORMALIZED_QUATERNION" in codes, codes


# ---- three.js -----------------------------------------------------------------------------------------------------
PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>skinned glb check</title><link rel="icon" href="data:,">
<script type="importmap">
{"imports": {"three": "/node_modules/three/build/three.module.js",
             "three/addons/": "/node_modules/three/examples/jsm/"}}
</script>
<script type="module">
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';

// Load `url`, play its first clip with an AnimationMixer and read the skinned positions three.js computes for
// `vertexIds` (SkinnedMesh.getVertexPosition: bone world matrices x bone inverses, the CPU twin of its shader) at
// each of `times`.
window.playSkinned = async (url, times, vertexIds) => {
  const gltf = await new GLTFLoader().loadAsync(url);
  const meshes = [];
  gltf.scene.traverse((o) => { if (o.isSkinnedMesh) meshes.push(o); });
  const mesh = meshes[0];
  const clip = gltf.animations[0];
  const mixer = new THREE.AnimationMixer(gltf.scene);
  const action = mixer.clipAction(clip);
  action.setLoop(THREE.LoopOnce, 1);
  action.clampWhenFinished = true;
  const positions = [];
  const v = new THREE.Vector3();
  for (const t of times) {
    action.reset().play();
    mixer.setTime(t);
    gltf.scene.updateMatrixWorld(true);
    positions.push(vertexIds.map((i) => { mesh.getVertexPosition(i, v); return [v.x, v.y, v.z]; }));
  }
  return {
    skinned: meshes.length, bones: mesh.skeleton.bones.map((b) => b.name), clips: gltf.animations.map((c) => c.name),
    tracks: clip.tracks.length, duration: clip.duration,
    interpolations: [...new Set(clip.tracks.map((t) => t.getInterpolation()))],
    vertexCount: mesh.geometry.attributes.position.count, positions,
  };
};
</script></head><body></body></html>
"""


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """(root folder, base address): a page, the node_modules and the GLBs we put in root, served on 127.0.0.1."""
    node_or_fail()
    root = tmp_path_factory.mktemp("served")
    with serve_folder(root, PAGE, NODE_MODULES) as address:
        yield root, address


def test_three_js_plays_our_skinning(tmp_path, served, browser, bones, demo):
    n = 45
    curves = speech_like_curves(n, seed=4)
    path = write_skinned_glb(tmp_path / "bones.glb", bones, curves, FPS, name="speech")
    bones, demo = bones.in_metres(), demo.in_metres()   # what the file holds: glTF's metres
    root, base = served
    (root / path.name).write_bytes(path.read_bytes())
    state = browser.load(f"{base}/index.html")
    assert state["errors"] == [], state
    times32 = (np.arange(n) / FPS).astype(np.float32)
    times = sorted({0.0, *[float(times32[k]) for k in range(0, n, 4)], float(times32[-1]),
                    *[(k + 0.5) / FPS for k in range(0, n - 1, 5)], (n - 2 + 0.3) / FPS})
    q, t = blend_poses(bones, curves)
    moving = np.linalg.norm(skin_vertices(bones, q, t) - demo.neutral, axis=2).max(axis=0)
    vertex_ids = sorted({0, demo.n_vertices - 1, *np.argsort(-moving)[:10].tolist(),
                         *np.random.default_rng(0).choice(demo.n_vertices, 20, replace=False).tolist()})
    call = f"window.playSkinned({json.dumps('/' + path.name)}, {json.dumps(times)}, {json.dumps(vertex_ids)})"
    result = browser.send("Runtime.evaluate", {"expression": call, "awaitPromise": True, "returnByValue": True})
    assert "exceptionDetails" not in result, result["exceptionDetails"]
    got = result["result"]["value"]
    assert got["skinned"] == 1 and got["clips"] == ["speech"] and got["vertexCount"] == demo.n_vertices
    assert got["bones"] == ["root", *bones.bone_names] and got["tracks"] == 2 * bones.n_bones
    assert got["interpolations"] == [2301]                       # THREE.InterpolateLinear
    assert got["duration"] == pytest.approx(float(times32[-1]), abs=1e-6)

    three = np.array(got["positions"])                           # (times, ids, 3)
    expected = []
    for time in times:
        qk, tk = expected_pose(q, t, times32, time)
        expected.append(skin_vertices(bones, qk[None], tk[None])[0][vertex_ids])
    expected = np.array(expected)
    face_size = float(np.linalg.norm(demo.neutral.max(axis=0) - demo.neutral.min(axis=0)))
    worst = float(np.abs(three - expected).max())
    print(f"\nthree.js skinning: {len(times)} times x {len(vertex_ids)} vertices, worst {worst:.2e} "
          f"(face size {face_size:.1f}, tolerance {1e-3 * face_size:.3f})")
    assert worst < 1e-3 * face_size
    # the check can fail: the animation moves these vertices by more than the tolerance
    assert np.abs(expected - demo.neutral[vertex_ids]).max() > 10 * 1e-3 * face_size
    # at frame times three.js shows exactly our blend of that frame
    on_frames = [i for i, time in enumerate(times) if abs(time * FPS - round(time * FPS)) < 1e-4]
    ours = skin_vertices(bones, q, t)[:, vertex_ids]
    frames = [int(round(times[i] * FPS)) for i in on_frames]
    assert np.abs(three[on_frames] - ours[frames]).max() < 1e-3 * face_size


# ---- USD ----------------------------------------------------------------------------------------------------------
def validation_errors(stage) -> list[str]:
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    return [f"{e.GetType()}: {e.GetMessage()}" for e in errors
            if e.GetType() == UsdValidation.ValidationErrorType.Error]


def test_usd_skel_animation_is_skinned_by_usdskel_as_we_skin(tmp_path, bones, demo):
    n = 12
    curves = speech_like_curves(n, seed=2)
    path = write_usd_skel(tmp_path / "bones.usda", bones, curves, FPS, name="utt 1")
    stage = Usd.Stage.Open(str(path))
    assert stage.GetTimeCodesPerSecond() == FPS and (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, n - 1)
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.01)
    root = UsdSkel.Root(stage.GetDefaultPrim())
    assert root and stage.GetDefaultPrim().GetName() == "utt_1"
    assert validation_errors(stage) == []

    cache = UsdSkel.Cache()
    assert cache.Populate(root, Usd.TraverseInstanceProxies())
    (binding,) = cache.ComputeSkelBindings(root, Usd.TraverseInstanceProxies())
    skel_query = cache.GetSkelQuery(binding.GetSkeleton())
    assert list(skel_query.GetJointOrder()) == joint_paths(bones)
    assert skel_query.HasBindPose() and skel_query.HasRestPose()
    (target,) = binding.GetSkinningTargets()
    assert target.GetNumInfluencesPerComponent() == 4 and not target.IsRigidlyDeformed()
    q, t = blend_poses(bones, curves)
    ours = skin_vertices(bones, q, t)
    mesh = UsdGeom.Mesh(target.GetPrim())
    # UsdSkel's own linear blend skinning of each frame through the queries
    for k in (0, 5, n - 1):
        xforms = skel_query.ComputeSkinningTransforms(Usd.TimeCode(k))
        points = mesh.GetPointsAttr().Get()
        assert target.ComputeSkinnedPoints(xforms, points, Usd.TimeCode(k))
        np.testing.assert_allclose(np.asarray(points), ours[k], rtol=0, atol=2e-4)
    # the written bound holds every frame (read before baking rewrites it)
    lo, hi = (np.array(v) for v in UsdGeom.Mesh(mesh.GetPrim()).GetExtentAttr().Get())
    assert (ours.min(axis=(0, 1)) >= lo - 1e-4).all() and (ours.max(axis=(0, 1)) <= hi + 1e-4).all()
    # and BakeSkinning (what a DCC does on import) writes the same points per time code
    assert UsdSkel.BakeSkinning(root, Gf.Interval(0, n - 1))
    for k in range(n):
        np.testing.assert_allclose(np.asarray(mesh.GetPointsAttr().Get(k)), ours[k], rtol=0, atol=2e-4)
    # not vacuous: the skinned points move
    assert np.abs(ours[5] - demo.neutral).max() > 0.1
