"""Avatars whose face is several meshes sharing morph target names (Ready Player Me, VRoid, Mixamo, MetaHuman,
Character Creator): one character drives them all, and the GLB export is the user's whole asset with our clip added.

The avatar is built by tests/avatar_glb.py with pygltflib: a skinned head (JOINTS_0/WEIGHTS_0, inverse bind matrices that do not
cancel the joints' rest transforms), teeth with the mouth targets in another order, two eyes with blink and mouth
targets (zero deltas), a body without targets, a textured material (an embedded PNG), a node hierarchy with
translations, and an existing animation (a rotation of the eyes' group). Checked: which meshes are driven and why
the others are not, `--mesh`, the errors, the Khronos validator, byte/JSON identity of everything that was there,
three.js playing the new clip on every driven mesh, and the animate flow writing the whole asset.
"""

import json
import struct
from pathlib import Path

import numpy as np
import pygltflib as gl
import pytest
from avatar_glb import HEAD_TARGETS, TEETH_TARGETS, HEAD_JOINT_OFFSET, AVATAR_AT, TEETH_AT, EYES_AT, make_avatar
from browser import serve_folder
from factories import NODE_MODULES, make_curve_store, node_or_fail, validate

from visemeflow.rig.character import CharacterError
from visemeflow.shapes.conventions import bind
from visemeflow.animation.gltf_asset import write_character_glb
from visemeflow.animation.load import load_character
from visemeflow.animation.package import AnimateConfig

@pytest.fixture(scope="module")
def avatar(tmp_path_factory) -> tuple[Path, dict]:
    path = tmp_path_factory.mktemp("avatar") / "avatar.glb"
    return path, make_avatar(path)


def glb_parts(path: Path) -> tuple[dict, bytes]:
    """(JSON document, binary chunk) of a GLB, read here without our code."""
    data = path.read_bytes()
    assert data[:4] == b"glTF" and struct.unpack_from("<II", data, 4) == (2, len(data))
    json_length, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A
    document = json.loads(data[20:20 + json_length])
    bin_length, bin_type = struct.unpack_from("<II", data, 20 + json_length)
    assert bin_type == 0x004E4942
    return document, data[28 + json_length: 28 + json_length + bin_length]


# ---- the loader -------------------------------------------------------------------------------------------------
def test_the_loader_drives_head_teeth_and_eyes_in_place_and_names_the_body(avatar):
    path, arrays = avatar
    c = load_character(path)
    assert [p.name for p in c.parts] == ["Wolf3D_Head", "Wolf3D_Teeth", "EyeLeft", "EyeRight"]
    # the object names Blender shows (the nodes') first, where the meshes' differ
    assert c.left_out == ("BodyNode (mesh Wolf3D_Body; no targets)",)
    assert c.name == "avatar" and c.shape_names == tuple(HEAD_TARGETS + ["tongueOut"])
    assert c.describe() == ("character avatar.glb: driving HeadNode (mesh Wolf3D_Head, 30 v), TeethNode (mesh "
                            "Wolf3D_Teeth, 6 v), EyeLeftNode (mesh EyeLeft, 4 v), EyeRightNode (mesh EyeRight, 4 v): 17 "
                            "targets, 1 of them on every mesh; not driven: BodyNode (mesh Wolf3D_Body; no targets)")
    head, teeth, left, right = c.parts
    assert (head.start, head.stop, teeth.stop, left.stop, right.stop) == (0, 30, 36, 40, 44) == (0, 30, 36, 40,
                                                                                                   c.n_vertices)
    assert head.nodes == (3,) and teeth.nodes == (4,) and left.nodes == (6,) and right.nodes == (7,)
    assert teeth.target_names == tuple(TEETH_TARGETS) and teeth.columns(c.shape_names) == [1, 0, 2, 16]
    # the skinned head in its rest pose: each vertex shifted by its head-joint weight times the joint's offset
    expected_head = arrays["head"] + arrays["head_weight"][:, None] * HEAD_JOINT_OFFSET
    np.testing.assert_allclose(c.neutral[:30], expected_head, atol=1e-6)
    np.testing.assert_allclose(c.deltas[:16, :30], arrays["head_deltas"], atol=1e-6)   # translations only
    assert "skin 0" in head.placement and "node 4" in teeth.placement
    # the other meshes by their nodes' world transforms (the root's translation included)
    np.testing.assert_allclose(c.neutral[30:36], arrays["teeth"] + AVATAR_AT + TEETH_AT, atol=1e-6)
    np.testing.assert_allclose(c.neutral[36:40], arrays["eye"] + AVATAR_AT + EYES_AT + [-0.03, 0, 0], atol=1e-6)
    np.testing.assert_allclose(c.neutral[40:44], arrays["eye"] + AVATAR_AT + EYES_AT + [0.03, 0, 0], atol=1e-6)
    # each part's targets in its columns, zeros elsewhere
    np.testing.assert_allclose(c.deltas[[1, 0, 2, 16], 30:36], arrays["teeth_deltas"], atol=1e-7)
    assert not c.deltas[3:16, 30:36].any() and not c.deltas[16, :30].any() and not c.deltas[:, 36:].any()
    assert c.faces.max() == 43 and c.faces[len(c.faces) - 1].min() >= 40
    assert bind(c).convention == "arkit52"


