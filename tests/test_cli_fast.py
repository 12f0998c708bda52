"""The CLI answers a wrong argument at once, and uses a Prefect server that is already up (issue 28, item 1).

A wrong path used to cost Prefect's temporary server start (20-25 s) and two tracebacks before the one sentence
that mattered; a cached one-file command paid that start every time even with `visemeflow serve` running.
"""

import base64
import os
import socket
import subprocess
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, HTTPServer
from pathlib import Path

import pytest
from factories import REPO, stop_process

from visemeflow.ops import connect

CHILD_ENV = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "PREFECT_API_AUTH_STRING")}


def run_cli(*args: str, env: dict | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    """The installed `visemeflow ARGS` under `python -X importtime`: what it printed, and every module it imported
    (stderr)."""
    command = str(Path(sys.executable).parent / "visemeflow")
    return subprocess.run([sys.executable, "-X", "importtime", command, *args], cwd=REPO,
                          env={**CHILD_ENV, "COLUMNS": "400", **(env or {})}, capture_output=True, text=True,
                          timeout=timeout, check=False)


def said(result: subprocess.CompletedProcess) -> list[str]:
    """stderr without -X importtime's lines."""
    return [line for line in result.stderr.splitlines() if not line.startswith("import time:")]


def imported(result: subprocess.CompletedProcess) -> set[str]:
    return {line.split("|")[-1].strip() for line in result.stderr.splitlines() if line.startswith("import time:")}


def test_importing_the_cli_imports_neither_prefect_nor_the_heavy_libraries():
    done = subprocess.run([sys.executable, "-c", "import sys, visemeflow.cli; print(sorted(m for m in sys.modules "
                           "if m.split('.')[0] in ('prefect', 'torch', 'pyarrow', 'pandas', 'httpx')))"],
                          cwd=REPO, env=CHILD_ENV, capture_output=True, text=True, timeout=120, check=True)
    assert done.stdout.strip() == "[]", done.stdout


def test_version_prints_the_installed_version_without_prefect():
    import tomllib

    declared = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]
    done = run_cli("--version")
    assert done.returncode == 0 and done.stdout == f"visemeflow {declared}\n"
    assert not {m for m in imported(done) if m.split(".")[0] in ("prefect", "torch")}


@pytest.mark.parametrize("command", ["ingest", "pipeline", "synth"])
def test_a_wrong_corpus_path_is_one_line_and_exit_2_before_prefect(tmp_path, command):
    missing = tmp_path / "no-such-corpus"
    done = run_cli(command, str(missing), "--store", str(tmp_path / "store"))
    assert done.returncode == 2, done.stdout + done.stderr
    assert said(done) == [f"error: corpus (a folder, a manifest CSV or one audio or video file) {missing} does not exist"]
    assert done.stdout == ""
    modules = imported(done)
    assert "visemeflow.cli" in modules  # the importtime listing is real
    assert not {m for m in modules if m.split(".")[0] in ("prefect", "torch", "pyarrow")}
    assert not (tmp_path / "store").exists()


@pytest.mark.parametrize("command", ["predict", "speak"])
def test_a_bad_audio_path_is_one_line_and_exit_2_before_prefect(tmp_path, command):
    good = tmp_path / "good.wav"
    good.write_bytes(b"RIFF")  # never read: the check comes first
    for bad, why in ((tmp_path / "missing.wav", "does not exist"),
                     (tmp_path, f"is a folder: give the files in it ({tmp_path / '*.wav'}, or the shell's other "
                                "patterns)")):
        done = run_cli(command, str(good), str(bad), "--store", str(tmp_path / "store"))
        assert done.returncode == 2, done.stdout + done.stderr
        assert said(done) == [f"error: audio file {bad} {why}"]
        assert not {m for m in imported(done) if m.split(".")[0] in ("prefect", "torch")}


