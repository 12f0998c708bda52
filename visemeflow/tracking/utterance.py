"""Tracking one utterance from its video: landmarks on the video's frames, the camera (and the speaker's identity
for real footage), the optical-flow term, then the solver (paper 4.3).

Pure of orchestration and storage: the caller passes the utterance's files and its procedural curves (None: track
without phoneme guidance) and gets arrays back. Bad input raises `TrackingInputError` with the file it concerns and
a short error type.

Video time. Curves live on the utterance's grid, frame k at k / fps on the audio's clock (the `curves` table
contract, shared with the procedural curves and the audio). The video's frames are shown at their presentation
times (`video.frame_times`). When those are the grid (constant-rate video that starts with its audio: GRID, the
synthetic takes; within `UNIFORM_TOLERANCE_S`) tracking runs on the grid as it always did. Otherwise (variable
frame rate, a video starting after its audio, a rate other than the grid's) the solver runs on the decoded frames
at their true times, with the procedural curves sampled at those times, and its curves and poses are then
resampled onto the grid by linear interpolation in time (held before the first and after the last frame). Grid
frames with no video frame within half a grid step are the ones the video lacks: `TrackedVideo.video_frame` is -1
there, and their diagnostics (landmarks, mouth error, flow, every loss term) are missing, not invented.
"""

import functools
import os
import itertools
import json
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import BinaryIO
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from visemeflow.rig import VisemeRig
from visemeflow.visemes import N_VISEMES
from visemeflow.render.camera import Intrinsics
from visemeflow.tracking.identity import (
    SpeakerIdentity,
    apply_identity,
    demo_identity_path,
    fit_identity,
    load_identity_modes,
    neutral_frames,
)
from visemeflow.tracking.landmarks import LandmarkError, LandmarkTrack, read_landmarks
from visemeflow.tracking.optical_flow import FlowConfig, estimate_optical_flow, roi_around, roi_scale
from visemeflow.tracking.photo import PhotoTerm
from visemeflow.tracking.solver import (
    FlowTerm,
    TrackingConfig,
    TrackingProblem,
    TrackingResult,
    check_problem,
    flow_vertices,
    solve_faithful,
    solve_fast,
    solve_fast_many,
)
from visemeflow.tracking.video import _open as _open_video
from visemeflow.tracking.video import _video_stream
from visemeflow.tracking.video import (
    VideoError,
    VideoInfo,
    frame_times,
    iter_timed_frames,
    packet_frame_times,
    probe_video,
    read_timed_frames,
)

LANDMARK_FILES = "<name>.landmarks.csv|.parquet, .mediapipe478.csv, .openface.csv"
FALLBACK_FOV_DEG = 25.0
UNIFORM_TOLERANCE_S = 1e-3
"""Frames within this of k / fps (every one of the grid's frames) are the grid: tracked on it as they are."""
LANDMARK_FRAME_TOLERANCE = 1
"""How many frames a landmark file may have more or fewer than the video: decoders (OpenCV's, which landmark tools
use, and PyAV's) and the curve grid (duration x fps, rounded) can disagree about a last, partial frame. A shorter
file is padded with missing frames, a longer one cut; any larger difference is a file of another clip or a broken one
(5 rows for a 47-frame video), refused rather than tracked on mostly empty frames."""
COVERAGE_TOLERANCE_S = 0.1
"""How far the curve grid or the alignment may run past the video's last frame (ingest's default tolerance)."""


class TrackingInputError(ValueError):
    """Input that cannot be tracked: the file concerned (None when it is not one file), a short type, the reason."""

    def __init__(self, path: str | None, error_type: str, reason: str):
        super().__init__(f"{path}: {reason}" if path else reason)
        self.path, self.error_type, self.reason = path, error_type, reason

    def __reduce__(self):
        return (type(self), (self.path, self.error_type, self.reason))


@dataclass(frozen=True)
class VideoInput:
    """One utterance's video and landmark files, with its curve grid (rate and frame count) from ingestion.

    `audio_path` (when given) is checked to exist; when it is the video itself the video must have an audio track.
    `alignment_end_s` (when given) is where the utterance's phones end: past the video's end it is a reject."""

    video_path: str
    landmark_path: str | None
    fps: float
    n_frames: int
    audio_path: str | None = None
    alignment_path: str | None = None
    alignment_end_s: float | None = None


