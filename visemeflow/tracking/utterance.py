"""Tracking one utterance from its video: landmarks on the video's frames, the camera (and the speaker's identity
for real footage), the optical-flow term, then the solver (paper 4.3).

Pure of orchestration and storage: the caller passes the utterance's files and its procedural curves and gets
arrays back. Bad input raises `TrackingInputError` with the file it concerns and a short error type.
"""

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from visemeflow.rig import VisemeRig
from visemeflow.tracking.camera import Intrinsics
from visemeflow.tracking.identity import (
    apply_identity,
    demo_identity_path,
    fit_identity,
    load_identity_modes,
    neutral_frames,
)
from visemeflow.tracking.landmarks import LandmarkError, LandmarkTrack, read_landmarks
from visemeflow.tracking.optical_flow import FlowConfig, estimate_optical_flow, roi_around
from visemeflow.tracking.photo import PhotoTerm
from visemeflow.tracking.solver import (
    FlowTerm,
    TrackingConfig,
    TrackingProblem,
    TrackingResult,
    flow_vertices,
    solve_faithful,
    solve_fast,
)
from visemeflow.tracking.video import VideoError, probe_video, read_video_frames

LANDMARK_FILES = "<name>.landmarks.csv|.parquet, .mediapipe478.csv, .openface.csv"
FALLBACK_FOV_DEG = 25.0


class TrackingInputError(ValueError):
    """Input that cannot be tracked: the file concerned (None when it is not one file), a short type, the reason."""

    def __init__(self, path: str | None, error_type: str, reason: str):
        super().__init__(f"{path}: {reason}" if path else reason)
        self.path, self.error_type, self.reason = path, error_type, reason

    def __reduce__(self):
        return (type(self), (self.path, self.error_type, self.reason))


@dataclass(frozen=True)
class VideoInput:
    """One utterance's video and landmark files, with the frame count and rate ingestion measured."""

    video_path: str
    landmark_path: str | None
    fps: float
    n_frames: int


@dataclass
class TrackedVideo:
    """What tracking one video gives: the solver's result, the landmarks used, the flow's valid fraction per
    frame ((T,), NaN at frame 0; None without flow) and how the camera/identity was chosen."""

    result: TrackingResult
    landmarks: LandmarkTrack
    flow_valid: np.ndarray | None
    camera_info: dict = field(default_factory=dict)


def camera_record_path(video_path: str) -> Path:
    """`<name>.camera.json` beside the video: the known intrinsics of a synthetic take."""
    video = Path(video_path)
    return video.with_name(video.name.rsplit(".", 1)[0] + ".camera.json")


def load_track(landmark_path: str | None, fps: float, n_frames: int, video_path: str | None = None) -> LandmarkTrack:
    """The landmark track of a video of `n_frames` frames, padded with missing frames to its length."""
    if not landmark_path:
        raise TrackingInputError(video_path, "NoLandmarks", f"no landmark file ({LANDMARK_FILES}) beside the video")
    try:
        track = read_landmarks(landmark_path, fps=fps)
    except LandmarkError as exc:
        raise TrackingInputError(landmark_path, "BadLandmarks",
                                 str(exc).removeprefix(f"{landmark_path}: ")) from exc
    if track.n_frames > n_frames + 1:
        raise TrackingInputError(landmark_path, "LandmarkFrameMismatch",
                                 f"{track.n_frames} landmark frames but the video has {n_frames}")
    points = np.full((n_frames, 68, 2), np.nan, np.float32)
    valid = np.zeros((n_frames, 68), bool)
    k = min(n_frames, track.n_frames)
    points[:k], valid[:k] = track.points[:k], track.valid[:k]
    if not valid.any():
        raise TrackingInputError(landmark_path, "NoLandmarks", "no frame has a detected landmark")
    return LandmarkTrack(points, valid, track.fps, track.source)


