"""Find a Prefect API that is already up, so that a command does not pay for Prefect's temporary server.

Without an API, every flow call starts Prefect's temporary ("ephemeral") server: a uvicorn subprocess that imports
the whole server application and checks the database's migrations, 10-25 s on a loaded 2-core machine before the
first task runs. A server that stays up (`visemeflow serve`, or any `prefect server start` named by PREFECT_API_URL)
answers in milliseconds, and its UI shows the command's runs beside the served ones.

This module is imported by the CLI's argument callbacks, before Prefect is: it uses the standard library only (no
Prefect, no httpx) and only reads what `visemeflow serve` leaves in `<store>/.prefect-serve/` (see
`visemeflow.ops.serve`: the auth string, the lock file holding serve's pid, the server log naming its address).
`unjoined_heartbeats`, for the command once its flow module is imported, imports Prefect when it is called.
"""

from __future__ import annotations

import atexit
import base64
import ctypes
import os
import re
import signal
import socket
import subprocess
import sys
import tomllib
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path

from visemeflow.location import is_url
from visemeflow.ops.prefect_db import seed_home

# The names `visemeflow.ops.serve` writes under; repeated here because importing serve would import Prefect.
SERVE_DIR = ".prefect-serve"
AUTH_FILE = "auth-string"
LOG_FILE = "server.log"
LOCK_FILE = "serve.lock"
DEFAULT_PORT = 4200
HEALTH_TIMEOUT_S = 5.0  # a serve on a loaded machine can take seconds to answer
# `prefect server start` prints the address it serves on (its welcome text, then uvicorn's line) into serve's log.
_ADDRESS = re.compile(r"http://(?:127\.0\.0\.1|localhost):(\d+)")


@dataclass(frozen=True)
class Api:
    """A reachable Prefect API: its URL, the auth string it wants (None: none), and where it was found."""

    url: str
    auth_string: str | None
    source: str  # "PREFECT_API_URL" or "visemeflow serve (pid N)"


def healthy(api_url: str, auth_string: str | None = None, timeout_s: float = HEALTH_TIMEOUT_S) -> bool:
    """Whether `api_url`/health answers 200 to a caller with `auth_string` (HTTP basic, as Prefect's client sends)."""
    request = urllib.request.Request(f"{api_url.rstrip('/')}/health")
    if auth_string:
        request.add_header("Authorization", "Basic " + base64.b64encode(auth_string.encode()).decode())
    try:
        with urllib.request.urlopen(request, timeout=timeout_s) as response:  # noqa: S310 (a local http URL)
            return response.status == 200
    except (urllib.error.URLError, OSError, ValueError):
        return False


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: not a serve of ours
        return False
    return True


def serve_api(store: Path) -> Api | None:
    """The server a running `visemeflow serve --store store` started, when it answers; else None.

    Read-only and lock-free: serve's lock file gives its pid (a dead pid: no serve), its log the port, its auth file
    the string the server wants. A serve given PREFECT_API_URL starts no server and writes no auth file: the caller
    then has PREFECT_API_URL too, which `find_api` uses first.
    """
    home = store / SERVE_DIR
    try:
        pid = int((home / LOCK_FILE).read_text(encoding="ascii").strip() or "0")
        auth_string = (home / AUTH_FILE).read_text(encoding="utf-8").strip()
    except (OSError, ValueError):
        return None
    if pid <= 0 or not auth_string or not _pid_alive(pid):
        return None
    try:
        found = _ADDRESS.search((home / LOG_FILE).read_text(encoding="utf-8", errors="replace")[:20000])
    except OSError:
        found = None
    url = f"http://127.0.0.1:{found.group(1) if found else DEFAULT_PORT}/api"
    if not healthy(url, auth_string):
        return None
    return Api(url, auth_string, f"visemeflow serve (pid {pid})")


def prefect_home() -> Path:
    """PREFECT_HOME, as Prefect reads it (default ~/.prefect)."""
    return Path(os.environ.get("PREFECT_HOME") or Path.home() / ".prefect").expanduser()


