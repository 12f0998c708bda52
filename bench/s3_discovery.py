"""Benchmark: discovering a corpus on object storage (issue 29), the way it was against the way it is, side by side.

Run:  .venv/bin/python bench/s3_discovery.py [--utterances N] [--repeats R]

A moto S3 server on 127.0.0.1 (bench/s3_store.py's `start_s3`) gets a corpus of N utterances, each the demo
LJSpeech utterances' .wav and .TextGrid in turn (real sizes: 100-300 kB of audio, 5-10 kB of alignment), under
10 speaker folders. Then `discover_corpus(s3://...)` runs on a machine with no local copies (a fresh TMPDIR each
time), three ways:
  whole, one by one     the mirror before this change: every object downloaded, one GET after another
  text, one by one      media only named (their ETag and size), the alignments downloaded one after another
  text, 32 at once      the default: media named, alignments fetched 32 at a time (fsspec's batched get)
and once more warm (the default again, its copies kept: a rerun lists the corpus and reads nothing). Per way: the
best wall time of R runs, the bytes the local copies hold, and the ratio to the first way.

moto on 127.0.0.1 answers at once, and on this 2-core machine it is CPU-bound, so many requests at once gain nothing
there; a real bucket is a network round trip away (AWS: some 10-50 ms a request in the region). `--latency-ms L`
(default 20) puts a relay in front of moto that holds every chunk the client sends for L ms before passing it on
(a request is one chunk, so about one round trip each); `--latency-ms 0` talks to moto directly. Prints a table
and never asserts.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from s3_store import start_s3  # bench/s3_store.py, beside this script
from report import print_grid  # bench/report.py, beside this script

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def start_relay(target: str, latency_s: float) -> str:
    """A TCP relay on a free port of 127.0.0.1 in a thread of its own, each chunk from a client delayed by
    `latency_s` before it reaches `target` (http://host:port); its URL."""
    import asyncio
    import threading
    from urllib.parse import urlsplit

    host, port = urlsplit(target).hostname, urlsplit(target).port
    ready: list[int] = []
    started = threading.Event()

    async def pump(reader, writer, delay: float) -> None:
        try:
            while chunk := await reader.read(1 << 16):
                if delay:
                    await asyncio.sleep(delay)
                writer.write(chunk)
                await writer.drain()
        except ConnectionError:
            pass
        finally:
            writer.close()

    async def handle(client_reader, client_writer) -> None:
        server_reader, server_writer = await asyncio.open_connection(host, port)
        await asyncio.gather(pump(client_reader, server_writer, latency_s), pump(server_reader, client_writer, 0.0))

    async def serve() -> None:
        server = await asyncio.start_server(handle, "127.0.0.1", 0)
        ready.append(server.sockets[0].getsockname()[1])
        started.set()
        async with server:
            await server.serve_forever()

    threading.Thread(target=lambda: asyncio.run(serve()), daemon=True).start()
    started.wait(30)
    return f"http://127.0.0.1:{ready[0]}"


def upload_corpus(n: int) -> str:
    import s3fs

    lj = sorted((REPO / "examples" / "corpus" / "LJ").glob("*.wav"))
    fs = s3fs.S3FileSystem(use_listings_cache=False, skip_instance_cache=True)
    files = {}
    for i in range(n):
        source = lj[i % len(lj)]
        for ext in (".wav", ".TextGrid"):
            files[f"bench/corpus/spk{i % 10}/utt{i:05d}{ext}"] = source.with_suffix(ext).read_bytes()
    fs.pipe(files)
    return "s3://bench/corpus"


def discover(url: str, work: Path, whole: bool, concurrency: int, fresh: bool) -> tuple[float, int, int]:
    """Wall seconds of one discovery as `discover_corpus(url)` runs it (the mirror, then discovery in its tree), the
    bytes of local copies it left, the entries found."""
    from visemeflow.ingest.corpus import discover_corpus, named_only
    from visemeflow.location import mirror

    if fresh:
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
    os.environ["TMPDIR"] = str(work)
    tempfile.tempdir = None
    started = time.perf_counter()
    found = discover_corpus(mirror(url, None if whole else named_only, concurrency=concurrency))
    wall = time.perf_counter() - started
    held = sum(p.stat().st_size for p in work.glob("visemeflow-objects-*/**/*") if p.is_file())
    return wall, held, len(found.entries)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--utterances", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--latency-ms", type=float, default=20.0,
                        help="each request held this long on its way to moto, as a bucket's round trip (0: none)")
    args = parser.parse_args()
    from visemeflow.location import FETCH_CONCURRENCY

    work = Path(tempfile.mkdtemp(prefix="visemeflow-s3-discovery-"))
    server, _ = start_s3(work)
    try:
        url = upload_corpus(args.utterances)
        if args.latency_ms > 0:   # the corpus is uploaded directly; discovery goes through the relay
            os.environ["AWS_ENDPOINT_URL"] = start_relay(os.environ["AWS_ENDPOINT_URL"], args.latency_ms / 1000)
        ways = [("whole corpus, one by one (before)", True, 1, True),
                ("text only, one by one", False, 1, True),
                (f"text only, {FETCH_CONCURRENCY} at once (default)", False, FETCH_CONCURRENCY, True),
                ("default again, warm (a rerun)", False, FETCH_CONCURRENCY, False)]
        rows, first = [], None
        for name, whole, concurrency, fresh in ways:
            best, held, n = float("inf"), 0, 0
            for _ in range(args.repeats):
                wall, held, n = discover(url, work / "machine", whole, concurrency, fresh)
                best = min(best, wall)
            first = first or best
            rows.append([name, f"{best:.2f} s", f"{held / 1e6:.1f} MB", f"{first / best:.1f}x", str(n)])
        print(f"discovery of {args.utterances} utterances (wav + TextGrid) on moto S3, {args.latency_ms:g} ms added "
              f"per request, best of {args.repeats}")
        print_grid(["way", "wall", "local copies", "speed-up", "entries"], rows)
    finally:
        server.terminate()
        server.wait(30)
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
