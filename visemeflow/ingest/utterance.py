"""Ingest one utterance: read its alignment and audio header, check them, map phones to visemes.

Alignments are read from Praat TextGrids (text or binary), SPPAS `.xra`, HTK label files and MLF entries, and
word spans (`.align`); each becomes the same phone intervals (and words), so everything after reading is one
path. An utterance with a video and no alignment (`CorpusEntry.alignment_path` "") gets its `utterances` row
(`alignment_format` `NO_ALIGNMENT`, no inventory, frames from the video) and no phones.

Audio samples are read only where they can be NaN or infinite (float WAV files, float PCM audio tracks of
videos; see `ingest.audio`): such audio is a reject naming the file and the bad sample range.
"""

import math
import os
import re
import zlib
from dataclasses import dataclass, replace
from pathlib import Path

import soundfile as sf

from visemeflow.ingest.audio import AudioError, check_audio_file_finite, decoder_reason, read_audio
from visemeflow.ingest.config import IngestConfig
from visemeflow.ingest.corpus import TRANSCRIPT_FORMAT, CorpusEntry
from visemeflow.location import is_url, local_input
from visemeflow.phonetics.htk import LabelFileError, load_mlf, parse_htk_label
from visemeflow.phonetics.inventory import (
    NoInventoryError,
    UnknownPhonemeError,
    choose_inventory,
    map_phone,
    split_interval,
)
from visemeflow.phonetics.textgrid import (
    MAX_ALIGNMENT_BYTES, TextGridError, alignment_size_error, parse_textgrid_bytes,
)
from visemeflow.phonetics.xra import XraError, parse_xra
from visemeflow.phonetics.types import Alignment, PhoneInterval, WordInterval
from visemeflow.phonetics.wordalign import (
    WordAlignmentError,
    load_cmudict,
    parse_word_alignment,
    spread_words_to_phones,
)
from visemeflow.schemas import C
from visemeflow.schemas.tables import NO_ALIGNMENT
from visemeflow.timebase import frame_count
from visemeflow.tracking.video import MAX_MEDIA_S, VideoError, VideoInfo, probe_video

LANGUAGE_OF_INVENTORY: dict[str, str | None] = {"arpabet": "en", "ipa": "en", "xsampa": None, "pinyin": "zh"}
"""The language an utterance gets from its inventory when neither the manifest nor the config names one
(X-SAMPA is written for every language: none)."""
FILE_END_FORMATS = frozenset({"textgrid", "word_align"})
"""Formats that say where the file ends (a TextGrid's xmax; the last word of an .align): such an alignment must
end with the audio. Label files (HTK, MLF) and XRA only say where their last label ends: they may stop before the
audio ends (the rest is silence) but not run past it."""
MAX_AUDIO_S = MAX_MEDIA_S
"""Audio whose header claims more (24 h) is refused before anything is sized by it (a 132-byte FLAC may declare 49
days): longer recordings are split into utterances first. Video is held to the same span (``probe_video``)."""
MIN_AUDIO_RATE = 4000
"""Audio whose header gives fewer samples a second is refused (no speech fits; a 1-Hz header stretches a second into
four hours)."""


class IngestError(ValueError):
    """Bad input for one utterance; names the utterance, the file and what was expected."""

    def __init__(self, utterance_id: str, path: str, error_type: str, reason: str):
        super().__init__(f"{utterance_id}: {path}: {reason}")
        self.utterance_id, self.path, self.error_type, self.reason = utterance_id, path, error_type, reason

    def __reduce__(self):  # keeps the four-argument constructor picklable (Prefect ships exceptions)
        return (type(self), (self.utterance_id, self.path, self.error_type, self.reason))


@dataclass(frozen=True, slots=True)
class IngestedUtterance:
    utterance: dict[str, object]
    phones: list[dict[str, object]]


def _located(message: str, path: str) -> str:
    """A reader's `path:12:3: reason` as `line 12, column 3: reason` (the IngestError names the path itself)."""
    rest = message.removeprefix(path)
    m = re.match(r"^:(\d+)(?::(\d+))?: ", rest)
    if m is None:
        return rest.removeprefix(": ")
    column = f", column {m.group(2)}" if m.group(2) else ""
    return f"line {m.group(1)}{column}: {rest[m.end():]}"


