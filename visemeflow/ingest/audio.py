"""Audio of an utterance, from an audio file or a video's audio track: the one reader every stage uses.

Ingest, training, evaluation, prediction and the dashboard all read an utterance's sound through `read_audio`,
so they agree on which files are videos (`VIDEO_EXTS`), on mono downmixing, and on refusing samples that are
NaN or infinite (`NonFiniteAudioError`) or beyond `MAX_FLOAT_AMPLITUDE` (`AudioAmplitudeError`), each naming the
file and the bad sample range. Such samples would turn features, losses and predicted curves into NaN far from
their cause: samples of 3e38 are finite, but their spectrum's power overflows float32, and a model trained on
them had NaN weights.

Out-of-range audio is refused, not normalised: a float file's full scale is 1.0, so a peak a thousand times
beyond it (60 dB) is not a recording's headroom but a broken or mis-scaled file (integer PCM values stored as
floats peak near 32768), and scaling it silently would hide that and make the samples differ from the file's.

At ingest only the header is read (`check_audio_file_finite` reads the samples of float files only: integer
PCM, the usual WAV and every FLAC, cannot hold NaN, infinity or a value beyond full scale, so checking it would
cost a full decode for nothing).
"""

import os
import re
from pathlib import Path

import numpy as np
import soundfile as sf

AUDIO_EXTS = (".wav", ".flac", ".ogg", ".mp3", ".m4a", ".opus", ".aac")
"""Audio files a corpus may hold, best first (lossless before lossy): every format `read_audio` (and so `speak`)
reads, so that a corpus is not refused a file the other commands take."""
# Containers read through PyAV. The first four, in this order, are those corpus discovery ranks (GRID's .mpg ...).
VIDEO_EXTS = (".mp4", ".avi", ".mpg", ".mov", ".m4v", ".mkv", ".mpeg", ".webm")
# soundfile subtypes whose samples are IEEE floats: the only ones that can be NaN or infinite.
FLOAT_SUBTYPES = frozenset({"FLOAT", "DOUBLE"})
# Largest |sample| accepted from a float file (full scale: 1.0): 60 dB of headroom, far below where features overflow.
MAX_FLOAT_AMPLITUDE = 1e3
_BLOCK_FRAMES = 1 << 20


class AudioError(ValueError):
    """Audio that cannot be used; names the file, a short error type and the reason."""

    def __init__(self, path: str, error_type: str, reason: str):
        super().__init__(f"{path}: {reason}")
        self.path, self.error_type, self.reason = str(path), error_type, reason

    def __reduce__(self):  # keeps the three-argument constructor picklable (Prefect ships exceptions)
        return (type(self), (self.path, self.error_type, self.reason))


class NonFiniteAudioError(AudioError):
    """Audio with NaN or infinite samples."""

    def __init__(self, path: str, error_type: str = "NonFiniteAudio", reason: str = "samples are NaN or infinite"):
        super().__init__(path, error_type, reason)


class AudioAmplitudeError(AudioError):
    """Audio with finite samples far beyond full scale (|x| > MAX_FLOAT_AMPLITUDE)."""

    def __init__(self, path: str, error_type: str = "AmplitudeOutOfRange",
                 reason: str = f"samples exceed |x| = {MAX_FLOAT_AMPLITUDE:g}"):
        super().__init__(path, error_type, reason)


def is_video_file(path: str | os.PathLike) -> bool:
    """Whether `path` is read as a video container (by its suffix, case-insensitive)."""
    return Path(path).suffix.lower() in VIDEO_EXTS


def non_finite_span(samples: np.ndarray) -> tuple[int, int, int] | None:
    """(first, last, count) of the sample frames (rows) holding a NaN or infinite value, or None."""
    return _span(~np.isfinite(samples))


def out_of_range_span(samples: np.ndarray) -> tuple[int, int, int, float] | None:
    """(first, last, count, peak |x|) of the sample frames (rows) holding a value beyond MAX_FLOAT_AMPLITUDE
    (infinity too: `check_finite` reports non-finite samples first), or None."""
    bad = (samples > MAX_FLOAT_AMPLITUDE) | (samples < -MAX_FLOAT_AMPLITUDE)  # no float copy of long audio
    span = _span(bad)
    return None if span is None else (*span, float(np.max(np.abs(samples[bad]))))


def _span(bad: np.ndarray) -> tuple[int, int, int] | None:
    if bad.ndim > 1:
        bad = bad.any(axis=tuple(range(1, bad.ndim)))
    if not bad.any():
        return None
    where = np.flatnonzero(bad)
    return int(where[0]), int(where[-1]), int(where.size)