def rig_and_camera(video_path: str, rig: VisemeRig, track: LandmarkTrack) -> tuple[VisemeRig, Intrinsics, dict]:
    """The rig and intrinsics to track with.

    With `<name>.camera.json` beside the video (synthetic takes), its intrinsics and the rig as given. Otherwise
    (real video) the rig's identity is fitted to the speaker from the landmarks of neutral frames (paper 4.2, ICT
    identity modes) together with the focal length, and the fitted rig and camera are used.
    """
    record = camera_record_path(video_path)
    if record.exists():
        return rig, Intrinsics.from_record(json.loads(record.read_text())), {"identity": "given camera"}
    info = probe_video(video_path)
    fallback = Intrinsics.from_fov(info.width, info.height, FALLBACK_FOV_DEG)
    modes_path = demo_identity_path()
    modes = load_identity_modes(modes_path) if modes_path.exists() else None
    if modes is None or modes.modes.shape[1] != rig.n_vertices:
        return rig, fallback, {"identity": "none (no modes for this rig)"}
    frames = neutral_frames(track, n=10)
    if len(frames) == 0:
        return rig, fallback, {"identity": "none (no neutral frame)"}
    fit = fit_identity(rig, modes, track, frames, camera=None, image_size=(info.width, info.height))
    fitted = apply_identity(rig, modes, fit.coefficients, fit.scale)
    return fitted, fit.camera, {"identity": "fitted", "identity_rms_px": round(float(fit.rms_px), 3)}


def flow_term(frames: np.ndarray, rig: VisemeRig, track: LandmarkTrack) -> tuple[FlowTerm, np.ndarray]:
    """Optical-flow correspondences over the face region of `frames` ((T, H, W, 3)), and the valid fraction per
    frame ((T,), NaN at frame 0)."""
    height, width = frames.shape[1:3]
    roi = roi_around(track.points[track.valid].reshape(-1, 2), width, height, margin=0.15)
    flow = estimate_optical_flow(frames, FlowConfig(), roi)
    valid_fraction = np.array([np.nan] + [flow.valid_fraction(j) for j in range(1, len(frames))], np.float32)
    return FlowTerm(flow_vertices(rig), flow.correspondences, flow.backward_correspondences), valid_fraction


def track_video(video: VideoInput, procedural: np.ndarray, rig: VisemeRig, config: TrackingConfig) -> TrackedVideo:
    """Fit viseme curves to one video, guided by its procedural curves ((n_frames, 16)); TrackingInputError for
    input that cannot be tracked (missing or bad landmarks, unreadable or short video, a diverging solve)."""
    n_frames = video.n_frames
    if len(procedural) != n_frames:
        raise TrackingInputError(None, "FrameMismatch",
                                 f"procedural curves have {len(procedural)} frames, the video {n_frames}: rerun procedural")
    try:
        track = load_track(video.landmark_path, video.fps, n_frames, video.video_path)
        rig, camera, camera_info = rig_and_camera(video.video_path, rig, track)
        flow = flow_valid = photo = None
        if (config.use_flow and n_frames > 1) or config.use_rgb:
            frames = read_video_frames(video.video_path, 0, n_frames)
            if len(frames) < n_frames:
                raise TrackingInputError(video.video_path, "ShortVideo",
                                         f"decoded {len(frames)} frames, expected {n_frames}")
            if config.use_flow and n_frames > 1:
                flow, flow_valid = flow_term(frames, rig, track)
            if config.use_rgb:
                photo = PhotoTerm(rig, camera, frames, track.points)
        problem = TrackingProblem(rig, camera, track.points, track.valid, procedural, flow=flow, rgb=photo)
        result = (solve_fast if config.solver == "fast" else solve_faithful)(problem, config)
    except VideoError as exc:
        raise TrackingInputError(video.video_path, "UnreadableVideo", str(exc)) from exc
    except FloatingPointError as exc:
        raise TrackingInputError(video.video_path, "NonFiniteLoss", str(exc)) from exc
    return TrackedVideo(result, track, flow_valid, camera_info)
