"""Benchmark: the `pipeline` flow and a training on a store in a local folder against the same on an S3 server,
with one worker and with a 2-worker Dask cluster, side by side in one run; and the projection to the paper's 16 hours.

Run:  .venv/bin/python bench/s3_store.py [--workers 2] [--epochs 5] [--keep DIR]

It prints one table and asserts nothing. The rendered demo corpus `visemeflow-out/demo-corpus` (25 utterances with
video) is used, rendered first when missing. A Prefect server (`ensure_server`) and a moto S3 server (`moto_server`,
a separate process on 127.0.0.1) are started first, not timed. Each run is a cold `pipeline_flow` call (ingest,
procedural, tracking) into a new store:
  sequential   `--runner threads --threads 1`, torch and OpenCV on one thread (what one Dask worker does);
  dask         `--runner dask`: a local cluster of `--workers` one-thread processes started by the flow (timed),
               each worker reaching the S3 store only through the endpoint in its environment.
Then a second, cached call on each store (every task a cache hit read from the store's result records). A fifth
run puts the corpus on S3 too (`s3://bench/corpus`, uploaded untimed, this machine's local copies cleared): the
flow mirrors it and each task fetches its utterance's files (`visemeflow.location`), inside the timed run.
Ratios: S3 wall / folder wall for the same runner (what object storage costs), and sequential / dask for the same
store (the speed-up the workers give). The S3 and folder stores' tracked curves are compared.

Then training on each sequential run's tracked curves (`train_flow`, fbank-blstm, d = 64, `--epochs` epochs, one
thread), on the folder and on S3, timed side by side: on S3 the checkpoint is uploaded after every epoch and the
model at the end; the two models' weights are compared.

The projection: the paper's 16 h of 25-fps video is 1.44 M frames; hours = frames / (frames/s of the dask run on
S3) / machines, for 1, 4 and 16 machines of this kind, each running `--workers` workers against one S3 store,
assuming the store is not the bottleneck (one S3 request per file; S3 serves thousands per second per prefix).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from orchestration import ensure_demo_corpus, free_port, one_thread, work_folder  # bench/orchestration.py, beside this script
from report import print_table  # bench/report.py, beside this script

PAPER_FRAMES = 16 * 3600 * 25


@dataclass
class Run:
    store_kind: str
    runner: str
    wall_s: float
    cached_wall_s: float
    frames: int
    tracked: int
    store: str


def start_s3(work: Path) -> tuple[subprocess.Popen, dict[str, str]]:
    """moto's S3 server in its own process on a free port; the environment that reaches it; a bucket made."""
    port = free_port()
    log = open(work / "moto.log", "w")  # noqa: SIM115 (closed with the process)
    server = subprocess.Popen([str(Path(sys.executable).with_name("moto_server")), "-H", "127.0.0.1", "-p", str(port)],
                              stdout=log, stderr=subprocess.STDOUT)
    env = {"AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}", "AWS_ACCESS_KEY_ID": "bench",
           "AWS_SECRET_ACCESS_KEY": "bench", "AWS_DEFAULT_REGION": "us-east-1"}
    os.environ.update(env)
    import s3fs

    deadline = time.monotonic() + 60
    while True:
        try:
            s3fs.S3FileSystem(skip_instance_cache=True).mkdir("bench")
            break
        except Exception:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)
    return server, env


def run_pipeline(kind: str, runner: str, corpus: Path | str, store: str, workers: int) -> Run:
    from visemeflow.flows.params import PipelineParams, RunnerConfig
    from visemeflow.flows.pipeline import pipeline_flow

    config = RunnerConfig(threads=1) if runner == "sequential" else RunnerConfig(kind="dask", dask_workers=workers)
    params = PipelineParams(corpus=corpus, store=store, runner=config)
    print(f"pipeline ({kind}, {runner}), load average {os.getloadavg()[0]:.2f}...", flush=True)
    started = time.perf_counter()
    if runner == "sequential":
        with one_thread():
            result = pipeline_flow(params)
    else:
        result = pipeline_flow(params)
    wall = time.perf_counter() - started
    started = time.perf_counter()
    again = pipeline_flow(params)
    cached = time.perf_counter() - started
    assert again["track"]["tracked"] == 0, "the second call should be all cache hits"
    return Run(kind, runner, wall, cached, result["track"]["frames"], result["track"]["tracked"], store)


def run_training(kind: str, store: str, epochs: int) -> tuple[float, dict]:
    """Wall time of a cold `train_flow` on the store's tracked curves, and its report."""
    from visemeflow.flows.params import TrainParams
    from visemeflow.flows.train import train_flow
    from visemeflow.learning.train import TrainConfig

    params = TrainParams(store=store, config=TrainConfig(preset="fbank-blstm", epochs=epochs, d_model=64),
                         model_name="bench")
    print(f"train ({kind}), load average {os.getloadavg()[0]:.2f}...", flush=True)
    started = time.perf_counter()
    with one_thread():
        report = train_flow(params)
    return time.perf_counter() - started, report


def same_weights(a: str, b: str) -> bool:
    import torch

    from visemeflow.learning.train import load_model
    from visemeflow.storage import Store

    x, y = (load_model(Store(s).model_file("bench"))[0].state_dict() for s in (a, b))
    return x.keys() == y.keys() and all(torch.equal(x[k], y[k]) for k in x)


