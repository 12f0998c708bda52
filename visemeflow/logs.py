"""Log lines a command prints in its own summary: said once on the terminal, still sent whole to the Prefect UI.

A stage's command ends with its summary and its rejects, one line each (`visemeflow.cli`): the utterance, the file
and the reason. The same facts are also logged while the flow runs, for the Prefect UI and for served runs, whose
log is all there is: Prefect's own two lines for a task that failed on bad input, the stage's `rejected` line and a
package's warnings. On the terminal of a command that prints them anyway, each reason then came three or four times.

A record logged with `extra=SUMMARISED` (or marked so by `tasks.common`'s reject filter) is held back from Prefect's
console handler while `summary_prints_them()` is entered, and nowhere else: the UI's log handler, served runs, tests
and library callers see every line as before. The commands that print their rejects and warnings enter it
(`cli.options.stage_command`); one that ends with an error (a stage that failed, a bug) gets the held-back lines on
the console after all, when it leaves, since its summary was never printed. At most `HELD` lines are kept for that,
and the count of the rest is said. This module imports nothing of Prefect (the commands import it before
`ops.connect` has set Prefect's environment).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from contextlib import contextmanager

MARK = "visemeflow_summarised"
SUMMARISED = {MARK: True}   # `logger.warning(..., extra=SUMMARISED)`: the command's summary prints it too
HELD = 200   # lines kept for a command that fails before its summary

_lock = threading.Lock()
_depth = 0
_held: list[tuple[logging.Handler, logging.LogRecord]] = []
_dropped = 0


@contextmanager
def summary_prints_them(printed: tuple[type[BaseException], ...] = (SystemExit,)) -> Iterator[None]:
    """While entered, records marked SUMMARISED stay off Prefect's console (the caller prints them itself); if the
    block raises anything but `printed` (the exits a command takes after its summary), they are put on the console
    when it is left."""
    global _depth, _dropped
    with _lock:
        _depth += 1
    failed = False
    try:
        yield
    except printed:
        raise
    except BaseException:
        failed = True
        raise
    finally:
        with _lock:
            _depth -= 1
            held, dropped = (list(_held), _dropped) if _depth == 0 else ([], 0)
            if _depth == 0:
                _held.clear()
                _dropped = 0
        if failed:
            for handler, record in held:
                handler.handle(record)
            if dropped:
                handler = held[-1][0] if held else None
                if handler is not None:
                    handler.handle(logging.LogRecord(
                        "visemeflow", logging.WARNING, __file__, 0,
                        "... and %d more such lines (the Prefect UI and `visemeflow rejects` have them all)",
                        (dropped,), None))


def mark(record: logging.LogRecord) -> None:
    setattr(record, MARK, True)


class SummarisedOffConsole(logging.Filter):
    """On a console handler: hold back the records a command's summary prints, while one says so."""

    def __init__(self, handler: logging.Handler) -> None:
        super().__init__()
        self.handler = handler

    def filter(self, record: logging.LogRecord) -> bool:
        global _dropped
        if not (_depth and getattr(record, MARK, False)):
            return True
        with _lock:
            if not _depth:   # the command has just left: show it
                return True
            if len(_held) < HELD:
                _held.append((self.handler, record))
            else:
                _dropped += 1
        return False


def keep_summarised_off(handlers: list[logging.Handler]) -> None:
    """Put one `SummarisedOffConsole` on each of `handlers` that has none."""
    for handler in handlers:
        if not any(isinstance(f, SummarisedOffConsole) for f in handler.filters):
            handler.addFilter(SummarisedOffConsole(handler))