@dataclass
class TrackedVideo:
    """What tracking one video gives, on the curve grid ((T,) = the utterance's frames): the solver's result, the
    landmarks used, the flow's valid fraction per frame (NaN at frame 0; None without flow), how the
    camera/identity was chosen, the decoded frame shown at each grid frame (`video_frame`, -1 where the video
    lacks one and the curves are interpolated) and the decoded frames' times (s, audio clock)."""

    result: TrackingResult
    landmarks: LandmarkTrack
    flow_valid: np.ndarray | None
    camera_info: dict = field(default_factory=dict)
    video_frame: np.ndarray | None = None
    frame_times: np.ndarray | None = None

    @property
    def interpolated(self) -> np.ndarray:
        """(T,) bool: grid frames the video lacks (curves interpolated in time, no diagnostics)."""
        if self.video_frame is None:
            return np.zeros(len(self.result.curves), bool)
        return self.video_frame < 0

    @property
    def guided(self) -> bool:
        return bool(self.result.extra.get("guided", True))


@dataclass(frozen=True)
class FrameTimeline:
    """Where the decoded frames (shown at `times`, s) sit on the curve grid k / `fps`, k < `n_grid`."""

    times: np.ndarray
    fps: float
    n_grid: int

    @property
    def grid_times(self) -> np.ndarray:
        return np.arange(self.n_grid, dtype=np.float64) / self.fps

    @property
    def uniform(self) -> bool:
        """The first `n_grid` frames are the grid's frames (so tracking runs on the grid as it is)."""
        return (len(self.times) >= self.n_grid
                and bool(np.abs(self.times[:self.n_grid] - self.grid_times).max() <= UNIFORM_TOLERANCE_S))

    def video_frame(self) -> np.ndarray:
        """(n_grid,) the decoded frame within half a grid step of each grid frame (the nearest), -1 where none."""
        grid = self.grid_times
        right = np.clip(np.searchsorted(self.times, grid), 1, len(self.times) - 1) if len(self.times) > 1 else \
            np.zeros(len(grid), int)
        left = np.maximum(right - 1, 0)
        nearest = np.where(np.abs(self.times[left] - grid) <= np.abs(self.times[right] - grid), left, right)
        close = np.abs(self.times[nearest] - grid) < 0.5 / self.fps
        return np.where(close, nearest, -1)

    def to_frames(self, values: np.ndarray) -> np.ndarray:
        """Grid values (n_grid, ...) linearly interpolated at the frames' times (held beyond the grid's ends)."""
        return _interp(self.times, self.grid_times, values)

    def to_grid(self, values: np.ndarray) -> np.ndarray:
        """Per-frame values (frames, ...) linearly interpolated at the grid's times (held beyond the frames)."""
        return _interp(self.grid_times, self.times, values)


def _interp(at: np.ndarray, times: np.ndarray, values: np.ndarray) -> np.ndarray:
    values = np.asarray(values)
    flat = values.reshape(len(values), -1).astype(np.float64)
    out = np.stack([np.interp(at, times, flat[:, i]) for i in range(flat.shape[1])], axis=1)
    return out.reshape((len(at),) + values.shape[1:]).astype(values.dtype)


def _pick(values: np.ndarray, index: np.ndarray, fill) -> np.ndarray:
    """values[index] where index >= 0, else `fill`."""
    out = values[np.maximum(index, 0)].copy()
    out[index < 0] = fill
    return out


def on_grid(tracked: TrackedVideo, timeline: FrameTimeline) -> TrackedVideo:
    """A result solved on the decoded frames, moved to the curve grid: curves and pose interpolated in time, the
    per-frame diagnostics of the frame shown at each grid frame (missing where the video lacks one)."""
    r, index = tracked.result, timeline.video_frame()
    curves = np.clip(timeline.to_grid(r.curves), 0.0, 1.0).astype(np.float32)
    terms = {k: _pick(np.asarray(v, np.float32), index, np.nan) for k, v in r.terms.items()}
    result = TrackingResult(
        curves, timeline.to_grid(r.rotation), timeline.to_grid(r.translation), terms,
        _pick(np.asarray(r.mouth_error_px, np.float32), index, np.nan), r.seconds, r.iterations,
        {**r.extra, "video_frames": len(timeline.times), "interpolated_frames": int((index < 0).sum())},
    )
    lm = tracked.landmarks
    landmarks = LandmarkTrack(_pick(lm.points, index, np.nan), _pick(lm.valid, index, False), lm.fps, lm.source)
    flow_valid = None if tracked.flow_valid is None else _pick(tracked.flow_valid, index, np.nan)
    return TrackedVideo(result, landmarks, flow_valid, tracked.camera_info, index, timeline.times)