def test_mesh_option_chooses_meshes_and_an_unknown_one_lists_them(avatar):
    path, _ = avatar
    c = load_character(path, meshes=["Wolf3D_Teeth", "Wolf3D_Head"])
    assert [p.name for p in c.parts] == ["Wolf3D_Teeth", "Wolf3D_Head"]
    assert c.shape_names[:4] == tuple(TEETH_TARGETS) and c.n_vertices == 36
    assert "EyeLeftNode (mesh EyeLeft; not asked for)" in c.left_out and \
        "BodyNode (mesh Wolf3D_Body; not asked for)" in c.left_out
    by_node = load_character(path, meshes=["EyeRightNode"])          # a node's name finds the mesh it instances
    assert [p.name for p in by_node.parts] == ["EyeRight"] and by_node.parts[0].nodes == (7,)
    with pytest.raises(CharacterError) as info:
        load_character(path, meshes=["Wolf3D_Haed"])
    message = str(info.value)
    assert str(path) in message and "no mesh 'Wolf3D_Haed'" in message
    assert "Wolf3D_Head (30 v, 16 targets)" in message and "Wolf3D_Body (9 v, no targets)" in message
    with pytest.raises(CharacterError, match="'Wolf3D_Body' has no morph targets"):
        load_character(path, meshes=["Wolf3D_Body"])


def test_a_body_with_other_targets_is_named_and_a_scene_with_nothing_usable_names_every_mesh(tmp_path):
    path = tmp_path / "breathing.glb"
    make_avatar(path, body_targets=["breathe"])
    c = load_character(path)
    assert [p.name for p in c.parts] == ["Wolf3D_Head", "Wolf3D_Teeth", "EyeLeft", "EyeRight"]
    assert c.left_out == ("BodyNode (mesh Wolf3D_Body; targets breathe: none usable)",)

    d = gl.GLTF2.load(str(path))
    for mesh in d.meshes:                  # every name made unusable: a head with "a0".. and a body with "breathe"
        names = mesh.extras.get("targetNames")
        if names and names != ["breathe"]:
            mesh.extras = mesh.primitives[0].extras = {"targetNames": [f"{mesh.name}_{k}" for k in range(len(names))]}
    d.save_binary(str(tmp_path / "nothing.glb"))
    with pytest.raises(CharacterError) as info:
        load_character(tmp_path / "nothing.glb")
    message = str(info.value)
    assert str(tmp_path / "nothing.glb") in message and "can drive" in message
    for expected in ("Wolf3D_Head (30 v, 16 targets: Wolf3D_Head_0,", "Wolf3D_Teeth (6 v, 4 targets",
                     "EyeLeft (4 v", "EyeRight (4 v", "Wolf3D_Body (9 v, 1 targets: breathe)"):
        assert expected in message, (expected, message)


@pytest.mark.parametrize("extension", ["KHR_draco_mesh_compression", "EXT_meshopt_compression"])
def test_compressed_geometry_is_refused_with_how_to_decompress(tmp_path, avatar, extension):
    d = gl.GLTF2.load(str(avatar[0]))
    d.extensionsUsed, d.extensionsRequired = [extension], [extension]
    d.save_binary(str(tmp_path / "packed.glb"))
    with pytest.raises(CharacterError) as info:
        load_character(tmp_path / "packed.glb")
    message = str(info.value)
    assert str(tmp_path / "packed.glb") in message and extension in message
    assert "gltf-transform" in message and "Blender" in message