def test_other_missing_paths_and_a_wrong_stage_are_refused_the_same_way(tmp_path):
    audio = tmp_path / "a.wav"
    audio.write_bytes(b"RIFF")
    cases = [
        (["speak", str(audio), "--character", str(tmp_path / "nobody.glb")], f"character {tmp_path / 'nobody.glb'}"),
        (["animate", "--mapping", str(tmp_path / "map.csv")], f"file {tmp_path / 'map.csv'}"),
        (["import-curves", str(tmp_path / "takes")], f"path {tmp_path / 'takes'}"),
        (["track", "--rig", str(tmp_path / "rig.glb")], f"path {tmp_path / 'rig.glb'}"),
    ]
    for args, named in cases:
        done = run_cli(*args, "--store", str(tmp_path / "store"))
        assert done.returncode == 2 and said(done) == [f"error: {named} does not exist"], (args, done.stderr)
        assert not {m for m in imported(done) if m.startswith("prefect")}, args
    done = run_cli("rerun", "spk/a", "--stage", "trak", "--store", str(tmp_path / "store"))
    assert done.returncode == 2
    assert said(done) == ["error: --stage must be one of ingest, procedural, landmarks, track, animate, not 'trak'"]
    (tmp_path / "afile").write_text("x")
    done = run_cli("procedural", "--store", str(tmp_path / "afile" / "store"))
    assert done.returncode == 2
    assert said(done) == [f"error: cannot use {tmp_path / 'afile' / 'store'} as a store: {tmp_path / 'afile'} is a "
                          "file, not a folder"]


def test_app_called_in_process_leaves_the_prefect_api_to_its_caller(tmp_path, monkeypatch):
    """Tests and other Python callers run `app` under their own Prefect settings: no server started, no
    environment changed; only the `visemeflow` command (main) chooses the API."""
    import psutil
    from typer.testing import CliRunner

    from visemeflow.cli import app

    monkeypatch.delenv("PREFECT_API_URL", raising=False)
    before = {c.pid for c in psutil.Process().children(recursive=True)}
    done = CliRunner().invoke(app, ["rerun", "spk/a", "--stage", "trak", "--store", str(tmp_path / "store")])
    assert done.exit_code == 2 and "--stage must be one of" in done.output
    assert "PREFECT_API_URL" not in os.environ
    assert {c.pid for c in psutil.Process().children(recursive=True)} == before


class _Health(BaseHTTPRequestHandler):
    """/api/health, 200 only to the caller with the right basic auth (as `serve`'s server answers)."""

    auth = "visemeflow:secret"

    def do_GET(self):  # noqa: N802 (http.server's name)
        expected = "Basic " + base64.b64encode(self.auth.encode()).decode()
        ok = self.path == "/api/health" and self.headers.get("Authorization") == expected
        self.send_response(200 if ok else 401)
        self.end_headers()
        self.wfile.write(b"true")

    def log_message(self, *args):
        pass


def fake_serve(store: Path, port: int, pid: int, auth: str = _Health.auth) -> None:
    """What `visemeflow serve` leaves in `<store>/.prefect-serve/` while it runs."""
    home = store / connect.SERVE_DIR
    home.mkdir(parents=True)
    (home / connect.LOCK_FILE).write_text(str(pid))
    (home / connect.AUTH_FILE).write_text(auth)
    (home / connect.LOG_FILE).write_text(f"prefect config set PREFECT_API_URL=http://127.0.0.1:{port}/api\n")