CAMERA_SUFFIX = ".camera.json"
"""`<name>.camera.json` beside a video: the known intrinsics of a synthetic take (what `local_input` of a video on
object storage must bring along: `beside=(CAMERA_SUFFIX,)`)."""


def camera_record_path(video_path: str) -> Path:
    """`<name>.camera.json` beside the video: the known intrinsics of a synthetic take."""
    video = Path(video_path)
    return video.with_name(video.name.rsplit(".", 1)[0] + CAMERA_SUFFIX)


def load_track(landmark_path: str | None, fps: float, n_frames: int, video_path: str | None = None) -> LandmarkTrack:
    """The landmark track of a video of `n_frames` frames (the file within LANDMARK_FRAME_TOLERANCE of that), padded
    with missing frames or cut to its length."""
    if not landmark_path:
        raise TrackingInputError(video_path, "NoLandmarks", f"no landmark file ({LANDMARK_FILES}) beside the video "
                                 "and none stored by the landmarks stage (run `visemeflow landmarks`; where it "
                                 "found no face, `visemeflow rejects --stage landmarks` says so)")
    try:
        track = read_landmarks(landmark_path, fps=fps)
    except LandmarkError as exc:
        raise TrackingInputError(landmark_path, "BadLandmarks",
                                 str(exc).removeprefix(f"{landmark_path}: ")) from exc
    if abs(track.n_frames - n_frames) > LANDMARK_FRAME_TOLERANCE:
        raise TrackingInputError(landmark_path, "LandmarkFrameMismatch",
                                 f"{track.n_frames} landmark frames but the video has {n_frames} (a landmark file "
                                 f"has a row per video frame, up to its last; {LANDMARK_FRAME_TOLERANCE} frame more "
                                 "or fewer is allowed)")
    points = np.full((n_frames, 68, 2), np.nan, np.float32)
    valid = np.zeros((n_frames, 68), bool)
    k = min(n_frames, track.n_frames)
    points[:k], valid[:k] = track.points[:k], track.valid[:k]
    if not valid.any():
        raise TrackingInputError(landmark_path, "NoLandmarks", "no frame has a detected landmark")
    return LandmarkTrack(points, valid, track.fps, track.source)


def identity_modes_for(rig: VisemeRig):
    """The shipped identity modes when they fit `rig`'s mesh, else None (no identity fit for this rig)."""
    modes_path = demo_identity_path()
    modes = load_identity_modes(modes_path) if modes_path.exists() else None
    return modes if modes is not None and modes.modes.shape[1] == rig.n_vertices else None


def needs_identity(video_path: str) -> bool:
    """Whether tracking this video fits a face and camera to it: real video, without `<name>.camera.json`."""
    return not camera_record_path(video_path).exists()


def video_size(video: str | BinaryIO) -> tuple[int, int] | None:
    """(width, height) of the video's frames from its stream header (no decoding); None when it cannot be read.
    `video`: a path, or a seekable binary file object (an object on S3 opened by fsspec: only the bytes of its
    header are fetched)."""
    local = isinstance(video, str | os.PathLike)
    name = Path(video) if local else Path(str(getattr(video, "path", "video")))
    try:
        with _open_video(Path(video) if local else video) as container:
            stream = _video_stream(container, name)
            width, height = int(stream.codec_context.width), int(stream.codec_context.height)
    except VideoError:
        return None
    return (width, height) if width and height else None