def _decode_label_text(data: bytes) -> str:
    """Label files are UTF-8 (with or without BOM); Latin-1 when they are not (old HTK tools)."""
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return data.decode("latin-1")


ENGLISH = re.compile(r"^(en|eng)([-_].*)?$", re.IGNORECASE)


def _check_aligner_applies(entry: CorpusEntry, config: IngestConfig, path: str, what: str) -> None:
    """IngestError naming `path` unless the built-in aligner may align this entry's words: on, and English."""
    if not config.align_transcripts:
        raise IngestError(entry.utterance_id, path, "MissingAlignment",
                          f"{what}, not an alignment (transcripts are not aligned: align_transcripts is off)")
    language = entry.language or config.language
    if language is not None and ENGLISH.match(language) is None:
        raise IngestError(entry.utterance_id, path, "TranscriptNotEnglish",
                          f"{what} in {language!r}; the built-in aligner is English only: align "
                          "it with the Montreal Forced Aligner (any language) and put the TextGrid beside the audio")


def align_transcript_file(entry: CorpusEntry, config: IngestConfig) -> Alignment:
    """The phones of a transcript without times (`NAME.lab`, `NAME.txt`), forced-aligned to the audio in English
    (`visemeflow.phonetics.forcealign`); IngestError naming the file when that is off, the utterance is in another
    language, or the aligner cannot place the words."""
    path = entry.alignment_path
    _check_aligner_applies(entry, config, path, "a transcript without times")
    try:
        text = _decode_label_text(Path(path).read_bytes())
    except OSError as exc:
        raise IngestError(entry.utterance_id, path, "UnreadableAlignment", f"cannot read: {exc.strerror}") from exc
    return _align_words_text(entry, path, text)


def _align_words_text(entry: CorpusEntry, path: str, text: str) -> Alignment:
    """The phones of `text`'s words forced-aligned to the entry's audio (errors name `path`)."""
    from visemeflow.phonetics.forcealign import AlignmentError, align_transcript

    try:
        samples, rate = read_audio(entry.audio_path)
    except AudioError as exc:
        raise IngestError(entry.utterance_id, exc.path, exc.error_type, exc.reason) from exc
    try:
        done = align_transcript(samples, rate, text, source=path)
    except AlignmentError as exc:
        raise IngestError(entry.utterance_id, path, "TranscriptNotAligned",
                          str(exc).removeprefix(f"{path}: ")) from exc
    if not done.phones:
        raise IngestError(entry.utterance_id, path, "TranscriptNotAligned", "the aligner placed no phone")
    return Alignment(done.phones, done.words, 0.0, len(samples) / rate, path)