def configured_api() -> Api | None:
    """The API the user configured for Prefect without the environment: the active profile's PREFECT_API_URL
    (`prefect config set`, in PREFECT_PROFILES_PATH or PREFECT_HOME/profiles.toml), or `[api] url` of a
    prefect.toml here. Prefect uses it whatever we do: it must not be replaced by a serve or an early server."""
    home = prefect_home()
    try:
        profiles = tomllib.loads(Path(os.environ.get("PREFECT_PROFILES_PATH") or home / "profiles.toml")
                                 .expanduser().read_text(encoding="utf-8"))
        name = os.environ.get("PREFECT_PROFILE") or profiles.get("active") or "ephemeral"
        profile = profiles.get("profiles", {}).get(name, {})
        if profile.get("PREFECT_API_URL"):
            return Api(str(profile["PREFECT_API_URL"]), profile.get("PREFECT_API_AUTH_STRING"), f"profile {name}")
    except (OSError, ValueError, AttributeError):
        pass
    try:
        url = tomllib.loads(Path("prefect.toml").read_text(encoding="utf-8")).get("api", {}).get("url")
    except (OSError, ValueError, AttributeError):
        url = None
    return Api(str(url), None, "prefect.toml") if url else None


def find_api(store: Path | None) -> Api | None:
    """PREFECT_API_URL when set, else the API a Prefect profile or prefect.toml configures (Prefect uses either
    whatever we do), else a running `visemeflow serve` of `store`."""
    configured = os.environ.get("PREFECT_API_URL")
    if configured:
        return Api(configured, os.environ.get("PREFECT_API_AUTH_STRING"), "PREFECT_API_URL")
    configured_elsewhere = configured_api()
    if configured_elsewhere is not None:
        return configured_elsewhere
    if store is None or is_url(store):
        return None   # `visemeflow serve` keeps its server's record in a local store folder
    return serve_api(Path(store))


class EarlyServer:
    """Prefect's temporary server, started by us while the command is still importing its libraries.

    Prefect starts its temporary server only when the flow is called, after the command has imported Prefect, torch
    and the flow modules: the server's own start (importing the server application, checking the database) then
    adds its whole 10-20 s to theirs. Started at argument-parsing time instead, the two overlap on the machine's
    cores. The socket is bound and listening here and handed to uvicorn (`--fd`): a request made before the server
    is ready waits in the socket's backlog instead of being refused, so nothing has to wait for the server
    explicitly. It is the very process Prefect would start (uvicorn on `prefect.server.api.server:create_app`, in
    ephemeral mode, with the same database in PREFECT_HOME): the runs are tracked as before. It dies with this
    process: terminated at exit (after Prefect's own exit handlers, which flush logs to it) and by the kernel when
    this process is killed.
    """

    def __init__(self) -> None:
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.bind(("127.0.0.1", 0))
        listener.listen(128)
        self.port = listener.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}/api"
        home = prefect_home()
        seed_home(home)   # a new home's database from the migrated template (visemeflow.ops.prefect_db)
        env = {**os.environ, "PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1",
               "PREFECT__SERVER_FINAL": "1"}
        env.pop("PREFECT_API_URL", None)
        # the server's own messages go to a file of this command's, not the terminal: stopped while it still starts
        # (a command that fails its checks within a second), uvicorn logs its interrupted start-up as errors.
        # A server that dies on its own has its last lines printed when the command ends (`stop`).
        self.log = home / f"early-server-{os.getpid()}.log"
        try:
            home.mkdir(parents=True, exist_ok=True)
            log = open(self.log, "wb")   # noqa: SIM115 - closed below, once the server holds its copy
        except OSError:   # a home we cannot write to: the server's messages are dropped, as Prefect's own would be
            log = open(os.devnull, "wb")   # noqa: SIM115
        with log:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "uvicorn", "--factory", "prefect.server.api.server:create_app",
                 "--fd", str(listener.fileno()), "--log-level", "error", "--lifespan", "on"],
                env=env, pass_fds=(listener.fileno(),), stdin=subprocess.DEVNULL, stdout=log, stderr=log,
                preexec_fn=_dies_with_parent(),
                # a session of its own: Ctrl-C in the terminal and `timeout`'s SIGTERM reach the command's process
                # group, not the server, which stays up while the command marks its run stopped, then dies with it
                start_new_session=True,
            )
        listener.close()  # the server holds its copy
        self.stopped = False
        atexit.register(self.stop)

    def stop(self, grace_s: float = 5.0) -> None:
        if self.stopped:   # once: at exit again, its code is our own SIGTERM's
            return
        self.stopped = True
        code = self.process.poll()
        if code is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        elif code != 0:   # it died on its own: what it said is the reason the command's API calls failed
            try:
                tail = self.log.read_text(encoding="utf-8", errors="replace").splitlines()[-20:]
            except OSError:
                tail = []
            print(f"the temporary Prefect server exited {code}" + (":\n" + "\n".join(tail) if tail else ""),
                  file=sys.stderr)
            return   # its log is kept for a closer look
        self.log.unlink(missing_ok=True)