def same_tracked(a: str, b: str) -> float:
    """Largest difference between the tracked curves of two stores (inf when their files differ)."""
    import numpy as np

    from visemeflow.schemas import C, curves_array
    from visemeflow.storage import Store

    def table(store: str):
        return Store(store).scan_curves("tracked").sort_by([(C.UTTERANCE_ID, "ascending"), (C.FRAME, "ascending")])

    x, y = table(a), table(b)
    if x.column(C.UTTERANCE_ID) != y.column(C.UTTERANCE_ID) or x.num_rows == 0:
        return float("inf")
    return float(np.abs(curves_array(x) - curves_array(y)).max())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=2, help="Workers of the local Dask cluster.")
    parser.add_argument("--epochs", type=int, default=5, help="Epochs of the training timed on each store.")
    parser.add_argument("--keep", type=Path, help="Folder for the stores (kept); default: a temporary folder.")
    args = parser.parse_args()
    work = work_folder(args.keep, "visemeflow-bench-s3-")
    from visemeflow.ops.serve import ensure_server

    corpus = ensure_demo_corpus(work)
    s3, _ = start_s3(work)
    load_before = os.getloadavg()
    runs: list[Run] = []
    try:
        with ensure_server(work / "prefect-server", free_port()):
            for i, (kind, runner) in enumerate([("folder", "sequential"), ("S3", "sequential"),
                                                ("folder", "dask"), ("S3", "dask")]):
                store = str(work / f"store-{i}") if kind == "folder" else f"s3://bench/store-{i}"
                runs.append(run_pipeline(kind, runner, corpus, store, args.workers))
            # the corpus on S3 too: uploaded (not timed), then mirrored and fetched per task within the timed run;
            # this process's local copies cleared first, so the run pays every download
            import s3fs

            from visemeflow.location import private_folder

            s3fs.S3FileSystem(skip_instance_cache=True).put(str(corpus), "bench/corpus", recursive=True)
            for kind_ in ("objects", "mirrors"):
                shutil.rmtree(private_folder(kind_, "bench"), ignore_errors=True)
            runs.append(run_pipeline("S3 corpus + S3", "dask", "s3://bench/corpus", "s3://bench/store-4",
                                     args.workers))
            diff = same_tracked(runs[2].store, runs[3].store)
            diff_corpus = same_tracked(runs[3].store, runs[4].store)
            trained = [run_training(kind, runs[i].store, args.epochs) for i, kind in ((0, "folder"), (1, "S3"))]
            same = same_weights(runs[0].store, runs[1].store)
    finally:
        s3.terminate()
        s3.wait(30)
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    load_after = os.getloadavg()
    by = {(r.store_kind, r.runner): r for r in runs}
    best = by[("S3", "dask")]
    rate = best.frames / best.wall_s
    rows = [(f"## cold pipeline_flow on the demo corpus ({best.tracked} videos, {best.frames} frames)", "", "", "")]
    rows += [(f"{r.store_kind}, {r.runner}: wall time (cached rerun)",
              f"{r.wall_s:.1f} s ({r.frames / r.wall_s:.1f} frames/s; cached {r.cached_wall_s:.1f} s)", "", "")
             for r in runs]
    for runner in ("sequential", "dask"):
        rows.append((f"S3 / folder wall, {runner}",
                     f"{by[('S3', runner)].wall_s / by[('folder', runner)].wall_s:.2f}x "
                     f"(cached {by[('S3', runner)].cached_wall_s / by[('folder', runner)].cached_wall_s:.2f}x)",
                     "", ""))
    for kind in ("folder", "S3"):
        rows.append((f"speed-up, dask ({args.workers} workers) vs sequential, {kind}",
                     f"{by[(kind, 'sequential')].wall_s / by[(kind, 'dask')].wall_s:.2f}x", "", ""))
    rows.append(("tracked curves, S3 vs folder (dask): largest difference", f"{diff:.1e}", "<= 1e-5", ""))
    with_corpus = by[("S3 corpus + S3", "dask")]
    rows.append(("corpus on S3 too / corpus in a folder (S3 store, dask)",
                 f"{with_corpus.wall_s / best.wall_s:.2f}x (cached {with_corpus.cached_wall_s / best.cached_wall_s:.2f}x)",
                 "", ""))
    rows.append(("tracked curves, corpus on S3 vs in a folder: largest difference", f"{diff_corpus:.1e}", "<= 1e-5",
                 ""))
    (folder_s, report), (s3_s, _) = trained
    rows.append((f"## train_flow, fbank-blstm d=64, {args.epochs} epochs on {report['train']} + {report['val']} "
                 "utterances' tracked curves, one thread", "", "", ""))
    rows.append(("folder / S3 wall time", f"{folder_s:.1f} s / {s3_s:.1f} s ({s3_s / folder_s:.2f}x)", "", ""))
    rows.append(("the two models' weights", "identical" if same else "DIFFERENT", "identical", ""))
    rows.append(("## the paper's 16 h (1.44 M frames) at the S3 dask rate, end to end", "", "", ""))
    for machines in (1, 4, 16):
        rows.append((f"{machines} machine(s) x {args.workers} workers", f"{PAPER_FRAMES / rate / machines / 3600:.1f} h",
                     "", ""))
    notes = [f"cores: {os.cpu_count()}; load average (1 min) before {load_before[0]:.2f}, after {load_after[0]:.2f}",
             "S3: moto's server in its own process on 127.0.0.1 (no network latency; a real S3 adds 10-50 ms per "
             "request)", "the projection assumes machines scale linearly against one store (not measured here)"]
    print_table(rows, notes)


if __name__ == "__main__":
    main()