def read_alignment(entry: CorpusEntry, config: IngestConfig) -> Alignment:
    """The phone alignment of an entry from its TextGrid, XRA, HTK label / MLF or word alignment file, or its
    transcript forced-aligned (`align_transcript_file`)."""
    path = entry.alignment_path
    fmt = entry.alignment_format
    if fmt == TRANSCRIPT_FORMAT:
        return align_transcript_file(entry, config)
    try:
        if fmt == "mlf":
            folder, _, stem = (entry.alignment_key or "").partition("/")
            if not stem:
                named = Path(entry.audio_path)
                folder, stem = named.parent.name, named.stem
            grid = load_mlf(path).tiers(folder, stem)
            phones, words = grid.tiers
            return Alignment(_attach_words(phones.items, _words(words)), _words(words), grid.start_s, grid.end_s, path)
        with open(path, "rb") as fh:
            data = fh.read(MAX_ALIGNMENT_BYTES + 1)
        if len(data) > MAX_ALIGNMENT_BYTES:
            size = max(len(data), os.path.getsize(path))
            raise IngestError(entry.utterance_id, path, "AlignmentTooLarge", str(alignment_size_error(path, size)))
    except OSError as exc:
        raise IngestError(entry.utterance_id, path, "UnreadableAlignment", f"cannot read: {exc.strerror}") from exc
    except LabelFileError as exc:
        raise IngestError(entry.utterance_id, path, "BadAlignmentFile", _located(str(exc), path)) from exc
    try:
        if fmt == "word_align":
            text = data.decode("utf-8", errors="strict")
            words = parse_word_alignment(text, path, config.grid_time_unit_s)
            phones = spread_words_to_phones(words, load_cmudict(), path, config.vowel_weight)
            return Alignment(phones, words, words[0].start_s, words[-1].end_s, path)
        if fmt == "htk":
            grid = parse_htk_label(_decode_label_text(data), path)
            phones, words = grid.tiers
            return Alignment(_attach_words(phones.items, _words(words)), _words(words), grid.start_s, grid.end_s, path)
        grid = parse_xra(data, path) if fmt == "xra" else parse_textgrid_bytes(data, path)
    except (TextGridError, WordAlignmentError) as exc:
        raise IngestError(entry.utterance_id, path, type(exc).__name__, str(exc).removeprefix(f"{path}: ")) from exc
    except (LabelFileError, XraError) as exc:
        raise IngestError(entry.utterance_id, path, "BadAlignmentFile", _located(str(exc), path)) from exc
    except UnicodeDecodeError as exc:
        raise IngestError(entry.utterance_id, path, "BadEncoding", f"not UTF-8 text: {exc}") from exc
    tier = grid.tier(config.phone_tiers)
    word_tier = grid.tier(config.word_tiers)
    spoken = [t for _, _, t in (word_tier.items if word_tier is not None else ()) if t.strip()]
    language = entry.language or config.language
    # a tier finer than the words is the phones under another name: the user's own, never replaced by an aligner's
    finer = [t.name for t in grid.tiers if t.kind == "IntervalTier" and t is not word_tier
             and sum(1 for _, _, x in t.items if x.strip()) > len(spoken)]
    if (tier is None and spoken and not finer and config.align_transcripts
            and (language is None or ENGLISH.match(language))):
        # words without phones (praatio's examples, a hand-made word tier): aligned as an English transcript is
        return _align_words_text(entry, path, " ".join(spoken))
    if tier is None:
        names = [t.name for t in grid.tiers]
        hint = (f"; if tier {finer[0]!r} holds the phones, name it: --phone-tier {finer[0]}" if finer else
                "; its words are aligned in English only (set the language), else add a phone tier (MFA, WebMAUS)"
                if spoken else "")
        raise IngestError(entry.utterance_id, path, "MissingPhoneTier",
                          f"no interval tier named {' or '.join(config.phone_tiers)}; tiers are {names}{hint}")
    words = _words(word_tier)
    return Alignment(_attach_words(tier.items, words), words, grid.start_s, grid.end_s, path)


def _words(tier) -> tuple[WordInterval, ...]:
    return tuple(WordInterval(t, a, b) for a, b, t in (tier.items if tier is not None else ()))


def _attach_words(items, words: tuple[WordInterval, ...]) -> tuple[PhoneInterval, ...]:
    """Phone intervals with the word whose span contains each phone's midpoint."""
    spoken = [(i, w) for i, w in enumerate(words) if w.label.strip()]
    phones: list[PhoneInterval] = []
    j = 0
    for start, end, label in items:
        mid = 0.5 * (start + end)
        while j < len(spoken) and spoken[j][1].end_s <= mid:
            j += 1
        if j < len(spoken) and spoken[j][1].start_s <= mid:
            phones.append(PhoneInterval(label, start, end, spoken[j][1].label, j))
        else:
            phones.append(PhoneInterval(label, start, end))
    return tuple(phones)


def check_intervals(entry: CorpusEntry, alignment: Alignment) -> None:
    """Times must be finite, not before the audio starts (0 s), ordered and not overlapping."""
    prev_end = -math.inf
    for i, p in enumerate(alignment.phones):
        if not (math.isfinite(p.start_s) and math.isfinite(p.end_s)):
            raise IngestError(entry.utterance_id, entry.alignment_path, "NonFiniteTime",
                              f"interval {i + 1} ({p.label!r}) has a non-finite time ({p.start_s}, {p.end_s})")
        if p.start_s < -1e-6:
            raise IngestError(entry.utterance_id, entry.alignment_path, "NegativeTime",
                              f"interval {i + 1} ({p.label!r}) starts at {p.start_s:.3f} s; times are seconds from "
                              "the start of the audio, 0 or later")
        if p.end_s < p.start_s:
            raise IngestError(entry.utterance_id, entry.alignment_path, "NegativeDuration",
                              f"interval {i + 1} ({p.label!r}) ends at {p.end_s:.3f} s before it starts at {p.start_s:.3f} s")
        if p.start_s < prev_end - 1e-6:
            raise IngestError(entry.utterance_id, entry.alignment_path, "OverlappingIntervals",
                              f"interval {i + 1} ({p.label!r}) starts at {p.start_s:.3f} s, before the previous one ends at {prev_end:.3f} s")
        prev_end = p.end_s
    if not alignment.phones:
        raise IngestError(entry.utterance_id, entry.alignment_path, "EmptyAlignment", "the phone tier has no intervals")


