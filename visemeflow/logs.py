"""Log lines a command prints in its own summary: said once on the terminal, still sent whole to the Prefect UI.

A stage's command ends with its summary and its rejects, one line each (`visemeflow.cli`): the utterance, the file
and the reason. The same facts are also logged while the flow runs, for the Prefect UI and for served runs, whose
log is all there is: Prefect's own two lines for a task that failed on bad input, the stage's `rejected` line and a
package's warnings. On the terminal of a command that prints them anyway, each reason then came three or four times.

A record logged with `extra=SUMMARISED` (or marked so by `tasks.common`'s reject filter) is left off Prefect's
console handler while `summary_prints_them()` is entered, and nowhere else: the UI's log handler, served runs, tests
and library callers see every line as before. This module imports nothing of Prefect (the commands import it before
`ops.connect` has set Prefect's environment).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from contextlib import contextmanager

MARK = "visemeflow_summarised"
SUMMARISED = {MARK: True}   # `logger.warning(..., extra=SUMMARISED)`: the command's summary prints it too

_lock = threading.Lock()
_depth = 0


@contextmanager
def summary_prints_them() -> Iterator[None]:
    """While entered, records marked SUMMARISED stay off Prefect's console (the caller prints them itself)."""
    global _depth
    with _lock:
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1


def mark(record: logging.LogRecord) -> None:
    setattr(record, MARK, True)


class SummarisedOffConsole(logging.Filter):
    """On a console handler: drop the records a command's summary prints, while one says so."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not (_depth and getattr(record, MARK, False))


def keep_summarised_off(handlers: list[logging.Handler]) -> None:
    """Put one `SummarisedOffConsole` on each of `handlers` that has none."""
    for handler in handlers:
        if not any(isinstance(f, SummarisedOffConsole) for f in handler.filters):
            handler.addFilter(SummarisedOffConsole())