# ---- the whole asset back -----------------------------------------------------------------------------------
def _weights(c, n: int = 40, seed: int = 5) -> np.ndarray:
    return np.random.default_rng(seed).random((n, c.n_shapes)).astype(np.float32)


KEPT = ("asset", "scene", "scenes", "nodes", "meshes", "materials", "textures", "images", "samplers", "skins")


def assert_whole_asset_kept(source: Path, written: Path) -> tuple[dict, bytes]:
    before, before_bin = glb_parts(source)
    after, after_bin = glb_parts(written)
    for key in KEPT:
        assert after.get(key) == before.get(key), key
    n_views, n_accessors = len(before["bufferViews"]), len(before["accessors"])
    assert after["bufferViews"][:n_views] == before["bufferViews"]
    assert after["accessors"][:n_accessors] == before["accessors"]
    assert after["animations"][1:] == before["animations"]    # ours first: the one Blender makes active
    for view in before["bufferViews"]:
        start, stop = view.get("byteOffset", 0), view.get("byteOffset", 0) + view["byteLength"]
        assert after_bin[start:stop] == before_bin[start:stop]
    assert after["buffers"] == [{"byteLength": len(after_bin)}]    # only its length changed: our data at its end
    return after, after_bin


def test_the_glb_export_is_the_whole_asset_with_one_clip_added_that_the_validator_accepts(tmp_path, avatar):
    path, _ = avatar
    c = load_character(path)
    w = _weights(c)
    out = write_character_glb(tmp_path / "spoken.glb", c, w, 30.0, name="hello")
    after, after_bin = assert_whole_asset_kept(path, out)
    clip = after["animations"][0]
    assert clip["name"] == "hello" and len(after["animations"]) == 2
    assert [ch["target"] for ch in clip["channels"]] == [{"node": n, "path": "weights"} for n in (3, 4, 6, 7)]
    accessors = after["accessors"]
    times = accessors[clip["samplers"][0]["input"]]
    assert times["count"] == 40 and times["min"] == [0.0] and times["max"] == pytest.approx([39 / 30])
    for part, sampler in zip(c.parts, clip["samplers"]):
        assert sampler["interpolation"] == "LINEAR"
        output = accessors[sampler["output"]]
        view = after["bufferViews"][output["bufferView"]]
        values = np.frombuffer(after_bin, "<f4", output["count"], view["byteOffset"]).reshape(40, -1)
        assert np.array_equal(values, w[:, part.columns(c.shape_names)]), part.name
    report = validate(out)
    issues = report["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]
    assert report["info"]["animationCount"] == 2 and report["info"]["hasTextures"]


def test_a_gltf_with_external_buffer_and_image_comes_back_as_one_self_contained_glb(tmp_path, avatar):
    path, _ = avatar
    folder = tmp_path / "split"
    folder.mkdir()
    d = gl.GLTF2.load(str(path))
    blob = d.binary_blob()
    image_view = d.bufferViews[d.images[0].bufferView]
    png = blob[image_view.byteOffset: image_view.byteOffset + image_view.byteLength]
    (folder / "skin.png").write_bytes(png)
    d.images[0].bufferView, d.images[0].mimeType, d.images[0].uri = None, None, "skin.png"
    (folder / "avatar.bin").write_bytes(blob)
    d.buffers[0].uri = "avatar.bin"
    d._glb_data = None
    d.save_json(str(folder / "avatar.gltf"))
    c = load_character(folder / "avatar.gltf")
    assert [p.name for p in c.parts] == ["Wolf3D_Head", "Wolf3D_Teeth", "EyeLeft", "EyeRight"]
    out = write_character_glb(tmp_path / "spoken.glb", c, _weights(c, 10), 30.0, name="hi")
    after, after_bin = glb_parts(out)
    image = after["images"][0]
    assert "uri" not in image and image["mimeType"] == "image/png"
    view = after["bufferViews"][image["bufferView"]]
    assert after_bin[view["byteOffset"]: view["byteOffset"] + view["byteLength"]] == png
    assert after["buffers"] == [{"byteLength": after["buffers"][0]["byteLength"]}]
    assert validate(out)["issues"]["numErrors"] == 0
    again = load_character(out)
    np.testing.assert_array_equal(again.neutral, c.neutral)
    np.testing.assert_array_equal(again.deltas, c.deltas)


# ---- three.js -------------------------------------------------------------------------------------------------
PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>avatar check</title><link rel="icon" href="data:,">
<script type="importmap">
{"imports": {"three": "/node_modules/three/build/three.module.js",
             "three/addons/": "/node_modules/three/examples/jsm/"}}
</script>
<script type="module">
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';

// Load `url`, play the clip named `clip` and read every morphing mesh's influences (by its node's name) at `times`.
window.playClip = async (url, clip, times) => {
  const gltf = await new GLTFLoader().loadAsync(url);
  const meshes = [];
  gltf.scene.traverse((o) => { if (o.isMesh && o.morphTargetInfluences) meshes.push(o); });
  const mixer = new THREE.AnimationMixer(gltf.scene);
  const action = mixer.clipAction(THREE.AnimationClip.findByName(gltf.animations, clip));
  action.setLoop(THREE.LoopOnce, 1);
  action.clampWhenFinished = true;
  const influences = Object.fromEntries(meshes.map((m) => [m.name, []]));
  for (const t of times) {
    action.reset().play();
    mixer.setTime(t);
    for (const m of meshes) influences[m.name].push(Array.from(m.morphTargetInfluences));
  }
  return { clips: gltf.animations.map((c) => c.name), influences,
           dictionaries: Object.fromEntries(meshes.map((m) => [m.name, m.morphTargetDictionary])),
           skinned: meshes.filter((m) => m.isSkinnedMesh).map((m) => m.name),
           textured: meshes.filter((m) => m.material.map).map((m) => m.name) };
};
window.pageReady = true;
</script></head><body></body></html>
"""


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    node_or_fail()
    root = tmp_path_factory.mktemp("served-avatar")
    with serve_folder(root, PAGE, NODE_MODULES) as address:
        yield root, address


def test_three_js_plays_the_new_clip_on_every_driven_mesh(tmp_path, avatar, served, browser):
    path, _ = avatar
    c = load_character(path)
    fps, n = 30.0, 40
    w = _weights(c, n)
    out = write_character_glb(tmp_path / "played.glb", c, w, fps, name="speech")
    root, base = served
    (root / out.name).write_bytes(out.read_bytes())
    state = browser.load(f"{base}/index.html")
    assert state["errors"] == [], state
    times = [0.0, 0.5 / fps, 7 / fps, 12.25 / fps, 30.5 / fps, (n - 1) / fps]
    call = f"window.playClip({json.dumps('/' + out.name)}, 'speech', {json.dumps(times)})"
    result = browser.send("Runtime.evaluate", {"expression": call, "awaitPromise": True, "returnByValue": True})
    assert "exceptionDetails" not in result, result["exceptionDetails"]
    got = result["result"]["value"]
    assert got["clips"] == ["speech", "idle"]
    assert got["skinned"] == ["HeadNode"] and got["textured"] == ["HeadNode"]
    frame_times = np.arange(n) / fps
    nodes = {"HeadNode": c.parts[0], "TeethNode": c.parts[1], "EyeLeftNode": c.parts[2], "EyeRightNode": c.parts[3]}
    assert set(got["influences"]) == set(nodes)
    for node, part in nodes.items():
        assert got["dictionaries"][node] == {name: k for k, name in enumerate(part.target_names)}
        own = w[:, part.columns(c.shape_names)]
        expected = np.stack([[np.interp(t, frame_times, own[:, k]) for k in range(own.shape[1])] for t in times])
        np.testing.assert_allclose(np.array(got["influences"][node]), expected, atol=1e-3, err_msg=node)


# ---- the flow -----------------------------------------------------------------------------------------------
@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_the_animate_flow_writes_the_whole_avatar_and_says_what_it_drives(tmp_path, avatar):
    from visemeflow.flows.animate import AnimateParams, animate_flow

    path, _ = avatar
    store = make_curve_store(tmp_path / "store", n=1)
    result = animate_flow(AnimateParams(store=store.root, characters=[path], source="ground_truth",
                                        config=AnimateConfig(formats=("glb", "usd", "json"), fps=30.0)))
    assert result["character_choices"] == [load_character(path).describe()]
    (report,) = result["packages_written"]
    assert report["meshes"] == ["Wolf3D_Head", "Wolf3D_Teeth", "EyeLeft", "EyeRight"]
    after, _ = assert_whole_asset_kept(path, Path(report["files"]["glb"]))
    assert [a["name"] for a in after["animations"]] == [Path(report["files"]["glb"]).stem, "idle"]
    assert validate(Path(report["files"]["glb"]))["issues"]["numErrors"] == 0

    chosen = animate_flow(AnimateParams(store=store.root, characters=[path], source="ground_truth",
                                        config=AnimateConfig(formats=("glb",), fps=30.0,
                                                             meshes=("Wolf3D_Head",)), out=tmp_path / "head"))
    (report,) = chosen["packages_written"]
    assert report["meshes"] == ["Wolf3D_Head"]
    channels = glb_parts(Path(report["files"]["glb"]))[0]["animations"][0]["channels"]
    assert [ch["target"]["node"] for ch in channels] == [3]


def test_the_cli_refuses_an_unknown_mesh_listing_the_meshes(avatar):
    from typer.testing import CliRunner

    from visemeflow.cli import app

    path, _ = avatar
    result = CliRunner().invoke(app, ["animate", "--character", str(path), "--mesh", "Nope"])
    assert result.exit_code == 2
    assert "no mesh 'Nope'" in result.output and "Wolf3D_Teeth (6 v, 4 targets)" in result.output


def test_usd_has_one_mesh_per_part_with_its_own_shapes_that_usdskel_deforms(tmp_path, avatar):
    from pxr import Gf, Usd, UsdGeom, UsdSkel
    from factories import usd_validation_errors as validation_errors

    from visemeflow.animation.usd import read_usd_weights, write_usd

    path, _ = avatar
    c = load_character(path)
    w = _weights(c, 6)
    out = write_usd(tmp_path / "avatar.usda", c, w, 30.0, name="speech")
    names, read, _ = read_usd_weights(out)
    assert names == c.shape_names and np.array_equal(read, w)
    stage = Usd.Stage.Open(str(out))
    assert validation_errors(stage) == []
    meshes = {p.GetName(): UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)}
    # the driven parts (by mesh), then the body no target moves (static, as the scene places it, by its node's name:
    # `animation.usd_scene`)
    assert list(meshes) == ["Wolf3D_Head", "Wolf3D_Teeth", "EyeLeft", "EyeRight", "BodyNode"]
    assert not UsdSkel.BindingAPI(meshes["BodyNode"].GetPrim()).GetSkeletonRel().GetTargets()
    for part in c.parts:
        tokens = UsdSkel.BindingAPI(meshes[part.name].GetPrim()).GetBlendShapesAttr().Get()
        assert tuple(tokens) == part.target_names
    assert UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetDefaultPrim()), Gf.Interval(0, 5))
    for k in (0, 3, 5):
        expected = c.neutral + np.einsum("s,svc->vc", w[k], c.deltas)
        for part in c.parts:
            points = np.asarray(meshes[part.name].GetPointsAttr().Get(k))
            np.testing.assert_allclose(points, expected[part.start:part.stop], atol=1e-5, err_msg=part.name)


# ---- output errors ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fmt", ["glb", "usd", "json", "audio"])
def test_a_full_disk_while_writing_an_export_names_the_output_file(tmp_path, avatar, monkeypatch, fmt):
    """ENOSPC when one export of a package is flushed to disk: the error names that output file (after the
    utterance), not the character file it was made from, and says what failed; no file is left half-written."""
    import errno

    import visemeflow.atomic as atomic
    from visemeflow.animation.package import EXPORTERS
    from visemeflow.tasks.animate import AnimateError, animate, content_hash

    path, _ = avatar
    store = make_curve_store(tmp_path / "store", n=1)
    out = tmp_path / "out"
    suffix = {**{name: e.suffix for name, e in EXPORTERS.items()}, "audio": ".wav"}[fmt]
    real_fsync = atomic._fsync_path

    def disk_full_for(temporary: Path) -> None:
        if f"u0{suffix}." in Path(temporary).name:
            raise OSError(errno.ENOSPC, "No space left on device")
        real_fsync(temporary)

    monkeypatch.setenv("VISEMEFLOW_FSYNC", "1")
    monkeypatch.setattr(atomic, "_fsync_path", disk_full_for)
    config = AnimateConfig(formats=("glb", "usd", "json"), fps=30.0)
    audio = store.read_table("utterances").column("audio_path")[0].as_py()
    with pytest.raises(AnimateError) as caught:
        animate(store, "spk/u0", "ground_truth", "cm", str(path), content_hash(path), None, None, config, audio,
                str(out))
    failed = next(out.rglob("u0")) / f"u0{suffix}"
    assert caught.value.path == str(failed)
    assert caught.value.error_type == "ExportWriteError"
    assert str(caught.value).startswith(f"spk/u0: {failed}: "), str(caught.value)
    assert "No space left on device" in str(caught.value) and str(path) not in str(caught.value)
    assert not failed.exists() and not [p for p in failed.parent.iterdir() if p.name.startswith(".")]


def _gltf_without_its_texture(source: Path, folder: Path) -> Path:
    """The avatar as `folder/avatar.gltf` whose image 0 is `skin.png`, a file not copied beside it."""
    g = gl.GLTF2().load(str(source))
    g.convert_buffers(gl.BufferFormat.DATAURI)
    g.images[0].bufferView, g.images[0].uri = None, "skin.png"
    folder.mkdir()
    path = folder / "avatar.gltf"
    path.write_text(json.dumps(json.loads(g.to_json())))
    return path


def test_a_gltf_whose_texture_file_is_missing_still_speaks_and_says_what_it_left_out(tmp_path, avatar):
    """The avatar as a .gltf whose skin.png was not copied beside it (a user's usual slip): the package is written,
    the GLB holds a grey stand-in for the skin (the Khronos validator accepts it), the USDZ leaves the skin out, and
    the report's warnings say so, naming the file; before, the run failed after the predictions with three tracebacks."""
    import zipfile

    from visemeflow.tasks.animate import animate, content_hash

    path = _gltf_without_its_texture(avatar[0], tmp_path / "model")
    store = make_curve_store(tmp_path / "store", n=1)
    config = AnimateConfig(formats=("glb", "usdz"), fps=30.0)
    audio = store.read_table("utterances").column("audio_path")[0].as_py()
    report = animate(store, "spk/u0", "ground_truth", "cm", str(path), content_hash(path), None, None, config, audio,
                     str(tmp_path / "out"))
    (note,) = [w for w in report["warnings"] if "skin.png" in w]
    assert "is not beside avatar.gltf: the GLB holds a grey 1-pixel stand-in" in note, report["warnings"]
    glb = Path(report["files"]["glb"])
    document, _ = glb_parts(glb)
    assert document["images"][0]["mimeType"] == "image/png" and "missing" in document["images"][0]["name"]
    assert validate(glb)["issues"]["numErrors"] == 0
    assert not [n for n in zipfile.ZipFile(report["files"]["usdz"]).namelist() if n.startswith("textures/")]


def test_animate_and_its_rerun_print_what_the_package_left_out(tmp_path, avatar):
    """The missing texture above, through the commands: `animate` prints the package's warning, and so does
    `rerun --stage animate` (whose summary held only counts; Prefect's console now leaves such lines to the
    commands, so without it the rerun would say nothing of the stand-in)."""
    from typer.testing import CliRunner

    from visemeflow.cli import app

    path = _gltf_without_its_texture(avatar[0], tmp_path / "model")
    store = make_curve_store(tmp_path / "store", n=1)
    runner = CliRunner()
    done = runner.invoke(app, ["animate", "spk/u0", "--character", str(path), "--store", str(store.root),
                               "--source", "ground_truth", "--variant", "cm", "--format", "glb"])
    assert done.exit_code == 0, done.output
    assert "warning: " in done.stderr and "(skin.png) is not beside avatar.gltf" in done.stderr, done.stderr
    done = runner.invoke(app, ["rerun", "spk/u0", "--stage", "animate", "--force", "--store", str(store.root)])
    assert done.exit_code == 0, done.output
    (line,) = [x for x in done.stderr.splitlines() if "skin.png" in x]
    assert line.startswith("warning: spk/u0 -> avatar: material 'skin'") and "is not beside avatar.gltf" in line, \
        done.stderr
