"""Benchmark: Prefect orchestration overhead of the `pipeline` flow, and tracking on a 2-worker Dask cluster.

Run:  .venv/bin/python bench/orchestration.py [--workers 2] [--keep DIR]

It prints one table (metric, value, target, met?) and asserts nothing. The rendered demo corpus
`visemeflow-out/demo-corpus` is used (rendered first with `visemeflow synth examples/corpus` when missing:
25 utterances with video). A local Prefect server is started first (`visemeflow.ops.serve.ensure_server`,
database in the work folder) unless PREFECT_API_URL names one; its start-up is not timed.

(a) Overhead. `pipeline_flow` runs cold (a new store: ingest, procedural, tracking of the 25 videos, Prefect's
    default thread pool). Its wall time (the call, in this process) is compared with its tasks' run time as the
    API recorded it (`total_run_time`: time in the Running state) over the task runs of the pipeline and its
    three subflow runs. Two readings of "the tasks' compute time":
      busy time   the union of the task runs' [start, end] intervals: the time at least one task ran.
                  Overhead ratio = wall / busy, the target's ratio: tasks run concurrently in the thread
                  pool, so this is the part of the wall time in which Prefect, not our code, was working.
      sum         the sum of the task run times; with concurrent tasks it exceeds what the cores did (a task
                  waiting for a core still counts as running), so wall / sum is shown but not judged.
(b) Scale-out. The store of (a) is copied without its tracking outputs, and `track_flow` tracks the 25 videos
    into each copy, one after the other in this process:
      sequential         one utterance at a time on one core: `--runner threads --threads 1`, torch and
                         OpenCV set to one thread, as in each Dask worker;
      dask               `--runner dask`: a local cluster of `--workers` processes with one thread each,
                         started inside the flow call and timed with it (as a user gets it), the workers
                         reporting to the same server;
      dask-running       `--dask-address`: a local cluster of as many workers started (and its workers'
                         imports done) before the flow call, outside the timing: a cluster that stays up;
      threads            `--runner threads`, the default: Prefect's thread pool in this process, one task per
                         CPU, torch and OpenCV with their default thread counts;
      threads-unbounded  Prefect's own default thread pool, which starts every utterance at once (what the
                         flows used before they bounded it), once.
    The runs are interleaved (sequential, dask, dask-running, threads, threads-unbounded, then `--repeat` - 1
    more rounds without the last), each into a fresh copy; the fastest run of each counts, since on a shared
    machine another process can slow any one run. Speed-up = sequential wall / dask wall (target >= 1.7 with 2
    workers on 2 cores): what the workers add to one core. The tracked curves of every copy are compared (they
    must be equal).

The machine may be shared: the load average before and after is printed.
"""

from __future__ import annotations

import argparse
import importlib
import os
import shutil
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from report import met, print_table  # bench/report.py, beside this script

REPO = Path(__file__).resolve().parents[1]
DEMO_CORPUS = REPO / "visemeflow-out" / "demo-corpus"
TARGET_OVERHEAD = 1.5
TARGET_SPEEDUP = 1.7


@dataclass
class PipelineRun:
    wall_s: float
    busy_s: float
    sum_s: float
    tasks: int
    cached: int
    summary: dict


@dataclass
class TrackRun:
    name: str
    wall_s: float
    frames: int
    tracked: int
    store: Path
    task_s: float = 0.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def work_folder(keep: Path | None, prefix: str) -> Path:
    """The bench's folder (`keep`, else a new temporary one), with a throw-away Prefect home there and no analytics,
    set before Prefect is imported."""
    work = keep or Path(tempfile.mkdtemp(prefix=prefix))
    work.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("PREFECT_HOME", str(work / "prefect-home"))
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    return work


