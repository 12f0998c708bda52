"""A progress line on the terminal for the stages that take minutes: done/total, rate, ETA, on stderr.

Prefect's progress artifact shows a stage's progress in the UI, but a user running `visemeflow pipeline` in a
terminal saw nothing for minutes while one video was tracked. `Progress` writes plain lines to stderr (no cursor
tricks: they interleave with Prefect's log lines and land whole in a CI log or a file), throttled to one every
`interval` seconds, plus a heartbeat from a daemon thread while nothing finishes, so a long single task still says
it is alive and for how long. Lines are written from the process that waits for the tasks (the flow's loop over
finished futures), so they reach the terminal whether the tasks run in Prefect's thread pool or on Dask workers.

`VISEMEFLOW_PROGRESS_SECONDS` sets the interval (default 2 s on a terminal, 10 s otherwise; 0 writes a line per
update; `off` writes none).
"""

import logging
import math
import os
import sys
import threading
import time
from collections.abc import Callable
from typing import TextIO

ENV = "VISEMEFLOW_PROGRESS_SECONDS"
TTY_SECONDS = 2.0
PIPE_SECONDS = 10.0


def interval_seconds(stream: TextIO | None) -> float | None:
    """Seconds between lines: the environment's, else by whether `stream` is a terminal (None: not one); None when
    turned off."""
    value = os.environ.get(ENV, "").strip().lower()
    if value in ("off", "no", "false", "none"):
        return None
    if value:
        try:
            return max(0.0, float(value))
        except ValueError:
            pass  # a typo must not stop a run: the default applies
    if stream is None:
        return PIPE_SECONDS
    try:
        tty = stream.isatty()
    except (AttributeError, ValueError):
        tty = False
    return TTY_SECONDS if tty else PIPE_SECONDS


def duration(seconds: float) -> str:
    """`42 s`, `3 min 05 s`, `1 h 02 min`: what a person reads at a glance."""
    seconds = max(0, int(round(seconds)))
    if seconds < 60:
        return f"{seconds} s"
    if seconds < 3600:
        return f"{seconds // 60} min {seconds % 60:02d} s"
    return f"{seconds // 3600} h {seconds % 3600 // 60:02d} min"


