"""Blender opens what we write and shows what we made: the demo face's blendshape GLB, its skinned (SSDR bones) GLB
and both as USD, imported by Blender's own importers (Blender 5.0 as the PyPI `bpy` module, in the venv of its own
that `make blender-deps` builds, a prerequisite of `make test`; without it these tests fail with that command, never
skip). Every mesh vertex Blender evaluates at frame times (shape keys, armature) is compared with ours, in metres
after Blender's axis conversion (glTF and USD are +Y up, Blender +Z up), and the lips are measured in millimetres
where the curves close them. Then `visemeflow blender FILE --save scene.blend`: the saved scene plays the file at
its own frame rate, over its frames, with its wav in the sequencer at frame 0.
"""

import subprocess
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from blender_check import Y_UP_TO_Z_UP, bpy_python, probe
from factories import REPO

from visemeflow.animation.bones import blend_poses, skin_vertices, solve_bones
from visemeflow.animation.gltf import write_glb
from visemeflow.animation.lips import character_gap_mm, inner_lip_pairs, pair_gap_mm
from visemeflow.animation.skinned_gltf import write_skinned_glb
from visemeflow.animation.usd import write_usd, write_usdz
from visemeflow.animation.usd_skel import write_usd_skel
from visemeflow.articulation import CLOSED_MM
from visemeflow.rig import load_demo_rig
from visemeflow.rig.character import character_from_rig
from visemeflow.rig.gltf import srgb_to_linear
from visemeflow.visemes import VISEMES

FPS = 30.0
N = 40


def speech_curves(n: int) -> np.ndarray:
    """Curves that move every viseme, with the lips shut (MBP 1, nothing else) at frames 10-12 and 30."""
    rng = np.random.default_rng(3)
    t = np.arange(n)[:, None] / FPS
    c = np.clip(np.sin(2 * np.pi * rng.uniform(1, 4, 16) * t + rng.uniform(0, 6, 16)), 0, 1) ** 2
    c = (c * rng.uniform(0.3, 0.9, 16)).astype(np.float32)
    c[[10, 11, 12, 30]] = 0.0
    c[[10, 11, 12, 30], VISEMES.index("MBP")] = 1.0
    return c


@pytest.fixture(scope="module")
def demo():
    return character_from_rig(load_demo_rig())


@pytest.fixture(scope="module")
def files(tmp_path_factory, demo):
    """The five files of one animation, and the vertices we computed for them (the demo rig's centimetres)."""
    root = tmp_path_factory.mktemp("blender")
    curves = speech_curves(N)
    bones = solve_bones(demo, 8, iterations=5)
    ours = {"morph": demo.neutral[None] + np.einsum("fs,svc->fvc", curves, demo.deltas),
            "bones": skin_vertices(bones, *blend_poses(bones, curves))}
    written = {
        "morph.glb": (write_glb(root / "morph.glb", demo, curves, FPS, name="speech"), "morph"),
        "bones.glb": (write_skinned_glb(root / "bones.glb", bones, curves, FPS, name="speech"), "bones"),
        "morph.usda": (write_usd(root / "morph.usda", demo, curves, FPS, name="speech"), "morph"),
        "morph.usdz": (write_usdz(root / "morph.usdz", demo, curves, FPS, name="speech"), "morph"),
        "bones.usda": (write_usd_skel(root / "bones.usda", bones, curves, FPS, name="speech"), "bones"),
    }
    return root, curves, ours, written


