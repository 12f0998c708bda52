"""Common mistakes with a corpus (issue 28, item 3): each was a crash or a silent success, each is now one clear
line. A flat folder of wavs or a binary file given as the corpus, an mp3 in a corpus, transcripts without timings,
`--model phones` on audio of any language, and P2FA's `.align` (an HTK MLF whose one entry names a temporary file).
A single audio or video file given as the corpus is a corpus of one utterance. The command-line cases run the real
`visemeflow` command in a child process."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import soundfile as sf

from factories import SHARED_DATA, make_corpus, textgrid_long, write_wav
from visemeflow.ingest import CorpusError, IngestConfig, check_corpus, discover_corpus, ingest_utterance
from visemeflow.ingest.corpus import SINGLE_FILE_SPEAKER, single_file_speaker
from visemeflow.ingest.hints import reject_advice, reject_lines

REPO = Path(__file__).resolve().parents[1]
PHONES = [("", 0.0, 0.1), ("HH", 0.1, 0.2), ("AH0", 0.2, 0.35), ("L", 0.35, 0.45), ("OW1", 0.45, 0.6)]
# P2FA (HVite) output: the pattern names the temporary file it aligned; scores and words after the phone
P2FA_MLF = ('#!MLF!#\n"/tmp/tmpk2x9ab/myl_26185.rec"\n0 1000000 sp -100.5 sp\n1000000 2000000 HH -50.1 HELLO\n'
            "2000000 3500000 AH0 -40.0\n3500000 4500000 L -30.0\n4500000 6000000 OW1 -30.0\n.\n")
GRID_ALIGN = "0 2500 sil\n2500 10000 bin\n10000 15000 blue\n"  # 1/25000 s: 0.6 s


def visemeflow(args: list[str], api_url: str, timeout: float = 600) -> subprocess.CompletedProcess:
    """The real command in a child process on the session's Prefect server; its exit status is the caller's to check."""
    env = {**os.environ, "PREFECT_API_URL": api_url, "PREFECT_LOGGING_LEVEL": "WARNING", "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "visemeflow.cli", *args], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=timeout)


def binary_video(path: Path) -> Path:
    """A file named like a video holding 114 KB of bytes that are not UTF-8 (what the manifest reader used to dump)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x00\x00\x00\x20ftypisom" + np.random.default_rng(0).integers(0, 256, 114_000, np.uint8).tobytes())
    return path


def write_mp3(path: Path, seconds: float, rate: int = 16000) -> Path:
    t = np.arange(int(seconds * rate)) / rate
    sf.write(path, 0.05 * np.sin(2 * np.pi * 220.0 * t), rate, format="MP3")
    return path


# --- the cheap check the command runs before any flow -----------------------------------------------------------

def test_check_corpus_takes_one_media_file_and_names_a_flat_folder_and_what_a_corpus_is(tmp_path):
    assert check_corpus(binary_video(tmp_path / "clip.mp4")) is None  # by its extension: ingest reads it
    assert check_corpus(write_wav(tmp_path / "take.WAV", 0.2)) is None
    blob = tmp_path / "weights.bin"
    blob.write_bytes(b"\x00\x01\xff\xfe" * 100)
    message = check_corpus(blob)
    assert message.startswith(f"{blob} is neither an audio or video file (.wav, ") and "<speaker>/<name>.wav" in message
    assert "\n" not in message
    grid = tmp_path / "take.TextGrid"
    grid.write_text(textgrid_long([(s, e, lab) for lab, s, e in PHONES], 0.6), "utf-8")
    assert check_corpus(grid).startswith(f"{grid} is an alignment file, not a corpus: give its audio or video")

    flat = tmp_path / "flat"
    for name in ("a", "b", "c", "d", "e"):
        write_wav(flat / f"{name}.wav", 0.2)
    message = check_corpus(flat)
    assert message.startswith(f"no utterances in {flat}: 5 audio/video/alignment files (a.wav, b.wav, c.wav and 2 "
                              "more) lie directly in it, not in a speaker folder"), message
    assert "one folder per speaker" in message

    (tmp_path / "empty" / "notes").mkdir(parents=True)
    assert "found 1 folder without audio, video or alignment files" in check_corpus(tmp_path / "empty")
    assert check_corpus(make_corpus(tmp_path / "good", {"spk/a": PHONES})) is None
    write_wav(flat / "speaker1" / "a.wav", 0.2)  # one speaker folder with audio: discovery takes over
    assert check_corpus(flat) is None


