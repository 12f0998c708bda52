"""Build an ARKit-named character from the ICT Face Model: the demo face with ICT's own ARKit-style shapes under
ARKit's names (`jawOpen`, `mouthStretchLeft`, ...), as a GLB that any glTF tool opens and `visemeflow animate
--character` drives through the ARKit table: a character to try `--character` with before you have your own.

Run from the repository root:  .venv/bin/python examples/build_arkit_character.py [--out GLB] [--ict DIR]
                                                                                [--write-shapes]

The mesh, triangles and vertex colours are the shipped demo rig's (the ICT head cropped to what a frontal camera
sees); the shapes are the ICT model's 35 mouth/jaw/cheek/nose shapes named as in ARKit (`_L` -> `Left`, `_R` ->
`Right`; `cheekPuff_L` + `_R` -> `cheekPuff`; `cheekRaiser` has no ARKit name and is left out): 32 shapes. They
come from the package's `visemeflow/rig/data/ict_arkit.npz` (ICT-FaceKit, MIT, its LICENSE beside it; float16 on
the 15,351 vertices they move, 1.5 MB, within 0.01 mm of the kit's), or with `--ict DIR` from the raw kit
(`../shared/data/ict_facekit`). `--write-shapes` (maintainers) writes that npz again from `--ict`. The GLB (about
6 MB) is not shipped: `make demo` builds it into visemeflow-out/characters/.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "examples"))

from build_arkit_table import DEFAULT_ICT, arkit_basis  # noqa: E402

from visemeflow.rig.character import Character, make_character  # noqa: E402
from visemeflow.animation.gltf import write_glb  # noqa: E402
from visemeflow.rig import demo_rig_path, load_demo_arkit_shapes, load_demo_rig  # noqa: E402

DEFAULT_OUT = REPO / "visemeflow-out" / "characters" / "ict_arkit.glb"


def build_character(ict: Path | None = None) -> Character:
    """The demo face with the ICT shapes under their ARKit names: from the raw kit `ict`, else the shipped shapes."""
    rig = load_demo_rig()
    if ict is None:
        names, deltas = load_demo_arkit_shapes()
        source = demo_rig_path().with_name("ict_arkit.npz")
    else:
        names, basis = arkit_basis(ict)
        deltas, source = basis.reshape(len(names), rig.n_vertices, 3), ict
    character = make_character("ict_arkit", rig.neutral, rig.faces, names, deltas, source, rig.vertex_colors)
    return replace(character, mm_per_unit=10.0)   # the ICT rig's centimetres: the GLB is written in metres


def write_shapes(ict: Path, path: Path) -> None:
    """The shipped `ict_arkit.npz` from the raw kit: names, the vertices any shape moves, float16 offsets."""
    names, basis = arkit_basis(ict)
    deltas = basis.reshape(len(names), -1, 3)
    moving = np.flatnonzero(np.abs(deltas).max(axis=(0, 2)) > 0)
    np.savez_compressed(path, names=np.array(names), vertices=moving.astype(np.int32),
                        deltas=deltas[:, moving].astype(np.float16))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ict", type=Path, default=None, help="the raw ICT-FaceKit (default: the shipped shapes)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--write-shapes", action="store_true", help="write visemeflow/rig/data/ict_arkit.npz from "
                                                                    "--ict (default ../shared/data/ict_facekit)")
    args = parser.parse_args(argv)
    if args.write_shapes:
        target = demo_rig_path().with_name("ict_arkit.npz")
        write_shapes(args.ict or DEFAULT_ICT, target)
        print(f"wrote {target}")
        return 0
    character = build_character(args.ict)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_glb(args.out, character, np.zeros((1, character.n_shapes), np.float32), 30.0, name="rest")
    print(f"wrote {args.out}: {character.n_vertices} vertices, {character.n_shapes} ARKit shapes "
          f"({', '.join(character.shape_names)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
