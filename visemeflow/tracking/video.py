"""Video and its audio track through PyAV (FFmpeg): probe, decode RGB frames, decode audio, encode.

Frames are RGB uint8 arrays (H, W, 3) everywhere. Frame ``i`` is the ``i``-th decoded frame in presentation
order, the index landmark tracks use.

Frame counts: many containers store no frame count or a wrong one (MPEG-1 program streams such as the GRID .mpg
report 0), so :func:`probe_video` trusts the stored count only when it agrees with the stream duration and
otherwise counts by decoding. fps is the stream's average frame rate (GRID: 25; its "base" rate r_frame_rate is
50, the field rate, and must not be used).

Bounds (hostile or damaged files): a frame of more than :data:`MAX_FRAME_PIXELS` pixels is refused before it is
converted (:class:`VideoTooLarge`), a clip whose header, stored frame count or frame time stamps span more than
:data:`MAX_MEDIA_S` is refused before anything is sized by it (:class:`VideoTooLong`: a 34 KB file may stamp its
second frame 10**8 s after its first), and an audio track decoded whole stops past :data:`MAX_DECODED_AUDIO_S`
(:class:`AudioTrackTooLong`). Each error names the file.

Frame times: frame ``i`` is shown at :func:`frame_times` ``[i]``, from its presentation time stamp, on the audio's
clock (0 = the first audio sample :func:`read_video_audio` returns). For constant-rate video starting with its
audio this is ``i / fps`` (GRID, the demo corpus); for variable-rate video it is not: ``talking_heads/1.mp4`` has
frames on a 30 fps grid with gaps (average rate 22.13 fps) whose first frame is shown 33 ms after the audio starts.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from typing import BinaryIO
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import av
import numpy as np

from visemeflow.atomic import atomic_path

# Encoders in order of preference, by container. The first one this PyAV build can open is used.
MP4_VIDEO_CODECS = ("libx264", "libopenh264", "mpeg4")
AVI_VIDEO_CODECS = ("mjpeg", "ffv1")
MP4_AUDIO_CODECS = ("aac",)
AVI_AUDIO_CODECS = ("pcm_s16le",)
_CONTAINERS = {".mp4": "mp4", ".m4v": "mp4", ".mov": "mov", ".avi": "avi", ".mkv": "matroska"}


MAX_MEDIA_S = 24 * 3600.0
"""The longest clip accepted: longer recordings are split into utterances first (``ingest.utterance.MAX_AUDIO_S``
is the same bound for audio files)."""
MAX_FRAME_PIXELS = 4096 * 4096
"""The most pixels a decoded frame may have (4K DCI, 4096 x 2160, fits; an 8192 x 8192 frame is 192 MiB of RGB and
a 198 KB file can hold ten): downscale larger video first; the face tracker works on a region of a few hundred
pixels."""
MAX_DECODED_AUDIO_S = 4 * 3600.0
"""The longest audio track decoded whole (a video's sound, .m4a, .aac: formats soundfile cannot seek in), about 2.6
GiB of mono float32 at 48 kHz; WAV and FLAC are read by range at any length up to ``MAX_MEDIA_S``."""
MAX_GRID_FRAMES = int(MAX_MEDIA_S * 240)
"""The most frames a clip's curve grid may have (24 h at 240 fps)."""


class VideoError(ValueError):
    """A video that cannot be read or written; the message names the file. ``error_type`` is the short name the
    rejects table gets."""

    error_type = "UnreadableVideo"


class VideoTooLong(VideoError):
    """A clip whose header or time stamps span more than :data:`MAX_MEDIA_S`."""

    error_type = "VideoTooLong"


class VideoTooLarge(VideoError):
    """A frame of more than :data:`MAX_FRAME_PIXELS` pixels."""

    error_type = "VideoTooLarge"


class AudioTrackTooLong(VideoError):
    """An audio track that holds, or whose header claims, more than the seconds asked for."""

    error_type = "AudioTooLong"


def _check_frame_size(width: int, height: int, path: Path) -> None:
    if width * height > MAX_FRAME_PIXELS:
        raise VideoTooLarge(f"{path}: frames of {width}x{height} pixels, more than the {MAX_FRAME_PIXELS:,} a frame "
                            "may have (4096 x 4096): downscale the video first")


def _check_span(seconds: float | None, what: str, path: Path) -> None:
    if seconds is not None and not abs(seconds) <= MAX_MEDIA_S:    # NaN fails too
        raise VideoTooLong(f"{path}: {what} {seconds:.6g} s, more than the {_span_words(MAX_MEDIA_S)} a clip may "
                           "span: split the recording into utterances (or its header or time stamps are damaged)")


@dataclass(frozen=True)
class VideoInfo:
    path: Path
    width: int
    height: int
    fps: float
    n_frames: int
    duration_s: float           # n_frames / fps: the span the frames cover
    has_audio: bool
    audio_rate: int | None
    audio_channels: int | None
    video_codec: str = ""
    audio_codec: str | None = None
    container_duration_s: float | None = None   # what the container header says (GRID: 2.98 for 75 frames at 25)
    # Frame times (presentation time stamps on the audio's clock, see frame_times); defaults: frame k at k / fps
    first_frame_s: float = 0.0       # when the first frame is shown (talking_heads/1.mp4: 0.033 s after the audio)
    last_frame_s: float | None = None
    grid_fps: float | None = None    # the rate whose grid the frames sit on (1.mp4: 30, while fps says 22.13)

    @property
    def nominal_fps(self) -> float:
        """The frame grid's rate: `grid_fps`, else `fps`."""
        return self.grid_fps or self.fps

    @property
    def grid_frames(self) -> int:
        """Frames at `nominal_fps` from the audio's start (time 0) to the last frame: the curve grid of the clip
        (k / nominal_fps). Equals `n_frames` for constant-rate video that starts with its audio."""
        last = self.last_frame_s if self.last_frame_s is not None else (self.n_frames - 1) / self.fps
        return max(1, int(round(last * self.nominal_fps)) + 1)

    @property
    def variable_rate(self) -> bool:
        """Whether frames are missing from the grid between the first and the last frame (or off it)."""
        if self.last_frame_s is None:
            return False
        span = int(round((self.last_frame_s - self.first_frame_s) * self.nominal_fps)) + 1
        return span != self.n_frames or abs(self.nominal_fps - self.fps) > 1e-3 * self.fps


def _open(path: Path | BinaryIO):
    """A PyAV container of the video file `path`, or of a seekable binary file object (read as far as asked)."""
    if not isinstance(path, Path):
        try:
            return av.open(path)
        except (av.error.FFmpegError, UnicodeDecodeError, ValueError) as exc:
            raise VideoError(f"{getattr(path, 'path', 'video')}: not a readable video ({exc})") from exc
    if not path.is_file():
        raise VideoError(f"{path}: video file not found")
    try:
        return av.open(str(path))
    except (av.error.FFmpegError, UnicodeDecodeError, ValueError) as exc:
        raise VideoError(f"{path}: not a readable video ({exc})") from exc


def _video_stream(container, path: Path):
    if not container.streams.video:
        raise VideoError(f"{path}: no video stream")
    stream = container.streams.video[0]
    if stream.codec_context is None or not stream.codec_context.name:
        raise VideoError(f"{path}: video stream has no decodable codec")
    _check_frame_size(int(stream.codec_context.width or 0), int(stream.codec_context.height or 0), path)
    return stream


def _stream_fps(stream) -> float | None:
    for rate in (stream.average_rate, stream.guessed_rate, stream.base_rate):
        if rate is not None and rate > 0:
            return float(rate)
    return None


def _decode_video(container, stream, path: Path) -> Iterator[av.VideoFrame]:
    """Decoded frames; :class:`VideoTooLarge` at the first frame over :data:`MAX_FRAME_PIXELS` (a header may say
    nothing of the size, or a stream change it), before it is converted."""
    try:
        for frame in container.decode(stream):
            _check_frame_size(frame.width, frame.height, path)
            yield frame
    except av.error.FFmpegError as exc:
        raise VideoError(f"{path}: video decoding failed ({exc})") from exc


def probe_video(path: str | os.PathLike) -> VideoInfo:
    """Size, fps, frame count, audio format of a video; raises :class:`VideoError` naming the file if unreadable."""
    path = Path(path)
    with _open(path) as container:
        stream = _video_stream(container, path)
        width, height = stream.codec_context.width, stream.codec_context.height
        fps = _stream_fps(stream)
        stored = _header_frames(stream, fps)
        if stored is not None:
            n_frames = stored
        else:
            n_frames = 0
            for frame in _decode_video(container, stream, path):
                n_frames += 1
                if not width:
                    width, height = frame.width, frame.height
        if fps is None:
            raise VideoError(f"{path}: video stream has no frame rate")
        if not width or not height:
            raise VideoError(f"{path}: video stream has no frame size")
        audio = container.streams.audio[0] if container.streams.audio else None
        container_dur = None if container.duration is None else container.duration / av.time_base
        rates = [float(r) for r in (stream.average_rate, stream.guessed_rate, stream.base_rate)
                 if r is not None and r > 0]
        audio_start = _audio_start_s(container)
        audio_rate = None if audio is None else int(audio.codec_context.sample_rate)
        audio_channels = None if audio is None else int(audio.codec_context.channels)
        video_codec = stream.codec_context.name
        audio_codec = None if audio is None else audio.codec_context.name
    if n_frames == 0:
        raise VideoError(f"{path}: no decodable video frames")
    _check_span(container_dur, "the container's header gives", path)
    _check_span(n_frames / fps, f"{n_frames} frames at {fps:g} fps span", path)
    times = _packet_times(path)
    if len(times) == n_frames:
        times = times - (times[0] if audio_start is None else audio_start)
    else:                                # packets without time stamps, or not one frame each: decode
        times = frame_times(path)
    _check_span(float(times[0]), "the first frame is shown at", path)
    _check_span(float(times[-1]), "the last frame is shown at", path)
    info = VideoInfo(
        path=path, width=int(width), height=int(height), fps=fps, n_frames=n_frames,
        duration_s=n_frames / fps, has_audio=audio is not None, audio_rate=audio_rate,
        audio_channels=audio_channels, video_codec=video_codec, audio_codec=audio_codec,
        container_duration_s=container_dur, first_frame_s=float(times[0]), last_frame_s=float(times[-1]),
        grid_fps=grid_rate(times, rates),
    )
    if info.grid_frames > MAX_GRID_FRAMES:
        raise VideoTooLong(f"{path}: its frames sit on a {info.nominal_fps:g} fps grid of {info.grid_frames} frames, "
                           f"more than the {MAX_GRID_FRAMES} a clip may have")
    return info


def _header_frames(stream, fps: float | None) -> int | None:
    """The frame count the stream's header stores, when it agrees with the stream's duration x fps; else None."""
    stored = int(stream.frames or 0)
    duration = (float(stream.duration * stream.time_base)
                if stream.duration is not None and stream.time_base is not None else None)
    trusted = stored > 0 and fps is not None and duration is not None and abs(stored - duration * fps) <= 1.0
    return stored if trusted else None


def _packet_times(path: Path) -> np.ndarray:
    """Sorted presentation times (s, container clock) of the video packets that carry one, read without decoding;
    packets without a time stamp are left out (the caller then decodes)."""
    return _demux_times(_open(path), path)[0]


def _demux_times(container, path: Path) -> tuple[np.ndarray, int]:
    """(the sorted distinct time stamps of the video packets that carry one, the number of non-empty video packets),
    read without decoding; closes `container`."""
    out: list[float] = []
    packets = 0
    with container:
        stream = _video_stream(container, path)
        try:
            for packet in container.demux(stream):
                if packet.size:
                    packets += 1
                    if packet.pts is not None and packet.time_base is not None:
                        out.append(float(packet.pts * packet.time_base))
        except av.error.FFmpegError as exc:
            raise VideoError(f"{path}: video demuxing failed ({exc})") from exc
    return np.unique(np.asarray(out, np.float64)), packets


def packet_frame_times(path: str | os.PathLike) -> np.ndarray | None:
    """:func:`frame_times` read from the container without decoding a frame, where the container vouches for them:
    the stream header's frame count agrees with its duration (as :func:`probe_video` trusts it), every video packet
    carries a time stamp, and the packets' distinct times are as many as that count. None otherwise (MPEG-1 program
    streams such as GRID's store no count): decode with :func:`frame_times`. A decoder may still drop a damaged
    frame, so a caller that decodes the frames afterwards should compare the times (tracking does,
    ``tracking.utterance``). 0.01 s for a clip whose decoding takes 0.25 s (``talking_heads/4.mp4``)."""
    path = Path(path)
    container = _open(path)
    try:
        stream = _video_stream(container, path)
        expected = _header_frames(stream, _stream_fps(stream))
        audio_start = _audio_start_s(container)
    except BaseException:
        container.close()
        raise
    if expected is None:
        container.close()
        return None
    times, packets = _demux_times(container, path)
    if packets != expected or len(times) != expected:
        return None
    times = times - (times[0] if audio_start is None else audio_start)
    _check_span(float(times[0]), "the first frame is shown at", path)
    _check_span(float(times[-1]), "the last frame is shown at", path)
    return times


def grid_rate(times: np.ndarray, rates: Iterable[float] = ()) -> float | None:
    """The frame rate whose grid (first frame + k / rate) the frame `times` sit on: the lowest of the stream's
    rates `rates` (average, guessed, base) that holds every frame within a tenth of a frame, else 1 / the median
    frame interval (rounded to 1e-3); None for fewer than two frames.

    GRID: 25 (its base rate 50 holds the frames too, but 25 is the lower); talking_heads/1.mp4: 30 (its average
    rate 22.13 does not hold them); a phone's jittery clip: about its median rate."""
    times = np.asarray(times, np.float64)
    if len(times) < 2:
        return None
    offsets = times - times[0]
    for rate in sorted(r for r in rates if r > 0):
        steps = offsets * rate
        if np.abs(steps - np.round(steps)).max() < 0.1:
            return float(rate)
    step = float(np.median(np.diff(times)))
    return round(1.0 / step, 3) if step > 0 else None


def _audio_start_s(container) -> float | None:
    """When the first audio stream starts, in seconds on the container's clock; None without audio."""
    if not container.streams.audio:
        return None
    audio = container.streams.audio[0]
    if audio.start_time is not None and audio.time_base is not None:
        return float(audio.start_time * audio.time_base)
    if container.start_time is not None:
        return container.start_time / av.time_base
    return 0.0


def frame_times(path: str | os.PathLike) -> np.ndarray:
    """The presentation time in seconds (float64) of every decoded frame, in decode-output (= presentation) order.

    Times are relative to the start of the first audio stream when the container has audio (so they index the
    samples of :func:`read_video_audio`), otherwise to the first frame. A frame without a time stamp is placed one
    nominal frame after the previous one. :class:`VideoError` naming the file when no frame decodes or the time
    stamps do not increase.
    """
    return _decode_timed(Path(path), images=False)[1]


def read_timed_frames(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Every decoded frame, (T, H, W, 3) uint8 RGB, with its :func:`frame_times` (T,), from one decoding pass."""
    images, times = _decode_timed(Path(path), images=True)
    return np.stack(images), times


def _decode_timed(path: Path, images: bool) -> tuple[list[np.ndarray], np.ndarray]:
    out: list[np.ndarray] = []
    times: list[float] = []
    for frame, t in _iter_timed(path, images):
        if images:
            out.append(frame)
        times.append(t)
    return out, np.asarray(times, np.float64)


def iter_timed_frames(path: str | os.PathLike) -> Iterator[tuple[np.ndarray, float]]:
    """Every decoded frame, RGB uint8 (H, W, 3), with its :func:`frame_times` time (s), one at a time from one
    decoding pass (what :func:`read_timed_frames` gives, without holding the clip in memory). The times are those of
    :func:`frame_times` to the bit; :class:`VideoError` naming the file when no frame decodes, or, when it is reached,
    at the first frame whose time stamp does not increase (the frames before it have been yielded)."""
    return _iter_timed(Path(path), True)


def _iter_timed(path: Path, images: bool) -> Iterator[tuple[np.ndarray | None, float]]:
    """(frame or None, time) per decoded frame. A frame without a time stamp is placed one nominal frame after the
    previous one (0 for the first); times must increase; they are shifted to the audio's start (the first frame's
    time without audio): the rules of :func:`frame_times`, applied as the frames come."""
    with _open(path) as container:
        stream = _video_stream(container, path)
        stream.thread_type = "AUTO"
        fps = _stream_fps(stream) or 25.0
        audio_start = _audio_start_s(container)
        offset = audio_start
        previous: float | None = None          # the previous frame's time stamp (container clock)
        i = -1
        for i, frame in enumerate(_decode_video(container, stream, path)):
            t = None if frame.pts is None or frame.time_base is None else float(frame.pts * frame.time_base)
            if t is None:
                t = previous + 1.0 / fps if previous is not None else 0.0
            if previous is not None and not t > previous:
                raise VideoError(f"{path}: frame {i} has presentation time {t:.6f} s, not after frame {i - 1}'s "
                                 f"{previous:.6f} s")
            if offset is None:
                offset = t
            previous = t
            _check_span(t - offset, f"frame {i} is shown at", path)
            yield (frame.to_ndarray(format="rgb24") if images else None), t - offset
        if i < 0:
            raise VideoError(f"{path}: no decodable video frames")


def iter_video_frames(path: str | os.PathLike) -> Iterator[np.ndarray]:
    """Decoded frames one at a time, RGB uint8 (H, W, 3)."""
    path = Path(path)
    with _open(path) as container:
        stream = _video_stream(container, path)
        stream.thread_type = "AUTO"
        for frame in _decode_video(container, stream, path):
            yield frame.to_ndarray(format="rgb24")


def read_video_frames(path: str | os.PathLike, start: int = 0, count: int | None = None) -> np.ndarray:
    """Frames ``start .. start+count-1`` (all from ``start`` when count is None) as (frames, H, W, 3) uint8 RGB.
    Fewer frames come back when the video ends first; none past the end gives shape (0, H, W, 3)."""
    if start < 0 or (count is not None and count < 0):
        raise ValueError(f"start and count must be >= 0, got {start}, {count}")
    path = Path(path)
    out: list[np.ndarray] = []
    with _open(path) as container:
        stream = _video_stream(container, path)
        stream.thread_type = "AUTO"
        shape = (0, stream.codec_context.height, stream.codec_context.width, 3)
        if count != 0:
            for i, frame in enumerate(_decode_video(container, stream, path)):
                if i < start:
                    continue
                out.append(frame.to_ndarray(format="rgb24"))
                if count is not None and len(out) >= count:
                    break
    if not out:
        return np.zeros(shape, dtype=np.uint8)
    return np.stack(out)


def read_video_audio(path: str | os.PathLike, mono: bool = True,
                     max_seconds: float | None = None) -> tuple[np.ndarray, int]:
    """The first audio track as float32 in [-1, 1] and its sample rate: (samples,) when ``mono`` (channel mean,
    taken as the track is decoded), else (samples, channels). :class:`VideoError` if there is no audio track;
    :class:`AudioTrackTooLong` when its header claims, or its decoding reaches, more than ``max_seconds`` (default
    :data:`MAX_DECODED_AUDIO_S`; checked as it decodes: memory stays bounded whatever the header says)."""
    path = Path(path)
    max_seconds = MAX_DECODED_AUDIO_S if max_seconds is None else float(max_seconds)
    chunks: list[np.ndarray] = []
    with _open(path) as container:
        if not container.streams.audio:
            raise VideoError(f"{path}: no audio stream")
        stream = container.streams.audio[0]
        rate = int(stream.codec_context.sample_rate)
        claims = [float(stream.duration * stream.time_base)
                  if stream.duration is not None and stream.time_base is not None else None,
                  None if container.duration is None else container.duration / av.time_base]
        for seconds in claims:
            if seconds is not None and seconds > max_seconds:
                raise AudioTrackTooLong(f"{path}: its header gives {_span_words(seconds)} of audio, more than the "
                                        f"{_span_words(max_seconds)} a track is decoded for: {_too_long_advice()}")
        resampler = None
        held = 0
        try:
            for frame in container.decode(stream):
                if resampler is None:
                    # Same rate and layout, planar float: to_ndarray() gives (channels, samples).
                    resampler = av.AudioResampler(format="fltp", layout=frame.layout.name, rate=frame.sample_rate)
                    rate = int(frame.sample_rate)
                for out in resampler.resample(frame):
                    held += _keep_chunk(chunks, out.to_ndarray(), mono)
                if held > max_seconds * rate:
                    raise AudioTrackTooLong(f"{path}: more than {_span_words(max_seconds)} of audio decoded "
                                            f"({held} samples at {rate} Hz), the most a track is decoded for: "
                                            f"{_too_long_advice()}")
            if resampler is not None:
                for out in resampler.resample(None):
                    held += _keep_chunk(chunks, out.to_ndarray(), mono)
        except av.error.FFmpegError as exc:
            raise VideoError(f"{path}: audio decoding failed ({exc})") from exc
    if not chunks:
        raise VideoError(f"{path}: audio stream holds no samples")
    audio = np.concatenate(chunks) if mono else np.concatenate(chunks, axis=1).T   # (samples[, channels])
    return audio, rate


def _keep_chunk(chunks: list[np.ndarray], block: np.ndarray, mono: bool) -> int:
    """Append a decoded (channels, samples) block, clipped to [-1, 1] (then its channel mean when ``mono``); the
    samples it holds."""
    block = np.clip(block.astype(np.float32, copy=False), -1.0, 1.0)
    chunks.append(block.mean(axis=0, dtype=np.float32) if mono else block)
    return block.shape[1]


def _span_words(seconds: float) -> str:
    """``90 s``, ``2.5 min``, ``4 h``."""
    if seconds < 120:
        return f"{seconds:.3g} s"
    return f"{seconds / 60:.3g} min" if seconds < 7200 else f"{seconds / 3600:.3g} h"


def _too_long_advice() -> str:
    return (f"split the recording, or convert it to WAV or FLAC, which are read by range (up to "
            f"{_span_words(MAX_MEDIA_S)}); or the header is damaged")


def _encoder_available(name: str) -> bool:
    try:
        av.codec.Codec(name, "w")
    except (av.error.FFmpegError, ValueError, KeyError):
        return False
    return True


def choose_video_codec(container_format: str) -> str:
    """The video encoder :func:`write_video` uses for a container: h264 (libx264, else libopenh264) or MPEG-4 part 2
    for mp4/mov/mkv; MJPEG (else FFV1) for avi."""
    prefs = AVI_VIDEO_CODECS if container_format == "avi" else MP4_VIDEO_CODECS
    for name in prefs:
        if _encoder_available(name):
            return name
    raise VideoError(f"none of the video encoders {prefs} is available in this PyAV build")


def choose_audio_codec(container_format: str) -> str:
    prefs = AVI_AUDIO_CODECS if container_format == "avi" else MP4_AUDIO_CODECS
    for name in prefs + ("pcm_s16le",):
        if _encoder_available(name) and not (name.startswith("pcm") and container_format == "mp4"):
            return name
    raise VideoError(f"none of the audio encoders {prefs} is available in this PyAV build")


def _as_rate(fps: float) -> Fraction:
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps!r}")
    return Fraction(fps).limit_denominator(1001)


def _audio_2d(audio: np.ndarray) -> np.ndarray:
    """(samples, channels) float32 in [-1, 1] from float or int16 input of shape (samples,) or (samples, ch)."""
    a = np.asarray(audio)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2 or a.shape[1] not in (1, 2):
        raise ValueError(f"audio must be (samples,) or (samples, 1|2), got shape {np.asarray(audio).shape}")
    if a.dtype == np.int16:
        a = a.astype(np.float32) / 32768.0
    a = np.clip(a.astype(np.float32), -1.0, 1.0)
    return np.ascontiguousarray(a)


def write_video(path: str | os.PathLike, frames: Iterable[np.ndarray], fps: float,
                audio: np.ndarray | None = None, audio_rate: int | None = None,
                video_codec: str | None = None) -> Path:
    """Encode RGB uint8 frames (H, W, 3) to ``path`` and mux ``audio`` (float in [-1, 1] or int16; (samples,) or
    (samples, channels)) at ``audio_rate`` if given.

    ``.mp4``/``.m4v``/``.mov``/``.mkv``: H.264 (libx264 crf 18, else libopenh264) or MPEG-4 part 2, yuv420p (even
    sizes needed; odd sizes use yuv444p with libx264), audio AAC. ``.avi``: MJPEG (else FFV1), audio 16-bit PCM.
    ``video_codec`` overrides the choice (e.g. ``"ffv1"``: lossless RGB, in .avi or .mkv).
    Written to a temporary name in the same folder and renamed, so a failed write leaves no half file.
    """
    path = Path(path)
    fmt = _CONTAINERS.get(path.suffix.lower())
    if fmt is None:
        raise VideoError(f"{path}: unsupported video extension; use one of {sorted(_CONTAINERS)}")
    rate = _as_rate(fps)
    if audio is not None and (audio_rate is None or int(audio_rate) <= 0):
        raise ValueError("audio_rate is required with audio")
    samples = _audio_2d(audio) if audio is not None else None
    if video_codec is not None and not _encoder_available(video_codec):
        raise VideoError(f"{path}: video encoder {video_codec!r} is not available in this PyAV build")
    vcodec = video_codec or choose_video_codec(fmt)
    acodec = choose_audio_codec(fmt) if samples is not None else None

    it = iter(frames)
    try:
        first = _check_frame(next(it), None)
    except StopIteration:
        raise ValueError("write_video needs at least one frame") from None
    height, width = first.shape[:2]
    odd = (width % 2) or (height % 2)
    if odd and vcodec not in ("libx264", "mjpeg", "ffv1"):
        raise VideoError(f"{path}: {vcodec} needs even frame sizes, got {width}x{height}")

    try:
        # atomic: a uniquely named hidden temporary file (keeping the suffix), renamed over `path` when whole
        with atomic_path(path, keep_suffix=True) as tmp, av.open(str(tmp), mode="w", format=fmt) as out:
            vs = out.add_stream(vcodec, rate=rate)
            vs.width, vs.height = width, height
            if vcodec in ("libx264", "libopenh264"):
                vs.pix_fmt = "yuv444p" if odd else "yuv420p"
                if vcodec == "libx264":
                    vs.options = {"crf": "18", "preset": "fast"}
            elif vcodec == "mpeg4":
                vs.pix_fmt = "yuv420p"
                vs.codec_context.qscale = 2
                vs.codec_context.flags |= av.codec.context.Flags.qscale
            elif vcodec == "mjpeg":
                vs.pix_fmt = "yuvj444p"
                vs.options = {"q:v": "2"}
            elif vcodec == "ffv1":
                vs.pix_fmt = "bgr0"     # 8-bit RGB: lossless round trip of RGB frames
            else:
                vs.pix_fmt = "yuv420p"
            vs.codec_context.time_base = Fraction(1, 1) / rate

            astream = None
            layout = None
            if samples is not None:
                layout = "mono" if samples.shape[1] == 1 else "stereo"
                astream = out.add_stream(acodec, rate=int(audio_rate), layout=layout)
            a_pos = 0
            n_samples = 0 if samples is None else samples.shape[0]

            def push_audio(upto: int) -> None:
                nonlocal a_pos
                upto = min(upto, n_samples)
                step = 4096
                while a_pos < upto:
                    chunk = samples[a_pos:min(upto, a_pos + step)]
                    frame = av.AudioFrame.from_ndarray(np.ascontiguousarray(chunk.T), format="fltp",
                                                       layout=layout)
                    frame.sample_rate = int(audio_rate)
                    frame.pts = a_pos
                    frame.time_base = Fraction(1, int(audio_rate))
                    out.mux(astream.encode(frame))
                    a_pos += chunk.shape[0]

            index = 0
            frame_rgb = first
            while True:
                vf = av.VideoFrame.from_ndarray(frame_rgb, format="rgb24")
                vf.pts = index
                vf.time_base = vs.codec_context.time_base
                out.mux(vs.encode(vf))
                index += 1
                if astream is not None:
                    push_audio(int(round(index / float(rate) * int(audio_rate))))
                try:
                    frame_rgb = _check_frame(next(it), (height, width))
                except StopIteration:
                    break
            out.mux(vs.encode(None))
            if astream is not None:
                push_audio(n_samples)
                out.mux(astream.encode(None))
    except av.error.FFmpegError as exc:
        raise VideoError(f"{path}: video encoding failed ({exc})") from exc
    return path


def _check_frame(frame: np.ndarray, size: tuple[int, int] | None) -> np.ndarray:
    a = np.asarray(frame)
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"frames must be RGB uint8 (H, W, 3), got {a.dtype} {a.shape}")
    if size is not None and a.shape[:2] != size:
        raise ValueError(f"all frames must have the first frame's size {size}, got {a.shape[:2]}")
    return np.ascontiguousarray(a)


__all__ = [
    "VideoError", "VideoInfo", "choose_audio_codec", "choose_video_codec", "frame_times", "grid_rate",
    "iter_timed_frames", "iter_video_frames", "packet_frame_times", "probe_video", "read_timed_frames", "read_video_audio",
    "read_video_frames", "write_video",
]