def test_binary_and_headerless_manifests_are_one_line_errors_not_decode_dumps(tmp_path):
    blob = binary_video(tmp_path / "clip.mp4").rename(tmp_path / "corpus.csv")
    message = check_corpus(blob)
    assert message.startswith(f"{blob} is not a manifest CSV (it is not UTF-8 text)")
    with pytest.raises(CorpusError) as caught:
        discover_corpus(blob)
    assert "not a manifest CSV" in str(caught.value) and len(str(caught.value)) < 600

    headerless = tmp_path / "list.csv"
    headerless.write_text("spk/a,spk/a.wav,spk/a.TextGrid\n", encoding="utf-8")
    assert "has no utterance_id column" in check_corpus(headerless)
    # an audio column misspelt: one line before any flow (it was 168 lines of tracebacks from inside the ingest run)
    misspelt = tmp_path / "typo" / "manifest.csv"
    misspelt.parent.mkdir()
    misspelt.write_text("utterance_id,audo,alignment\nspk/a,a.wav,a.TextGrid\n", encoding="utf-8")
    for given in (misspelt, misspelt.parent):
        assert check_corpus(given).startswith(f"manifest {misspelt}: no audio or video column (its columns: "
                                              "utterance_id, audo, alignment; expected utterance_id, audio")

    # text at first, bytes that are not UTF-8 further on: discovery's own error, never the bytes
    late = tmp_path / "late" / "manifest.csv"
    late.parent.mkdir()
    late.write_bytes(b"utterance_id,audio,alignment\n" + b"spk/a,a.wav,a.TextGrid\n" * 600 + b"spk/\xff\xfe,x,y\n")
    assert check_corpus(late.parent) is None  # the first 8 KB are a manifest
    with pytest.raises(CorpusError, match=r"not UTF-8 text at byte \d+"):
        discover_corpus(late.parent)


def test_one_audio_or_video_file_is_a_corpus_of_one_utterance_with_what_lies_beside_it(tmp_path):
    corpus = make_corpus(tmp_path / "corpus", {"Speaker One/hello": PHONES, "Speaker One/other": PHONES})
    found = discover_corpus(corpus / "Speaker One" / "hello.wav")
    assert not found.rejects and [e.utterance_id for e in found.entries] == ["Speaker One/hello"]
    assert found.entries[0].alignment_path == str((corpus / "Speaker One" / "hello.TextGrid").resolve())
    assert discover_corpus(corpus / "Speaker One" / "hello.wav", only="Speaker One/hello").entries == found.entries
    assert discover_corpus(corpus / "Speaker One" / "hello.wav", only="Speaker One/other").entries == ()

    folder = tmp_path / "takes"
    write_mp3(write_wav(folder / "a.wav", 0.3).with_suffix(".mp3"), 0.3)  # the named file wins over a.wav
    (folder / "a.txt").write_text("hello\n", encoding="utf-8")                 # a transcript: ingest aligns it
    (folder / "a.landmarks.csv").write_text("frame\n", encoding="utf-8")
    (entry,) = discover_corpus(folder / "a.mp3").entries
    assert entry.utterance_id == "takes/a" and entry.audio_path.endswith("a.mp3")
    assert entry.alignment_format == "transcript" and entry.landmark_path.endswith("a.landmarks.csv")
    binary_video(folder / "v.MP4")
    write_wav(folder / "v.wav", 0.3)  # the audio beside a video, which has no alignment: tracked unguided
    (entry,) = discover_corpus(folder / "v.MP4").entries
    assert (entry.audio_path.endswith("v.wav"), entry.video_path.endswith("v.MP4"), entry.alignment_format) == (
        True, True, "none")
    (reject,) = discover_corpus(write_wav(folder / "lone.wav", 0.3)).rejects
    assert reject.error_type == "MissingAlignment" and str((folder / "lone.wav").resolve()) in reject.message
    assert (reject.utterance_id, reject.path) == ("takes/lone", str((folder / "lone.wav").resolve()))
    assert [single_file_speaker(n) for n in ("", ".cache", "a\nb", "Speaker One")] == [SINGLE_FILE_SPEAKER] * 3 + [
        "Speaker One"]
    (reject,) = discover_corpus(write_wav(folder / ".hidden.wav", 0.3)).rejects
    assert reject.error_type == "InvalidId" and ".hidden.wav" in reject.message