def rig_and_camera(video_path: str, rig: VisemeRig, track: LandmarkTrack, info: VideoInfo | None = None,
                   identity: SpeakerIdentity | None = None) -> tuple[VisemeRig, Intrinsics, dict]:
    """The rig and intrinsics to track with.

    With `<name>.camera.json` beside the video (synthetic takes), its intrinsics and the rig as given. Otherwise
    (real video) the speaker's face and camera: `identity` (fitted once per speaker and image size on neutral
    frames of a few of their clips, `identity.fit_speaker_identity`) when given and of this video's size; else the
    rig's identity is fitted to this clip's neutral frames (paper 4.2, ICT identity modes) together with the focal
    length. `info`: the video's `probe_video`, when the caller has it (probed here otherwise).
    """
    record = camera_record_path(video_path)
    if record.exists():
        return rig, Intrinsics.from_record(json.loads(record.read_text())), {"identity": "given camera"}
    info = info or probe_video(video_path)
    fallback = Intrinsics.from_fov(info.width, info.height, FALLBACK_FOV_DEG)
    modes = identity_modes_for(rig)
    if modes is None:
        return rig, fallback, {"identity": "none (no modes for this rig)"}
    if identity is not None and tuple(identity.image_size) == (info.width, info.height):
        return identity.apply(rig, modes), identity.camera(FALLBACK_FOV_DEG), {
            "identity": "speaker", "identity_rms_px": round(float(identity.rms_px), 3),
            "identity_clips": len(identity.clips), "identity_digest": identity.digest}
    frames = neutral_frames(track, n=10)
    if len(frames) == 0:
        return rig, fallback, {"identity": "none (no neutral frame)"}
    fit = fit_identity(rig, modes, track, frames, camera=None, image_size=(info.width, info.height))
    fitted = apply_identity(rig, modes, fit.coefficients, fit.scale)
    return fitted, fit.camera, {"identity": "fitted", "identity_rms_px": round(float(fit.rms_px), 3)}


# The 68 landmarks around the part of the face L_flow follows (`solver.flow_vertices`: between the bottom of the
# nose and the chin, about the mouth's width): the chin's stretch of the jaw line, the nose's base and the mouth.
LOWER_FACE_POINTS = np.r_[4:13, 31:36, 48:68]


def flow_config_of(config: TrackingConfig) -> FlowConfig:
    """The DIS settings of L_flow that `config` names."""
    return FlowConfig(preset=config.flow_preset, max_roi_px=config.flow_max_roi_px)


def flow_roi(track: LandmarkTrack, width: int, height: int, region: str = "lower") -> tuple[int, int, int, int]:
    """The region (x0, y0, w, h) of a width x height clip on which L_flow's optical flow is computed: around all
    frames' landmarks of the whole face ("face") or of the lower face only ("lower", `LOWER_FACE_POINTS`; the whole
    face's region where no lower-face landmark was detected), grown by 15% of its size on every side."""
    if region not in ("face", "lower"):
        raise ValueError(f"flow region must be 'face' or 'lower', got {region!r}")
    lower = track.points[:, LOWER_FACE_POINTS]
    points = lower if region == "lower" and np.isfinite(lower).all(axis=-1).any() else track.points
    return roi_around(points.reshape(-1, 2), width, height, margin=0.15)


MIN_FLOW_SIDE_PX = 32
"""The lower face's region is used only while its shorter side, at the whole face's resolution, keeps this many
array pixels: DIS fails on crops of about 12 px, and a few detected points make a sliver."""


def flow_regions(track: LandmarkTrack, width: int, height: int, region: str,
                 config: FlowConfig) -> tuple[tuple[int, int, int, int], tuple[int, int, int, int]]:
    """(the region DIS runs on, the whole face's region whose size sets the resolution): the lower face's for
    `region` "lower" unless it is too small at that resolution (`MIN_FLOW_SIDE_PX`) or lies outside the image, then
    the whole face's."""
    face = flow_roi(track, width, height, "face")
    if region == "face":
        return face, face
    try:
        lower = flow_roi(track, width, height, region)
    except ValueError:         # outside the image
        return face, face
    small = min(lower[2], lower[3]) * roi_scale(face, config) < MIN_FLOW_SIDE_PX
    return (face if small else lower), face


