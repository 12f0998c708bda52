"""What the terminal shows: progress lines of long stages (issue 28, item 2) and summaries a person reads (item 6).

The CLI tests run the real `visemeflow` command in a child process on the session's Prefect server.
"""

import io
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from factories import make_corpus, make_curve_store, tiny_model
from visemeflow.tasks.progress import ENV, Progress, duration

REPO = Path(__file__).resolve().parents[1]
PHONES = [("sil", 0.0, 0.2), ("HH", 0.2, 0.3), ("AH0", 0.3, 0.5), ("L", 0.5, 0.6), ("OW1", 0.6, 0.9),
          ("sil", 0.9, 1.0)]
# a float printed with more digits than any of our measures can tell (`9.42157706669109`)
RAW_FLOAT = re.compile(r"\d+\.\d{4,}")


class Clock:
    """A clock the test moves by hand."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def progress(monkeypatch, interval: str, total: int = 4, **kwargs) -> tuple[Progress, io.StringIO, Clock]:
    monkeypatch.setenv(ENV, interval)
    stream, clock = io.StringIO(), Clock()
    return Progress("track", total, stream=stream, clock=clock, heartbeat=False, **kwargs), stream, clock


def test_progress_writes_done_total_rate_and_eta_once_per_interval(monkeypatch):
    line, out, clock = progress(monkeypatch, "10", work_total=400)
    clock.now += 4
    line.advance(work=100)          # before the first interval: nothing yet
    assert out.getvalue() == ""
    clock.now += 6
    line.advance(work=100)          # 10 s: 200 of 400 frames at 20 frames/s, 10 s to go
    assert out.getvalue() == "track: 2/4 utterances, 200 of 400 frames, 20 frames/s, 10 s elapsed, ETA 10 s\n"
    clock.now += 1
    line.advance(work=50, failed=True)   # within the interval: throttled
    assert out.getvalue().count("\n") == 1
    clock.now += 1
    line.advance(work=150)          # the last one: always said once lines were written
    last = out.getvalue().splitlines()[-1]
    assert last == "track: 4/4 utterances (1 failed), 400 of 400 frames, 33 frames/s, 12 s elapsed"
    line.close()
    assert out.getvalue().count("\n") == 2


def test_progress_is_quiet_for_a_fast_stage_says_every_update_at_zero_and_nothing_when_off(monkeypatch):
    line, out, clock = progress(monkeypatch, "10", total=2, unit="shards")
    line.advance()
    line.advance()
    line.close()
    assert out.getvalue() == ""     # a cached rerun prints no progress
    line, out, clock = progress(monkeypatch, "0", total=2, unit="shards")
    clock.now += 3
    line.advance()
    assert out.getvalue() == "track: 1/2 shards, 0.33 shards/s, 3 s elapsed, ETA 3 s\n"
    line, out, clock = progress(monkeypatch, "off")
    clock.now += 1000
    line.advance()
    line.close()
    assert out.getvalue() == ""


def test_a_resumed_training_counts_earlier_epochs_but_rates_only_this_runs(monkeypatch):
    line, out, clock = progress(monkeypatch, "0", total=10, unit="epochs")
    line.resume(6)                  # epochs 1-6 were done by a killed run
    clock.now += 30
    line.advance()
    assert out.getvalue() == "track: 7/10 epochs, 0.03 epochs/s, 30 s elapsed, ETA 1 min 30 s\n"


def test_the_heartbeat_says_a_long_task_is_alive_before_anything_finishes(monkeypatch):
    monkeypatch.setenv(ENV, "0.05")
    out = io.StringIO()
    with Progress("track", 1, stream=out, work_total=130) as line:
        deadline = time.monotonic() + 20
        while "\n" not in out.getvalue() and time.monotonic() < deadline:
            time.sleep(0.01)
        line.advance(work=130)
    first = out.getvalue().splitlines()[0]
    assert re.fullmatch(r"track: 0/1 utterances, 0 of 130 frames, \d+ s elapsed, ETA after the first finishes", first)
    assert out.getvalue().splitlines()[-1].startswith("track: 1/1 utterances, 130 of 130 frames")


def test_a_tasks_step_lines_reach_stderr_where_prefect_hides_info_and_quiet_the_heartbeat(monkeypatch, capsys):
    """`speak --preview` of 2 minutes said only `animate: 0/1 packages, 4 min elapsed, ETA after the first finishes`:
    the preview's frame count went to Prefect's INFO lines, which a command on the temporary server hides."""
    import logging

    from visemeflow.tasks.progress import step_log

    monkeypatch.setenv(ENV, "0")
    shown = logging.getLogger("visemeflow.test.shown")
    shown.setLevel(logging.INFO)
    records: list[str] = []
    monkeypatch.setattr(shown, "info", records.append)
    step_log("animate[a]", shown)("preview", 5, 10)
    assert records == ["animate[a]: preview 5/10 frames, " + records[0].split(", ", 1)[1]]
    assert capsys.readouterr().err == ""                  # on the run's logger only: terminal and UI
    hidden = logging.getLogger("visemeflow.test.hidden")
    hidden.setLevel(logging.WARNING)                      # PREFECT_LOGGING_LEVEL=WARNING
    steps = step_log("animate[a]", hidden)
    steps("preview", 0, 10)
    steps("preview", 4, 10)
    assert re.fullmatch(r"animate\[a\]: preview 4/10 frames, \d+/s, about \d+ s left\n", capsys.readouterr().err)
    out = io.StringIO()                                   # the stage's heartbeat: quiet while a step line is newer
    monkeypatch.setenv(ENV, "0.3")
    with Progress("animate", 1, stream=out, unit="packages") as line:
        deadline = time.monotonic() + 1.2
        while time.monotonic() < deadline:
            steps("preview", 5, 10)
            time.sleep(0.05)
        assert out.getvalue() == ""
        deadline = time.monotonic() + 20
        while "\n" not in out.getvalue() and time.monotonic() < deadline:
            time.sleep(0.01)
        line.advance()
    assert re.match(r"animate: 0/1 packages, \d+ s elapsed, ETA after the first finishes\n", out.getvalue())


def test_durations_read_at_a_glance():
    assert [duration(s) for s in (0.4, 59.6, 61, 3599, 3720)] == ["0 s", "1 min 00 s", "1 min 01 s",
                                                                 "59 min 59 s", "1 h 02 min"]


def test_summaries_round_name_units_omit_none_and_title_the_modes_used(capsys):
    from visemeflow.cli import _print_summary

    _print_summary("track", {"utterances": 2, "variant": "guided-fast", "variants": "unguided-fast",
                             "unguided_why": None, "mean_mouth_error_px": 3.5730416798920666, "guided": False})
    _print_summary("train", {"model": "m", "val_l1_x100": 9.42157706669109, "real_time_factor": 0.001234,
                             "loss": float("nan")})
    assert capsys.readouterr().out.splitlines() == [
        "track (unguided-fast): utterances 2, mean_mouth_error 3.57 px, guided no",
        "train: model m, validation L1 x 100 9.42, real_time_factor 0.001",
    ]


def visemeflow(args: list[str], api_url: str, interval: str = "0", timeout: float = 600) -> subprocess.CompletedProcess:
    env = {**os.environ, "PREFECT_API_URL": api_url, "PREFECT_LOGGING_LEVEL": "WARNING", ENV: interval,
           "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-m", "visemeflow.cli", *args], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=timeout)
    assert done.returncode == 0, done.stdout + done.stderr
    return done


@pytest.mark.flow
def test_pipeline_shows_each_stages_progress_and_a_rounded_summary(tmp_path, prefect_api_url):
    corpus = make_corpus(tmp_path / "corpus", {f"spk/u{i}": PHONES for i in range(6)})   # shards 1 1 1 1 0 0
    done = visemeflow(["pipeline", str(corpus), "--store", str(tmp_path / "store"), "--shards", "2"],
                      prefect_api_url)
    for stage in ("ingest", "procedural"):   # one line per finished shard (interval 0), the last without an ETA
        lines = [line for line in done.stderr.splitlines() if line.startswith(f"{stage}: ")]
        assert len(lines) == 2, done.stderr
        assert re.fullmatch(rf"{stage}: 1/2 shards, [\d.]+ shards/s, \d+ s elapsed, ETA \d+ s", lines[0])
        assert re.fullmatch(rf"{stage}: 2/2 shards, [\d.]+ shards/s, \d+ s elapsed", lines[1])
    assert "procedural: utterances 6, generated 6" in done.stdout
    assert "None" not in done.stdout and not RAW_FLOAT.search(done.stdout), done.stdout
    # quiet by default on a pipe when a stage ends within its first 10 s
    again = visemeflow(["pipeline", str(corpus), "--store", str(tmp_path / "store"), "--shards", "2"],
                       prefect_api_url, interval="")
    assert not re.search(r"(ingest|procedural): \d+/\d+ shards", again.stderr), again.stderr


@pytest.mark.flow
def test_train_and_evaluate_print_rounded_figures_and_label_the_baseline(tmp_path, prefect_api_url):
    store = make_curve_store(tmp_path / "store")
    tiny_model(store, "tiny")
    trained = visemeflow(["train", "--store", str(store.root), "--preset", "mean-curve", "--source", "ground_truth",
                          "--name", "mean"], prefect_api_url)
    summary = trained.stdout.splitlines()
    assert re.fullmatch(r"train: model mean, epochs 1, validation L1 x 100 \d+\.\d\d, training_utterances 4, "
                        r"validation_utterances 2", summary[0]), trained.stdout
    assert summary[1] == f"model: {store.model_path('mean')} (use it with --model mean)"
    done = visemeflow(["evaluate", "--models", "tiny,mean", "--store", str(store.root), "--conditions", "volume",
                       "--source", "ground_truth", "--variant", "cm"], prefect_api_url)
    out = done.stdout
    assert not RAW_FLOAT.search(out) and "None" not in out, out
    rows = {line.split()[0]: line for line in out.splitlines() if line.startswith(("tiny ", "mean "))}
    assert "baseline" in rows["mean"] and "baseline" not in rows["tiny"], out
    assert re.search(r"full table.*robustness\.md", out), out
    assert "evaluate: 2 of 2 models judged, 0 rejected" in out


@pytest.mark.flow
def test_a_command_on_a_temporary_server_sends_its_last_logs_before_the_server_stops(tmp_path):
    """With no Prefect server running, a command starts a temporary one and stops it at exit. The run's last logs
    go out first (Prefect's log worker drains in the threading module's exit callbacks, before the atexit handler
    that stops the server): a cached predict used to end with "Error logging to API / All connection attempts
    failed" on every run."""
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "PREFECT_API_AUTH_STRING")}
    env.update({"PREFECT_HOME": str(tmp_path / "prefect-home"), "OMP_NUM_THREADS": "1", "PREFECT_LOGGING_LEVEL": "INFO"})
    wav = REPO / "examples" / "corpus" / "LJ" / "LJ001-0002.wav"
    for attempt in ("predicted", "cached"):
        done = subprocess.run([sys.executable, "-m", "visemeflow.cli", "predict", str(wav), "--model", "default-fbank",
                               "--store", str(tmp_path / "store")], cwd=REPO, env=env, capture_output=True, text=True,
                              timeout=600)
        assert done.returncode == 0, done.stdout + done.stderr
        assert f"1 file, {int(attempt == 'predicted')} predicted, {int(attempt == 'cached')} cached" in done.stdout
        assert "Error logging to API" not in done.stderr and "connection attempts failed" not in done.stderr, (
            attempt, done.stderr[-2000:])


