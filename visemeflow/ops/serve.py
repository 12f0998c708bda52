"""`visemeflow serve`: a local Prefect server when none is configured, and a deployment of every stage.

The `pipeline` deployment runs on a cron schedule; since every stage caches on content hashes, a scheduled run
reprocesses only what changed. The other stages and `rerun` (one utterance, one stage) are deployments without a
schedule, run from the UI's forms (flow parameters are pydantic models) or `prefect deployment run`.
"""

import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
from prefect.deployments.runner import EntrypointType, RunnerDeployment
from prefect.settings import PREFECT_API_URL, PREFECT_UI_URL, temporary_settings

from visemeflow.storage import Store

DEFAULT_CRON = "0 3 * * *"
DEFAULT_PORT = 4200
DEPLOYMENT = "served"
TAGS = ["visemeflow"]


class ServerStartError(RuntimeError):
    """The local Prefect server did not answer its health check; the message quotes its log."""


def last_ingested_corpus(store: Path) -> Path | None:
    """The corpus the store's last ingest run read, if any."""
    run = Store(store).read_run_config("ingest")
    return Path(run["corpus"]) if run and run.get("corpus") else None


def build_deployments(
    store: Path, corpus: Path | None, cron: str | None = DEFAULT_CRON, timezone: str = "UTC",
) -> list[RunnerDeployment]:
    """Deployments of `pipeline` (on `cron` in `timezone`), of each stage, `predict`, `speak`, `preview` and `rerun`; the store is their
    default.

    Without `corpus`, the pipeline and ingest deployments default to the corpus the store last ingested; with
    neither, they have no default corpus and the pipeline no schedule (a run would have nothing to read).
    """
    from prefect.schedules import Cron

    from visemeflow.flows.animate import animate_flow, preview_flow, speak_flow
    from visemeflow.flows.evaluate import evaluate_flow
    from visemeflow.flows.import_curves import import_curves_flow
    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.landmarks import landmarks_flow
    from visemeflow.flows.pipeline import pipeline_flow
    from visemeflow.flows.predict import predict_flow
    from visemeflow.flows.procedural import procedural_flow
    from visemeflow.flows.rerun import rerun_flow
    from visemeflow.flows.sweep import sweep_flow
    from visemeflow.flows.track import track_flow
    from visemeflow.flows.train import train_flow

    store = store.resolve()
    corpus = corpus.resolve() if corpus else last_ingested_corpus(store)
    on_store = {"params": {"store": str(store)}}
    on_corpus = {"params": {"store": str(store), "corpus": str(corpus)}} if corpus else on_store

    def deployment(flow, parameters: dict, **kwargs) -> RunnerDeployment:
        return flow.to_deployment(
            DEPLOYMENT, parameters=parameters, tags=TAGS, entrypoint_type=EntrypointType.MODULE_PATH, **kwargs
        )

    return [
        deployment(pipeline_flow, on_corpus, schedule=Cron(cron, timezone=timezone) if corpus and cron else None,
                   concurrency_limit=1, description="Every stage on the corpus; unchanged utterances are cache hits."),
        deployment(ingest_flow, on_corpus),
        deployment(procedural_flow, on_store),
        deployment(landmarks_flow, on_store,
                   description="MediaPipe FaceMesh landmarks of every video without a landmark file."),
        deployment(track_flow, on_store),
        deployment(train_flow, on_store),
        deployment(sweep_flow, on_store),
        deployment(evaluate_flow, on_store,
                   description="Models judged on validation and on volume/pitch/speed/noise copies (robustness table)."),
        deployment(predict_flow, on_store,
                   description="Curves of new audio files from a trained model (the form asks for model and files)."),
        deployment(import_curves_flow, on_store,
                   description="Captured animation (Live Link CSV, channel files) as `captured` curves of real speech."),
        deployment(animate_flow, on_store,
                   description="Stored curves on characters: GLB, USD, Live Link CSV, web JSON and the audio."),
        deployment(speak_flow, on_store,
                   description="Audio files to talking characters: predict, then animate (the form asks for model, "
                               "files and characters)."),
        deployment(preview_flow, on_store,
                   description="One utterance's preview MP4: the character driven by each source side by side."),
        deployment(rerun_flow, on_store,
                   description="One utterance through one stage (ingest, procedural, track, animate), even when cached."),
    ]