def flow_term(frames: Iterable[np.ndarray], rig: VisemeRig, track: LandmarkTrack,
              config: FlowConfig | None = None, region: str = "lower") -> tuple[FlowTerm, np.ndarray]:
    """Optical-flow correspondences over the lower face (`region` "lower", see `flow_roi`) or the whole face
    ("face") of `frames` ((T, H, W, 3), or RGB frames one at a time: only their crops are kept), and the valid
    fraction per frame ((T,), NaN at frame 0). Either region is sampled at the resolution `config.max_roi_px`
    sets for the whole face."""
    it = iter(frames)
    first = next(it, None)
    if first is None:
        raise ValueError("flow_term needs at least one frame")
    height, width = first.shape[:2]
    config = config or FlowConfig()
    roi, face = flow_regions(track, width, height, region, config)
    flow = estimate_optical_flow(itertools.chain([first], it), config, roi, scale_roi=face)
    valid_fraction = np.array([np.nan] + [flow.valid_fraction(j) for j in range(1, flow.n_frames)], np.float32)
    return (FlowTerm(flow_vertices(rig), flow.correspondences, flow.backward_correspondences,
                     flow.all_correspondences), valid_fraction)


def _counted(frames: Iterable[np.ndarray], seen: Callable[[int], None]) -> Iterator[np.ndarray]:
    """The frames, `seen(k)` called before the k-th (0-based) is handed on."""
    for k, frame in enumerate(frames):
        seen(k)
        yield frame


def _audio_is_video(video: VideoInput) -> bool:
    return video.audio_path is not None and (not video.audio_path or Path(video.audio_path) == Path(video.video_path))


def check_audio(video: VideoInput, info: VideoInfo | None = None) -> None:
    """The utterance's audio must exist; when it is the video's own track, the video must have one (`info`: the
    video's `probe_video`, when the caller has it)."""
    audio = video.audio_path
    if audio is None:
        return
    if _audio_is_video(video):
        if not (info or probe_video(video.video_path)).has_audio:
            raise TrackingInputError(video.video_path, "MissingAudio",
                                     "no audio file for the utterance and no audio track in its video")
    elif not Path(audio).is_file():
        raise TrackingInputError(audio, "MissingAudio", "the utterance's audio file is missing")


def check_coverage(video: VideoInput, times: np.ndarray) -> None:
    """The video must reach the end of the curve grid and of the alignment (within COVERAGE_TOLERANCE_S)."""
    step = 1.0 / video.fps
    end = float(times[-1]) + step            # the last frame is shown until one frame later
    grid_end = video.n_frames * step
    if grid_end > end + COVERAGE_TOLERANCE_S:
        raise TrackingInputError(video.video_path, "ShortVideo",
                                 f"the video's frames end at {end:.3f} s ({len(times)} frames) but its curves "
                                 f"run to {grid_end:.3f} s ({video.n_frames} frames at {video.fps:g} fps)")
    if video.alignment_end_s is not None and video.alignment_end_s > end + COVERAGE_TOLERANCE_S:
        raise TrackingInputError(video.alignment_path or video.video_path, "AlignmentPastVideo",
                                 f"the alignment runs to {video.alignment_end_s:.3f} s but the video "
                                 f"{video.video_path} ends at {end:.3f} s (tolerance {COVERAGE_TOLERANCE_S} s)")


def track_video(video: VideoInput, procedural: np.ndarray | None, rig: VisemeRig,
                config: TrackingConfig, on_step: Callable[[str, int, int], None] | None = None,
                identity: SpeakerIdentity | None = None) -> TrackedVideo:
    """Fit viseme curves to one video on its curve grid ((n_frames, 16)), guided by its procedural curves on that
    grid, or unguided when `procedural` is None (no alignment: no L_sup/L_act, weights start from the neutral
    face). TrackingInputError for input that cannot be tracked (missing or bad landmarks, unreadable or short
    video, no audio, an alignment past the video's end, a diverging solve). `on_step(phase, done, total)` hears
    the progress of the long parts: "optical flow" (frames) and "solve" (iterations, or frames when faithful).
    `identity`: the speaker's face and camera (`rig_and_camera`); None fits them to this clip."""
    prepared = _prepare(video, procedural, rig, config, on_step, identity)
    solve = solve_fast if prepared.config.solver == "fast" else solve_faithful
    try:
        result = solve(prepared.problem, prepared.config,
                       None if on_step is None else (lambda k, n: on_step("solve", k, n)))
    except FloatingPointError as exc:
        raise TrackingInputError(video.video_path, "NonFiniteLoss", str(exc)) from exc
    return prepared.finish(result)


