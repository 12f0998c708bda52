"""The Prefect server a bench's flows report to (`prefect_server()`): a throw-away local one by default
(Prefect's `prefect_test_harness` on a copy of the migrated database template, `visemeflow.ops.prefect_db`:
about 10 s of a core to start, 20 s when it has to migrate its own), or the running server that
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
    from visemeflow.ops.prefect_db import test_harness

    with test_harness(startup_timeout_s=startup_timeout):
        yield
