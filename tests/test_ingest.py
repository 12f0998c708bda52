"""Corpus discovery and per-utterance ingestion, on built corpora, bad inputs and the shared real data."""

import csv
import math
import os
import pickle
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from factories import make_corpus, textgrid_long, textgrid_short, two_frames_apart, write_wav
from visemeflow.ingest import CorpusEntry, DiscoveryReject, IngestConfig, IngestError, discover_corpus, ingest_utterance
from visemeflow.phonetics.textgrid import TextGridError, decode_textgrid_bytes, parse_textgrid
from visemeflow.schemas import PHONES, UTTERANCES, C, table_from_rows
from visemeflow.visemes import VISEMES

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
CONFIG = IngestConfig()

HELLO = [("sil", 0.0, 0.2), ("HH", 0.2, 0.3), ("AH0", 0.3, 0.45), ("L", 0.45, 0.55), ("OW1", 0.55, 0.8), ("", 0.8, 1.0)]


def entry_of(corpus: Path, utterance_id: str) -> CorpusEntry:
    found = discover_corpus(corpus, only=utterance_id)
    assert not found.rejects, found.rejects
    (entry,) = found.entries
    return entry


def write_manifest(path: Path, rows: list[dict[str, str]]) -> Path:
    columns = ["utterance_id", "audio", "alignment", "video", "landmarks", "language", "split"]
    with open(path, "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns)
        writer.writeheader()
        for row in rows:
            writer.writerow({c: row.get(c, "") for c in columns})
    return path


def assert_names(exc: IngestError, utterance_id: str, path: Path) -> str:
    message = str(exc)
    assert utterance_id in message and str(path) in message, message
    assert exc.utterance_id == utterance_id and exc.path == str(path)
    return message


# ---- discovery ---------------------------------------------------------------------------------

def test_discover_folder_layout(tmp_path):
    make_corpus(tmp_path, {"spk1/a": HELLO, "spk1/b": HELLO, "spk2/a": HELLO})
    (tmp_path / "spk1" / "a.mp4").write_bytes(b"video")
    (tmp_path / "spk1" / "a.landmarks.csv").write_text("frame,time_s\n")
    (tmp_path / "spk1" / "notes.txt").write_text("ignored")
    (tmp_path / ".hidden").mkdir()
    write_wav(tmp_path / ".hidden" / "x.wav", 0.1)
    found = discover_corpus(tmp_path)
    assert found.rejects == ()
    assert [e.utterance_id for e in found.entries] == ["spk1/a", "spk1/b", "spk2/a"]
    a = found.entries[0]
    assert a.speaker == "spk1" and a.alignment_format == "textgrid"
    assert a.audio_path == str((tmp_path / "spk1" / "a.wav").resolve())
    assert a.alignment_path == str((tmp_path / "spk1" / "a.TextGrid").resolve())
    assert a.video_path == str((tmp_path / "spk1" / "a.mp4").resolve())
    assert a.landmark_path == str((tmp_path / "spk1" / "a.landmarks.csv").resolve())
    assert found.entries[1].video_path is None and found.entries[1].landmark_path is None
    assert all(len(e.content_hash) == 32 for e in found.entries)
    # identical files give identical hashes, whatever the id
    assert found.entries[1].content_hash == found.entries[2].content_hash
    assert a.content_hash != found.entries[1].content_hash  # a has a video


def test_discover_manifest(tmp_path):
    make_corpus(tmp_path / "files", {"s/one": HELLO, "s/two": HELLO})
    rows = [
        {"utterance_id": "spkA/u1", "audio": "files/s/one.wav", "alignment": "files/s/one.TextGrid",
         "language": "en", "split": "val"},
        {"utterance_id": "spkB/u2", "audio": "files/s/two.wav", "alignment": "files/s/two.TextGrid",
         "video": "files/s/two.wav"},
    ]
    manifest = write_manifest(tmp_path / "list.csv", rows)
    found = discover_corpus(manifest)
    assert found.rejects == ()
    u1, u2 = found.entries
    assert (u1.utterance_id, u1.speaker, u1.language, u1.split) == ("spkA/u1", "spkA", "en", "val")
    assert u1.audio_path == str((tmp_path / "files" / "s" / "one.wav").resolve())
    assert (u2.language, u2.split, u2.video_path) == (None, None, str((tmp_path / "files/s/two.wav").resolve()))
    # a corpus folder holding manifest.csv is read through the manifest, not the folder layout
    shutil.copy(manifest, tmp_path / "manifest.csv")
    assert [e.utterance_id for e in discover_corpus(tmp_path).entries] == ["spkA/u1", "spkB/u2"]
    assert discover_corpus(tmp_path, only="spkB/u2").entries == (u2,)
    # the manifest's language and split reach the utterance row
    row = ingest_utterance(u1, CONFIG).utterance
    assert row[C.LANGUAGE] == "en" and row[C.SPLIT] == "val" and row[C.SPEAKER] == "spkA"


def test_manifest_rejects_duplicates_and_missing_files(tmp_path):
    make_corpus(tmp_path, {"s/one": HELLO})
    manifest = write_manifest(tmp_path / "m.csv", [
        {"utterance_id": "s/one", "audio": "s/one.wav", "alignment": "s/one.TextGrid"},
        {"utterance_id": "s/one", "audio": "s/one.wav", "alignment": "s/one.TextGrid"},
        {"utterance_id": "s/two", "audio": "s/two.wav", "alignment": "s/one.TextGrid"},
        {"utterance_id": "s/three", "audio": "s/one.wav", "alignment": ""},
    ])
    found = discover_corpus(manifest)
    assert [e.utterance_id for e in found.entries] == ["s/one"]
    assert [(r.utterance_id, r.error_type) for r in found.rejects] == [
        ("s/one", "DuplicateId"), ("s/two", "MissingAudio"), ("s/three", "MissingInput")]
    assert str(manifest) in found.rejects[0].message and ":3:" in found.rejects[0].message
    assert found.rejects[1].path == str((tmp_path / "s" / "two.wav").resolve())


def test_manifest_split_and_language_are_checked_naming_the_line(tmp_path):
    """`split` is train or val (training takes every split but val: a `test` row would be trained on); `language`
    is a language tag (`en`, `zh-CN`, `cmn`), not free text that the inventory choice would silently ignore."""
    make_corpus(tmp_path, {"s/one": HELLO})
    good = {"audio": "s/one.wav", "alignment": "s/one.TextGrid"}
    manifest = write_manifest(tmp_path / "m.csv", [
        {"utterance_id": "s/a", **good, "split": "train", "language": "en"},
        {"utterance_id": "s/b", **good, "split": "test"},
        {"utterance_id": "s/c", **good, "language": "English; DROP TABLE"},
        {"utterance_id": "s/d", **good, "split": "Val", "language": "zh-CN"},
        {"utterance_id": "s/e", **good, "language": "x" * 200},
        {"utterance_id": "s/f", **good, "language": "cmn_Hans"},
    ])
    found = discover_corpus(manifest)
    assert [(e.utterance_id, e.split, e.language) for e in found.entries] == [
        ("s/a", "train", "en"), ("s/d", "val", "zh-CN"), ("s/f", None, "cmn_Hans")]
    assert [(r.utterance_id, r.error_type) for r in found.rejects] == [
        ("s/b", "BadSplit"), ("s/c", "BadLanguage"), ("s/e", "BadLanguage")]
    split, language, long = found.rejects
    assert split.message.startswith(f"{manifest}:3: s/b: split 'test'") and "train, val" in split.message
    assert language.message.startswith(f"{manifest}:4: s/c: language 'English; DROP TABLE'")
    assert "en, zh-CN" in language.message and len(long.message) < 400
    assert {r.path for r in found.rejects} == {str(manifest)}


def test_manifest_without_required_columns(tmp_path):
    (tmp_path / "m.csv").write_text("id,wav\nx/y,y.wav\n")
    with pytest.raises(ValueError, match="alignment"):
        discover_corpus(tmp_path / "m.csv")


def test_missing_corpus_and_invalid_only(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere"):
        discover_corpus(tmp_path / "nowhere")
    make_corpus(tmp_path, {"s/a": HELLO})
    with pytest.raises(ValueError, match=r"\.\./a"):
        discover_corpus(tmp_path, only="../a")


def test_content_hash_changes_with_the_files_only(tmp_path):
    make_corpus(tmp_path, {"s/a": HELLO, "s/b": HELLO})
    (tmp_path / "s" / "b.mp4").write_bytes(b"\x00" * 64)
    before = {e.utterance_id: e.content_hash for e in discover_corpus(tmp_path).entries}
    assert before == {e.utterance_id: e.content_hash for e in discover_corpus(tmp_path).entries}
    os.utime(tmp_path / "s" / "a.wav", (1, 1))  # a touch alone changes nothing
    assert discover_corpus(tmp_path).entries[0].content_hash == before["s/a"]

    tg = tmp_path / "s" / "a.TextGrid"
    tg.write_text(tg.read_text().replace('"HH"', '"HH "'))
    after = {e.utterance_id: e.content_hash for e in discover_corpus(tmp_path).entries}
    assert after["s/a"] != before["s/a"] and after["s/b"] == before["s/b"]

    write_wav(tmp_path / "s" / "b.wav", 1.01)
    after2 = {e.utterance_id: e.content_hash for e in discover_corpus(tmp_path).entries}
    assert after2["s/b"] != after["s/b"] and after2["s/a"] == after["s/a"]

    (tmp_path / "s" / "b.mp4").write_bytes(b"\x01" + b"\x00" * 63)
    assert discover_corpus(tmp_path, only="s/b").entries[0].content_hash != after2["s/b"]


def test_only_finds_just_one_utterance(tmp_path):
    make_corpus(tmp_path, {"s/a": HELLO, "s/ab": HELLO, "s/a.b": HELLO, "t/a": HELLO})
    (tmp_path / "s" / "b.wav").write_bytes(b"broken, no alignment either")
    for uid in ("s/a", "s/ab", "s/a.b", "t/a"):
        found = discover_corpus(tmp_path, only=uid)
        assert [e.utterance_id for e in found.entries] == [uid] and found.rejects == ()
        assert found.entries[0].audio_path.endswith(uid + ".wav")
    assert discover_corpus(tmp_path, only="s/zz").entries == ()
    assert discover_corpus(tmp_path, only="u/a").entries == ()
    # the one utterance's hash is the hash a full discovery gives
    full = {e.utterance_id: e.content_hash for e in discover_corpus(tmp_path).entries}
    assert discover_corpus(tmp_path, only="s/ab").entries[0].content_hash == full["s/ab"]


# ---- ingestion of good input ----------------------------------------------------------------------

def test_ingest_rows_fit_the_schemas(tmp_path):
    make_corpus(tmp_path, {"spk/hello": HELLO}, duration=1.02, rate=22050)
    result = ingest_utterance(entry_of(tmp_path, "spk/hello"), IngestConfig(fps=25))
    u = result.utterance
    assert (u[C.SAMPLE_RATE], u[C.FPS], u[C.N_FRAMES], u[C.INVENTORY], u[C.LANGUAGE]) == (22050, 25, 26, "arpabet", "en")
    assert u[C.DURATION_S] == pytest.approx(1.02, abs=1e-4)
    assert u[C.SPLIT] in ("train", "val") and u[C.ALIGNMENT_FORMAT] == "textgrid"
    assert [p[C.PHONEME] for p in result.phones] == [None, "HH", "AH", "L", "OW", None]
    assert [p[C.STRESS] for p in result.phones] == [None, None, 0, None, 1, None]
    assert result.phones[0][C.VISEME] is None and result.phones[-1][C.VISEME] is None
    assert all(p[C.VISEME] in VISEMES for p in result.phones[1:-1])
    assert [p[C.INDEX] for p in result.phones] == list(range(6))
    table_from_rows([u], UTTERANCES)
    table_from_rows(result.phones, PHONES)


def test_words_are_attached_to_phones(tmp_path):
    phones = [(0.0, 0.2, ""), (0.2, 0.3, "HH"), (0.3, 0.5, "AY1"), (0.5, 0.6, "")]
    words = [(0.0, 0.2, ""), (0.2, 0.5, "hi"), (0.5, 0.6, "")]
    (tmp_path / "s").mkdir()
    write_wav(tmp_path / "s" / "hi.wav", 0.6)
    (tmp_path / "s" / "hi.TextGrid").write_text(textgrid_short(phones, 0.6, words=words))
    rows = ingest_utterance(entry_of(tmp_path, "s/hi"), CONFIG).phones
    assert [(r[C.WORD], r[C.WORD_INDEX]) for r in rows] == [(None, None), ("hi", 0), ("hi", 0), (None, None)]


def test_alignment_within_tolerance_is_accepted(tmp_path):
    make_corpus(tmp_path, {"s/a": HELLO}, duration=1.08)
    assert ingest_utterance(entry_of(tmp_path, "s/a"), CONFIG).utterance[C.DURATION_S] == pytest.approx(1.08)


# ---- one test per bad-input class ------------------------------------------------------------------

def test_broken_textgrid(tmp_path):
    make_corpus(tmp_path, {"s/cut": HELLO})
    tg = tmp_path / "s" / "cut.TextGrid"
    tg.write_text(tg.read_text()[:300])
    entry = entry_of(tmp_path, "s/cut")
    with pytest.raises(IngestError) as info:
        ingest_utterance(entry, CONFIG)
    assert_names(info.value, "s/cut", tg.resolve())
    assert info.value.error_type == "TextGridError"
    assert "ends early" in str(info.value) and "not a number" not in str(info.value)
    # a value the format skips (`xmin = oops`) just before the cut: named, since it is why the values ran out
    rows = tg.read_text().splitlines()
    line = max(n for n, row in enumerate(rows, 1) if row.strip().startswith("xmin = "))
    rows[line - 1] = rows[line - 1].split("=")[0] + "= oops"
    tg.write_text("\n".join(rows) + "\n")
    with pytest.raises(IngestError, match=rf"ends early, expected .* \(line {line}, 'xmin = oops': not a number"):
        ingest_utterance(entry_of(tmp_path, "s/cut"), CONFIG)


def test_missing_phone_tier(tmp_path):
    make_corpus(tmp_path, {"s/tiers": HELLO}, fmt="short", tier="segments")
    tg = tmp_path / "s" / "tiers.TextGrid"
    with pytest.raises(IngestError) as info:
        ingest_utterance(entry_of(tmp_path, "s/tiers"), CONFIG)
    message = assert_names(info.value, "s/tiers", tg.resolve())
    assert info.value.error_type == "MissingPhoneTier"
    assert "'segments'" in message and "phones" in message
    assert "if tier 'segments' holds the phones, name it: --phone-tier segments" in message   # never re-aligned
    # the same file is fine when the tier name is configured
    ok = ingest_utterance(entry_of(tmp_path, "s/tiers"), IngestConfig(phone_tiers=("SEGMENTS",)))
    assert len(ok.phones) == len(HELLO)


def test_unknown_phoneme(tmp_path):
    make_corpus(tmp_path, {"s/unk": HELLO[:3] + [("QX7", 0.45, 0.55)] + HELLO[4:]})
    tg = tmp_path / "s" / "unk.TextGrid"
    with pytest.raises(IngestError) as info:
        ingest_utterance(entry_of(tmp_path, "s/unk"), CONFIG)
    message = assert_names(info.value, "s/unk", tg.resolve())
    assert info.value.error_type == "UnknownPhoneme"
    assert "'QX7'" in message and "0.450" in message


def test_an_alignment_file_too_large_to_be_one_is_refused_before_it_is_parsed(tmp_path, monkeypatch):
    """An alignment bigger than `MAX_ALIGNMENT_BYTES` (parsing holds about 5 times a file) is a reject naming the
    utterance and file, read no further; one below it ingests (the limit lowered here, so the files stay small)."""
    import visemeflow.ingest.utterance as ingest_utterance_module
    import visemeflow.phonetics.textgrid as textgrid_module
    from visemeflow.phonetics.textgrid import read_textgrid

    make_corpus(tmp_path, {"s/long": HELLO, "s/short": HELLO})
    grid = tmp_path / "s" / "long.TextGrid"
    limit = grid.stat().st_size + 10
    monkeypatch.setattr(textgrid_module, "MAX_ALIGNMENT_BYTES", limit)
    monkeypatch.setattr(ingest_utterance_module, "MAX_ALIGNMENT_BYTES", limit)
    grid.write_bytes(grid.read_bytes() + b" " * 20)
    with pytest.raises(IngestError) as info:
        ingest_utterance(entry_of(tmp_path, "s/long"), CONFIG)
    message = assert_names(info.value, "s/long", grid.resolve())
    assert info.value.error_type == "AlignmentTooLarge" and f"more than the {limit} an alignment file may have" in \
        message, message
    ingest_utterance(entry_of(tmp_path, "s/short"), CONFIG)          # below the limit: read
    with pytest.raises(TextGridError, match=rf"long\.TextGrid: {limit + 10} bytes, more than the {limit}"):
        read_textgrid(grid)


def test_corrupt_audio(tmp_path):
    make_corpus(tmp_path, {"s/noise": HELLO})
    wav = tmp_path / "s" / "noise.wav"
    wav.write_bytes(b"RIFF" + bytes(range(256)) * 8)
    with pytest.raises(IngestError) as info:
        ingest_utterance(entry_of(tmp_path, "s/noise"), CONFIG)
    assert_names(info.value, "s/noise", wav.resolve())
    assert info.value.error_type == "UnreadableAudio"


def test_empty_audio_says_the_file_is_empty(tmp_path):
    """A 0-byte wav (a recorder stopped before writing, a failed copy) gave two decoders' errors ("Format not
    recognised.; as a video: ... [Errno 1094995529] Invalid data ..."); it says the file is empty."""
    make_corpus(tmp_path, {"s/empty": HELLO})
    wav = tmp_path / "s" / "empty.wav"
    wav.write_bytes(b"")
    with pytest.raises(IngestError) as info:
        ingest_utterance(entry_of(tmp_path, "s/empty"), CONFIG)
    assert_names(info.value, "s/empty", wav.resolve())
    assert info.value.error_type == "EmptyAudio" and "the file is empty (0 bytes)" in str(info.value)


def test_nan_time(tmp_path):
    make_corpus(tmp_path, {"s/nan": HELLO})
    tg = tmp_path / "s" / "nan.TextGrid"
    tg.write_text(tg.read_text().replace("xmax = 0.45 ", "xmax = nan ", 1))
    with pytest.raises(IngestError) as info:
        ingest_utterance(entry_of(tmp_path, "s/nan"), CONFIG)
    message = assert_names(info.value, "s/nan", tg.resolve())
    assert info.value.error_type == "NonFiniteTime"
    assert "interval 3" in message and "'AH0'" in message


def test_overlapping_intervals(tmp_path):
    overlapping = [("sil", 0.0, 0.2), ("HH", 0.2, 0.35), ("AH0", 0.3, 0.45), ("", 0.45, 1.0)]
    make_corpus(tmp_path, {"s/over": overlapping})
    tg = tmp_path / "s" / "over.TextGrid"
    with pytest.raises(IngestError) as info:
        ingest_utterance(entry_of(tmp_path, "s/over"), CONFIG)
    message = assert_names(info.value, "s/over", tg.resolve())
    assert info.value.error_type == "OverlappingIntervals"
    assert "interval 3" in message and "'AH0'" in message


def test_interval_ending_before_it_starts(tmp_path):
    backwards = [("sil", 0.0, 0.2), ("HH", 0.3, 0.2), ("AH0", 0.3, 0.45), ("", 0.45, 1.0)]
    make_corpus(tmp_path, {"s/back": backwards})
    tg = tmp_path / "s" / "back.TextGrid"
    with pytest.raises(IngestError) as info:
        ingest_utterance(entry_of(tmp_path, "s/back"), CONFIG)
    message = assert_names(info.value, "s/back", tg.resolve())
    assert info.value.error_type == "NegativeDuration"
    assert "interval 2" in message and "'HH'" in message


def test_negative_start_times_are_rejects_naming_the_interval(tmp_path):
    """A phone starting at -500 s (a TextGrid whose xmin is -500, an HTK label in seconds) is no time in the audio."""
    negative = [(-500.0, 0.2, "sil"), (0.2, 0.3, "HH"), (0.3, 1.0, "AH0")]
    write_wav(tmp_path / "s" / "tg.wav", 1.0)
    (tmp_path / "s" / "tg.TextGrid").write_text(textgrid_long(negative, 1.0, xmin=-500.0), encoding="utf-8")
    write_wav(tmp_path / "s" / "lab.wav", 1.0)
    (tmp_path / "s" / "lab.lab").write_text("".join(f"{a:.6f} {b:.6f} {x}\n" for a, b, x in negative))
    for uid, name in (("s/tg", "tg.TextGrid"), ("s/lab", "lab.lab")):
        with pytest.raises(IngestError) as info:
            ingest_utterance(entry_of(tmp_path, uid), CONFIG)
        message = assert_names(info.value, uid, (tmp_path / "s" / name).resolve())
        assert info.value.error_type == "NegativeTime"
        assert "interval 1" in message and "'sil'" in message and "-500.000 s" in message
    (tmp_path / "s" / "lab.lab").write_text("0.000000 0.200000 sil\n0.200000 1.000000 AH0\n")
    assert ingest_utterance(entry_of(tmp_path, "s/lab"), CONFIG).phones


def test_alignment_longer_than_audio(tmp_path):
    make_corpus(tmp_path, {"s/long": HELLO}, duration=0.7)
    tg, wav = tmp_path / "s" / "long.TextGrid", tmp_path / "s" / "long.wav"
    with pytest.raises(IngestError) as info:
        ingest_utterance(entry_of(tmp_path, "s/long"), CONFIG)
    message = assert_names(info.value, "s/long", tg.resolve())
    assert info.value.error_type == "AlignmentAudioMismatch"
    assert str(wav.resolve()) in message and "1.000" in message and "0.700" in message
    # a looser tolerance accepts it
    ingest_utterance(entry_of(tmp_path, "s/long"), IngestConfig(alignment_tolerance_s=0.5))


def test_manifest_path_outside_corpus(tmp_path):
    make_corpus(tmp_path / "outside", {"s/a": HELLO})
    root = tmp_path / "corpus"
    make_corpus(root, {"s/a": HELLO})
    manifest = write_manifest(root / "manifest.csv", [
        {"utterance_id": "s/a", "audio": "s/a.wav", "alignment": "s/a.TextGrid"},
        {"utterance_id": "s/x", "audio": "../x.wav", "alignment": "s/a.TextGrid"},
        {"utterance_id": "s/y", "audio": "s/a.wav", "alignment": "../outside/s/a.TextGrid"},
        {"utterance_id": "s/z", "audio": str((tmp_path / "outside" / "s" / "a.wav").resolve()),
         "alignment": "s/a.TextGrid"},
    ])
    write_wav(tmp_path / "x.wav", 1.0)
    found = discover_corpus(root)
    assert [e.utterance_id for e in found.entries] == ["s/a"]
    assert all(isinstance(r, DiscoveryReject) and r.error_type == "PathOutsideCorpus" for r in found.rejects)
    assert [r.utterance_id for r in found.rejects] == ["s/x", "s/y", "s/z"]
    x = found.rejects[0]
    assert "s/x" in x.message and "../x.wav" in x.message and str(manifest) in x.message
    assert x.path == "../x.wav"


def test_invalid_utterance_id(tmp_path):
    make_corpus(tmp_path, {"good/a": HELLO})
    bad = tmp_path / "bad\\speaker"  # a backslash: a path separator on Windows
    bad.mkdir()
    write_wav(bad / "a.wav", 1.0)
    write_wav(bad / "a.flac", 1.0)   # outranked by the wav, and left out with it all the same
    (bad / "a.TextGrid").write_text(textgrid_long([(0.0, 1.0, "AA1")], 1.0))
    found = discover_corpus(tmp_path)
    assert [e.utterance_id for e in found.entries] == ["good/a"]
    (reject,) = found.rejects
    assert reject.error_type == "InvalidId"
    assert "bad\\\\speaker/a" in reject.message and "backslash" in reject.message
    assert reject.path.startswith(str(bad)) and reject.path in reject.message
    # both of its files are named: the wav is left out with the TextGrid, not silently
    assert str(bad / "a.wav") in reject.message and str(bad / "a.TextGrid") in reject.message
    assert str(bad / "a.flac") in reject.message
    assert "left out with it" in reject.message
    # in a manifest too
    manifest = write_manifest(tmp_path / "m.csv", [{"utterance_id": "a/b/c", "audio": "good/a.wav",
                                                     "alignment": "good/a.TextGrid"}])
    (reject,) = discover_corpus(manifest).rejects
    assert reject.error_type == "InvalidId" and "a/b/c" in reject.message and str(manifest) in reject.message


def test_wav_without_textgrid(tmp_path):
    make_corpus(tmp_path, {"s/a": HELLO})
    write_wav(tmp_path / "s" / "lonely.wav", 0.5)
    (tmp_path / "s" / "orphan.TextGrid").write_text(textgrid_long([(0.0, 1.0, "AA1")], 1.0))
    found = discover_corpus(tmp_path)
    assert [e.utterance_id for e in found.entries] == ["s/a"]
    by_id = {r.utterance_id: r for r in found.rejects}
    lonely = by_id["s/lonely"]
    assert lonely.error_type == "MissingAlignment"
    assert "s/lonely" in lonely.message and str(tmp_path / "s" / "lonely.wav") in lonely.message
    assert by_id["s/orphan"].error_type == "MissingAudio"


def test_ingest_error_survives_pickling(tmp_path):
    make_corpus(tmp_path, {"s/long": HELLO}, duration=0.5)
    with pytest.raises(IngestError) as info:
        ingest_utterance(entry_of(tmp_path, "s/long"), CONFIG)
    copy = pickle.loads(pickle.dumps(info.value))
    assert (copy.utterance_id, copy.path, copy.error_type, copy.reason, str(copy)) == (
        info.value.utterance_id, info.value.path, info.value.error_type, info.value.reason, str(info.value))


def test_config_is_validated():
    with pytest.raises(ValidationError):
        IngestConfig(alignment_tolerance_s=-1)
    with pytest.raises(ValidationError):
        IngestConfig(phone_tier="phones")
    with pytest.raises(ValidationError):
        IngestConfig(inventory="klingon")


# ---- real data -----------------------------------------------------------------------------------

def ingest_all(corpus: Path, config: IngestConfig = CONFIG) -> dict[str, object]:
    found = discover_corpus(corpus)
    assert found.rejects == (), found.rejects
    return {e.utterance_id: ingest_utterance(e, config) for e in found.entries}


def check_phone_rows(result) -> None:
    rows = result.phones
    assert rows, result.utterance
    for a, b in zip(rows, rows[1:]):
        assert (a[C.INDEX], a[C.PART]) < (b[C.INDEX], b[C.PART])
        assert a[C.END_S] <= b[C.START_S] + 1e-9
    assert all(r[C.VISEME] is None or r[C.VISEME] in VISEMES for r in rows)
    assert rows[-1][C.END_S] <= result.utterance[C.DURATION_S] + CONFIG.alignment_tolerance_s
    table_from_rows(rows, PHONES)
    table_from_rows([result.utterance], UTTERANCES)


def test_ljspeech_mfa_via_manifest(tmp_path):
    src = DATA / "ljspeech_mfa"
    grids = sorted((src / "TextGrid").glob("*.TextGrid"))
    assert len(grids) == 24, f"shared data missing under {src}"
    rows = []
    for tg in grids:
        for sub, path in (("align", tg), ("audio", src / "wav" / f"{tg.stem}.wav")):
            (tmp_path / sub).mkdir(exist_ok=True)
            shutil.copy(path, tmp_path / sub / path.name)
        rows.append({"utterance_id": f"LJ/{tg.stem}", "audio": f"audio/{tg.stem}.wav",
                     "alignment": f"align/{tg.name}", "language": "en"})
    write_manifest(tmp_path / "manifest.csv", rows)
    results = ingest_all(tmp_path)
    assert len(results) == 24
    for result in results.values():
        u = result.utterance
        assert (u[C.INVENTORY], u[C.SAMPLE_RATE], u[C.LANGUAGE]) == ("arpabet", 22050, "en")
        check_phone_rows(result)
        spoken = [r for r in result.phones if r[C.VISEME] is not None]
        assert len(spoken) > 5 and all(r[C.WORD] for r in spoken)


def copy_charsiu(root: Path) -> Path:
    src = DATA / "charsiu_mandarin"
    (root / "SSB1624").mkdir(parents=True)
    shutil.copy(src / "SSB16240001_16k.wav", root / "SSB1624" / "SSB16240001.wav")
    shutil.copy(src / "SSB16240001.TextGrid", root / "SSB1624" / "SSB16240001.TextGrid")
    return root


def check_compound_final(result, alignment_path: str) -> None:
    items = parse_textgrid(decode_textgrid_bytes(Path(alignment_path).read_bytes())).tier(("phones",)).items
    index = [x[2] for x in items].index("ing2")
    start, end = items[index][:2]
    parts = [r for r in result.phones if r[C.LABEL] == "ing2"]
    assert [(r[C.INDEX], r[C.PART]) for r in parts] == [(index, 0), (index, 1)]
    assert [r[C.VISEME] for r in parts] == ["IEE", "GK"]
    assert {r[C.PHONEME] for r in parts} == {"ing"} and {r[C.STRESS] for r in parts} == {2}
    assert parts[0][C.START_S] == start and parts[-1][C.END_S] == end
    assert parts[0][C.END_S] == parts[1][C.START_S]
    assert start < parts[0][C.END_S] < end


def test_charsiu_mandarin(tmp_path):
    (result,) = ingest_all(copy_charsiu(tmp_path)).values()
    assert result.utterance[C.INVENTORY] == "pinyin" and result.utterance[C.LANGUAGE] == "zh"
    check_phone_rows(result)
    check_compound_final(result, result.utterance[C.ALIGNMENT_PATH])


GRID_CLIPS = ("bwbg8n", "lrik4p", "sbwo1s")


def test_grid_word_alignments(tmp_path):
    for clip in GRID_CLIPS:
        src = DATA / "grid_s1" / "align" / f"{clip}.align"
        assert src.is_file(), f"shared data missing: {src}"
        (tmp_path / "s1").mkdir(exist_ok=True)
        shutil.copy(src, tmp_path / "s1" / src.name)
        write_wav(tmp_path / "s1" / f"{clip}.wav", 2.98, rate=16000)
    results = ingest_all(tmp_path)
    assert sorted(results) == sorted(f"s1/{c}" for c in GRID_CLIPS)
    for uid, result in results.items():
        u = result.utterance
        assert (u[C.INVENTORY], u[C.LANGUAGE], u[C.ALIGNMENT_FORMAT]) == ("arpabet", "en", "word_align")
        check_phone_rows(result)
        assert result.phones[0][C.LABEL] == "sil" and result.phones[0][C.VISEME] is None
        assert math.isclose(result.phones[-1][C.END_S], 2.98)
        spoken = [r for r in result.phones if r[C.LABEL] != "sil"]
        assert all(r[C.VISEME] in VISEMES and r[C.WORD] for r in spoken)
    bin_rows = [r for r in results["s1/bwbg8n"].phones if r[C.WORD] == "bin"]
    assert [r[C.LABEL] for r in bin_rows] == ["B", "IH1", "N"]
    assert [r[C.VISEME] for r in bin_rows] == ["MBP", "IEE", "LNTD"]
    assert bin_rows[0][C.START_S] == pytest.approx(17250 / 25000) and bin_rows[-1][C.END_S] == pytest.approx(23000 / 25000)
    assert {r[C.WORD_INDEX] for r in bin_rows} == {0}


def test_grid_unknown_word(tmp_path):
    (tmp_path / "s1").mkdir()
    align = tmp_path / "s1" / "odd.align"
    align.write_text("0 25000 sil\n25000 50000 blorfquux\n50000 74500 sil\n")
    write_wav(tmp_path / "s1" / "odd.wav", 2.98)
    with pytest.raises(IngestError) as info:
        ingest_utterance(entry_of(tmp_path, "s1/odd"), CONFIG)
    message = assert_names(info.value, "s1/odd", align.resolve())
    assert info.value.error_type == "WordAlignmentError" and "blorfquux" in message


def test_shipped_demo_corpus():
    corpus = REPO / "examples" / "corpus"
    results = ingest_all(corpus)
    assert len(results) == 25
    assert {r.utterance[C.INVENTORY] for r in results.values()} == {"arpabet", "pinyin"}
    for result in results.values():
        check_phone_rows(result)
    mandarin = results["SSB1624/SSB16240001"]
    check_compound_final(mandarin, mandarin.utterance[C.ALIGNMENT_PATH])


def test_every_shared_textgrid_reads_and_maps_with_no_unknown_symbol():
    """Every TextGrid under ../shared/data with a phone tier: our reader, detected inventory, no unknown label."""
    from visemeflow.phonetics.inventory import detect_inventory, map_phone

    grids = sorted(DATA.rglob("*.TextGrid"))
    assert len(grids) >= 27, f"expected the shared TextGrids under {DATA}, found {len(grids)}"
    with_phones = 0
    for path in grids:
        grid = parse_textgrid(decode_textgrid_bytes(path.read_bytes()), str(path))
        tier = grid.tier(CONFIG.phone_tiers)
        if tier is None:
            assert path.name == "bobby_words.TextGrid", f"{path}: no phone tier in {[t.name for t in grid.tiers]}"
            continue
        labels = [text.strip() for _, _, text in tier.items]
        inventory = detect_inventory(labels)
        mapped = [map_phone(label, inventory) for label in labels]  # raises on an unknown symbol
        assert any(m.visemes for m in mapped), path
        with_phones += 1
    assert with_phones >= 27


def test_grid_clip_with_audio_inside_the_video_and_landmarks(tmp_path):
    """A GRID clip laid out as a corpus: .mpg (audio inside) + .align + MediaPipe landmarks, no wav."""
    clip = "bbaf2n"
    folder = tmp_path / "s1"
    folder.mkdir()
    shutil.copyfile(DATA / "grid_s1" / "video" / f"{clip}.mpg", folder / f"{clip}.mpg")
    shutil.copyfile(DATA / "grid_s1" / "align" / f"{clip}.align", folder / f"{clip}.align")
    shutil.copyfile(DATA / "grid_s1" / "landmarks" / f"{clip}.mediapipe478.csv", folder / f"{clip}.mediapipe478.csv")
    entry = entry_of(tmp_path, f"s1/{clip}")
    assert entry.audio_path == entry.video_path and entry.landmark_path.endswith(".mediapipe478.csv")
    result = ingest_utterance(entry, CONFIG)
    u = result.utterance
    assert u[C.FPS] == 25 and u[C.N_FRAMES] == 75 and u[C.SAMPLE_RATE] == 44100
    assert [p[C.VISEME] for p in result.phones if p[C.WORD] == "bin"] == ["MBP", "IEE", "LNTD"]


def test_video_shorter_than_alignment(tmp_path):
    from visemeflow.tracking.video import write_video

    corpus = make_corpus(tmp_path, {"spk/u1": HELLO})
    frames = np.zeros((10, 32, 32, 3), dtype=np.uint8)  # 0.4 s at 25 fps, alignment is 1.0 s
    video = write_video(corpus / "spk" / "u1.mp4", frames, 25.0)
    entry = entry_of(corpus, "spk/u1")
    with pytest.raises(IngestError) as err:
        ingest_utterance(entry, CONFIG)
    assert err.value.error_type == "VideoShorterThanAlignment"
    assert_names(err.value, "spk/u1", video)


# ---- ids in any script, links leaving the corpus, non-finite audio -------------------------------

UNICODE_SPEAKERS = {"Speaker One/take 1": HELLO, "Sprecher_ü/Äpfel": HELLO, "张三/一": HELLO}


def test_speakers_named_in_any_script_are_discovered(tmp_path):
    make_corpus(tmp_path, UNICODE_SPEAKERS)
    found = discover_corpus(tmp_path)
    assert found.rejects == ()
    assert sorted(e.utterance_id for e in found.entries) == sorted(UNICODE_SPEAKERS)
    assert entry_of(tmp_path, "张三/一").audio_path == str((tmp_path / "张三" / "一.wav").resolve())
    for uid in UNICODE_SPEAKERS:
        result = ingest_utterance(entry_of(tmp_path, uid), CONFIG)
        assert result.utterance[C.UTTERANCE_ID] == uid and result.utterance[C.SPEAKER] == uid.split("/")[0]


def test_decomposed_folder_names_give_nfc_ids(tmp_path):
    """A folder named on macOS arrives decomposed (u + combining diaeresis): its id is the composed form."""
    make_corpus(tmp_path, {"Sprecher_u\u0308/a": HELLO})
    (entry,) = discover_corpus(tmp_path).entries
    assert entry.utterance_id == "Sprecher_\u00fc/a"
    assert entry_of(tmp_path, "Sprecher_\u00fc/a").audio_path == entry.audio_path


def test_nfc_and_nfd_spellings_of_one_name_are_both_rejected_naming_both_files(tmp_path):
    """`café` composed and decomposed are one id: two utterances under it would share one `utterances` id and
    merge their phones. Both are refused, each reject naming every file; other utterances go on."""
    composed, decomposed = "caf\u00e9", "cafe\u0301"
    make_corpus(tmp_path, {f"s/{composed}": HELLO, f"s/{decomposed}": HELLO[:3], "s/other": HELLO,
                           "Jos\u00e9/a": HELLO, "Jose\u0301/a": HELLO})
    found = discover_corpus(tmp_path)
    assert [e.utterance_id for e in found.entries] == ["s/other"]
    by_id: dict[str, list[DiscoveryReject]] = {}
    for r in found.rejects:
        by_id.setdefault(r.utterance_id, []).append(r)
    assert sorted(by_id) == ["Jos\u00e9/a", "s/caf\u00e9"]
    for uid, spellings in ((f"s/{composed}", [f"s/{composed}", f"s/{decomposed}"]),
                           ("Jos\u00e9/a", ["Jos\u00e9/a", "Jose\u0301/a"])):
        rejects = by_id[uid]
        files = [str(tmp_path / f"{s}{ext}") for s in spellings for ext in (".wav", ".TextGrid")]
        assert len(rejects) == 2 and {r.error_type for r in rejects} == {"IdCollision"}
        assert sorted(Path(r.path).parent.name + "/" + Path(r.path).stem for r in rejects) == sorted(spellings)
        for r in rejects:
            assert all(f in r.message for f in files), r.message
            assert "NFC" in r.message
    assert discover_corpus(tmp_path, only=f"s/{decomposed}").entries == ()


def test_a_symlink_leaving_the_corpus_is_a_reject(tmp_path):
    outside = make_corpus(tmp_path / "elsewhere", {"x/secret": HELLO})
    root = make_corpus(tmp_path / "corpus", {"s/a": HELLO})
    (root / "s" / "b.wav").symlink_to(outside / "x" / "secret.wav")
    (root / "s" / "b.TextGrid").write_text((root / "s" / "a.TextGrid").read_text())
    (root / "s" / "c.wav").symlink_to(root / "s" / "a.wav")  # a link inside the corpus is fine
    (root / "s" / "c.TextGrid").write_text((root / "s" / "a.TextGrid").read_text())
    (root / "linked").symlink_to(outside / "x", target_is_directory=True)  # a whole speaker outside
    found = discover_corpus(root)
    assert [e.utterance_id for e in found.entries] == ["s/a", "s/c"]
    by_id = {r.utterance_id: r for r in found.rejects}
    assert sorted(by_id) == ["linked/secret", "s/b"]
    b = by_id["s/b"]
    assert b.error_type == "PathOutsideCorpus" and b.path == str(root / "s" / "b.wav")
    assert str(root / "s" / "b.wav") in b.message and "outside the corpus" in b.message
    assert by_id["linked/secret"].error_type == "PathOutsideCorpus"
    assert discover_corpus(root, only="s/b").entries == ()


def test_a_transcript_linked_outside_the_corpus_is_never_read(tmp_path):
    secret = tmp_path / "secret.txt"
    secret.write_text("my secret password hunter two\n", encoding="utf-8")
    root = tmp_path / "corpus"
    write_wav(root / "s" / "u.wav", 1.0)
    (root / "s" / "u.txt").symlink_to(secret)
    write_wav(root / "s" / "v.wav", 1.0)
    (root / "s" / "v.txt").write_text("hello there\n", encoding="utf-8")   # a transcript inside stays an entry
    found = discover_corpus(root)
    assert [(e.utterance_id, e.alignment_format) for e in found.entries] == [("s/v", "transcript")]
    [reject] = found.rejects
    assert (reject.utterance_id, reject.error_type, reject.path) == ("s/u", "PathOutsideCorpus", str(root / "s" / "u.txt"))
    assert "outside the corpus" in reject.message and "password" not in reject.message


def _float_wav(path: Path, seconds: float, bad: dict[int, float], rate: int = 16000, channels: int = 1,
               subtype: str = "FLOAT") -> Path:
    import soundfile as sf

    n = int(round(seconds * rate))
    samples = 0.05 * np.sin(2 * np.pi * 220.0 * np.arange(n) / rate)
    samples = np.repeat(samples[:, None], channels, axis=1)
    for index, value in bad.items():
        samples[index, channels - 1] = value
    sf.write(path, samples, rate, subtype=subtype)
    return path


@pytest.mark.parametrize("bad_value", [np.nan, np.inf])
def test_float_audio_with_nan_or_inf_is_a_reject_naming_the_samples(tmp_path, bad_value):
    make_corpus(tmp_path, {"s/bad": HELLO, "s/good": HELLO})
    wav = _float_wav(tmp_path / "s" / "bad.wav", 1.0, {1000: bad_value, 1200: bad_value, 1499: bad_value}, channels=2)
    _float_wav(tmp_path / "s" / "good.wav", 1.0, {})  # float audio without a bad sample is fine
    with pytest.raises(IngestError) as info:
        ingest_utterance(entry_of(tmp_path, "s/bad"), CONFIG)
    message = assert_names(info.value, "s/bad", wav.resolve())
    assert info.value.error_type == "NonFiniteAudio"
    assert "samples 1000..1499" in message and "0.062..0.094 s" in message and "3 samples" in message
    assert ingest_utterance(entry_of(tmp_path, "s/good"), CONFIG).utterance[C.DURATION_S] == 1.0


@pytest.mark.parametrize("subtype, peak", [("FLOAT", 3e38), ("FLOAT", -2.5e3), ("DOUBLE", 1e300)])
def test_float_audio_of_absurd_amplitude_is_a_reject_naming_the_samples(tmp_path, subtype, peak):
    """Finite samples of 3e38 passed ingest and trained a NaN model (the features overflow): float audio louder
    than MAX_FLOAT_AMPLITUDE is refused. A double file's 1e300 is finite there, and infinite once read as float32."""
    from visemeflow.ingest.audio import MAX_FLOAT_AMPLITUDE

    make_corpus(tmp_path, {"s/loud": HELLO, "s/hot": HELLO})
    wav = _float_wav(tmp_path / "s" / "loud.wav", 1.0, {1000: peak, 1200: 0.5, 1499: peak}, channels=2,
                     subtype=subtype)
    _float_wav(tmp_path / "s" / "hot.wav", 1.0, {100: 8.0, 200: -40.0})  # loud float audio past full scale is fine
    with pytest.raises(IngestError) as info:
        ingest_utterance(entry_of(tmp_path, "s/loud"), CONFIG)
    message = assert_names(info.value, "s/loud", wav.resolve())
    assert info.value.error_type == "AmplitudeOutOfRange"
    assert "samples 1000..1499 (0.062..0.094 s)" in message and "2 samples" in message, message
    assert f"{abs(peak):.3g}" in message and f"{MAX_FLOAT_AMPLITUDE:g}" in message, message
    assert ingest_utterance(entry_of(tmp_path, "s/hot"), CONFIG).utterance[C.DURATION_S] == 1.0


def test_audio_loading_for_training_and_prediction_refuses_absurd_amplitude(tmp_path):
    from visemeflow.ingest.audio import AudioAmplitudeError, read_audio
    from visemeflow.tasks.train import load_audio

    wav = _float_wav(tmp_path / "loud.wav", 0.5, {2000: 3e38}, rate=8000)
    for load in (load_audio, lambda p: read_audio(p)[0]):
        with pytest.raises(AudioAmplitudeError) as info:
            load(str(wav))
        assert str(wav) in str(info.value) and "samples 2000..2000 (0.250..0.250 s)" in str(info.value)
        assert pickle.loads(pickle.dumps(info.value)).reason == info.value.reason


def test_integer_audio_is_not_decoded_for_the_finiteness_check(tmp_path, monkeypatch):
    import soundfile as sf

    from visemeflow.ingest.audio import check_audio_file_finite

    make_corpus(tmp_path, {"s/pcm": HELLO})
    monkeypatch.setattr(sf, "blocks", lambda *a, **k: pytest.fail("integer PCM was decoded"))
    assert check_audio_file_finite(tmp_path / "s" / "pcm.wav") is False
    ingest_utterance(entry_of(tmp_path, "s/pcm"), CONFIG)


def test_audio_loading_for_training_and_prediction_refuses_nan(tmp_path):
    """The one audio reader (training, evaluation, prediction) refuses NaN samples with the same clear error."""
    from visemeflow.ingest.audio import NonFiniteAudioError, read_audio
    from visemeflow.tasks.train import load_audio

    wav = _float_wav(tmp_path / "bad.wav", 0.5, {2000: np.nan}, rate=8000)
    for load in (load_audio, lambda p: read_audio(p)[0]):
        with pytest.raises(NonFiniteAudioError) as info:
            load(str(wav))
        assert str(wav) in str(info.value) and "samples 2000..2000 (0.250..0.250 s)" in str(info.value)
        assert isinstance(info.value, ValueError) and pickle.loads(pickle.dumps(info.value)).path == str(wav)
    good = write_wav(tmp_path / "good.wav", 0.5, rate=8000)
    assert load_audio(str(good)).shape == (8000,)  # resampled to 16 kHz


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_procedural_curves_follow_a_new_frame_rate_of_the_ingest(tmp_path):
    """`pipeline --fps 25` after a run at 30 re-read every utterance at 25 fps, but the procedural stage reused the
    30-fps curves (their provenance held the files and the rules, not the clock): the store mixed frame rates."""
    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.params import IngestParams, ProceduralParams
    from visemeflow.flows.procedural import procedural_flow
    from visemeflow.storage import Store

    corpus = make_corpus(tmp_path / "corpus", {"s/a": HELLO, "s/b": HELLO})
    store_root = tmp_path / "store"
    store = Store(store_root)
    for fps, generated in ((30.0, 2), (25.0, 2), (25.0, 0)):
        ingest_flow(IngestParams(corpus=corpus, store=store_root, n_shards=1, config=IngestConfig(fps=fps)))
        report = procedural_flow(ProceduralParams(store=store_root, n_shards=1))
        assert report.get("generated", 0) == generated, (fps, report)   # the last: the shard cached
        for uid in ("s/a", "s/b"):
            table = store.read_curves(uid, "procedural", report["variant"])
            (row,) = store.read_table("utterances", utterance_ids=[uid]).to_pylist()
            assert table.num_rows == row[C.N_FRAMES] == round(row[C.DURATION_S] * fps), (fps, uid)
            times = table.column(C.TIME_S).to_numpy()
            assert abs(1.0 / (times[1] - times[0]) - fps) < 1e-6, (fps, uid)


def test_a_curve_file_cut_short_is_made_again_and_named_when_read(tmp_path):
    """A curve file cut to half (a copy or a full disk) passed the stage's check, which only caught empty files, so
    the pipeline kept it and `curves show` died with Arrow's traceback: it is now remade, and read, a StoreError
    naming the file and the command that remakes it."""
    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.params import IngestParams, ProceduralParams
    from visemeflow.flows.procedural import procedural_flow
    from visemeflow.storage import Store
    from visemeflow.storage.store import StoreError

    corpus = make_corpus(tmp_path / "corpus", {"s/a": HELLO, "s/b": HELLO})
    store_root = tmp_path / "store"
    store = Store(store_root)
    ingest_flow(IngestParams(corpus=corpus, store=store_root, n_shards=1))
    procedural_flow(ProceduralParams(store=store_root, n_shards=1))
    path = store.curve_path("procedural", "jali", "s/a")
    whole = path.read_bytes()
    path.write_bytes(whole[: len(whole) // 2])
    assert not store.has_curves("procedural", "jali", "s/a") and store.has_curves("procedural", "jali", "s/b")
    with pytest.raises(StoreError, match=rf"{re.escape(str(path))}: the procedural curves of s/a are damaged, not a "
                                         r"whole Parquet file .*`visemeflow rerun s/a --stage procedural`"):
        store.read_curves("s/a", "procedural", "jali")
    report = procedural_flow(ProceduralParams(store=store_root, n_shards=1))
    assert report["generated"] == 1 and report["reused"] == 1, report
    assert store.read_curves("s/a", "procedural", "jali").num_rows == 30


def test_unicode_corpus_through_ingest_and_procedural_flows(tmp_path):
    """Speakers 'Speaker One', 'Sprecher_ü', '张三' ingest; their curves are written and read back by id; a NaN
    float WAV and a link leaving the corpus are rejects with clear messages while the rest goes on."""
    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.params import IngestParams, ProceduralParams
    from visemeflow.flows.procedural import procedural_flow
    from visemeflow.storage import Store

    corpus = make_corpus(tmp_path / "corpus", {**UNICODE_SPEAKERS, "s/nan": HELLO, "s/link": HELLO, "s/loud": HELLO})
    _float_wav(corpus / "s" / "nan.wav", 1.0, {8000: np.nan})
    _float_wav(corpus / "s" / "loud.wav", 1.0, {8000: 3e38})
    outside = write_wav(tmp_path / "outside.wav", 1.0)
    (corpus / "s" / "link.wav").unlink()
    (corpus / "s" / "link.wav").symlink_to(outside)
    store_root = tmp_path / "store"
    ingest_flow(IngestParams(corpus=corpus, store=store_root, n_shards=2))
    procedural_flow(ProceduralParams(store=store_root, n_shards=2))

    store = Store(store_root)
    assert sorted(store.read_table("utterances").column(C.UTTERANCE_ID).to_pylist()) == sorted(UNICODE_SPEAKERS)
    assert store.curve_ids("procedural", "jali") == sorted(UNICODE_SPEAKERS)
    for uid in UNICODE_SPEAKERS:
        curves = store.read_curves(uid, "procedural", "jali")
        assert set(curves.column(C.UTTERANCE_ID).to_pylist()) == {uid} and curves.num_rows == 30
    rejects = {r[C.UTTERANCE_ID]: r for r in store.read_table("rejects").to_pylist()}
    assert sorted(rejects) == ["s/link", "s/loud", "s/nan"]
    assert rejects["s/nan"][C.ERROR_TYPE] == "NonFiniteAudio" and "samples 8000..8000" in rejects["s/nan"][C.MESSAGE]
    loud = rejects["s/loud"]
    assert loud[C.ERROR_TYPE] == "AmplitudeOutOfRange" and "samples 8000..8000" in loud[C.MESSAGE]
    assert str(corpus / "s" / "loud.wav") in loud[C.MESSAGE]
    assert rejects["s/link"][C.ERROR_TYPE] == "PathOutsideCorpus"
    assert str(corpus / "s" / "link.wav") in rejects["s/link"][C.MESSAGE]
    # a power loss inside a shard's group flush (atomic.group_sync): a curve file back empty. With the shard's
    # earlier result still recorded (a rewrite of a deleted file) and with none (a first run: results are written
    # after the flush), the rerun writes that file again and reuses the others untouched
    import shutil

    uid = sorted(UNICODE_SPEAKERS)[0]
    kept = {u: store.curve_path("procedural", "jali", u).stat().st_mtime_ns for u in UNICODE_SPEAKERS if u != uid}
    for drop_results in (False, True):
        store.curve_path("procedural", "jali", uid).write_bytes(b"")
        if drop_results:
            shutil.rmtree(store.results_dir())
        report = procedural_flow(ProceduralParams(store=store_root, n_shards=2))
        assert store.read_curves(uid, "procedural", "jali").num_rows == 30
        assert report["generated"] == 1 and report["reused"] == len(UNICODE_SPEAKERS) - 1
        assert kept == {u: store.curve_path("procedural", "jali", u).stat().st_mtime_ns for u in kept}


def _flac_claiming(path: Path, samples: int, claimed: int) -> Path:
    """A real one-channel 16 kHz FLAC of `samples` whose STREAMINFO claims `claimed` (a 36-bit field)."""
    import soundfile as sf

    sf.write(path, (0.1 * np.sin(np.arange(samples) / 5.0)).astype(np.float32), 16000, subtype="PCM_16")
    data = bytearray(path.read_bytes())
    assert data[:4] == b"fLaC"
    data[21] = (data[21] & 0xF0) | ((claimed >> 32) & 0x0F)     # STREAMINFO: total samples, bits 108-143
    data[22:26] = (claimed & 0xFFFFFFFF).to_bytes(4, "big")
    path.write_bytes(bytes(data))
    return path


def test_audio_whose_header_lies_about_its_length_is_refused_before_anything_is_sized_by_it(tmp_path):
    root = make_corpus(tmp_path / "corpus", {"s/good": HELLO})
    grid = (root / "s" / "good.TextGrid").read_text()
    for name, claimed in (("days", 2**36 - 1), ("double", 32000), ("honest", 16000)):
        _flac_claiming(root / "s" / f"{name}.flac", 16000, claimed)
        (root / "s" / f"{name}.TextGrid").write_text(grid)
    entries = {e.utterance_id: e for e in discover_corpus(root).entries}
    assert ingest_utterance(entries["s/honest"], IngestConfig()).utterance["duration_s"] == pytest.approx(1.0)
    with pytest.raises(IngestError, match=r"the header gives 1193\.0 h of audio, more than 24 h") as info:
        ingest_utterance(entries["s/days"], IngestConfig())     # a 49-day claim: 7.7 GiB of curves downstream
    assert info.value.error_type == "AudioTooLong" and info.value.path.endswith("days.flac")
    with pytest.raises(IngestError, match=r"the header gives 32000 samples, but sample 32000 cannot be read") as info:
        ingest_utterance(entries["s/double"], IngestConfig())
    assert info.value.error_type == "TruncatedAudio" and info.value.path.endswith("double.flac")
    assert ingest_utterance(entries["s/good"], IngestConfig()).utterance["duration_s"] == pytest.approx(1.0)


def test_a_video_stamped_to_span_days_is_rejected_and_the_rest_of_the_corpus_is_ingested(tmp_path):
    """A 34 KB .mkv whose second frame is shown 10**8 s after its first sized a 2.5-billion-frame curve grid."""
    root = make_corpus(tmp_path / "corpus", {"s/good": HELLO})
    grid = (root / "s" / "good.TextGrid").read_text()
    for name, gap in (("days", 1e8), ("honest", 0.96)):
        two_frames_apart(root / "s" / f"{name}.mkv", gap)
        (root / "s" / f"{name}.TextGrid").write_text(grid)
    entries = {e.utterance_id: e for e in discover_corpus(root).entries}
    assert entries["s/days"].video_path.endswith("days.mkv")
    honest = ingest_utterance(entries["s/honest"], IngestConfig()).utterance
    assert (honest["fps"], honest["n_frames"]) == (25.0, 25)
    with pytest.raises(IngestError, match=r"s/days: .*days\.mkv: the container's header gives 1e\+08 s, more than "
                                          r"the 24 h a clip may span") as info:
        ingest_utterance(entries["s/days"], IngestConfig())
    assert info.value.error_type == "VideoTooLong"
    assert ingest_utterance(entries["s/good"], IngestConfig()).utterance["duration_s"] == pytest.approx(1.0)
