"""Measure how ARKit blendshape weights become our 16 viseme weights; write `visemeflow/shapes/data/arkit_to_visemes.csv`.

Run from the repository root:  .venv/bin/python examples/build_arkit_to_visemes.py [--ict DIR] [--out CSV] [--check]

The ICT Face Model (`../shared/data/ict_facekit`, MIT) carries ARKit-style shapes, and the shipped demo rig
(`visemeflow/rig/data/ict_visemes.npz`) holds our 16 visemes on the same mesh. Captured ARKit weights a (52) become
viseme weights x (16) by the non-negative least-squares fit (`visemeflow.shapes.capture`):

    minimise ||D_vis x - D_arkit a||^2 over x >= 0  (x <= 1 where the plain fit goes past 1)

over **all** the demo rig's vertices (21,984: face, mouth socket, gums and tongue, teeth, eyeballs; the rig is
already cropped to what a face camera sees, and teeth and gums tell the jaw from the lips), with D_vis the (3V, 16)
viseme offsets and D_arkit the (3V, 52) ARKit offsets (zero columns for the 20 ARKit names ICT lacks: eyes, brows,
tongue, `cheekSquint`... see `arkit_basis`). Only inner products are needed at run time: the Gram matrix
M = D^T D of D = [D_vis | D_arkit] (48 x 48, centimetres squared), which holds G = D_vis^T D_vis (16 x 16),
B = D_vis^T D_arkit and C = D_arkit^T D_arkit (for the residual ||D_vis x - D_arkit a||^2 = x'Gx - 2x'Ba + a'Ca).
The CSV stores M at full float64 precision (Python's shortest round-trip text), one row per shape.

`--check` computes M again and fails (exit 1) when the shipped table differs by more than 1e-9 of its largest entry.
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

from visemeflow.shapes.capture import (  # noqa: E402
    CHECK_TOLERANCE,
    ArkitToVisemes,
    fit_visemes,
    gram_table_text,
    load_arkit_to_visemes,
)
from visemeflow.shapes.conventions import arkit_weights  # noqa: E402
from visemeflow.rig import load_demo_rig  # noqa: E402
from visemeflow.visemes import VISEMES  # noqa: E402

DEFAULT_OUT = REPO / "visemeflow" / "shapes" / "data" / "arkit_to_visemes.csv"


def measure(ict: Path) -> ArkitToVisemes:
    """The Gram matrix of the demo rig's 16 viseme offsets and ICT's ARKit offsets, on all the rig's vertices."""
    rig = load_demo_rig()
    names, basis = arkit_basis(ict)
    if basis.shape[1] != rig.deltas[0].size:
        raise SystemExit(f"the ICT shapes have {basis.shape[1] // 3} vertices after cropping, the demo rig "
                         f"{rig.n_vertices}: rebuild the demo rig first (examples/build_demo_rig.py)")
    d = np.concatenate([rig.deltas.reshape(len(VISEMES), -1).astype(np.float64),
                        basis.astype(np.float64)]).T  # (3V, 16 + n)
    gram = d.T @ d
    gram = 0.5 * (gram + gram.T)
    return ArkitToVisemes.from_gram(tuple(VISEMES) + tuple(names), gram, n_vertices=rig.n_vertices)


def describe(table: ArkitToVisemes) -> list[str]:
    """What the fit can and cannot tell apart, for the CSV's comment lines and the console."""
    eig = np.linalg.eigvalsh(table.gram)
    lines = [f"G = D_vis^T D_vis: eigenvalues {eig[0]:.3g} .. {eig[-1]:.3g} (condition {eig[-1] / eig[0]:.3g}); "
             f"{int((eig < 1e-6 * eig[-1]).sum())} of 16 directions are below 1e-6 of the largest"]
    single = np.eye(len(VISEMES)) * 0.8
    fit = fit_visemes(arkit_weights(single), table)
    for i, viseme in enumerate(VISEMES):
        row = fit.curves[i]
        if abs(float(row[i]) - 0.8) > 0.02 or np.delete(row, i).max() > 0.02:
            top = np.argsort(-row)[:3]
            lines.append(f"  {viseme} 0.8 through the ARKit table comes back as "
                         + " + ".join(f"{VISEMES[j]} {row[j]:.2f}" for j in top if row[j] > 0.005)
                         + f" (residual {fit.residual[i]:.1e})")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ict", type=Path, default=DEFAULT_ICT)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--check", action="store_true", help="fail if the shipped table differs from a new measure")
    args = parser.parse_args(argv)
    fresh = measure(args.ict)
    notes = describe(fresh)
    print("\n".join(notes))
    if args.check:
        shipped = load_arkit_to_visemes(args.out)
        if shipped.names != fresh.names:
            print(f"{args.out}: shapes {shipped.names} differ from a new measure's {fresh.names}", file=sys.stderr)
            return 1
        worst = float(np.abs(shipped.matrix - fresh.matrix).max())
        scale = float(np.abs(fresh.matrix).max())
        if worst > CHECK_TOLERANCE * scale:
            print(f"{args.out}: differs from a new measure by {worst:.3g} (largest entry {scale:.3g}); "
                  "rerun without --check", file=sys.stderr)
            return 1
        print(f"shipped table matches a new measure (largest difference {worst:.3g} of {scale:.3g})")
        return 0
    args.out.write_text(gram_table_text(fresh, notes), encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
