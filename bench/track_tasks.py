"""Benchmark: what Prefect costs the track stage per utterance, one task each against joint groups (issue 29,
item 3: "one track task per video means 24,000 task runs at paper scale").

Run:  .venv/bin/python bench/track_tasks.py [--utterances 200] [--repeats 2]

A corpus of N copies of one GRID clip (video, alignment, landmarks) is ingested and given procedural curves once,
then copied into two stores. The tracking itself is replaced by a stub that stores zero curves (`track_one` and
`track_many` of tasks/track.py), so what is timed is the stage around it: Prefect's task runs, cache keys and
records, the store's reads and writes. In each store, side by side:
  per task   `TrackParams(joint_frames=0)`: one `track[...]` task per utterance (each a cache hit on the rerun)
  grouped    the default `joint_frames` (400): `track-joint[...]` tasks of about 400 frames; on the rerun each
             utterance's record is read without a task run
Each is timed on a fresh store (every utterance tracked) and on a rerun with nothing changed (every utterance
cached), R times (the best kept), in one process on Prefect's temporary test server (or the server VISEMEFLOW_BENCH_API_URL names,
bench/prefect_api.py). Printed, never asserted.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
GRID = REPO.parent / "shared" / "data" / "grid_s1"
CLIP = "bbaf2n"


def corpus(root: Path, n: int) -> Path:
    speaker = root / "s1"
    speaker.mkdir(parents=True)
    for k in range(n):
        for src, ext in ((GRID / "video" / f"{CLIP}.mpg", ".mpg"), (GRID / "align" / f"{CLIP}.align", ".align"),
                         (GRID / "landmarks" / f"{CLIP}.mediapipe478.csv", ".mediapipe478.csv")):
            shutil.copyfile(src, speaker / f"c{k:05d}{ext}")
    return root


def stub_tracking() -> None:
    from visemeflow.schemas import C, Curves
    from visemeflow.tasks import track as track_task
    from visemeflow.visemes import N_VISEMES

    def track_one(store, utterance, procedural_variant, rig, config, on_step=None, identity=None):
        uid = utterance[C.UTTERANCE_ID]
        curves = np.zeros((int(utterance[C.N_FRAMES]), N_VISEMES), np.float32)
        store.save_curves(Curves(curves, utterance[C.FPS], uid, track_task.SOURCE, config.variant,
                                 track_task.tracked_provenance(utterance, config, identity)))
        return {"utterance_id": uid, "frames": int(utterance[C.N_FRAMES]), "seconds": 0.0, "mouth_error_px": 1.0,
                "variant": config.variant, "guided": True, "unguided_reason": None, "interpolated_frames": 0}

    def track_many(store, utterances, procedural_variant, rig, config, identities=None, on_step=None):
        return [track_one(store, u, procedural_variant, rig, config) for u in utterances]

    track_task.track_one, track_task.track_many = track_one, track_many


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--utterances", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    if not (GRID / "video").is_dir():
        print(f"missing benchmark data: {GRID}")
        return 0
    from prefect.logging import disable_run_logger
    from prefect_api import prefect_server

    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.params import IngestParams, ProceduralParams, TrackParams
    from visemeflow.flows.procedural import procedural_flow
    from visemeflow.flows.track import track_flow

    stub_tracking()
    modes = {"per task": 0, "grouped": TrackParams.model_fields["joint_frames"].default}
    with tempfile.TemporaryDirectory(prefix="visemeflow-track-tasks-") as tmp_name, prefect_server(), \
            disable_run_logger():
        tmp = Path(tmp_name)
        base = tmp / "base"
        started = time.perf_counter()
        ingest_flow(IngestParams(corpus=corpus(tmp / "corpus", args.utterances), store=base))
        procedural_flow(ProceduralParams(store=base))
        print(f"{args.utterances} utterances ingested with procedural curves in {time.perf_counter() - started:.0f} s "
              "(not timed below)", file=sys.stderr)
        best: dict[tuple[str, str], float] = {}
        tasks: dict[str, str] = {}
        for r in range(args.repeats):
            for mode, joint in modes.items():
                store = tmp / f"store-{mode.replace(' ', '-')}-{r}"
                shutil.copytree(base, store)
                for run in ("fresh", "rerun"):
                    started = time.perf_counter()
                    summary = track_flow(TrackParams(store=store, joint_frames=joint))
                    wall = time.perf_counter() - started
                    best[(mode, run)] = min(wall, best.get((mode, run), float("inf")))
                    assert summary["tracked" if run == "fresh" else "cached"] == args.utterances, summary
                if joint:
                    per_group = -(-joint // 75)          # joint_groups: a group closes once it reaches `joint`
                    groups = -(-args.utterances // per_group)
                    tasks[mode] = f"{groups} track-joint tasks; rerun: none"
                else:
                    tasks[mode] = f"{args.utterances} track tasks (rerun: {args.utterances} cache hits)"
        n = args.utterances
        print(f"\ntrack stage around a stub tracker, {n} utterances of 75 frames; best of {args.repeats}")
        print(f"  {'mode':<10}{'fresh s':>9}{'ms/utt':>8}{'rerun s':>9}{'ms/utt':>8}   tasks")
        for mode in modes:
            fresh, rerun = best[(mode, "fresh")], best[(mode, "rerun")]
            print(f"  {mode:<10}{fresh:9.2f}{1000 * fresh / n:8.1f}{rerun:9.2f}{1000 * rerun / n:8.1f}   {tasks[mode]}")
        p, g = best[("per task", "rerun")], best[("grouped", "rerun")]
        print(f"  cached rerun, per task / grouped: {p / g:.1f}x; fresh: "
              f"{best[('per task', 'fresh')] / best[('grouped', 'fresh')]:.1f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