def _float_pcm_codec(codec: str | None) -> bool:
    """Whether an audio codec stores IEEE float samples (pcm_f32le, pcm_f64be, ...), which can be NaN."""
    return bool(codec) and codec.startswith("pcm_f")


def read_audio_info(entry: CorpusEntry) -> tuple[int, float]:
    """(sample rate, duration in seconds) from the audio header (or the video's audio track).

    Float audio is read whole to check that every sample is finite (integer audio cannot be anything else).
    """
    if entry.video_path is not None and entry.audio_path == entry.video_path:
        info = read_video_info(entry)
        if not info.has_audio or not info.audio_rate:
            raise IngestError(entry.utterance_id, entry.video_path, "MissingAudio",
                              "no audio file beside the video and no audio track in it")
        if _float_pcm_codec(info.audio_codec):
            try:
                read_audio(entry.video_path)
            except AudioError as exc:
                raise IngestError(entry.utterance_id, exc.path, exc.error_type, exc.reason) from exc
        return int(info.audio_rate), float(info.container_duration_s or info.duration_s)
    try:
        info = sf.info(entry.audio_path)
    except (RuntimeError, OSError) as exc:
        # a format libsndfile does not read (.m4a, .aac): decoded whole by PyAV, as `read_audio` does for `speak`
        try:
            samples, rate = read_audio(entry.audio_path)
        except AudioError as exc2:
            raise IngestError(entry.utterance_id, exc2.path, exc2.error_type, exc2.reason) from exc
        if not len(samples):
            raise IngestError(entry.utterance_id, entry.audio_path, "EmptyAudio", "the audio has no samples") from exc
        return int(rate), len(samples) / rate
    if info.frames <= 0 or info.samplerate <= 0:
        raise IngestError(entry.utterance_id, entry.audio_path, "EmptyAudio", "the audio has no samples")
    if info.samplerate < MIN_AUDIO_RATE:
        raise IngestError(entry.utterance_id, entry.audio_path, "UnsupportedSampleRate",
                          f"the header gives {info.samplerate} samples a second; speech needs at least "
                          f"{MIN_AUDIO_RATE} (a damaged header?)")
    seconds = info.frames / info.samplerate
    if seconds > MAX_AUDIO_S:
        raise IngestError(entry.utterance_id, entry.audio_path, "AudioTooLong",
                          f"the header gives {seconds / 3600:.1f} h of audio, more than {MAX_AUDIO_S / 3600:.0f} h: "
                          "split the recording into utterances (or the header is damaged)")
    try:
        check_audio_file_finite(entry.audio_path, info)
        if info.format != "MPEG":   # an MP3's count may be the encoder's estimate: its decoder is the judge
            _check_last_frame(entry.audio_path, info.frames)
    except AudioError as exc:
        raise IngestError(entry.utterance_id, exc.path, exc.error_type, exc.reason) from exc
    except (RuntimeError, OSError) as exc:
        raise IngestError(entry.utterance_id, entry.audio_path, "UnreadableAudio",
                          f"soundfile cannot read it: {decoder_reason(exc, entry.audio_path)}") from exc
    return int(info.samplerate), seconds


def _check_last_frame(path: str, frames: int) -> None:
    """AudioError unless the header's last frame can be read: a truncated file, or a header that claims more samples
    than the file holds, would otherwise size every later array by the claim."""
    try:
        with sf.SoundFile(path) as f:
            f.seek(frames - 1)
            got = len(f.read(1))
    except (RuntimeError, OSError, ValueError) as exc:   # libsndfile: "Internal psf_fseek() failed"
        raise AudioError(path, "TruncatedAudio", f"the header gives {frames} samples, but sample {frames} cannot "
                                                 f"be read ({type(exc).__name__}: {exc})") from exc
    if got != 1:
        raise AudioError(path, "TruncatedAudio", f"the header gives {frames} samples, but the file ends before the last")


