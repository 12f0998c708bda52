"""Scale-out with prefect-dask: tracking on a local 2-worker cluster equals the run on Prefect's thread pool."""

import os
import threading
import time

import numpy as np
import pyarrow.parquet as pq
import pytest
from factories import render_videos
from prefect import flow, task
from prefect.settings import PREFECT_API_URL, temporary_settings

from visemeflow.flows.params import PipelineParams, RunnerConfig
from visemeflow.flows.runners import (
    available_cpus,
    local_cluster,
    on_requested_runner,
    run_on_runner,
    shared_api,
    task_runner_for,
    thread_workers,
)
from visemeflow.schemas import C, curves_array
from visemeflow.storage import Store

pytestmark = [pytest.mark.flow, pytest.mark.usefixtures("prefect_harness")]

SHORT = [("LJ", "LJ001-0002"), ("LJ", "LJ001-0008"), ("LJ", "LJ001-0013"), ("SSB1624", "SSB16240001")]
DASK = RunnerConfig(kind="dask", dask_workers=2)


@pytest.fixture(scope="module")
def video_corpus(tmp_path_factory, prefect_harness):
    """Four short demo utterances rendered as talking-face videos (about 8 s of speech)."""
    return render_videos(tmp_path_factory.mktemp("dask"), SHORT)


def tracked_store(store) -> dict[str, object]:
    """Relative curve file paths, each tracked curve file's table and the per-frame diagnostics, in a stable order."""
    s = Store(store)
    return {
        "files": sorted(os.path.relpath(p, s.root) for p in s.curve_files()),
        "tracked": {os.path.relpath(p, s.root): pq.read_table(p) for p in s.curve_files("tracked")},
        "frames": s.read_tracking_frames("guided-fast").sort_by([(C.UTTERANCE_ID, "ascending"), (C.FRAME, "ascending")]),
    }


def test_pipeline_tracking_on_a_local_dask_cluster_equals_the_thread_pool_run(tmp_path, video_corpus):
    from visemeflow.flows.pipeline import pipeline_flow

    threads = pipeline_flow(PipelineParams(corpus=video_corpus, store=tmp_path / "threads", n_shards=2))
    dask = pipeline_flow(PipelineParams(corpus=video_corpus, store=tmp_path / "dask", n_shards=2, runner=DASK))
    assert threads["track"]["tracked"] == dask["track"]["tracked"] == len(SHORT)
    assert dask["track"]["rejected"] == 0
    a, b = tracked_store(tmp_path / "threads"), tracked_store(tmp_path / "dask")
    assert a["files"] == b["files"] and len(a["tracked"]) == len(SHORT)
    for path, table in a["tracked"].items():
        other = b["tracked"][path]
        assert other.select([C.UTTERANCE_ID, C.FRAME, C.TIME_S]).equals(table.select([C.UTTERANCE_ID, C.FRAME, C.TIME_S]))
        # equal up to float summation order: torch splits a reduction by its thread count, one thread per Dask
        # worker against the threads a busy intra-op pool lends in the thread-pool run (seen: 7e-7 apart)
        np.testing.assert_allclose(curves_array(other), curves_array(table), rtol=0, atol=1e-5)
    assert b["frames"].num_rows == a["frames"].num_rows
    assert b["frames"].column(C.UTTERANCE_ID).equals(a["frames"].column(C.UTTERANCE_ID))


@task
def _worker_facts(i: int) -> dict:
    import cv2
    import torch

    return {"pid": os.getpid(), "api": str(PREFECT_API_URL.value()).rstrip("/"), "torch": torch.get_num_threads(),
            "opencv": cv2.getNumThreads(), "malloc_trim": os.environ.get("MALLOC_TRIM_THRESHOLD_")}


@flow
def _facts_flow(params: PipelineParams) -> list[dict]:
    return [f.result() for f in [_worker_facts.submit(i) for i in range(6)]]


def test_dask_workers_report_to_the_flows_api_with_one_thread_each(tmp_path, prefect_api_url):
    params = PipelineParams(corpus=tmp_path, runner=DASK)
    # as without a configured server: the workers must still be told the API the flow uses
    with temporary_settings(restore_defaults={PREFECT_API_URL}):
        facts = run_on_runner(_facts_flow, params)
    assert {f["api"] for f in facts} == {prefect_api_url.rstrip("/")}
    assert {(f["torch"], f["opencv"]) for f in facts} == {(1, 1)}
    assert {f["malloc_trim"] for f in facts} == {None}  # glibc's default, not Dask's slow 64 KiB trimming
    assert os.getpid() not in {f["pid"] for f in facts}