@dataclass
class _Prepared:
    """One video made ready for the solver: its problem and what turns the solve into a TrackedVideo."""

    video: VideoInput
    config: TrackingConfig
    problem: TrackingProblem
    track: LandmarkTrack
    flow_valid: np.ndarray | None
    camera_info: dict
    timeline: FrameTimeline
    times: np.ndarray
    guided: bool

    def finish(self, result: TrackingResult) -> TrackedVideo:
        result.extra["guided"] = self.guided
        if self.timeline.uniform:
            return TrackedVideo(result, self.track, self.flow_valid, self.camera_info,
                                np.arange(self.video.n_frames), self.times)
        return on_grid(TrackedVideo(result, self.track, self.flow_valid, self.camera_info), self.timeline)


def _prepare(video: VideoInput, procedural: np.ndarray | None, rig: VisemeRig, config: TrackingConfig,
             on_step: Callable[[str, int, int], None] | None, identity: SpeakerIdentity | None) -> _Prepared:
    """Everything of `track_video` before the solve: checks, frame times, landmarks, identity, optical flow."""
    n_grid = video.n_frames
    guided = procedural is not None
    if not guided and config.guidance:
        config = config.model_copy(update={"guidance": False})
    if guided and len(procedural) != n_grid:
        raise TrackingInputError(None, "FrameMismatch",
                                 f"procedural curves have {len(procedural)} frames, the video {n_grid}: rerun procedural")
    try:
        # one probe for the audio check and the camera (probing decodes a clip whose container stores no frame count)
        info = probe_video(video.video_path) if _audio_is_video(video) else None
        check_audio(video, info)
        # Frame times from the packets, without decoding, where the container vouches for them and the flow's pass
        # decodes every frame anyway to check them; anything else (no such times, a time that differs, an error on
        # the way) prepares again from decoded times, exactly as without them.
        quick = packet_frame_times(video.video_path) if config.use_flow and not config.use_rgb else None
    except VideoError as exc:
        raise TrackingInputError(video.video_path, exc.error_type,
                                 str(exc).removeprefix(f"{Path(video.video_path)}: ")) from exc
    if quick is not None:
        try:
            return _prepare_on(video, procedural, rig, config, on_step, identity, info, quick)
        except (_TimesDisagree, TrackingInputError):
            pass
    return _prepare_on(video, procedural, rig, config, on_step, identity, info, None)


class _TimesDisagree(Exception):
    """Frame times read from the packets that the decoded frames do not bear out."""


class _CheckedFrames:
    """The decoded (frame, time) pairs of a video, each time compared with `times` (read from its packets)."""

    def __init__(self, pairs: Iterable[tuple[np.ndarray, float]], times: np.ndarray):
        self.pairs, self.times, self.seen = iter(pairs), times, 0

    def _check(self, t: float) -> None:
        k, self.seen = self.seen, self.seen + 1
        if k >= len(self.times) or t != self.times[k]:
            raise _TimesDisagree(f"frame {k}")

    def first(self, n: int) -> Iterator[np.ndarray]:
        """The first `n` frames (_TimesDisagree at a frame whose time differs, or when the video ends first)."""
        while self.seen < n:
            frame, t = next(self.pairs, (None, None))
            if frame is None:
                raise _TimesDisagree(f"{self.seen} frames decoded, {len(self.times)} time stamps")
            self._check(t)
            yield frame

    def finish(self) -> None:
        """Decode the rest and check it: as many frames as times, each at its time."""
        for _, t in self.pairs:
            self._check(t)
        if self.seen != len(self.times):
            raise _TimesDisagree(f"{self.seen} frames decoded, {len(self.times)} time stamps")


