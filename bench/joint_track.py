"""Benchmark: the track stage one clip at a time against several clips in one joint solve (issue 29, item 1).

Run:  .venv/bin/python bench/joint_track.py [--repeats R] [--joint 5,10] [--no-pin] [--config JSON] [--clips N] [--grid-only]
      [--reference]

Clips and set-up as bench/end_to_end.py (GRID s1's 10 guided clips, talking_heads 1 and 4 unguided; landmarks made
once by the landmarks stage's own function, not timed here). Timed, on one pinned core, side by side in one run:
  alone     `tracking.utterance.track_video` per clip (what the track stage ran per utterance until now)
  joint N   `tracking.utterance.track_videos` on groups of N clips of a set (one `solve_fast_many` per group)
The track stage's work only: frame times, landmark file, identity, optical flow, the solve. Per set: wall seconds,
frames/s per core, the solver's part (`solve_fast` / `solve_fast_many`), the speed-up against alone, and the largest
difference of the joint curves from the alone ones (the joint solve is the same objective: float rounding only).
  ref N     (`--reference`) joint N as it was before the written-out derivatives: the solver's Adam steps take
            their gradient from autograd through the loss terms, the identity fit its Jacobian from forward-mode AD
Each configuration runs R times (default 2), interleaved; the best run is kept. Printed, never asserted.
`--config '{"speaker_identity": true}'` tracks with one identity per speaker and image size, fitted once as the
track flow fits it (bench/end_to_end.py's `fit_identities`, best of R); its time is added to every path's wall.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import end_to_end as e2e  # noqa: E402  (pins the thread count before numpy and torch are imported)

import numpy as np  # noqa: E402

from visemeflow.rig import load_demo_rig  # noqa: E402
from visemeflow.schemas import C  # noqa: E402
from visemeflow.storage import Store  # noqa: E402
from visemeflow.tracking.facemesh import FaceMeshConfig  # noqa: E402
from visemeflow.tracking.solver import TrackingConfig  # noqa: E402
import visemeflow.tracking.utterance as utterance_mod  # noqa: E402

SOLVER = {"s": 0.0}


@contextlib.contextmanager
def autodiff():
    """The solver's gradient and the identity fit's Jacobian from autograd, as before they were written out."""
    import functools

    import torch

    import visemeflow.tracking.identity as identity_mod
    import visemeflow.tracking.solver as solver_mod

    adam, jacobian = solver_mod._adam_joined, identity_mod._Problem.jacobian

    def forward_mode(self, theta, identity=True):
        return torch.func.jacfwd(lambda th: self.residuals(th, identity))(theta)

    solver_mod._adam_joined = functools.partial(adam, gradient="autograd")
    identity_mod._Problem.jacobian = forward_mode
    try:
        yield
    finally:
        solver_mod._adam_joined, identity_mod._Problem.jacobian = adam, jacobian


def _timed(fn):
    def wrapper(*args, **kwargs):
        started = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            SOLVER["s"] += time.perf_counter() - started
    return wrapper


def video_of(clip, store: Store):
    u = clip.utterance
    return utterance_mod.VideoInput(u[C.VIDEO_PATH], str(store.landmark_path(clip.uid)), u[C.FPS],
                                    int(u[C.N_FRAMES]), audio_path=u.get(C.AUDIO_PATH),
                                    alignment_path=u.get(C.ALIGNMENT_PATH) or None,
                                    alignment_end_s=clip.alignment_end_s)


def run(clips, store, rig, config, joint: int | None, identities: dict | None = None
        ) -> tuple[float, float, list[np.ndarray]]:
    """(wall s, solver s, curves per clip) of the track stage's work on `clips` (`identities`: uid -> the
    speaker's identity)."""
    identities = identities or {}
    SOLVER["s"] = 0.0
    started = time.perf_counter()
    curves = []
    if joint is None:
        for clip in clips:
            curves.append(utterance_mod.track_video(video_of(clip, store), clip.procedural, rig, config,
                                                    identity=identities.get(clip.uid)).result.curves)
    else:
        for k in range(0, len(clips), joint):
            group = clips[k:k + joint]
            out = utterance_mod.track_videos([(video_of(c, store), c.procedural) for c in group], rig, config,
                                             [identities.get(c.uid) for c in group])
            for tracked in out:
                if isinstance(tracked, Exception):
                    raise tracked
                curves.append(tracked.result.curves)
    return time.perf_counter() - started, SOLVER["s"], curves


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--joint", default="5,10", help="group sizes to time against one clip at a time")
    parser.add_argument("--no-pin", action="store_true")
    parser.add_argument("--clips", type=int, default=None, help="only the first N GRID clips (default all 10)")
    parser.add_argument("--grid-only", action="store_true", help="leave out the talking heads")
    parser.add_argument("--config", default=None, metavar="JSON", help="TrackingConfig fields for every path")
    parser.add_argument("--reference", action="store_true",
                        help="also the largest group with autograd's gradient and Jacobian (see the doc)")
    args = parser.parse_args()
    if not (e2e.GRID / "video").is_dir():
        print(f"missing benchmark data: {e2e.GRID}")
        return 0
    print("joint-track bench:", "not pinned" if args.no_pin else e2e.pin_one_core())
    sizes = [int(s) for s in args.joint.split(",") if s]
    config, mesh, rig = TrackingConfig(), FaceMeshConfig(), load_demo_rig()
    if args.config:
        import json

        config = config.model_copy(update=json.loads(args.config))
        print("TrackingConfig:", json.loads(args.config))
    utterance_mod.solve_fast = _timed(utterance_mod.solve_fast)
    utterance_mod.solve_fast_many = _timed(utterance_mod.solve_fast_many)
    with tempfile.TemporaryDirectory(prefix="visemeflow-joint-") as tmp_name:
        tmp = Path(tmp_name)
        clips = e2e.build_corpus(tmp, args.clips)
        if args.grid_only:
            clips = [c for c in clips if c.set_name.startswith("GRID")]
        store = Store(tmp / "store")
        for clip in clips:
            e2e.landmarks_task.landmarks_one(store, clip.utterance, mesh)
        identities, shares = e2e.fit_identities(clips, store, rig, config, mesh, args.repeats)
        sets: dict[str, list] = {}
        for clip in clips:
            sets.setdefault(clip.set_name, []).append(clip)
        paths: list = [None, *sizes] + ([("ref", max(sizes))] if args.reference else [])
        for name, members in sets.items():
            run(members[:1], store, rig, config, None, identities)     # warm-up
            fitting = sum(shares.get(c.uid, (0.0, 0.0))[0] for c in members)
            best: dict = {}
            for _ in range(args.repeats):
                for joint in paths:
                    if isinstance(joint, tuple):
                        with autodiff():
                            wall, solver, curves = run(members, store, rig, config, joint[1], identities)
                    else:
                        wall, solver, curves = run(members, store, rig, config, joint, identities)
                    wall += fitting
                    if joint not in best or wall < best[joint][0]:
                        best[joint] = (wall, solver, curves)
            frames = sum(c.frames for c in members)
            alone = best[None]
            print(f"\n{name}: {len(members)} clips, {frames} frames; best of {args.repeats}")
            print(f"  {'path':<10}{'wall s':>8}{'frames/s':>10}{'solver s':>10}{'solver f/s':>12}{'speed-up':>10}"
                  f"{'solver x':>10}{'max |curve diff|':>18}")
            for joint in paths:
                wall, solver, curves = best[joint]
                diff = max(float(np.abs(a - b).max()) for a, b in zip(curves, alone[2]))
                label = ("alone" if joint is None else f"ref {joint[1]}" if isinstance(joint, tuple)
                         else f"joint {joint}")
                print(f"  {label:<10}{wall:8.2f}{frames / wall:10.1f}{solver:10.2f}{frames / solver:12.0f}"
                      f"{alone[0] / wall:10.2f}{alone[1] / solver:10.2f}{diff:18.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