def read_video_info(entry: CorpusEntry) -> VideoInfo:
    """Frame size, rate and count of the entry's video (decoded to count when the header has no count)."""
    try:
        return probe_video(entry.video_path)
    except VideoError as exc:
        raise IngestError(entry.utterance_id, entry.video_path, exc.error_type,
                          str(exc).removeprefix(f"{entry.video_path}: ")) from exc


def map_phones(entry: CorpusEntry, alignment: Alignment, config: IngestConfig) -> tuple[str, list[dict[str, object]]]:
    """(inventory, phone rows) with compound phones split into one row per viseme."""
    labels = [p.label.strip() for p in alignment.phones]
    if config.inventory == "auto":
        try:
            inventory = choose_inventory(labels, entry.language or config.language)
        except NoInventoryError as exc:
            tried = "; ".join(
                f"{t.inventory}: {t.first_unknown!r} at {alignment.phones[t.index].start_s:.3f} s (interval "
                f"{t.index + 1}; {t.unknown} unknown label{'s' if t.unknown != 1 else ''})" for t in exc.trials)
            raise IngestError(
                entry.utterance_id, entry.alignment_path, "UnknownPhoneme",
                f"no phone inventory knows every label; the first unknown label of each inventory tried: {tried}. "
                "Fix the labels, set the inventory, or add rows to visemeflow/phonetics/data (docs/phonemes.md)",
            ) from exc
    else:
        inventory = config.inventory
    rows: list[dict[str, object]] = []
    for index, (p, label) in enumerate(zip(alignment.phones, labels)):
        if p.end_s <= p.start_s:
            continue
        try:
            m = map_phone(label, inventory)
        except UnknownPhonemeError as exc:
            raise IngestError(
                entry.utterance_id, entry.alignment_path, "UnknownPhoneme",
                f"unknown {inventory} phoneme {label!r} at {p.start_s:.3f} s (interval {index + 1}); inventory "
                f"{inventory} was set in the ingest config, no other was tried; fix the label or choose another "
                "inventory",
            ) from exc
        visemes = m.visemes or ((None, 1.0),)
        spans = split_interval(p.start_s, p.end_s, [w for _, w in visemes])
        for part, ((viseme, _), (a, b)) in enumerate(zip(visemes, spans)):
            rows.append({
                C.UTTERANCE_ID: entry.utterance_id, C.INDEX: index, C.PART: part, C.LABEL: p.label,
                C.PHONEME: m.phoneme or None, C.VISEME: viseme, C.START_S: a, C.END_S: b,
                C.WORD: p.word, C.WORD_INDEX: p.word_index, C.STRESS: m.stress,
            })
    return inventory, rows


def assign_split(utterance_id: str, val_fraction: float) -> str:
    """'val' for a stable pseudo-random `val_fraction` of ids, else 'train'."""
    return "val" if zlib.crc32(b"split:" + utterance_id.encode()) / 2**32 < val_fraction else "train"


def ingest_unaligned(entry: CorpusEntry, config: IngestConfig) -> IngestedUtterance:
    """The `utterances` row of a video without an alignment: audio from its file or the video's audio track,
    frames from the video, no inventory and no phones (`alignment_format` NO_ALIGNMENT)."""
    if entry.video_path is None:
        raise IngestError(entry.utterance_id, entry.audio_path, "MissingAlignment",
                          "no alignment, and no video to track without one")
    sample_rate, duration = read_audio_info(entry)
    video = read_video_info(entry)
    utterance = {
        C.UTTERANCE_ID: entry.utterance_id, C.SPEAKER: entry.speaker,
        C.LANGUAGE: entry.language or config.language, C.INVENTORY: None,
        C.AUDIO_PATH: entry.audio_path, C.VIDEO_PATH: entry.video_path,
        C.ALIGNMENT_PATH: "", C.ALIGNMENT_FORMAT: NO_ALIGNMENT,
        C.LANDMARK_PATH: entry.landmark_path, C.SAMPLE_RATE: sample_rate, C.DURATION_S: duration,
        C.FPS: video.nominal_fps, C.N_FRAMES: video.grid_frames, C.CONTENT_HASH: entry.content_hash,
        C.SPLIT: entry.split or assign_split(entry.utterance_id, config.val_fraction),
    }
    return IngestedUtterance(utterance, [])