def ensure_demo_corpus(work: Path) -> Path:
    if not DEMO_CORPUS.exists():
        print(f"rendering the demo corpus into {DEMO_CORPUS} (once)...", flush=True)
        subprocess.run([str(REPO / ".venv" / "bin" / "visemeflow"), "synth", str(REPO / "examples" / "corpus"),
                        "--out", str(DEMO_CORPUS), "--store", str(work / "synth-store")], check=True, cwd=REPO)
    return DEMO_CORPUS


def union_seconds(intervals: list[tuple[datetime, datetime]]) -> float:
    total, end = 0.0, None
    for a, b in sorted(intervals):
        if end is None or a > end:
            total += (b - a).total_seconds()
            end = b
        elif b > end:
            total += (b - end).total_seconds()
            end = b
    return total


def task_seconds_between(start: datetime, end: datetime) -> float:
    """Sum of the run times of the task runs that started in [start, end]."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import TaskRunFilter, TaskRunFilterStartTime

    with get_client(sync_client=True) as client:
        total, offset = 0.0, 0
        while True:
            page = client.read_task_runs(task_run_filter=TaskRunFilter(
                start_time=TaskRunFilterStartTime(after_=start, before_=end)), limit=200, offset=offset)
            total += sum(r.total_run_time.total_seconds() for r in page)
            if len(page) < 200:
                return total
            offset += 200


def task_runs_of(flow_run_id) -> list:
    """Task runs of a flow run and of its subflow runs, without the task runs that stand for subflows."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import (
        FlowRunFilter,
        FlowRunFilterParentFlowRunId,
        TaskRunFilter,
        TaskRunFilterFlowRunId,
        TaskRunFilterSubFlowRuns,
    )

    with get_client(sync_client=True) as client:
        children = client.read_flow_runs(flow_run_filter=FlowRunFilter(
            parent_flow_run_id=FlowRunFilterParentFlowRunId(any_=[flow_run_id])))
        ids = [flow_run_id, *(c.id for c in children)]
        runs, offset = [], 0
        while True:
            page = client.read_task_runs(task_run_filter=TaskRunFilter(
                flow_run_id=TaskRunFilterFlowRunId(any_=ids), subflow_runs=TaskRunFilterSubFlowRuns(exists_=False),
            ), limit=200, offset=offset)
            runs += page
            if len(page) < 200:
                return runs
            offset += 200


def bench_pipeline(corpus: Path, store: Path) -> PipelineRun:
    from visemeflow.flows.params import PipelineParams
    from visemeflow.flows.pipeline import pipeline_flow

    started = time.perf_counter()
    state = pipeline_flow(PipelineParams(corpus=corpus, store=store), return_state=True)
    wall = time.perf_counter() - started
    summary = state.result()
    runs = task_runs_of(state.state_details.flow_run_id)
    intervals = [(r.start_time, r.end_time) for r in runs if r.start_time and r.end_time]
    return PipelineRun(
        wall_s=wall, busy_s=union_seconds(intervals), sum_s=sum(r.total_run_time.total_seconds() for r in runs),
        tasks=len(runs), cached=sum(1 for r in runs if r.state_name == "Cached"), summary=summary,
    )


def untracked_copy(store: Path, to: Path) -> Path:
    """The store without anything the track stage wrote, nor Prefect's cache records."""

    def ignore(folder: str, names: list[str]) -> set[str]:
        here = Path(folder)
        skip = {".prefect-results", "tracking_frames"} if here == store else set()
        if here == store / "curves":
            skip.add("tracked")
        if here == store / "configs":
            skip.add("track.json")
        if here == store / "tables" / "rejects":
            skip.add("track")
        return skip & set(names)

    shutil.copytree(store, to, ignore=ignore)
    return to


@contextmanager
def one_thread() -> Iterator[None]:
    """torch and OpenCV on one thread in this process, as in a Dask worker; restored after."""
    import cv2
    import torch

    threads, cv_threads = torch.get_num_threads(), cv2.getNumThreads()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
        cv2.setNumThreads(cv_threads)


