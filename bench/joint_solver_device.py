"""Benchmark: the joint fast solver (`solve_fast_many`) on the CPU and on a CUDA GPU, many clips at once (issue 29,
item 1: "a GPU path that tracks many clips at once").

Run:  .venv/bin/python bench/joint_solver_device.py [--clips 1,10,100,400] [--cpu-clips 1,10] [--frames 75]

Problems: `--clips` synthetic takes of `--frames` frames at 25 fps (`synth.take.make_take`: the demo rig, a moving
head, detector-like landmark noise and misses; each take its own seed and phone sequence), with the procedural
curves of their phones as guidance and an L_flow term on 300 face vertices whose correspondences are made up
(seeded noise): the solver's work, not the optical flow's, is what is timed. Beyond 100 clips the 100 takes
repeat (as separate problems). The default TrackingConfig (50 pose +
200 joint Adam steps). Per number of clips and device: wall seconds of the solve, frames/s, and the largest curve
difference between the devices where both ran. The CPU runs on one thread (frames/s per core); the GPU one is
timed after a warm-up solve. Printed, never asserted; without CUDA only the CPU rows are printed.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from visemeflow.phonetics.types import VisemeSegment  # noqa: E402
from visemeflow.procedural import generate_procedural_curves  # noqa: E402
from visemeflow.render.camera import Intrinsics  # noqa: E402
from visemeflow.rig import load_demo_rig  # noqa: E402
from visemeflow.synth.take import SynthConfig, make_take  # noqa: E402
from visemeflow.tracking.solver import FlowTerm, TrackingConfig, TrackingProblem, flow_vertices, solve_fast_many  # noqa: E402
from visemeflow.visemes import VISEMES  # noqa: E402

FPS = 25.0


def problems(n: int, frames: int, distinct: int = 100) -> list[TrackingProblem]:
    """`n` problems: `distinct` different takes, repeated (as separate problems) beyond that."""
    rig = load_demo_rig()
    ids = flow_vertices(rig)
    out = []
    for k in range(min(n, distinct)):
        rng = np.random.default_rng(k)
        segments, t = [], 0.1
        while t < frames / FPS - 0.2:
            length = float(rng.uniform(0.06, 0.2))
            segments.append(VisemeSegment(VISEMES[int(rng.integers(len(VISEMES)))], t, t + length, 0))
            t += length
        take = make_take(rig, segments, frames, f"spk{k % 7}", f"spk/take{k}", SynthConfig())
        cam = take.camera
        problem = TrackingProblem(rig, Intrinsics(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height),
                                  take.landmarks.points, take.landmarks.valid,
                                  generate_procedural_curves(segments, frames, FPS))
        disp = rng.normal(0.0, 0.3, (frames, len(ids), 2))
        ok = rng.random((frames, len(ids))) > 0.2

        def correspond(j, points, disp=disp, ok=ok):
            return np.where(ok[j][:, None], disp[j], np.nan), ok[j]

        out.append(dataclasses.replace(problem, flow=FlowTerm(ids, correspond, correspond)))
    return [dataclasses.replace(out[k % len(out)]) for k in range(n)]


def timed(batch, config, device) -> tuple[float, list]:
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    started = time.perf_counter()
    results = solve_fast_many(batch, config, device=device)
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    return time.perf_counter() - started, results


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clips", default="1,10,100,400")
    parser.add_argument("--cpu-clips", default="1,10", help="clip counts also solved on the CPU (it is slow)")
    parser.add_argument("--frames", type=int, default=75)
    args = parser.parse_args()
    torch.set_num_threads(1)
    counts = [int(c) for c in args.clips.split(",")]
    cpu_counts = {int(c) for c in args.cpu_clips.split(",") if c}
    cuda = torch.cuda.is_available()
    print(f"torch {torch.__version__}; CUDA: {torch.cuda.get_device_name(0) if cuda else 'none'}; CPU threads 1")
    started = time.perf_counter()
    pool = problems(max(counts), args.frames)
    print(f"{len(pool)} synthetic takes of {args.frames} frames made in {time.perf_counter() - started:.0f} s")
    config = TrackingConfig()
    timed(pool[:1], config, "cpu")                            # warm-up: first-use costs
    if cuda:
        timed(pool[:2], config, "cuda")                       # warm-up: CUDA context, kernels
    print(f"\n{'clips':>6}{'frames':>8}{'cpu s':>9}{'cpu f/s':>9}{'cuda s':>9}{'cuda f/s':>10}{'cuda/cpu':>10}"
          f"{'max |curve diff|':>18}{'cuda MiB':>10}")
    for n in counts:
        batch = pool[:n]
        frames = n * args.frames
        cpu = gpu = None
        if n in cpu_counts or not cuda:
            cpu = timed(batch, config, "cpu")
        if cuda:
            torch.cuda.reset_peak_memory_stats()
            gpu = timed(batch, config, "cuda")
        diff = (max(float(np.abs(a.curves - b.curves).max()) for a, b in zip(cpu[1], gpu[1]))
                if cpu and gpu else None)
        row = f"{n:6d}{frames:8d}"
        row += f"{cpu[0]:9.2f}{frames / cpu[0]:9.0f}" if cpu else f"{'-':>9}{'-':>9}"
        row += f"{gpu[0]:9.2f}{frames / gpu[0]:10.0f}" if gpu else f"{'-':>9}{'-':>10}"
        row += f"{cpu[0] / gpu[0]:10.1f}" if cpu and gpu else f"{'-':>10}"
        row += f"{diff:18.2e}" if diff is not None else f"{'-':>18}"
        row += f"{torch.cuda.max_memory_allocated() / 2**20:10.0f}" if gpu else f"{'-':>10}"
        print(row, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