# --- every format `speak` reads --------------------------------------------------------------------------------

def test_an_mp3_beside_its_textgrid_is_ingested(tmp_path):
    corpus = tmp_path / "corpus"
    make_corpus(corpus, {"spk/hello": PHONES})
    (corpus / "spk" / "hello.wav").unlink()
    write_mp3(corpus / "spk" / "hello.mp3", 0.6)
    found = discover_corpus(corpus)
    assert not found.rejects, found.rejects
    (entry,) = found.entries
    assert entry.audio_path.endswith("hello.mp3")
    row = ingest_utterance(entry, IngestConfig()).utterance
    assert row["sample_rate"] == 16000 and abs(row["duration_s"] - 0.6) < 0.06


# --- P2FA: a label file beside its audio is that audio's ---------------------------------------------------------

def test_p2fa_align_holding_an_mlf_of_a_temporary_file_belongs_to_the_audio_beside_it(tmp_path):
    corpus = tmp_path / "corpus"
    write_wav(corpus / "spk" / "hello.wav", 0.6)
    (corpus / "spk" / "hello.align").write_text(P2FA_MLF, encoding="utf-8")
    write_wav(corpus / "grid" / "bbaf2n.wav", 0.6)
    (corpus / "grid" / "bbaf2n.align").write_text(GRID_ALIGN, encoding="utf-8")  # word spans stay word spans
    write_wav(corpus / "mlf" / "take.wav", 0.6)
    (corpus / "mlf" / "take.mlf").write_text(P2FA_MLF, encoding="utf-8")  # NAME.mlf beside NAME.wav, same rule
    found = discover_corpus(corpus)
    assert not found.rejects, found.rejects
    entries = {e.utterance_id: e for e in found.entries}
    assert {uid: e.alignment_format for uid, e in entries.items()} == {
        "spk/hello": "mlf", "grid/bbaf2n": "word_align", "mlf/take": "mlf"}
    for uid in ("spk/hello", "mlf/take"):
        phones = ingest_utterance(entries[uid], IngestConfig()).phones
        assert [p["label"] for p in phones][:2] == ["sp", "HH"] and phones[1]["word"] == "HELLO"
        assert abs(phones[-1]["end_s"] - 0.6) < 1e-6

    # the same file named in a manifest
    (corpus / "manifest.csv").write_text("utterance_id,audio,alignment\nspk/hello,spk/hello.wav,spk/hello.align\n",
                                         encoding="utf-8")
    (entry,) = discover_corpus(corpus).entries
    assert entry.alignment_format == "mlf" and len(ingest_utterance(entry, IngestConfig()).phones) == 5


def test_an_align_holding_a_textgrid_is_read_as_one_and_a_shared_mlf_still_needs_its_entry(tmp_path):
    corpus = tmp_path / "corpus"
    write_wav(corpus / "spk" / "a.wav", 0.6)
    (corpus / "spk" / "a.align").write_text(textgrid_long([(s, e, lab) for lab, s, e in PHONES], 0.6), "utf-8")
    write_wav(corpus / "spk" / "b.wav", 0.6)
    two = P2FA_MLF + '"/tmp/tmpzz/other.rec"\n0 6000000 sil\n.\n'  # two entries, neither for b: ambiguous
    (corpus / "spk" / "b.align").write_text(two, encoding="utf-8")
    found = discover_corpus(corpus)
    (entry,) = found.entries
    assert entry.utterance_id == "spk/a" and entry.alignment_format == "textgrid"
    assert len(ingest_utterance(entry, IngestConfig()).phones) == 5
    (reject,) = found.rejects
    assert reject.error_type == "BadAlignmentFile" and "2 entries and none for spk/b" in reject.message


# --- rejects on the terminal ------------------------------------------------------------------------------------