def test_a_running_serve_of_the_store_is_found_by_its_pid_log_and_auth_string(tmp_path, monkeypatch):
    monkeypatch.delenv("PREFECT_API_URL", raising=False)
    server = HTTPServer(("127.0.0.1", 0), _Health)
    port = server.server_address[1]
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        fake_serve(tmp_path / "live", port, os.getpid())
        api = connect.serve_api(tmp_path / "live")
        assert api == connect.Api(f"http://127.0.0.1:{port}/api", _Health.auth, f"visemeflow serve (pid {os.getpid()})")
        fake_serve(tmp_path / "wrong-auth", port, os.getpid(), auth="visemeflow:stale")  # an earlier serve's file
        assert connect.serve_api(tmp_path / "wrong-auth") is None
        dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                              text=True, check=True)
        fake_serve(tmp_path / "dead", port, int(dead.stdout))  # serve exited: its pid is gone
        assert connect.serve_api(tmp_path / "dead") is None
        assert connect.serve_api(tmp_path / "never-served") is None
        monkeypatch.setenv("PREFECT_HOME", str(tmp_path / "no-profiles"))
        monkeypatch.setenv("PREFECT_API_AUTH_STRING", "")
        assert connect.use_running_api(tmp_path / "live") == api  # the command's Prefect will talk to it
        assert os.environ["PREFECT_API_URL"] == api.url and os.environ["PREFECT_API_AUTH_STRING"] == _Health.auth
        monkeypatch.setenv("PREFECT_API_URL", "http://elsewhere:4200/api")
        assert connect.find_api(tmp_path / "live").source == "PREFECT_API_URL"  # the user's choice comes first
    finally:
        server.shutdown()


