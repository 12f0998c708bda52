"""The Prefect server a bench's flows report to (`prefect_server()`): a throw-away local one by default
(`prefect_test_harness`, about 20 s of a core to start, mostly its database set-up), or the running server that
`VISEMEFLOW_BENCH_API_URL` names (a `prefect server start` of your own; tests/test_benches.py no longer hands the
benches its session's server: a work-pool test in the same worker then found that server's SQLite locked).
A bench variable rather than PREFECT_API_URL, so that a user's own PREFECT_API_URL (their team's server, Prefect
Cloud) never receives a bench's throw-away runs."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

API_ENV = "VISEMEFLOW_BENCH_API_URL"


@contextlib.contextmanager
def prefect_server(startup_timeout: float = 180) -> Iterator[None]:
    """Inside it, flows run against the server of `VISEMEFLOW_BENCH_API_URL` when set, else a temporary one."""
    url = os.environ.get(API_ENV, "").strip()
    if url:
        from prefect.settings import PREFECT_API_URL, temporary_settings

        with temporary_settings({PREFECT_API_URL: url}):
            yield
        return
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=startup_timeout):
        yield