def test_reject_lines_name_utterance_file_and_reason_and_advise_an_aligner():
    rows = [{"stage": "discover", "error_type": "MissingAlignment", "utterance_id": f"spk/u{i}", "path": f"/c/u{i}.wav",
             "message": f"spk/u{i}: no alignment for /c/u{i}.wav: no .TextGrid file beside it (u{i}.lab is a "
                        "transcript without times, not an alignment)"} for i in range(7)]
    rows.append({"stage": "ingest", "error_type": "UnknownPhoneme", "utterance_id": "spk/x", "path": "/c/x.TextGrid",
                 "message": "line one\nline two"})
    lines = reject_lines(rows[::-1])
    assert lines[0] == "  [ingest] UnknownPhoneme: spk/x: line one (/c/x.TextGrid)"
    assert lines[1].startswith("  [discover] MissingAlignment: spk/u6: no alignment for /c/u6.wav")
    assert lines[-1] == "  ... and 3 more" and len(lines) == 6
    (advice,) = reject_advice(rows)
    assert "transcripts without times" in advice and "Montreal Forced Aligner" in advice and "speak" in advice
    assert reject_advice(rows[-1:]) == []


# --- the real command ---------------------------------------------------------------------------------------------

@pytest.mark.flow
def test_pipeline_on_a_binary_file_or_a_flat_folder_says_what_a_corpus_is(tmp_path, prefect_api_url):
    blob = binary_video(tmp_path / "clip.mp4").rename(tmp_path / "clip.bin")  # neither media nor a manifest
    done = visemeflow(["pipeline", str(blob), "--store", str(tmp_path / "store")], prefect_api_url)
    output = done.stdout + done.stderr
    assert done.returncode == 2 and done.stdout == "", output
    (line,) = done.stderr.splitlines()  # one line, before Prefect starts: no store either
    assert line.startswith(f"error: {blob} is neither an audio or video file") and "<speaker>/<name>.wav" in line
    assert not (tmp_path / "store").exists()

    flat = tmp_path / "flat"
    for name in ("a", "b", "c"):
        write_wav(flat / f"{name}.wav", 0.3)
    done = visemeflow(["pipeline", str(flat), "--store", str(tmp_path / "store2")], prefect_api_url)
    assert done.returncode != 0, done.stdout + done.stderr
    assert f"no utterances in {flat}: 3 audio/video/alignment files (a.wav, b.wav, c.wav)" in done.stderr
    assert "all 0 utterances done" not in done.stdout + done.stderr


@pytest.mark.flow
def test_pipeline_and_ingest_take_one_audio_or_video_file_as_a_corpus_of_one(tmp_path, prefect_api_url):
    corpus = make_corpus(tmp_path / "corpus", {"alice/hello": PHONES, "alice/other": PHONES})
    store = tmp_path / "store"
    done = visemeflow(["pipeline", str(corpus / "alice" / "hello.wav"), "--store", str(store)], prefect_api_url)
    assert done.returncode == 0, done.stdout + done.stderr
    (row,) = pq.read_table(store / "tables" / "utterances").to_pylist()  # hello alone, not the folder
    assert row["utterance_id"] == "alice/hello" and row["alignment_format"] == "textgrid"
    phones = pq.read_table(store / "tables" / "phones").to_pylist()
    assert [p["label"] for p in phones] == [p[0] for p in PHONES]
    # the folder holds hello too: it may follow; then hello alone again would drop `other`: it stops and says so
    done = visemeflow(["ingest", str(corpus), "--store", str(store)], prefect_api_url)
    assert done.returncode == 0, done.stdout + done.stderr
    for command in ("pipeline", "ingest"):   # one line, exit 2, before any flow (no Prefect log, no `failed:`)
        done = visemeflow([command, str(corpus / "alice" / "hello.wav"), "--store", str(store)], prefect_api_url)
        assert done.returncode == 2 and done.stdout == "", done.stdout + done.stderr
        (line,) = done.stderr.splitlines()
        assert line.startswith(f"error: {store} was ingested from {corpus}; {corpus / 'alice' / 'hello.wav'} lacks 1 "
                               f"of its utterances (alice/other), which this ingest would drop") and "--replace" in line
    # a flow run from a deployment or the UI (no command before it) refuses the same way and stops the pipeline there
    from visemeflow.flows.params import PipelineParams
    from visemeflow.flows.pipeline import pipeline_flow

    state = pipeline_flow(PipelineParams(corpus=corpus / "alice" / "hello.wav", store=store), return_state=True)
    assert state.is_failed() and "which this ingest would drop" in state.message
    assert sorted(r["utterance_id"] for r in pq.read_table(store / "tables" / "utterances").to_pylist()) == [
        "alice/hello", "alice/other"]
    done = visemeflow(["ingest", str(corpus / "alice" / "hello.wav"), "--store", str(store), "--replace"],
                      prefect_api_url)
    assert done.returncode == 0, done.stdout + done.stderr
    assert [r["utterance_id"] for r in pq.read_table(store / "tables" / "utterances").to_pylist()] == ["alice/hello"]

    clip = tmp_path / "s1" / "bbaf2n.MPG"  # a real GRID clip alone: no alignment, tracked unguided
    clip.parent.mkdir()
    shutil.copyfile(SHARED_DATA / "grid_s1" / "video" / "bbaf2n.mpg", clip)
    done = visemeflow(["ingest", str(clip), "--store", str(tmp_path / "videos")], prefect_api_url)
    assert done.returncode == 0, done.stdout + done.stderr
    (row,) = pq.read_table(tmp_path / "videos" / "tables" / "utterances").to_pylist()
    assert (row["utterance_id"], row["video_path"], row["alignment_format"]) == ("s1/bbaf2n", str(clip.resolve()), "none")
    assert row["n_frames"] == 75

    lone = write_wav(tmp_path / "loose" / "take.wav", 0.4).resolve()  # nothing to align it: a reject naming it, not a crash
    done = visemeflow(["ingest", str(lone), "--store", str(tmp_path / "lone")], prefect_api_url)
    assert done.returncode == 1, done.stdout + done.stderr
    assert "its one utterance failed" in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert f"MissingAlignment: loose/take: no alignment for {lone}" in done.stderr and "Montreal" in done.stderr
    assert "for English speech, put its words in <name>.txt" in done.stderr   # the route without an aligner
    (reject,) = pq.read_table(tmp_path / "lone" / "tables" / "rejects").to_pylist()
    assert (reject["utterance_id"], reject["error_type"], reject["path"]) == ("loose/take", "MissingAlignment",
                                                                              str(lone))