def non_finite_reason(first: int, last: int, count: int, rate: float) -> str:
    """`samples 100..250 (0.006..0.016 s): 12 NaN or infinite samples` and what to do."""
    return (f"samples {first}..{last} ({first / rate:.3f}..{last / rate:.3f} s) hold NaN or infinite values "
            f"({count} sample{'s' if count != 1 else ''}); repair or re-export the audio")


def out_of_range_reason(first: int, last: int, count: int, peak: float, rate: float) -> str:
    """`samples 100..250 (0.006..0.016 s) reach |x| = 3e+38 ...` and what to do."""
    return (f"samples {first}..{last} ({first / rate:.3f}..{last / rate:.3f} s) reach |x| = {peak:.3g}, beyond "
            f"{MAX_FLOAT_AMPLITUDE:g} ({count} sample{'s' if count != 1 else ''}); float audio has full scale 1.0: "
            "rescale or re-export the audio")


def check_finite(samples: np.ndarray, rate: float, path: str | os.PathLike, offset: int = 0) -> None:
    """Raise NonFiniteAudioError (AudioAmplitudeError) naming `path` and the bad sample range when `samples` are
    not all finite (not all within MAX_FLOAT_AMPLITUDE); `offset`: the file's sample index of `samples[0]`, for a
    block read from the middle of a file."""
    span = non_finite_span(samples)
    if span is not None:
        first, last, count = span
        raise NonFiniteAudioError(str(path), reason=non_finite_reason(first + offset, last + offset, count, rate))
    loud = out_of_range_span(samples)
    if loud is not None:
        first, last, count, peak = loud
        raise AudioAmplitudeError(str(path), reason=out_of_range_reason(first + offset, last + offset, count, peak,
                                                                        rate))


def _merge_span(total: tuple | None, span: tuple | None, offset: int) -> tuple | None:
    """The file's (first, last, count[, peak]) so far, with one block's span at frame `offset` added."""
    if span is None:
        return total
    if total is None:
        return (offset + span[0], offset + span[1], *span[2:])
    return (total[0], offset + span[1], total[2] + span[2], *(max(a, b) for a, b in zip(total[3:], span[3:])))


def check_audio_file_finite(path: str | os.PathLike, info: "sf._SoundFileInfo | None" = None) -> bool:
    """Raise NonFiniteAudioError when a float audio file holds NaN or infinite samples, AudioAmplitudeError when
    it holds finite samples beyond MAX_FLOAT_AMPLITUDE.

    Only float subtypes are decoded (in blocks of about a million frames); integer files return at once.
    Doubles are checked as read (a 1e300 is out of range, not infinite). Returns whether the samples were read.
    """
    info = info if info is not None else sf.info(str(path))
    if info.subtype not in FLOAT_SUBTYPES:
        return False
    dtype = "float64" if info.subtype == "DOUBLE" else "float32"
    non_finite = loud = None
    offset = 0
    for block in sf.blocks(str(path), blocksize=_BLOCK_FRAMES, dtype=dtype, always_2d=True):
        non_finite = _merge_span(non_finite, non_finite_span(block), offset)
        loud = _merge_span(loud, out_of_range_span(block), offset)
        offset += block.shape[0]
    if non_finite is not None:
        raise NonFiniteAudioError(str(path), reason=non_finite_reason(*non_finite, info.samplerate))
    if loud is not None:
        raise AudioAmplitudeError(str(path), reason=out_of_range_reason(*loud, info.samplerate))
    return True


def decoder_reason(exc: BaseException, path: str) -> str:
    """A decoder's error without the path it repeats (the AudioError names the file once): soundfile's
    "Error opening '/x.wav': Format not recognised." is "Format not recognised", FFmpeg's "/x.wav: not a readable
    video ([Errno 1094995529] Invalid data found when processing input: '/x.wav')" is "not a readable video (Invalid
    data found when processing input)"."""
    text = str(exc).removeprefix(f"{path}: ")
    for quoted in (repr(path), f"'{path}'", f'"{path}"'):
        text = text.replace(f"Error opening {quoted}: ", "").replace(f": {quoted}", "").replace(quoted, "the file")
    text = re.sub(r"\[Errno -?\d+\] ", "", text)
    return text.strip().rstrip(".") or type(exc).__name__