@flow
def _api_inside_a_flow() -> str:
    with shared_api() as url:
        return url


def test_shared_api_names_the_temporary_server_when_none_is_configured(prefect_api_url):
    # the harness's server stands in for the temporary one Prefect starts when no server is configured
    with temporary_settings(restore_defaults={PREFECT_API_URL}):
        assert not PREFECT_API_URL.value()
        with shared_api() as url:
            assert PREFECT_API_URL.value() == url
            assert url.rstrip("/") == prefect_api_url.rstrip("/")
        assert not PREFECT_API_URL.value()
        assert _api_inside_a_flow().rstrip("/") == prefect_api_url.rstrip("/")


def test_runner_choices(tmp_path):
    from prefect.task_runners import ThreadPoolTaskRunner
    from prefect_dask import DaskTaskRunner

    assert isinstance(task_runner_for(PipelineParams(corpus=tmp_path)), ThreadPoolTaskRunner)
    local = task_runner_for(PipelineParams(corpus=tmp_path, runner=DASK))
    assert isinstance(local, DaskTaskRunner) and local.cluster_class is local_cluster
    assert local.cluster_kwargs == {"n_workers": 2, "threads_per_worker": 1, "processes": True}
    remote = task_runner_for(PipelineParams(corpus=tmp_path, runner=RunnerConfig(
        kind="dask", dask_address="tcp://10.0.0.5:8786")))
    assert remote.address == "tcp://10.0.0.5:8786" and not remote.cluster_kwargs


def test_the_thread_pool_runs_one_task_per_cpu_unless_told(tmp_path):
    from prefect.settings import PREFECT_TASKS_RUNNER_THREAD_POOL_MAX_WORKERS

    from visemeflow.flows.sweep import sweep_flow
    from visemeflow.flows.track import track_flow

    assert thread_workers() == available_cpus() >= 1
    assert thread_workers(3) == 3
    assert task_runner_for(PipelineParams(corpus=tmp_path))._max_workers == available_cpus()
    assert task_runner_for(PipelineParams(corpus=tmp_path, runner=RunnerConfig(threads=5)))._max_workers == 5
    with temporary_settings(updates={PREFECT_TASKS_RUNNER_THREAD_POOL_MAX_WORKERS: 7}):  # an operator's setting
        assert thread_workers() == 7 and thread_workers(2) == 2
    # deployments call the flows directly: their own default is the bounded pool too (Prefect's has no limit)
    assert track_flow.task_runner._max_workers == sweep_flow.task_runner._max_workers == available_cpus()


_occupancy = {"running": 0, "peak": 0}
_occupancy_changed = threading.Condition()


@task
def _occupy(wanted: int) -> None:
    """Hold a worker until `wanted` tasks have run at once (or 60 s), then a little longer: the most tasks ever
    running together is then exactly the pool's limit, whatever the machine's load, when that limit is `wanted`."""
    with _occupancy_changed:
        _occupancy["running"] += 1
        _occupancy["peak"] = max(_occupancy["peak"], _occupancy["running"])
        _occupancy_changed.notify_all()
        _occupancy_changed.wait_for(lambda: _occupancy["peak"] >= wanted, timeout=60)
    time.sleep(0.2)  # room for a task beyond the limit to start, if the pool allowed one
    with _occupancy_changed:
        _occupancy["running"] -= 1


@flow
def _occupancy_flow(params: PipelineParams) -> dict:
    wanted = params.runner.threads or 1
    _occupancy.update(running=0, peak=0)
    for future in [_occupy.submit(wanted) for _ in range(6)]:
        future.result()
    return {"on_requested": on_requested_runner(params), "peak": _occupancy["peak"]}


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_run_on_runner_limits_the_tasks_at_once(tmp_path, threads):
    params = PipelineParams(corpus=tmp_path, runner=RunnerConfig(threads=threads))
    out = run_on_runner(_occupancy_flow, params)
    assert out["on_requested"] is True
    assert out["peak"] == threads
    # called without the runner it asks for (Prefect's unbounded default), the flow knows it
    assert _occupancy_flow(params)["on_requested"] is False
    # with no size asked for, the thread pool the caller chose is respected
    assert _occupancy_flow(PipelineParams(corpus=tmp_path))["on_requested"] is True
