"""Open an animation visemeflow wrote (GLB, skinned GLB, USD) in Blender, ready to play with its sound.

This file runs inside Blender's Python (it imports `bpy`, and only the standard library besides), never inside
visemeflow: `visemeflow blender FILE` runs it for you, or run it yourself:

    blender --python blender_open.py -- LJ001-0002.glb [--fps 30] [--wav LJ001-0002.wav] [--save scene.blend]
    python blender_open.py LJ001-0002.glb --save scene.blend        # a Python with the `bpy` module (PyPI bpy)

Blender's own importers play our files as we made them (tests/test_blender.py measures it), but leave three things
to do by hand that decide whether the mouth moves with the voice: the scene's frame rate (glTF has none: the glTF
importer converts seconds at the scene's rate, 24 fps by default, which is right; the USD importer puts time code k
on frame k whatever the scene's rate, so 30-fps curves in a 24-fps scene play 25% slow), the frame range (250
frames by default) and the sound. This script sets the scene's rate to the file's, imports it, sets the frame range
to the animation's (frame 0 is time 0), puts the wav beside the file (same name) in the sequencer at frame 0, and
plays in sync with the audio (frames are dropped rather than the sound drifting).
"""

from __future__ import annotations

import argparse
import json
import re
import struct
import sys
from pathlib import Path

GLTF_SUFFIXES = (".glb", ".gltf")
USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")


def gltf_fps(path: Path) -> float | None:
    """The frame rate of a GLB/glTF's first animation, from its key times' accessor (count, min and max, which the
    glTF specification requires of animation inputs): (count - 1) / (max - min), to 1/1000 of a frame a second
    (float32 times make 30 fps 30.0000018); None without an animation."""
    data = path.read_bytes()
    if data[:4] == b"glTF":
        (length,) = struct.unpack_from("<I", data, 12)
        doc = json.loads(data[20:20 + length])
    else:
        doc = json.loads(data)
    for animation in doc.get("animations", []):
        for sampler in animation.get("samplers", []):
            accessor = doc["accessors"][sampler["input"]]
            count, low, high = accessor["count"], accessor["min"][0], accessor["max"][0]
            if count > 1 and high > low:
                return round((count - 1) / (high - low), 3)
    return None


def usda_fps(path: Path) -> float | None:
    """A text USD's rate from its layer header (`timeCodesPerSecond`, else `framesPerSecond`); None for a binary
    crate or a header without either (give --fps; `visemeflow blender` reads any USD's with usd-core)."""
    with open(path, "rb") as fh:
        head = fh.read(8192)
    if not head.startswith(b"#usda"):
        return None
    for key in (rb"timeCodesPerSecond", rb"framesPerSecond"):
        found = re.search(key + rb"\s*=\s*([0-9.]+)", head)
        if found:
            return float(found.group(1))
    return None


def sound_beside(path: Path) -> Path:
    """The wav an export wrote beside `path`: NAME.wav for NAME.glb, and for the bone exports NAME.bones.glb too."""
    stem = path.stem.removesuffix(".bones")
    return path.with_name(f"{stem}.wav")


def scene_objects(scene) -> list:
    """The scene's objects a user sees: without the shapes that only draw bones (the glTF importer adds an
    "Icosphere" for the joints of a skin; it is a bone's custom shape, not part of the file)."""
    shapes = {bone.custom_shape for o in scene.objects if o.type == "ARMATURE" and o.pose is not None
              for bone in o.pose.bones if bone.custom_shape is not None}
    return [o for o in scene.objects if o not in shapes]