def test_a_task_rejecting_bad_input_is_one_warning_line_and_a_bug_keeps_its_trace():
    """Prefect logs a failed task run at ERROR with a 30-line traceback. For the errors that name a reject (an
    `error_type`, e.g. LandmarksError: no face) it is one WARNING line, the state line after it too; any other
    error (a bug) keeps its level and its trace."""
    import logging

    import visemeflow.tasks.common  # noqa: F401  (puts the filter on Prefect's task-run logger)
    from visemeflow.tasks.landmarks import LandmarksError

    records = []

    class Keep(logging.Handler):
        def emit(self, record):
            records.append((record.levelname, self.format(record)))

    logger = logging.getLogger("prefect.task_runs")
    handler = Keep()
    logger.addHandler(handler)
    try:
        for error in (LandmarksError("s1/x", "/c/x.mpg", "NoFace", "no face found on any of its 75 frames"),
                      KeyError("bug")):
            try:
                raise error
            except Exception as exc:
                logger.error("Task run failed with exception: %r - Retries are exhausted", exc, exc_info=True)
                logger.error("Finished in state Failed('Task run encountered an exception %s: %s')",
                             type(exc).__name__, exc)
    finally:
        logger.removeHandler(handler)
    (level1, text1), (level2, text2), (level3, text3), (level4, _) = records
    assert (level1, level2) == ("WARNING", "WARNING")
    assert "Traceback" not in text1 and len(text1.splitlines()) == 1 and "no face found" in text1
    assert level3 == level4 == "ERROR" and "Traceback" in text3 and "KeyError" in text3