@pytest.mark.flow
def test_ingest_reads_mp3_and_p2fa_and_prints_the_first_rejects_with_what_to_do(tmp_path, prefect_api_url):
    corpus = make_corpus(tmp_path / "corpus", {"spk/good": PHONES})
    write_mp3(corpus / "spk" / "song.mp3", 0.6)
    (corpus / "spk" / "song.TextGrid").write_text(textgrid_long([(s, e, lab) for lab, s, e in PHONES], 0.6), "utf-8")
    write_wav(corpus / "p2fa" / "hello.wav", 0.6)
    (corpus / "p2fa" / "hello.align").write_text(P2FA_MLF, encoding="utf-8")
    for name in ("t1", "t2"):  # transcripts (MFA's input), no timings, in a language the built-in aligner lacks
        write_wav(corpus / "spk" / f"{name}.wav", 0.6)
        (corpus / "spk" / f"{name}.lab").write_text("你好世界\n", encoding="utf-8")
    store = tmp_path / "store"
    done = visemeflow(["ingest", str(corpus), "--store", str(store), "--shards", "1"], prefect_api_url)
    assert done.returncode == 0, done.stdout + done.stderr
    rows = {r["utterance_id"]: r for r in pq.read_table(store / "tables" / "utterances").to_pylist()}
    assert sorted(rows) == ["p2fa/hello", "spk/good", "spk/song"], done.stdout
    assert rows["spk/song"]["audio_path"].endswith("song.mp3") and rows["p2fa/hello"]["alignment_format"] == "mlf"
    out = done.stdout
    assert "2 rejected:" in out, out
    for name in ("t1", "t2"):
        line = next(x for x in out.splitlines() if f"spk/{name}:" in x)
        assert "TranscriptNotAligned" in line and str(corpus / "spk" / f"{name}.lab") in line
        assert "no English pronunciation for '你好世界'" in line
    assert "hint: English transcripts beside their audio" in out and "Montreal Forced Aligner" in out
    assert "`visemeflow speak` / `visemeflow predict`" in out and f"visemeflow rejects --store {store}" in out
    # each reject on the terminal once, in the command's list at the end (its task's line is INFO, which the
    # temporary server hides and the UI keeps); the flow's count line goes to the UI only, since the command says
    # the count itself (it lists them itself when the run ends Failed, below)
    both = done.stdout + done.stderr
    for name in ("t1", "t2"):
        assert both.count(str(corpus / "spk" / f"{name}.lab")) == 1, both
    assert "rejected 2" in done.stdout and "ingest: 2 of 5 rejected" not in both, both

    # every utterance rejected: the run fails, and the reasons and the hint are still on the terminal
    only = tmp_path / "only"
    for name in ("t1", "t2"):
        write_wav(only / "spk" / f"{name}.wav", 0.6)
        (only / "spk" / f"{name}.lab").write_text("你好世界\n", encoding="utf-8")
    done = visemeflow(["ingest", str(only), "--store", str(tmp_path / "store2")], prefect_api_url)
    assert done.returncode == 1, done.stdout + done.stderr
    assert "TranscriptNotAligned: spk/t1:" in done.stderr and "Montreal Forced Aligner" in done.stderr, done.stderr