def test_an_api_set_in_the_prefect_profile_is_left_to_prefect(tmp_path, monkeypatch):
    """`prefect config set PREFECT_API_URL=...` (the active profile) is the user's server: neither a serve nor an
    early server replaces it, and the environment is left alone for Prefect to read the profile."""
    for name in ("PREFECT_API_URL", "PREFECT_API_AUTH_STRING", "PREFECT_PROFILE", "PREFECT_PROFILES_PATH"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("PREFECT_HOME", str(tmp_path / "home"))
    monkeypatch.chdir(tmp_path)
    (tmp_path / "home").mkdir()
    (tmp_path / "home" / "profiles.toml").write_text(
        'active = "work"\n[profiles.work]\nPREFECT_API_URL = "http://prefect.example:4200/api"\n')
    api = connect.use_running_api(tmp_path / "store")
    assert api == connect.Api("http://prefect.example:4200/api", None, "profile work")
    assert "PREFECT_API_URL" not in os.environ
    monkeypatch.setenv("PREFECT_PROFILE", "other")  # a profile without an API: nothing configured
    (tmp_path / "prefect.toml").write_text('[api]\nurl = "http://toml.example/api"\n')
    assert connect.configured_api() == connect.Api("http://toml.example/api", None, "prefect.toml")


def test_on_an_early_temporary_server_prefects_info_lines_are_held_back_unless_asked_for(tmp_path, monkeypatch):
    """The early temporary server dies with the command: its "View at" run links would be dead, so Prefect logs at
    WARNING there unless the user set PREFECT_LOGGING_LEVEL; a configured API keeps Prefect's default."""
    class FakeServer:   # no uvicorn started: only what use_running_api reads
        url = "http://127.0.0.1:1/api"
        process = type("P", (), {"pid": 1})()

    for name in ("PREFECT_API_URL", "PREFECT_API_AUTH_STRING", "PREFECT_PROFILE", "PREFECT_PROFILES_PATH",
                 "PREFECT_LOGGING_LEVEL", "VISEMEFLOW_NO_SERVER_LOOKUP", "VISEMEFLOW_EARLY_SERVER"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("PREFECT_HOME", str(tmp_path / "home"))
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(connect, "EarlyServer", FakeServer)
    assert connect.use_running_api(tmp_path / "store").source.startswith("early temporary server")
    assert os.environ["PREFECT_LOGGING_LEVEL"] == "WARNING"
    monkeypatch.setenv("PREFECT_LOGGING_LEVEL", "INFO")    # the user's choice stands
    monkeypatch.delenv("PREFECT_API_URL")
    connect.use_running_api(tmp_path / "store")
    assert os.environ["PREFECT_LOGGING_LEVEL"] == "INFO"
    monkeypatch.delenv("PREFECT_LOGGING_LEVEL")
    monkeypatch.setenv("PREFECT_API_URL", "http://prefect.example:4200/api")   # a server that outlives the command
    assert connect.use_running_api(tmp_path / "store").source == "PREFECT_API_URL"
    assert "PREFECT_LOGGING_LEVEL" not in os.environ


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.server
def test_a_command_runs_its_flow_on_the_running_serve_of_its_store(tmp_path):
    """`visemeflow serve` up: a command on that store, with no PREFECT_API_URL, runs its flow on serve's server
    (the run is in that server's API) instead of starting Prefect's temporary one."""
    from factories import make_corpus
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_AUTH_STRING, PREFECT_API_URL, temporary_settings

    port = _free_port()
    store = tmp_path / "store"
    corpus = make_corpus(tmp_path / "corpus", {"spk/a": [("", 0.0, 0.2), ("AA1", 0.2, 0.5), ("M", 0.5, 0.7)]})
    env = {**CHILD_ENV, "PREFECT_HOME": str(tmp_path / "prefect-home"), "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}
    log = tmp_path / "serve.log"
    with log.open("w") as out:
        serve = subprocess.Popen([sys.executable, "-m", "visemeflow.cli", "serve", "--store", str(store), "--corpus",
                                  str(corpus), "--port", str(port), "--cron", ""], env=env, cwd=tmp_path,
                                 stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 240
        while "stop with Ctrl-C" not in log.read_text():
            assert serve.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.5)
        api = connect.serve_api(store)
        assert api is not None and api.url == f"http://127.0.0.1:{port}/api"
        # the line that says how another shell reaches this server for `prefect deployment run` works when run
        hint = next(line for line in log.read_text().splitlines() if line.startswith("for `prefect deployment run`"))
        exports = hint.split(": ", 1)[1].split("  (")[0]
        shell = subprocess.run(["bash", "-c", exports + '; echo "$PREFECT_API_URL $PREFECT_API_AUTH_STRING"'],
                               capture_output=True, text=True, check=True, timeout=30)
        assert shell.stdout.split() == [api.url, api.auth_string], hint
        done = subprocess.run([sys.executable, "-m", "visemeflow.cli", "ingest", str(corpus), "--store", str(store)],
                              env=env, cwd=tmp_path, capture_output=True, text=True, timeout=300, check=False)
        assert done.returncode == 0, done.stdout + done.stderr
        assert "Starting temporary server" not in done.stdout + done.stderr
        with temporary_settings(updates={PREFECT_API_URL: api.url, PREFECT_API_AUTH_STRING: api.auth_string}):
            with get_client(sync_client=True) as client:
                runs = [r for r in client.read_flow_runs() if r.deployment_id is None]
                flows = {client.read_flow(r.flow_id).name for r in runs}
    finally:
        stop_process(serve)
    assert "ingest" in flows, (flows, done.stderr[-3000:], log.read_text()[-3000:])
    assert all(r.state.is_completed() for r in runs), [(r.name, r.state) for r in runs]


@pytest.mark.server
def test_without_a_server_the_flow_runs_on_the_early_temporary_server_and_is_tracked(tmp_path):
    """No server up: the command starts Prefect's temporary server itself while it imports (not Prefect when the
    flow is called); the run is recorded in PREFECT_HOME's database as before, and the server ends with the
    command."""
    import sqlite3

    import psutil
    from factories import make_corpus

    corpus = make_corpus(tmp_path / "corpus", {"spk/a": [("", 0.0, 0.2), ("AA1", 0.2, 0.5), ("M", 0.5, 0.7)]})
    home = tmp_path / "prefect-home"
    env = {**CHILD_ENV, "PREFECT_HOME": str(home), "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}
    done = subprocess.run([sys.executable, "-m", "visemeflow.cli", "ingest", str(corpus), "--store",
                           str(tmp_path / "store")], env=env, cwd=tmp_path, capture_output=True, text=True,
                          timeout=600, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "ingest: utterances 1, ingested 1" in done.stdout
    assert "Starting temporary server" not in done.stdout + done.stderr  # Prefect did not start its own
    with sqlite3.connect(home / "prefect.db") as db:
        runs = db.execute("SELECT flow.name, flow_run.state_type FROM flow_run JOIN flow ON flow.id = "
                          "flow_run.flow_id").fetchall()
    assert runs == [("ingest", "COMPLETED")]
    left = []
    for process in psutil.process_iter(["cmdline"]):
        try:
            if "uvicorn" in (process.info["cmdline"] or []) and process.environ().get("PREFECT_HOME") == str(home):
                left.append(process.pid)
        except psutil.Error:
            continue
    assert left == []


def _modules_after(code: str) -> set[str]:
    done = subprocess.run([sys.executable, "-c", code + "\nimport sys\nprint('\\n'.join(sys.modules))"], cwd=REPO,
                          env=CHILD_ENV, capture_output=True, text=True, timeout=120, check=True)
    return set(done.stdout.split())


def test_the_predict_flow_and_a_cpu_device_check_import_no_torch():
    """torch (1.5-2 s of every command) is imported where a model runs, not where the predict flow is defined or a
    device word is checked: a second `predict` of the same file, all cached, never loads it (bench/cli.py)."""
    loaded = _modules_after("import visemeflow.flows.predict, visemeflow.animation, visemeflow.animation.package\n"
                            "from visemeflow.learning.device import check_device_here\n"
                            "assert check_device_here(' CPU ') == 'cpu' and check_device_here('auto') == 'auto'\n"
                            "assert check_device_here('cpu', 'bf16') == 'cpu'")
    assert "visemeflow.flows.predict" in loaded and "torch" not in loaded
    # a precision that only a GPU could refuse, asked of `auto`: now torch must answer
    assert "torch" in _modules_after("from visemeflow.learning.device import check_device_here\n"
                                     "check_device_here('auto', 'bf16')")


def test_cuda_on_this_cpu_machine_and_a_bad_precision_are_still_refused():
    import torch

    from visemeflow.learning.device import DeviceError, check_device_here

    with pytest.raises(DeviceError, match="unknown precision"):
        check_device_here("cpu", "fp8")
    with pytest.raises(DeviceError, match="unknown device"):
        check_device_here("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(DeviceError, match="cuda requested"):
            check_device_here("cuda")


def test_what_a_store_model_needs_is_remembered_by_content_hash(tmp_path, monkeypatch):
    """`predict` asks whether a model runs on the packaged Whisper weights before anything runs; the answer is kept
    beside the store's model file under its hash, so a cached run need not torch-load the file; a replaced file is
    read again."""
    import json
    import shutil

    from visemeflow.flows import predict as P
    from visemeflow.learning.default_model import shipped_model_path

    model = tmp_path / "model.pt"
    memo = tmp_path / P.FEATURES_MEMO
    shutil.copyfile(shipped_model_path("default"), model)
    assert P._packaged_whisper(model, memo) == (True, "whisper-base-blstm")
    assert json.loads(memo.read_text())["packaged_whisper"] is True

    def no_torch_load(path):
        raise AssertionError("read the model file although the memo answers")

    import visemeflow.learning.train as T

    monkeypatch.setattr(T, "read_model_file", no_torch_load)
    assert P._packaged_whisper(model, memo) == (True, "whisper-base-blstm")
    monkeypatch.undo()
    shutil.copyfile(shipped_model_path("default-fbank"), model)   # another model under the same name
    assert P._packaged_whisper(model, memo) == (False, "fbank-blstm")
    memo.write_text("{not json")
    assert P._packaged_whisper(model, memo) == (False, "fbank-blstm")
    assert json.loads(memo.read_text())["preset"] == "fbank-blstm"
    assert P._packaged_whisper(model) == (False, "fbank-blstm")   # without a memo: read, nothing written


def test_the_command_ends_its_flow_run_without_waiting_for_the_heartbeat_thread(monkeypatch):
    """Prefect's synchronous engine joins its heartbeat thread, which sleeps in 1 s steps, at the end of every flow
    run (0.7-0.9 s of a cached `predict`); the command asks for what the asynchronous engine does, no join. The
    heartbeats themselves still go (tests/test_predict.py finds the cached command's in the API)."""
    import inspect

    from prefect import flow_engine

    # the Prefect installed has the parameter: an upgrade that drops it (the speed-up silently gone) shows here
    assert "join_on_exit" in inspect.signature(flow_engine._send_heartbeats).parameters
    calls = []

    def send(engine, join_on_exit: bool = True):
        calls.append((engine, join_on_exit))
        return "context"

    monkeypatch.setattr(flow_engine, "_send_heartbeats", send)
    assert connect.unjoined_heartbeats() and connect.unjoined_heartbeats()   # once is enough, twice wraps once
    assert flow_engine._send_heartbeats("engine") == "context" and calls == [("engine", False)]

    def older(engine):   # a Prefect without the parameter is left as it is
        return "older"

    monkeypatch.setattr(flow_engine, "_send_heartbeats", older)
    assert not connect.unjoined_heartbeats() and flow_engine._send_heartbeats is older


def test_the_command_ends_its_process_after_the_exit_handlers_with_its_output_and_status(tmp_path):
    """`main`, as the program, ends the process with `os._exit` once the exit handlers ran and the output is
    flushed (Python's teardown of Prefect, pydantic and pyarrow took 0.4-0.5 s after a cached `predict` had
    printed): what was printed, the handlers' work and the exit status are those of a normal exit."""
    script = ("import atexit, runpy, sys\n"
              "atexit.register(lambda: print('exit handler ran'))\n"
              "sys.argv = ['visemeflow', *sys.argv[1:]]\n"
              "runpy.run_module('visemeflow.cli', run_name='__main__', alter_sys=True)\n")
    store = tmp_path / "store"
    store.mkdir()
    for args, status, out, err in (
        (["rejects", "--store", str(store)], 0, ["no rejects", "exit handler ran"], []),
        (["rejects", "--store", str(tmp_path / "stor")], 2, ["exit handler ran"],
         [f"error: no store at {tmp_path / 'stor'}: give the folder a pipeline wrote with --store"]),
        (["predict", str(tmp_path / "missing.wav"), "--store", str(store)], 2, ["exit handler ran"],
         [f"error: audio file {tmp_path / 'missing.wav'} does not exist"]),
    ):
        done = subprocess.run([sys.executable, "-c", script, *args], cwd=REPO, env=CHILD_ENV, capture_output=True,
                              text=True, timeout=120, check=False)
        assert (done.returncode, done.stdout.splitlines(), done.stderr.splitlines()) == (status, out, err)


def test_the_early_server_stopped_while_starting_says_nothing_and_one_that_died_says_why(tmp_path, monkeypatch,
                                                                                        capfd):
    """A command that fails its checks within a second stops the early server mid-start: uvicorn's errors about the
    interrupted start-up used to reach the terminal after the command's one clean line. They go to a log of the
    command's own, removed when it stops the server; a server that died on its own has its end printed."""
    monkeypatch.setenv("PREFECT_HOME", str(tmp_path / "home"))
    early = connect.EarlyServer()
    time.sleep(1.0)                       # importing the server application: well before it is ready
    early.stop()
    out, err = capfd.readouterr()
    assert out == "" and err == "" and not early.log.exists()
    dead = connect.EarlyServer()
    dead.process.kill()
    dead.process.wait()
    dead.stop()
    err = capfd.readouterr().err
    assert err.startswith("the temporary Prefect server exited -9") and dead.log.exists()