def merge_split_nodes(bpy, objects) -> list[str]:
    """Undo the glTF importer's split of an animated skinned node: it makes an Empty for the node and a mesh object
    beside it, one of them named `NAME.001` where the node and its mesh share a name (Ready Player Me's
    `Wolf3D_Head`), so a script that looks the head up by name may find an Empty. The Empty holds nothing (a
    skinned mesh's node transform is not used; our clip drives the mesh's shape keys): it is removed and the mesh
    takes the name. Returns the names given back."""
    def base(name: str) -> str:
        stem, dot, number = name.rpartition(".")
        return stem if dot and number.isdigit() and len(number) == 3 else name

    groups: dict[str, list] = {}
    for o in objects:
        groups.setdefault(base(o.name), []).append(o)
    back = []
    for name, group in groups.items():
        meshes = [o for o in group if o.type == "MESH" and any(m.type == "ARMATURE" for m in o.modifiers)]
        empties = [o for o in group if o.type == "EMPTY" and not o.children
                   and not (o.animation_data and o.animation_data.action)]
        if len(group) != 2 or len(meshes) != 1 or len(empties) != 1:
            continue
        bpy.data.objects.remove(empties[0])
        meshes[0].name = name
        back.append(name)
    return back


def parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="blender_open.py", description=__doc__.splitlines()[0])
    parser.add_argument("animation", type=Path, help="A GLB/glTF or USD file visemeflow wrote.")
    parser.add_argument("--fps", type=float, help="The file's frame rate (default: a glTF's key times, a text USD's "
                                                  "header; a binary USD needs it).")
    parser.add_argument("--wav", type=Path, help="The sound (default: the .wav of the same name beside the file).")
    parser.add_argument("--save", type=Path, help="Save the scene as this .blend (then Blender may run --background).")
    parser.add_argument("--empty", action="store_true", help="Start from an empty scene (the default with --save).")
    return parser.parse_args(argv)


def script_args() -> list[str]:
    """The arguments meant for this script: after `--` when Blender runs it, else the command line's."""
    return sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]


def main(argv: list[str] | None = None) -> dict:
    import bpy

    args = parse(script_args() if argv is None else argv)
    path = args.animation.resolve()
    suffix = path.suffix.lower()
    if not path.is_file() or suffix not in GLTF_SUFFIXES + USD_SUFFIXES:
        raise SystemExit(f"blender_open.py: {path}: not a GLB, glTF or USD file")
    if args.empty or args.save:
        bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    fps = args.fps or (gltf_fps(path) if suffix in GLTF_SUFFIXES else usda_fps(path))
    if fps:
        scene.render.fps = max(1, round(fps))
        scene.render.fps_base = scene.render.fps / fps       # 29.97 fps: 30 / 1.001
    before = set(bpy.data.actions)
    if suffix in GLTF_SUFFIXES:
        existing = set(bpy.data.objects)
        bpy.ops.import_scene.gltf(filepath=str(path))
        merge_split_nodes(bpy, [o for o in bpy.data.objects if o not in existing])
    else:
        bpy.ops.wm.usd_import(filepath=str(path), set_frame_range=True)
    ranges = [action.frame_range for action in bpy.data.actions if action not in before]
    if ranges:
        scene.frame_start = 0                                 # time 0 of the file
        scene.frame_end = max(0, int(round(max(r[1] for r in ranges))))
    wav = args.wav or sound_beside(path)
    sound = None
    if wav.is_file():
        editor = scene.sequence_editor_create()
        strips = getattr(editor, "strips", None)
        strips = strips if strips is not None else editor.sequences   # Blender before 4.4
        sound = strips.new_sound(wav.stem, str(wav.resolve()), 1, 0)
        scene.sync_mode = "AUDIO_SYNC"
    elif args.wav:
        raise SystemExit(f"blender_open.py: {wav}: no such sound file")
    if args.save:
        bpy.ops.wm.save_as_mainfile(filepath=str(args.save.resolve()))
    report = {"file": str(path), "fps": scene.render.fps / scene.render.fps_base, "frame_start": scene.frame_start,
              "frame_end": scene.frame_end, "objects": sorted(o.name for o in scene_objects(scene)),
              "sound": str(wav.resolve()) if sound is not None else None,
              "saved": str(args.save.resolve()) if args.save else None}
    print("blender_open: " + json.dumps(report), flush=True)
    return report


if __name__ == "__main__":
    main()