@pytest.mark.flow
def test_predict_with_the_phone_recogniser_warns_that_it_knows_english_only(tmp_path, prefect_api_url):
    audio = write_wav(tmp_path / "ni_hao.wav", 0.5)
    done = visemeflow(["predict", str(audio), "--model", "phones", "--store", str(tmp_path / "store")],
                      prefect_api_url)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stderr.count("the phone recogniser (pocketsphinx) knows English only") == 1, done.stderr
    assert "--model default" in done.stderr


def test_evaluating_the_phone_recogniser_on_mandarin_warns_naming_the_language(tmp_path):
    from visemeflow.flows.evaluate import _warn_phones_language
    from visemeflow.schemas import UTTERANCES, C, table_from_rows
    from visemeflow.storage import Store

    def row(uid: str, language: str | None) -> dict:
        return {C.UTTERANCE_ID: uid, C.SPEAKER: uid.split("/")[0], C.LANGUAGE: language, C.AUDIO_PATH: "a.wav",
                C.ALIGNMENT_PATH: "", C.ALIGNMENT_FORMAT: "none", C.SAMPLE_RATE: 16000, C.DURATION_S: 1.0,
                C.FPS: 30.0, C.N_FRAMES: 30, C.CONTENT_HASH: "h", C.SPLIT: "val"}

    class Logger:
        def __init__(self):
            self.warnings: list[str] = []

        def warning(self, message: str, *args) -> None:
            self.warnings.append(message % args)

    store = Store(tmp_path / "store")
    store.write_shard("utterances", 0, table_from_rows(
        [row("zh/a", "zh-CN"), row("zh/b", "zh-CN"), row("en/c", "en_US"), row("x/d", None)], UTTERANCES))
    logger = Logger()
    _warn_phones_language(store, [{C.UTTERANCE_ID: u} for u in ("zh/a", "zh/b", "en/c", "x/d")], logger)
    (warning,) = logger.warnings
    assert "knows English only, but 2 validation utterances are in zh-CN" in warning
    english = Logger()
    _warn_phones_language(store, [{C.UTTERANCE_ID: "en/c"}, {C.UTTERANCE_ID: "x/d"}], english)
    assert english.warnings == []


def test_upper_case_extensions_are_found_as_recorders_and_windows_tools_write_them(tmp_path):
    corpus = tmp_path / "corpus"
    write_wav(corpus / "spk" / "TAKE01.WAV", 0.6)
    (corpus / "spk" / "TAKE01.TEXTGRID").write_text(textgrid_long([(s, e, lab) for lab, s, e in PHONES], 0.6),
                                                    encoding="utf-8")
    write_wav(corpus / "spk" / "take02.Wav", 0.6)
    (corpus / "spk" / "take02.Lab").write_text("0 1000000 sil\n1000000 6000000 AA1\n", encoding="utf-8")
    assert check_corpus(corpus) is None
    found = discover_corpus(corpus)
    assert found.rejects == ()
    by_id = {e.utterance_id: e for e in found.entries}
    assert sorted(by_id) == ["spk/TAKE01", "spk/take02"]
    assert by_id["spk/TAKE01"].alignment_format == "textgrid" and by_id["spk/take02"].alignment_format == "htk"
    assert [p["label"] for p in ingest_utterance(by_id["spk/TAKE01"], IngestConfig()).phones] == [p[0] for p in PHONES]
    assert by_id["spk/take02"].audio_path.endswith("take02.Wav")