def test_the_animate_and_speak_summaries_say_what_was_animated_in_words():
    from visemeflow.cli import _animations_line

    animate = {"packages": 3, "written": 2, "cached": 1, "rejected": 0, "frames": 870, "source": "tracked",
               "variant": "guided-fast", "characters": 1}
    assert _animations_line("animate", animate) == (
        "animate: 3 animations of tracked/guided-fast curves on 1 character: 2 animations written, 1 reused from "
        "the store (cached); 870 frames")
    both = {**animate, "variants": "guided-fast: 2, unguided-fast: 1", "characters": 2, "cached": 0, "rejected": 1}
    assert _animations_line("animate", both) == (
        "animate: 3 animations of tracked/guided-fast: 2, unguided-fast: 1 curves on 2 characters: 2 animations "
        "written, 1 rejected; 870 frames")
    speak = {"packages": 1, "written": 1, "cached": 0, "rejected": 0, "frames": 290, "source": "predicted",
             "variant": "default", "characters": 1, "audio_files": 1, "audio_rejected": 0}
    assert _animations_line("speak", speak) == (
        "speak: 1 audio file on 1 character (model default): 1 animation written; 290 frames")


def test_speak_names_the_file_of_each_take_whose_id_has_a_hash(capsys):
    """Two files of one name (a/take.wav, b/take.wav) become predict/take-<hash> each: which one is which."""
    from visemeflow.cli import _print_packages

    def package(uid):
        return {"utterance_id": uid, "character": "head", "convention": "arkit52", "frames": 30, "fps": 30.0,
                "files": {"glb": f"out/{uid}.glb"}}

    speak = {"packages": 3, "written": 3, "frames": 90, "source": "predicted", "variant": "default",
             "characters": 1, "audio_files": 3, "audio_rejected": 0,
             "packages_written": [package("predict/take-1afb83b6"), package("predict/take-8f514164"),
                                  package("predict/hello")],
             "audio_of": {"predict/take-1afb83b6": "a/take.wav", "predict/take-8f514164": "b/take.wav",
                          "predict/hello": "c/hello.wav"}}
    _print_packages(speak, "speak")
    printed = capsys.readouterr().out
    assert "not counted" not in printed   # no lips report: nothing said about the count
    lines = [x for x in printed.splitlines() if " -> " in x]
    assert lines == ["predict/take-1afb83b6 (a/take.wav) -> head [arkit52], 30 frames at 30 fps:",
                     "predict/take-8f514164 (b/take.wav) -> head [arkit52], 30 frames at 30 fps:",
                     "predict/hello -> head [arkit52], 30 frames at 30 fps:"]   # its own name: said by the id
    speak["packages_written"] = [{**package("predict/hello"), "lips": {"mbp_shape_gap_mm": 0.9}},
                                 {**package("predict/take"), "lips": {"bilabials": 4, "closed": 4, "median_gap_mm": 1.1}}]
    _print_packages(speak, "speak")
    out = capsys.readouterr().out
    assert "lips on the mesh: 4 of 4 b/p/m closed below 1.5 mm (median gap 1.1 mm)" in out
    assert "b/p/m closures not counted for 1 package (no phones known): put an alignment (NAME.TextGrid) or an " \
           "English transcript (NAME.txt) beside the audio" in out