def ui_url(api_url: str) -> str:
    """The UI address of a Prefect API: the configured PREFECT_UI_URL, else the API address without `/api`."""
    configured = PREFECT_UI_URL.value()
    if configured:
        return str(configured)
    return api_url.rstrip("/").removesuffix("/api")


def api_healthy(api_url: str) -> bool:
    try:
        return httpx.get(f"{api_url.rstrip('/')}/health", timeout=2.0).status_code == 200
    except httpx.HTTPError:
        return False


@contextmanager
def using_api(api_url: str) -> Iterator[str]:
    """This process and the processes it starts (served flow runs, Dask workers) talk to `api_url`."""
    before = os.environ.get("PREFECT_API_URL")
    os.environ["PREFECT_API_URL"] = api_url
    try:
        with temporary_settings(updates={PREFECT_API_URL: api_url}):
            yield api_url
    finally:
        if before is None:
            os.environ.pop("PREFECT_API_URL", None)
        else:
            os.environ["PREFECT_API_URL"] = before


@contextmanager
def ensure_server(port: int = DEFAULT_PORT, timeout_s: float = 180.0) -> Iterator[str]:
    """The configured Prefect API; else `prefect server start` on 127.0.0.1:`port` for the block. Yields the API URL.

    A server already answering on that port (started by hand) is used as it is and left running.
    """
    configured = PREFECT_API_URL.value()
    if configured:
        yield str(configured)
        return
    api_url = f"http://127.0.0.1:{port}/api"
    if api_healthy(api_url):
        with using_api(api_url):
            yield api_url
        return
    log = Path(tempfile.gettempdir()) / f"visemeflow-prefect-server-{port}.log"
    with log.open("wb") as out:
        # its own session, so stopping it also stops the web server process it starts
        process = subprocess.Popen(
            [sys.executable, "-m", "prefect", "server", "start", "--host", "127.0.0.1", "--port", str(port)],
            stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True,
            # the UI is served with the API address it calls; without this it calls port 4200 whatever `port` is
            env={**os.environ, "PREFECT_UI_API_URL": api_url, "PREFECT_SERVER_ANALYTICS_ENABLED": "false"},
        )
    try:
        wait_until_healthy(api_url, process, log, timeout_s)
        with using_api(api_url):
            yield api_url
    finally:
        stop_server(process)


def wait_until_healthy(api_url: str, process: subprocess.Popen, log: Path, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise ServerStartError(f"prefect server exited with code {process.returncode}; its log {log}:\n"
                                   f"{_tail(log)}")
        if api_healthy(api_url):
            return
        time.sleep(0.25)
    stop_server(process)
    raise ServerStartError(f"prefect server did not answer {api_url}/health within {timeout_s:.0f} s; its log {log}:\n"
                           f"{_tail(log)}")


def stop_server(process: subprocess.Popen, grace_s: float = 15.0) -> None:
    """SIGTERM to the server's process group, SIGKILL after `grace_s`."""
    if process.poll() is not None:
        return
    for sig, wait in ((signal.SIGTERM, grace_s), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            return
        try:
            process.wait(timeout=wait)
            return
        except subprocess.TimeoutExpired:
            continue


def _tail(log: Path, lines: int = 30) -> str:
    try:
        return "\n".join(log.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"


def serve_stages(store: Path, corpus: Path | None, cron: str | None = DEFAULT_CRON, timezone: str = "UTC",
                 port: int = DEFAULT_PORT, echo=print) -> None:
    """Serve every deployment until interrupted, with a local server unless PREFECT_API_URL names one."""
    from prefect import serve

    def stop(signum: int, frame: object) -> None:  # systemd and `kill` stop with SIGTERM: leave like Ctrl-C does
        raise SystemExit(0)

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, stop)  # until Prefect's runner installs its own, which also exits
    with ensure_server(port) as api_url:
        deployments = build_deployments(store, corpus, cron, timezone)
        pipeline = deployments[0]
        echo(f"Prefect UI: {ui_url(api_url)}  (API {api_url})")
        if pipeline.schedules:
            echo(f"pipeline on {pipeline.parameters['params']['corpus']}: cron '{cron}' ({timezone})")
        else:
            echo("pipeline: no schedule (no --corpus and the store has no ingest run); run it from the UI")
        echo("stop with Ctrl-C")
        serve(*deployments, print_starting_message=True)
