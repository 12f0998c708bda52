"""A reason is said once on a command's terminal, and whole in the Prefect UI (`visemeflow.logs`)."""

import io
import logging
import os
import subprocess
import sys
from pathlib import Path

from factories import REPO
from prefect.logging.handlers import PrefectConsoleHandler

from visemeflow import logs
from visemeflow.logs import SUMMARISED, summary_prints_them
from visemeflow.tasks.common import _RejectsInOneLine


class _Kept(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def test_a_summarised_record_leaves_only_the_console_and_only_while_a_command_prints_it():
    stream = io.StringIO()
    console, api = PrefectConsoleHandler(stream=stream), _Kept()
    logs.keep_summarised_off([console])
    logs.keep_summarised_off([console])   # once is enough: a second call adds no second filter
    assert sum(isinstance(f, logs.SummarisedOffConsole) for f in console.filters) == 1
    logger = logging.getLogger("visemeflow.test_logs")
    logger.propagate = False
    logger.addHandler(console)
    logger.addHandler(api)
    try:
        logger.warning("predict: rejected a.wav", extra=SUMMARISED)   # no command prints it: the console does
        logger.warning("a warning of its own")
        with summary_prints_them():
            logger.warning("predict: rejected b.wav", extra=SUMMARISED)
            logger.warning("kept on the console")
        logger.warning("predict: rejected c.wav", extra=SUMMARISED)   # after the command: shown again
    finally:
        logger.removeHandler(console)
        logger.removeHandler(api)
    shown = stream.getvalue()
    assert "rejected a.wav" in shown and "a warning of its own" in shown and "kept on the console" in shown
    assert "rejected c.wav" in shown and "rejected b.wav" not in shown
    assert api.messages == ["predict: rejected a.wav", "a warning of its own", "predict: rejected b.wav",
                            "kept on the console", "predict: rejected c.wav"]   # the UI's handler gets every line


def test_a_command_that_fails_before_its_summary_gets_the_held_lines_on_the_console_after_all():
    """A stage that ends Failed (or a bug) never prints its rejects list: what was held back is shown as the command
    leaves, at most HELD lines and a count of the rest. An exit after the summary (typer.Exit, SystemExit) shows
    nothing more."""
    import click
    import pytest
    import typer

    stream = io.StringIO()
    console = PrefectConsoleHandler(stream=stream)
    logs.keep_summarised_off([console])
    logger = logging.getLogger("visemeflow.test_logs.failed")
    logger.propagate = False
    logger.addHandler(console)
    try:
        with pytest.raises(typer.Exit), summary_prints_them((SystemExit, typer.Exit, click.exceptions.Exit)):
            logger.warning("rejected a.wav", extra=SUMMARISED)
            raise typer.Exit(1)   # speak's exit 1 after it printed its rejects
        assert "a.wav" not in stream.getvalue()
        with pytest.raises(RuntimeError), summary_prints_them():
            logger.warning("rejected b.wav", extra=SUMMARISED)
            for i in range(logs.HELD + 5):
                logger.warning("rejected c%d.wav", i, extra=SUMMARISED)
            assert "b.wav" not in stream.getvalue()   # held while the command runs
            raise RuntimeError("the stage failed")
    finally:
        logger.removeHandler(console)
    shown = stream.getvalue()
    assert "rejected b.wav" in shown and f"rejected c{logs.HELD - 2}.wav" in shown
    assert f"rejected c{logs.HELD - 1}.wav" not in shown and "and 6 more such lines" in shown
    assert not logs._held and logs._depth == 0


def test_prefects_lines_for_a_task_that_failed_on_bad_input_are_marked_and_a_bug_is_not():
    class AudioError(Exception):
        error_type = "AudioError"

    flt = _RejectsInOneLine()

    def record(level: int, msg: str, error: BaseException | None = None) -> logging.LogRecord:
        return logging.LogRecord("prefect.task_runs", level, __file__, 1, msg, None,
                                 (type(error), error, None) if error else None)

    failed = record(logging.ERROR, "Task run failed with exception: AudioError('x.wav: not audio')",
                    AudioError("x.wav: not audio"))
    finished = record(logging.ERROR, "Finished in state Failed('Task run encountered an exception AudioError: x')")
    bug = record(logging.ERROR, "Task run failed with exception: KeyError('k')", KeyError("k"))
    for r in (failed, finished, bug):
        assert flt.filter(r)
    assert getattr(failed, logs.MARK, False) and getattr(finished, logs.MARK, False)
    assert failed.levelno == finished.levelno == logging.WARNING
    assert not getattr(bug, logs.MARK, False) and bug.levelno == logging.ERROR and bug.exc_info is not None


def test_a_rejected_audio_file_is_named_once_on_the_terminal(tmp_path):
    """Before: Prefect's two task-run lines and the flow's `predict: rejected` line, then the command's own line."""
    bad = tmp_path / "bad.wav"
    bad.write_text("not audio")
    good = REPO / "examples/corpus/LJ/LJ001-0002.wav"
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "PREFECT_API_AUTH_STRING")}
    done = subprocess.run([str(Path(sys.executable).parent / "visemeflow"), "predict", str(bad), str(good),
                           "--model", "phones", "--store", str(tmp_path / "store")], cwd=REPO,
                          env={**env, "COLUMNS": "400"}, capture_output=True, text=True, timeout=300, check=False)
    said = done.stdout + done.stderr
    assert "1 predicted, 0 cached, 1 rejected" in done.stdout, said
    assert said.count("neither soundfile nor FFmpeg reads it as audio") == 1, said
    assert f"rejected {bad}: neither soundfile" in said