class Progress:
    """Progress of one stage over `total` items (utterances, packages), with optional work units (frames) whose
    total is known up front: the rate and ETA then come from work done, which is fairer when items differ in length.

    Call `advance(work=...)` per finished item and `close()` at the end (or use it as a context manager). Nothing
    is written for a stage that ends before its first interval (a cached rerun stays quiet), except with an
    interval of 0.
    """

    def __init__(self, stage: str, total: int, unit: str = "utterances", work_total: float | None = None,
                 work_unit: str = "frames", stream: TextIO | None = None,
                 clock: Callable[[], float] = time.monotonic, heartbeat: bool = True):
        self.stage, self.total, self.unit = stage, total, unit
        self.work_total = work_total if work_total and work_total > 0 else None
        self.work_unit = work_unit
        self.stream = stream if stream is not None else sys.stderr
        self.clock = clock
        self.interval = interval_seconds(self.stream)
        self.done, self.work_done, self.failed = 0, 0.0, 0
        self.resumed = 0  # items done by an earlier run (a resumed training): not in the rate
        self.started = self.last = clock()
        self.written = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if heartbeat and self.interval and total > 0:
            self._thread = threading.Thread(target=self._beat, name=f"progress[{stage}]", daemon=True)
            self._thread.start()

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def line(self) -> str:
        """The current line, e.g. `track: 3/10 utterances (1 failed), 412 of 1370 frames, 9.5 frames/s, 1 min 40 s
        elapsed, ETA 1 min 41 s`."""
        elapsed = self.clock() - self.started
        parts = [f"{self.stage}: {self.done}/{self.total} {self.unit}" + (f" ({self.failed} failed)" if self.failed
                                                                         else "")]
        if self.work_total is not None:
            parts.append(f"{self.work_done:,.0f} of {self.work_total:,.0f} {self.work_unit}")
        done, total, unit = ((self.work_done, self.work_total, self.work_unit) if self.work_total is not None
                             else (self.done - self.resumed, self.total - self.resumed, self.unit))
        rate = done / elapsed if elapsed > 0 else math.nan
        if done and math.isfinite(rate):
            parts.append(f"{rate:.2f} {unit}/s" if rate < 10 else f"{rate:.0f} {unit}/s")
        parts.append(f"{duration(elapsed)} elapsed")
        if self.done < self.total:  # items, not work: a failed utterance's frames are done too, untracked
            parts.append(f"ETA {duration(max(0.0, total - done) / rate)}" if done and rate > 0
                         else "ETA after the first finishes")
        return ", ".join(parts)

    def advance(self, n: int = 1, work: float = 0.0, failed: bool = False) -> None:
        """Count `n` finished items (`work` units of them); write a line if the interval has passed."""
        with self._lock:
            self.done += n
            self.work_done += work
            self.failed += int(failed)
            if self.interval is None:
                return
            now = self.clock()
            last_item = self.done >= self.total
            if self.interval == 0 or now - self.last >= self.interval or (last_item and self.written):
                self._write(now)

    def resume(self, done: int) -> None:
        """Items an earlier run already did (a training resumed at its last epoch): counted, but not in the rate."""
        with self._lock:
            self.done = self.resumed = max(self.done, done)

    def close(self) -> None:
        """Stop the heartbeat; a last line if earlier lines were written and the last one is stale."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
        with self._lock:
            if self.interval is not None and self.written and self.last < self.clock() and self.done < self.total:
                self._write(self.clock())

    def _write(self, now: float) -> None:
        self.last = now
        self.written += 1
        try:
            self.stream.write(self.line() + "\n")
            self.stream.flush()
        except (OSError, ValueError):  # a closed pipe must not fail the stage
            pass

    def _beat(self) -> None:
        assert self.interval
        while not self._stop.wait(min(self.interval, 1.0)):
            with self._lock:
                now = self.clock()
                stepped = time.monotonic() - _STEP_LINE_AT[0] < self.interval   # a task said where it is meanwhile
                if self.done < self.total and now - self.last >= self.interval and not stepped:
                    self._write(now)


_STEP_LINE_AT = [-math.inf]
"""When (time.monotonic) a task's step line was last written to this process's stderr: `Progress`'s heartbeat
("0/1 packages, 3 s elapsed") is left out while a step line newer than its interval says more."""


class StepLog:
    """Progress inside one long task (the phases of tracking one video) as log lines: `track[uid]: optical flow
    120/250 frames, 35/s, about 4 s left`, at most one every `interval` seconds per task (`VISEMEFLOW_PROGRESS_SECONDS`
    as for `Progress`, default 10 s: these go through Prefect's logger, to the terminal and the UI, from any worker).
    A phase's first step is not logged; nothing is written for a task that ends within its first interval."""

    def __init__(self, name: str, log: Callable[[str], None], interval: float | None = None,
                 clock: Callable[[], float] = time.monotonic):
        self.name, self.log, self.clock = name, log, clock
        if interval is None:   # the environment's, else PIPE_SECONDS: log lines have no terminal of their own
            interval = interval_seconds(None)
        self.interval = math.inf if interval is None else interval
        self.started = self.last = clock()
        self.phase, self.phase_started = None, self.started

    def __call__(self, phase: str, done: int, total: int) -> None:
        now = self.clock()
        if phase != self.phase:
            self.phase, self.phase_started = phase, now
        if done <= 0 or now - self.last < self.interval or now - self.started < self.interval:
            return
        self.last = now
        rate = done / max(now - self.phase_started, 1e-9)
        unit = "frames" if phase in ("optical flow", "preview") else "steps"
        left = f", about {duration((total - done) / rate)} left" if total > done and rate > 0 else ""
        self.log(f"{self.name}: {phase} {done}/{total} {unit}, {rate:.0f}/s{left}")


def step_log(name: str, logger) -> StepLog:
    """`StepLog` lines on `logger` (a run's logger: the terminal and the UI) where it shows INFO lines; else on stderr
    at a terminal's pace: a command on Prefect's temporary server hides INFO lines (`ops.connect`), and a 4-minute
    preview or a long clip's tracking then said nothing but "0/1 packages, 3 min elapsed"."""
    if logger.isEnabledFor(logging.INFO):
        return StepLog(name, logger.info)

    def to_stderr(line: str) -> None:
        _STEP_LINE_AT[0] = time.monotonic()
        try:
            sys.stderr.write(line + "\n")
            sys.stderr.flush()
        except (OSError, ValueError):  # a closed pipe must not fail the task
            pass

    interval = interval_seconds(sys.stderr)
    return StepLog(name, to_stderr, math.inf if interval is None else interval)
