"""Audio of an utterance, from an audio file or a video's audio track: the one reader every stage uses.

Ingest, training, evaluation, prediction and the dashboard all read an utterance's sound through `read_audio`,
so they agree on which files are videos (`VIDEO_EXTS`), on mono downmixing, and on refusing samples that are
NaN or infinite (`NonFiniteAudioError`, naming the file and the bad sample range). Such samples would turn
features, losses and predicted curves into NaN far from their cause.

At ingest only the header is read (`check_audio_file_finite` reads the samples of float files only: integer
PCM, the usual WAV and every FLAC, cannot hold NaN or infinity, so checking it would cost a full decode for
nothing).
"""

import os
from pathlib import Path

import numpy as np
import soundfile as sf

AUDIO_EXTS = (".wav", ".flac", ".ogg")
# Containers read through PyAV. The first four, in this order, are those corpus discovery ranks (GRID's .mpg ...).
VIDEO_EXTS = (".mp4", ".avi", ".mpg", ".mov", ".m4v", ".mkv", ".mpeg", ".webm")
# soundfile subtypes whose samples are IEEE floats: the only ones that can be NaN or infinite.
FLOAT_SUBTYPES = frozenset({"FLOAT", "DOUBLE"})
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


def is_video_file(path: str | os.PathLike) -> bool:
    """Whether `path` is read as a video container (by its suffix, case-insensitive)."""
    return Path(path).suffix.lower() in VIDEO_EXTS


def non_finite_span(samples: np.ndarray) -> tuple[int, int, int] | None:
    """(first, last, count) of the sample frames (rows) holding a NaN or infinite value, or None."""
    bad = ~np.isfinite(samples)
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


def check_finite(samples: np.ndarray, rate: float, path: str | os.PathLike) -> None:
    """Raise NonFiniteAudioError naming `path` and the bad sample range when `samples` are not all finite."""
    span = non_finite_span(samples)
    if span is not None:
        raise NonFiniteAudioError(str(path), reason=non_finite_reason(*span, rate))


def check_audio_file_finite(path: str | os.PathLike, info: "sf._SoundFileInfo | None" = None) -> bool:
    """Raise NonFiniteAudioError when a float audio file holds NaN or infinite samples.

    Only float subtypes are decoded (in blocks of about a million frames); integer files return at once.
    Returns whether the samples were read.
    """
    info = info if info is not None else sf.info(str(path))
    if info.subtype not in FLOAT_SUBTYPES:
        return False
    dtype = "float64" if info.subtype == "DOUBLE" else "float32"
    first = last = None
    count = offset = 0
    for block in sf.blocks(str(path), blocksize=_BLOCK_FRAMES, dtype=dtype, always_2d=True):
        span = non_finite_span(block)
        if span is not None:
            first = offset + span[0] if first is None else first
            last = offset + span[1]
            count += span[2]
        offset += block.shape[0]
    if first is not None:
        raise NonFiniteAudioError(str(path), reason=non_finite_reason(first, last, count, info.samplerate))
    return True


def read_audio(path: str | os.PathLike, mono: bool = True) -> tuple[np.ndarray, int]:
    """(float32 samples, sample rate) of an audio file or of a video's first audio track.

    Samples are (frames,) when `mono` (mean of the channels), else (frames, channels). Files with a video
    suffix are decoded by PyAV; others by soundfile, then by PyAV when soundfile cannot read them (an .m4a).
    Raises AudioError when nothing can read the file, NonFiniteAudioError when a sample is NaN or infinite.
    """
    from visemeflow.tracking.video import VideoError, read_video_audio

    path_str = str(path)
    if is_video_file(path_str):
        try:
            samples, rate = read_video_audio(path_str, mono=False)
        except VideoError as exc:
            raise AudioError(path_str, "UnreadableAudio", str(exc).removeprefix(f"{path_str}: ")) from exc
    else:
        try:
            samples, rate = sf.read(path_str, dtype="float32", always_2d=True)
        except (RuntimeError, OSError) as exc:  # soundfile's LibsndfileError is a RuntimeError
            try:
                samples, rate = read_video_audio(path_str, mono=False)
            except (VideoError, OSError) as exc2:
                raise AudioError(path_str, "UnreadableAudio", f"cannot read audio: {exc}; as a video: {exc2}") from exc
    check_finite(samples, rate, path_str)
    if mono:
        samples = samples.mean(axis=1, dtype=np.float32) if samples.shape[1] > 1 else samples[:, 0].copy()
    return np.asarray(samples, dtype=np.float32), int(rate)
