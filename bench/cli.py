"""Benchmark: how long a `visemeflow` command takes before it does anything (issue 28, item 1).

Run:  .venv/bin/python bench/cli.py [--before DIR] [--repeat 2] [--keep DIR]

Each figure is the wall time of the real command in a new process (what a user waits for), the best of `--repeat`
runs; it prints one table and asserts nothing. Rows:
  --help                   `visemeflow --help`;
  bad argument             `visemeflow ingest /no/such/corpus`: refused, exit 2;
  wrong path               `visemeflow predict /no/such.wav`: refused, exit 2, before Prefect is imported;
  cached predict, cold     `visemeflow predict SHORT.wav` a second time (its task cached), no server running:
                           "Prefect's own" lets Prefect start its temporary server when the flow is called
                           (VISEMEFLOW_NO_SERVER_LOOKUP=1, the behaviour before issue 28); "early" is the default,
                           the same server started while the command imports its libraries;
  cached predict, served   the same with `visemeflow serve --store STORE` running: "found" by the command itself
                           (the default), or named by PREFECT_API_URL and PREFECT_API_AUTH_STRING.
With `--before DIR`, a checkout of the code before (e.g. `git worktree add /tmp/wt HEAD` before a change) runs the
same commands (PYTHONPATH=DIR) in the same session, interleaved with the current code, row by row.
Each version has its own store (and its own `serve` of it): their code digests differ, so on one store each would
recompute what the other stored and no "cached" row after a switch of version would be cached. The stores, a Prefect
home and serve's databases live in a temporary work folder (`--keep` keeps it). The machine may
be shared: the load average before and after is printed, and timings of a loaded machine are much longer.
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
AUDIO = REPO / "examples" / "corpus" / "LJ" / "LJ001-0002.wav"
COMMAND = [sys.executable, "-m", "visemeflow.cli"]


def timed(args: list[str], env: dict[str, str], cwd: Path, expect: int | None = 0) -> float:
    """Wall seconds of `visemeflow ARGS`; it must exit `expect` (None: with any error, as the code before did on a
    wrong path, 1 and a traceback)."""
    started = time.perf_counter()
    done = subprocess.run(COMMAND + args, env=env, cwd=cwd, capture_output=True, text=True, timeout=900, check=False)
    seconds = time.perf_counter() - started
    if done.returncode != expect and not (expect is None and done.returncode != 0):
        raise SystemExit(f"{' '.join(args)} exited {done.returncode}, not {expect}:\n{done.stdout}\n{done.stderr}")
    return seconds


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_serve(store: Path, env: dict[str, str], work: Path, name: str = "") -> tuple[subprocess.Popen, str, str]:
    """`visemeflow serve` on `store`, until it says it serves; its API address and auth string."""
    port = free_port()
    log = work / f"serve{'-' + name if name else ''}.log"
    with log.open("w") as out:
        serve = subprocess.Popen(COMMAND + ["serve", "--store", str(store), "--port", str(port), "--cron", ""],
                                 env=env, cwd=work, stdout=out, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 300
    while "stop with Ctrl-C" not in log.read_text():
        if serve.poll() is not None or time.monotonic() > deadline:
            raise SystemExit(f"serve did not start:\n{log.read_text()}")
        time.sleep(0.5)
    return serve, f"http://127.0.0.1:{port}/api", (store / ".prefect-serve" / "auth-string").read_text()


def stop(serve: subprocess.Popen) -> None:
    serve.terminate()
    try:
        serve.wait(timeout=60)
    except subprocess.TimeoutExpired:
        serve.kill()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--before", type=Path, help="A checkout of the code before, run with PYTHONPATH=DIR.")
    parser.add_argument("--repeat", type=int, default=2, help="Runs of each command; the fastest counts.")
    parser.add_argument("--keep", type=Path, help="Work folder to keep (default: a temporary one, removed).")
    args = parser.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="visemeflow-bench-cli-"))
    work.mkdir(parents=True, exist_ok=True)
    # one store per version: the two versions' code digests differ, so on one store each would recompute what the
    # other just stored, and every "cached" figure after a switch of version would be a full prediction
    stores = {"now": work / "store-now", "before": work / "store-before"}
    base = {k: v for k, v in os.environ.items()
            if k not in ("PREFECT_API_URL", "PREFECT_API_AUTH_STRING", "VISEMEFLOW_NO_SERVER_LOOKUP",
                         "VISEMEFLOW_EARLY_SERVER", "PYTHONPATH")}
    base.update(PREFECT_HOME=str(work / "prefect-home"), PREFECT_SERVER_ANALYTICS_ENABLED="false")
    versions = {"now": base}
    if args.before:
        versions["before"] = {**base, "PYTHONPATH": str(args.before.resolve())}
    predicts = {v: ["predict", str(AUDIO), "--store", str(stores[v]), "--device", "cpu"] for v in stores}
    print(f"load average before: {os.getloadavg()}; {os.cpu_count()} CPUs; audio {AUDIO.name}", flush=True)
    for version, env in versions.items():  # computes the curves, migrates the Prefect database: not timed
        timed(predicts[version], env, work)
    rows: dict[str, list[float]] = {}

    def measure(name: str, command: list[str], env: dict[str, str], expect: int | None = 0) -> None:
        rows.setdefault(name, []).append(timed(command, env, work, expect))
        print(f"  {name}: {rows[name][-1]:.2f} s (load {os.getloadavg()[0]:.1f})", flush=True)

    for _ in range(args.repeat):
        for version, env in versions.items():
            predict = predicts[version]
            measure(f"--help ({version})", ["--help"], env)
            measure(f"bad argument ({version})", ["ingest", str(work / "no-such-corpus"), "--store",
                                                  str(stores[version])], env,
                    expect=2 if version == "now" else None)
            measure(f"wrong path ({version})", ["predict", str(work / "no-such.wav"), "--store", str(stores[version])],
                    env, expect=2 if version == "now" else None)
            measure(f"cached predict, cold, Prefect's own server ({version})", predict,
                    {**env, "VISEMEFLOW_NO_SERVER_LOOKUP": "1"})
            measure(f"cached predict, cold, early server ({version})", predict, env)
    served = {v: start_serve(stores[v], versions[v], work, v) for v in versions}
    try:
        for _ in range(args.repeat):
            for version, env in versions.items():
                predict = predicts[version]
                _, api_url, auth = served[version]
                measure(f"cached predict, serve running, found ({version})", predict, env)
                measure(f"cached predict, serve running, PREFECT_API_URL set ({version})", predict,
                        {**env, "PREFECT_API_URL": api_url, "PREFECT_API_AUTH_STRING": auth})
    finally:
        for serve, _, _ in served.values():
            stop(serve)
    width = max(map(len, rows))
    print(f"{'command':<{width}}  {'best s':>7}  {'runs s':>20}")
    kinds = list(dict.fromkeys(name.rsplit(" (", 1)[0] for name in rows))  # each row of both versions together
    for name, seconds in sorted(rows.items(), key=lambda row: kinds.index(row[0].rsplit(" (", 1)[0])):
        print(f"{name:<{width}}  {min(seconds):7.2f}  {', '.join(f'{s:.2f}' for s in seconds):>20}")
    print(f"load average after: {os.getloadavg()}")
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
