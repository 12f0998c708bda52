"""Build an ARKit-named character from the ICT Face Model: the demo face with ICT's own ARKit-style shapes under
ARKit's names (`jawOpen`, `mouthStretchLeft`, ...), as a GLB that any glTF tool opens and `visemeflow animate
--character` drives through the ARKit table.

Run from the repository root:  .venv/bin/python examples/build_arkit_character.py [--ict DIR] [--out GLB]

Input: `../shared/data/ict_facekit` (ICT-FaceKit, MIT; its LICENSE applies to the GLB). The mesh, triangles and
vertex colours are the shipped demo rig's (the ICT head cropped to what a frontal camera sees); the shapes are the
ICT model's 35 mouth/jaw/cheek/nose shapes named as in ARKit (`_L` -> `Left`, `_R` -> `Right`; `cheekPuff_L` + `_R`
-> `cheekPuff`; `cheekRaiser` has no ARKit name and is left out): 32 shapes. The output is not shipped (about 4 MB);
the tests build it from the shared data.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "examples"))

from build_arkit_table import DEFAULT_ICT, arkit_basis  # noqa: E402

from visemeflow.rig.character import Character, make_character  # noqa: E402
from visemeflow.animation.gltf import write_glb  # noqa: E402
from visemeflow.rig import load_demo_rig  # noqa: E402

DEFAULT_OUT = REPO / "visemeflow-out" / "characters" / "ict_arkit.glb"


def build_character(ict: Path = DEFAULT_ICT) -> Character:
    """The demo face with the ICT shapes under their ARKit names."""
    rig = load_demo_rig()
    names, basis = arkit_basis(ict)
    return make_character("ict_arkit", rig.neutral, rig.faces, names, basis.reshape(len(names), rig.n_vertices, 3),
                          ict, rig.vertex_colors)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ict", type=Path, default=DEFAULT_ICT)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    character = build_character(args.ict)
    write_glb(args.out, character, np.zeros((1, character.n_shapes), np.float32), 30.0, name="rest")
    print(f"wrote {args.out}: {character.n_vertices} vertices, {character.n_shapes} ARKit shapes "
          f"({', '.join(character.shape_names)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