def test_media_a_folder_too_deep_is_a_reject_naming_the_folder_and_appledouble_files_are_not_media(tmp_path):
    """A studio folder of speakers inside the corpus (corpus/studioA/dave/d1.wav) was left out without a word, and
    the `._take.wav` metadata files macOS writes on foreign disks were each an InvalidId reject (a new user's
    report). The deep folder is now one NestedFolder reject saying what a corpus is; AppleDouble files are skipped."""
    corpus = tmp_path / "corpus"
    grid = textgrid_long([(s, e, lab) for lab, s, e in PHONES], 0.6)
    write_wav(corpus / "spk" / "a.wav", 0.6)
    (corpus / "spk" / "a.TextGrid").write_text(grid, encoding="utf-8")
    (corpus / "spk" / "._a.wav").write_bytes(b"\x00\x05\x16\x07" + bytes(60))       # AppleDouble
    for name in ("dave", "erin"):
        write_wav(corpus / "studioA" / name / f"{name}1.wav", 0.6)
        (corpus / "studioA" / name / f"{name}1.TextGrid").write_text(grid, encoding="utf-8")
    (corpus / "spk" / "notes").mkdir()
    (corpus / "spk" / "notes" / "readme.txt").write_text("no media here", encoding="utf-8")
    found = discover_corpus(corpus)
    assert [e.utterance_id for e in found.entries] == ["spk/a"]
    assert [(r.error_type, Path(r.path).name) for r in found.rejects] == [("NestedFolder", "dave"),
                                                                          ("NestedFolder", "erin")]
    assert found.rejects[0].message == (
        f"{corpus / 'studioA' / 'dave'}: 1 audio or video file two folders deep, left out (e.g. dave1.wav); a corpus "
        f"is SPEAKER/UTTERANCE files: point visemeflow at {corpus / 'studioA'} if its folders are the speakers, or "
        "move the files up a level")
    assert [e.utterance_id for e in discover_corpus(corpus, only="spk/a").entries] == ["spk/a"]


def test_two_audio_files_of_one_name_are_read_by_rank_and_the_one_left_out_is_named(tmp_path, caplog):
    """`take.wav` beside `take.flac` (a re-export, or another take): the wav ranks higher and is read, as before;
    now the flac left out is named in a discovery note that the ingest run logs as a warning (it was silent). So
    is an HTK .lab beside a TextGrid. A file the user names (`ingest take.flac`) is that utterance's audio, no note."""
    from visemeflow.tasks.ingest import discover_corpus_task

    corpus = tmp_path / "corpus"
    grid = textgrid_long([(s, e, lab) for lab, s, e in PHONES], 0.6)
    write_wav(corpus / "spk" / "take.wav", 0.6)
    write_wav(corpus / "spk" / "take.flac", 0.6)
    (corpus / "spk" / "take.TextGrid").write_text(grid, encoding="utf-8")
    write_wav(corpus / "spk" / "other.wav", 0.6)
    (corpus / "spk" / "other.TextGrid").write_text(grid, encoding="utf-8")
    (corpus / "spk" / "other.lab").write_text("0 1000000 sil\n1000000 6000000 AA1\n", encoding="utf-8")
    write_wav(corpus / "spk" / "alone.wav", 0.6)
    (corpus / "spk" / "alone.TextGrid").write_text(grid, encoding="utf-8")
    found = discover_corpus(corpus)
    by_id = {e.utterance_id: e for e in found.entries}
    assert sorted(by_id) == ["spk/alone", "spk/other", "spk/take"] and found.rejects == ()
    assert by_id["spk/take"].audio_path.endswith("take.wav") and by_id["spk/other"].alignment_format == "textgrid"
    assert found.notes == (
        "spk/other: other.TextGrid is its alignment; other.lab beside it left out (an alignment file of the same "
        "name ranks lower: rename it if it is another take)",
        "spk/take: take.wav is its audio; take.flac beside it left out (an audio file of the same name ranks lower: "
        "rename it if it is another take)")
    with caplog.at_level("WARNING"):
        returned = discover_corpus_task.fn(str(corpus))
    assert returned["notes"] == list(found.notes)
    assert "discover: spk/take: take.wav is its audio; take.flac beside it left out" in caplog.text
    assert discover_corpus(corpus / "spk" / "take.flac").notes == ()
    assert discover_corpus(corpus / "spk" / "take.flac").entries[0].audio_path.endswith("take.flac")
