"""Task runners for the stages that scale out (tracking, sweeps): Prefect's thread pool, or Dask via prefect-dask.

A task run sent to a Dask worker carries the flow's Prefect settings, not the worker's environment. With no
`PREFECT_API_URL` those settings say "no server", so every worker process starts its own temporary server
(seconds each, all writing one SQLite file) and the flow's tasks are split across servers. `shared_api` names
the API explicitly before tasks are submitted: the configured one, else the temporary server this process
already uses, so every worker reports to the server the flow reports to.
"""

import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Protocol, TypeVar
from urllib.parse import urlparse

from prefect import Flow
from prefect.context import FlowRunContext
from prefect.settings import PREFECT_API_URL, get_current_settings, temporary_settings
from prefect.task_runners import TaskRunner, ThreadPoolTaskRunner

from visemeflow.flows.params import RunnerConfig

if TYPE_CHECKING:
    from distributed import LocalCluster

logger = logging.getLogger(__name__)

R = TypeVar("R")

# Environment of a local worker process from its start: one thread for torch (OpenMP), BLAS and OpenCV, so n
# workers use n cores; and glibc's own malloc tuning. Dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 so that
# workers hand memory back to the OS, which makes tracking 1.6-1.7x slower (its many large tensor allocations
# then go back and forth to the kernel); None removes it.
WORKER_ENVIRON: dict[str, str | None] = {
    "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "OPENCV_FOR_THREADS_NUM": "1",
    "MALLOC_TRIM_THRESHOLD_": None,
}
LOOPBACK = {"127.0.0.1", "localhost", "::1"}


class HasRunner(Protocol):
    runner: RunnerConfig


def available_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def thread_workers(requested: int | None = None) -> int:
    """Tasks at once in a thread pool: as requested, else Prefect's setting, else the CPUs this process may use.

    Prefect's own default has no limit: every utterance of a corpus would start at once, each with torch's and
    OpenCV's thread pools, and tracking the demo corpus took 2.1x as long as with one task per CPU.
    """
    return requested or get_current_settings().tasks.runner.thread_pool_max_workers or available_cpus()


class StoppableThreadPool(ThreadPoolTaskRunner):
    """Prefect's thread pool, except that a run stopped by Ctrl-C or SIGTERM (Prefect's TerminationSignal) does not
    wait for the tasks still running (a training run of hours, a long clip): their cancel events are set and the
    pool is shut down without joining them, so the command ends now (`visemeflow.cli.main` exits the process; every
    store write is atomic and the next run resumes). Any other ending waits for them as Prefect's pool does."""

    def __exit__(self, exc_type, exc_value, traceback) -> None:
        from prefect.exceptions import TerminationSignal

        if exc_type is None or not issubclass(exc_type, (KeyboardInterrupt, TerminationSignal)):
            return super().__exit__(exc_type, exc_value, traceback)
        for event in self._cancel_events.values():
            event.set()
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None
        return TaskRunner.__exit__(self, exc_type, exc_value, traceback)


def cpu_thread_pool(max_workers: int | None = None) -> ThreadPoolTaskRunner:
    """A thread pool task runner with `thread_workers(max_workers)` threads: the default of the CPU-bound flows."""
    return StoppableThreadPool(max_workers=thread_workers(max_workers))


def task_runner_for(params: HasRunner) -> TaskRunner:
    """The task runner `params.runner` asks for: a thread pool, a local Dask cluster, or an existing one."""
    runner = params.runner
    if runner.kind == "threads":
        return cpu_thread_pool(runner.threads)
    from prefect_dask import DaskTaskRunner

    if runner.dask_address:
        return DaskTaskRunner(address=runner.dask_address)
    return DaskTaskRunner(cluster_class=local_cluster, cluster_kwargs={
        "n_workers": runner.dask_workers, "threads_per_worker": 1, "processes": True,
    })


def local_cluster(**kwargs) -> "LocalCluster":
    """A `distributed.LocalCluster` whose worker processes start with `WORKER_ENVIRON`."""
    import dask
    from distributed import LocalCluster

    # the nanny sets these variables before it spawns a worker: in time for the C libraries, unlike `env`
    key = "distributed.nanny.pre-spawn-environ"
    with dask.config.set({key: {**dask.config.get(key), **WORKER_ENVIRON}}):
        return LocalCluster(**kwargs)


def with_runner(flow: Flow[..., R], params: HasRunner) -> Flow[..., R]:
    """`flow` with the task runner its parameters ask for."""
    return flow.with_options(task_runner=task_runner_for(params))


def on_requested_runner(params: HasRunner) -> bool:
    """Whether the flow run in progress already uses the task runner `params.runner` asks for."""
    context = FlowRunContext.get()
    if context is None:
        return False
    if params.runner.kind == "threads":  # a thread pool the caller chose counts unless a size is asked for
        requested = params.runner.threads
        return isinstance(context.task_runner, ThreadPoolTaskRunner) and (
            requested is None or getattr(context.task_runner, "_max_workers", None) == requested)
    from prefect_dask import DaskTaskRunner

    return isinstance(context.task_runner, DaskTaskRunner)


def run_on_runner(flow: Flow[..., R], params: HasRunner) -> R:
    """Call `flow(params)` on the task runner its parameters ask for, with Dask workers reporting to this API."""
    if params.runner.kind == "threads":
        return with_runner(flow, params)(params)
    with shared_api() as api_url:
        warn_if_unreachable(api_url, params.runner)
        return with_runner(flow, params)(params)


@contextmanager
def shared_api() -> Iterator[str]:
    """Settings naming the Prefect API this process uses, so Dask workers report to it; yields its URL."""
    configured = PREFECT_API_URL.value()
    if configured:
        yield configured
        return
    context = FlowRunContext.get()
    if context is not None and context.client is not None:
        url = str(context.client.api_url)
    else:
        from prefect.server.api.server import SubprocessASGIServer

        # the same temporary server Prefect starts for this process on its first API call (one per port, reused)
        server = SubprocessASGIServer()
        server.start()
        url = server.api_url
    with temporary_settings(updates={PREFECT_API_URL: url}):
        yield url


def warn_if_unreachable(api_url: str, runner: RunnerConfig) -> None:
    """A remote Dask cluster cannot report to a Prefect API on this machine's loopback address; say so."""
    if not runner.dask_address:
        return
    api_host = urlparse(api_url).hostname
    scheduler_host = urlparse(runner.dask_address if "://" in runner.dask_address
                              else f"tcp://{runner.dask_address}").hostname
    if api_host in LOOPBACK and scheduler_host not in LOOPBACK:
        logger.warning(
            "Dask workers behind %s cannot reach the Prefect API at %s; start a server they can reach "
            "(prefect server start --host 0.0.0.0) and set PREFECT_API_URL to it", runner.dask_address, api_url,
        )