def _dies_with_parent():
    """A preexec_fn asking Linux to SIGKILL the child when this process dies, even by kill -9 (None elsewhere)."""
    if sys.platform != "linux":
        return None
    prctl = ctypes.CDLL(None, use_errno=True).prctl  # looked up before the fork: the child only calls it

    def preexec() -> None:
        prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG

    return preexec


def use_running_api(store: Path | None, start_early: bool = True) -> Api | None:
    """Point this process (and the processes it starts) at a Prefect API before Prefect is imported: one already
    up (PREFECT_API_URL, a running `visemeflow serve` of `store`), else, with `start_early`, Prefect's temporary
    server started now (`EarlyServer`). None when neither: Prefect then starts its temporary server itself.

    VISEMEFLOW_NO_SERVER_LOOKUP=1 does neither (Prefect's own behaviour, what the commands did before; the
    benchmark's "before"); VISEMEFLOW_EARLY_SERVER=0 only skips the early start.
    """
    if os.environ.get("VISEMEFLOW_NO_SERVER_LOOKUP") == "1" and not os.environ.get("PREFECT_API_URL"):
        return None
    api = find_api(store)
    if api is None and start_early and os.environ.get("VISEMEFLOW_EARLY_SERVER", "1") != "0":
        server = EarlyServer()
        api = Api(server.url, None, f"early temporary server (pid {server.process.pid})")
        os.environ["PREFECT_API_URL"] = api.url
        os.environ.pop("PREFECT_API_AUTH_STRING", None)
        # a temporary server dies with the command: Prefect's INFO lines ("View at http://127.0.0.1:PORT/runs/...")
        # would point at pages no one can open afterwards. Warnings and our own progress and summary lines stay;
        # PREFECT_LOGGING_LEVEL=INFO brings the rest back, and with `visemeflow serve` up the links work and show.
        os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    elif api is not None and api.source.startswith("visemeflow serve"):
        os.environ["PREFECT_API_URL"] = api.url
        os.environ["PREFECT_API_AUTH_STRING"] = api.auth_string or ""
    return api


def unjoined_heartbeats() -> bool:
    """Let this process's synchronous flow runs end without waiting for their heartbeat thread; whether it was done.

    A flow run sends heartbeats (events saying the run is alive, every PREFECT_FLOWS_HEARTBEAT_FREQUENCY, 180 s by
    default) from a thread that sleeps in steps of one second; Prefect's synchronous engine joins that thread when
    the run ends, so every flow run of a command ends up to 1 s late (0.7-0.9 s of a cached 3.5 s `predict`: the
    thread's first heartbeat is sent as the run starts, and the join then waits out the rest of its first second).
    Prefect's asynchronous engine does not join it (`join_on_exit=False`); this makes the synchronous engine do the
    same. The heartbeats are still sent: the first as the run starts, the next ones while it runs; the thread stops
    at its next one-second check after the run ends, and dies with the process, which a command ends right after
    its flow. Meant for the `visemeflow` command only (tests and callers of `app` keep Prefect's behaviour); a
    Prefect whose engine has no such function or parameter is left alone (False)."""
    import inspect

    from prefect import flow_engine

    send = getattr(flow_engine, "_send_heartbeats", None)
    if getattr(send, "visemeflow_unjoined", False):
        return True
    try:
        if send is None or "join_on_exit" not in inspect.signature(send).parameters:
            return False
    except (TypeError, ValueError):
        return False

    def send_unjoined(engine, join_on_exit: bool = True):
        return send(engine, join_on_exit=False)

    send_unjoined.visemeflow_unjoined = True
    flow_engine._send_heartbeats = send_unjoined
    return True