@pytest.mark.parametrize("name", ["morph.glb", "bones.glb", "morph.usda", "morph.usdz", "bones.usda"])
def test_blender_imports_each_file_and_plays_our_vertices_in_metres(files, demo, name):
    root, curves, ours, written = files
    path, kind = written[name]
    frames = [0, 5, 11, 17, 30, N - 1]
    report, meshes = probe(path, frames, root / f"{name}.npz")
    (face,) = [m for m in meshes.values() if m.shape[1] == demo.n_vertices]   # (a skinned GLB adds a bone shape)
    expected = np.einsum("ij,fvj->fvi", Y_UP_TO_Z_UP, ours[kind][frames].astype(np.float64) * 0.01)   # cm -> m
    worst = float(np.abs(face - expected).max())
    width = float(np.ptp(face[0][:, 0]))
    print(f"\n{name}: {report['objects']}; worst vertex difference {worst * 1e3:.4f} mm; head width {width:.3f} m")
    assert worst < 1e-5, worst                         # 0.01 mm: float32 positions of a 30-cm head
    assert 0.15 < width < 0.25                          # a head's size in the user's scene (it was 18 m in a GLB)
    moved = float(np.abs(expected - expected[:1]).max())
    assert moved > 1e-3                                 # the check can fail: the face moves by millimetres
    if kind == "morph":
        assert report["shape_keys"] and [k for k in next(iter(report["shape_keys"].values()))][1:] == list(VISEMES)
    if name.startswith("morph.usd"):
        # the demo head's skin colours: USD's displayColor (linear), wired by Blender's importer to Base Color
        (mesh_name,) = [n for n, m in meshes.items() if m.shape[1] == demo.n_vertices]
        np.testing.assert_allclose(report["color"][mesh_name], srgb_to_linear(demo.vertex_colors), atol=1e-5)
        assert report["base_colour"][mesh_name] == [["ShaderNodeAttribute", "displayColor"]], report["base_colour"]
    # the lips: where the curves shut them, Blender's mesh has them shut, measured in millimetres as our preview does
    pairs = inner_lip_pairs(demo)
    gaps = pair_gap_mm(face[:, pairs.ravel()].reshape(len(frames), 3, 2, 3), 1000.0)
    if kind == "morph":
        np.testing.assert_allclose(gaps, character_gap_mm(demo, curves[frames]), atol=0.01)
    closed = [i for i, f in enumerate(frames) if f in (11, 30)]
    assert (gaps[closed] < CLOSED_MM).all() and (np.delete(gaps, closed) > CLOSED_MM).any(), gaps


