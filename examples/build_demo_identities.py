"""Rebuild `visemeflow/rig/data/ict_identities.npz` (package data): the first 20 ICT Face Model identity modes, cropped
like the demo rig.

Run from the repository root:  .venv/bin/python examples/build_demo_identities.py [--ict DIR] [--out NPZ]

Input: `../shared/data/ict_facekit` (ICT-FaceKit, MIT): `generic_neutral_mesh.obj.gz` and
`identities/identity000..019.obj.gz`. Each identity file is a full mesh, the neutral plus one standard deviation of
one PCA mode, so mode_k = identity_k - neutral and a face is neutral + sum_k c_k mode_k with c_k ~ N(0, 1).
The modes are cropped to the demo rig's vertices (the same ICT ranges, in the same order, as
`examples/build_demo_rig.py`), so they add directly to `visemeflow/rig/data/ict_visemes.npz`'s neutral.
"""

from __future__ import annotations

import argparse
import sys
import zipfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "examples"))

# the crop of the demo rig: one definition for both files
from build_demo_rig import PARTS

from visemeflow.rig import read_obj

DEFAULT_ICT = REPO.parent / "shared" / "data" / "ict_facekit"
DEFAULT_OUT = REPO / "visemeflow" / "rig" / "data" / "ict_identities.npz"  # package data, shipped in the wheel
N_MODES = 20
FORMAT = "visemeflow-identity-modes/1"


def kept_vertex_ids() -> np.ndarray:
    """(V,) ICT vertex ids of the demo rig's vertices, in the rig's order."""
    return np.concatenate([np.arange(start, end) for start, end in PARTS.values()])


def build_identity_modes(ict: Path, n_modes: int = N_MODES) -> tuple[list[str], np.ndarray]:
    """Mode names (`identity000`, ...) and (K, V, 3) float64 modes (identity_k - neutral) on the demo rig's vertices."""
    neutral = read_obj(ict / "generic_neutral_mesh.obj.gz").vertices
    kept = kept_vertex_ids()
    names, modes = [], []
    for k in range(n_modes):
        name = f"identity{k:03d}"
        mesh = read_obj(ict / "identities" / f"{name}.obj.gz").vertices
        if mesh.shape != neutral.shape:
            raise SystemExit(f"{name}: {len(mesh)} vertices, the neutral has {len(neutral)}")
        names.append(name)
        modes.append((mesh - neutral)[kept])
    return names, np.stack(modes)


def write_identity_npz(names: list[str], modes: np.ndarray, path: Path) -> Path:
    """np.savez_compressed's layout with fixed entry timestamps, so the same inputs always give the same bytes."""
    arrays = {
        "format": np.array(FORMAT),
        "names": np.array(names),
        "modes": modes.astype(np.float16),
        "ict_vertex_ids": kept_vertex_ids().astype(np.int32),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for key, array in arrays.items():
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            with archive.open(info, "w", force_zip64=True) as handle:
                np.lib.format.write_array(handle, np.asanyarray(array), allow_pickle=False)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ict", type=Path, default=DEFAULT_ICT, help="ICT-FaceKit copy (default ../shared/data/ict_facekit)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="identity npz to write")
    args = parser.parse_args(argv)
    names, modes = build_identity_modes(args.ict)
    write_identity_npz(names, modes, args.out)
    error = np.abs(modes.astype(np.float16).astype(np.float64) - modes).max()
    print(f"{args.out}: {len(names)} modes x {modes.shape[1]} vertices, float16 (max error {error:.5f}), "
          f"{args.out.stat().st_size / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