def wait_for_quiet(max_load: float | None, limit_s: float = 900.0) -> None:
    """On a shared machine: wait (at most `limit_s`) until the 1-minute load average is below `max_load`."""
    deadline = time.monotonic() + limit_s
    while max_load is not None and os.getloadavg()[0] >= max_load and time.monotonic() < deadline:
        time.sleep(10)


def bench_tracking(store: Path, work: Path, workers: int, repeat: int, max_load: float | None) -> list[TrackRun]:
    order = ("sequential", "dask", "dask-running", "threads", "threads-unbounded",
             *(("sequential", "dask", "dask-running", "threads") * (repeat - 1)))
    return [track_once(name, work / f"track-{i}-{name}", store, workers, max_load) for i, name in enumerate(order)]


@contextmanager
def running_cluster(workers: int) -> Iterator[str]:
    """A local Dask cluster, started and its workers warmed (tracking code imported) before the timing starts."""
    from distributed import Client

    from visemeflow.flows.runners import local_cluster

    with local_cluster(n_workers=workers, threads_per_worker=1, processes=True) as cluster, Client(cluster) as client:
        client.run(importlib.import_module, "visemeflow.tasks.track")
        yield cluster.scheduler_address


def track_once(name: str, into: Path, store: Path, workers: int, max_load: float | None) -> TrackRun:
    """Track the videos of `store` into a copy at `into` with the runner `name`; timed from the flow call."""
    from prefect.task_runners import ThreadPoolTaskRunner

    from visemeflow.flows.params import RunnerConfig, TrackParams
    from visemeflow.flows.track import track_flow
    from visemeflow.flows.runners import run_on_runner

    copy = untracked_copy(store, into)
    with ExitStack() as stack:
        address = stack.enter_context(running_cluster(workers)) if name == "dask-running" else None
        wait_for_quiet(max_load)
        print(f"tracking ({name}), load average {os.getloadavg()[0]:.2f}...", flush=True)
        started, since = time.perf_counter(), datetime.now(UTC)
        if name == "sequential":
            with one_thread():
                report = run_on_runner(track_flow, TrackParams(store=copy, runner=RunnerConfig(threads=1)))
        elif name == "threads":
            report = run_on_runner(track_flow, TrackParams(store=copy))
        elif name == "threads-unbounded":
            report = track_flow.with_options(task_runner=ThreadPoolTaskRunner())(TrackParams(store=copy))
        else:
            runner = RunnerConfig(kind="dask", dask_workers=workers, dask_address=address)
            report = run_on_runner(track_flow, TrackParams(store=copy, runner=runner))
        wall = time.perf_counter() - started
    task_s = task_seconds_between(since, datetime.now(UTC))
    return TrackRun(name, wall, report["frames"], report["tracked"], copy, task_s)


