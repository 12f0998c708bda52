"""Benchmark: the head pose's rotation matrices, Rodrigues in closed form (`render.camera.rotation_matrices`) against
kornia's `axis_angle_to_rotation_matrix` (which evaluates a Taylor branch and a full branch on every call), alone
and inside the fast tracking solver. Printed, never asserted.

Run: .venv/bin/python bench/rotation.py [--takes 6] [--repeats 2] [--calls 2000]

Rows, one thread, the two side by side in one process, alternating:
  matrices   forward + backward of (75, 3) axis-angles -> (75, 3, 3), milliseconds per call, and the largest
             difference of the matrices and of the gradient of a weighted sum;
  solver     `solve_fast` with the default TrackingConfig without flow on the first `--takes` synthetic takes of
             bench/tracking.py (the examples corpus rendered on the demo rig), frames/s of the best of `--repeats`,
             with `render.camera.rotation_matrices` set to each; and the largest difference of the curves.
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_name] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from kornia.geometry.conversions import axis_angle_to_rotation_matrix  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

import tracking as T  # noqa: E402

import visemeflow.render.camera as camera  # noqa: E402
from visemeflow.rig import load_demo_rig  # noqa: E402
from visemeflow.tracking.solver import TrackingConfig, solve_fast  # noqa: E402

CLOSED = camera.rotation_matrices


def per_call_ms(fn, r: torch.Tensor, calls: int) -> float:
    started = time.perf_counter()
    for _ in range(calls):
        fn(r).sum().backward()
    return (time.perf_counter() - started) / calls * 1e3


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--takes", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--calls", type=int, default=2000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    r = (torch.randn(75, 3, generator=torch.Generator().manual_seed(0)) * 0.3).requires_grad_(True)
    weights = torch.arange(9.0).reshape(3, 3)
    grads = [torch.autograd.grad((fn(r) * weights).sum(), r)[0] for fn in (axis_angle_to_rotation_matrix, CLOSED)]
    print(f"matrices: max |closed - kornia| {(CLOSED(r) - axis_angle_to_rotation_matrix(r)).abs().max():.2e}, "
          f"gradient {(grads[0] - grads[1]).abs().max():.2e}")
    times = {"kornia": [], "closed form": []}
    for _ in range(2):
        times["kornia"].append(per_call_ms(axis_angle_to_rotation_matrix, r, args.calls))
        times["closed form"].append(per_call_ms(CLOSED, r, args.calls))
    k, c = min(times["kornia"]), min(times["closed form"])
    print(f"matrices, forward + backward of (75, 3): kornia {k:.3f} ms, closed form {c:.3f} ms ({k / c:.2f}x)")

    rig = load_demo_rig()
    takes = T.load_utterances(rig, args.takes)
    T.warm_up(rig, takes[0])
    config = TrackingConfig(use_flow=False)
    rates: dict[str, list[float]] = {"kornia": [], "closed form": []}
    curves: dict[str, list[np.ndarray]] = {}
    try:
        for _ in range(args.repeats):
            for name, fn in (("kornia", axis_angle_to_rotation_matrix), ("closed form", CLOSED)):
                camera.rotation_matrices = fn
                started, frames, out = time.perf_counter(), 0, []
                for u in takes:
                    out.append(solve_fast(T.problem_of(rig, u), config).curves)
                    frames += u.n
                rates[name].append(frames / (time.perf_counter() - started))
                curves[name] = out
    finally:
        camera.rotation_matrices = CLOSED
    gap = max(float(np.abs(a - b).max()) for a, b in zip(curves["kornia"], curves["closed form"]))
    kb, cb = max(rates["kornia"]), max(rates["closed form"])
    print(f"solve_fast on {len(takes)} synthetic takes ({sum(u.n for u in takes)} frames), best of {args.repeats}: "
          f"kornia {kb:.1f} frames/s, closed form {cb:.1f} frames/s ({cb / kb:.2f}x); curves differ by at most "
          f"{gap:.1e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
