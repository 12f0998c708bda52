"""Measure our 16 visemes as ARKit blendshape weights and write `visemeflow/shapes/data/arkit_visemes.csv`.

Run from the repository root:  .venv/bin/python examples/build_arkit_table.py [--ict DIR] [--out CSV] [--check]

The ICT Face Model (`../shared/data/ict_facekit`, MIT) carries ARKit-style shapes (`jawOpen`, `mouthStretch_L`, ...),
and the shipped demo rig (`visemeflow/rig/data/ict_visemes.npz`) holds our 16 visemes on the same mesh. For each
viseme, the ARKit weights are the best bounded least-squares fit of its vertex offsets by the ARKit shapes' offsets
on the demo rig's vertices: minimise ||A w - d||^2 with 0 <= w <= 1 (ARKit weights live in [0, 1]). ICT shape names
become ARKit names (`_L` -> `Left`, `_R` -> `Right`); ICT's `cheekPuff_L`/`_R` are one ARKit `cheekPuff` (their sum);
`cheekRaiser_L`/`_R` have no ARKit name and are left out. Weights below 1e-3 are dropped.

The residual per viseme (relative: ||A w - d|| / ||d||, and the largest vertex error in mm) is printed and written
as comment lines at the top of the CSV. `--check` solves again and fails if the shipped table differs.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import lsq_linear

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "examples"))

from build_demo_rig import PARTS, read_ict  # noqa: E402

from visemeflow.shapes.conventions import ARKIT_52, builtin_table, parse_table  # noqa: E402
from visemeflow.rig import load_demo_rig  # noqa: E402
from visemeflow.visemes import VISEMES  # noqa: E402

DEFAULT_ICT = REPO.parent / "shared" / "data" / "ict_facekit"
DEFAULT_OUT = REPO / "visemeflow" / "shapes" / "data" / "arkit_visemes.csv"
ICT_SHAPES_DIR = "shapes_mouth_jaw_cheek_nose"
MIN_WEIGHT = 1e-3


def arkit_name(ict_name: str) -> str | None:
    """ICT shape name -> ARKit name, None when ARKit has no such shape."""
    name = ict_name.removesuffix("_L") + "Left" if ict_name.endswith("_L") else (
        ict_name.removesuffix("_R") + "Right" if ict_name.endswith("_R") else ict_name)
    if name in ("cheekPuffLeft", "cheekPuffRight"):
        return "cheekPuff"
    return name if name in ARKIT_52 else None


def arkit_basis(ict: Path) -> tuple[list[str], np.ndarray]:
    """ARKit names and their (n, 3V') offsets on the demo rig's vertices (the cropped ICT mesh)."""
    ict_names = sorted(p.name.removesuffix(".obj.gz") for p in (ict / ICT_SHAPES_DIR).glob("*.obj.gz"))
    _, _, deltas, _ = read_ict(ict, ict_names)
    kept = np.concatenate([np.arange(start, end) for start, end in PARTS.values()])
    basis: dict[str, np.ndarray] = {}
    for ict_name in ict_names:
        name = arkit_name(ict_name)
        if name is not None:
            basis[name] = basis.get(name, 0) + deltas[ict_name][kept]
    names = [n for n in ARKIT_52 if n in basis]
    return names, np.stack([basis[n].reshape(-1) for n in names])


def solve(ict: Path) -> tuple[dict[str, dict[str, float]], dict[str, tuple[float, float]]]:
    """{viseme: {arkit: weight}} and {viseme: (relative residual, largest vertex error in mm)}."""
    rig = load_demo_rig()
    names, basis = arkit_basis(ict)
    if basis.shape[1] != rig.deltas[0].size:
        raise SystemExit(f"the ICT shapes have {basis.shape[1] // 3} vertices after cropping, the demo rig "
                         f"{rig.n_vertices}: rebuild the demo rig first (examples/build_demo_rig.py)")
    a = basis.T.astype(np.float64)
    table, residuals = {}, {}
    for i, viseme in enumerate(VISEMES):
        d = rig.deltas[i].reshape(-1).astype(np.float64)
        fit = lsq_linear(a, d, bounds=(0.0, 1.0), lsmr_tol="auto", tol=1e-12, max_iter=5000)
        w = np.where(fit.x >= MIN_WEIGHT, fit.x, 0.0)
        err = (a @ w - d).reshape(-1, 3)
        residuals[viseme] = (float(np.linalg.norm(err) / np.linalg.norm(d)),
                             float(np.linalg.norm(err, axis=1).max() * 10.0))  # the ICT mesh is in cm
        table[viseme] = {n: round(float(x), 4) for n, x in zip(names, w) if x > 0}
    return table, residuals


def table_text(table: dict[str, dict[str, float]], residuals: dict[str, tuple[float, float]]) -> str:
    lines = ["# Our 16 visemes as ARKit blendshape weights, measured by examples/build_arkit_table.py: a bounded",
             "# least-squares fit (weights in [0, 1]) of each viseme's offsets on the ICT Face Model (MIT) by the",
             "# ICT model's ARKit-style shapes. Residual per viseme (||A w - d|| / ||d||; largest vertex error):"]
    lines += [f"#   {v}: {r:.2e} relative, {mm:.3f} mm" for v, (r, mm) in residuals.items()]
    lines.append("viseme,shape,weight")
    for viseme in VISEMES:
        lines += [f"{viseme},{shape},{weight:g}" for shape, weight in table[viseme].items()]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ict", type=Path, default=DEFAULT_ICT)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--check", action="store_true", help="fail if the shipped table differs from a new solve")
    args = parser.parse_args(argv)
    table, residuals = solve(args.ict)
    for viseme, (rel, mm) in residuals.items():
        print(f"{viseme:6s} residual {rel:.2e} relative, {mm:.3f} mm max  <- "
              + ", ".join(f"{s} {w:g}" for s, w in table[viseme].items()))
    if args.check:
        shipped = builtin_table("arkit52")
        fresh = parse_table(table_text(table, residuals), "fresh solve")
        if shipped != fresh:
            print(f"{args.out}: differs from a new solve; rerun without --check", file=sys.stderr)
            return 1
        print("shipped table matches a new solve")
        return 0
    args.out.write_text(table_text(table, residuals), encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