def _prepare_on(video: VideoInput, procedural: np.ndarray | None, rig: VisemeRig, config: TrackingConfig,
                on_step: Callable[[str, int, int], None] | None, identity: SpeakerIdentity | None,
                info: VideoInfo | None, quick: np.ndarray | None) -> _Prepared:
    """`_prepare` on the frame times `quick` (read from the packets; checked against the flow's decoded frames,
    _TimesDisagree where they differ), or on times decoded here when None."""
    n_grid = video.n_frames
    guided = procedural is not None
    try:
        # The clip is held whole only for the photometric term; flow decodes it again frame by frame and keeps the
        # face crops, so a 4K clip never sits in memory (bench/memory_tracking.py).
        if config.use_rgb:
            frames, times = read_timed_frames(video.video_path)
        else:
            frames, times = None, frame_times(video.video_path) if quick is None else quick
        timeline = FrameTimeline(times, float(video.fps), n_grid)
        check_coverage(video, times)
        if timeline.uniform:            # the frames are the grid: as tracked before frame times were read
            n_frames = n_grid
            frames = None if frames is None else frames[:n_grid]
            prior = procedural if guided else np.zeros((n_grid, N_VISEMES), np.float32)
        else:
            n_frames = len(times)
            prior = (timeline.to_frames(procedural).astype(np.float32) if guided
                     else np.zeros((n_frames, N_VISEMES), np.float32))
        track = load_track(video.landmark_path, video.fps, n_frames, video.video_path)
        rig, camera, camera_info = rig_and_camera(video.video_path, rig, track, info, identity)
        flow = flow_valid = photo = None
        checked = None if quick is None else _CheckedFrames(iter_timed_frames(video.video_path), quick)
        if config.use_flow and n_frames > 1:
            if frames is not None:
                decoded = frames
            elif checked is not None:
                decoded = checked.first(n_frames)
            else:
                decoded = (f for f, _ in itertools.islice(iter_timed_frames(video.video_path), n_frames))
            if on_step is not None:
                decoded = _counted(decoded, lambda k: on_step("optical flow", k, n_frames))
            flow, flow_valid = flow_term(decoded, rig, track, flow_config_of(config), config.flow_region)
        if checked is not None:
            checked.finish()
        if config.use_rgb:
            photo = PhotoTerm(rig, camera, frames, track.points)
    except VideoError as exc:
        raise TrackingInputError(video.video_path, exc.error_type,
                                 str(exc).removeprefix(f"{Path(video.video_path)}: ")) from exc
    problem = TrackingProblem(rig, camera, track.points, track.valid, prior, flow=flow, rgb=photo)
    try:
        check_problem(problem)
    except ValueError as exc:
        raise TrackingInputError(video.video_path, "BadTrackingInput", str(exc)) from exc
    return _Prepared(video, config, problem, track, flow_valid, camera_info, timeline, times, guided)


def track_videos(videos: Sequence[tuple[VideoInput, np.ndarray | None]], rig: VisemeRig, config: TrackingConfig,
                 identities: Sequence[SpeakerIdentity | None] | None = None,
                 on_step: Callable[[int, str, int, int], None] | None = None, device: str = "cpu",
                 ) -> list[TrackedVideo | TrackingInputError]:
    """`track_video` of several (video, procedural curves or None) with one joint solve (`solve_fast_many`: the
    same curves as one by one, at a fraction of the solver's cost). One TrackedVideo or TrackingInputError per
    video, in order: a bad video never stops the others. `on_step(index, phase, done, total)`: progress, `index`
    the video's place, -1 for the joint solve. `device`: where the joint solve runs (`solve_fast_many`). The
    faithful solver runs one video at a time."""
    identities = list(identities) if identities is not None else [None] * len(videos)
    out: list[TrackedVideo | TrackingInputError | None] = [None] * len(videos)
    ready: list[tuple[int, _Prepared]] = []
    for i, ((video, procedural), identity) in enumerate(zip(videos, identities)):
        step = None if on_step is None else functools.partial(on_step, i)
        try:
            if config.solver != "fast":
                out[i] = track_video(video, procedural, rig, config, step, identity)
            else:
                ready.append((i, _prepare(video, procedural, rig, config, step, identity)))
        except TrackingInputError as exc:
            out[i] = exc
    # guided and unguided clips differ in their configs (no guidance without an alignment): one solve per config
    groups: dict[str, list[tuple[int, _Prepared]]] = {}
    for item in ready:
        groups.setdefault(item[1].config.model_dump_json(), []).append(item)
    for members in groups.values():
        solved = solve_fast_many([p.problem for _, p in members], members[0][1].config,
                                 None if on_step is None else (lambda k, n: on_step(-1, "solve", k, n)), device)
        for (i, prepared), result in zip(members, solved):
            if isinstance(result, FloatingPointError):
                out[i] = TrackingInputError(prepared.video.video_path, "NonFiniteLoss", str(result))
            else:
                out[i] = prepared.finish(result)
    return out  # type: ignore[return-value]