def unreadable_reason(path: str | os.PathLike) -> str | None:
    """Why no sound can be read from `path`, judged on its header (nothing is decoded), or None when it can: what
    `speak` and `predict` check before they start, so that a file that is no audio fails in a second, not after the
    model is loaded."""
    path_str = str(path)
    try:
        if os.path.getsize(path_str) == 0:
            return "the file is empty (0 bytes)"
    except OSError:
        pass   # not there: said by the checks before this one, or by the decoders below
    if not is_video_file(path_str):
        try:
            sf.info(path_str)
            return None
        except (RuntimeError, OSError):   # not a format soundfile reads: FFmpeg's turn (an .m4a, a video's track)
            pass
    try:
        import av

        with av.open(path_str) as container:
            return None if container.streams.audio else "it has no audio track"
    except Exception as exc:  # noqa: BLE001 - PyAV raises many types for a file it cannot open
        return f"neither soundfile nor FFmpeg reads it as audio ({decoder_reason(exc, path_str)})"


def read_audio(path: str | os.PathLike, mono: bool = True) -> tuple[np.ndarray, int]:
    """(float32 samples, sample rate) of an audio file or of a video's first audio track.

    Samples are (frames,) when `mono` (mean of the channels), else (frames, channels). Files with a video
    suffix are decoded by PyAV; others by soundfile, then by PyAV when soundfile cannot read them (an .m4a).
    A track PyAV decodes is decoded whole, so it may hold at most ``tracking.video.MAX_DECODED_AUDIO_S`` (AudioError
    ``AudioTooLong`` beyond, found as it decodes). Raises AudioError when nothing can read the file,
    NonFiniteAudioError when a sample is NaN or infinite, AudioAmplitudeError when one is beyond
    MAX_FLOAT_AMPLITUDE.
    """
    from visemeflow.tracking.video import AudioTrackTooLong, VideoError, read_video_audio

    path_str = str(path)
    try:
        empty = os.path.getsize(path_str) == 0
    except OSError:
        empty = False           # a missing file: the readers below name it
    if empty:   # a recorder stopped before writing, a failed copy: say that, not two decoders' errors
        raise AudioError(path_str, "EmptyAudio", "the file is empty (0 bytes): record or copy it again")
    if is_video_file(path_str):
        try:
            samples, rate = read_video_audio(path_str, mono=mono)
        except VideoError as exc:
            raise AudioError(path_str, exc.error_type if isinstance(exc, AudioTrackTooLong) else "UnreadableAudio",
                             str(exc).removeprefix(f"{path_str}: ")) from exc
    else:
        try:
            samples, rate = sf.read(path_str, dtype="float32", always_2d=True)
        except (RuntimeError, OSError) as exc:  # soundfile's LibsndfileError is a RuntimeError
            try:
                samples, rate = read_video_audio(path_str, mono=mono)
            except AudioTrackTooLong as exc2:
                raise AudioError(path_str, exc2.error_type, str(exc2).removeprefix(f"{path_str}: ")) from exc2
            except (VideoError, OSError) as exc2:
                raise AudioError(path_str, "UnreadableAudio", "neither soundfile nor FFmpeg reads it as audio "
                                 f"({decoder_reason(exc, path_str)}; {decoder_reason(exc2, path_str)})") from exc
    samples = samples.reshape(len(samples), -1)   # PyAV's mono track: one column
    check_finite(samples, rate, path_str)
    if mono:
        samples = samples.mean(axis=1, dtype=np.float32) if samples.shape[1] > 1 else samples[:, 0].copy()
    return np.asarray(samples, dtype=np.float32), int(rate)


class AudioFile:
    """The mono float32 samples of an audio file, read by range (``visemeflow.learning.longform.AudioSource``).

    A file soundfile can seek in is read block by block and never whole (long audio in bounded memory), each block
    checked as :func:`read_audio` checks the whole file; a video's track, or a format only PyAV reads, is decoded
    whole by :func:`read_audio` (same errors)."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = str(path)
        self._samples: np.ndarray | None = None
        if not is_video_file(self.path):
            try:
                with sf.SoundFile(self.path) as f:
                    self.rate, self.n_samples = int(f.samplerate), int(f.frames)
                return
            except (RuntimeError, OSError):  # soundfile's LibsndfileError is a RuntimeError: let PyAV try
                pass
        self._samples, self.rate = read_audio(self.path)
        self.n_samples = len(self._samples)

    def read(self, start: int, stop: int) -> np.ndarray:
        """(stop - start,) float32 samples ``[start, stop)`` (fewer at the end of the file)."""
        if self._samples is not None:
            return self._samples[start:stop]
        with sf.SoundFile(self.path) as f:
            f.seek(start)
            block = f.read(stop - start, dtype="float32", always_2d=True)
        check_finite(block, self.rate, self.path, offset=start)
        return block.mean(axis=1, dtype=np.float32) if block.shape[1] > 1 else block[:, 0]