def test_visemeflow_blender_saves_a_scene_that_plays_the_file_with_its_sound(tmp_path, files, demo):
    root, curves, ours, written = files
    # the names the exports write: NAME.glb / NAME.usd beside NAME.wav, and the bone exports NAME.bones.glb beside it
    for name, file_name, stem in (("morph.glb", "take.glb", "take"), ("bones.usda", "usd.usda", "usd"),
                                  ("bones.glb", "voice.bones.glb", "voice"), ("morph.usdz", "pack.usdz", "pack")):
        src, kind = written[name]
        path = tmp_path / file_name
        path.write_bytes(src.read_bytes())
        sf.write(tmp_path / f"{stem}.wav", np.zeros(int(16000 * N / FPS), np.float32), 16000, subtype="PCM_16")
        done = subprocess.run([str(REPO / ".venv" / "bin" / "visemeflow"), "blender", str(path), "--save",
                               str(tmp_path / f"{file_name}.blend"), "--blender", str(bpy_python())],
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stdout + done.stderr
        assert done.stdout.startswith(f"wrote {tmp_path / file_name}.blend: ") and f"30 fps, frames 0-{N - 1}" in \
            done.stdout and f"sound {tmp_path / stem}.wav" in done.stdout, done.stdout
        # the objects listed are the file's: not the sphere Blender's glTF importer adds to draw a skin's joints
        assert "Icosphere" not in done.stdout, done.stdout
        # the .blend as saved: no fps given to the probe, the scene's own
        report, meshes = probe(tmp_path / f"{file_name}.blend", [0, 11, N - 1], tmp_path / "saved.npz", fps=None)
        assert report["fps"] == FPS and (report["frame_start"], report["frame_end"]) == (0, N - 1), report
        assert report["sync_mode"] == "AUDIO_SYNC"
        ((sound, start, length, file),) = report["sounds"]
        assert (start, length, Path(file)) == (0, N, tmp_path / f"{stem}.wav")
        (face,) = [m for m in meshes.values() if m.shape[1] == demo.n_vertices]
        expected = np.einsum("ij,fvj->fvi", Y_UP_TO_Z_UP, ours[kind][[0, 11, N - 1]].astype(np.float64) * 0.01)
        assert np.abs(face - expected).max() < 1e-5


def test_visemeflow_blender_without_a_blender_says_how_to_get_one(tmp_path, files):
    root, curves, ours, written = files
    path = written["morph.glb"][0]
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    done = subprocess.run([str(REPO / ".venv" / "bin" / "visemeflow"), "blender", str(path)], capture_output=True,
                          text=True, timeout=120, env=env)
    assert done.returncode == 2 and done.stdout == ""
    (line,) = done.stderr.splitlines()
    assert line.startswith("error: no Blender found: install Blender") and "--blender" in line and \
        "blender_open.py -- FILE" in line
    done = subprocess.run([str(REPO / ".venv" / "bin" / "visemeflow"), "blender", str(path), "--blender",
                           str(bpy_python())], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "has no window: give --save FILE.blend" in done.stderr
    (tmp_path / "curves.csv").write_text("frame\n")
    done = subprocess.run([str(REPO / ".venv" / "bin" / "visemeflow"), "blender", str(tmp_path / "curves.csv"),
                           "--blender", str(bpy_python())], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "not a GLB, glTF or USD file" in done.stderr
    # a GLB cut short, a glTF whose animation names no accessor: one line naming the file, no traceback
    (tmp_path / "cut.glb").write_bytes(path.read_bytes()[:12])
    (tmp_path / "bad.gltf").write_text('{"asset": {"version": "2.0"}, "animations": [{"samplers": [{"input": 7}]}]}')
    for name in ("cut.glb", "bad.gltf"):
        done = subprocess.run([str(REPO / ".venv" / "bin" / "visemeflow"), "blender", str(tmp_path / name),
                               "--save", str(tmp_path / "x.blend"), "--blender", str(bpy_python())],
                              capture_output=True, text=True, timeout=120)
        (line,) = done.stderr.splitlines()
        assert done.returncode == 2 and line.startswith(f"error: {tmp_path / name}: not a glTF whose animation"), \
            done.stderr


def test_visemeflow_blender_keeps_the_avatars_object_names(tmp_path):
    """Blender's glTF importer splits an animated skinned node: an Empty takes its name (`Wolf3D_Head`) and the mesh
    becomes `Wolf3D_Head.001`, so a user's script finding the head by name got an Empty. `visemeflow blender` removes
    those empty nodes and gives the meshes their names back; the saved scene still plays our weights on them."""
    from avatar_glb import make_avatar

    from visemeflow.animation.gltf_asset import write_character_glb
    from visemeflow.animation.load import load_character

    import pygltflib as gl

    source = tmp_path / "avatar.glb"
    make_avatar(source)
    avatar = gl.GLTF2().load(str(source))
    avatar.nodes[3].name = avatar.meshes[avatar.nodes[3].mesh].name   # a skinned head node named as its mesh, as RPM's
    avatar.save(str(source))
    character = load_character(source)
    weights = np.random.default_rng(7).random((N, character.n_shapes)).astype(np.float32)
    out = write_character_glb(tmp_path / "spoken.glb", character, weights, FPS, name="speech")
    blend = tmp_path / "spoken.blend"
    done = subprocess.run([str(REPO / ".venv" / "bin" / "visemeflow"), "blender", str(out), "--save", str(blend),
                           "--blender", str(bpy_python())], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    report, meshes = probe(blend, [0, 11], tmp_path / "names.npz", fps=None)
    import re

    from visemeflow.rig.gltf import GltfScene

    kinds = {name: kind for name, kind, _ in report["objects"]}
    assert not any(re.search(r"\.\d{3}$", name) for name in kinds), kinds      # no `TeethNode.001`
    scene = GltfScene(source)
    ours = character.neutral[None] + np.einsum("fs,svc->fvc", weights[[0, 11]], character.deltas)
    ours = np.einsum("ij,fvj->fvi", Y_UP_TO_Z_UP, ours.astype(np.float64))
    for part in character.parts:   # each driven mesh named as its node (or, where Blender split it, its mesh)
        names = [node.name for node in scene.gltf.nodes if node.mesh == part.mesh] + [part.name]
        shown = [n for n in names if kinds.get(n) == "MESH"]
        assert shown, (part.name, names, kinds)
        assert np.abs(meshes[shown[0]] - ours[:, part.start:part.stop]).max() < 1e-5, part.name


@pytest.mark.parametrize("suffix", [".glb", ".usda", ".usdz"])
def test_blender_plays_our_clip_on_a_users_whole_avatar_before_its_own_clips(tmp_path, suffix):
    """A Ready-Player-Me-like avatar (head skinned and textured, teeth, two eyes, a body, and an `idle` clip of its own,
    tests/test_multimesh.py): in the GLB our clip comes first, so Blender's importer makes it the active one (with it
    last, Blender muted it in the NLA and the face did not move); head and teeth play our weights, in place, in
    metres. The USD (one Mesh per part, metersPerUnit 1 for a glTF character: it said 0.01) the same. Every file
    is the whole avatar as Blender shows it: the body too, in place, the head's UVs as Blender's glTF importer gives
    them, and, in the GLB and the USDZ, the head's material with its texture (the USD held the driven meshes alone,
    untextured, until the USD writer carried the scene: `animation.usd_scene`)."""
    from avatar_glb import make_avatar
    from PIL import Image

    from visemeflow.animation.gltf_asset import write_character_glb
    from visemeflow.animation.load import load_character
    from visemeflow.rig.gltf import GltfScene

    source = tmp_path / "avatar.glb"
    make_avatar(source)
    character = load_character(source)
    weights = np.random.default_rng(5).random((N, character.n_shapes)).astype(np.float32)
    if suffix == ".glb":
        out = write_character_glb(tmp_path / "spoken.glb", character, weights, FPS, name="speech")
    elif suffix == ".usda":
        out = write_usd(tmp_path / "spoken.usda", character, weights, FPS, name="speech")
    else:
        out = write_usdz(tmp_path / "spoken.usdz", character, weights, FPS, name="speech")
    frames = [0, 6, 12, N - 1]
    report, meshes = probe(out, frames, tmp_path / "avatar.npz")
    ours = character.neutral[None] + np.einsum("fs,svc->fvc", weights[frames], character.deltas)
    ours = np.einsum("ij,fvj->fvi", Y_UP_TO_Z_UP, ours.astype(np.float64))    # metres, as the avatar's file is
    for part in character.parts:
        expected = ours[:, part.start:part.stop]
        # the Blender object holding this part: the mesh of its size nearest it at frame 0
        name = min((n for n, m in meshes.items() if m.shape[1] == part.n_vertices),
                   key=lambda n: np.abs(meshes[n][0] - expected[0]).max())
        worst = float(np.abs(meshes[name] - expected).max())
        print(f"\n{part.name} -> Blender {name}: worst {worst * 1e3:.4f} mm")
        assert worst < 1e-5, (part.name, name, worst)
    head = next(p for p in character.parts if p.name == "Wolf3D_Head")
    assert np.abs(ours[1:, head.start:head.stop] - ours[0, head.start:head.stop]).max() > 1e-3   # it moves: mm
    # the body, which no target moves, is in the scene where the file puts it
    scene = GltfScene(source)
    body_info = next(i for i in scene.meshes if i.label == "Wolf3D_Body")
    _, body_at, _, _ = scene.placed_mesh(body_info.index)
    body = Y_UP_TO_Z_UP @ body_at.astype(np.float64).T
    found = [n for n, m in meshes.items() if m.shape[1] == len(body_at) and np.abs(m[0] - body.T).max() < 1e-5]
    assert found, (suffix, report["objects"])
    # the head's texture coordinates: glTF's (u, v) from the top left, Blender's UV map (u, 1 - v) from the bottom
    head_name = next(n for n, m in meshes.items() if m.shape[1] == head.n_vertices
                     and np.abs(m[0] - ours[0, head.start:head.stop]).max() < 1e-5)
    uv = scene.placed_mesh(head.mesh)[0].uvs
    np.testing.assert_allclose(report["uv"][head_name], np.c_[uv[:, 0], 1 - uv[:, 1]], atol=1e-6)
    textures = [image for _, images in report["materials"][head_name] for image in images]
    if suffix == ".usda":     # one file holds no image: its materials carry the factors alone
        assert not textures and report["materials"][head_name], report["materials"]
    else:                     # the avatar's 2x2 skin, whose bottom-left pixel Blender stores first
        (name, width, height, pixel), = textures
        png = np.asarray(Image.open(__import__("io").BytesIO(scene.image(0)[0])).convert("RGBA"), np.float64)
        assert (width, height) == (2, 2)
        np.testing.assert_allclose(pixel, png[-1, 0] / 255, atol=1 / 255)


def test_the_script_alone_in_blender_reads_the_rate_of_a_glb_or_a_text_usd(tmp_path, files):
    """Run by hand inside Blender (`python blender_open.py FILE --save S.blend` with bpy), without --fps: the rate
    comes from the glTF's key times or the .usda header (Blender's default is 24)."""
    from visemeflow.animation.blender import SCRIPT

    root, curves, ours, written = files
    for name in ("bones.glb", "morph.usda"):
        blend = tmp_path / f"{name}.blend"
        done = subprocess.run([str(bpy_python()), str(SCRIPT), str(written[name][0]), "--save", str(blend)],
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, (done.stdout + done.stderr)[-2000:]
        report, _ = probe(blend, [0], tmp_path / "one.npz", fps=None)
        assert report["fps"] == FPS and (report["frame_start"], report["frame_end"]) == (0, N - 1), (name, report)
        assert report["sounds"] == []   # no wav beside these files