PATH_COLUMNS = (C.AUDIO_PATH, C.VIDEO_PATH, C.ALIGNMENT_PATH, C.LANDMARK_PATH)


def ingest_utterance(entry: CorpusEntry, config: IngestConfig) -> IngestedUtterance:
    """Rows of the `utterances` and `phones` tables for one corpus entry (`ingest_unaligned` without alignment).

    An entry of a corpus on object storage (URL paths) is read from local copies of its files
    (`location.local_input`); its rows and errors name the URLs, which every later stage reads the same way."""
    urls: dict[str, str] = {}
    for url in (entry.audio_path, entry.alignment_path, entry.video_path, entry.landmark_path):
        if url and is_url(url) and url not in urls:
            try:
                urls[url] = local_input(url)
            except OSError as exc:   # gone since discovery, or the server refuses: this utterance's reject
                raise IngestError(entry.utterance_id, url, "UnreadableObject", f"cannot fetch it: {exc}") from exc
    if not urls:
        return _ingest_files(entry, config)
    back = {local: url for url, local in urls.items()}

    def local(path):
        return urls.get(path, path)

    def named(text):
        for copy, url in back.items():
            text = text.replace(copy, url)
        return text

    copy = replace(entry, audio_path=local(entry.audio_path), alignment_path=local(entry.alignment_path),
                   video_path=local(entry.video_path), landmark_path=local(entry.landmark_path))
    try:
        result = _ingest_files(copy, config)
    except IngestError as exc:
        raise IngestError(exc.utterance_id, named(exc.path), exc.error_type, named(exc.reason)) from exc
    row = {**result.utterance, **{c: back.get(result.utterance[c], result.utterance[c]) for c in PATH_COLUMNS}}
    return IngestedUtterance(row, result.phones)


def _ingest_files(entry: CorpusEntry, config: IngestConfig) -> IngestedUtterance:
    if not entry.has_alignment:
        return ingest_unaligned(entry, config)
    alignment = read_alignment(entry, config)
    check_intervals(entry, alignment)
    sample_rate, duration = read_audio_info(entry)
    align_end = max(alignment.end_s, alignment.phones[-1].end_s)
    tolerance = config.alignment_tolerance_s
    past = align_end > duration + tolerance
    if past or (entry.alignment_format in FILE_END_FORMATS and align_end < duration - tolerance):
        raise IngestError(
            entry.utterance_id, entry.alignment_path, "AlignmentAudioMismatch",
            f"alignment ends at {align_end:.3f} s but the audio {entry.audio_path} lasts {duration:.3f} s "
            f"(tolerance {tolerance} s){'; its labels run past the end of the audio' if past else ''}",
        )
    fps, n_frames = config.fps, frame_count(duration, config.fps)
    if entry.video_path is not None:
        video = read_video_info(entry)
        # when the last frame stops showing (its presentation time stamp + one frame)
        video_end = video.duration_s if video.last_frame_s is None else video.last_frame_s + 1.0 / video.nominal_fps
        if video_end < align_end - config.alignment_tolerance_s:
            raise IngestError(
                entry.utterance_id, entry.video_path, "VideoShorterThanAlignment",
                f"the video has {video.n_frames} frames ({video.duration_s:.3f} s at {video.fps:g} fps) but the "
                f"alignment {entry.alignment_path} runs to {align_end:.3f} s",
            )
        fps, n_frames = video.nominal_fps, video.grid_frames
    inventory, phones = map_phones(entry, alignment, config)
    utterance = {
        C.UTTERANCE_ID: entry.utterance_id, C.SPEAKER: entry.speaker,
        C.LANGUAGE: entry.language or config.language or LANGUAGE_OF_INVENTORY[inventory],
        C.INVENTORY: inventory, C.AUDIO_PATH: entry.audio_path, C.VIDEO_PATH: entry.video_path,
        C.ALIGNMENT_PATH: entry.alignment_path, C.ALIGNMENT_FORMAT: entry.alignment_format,
        C.LANDMARK_PATH: entry.landmark_path, C.SAMPLE_RATE: sample_rate, C.DURATION_S: duration,
        C.FPS: fps, C.N_FRAMES: n_frames, C.CONTENT_HASH: entry.content_hash,
        C.SPLIT: entry.split or assign_split(entry.utterance_id, config.val_fraction),
    }
    return IngestedUtterance(utterance, phones)