def tracked_stores_equal(runs: list[TrackRun]) -> bool:
    import numpy as np

    from visemeflow.schemas import curves_array
    from visemeflow.storage import Store

    def curves(store: Path) -> dict[str, np.ndarray]:
        s = Store(store)
        import pyarrow.parquet as pq

        return {os.path.relpath(p, s.root): curves_array(pq.read_table(p)) for p in s.curve_files("tracked")}

    first = curves(runs[0].store)
    return all(
        (other := curves(r.store)).keys() == first.keys() and all(np.array_equal(other[k], v) for k, v in first.items())
        for r in runs[1:]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=2, help="Workers of the local Dask cluster.")
    parser.add_argument("--repeat", type=int, default=2,
                        help="Runs of sequential and dask tracking, interleaved; the fastest of each is compared.")
    parser.add_argument("--max-load", type=float,
                        help="Before each tracking run, wait (up to 15 min) for the 1-minute load average to fall "
                             "below this (a shared machine); default: do not wait.")
    parser.add_argument("--keep", type=Path, help="Folder for the stores (kept); default: a temporary folder.")
    args = parser.parse_args()
    work = work_folder(args.keep, "visemeflow-bench-orchestration-")
    from visemeflow.ops.serve import ensure_server

    corpus = ensure_demo_corpus(work)
    load_before = os.getloadavg()
    try:
        with ensure_server(work / "prefect-server", free_port()) as api:
            print(f"Prefect API {api.url}; pipeline (cold)...", flush=True)
            pipeline = bench_pipeline(corpus, work / "store")
            tracking = bench_tracking(work / "store", work, args.workers, max(1, args.repeat), args.max_load)
        equal = tracked_stores_equal(tracking)
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    load_after = os.getloadavg()

    by_name = {r.name: min((t for t in tracking if t.name == r.name), key=lambda t: t.wall_s) for r in tracking}
    overhead = pipeline.wall_s / pipeline.busy_s
    speedup = by_name["sequential"].wall_s / by_name["dask"].wall_s
    track = pipeline.summary.get("track", {})
    rows = [
        ((f"## (a) pipeline_flow, cold, on the demo corpus ({pipeline.summary['ingest'].get('utterances', '?')} "
          f"utterances, {track.get('tracked', 0)} videos tracked, {track.get('frames', 0)} frames)"), "", "", ""),
        ("wall time of the flow call", f"{pipeline.wall_s:.1f} s", "", ""),
        (f"task runs ({pipeline.tasks}, {pipeline.cached} cached): busy time (union)", f"{pipeline.busy_s:.1f} s", "", ""),
        ("task runs: sum of run times", f"{pipeline.sum_s:.1f} s", "", ""),
        ("overhead ratio = wall / busy time", f"{overhead:.2f}x", f"<= {TARGET_OVERHEAD}x",
         met(overhead <= TARGET_OVERHEAD)),
        ("wall / sum of run times", f"{pipeline.wall_s / pipeline.sum_s:.2f}x", "", ""),
        (f"## (b) track_flow on the {by_name['dask'].tracked} videos ({by_name['dask'].frames} frames), side by side",
         "", "", ""),
        *[(f"run {i + 1}: {r.name} wall time", (f"{r.wall_s:.1f} s ({r.frames / r.wall_s:.0f} frames/s; "
           f"task run time {r.task_s:.0f} s)"), "", "") for i, r in enumerate(tracking)],
        (f"dask (fastest run): task run time / ({args.workers} workers x wall)",
         f"{by_name['dask'].task_s / (args.workers * by_name['dask'].wall_s):.2f}", "", ""),
        (f"speed-up, dask ({args.workers} workers x 1 thread, local cluster started by the flow) vs sequential",
         f"{speedup:.2f}x", f">= {TARGET_SPEEDUP}x", met(speedup >= TARGET_SPEEDUP)),
        ("speed-up, dask on a running cluster (started and warmed before) vs sequential",
         f"{by_name['sequential'].wall_s / by_name['dask-running'].wall_s:.2f}x", "", ""),
        ("speed-up, threads (default, one task per CPU) vs sequential",
         f"{by_name['sequential'].wall_s / by_name['threads'].wall_s:.2f}x", "", ""),
        ("speed-up, threads (default) vs Prefect's unbounded thread pool",
         f"{by_name['threads-unbounded'].wall_s / by_name['threads'].wall_s:.2f}x", "", ""),
        ("tracked curves equal in every store", "yes" if equal else "NO", "yes", met(equal)),
    ]
    notes = [
        f"cores: {os.cpu_count()}; load average (1 min) before {load_before[0]:.2f}, after {load_after[0]:.2f}",
        "dask: the wall time includes starting the local cluster and each worker's first import of torch/OpenCV;",
        "dask-running: a cluster started before the flow call (as with --dask-address), not timed; speed-ups compare",
        "the fastest run of each",
    ]
    print_table(rows, notes)


if __name__ == "__main__":
    main()
