"""Tracking task: phoneme-guided viseme fitting of one utterance's video into `tracked` curves."""

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
from prefect import get_run_logger, task

from visemeflow.hashing import stable_hash
from visemeflow.rig import VisemeRig, load_rig
from visemeflow.schemas import (
    LOSS_TERMS,
    TRACKING_FRAMES,
    C,
    curves_array,
    curves_table,
)
from visemeflow.storage import Store
from visemeflow.tasks.common import CACHE_POLICY
from visemeflow.tracking.camera import Intrinsics
from visemeflow.tracking.optical_flow import FlowConfig, estimate_optical_flow, roi_around
from visemeflow.tracking.identity import (
    apply_identity,
    demo_identity_path,
    fit_identity,
    load_identity_modes,
    neutral_frames,
)
from visemeflow.tracking.landmarks import LandmarkError, LandmarkTrack, read_landmarks
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

STAGE = "track"
SOURCE = "tracked"


class TrackError(ValueError):
    """An utterance that cannot be tracked; names the utterance, the file and the reason."""

    def __init__(self, utterance_id: str, path: str | None, error_type: str, reason: str):
        super().__init__(f"{utterance_id}: {path}: {reason}" if path else f"{utterance_id}: {reason}")
        self.utterance_id, self.path, self.error_type, self.reason = utterance_id, path, error_type, reason

    def __reduce__(self):
        return (type(self), (self.utterance_id, self.path, self.error_type, self.reason))


def camera_record_path(video_path: str) -> Path:
    video = Path(video_path)
    return video.with_name(video.name.rsplit(".", 1)[0] + ".camera.json")


def load_track(utterance: dict, n_frames: int) -> LandmarkTrack:
    """The utterance's landmark track, padded with missing frames to the video's length."""
    uid, path = utterance[C.UTTERANCE_ID], utterance[C.LANDMARK_PATH]
    if not path:
        raise TrackError(uid, utterance[C.VIDEO_PATH], "NoLandmarks",
                         "no landmark file (<name>.landmarks.csv|.parquet, .mediapipe478.csv, .openface.csv) beside the video")
    try:
        track = read_landmarks(path, fps=utterance[C.FPS])
    except LandmarkError as exc:
        raise TrackError(uid, path, "BadLandmarks", str(exc).removeprefix(f"{path}: ")) from exc
    if track.n_frames > n_frames + 1:
        raise TrackError(uid, path, "LandmarkFrameMismatch",
                         f"{track.n_frames} landmark frames but the video has {n_frames}")
    points = np.full((n_frames, 68, 2), np.nan, np.float32)
    valid = np.zeros((n_frames, 68), bool)
    k = min(n_frames, track.n_frames)
    points[:k], valid[:k] = track.points[:k], track.valid[:k]
    if not valid.any():
        raise TrackError(uid, path, "NoLandmarks", "no frame has a detected landmark")
    return LandmarkTrack(points, valid, track.fps, track.source)


def rig_and_camera(utterance: dict, rig: VisemeRig, track: LandmarkTrack) -> tuple[VisemeRig, Intrinsics, dict]:
    """The rig and intrinsics to track with.

    With `<name>.camera.json` beside the video (synthetic takes), its intrinsics and the rig as given. Otherwise
    (real video) the rig's identity is fitted to the speaker from the landmarks of neutral frames (paper 4.2, ICT
    identity modes) together with the focal length, and the fitted rig and camera are used.
    """
    record = camera_record_path(utterance[C.VIDEO_PATH])
    if record.exists():
        return rig, Intrinsics.from_record(json.loads(record.read_text())), {"identity": "given camera"}
    info = probe_video(utterance[C.VIDEO_PATH])
    modes_path = demo_identity_path()
    if not modes_path.exists() or load_identity_modes(modes_path).modes.shape[1] != rig.n_vertices:
        return rig, Intrinsics.from_fov(info.width, info.height, 25.0), {"identity": "none (no modes for this rig)"}
    modes = load_identity_modes(modes_path)
    frames = neutral_frames(track, n=10)
    if len(frames) == 0:
        return rig, Intrinsics.from_fov(info.width, info.height, 25.0), {"identity": "none (no neutral frame)"}
    fit = fit_identity(rig, modes, track, frames, camera=None, image_size=(info.width, info.height))
    fitted = apply_identity(rig, modes, fit.coefficients, fit.scale)
    return fitted, fit.camera, {"identity": "fitted", "identity_rms_px": round(float(fit.rms_px), 3)}


def flow_term(frames: np.ndarray, rig: VisemeRig, track: LandmarkTrack) -> tuple[FlowTerm, np.ndarray]:
    """Optical-flow correspondences over the face region of the video, and the valid fraction per frame."""
    height, width = frames.shape[1:3]
    roi = roi_around(track.points[track.valid].reshape(-1, 2), width, height, margin=0.15)
    field = estimate_optical_flow(frames, FlowConfig(), roi)
    valid_fraction = np.array([np.nan] + [field.valid_fraction(j) for j in range(1, len(frames))], np.float32)
    return FlowTerm(flow_vertices(rig), field.correspondences, field.backward_correspondences), valid_fraction


def diagnostics_table(uid: str, variant: str, result: TrackingResult, track: LandmarkTrack,
                      flow_valid: np.ndarray | None) -> pa.Table:
    n = len(result.curves)
    columns = {
        C.UTTERANCE_ID: [uid] * n, C.VARIANT: [variant] * n, C.FRAME: np.arange(n, dtype=np.int32),
        C.MOUTH_ERROR_PX: pa.array(result.mouth_error_px, pa.float32(), from_pandas=True),
        C.LANDMARKS_VALID: track.valid.any(axis=1),
        C.FLOW_VALID_FRACTION: pa.array(flow_valid if flow_valid is not None else np.full(n, np.nan), pa.float32(),
                                        from_pandas=True),
    }
    for term in LOSS_TERMS:
        values = result.terms.get(term)
        columns[C.LOSS_PREFIX + term] = pa.array(values if values is not None else np.full(n, np.nan), pa.float32(),
                                                 from_pandas=True)
    pose = np.concatenate([result.rotation, result.translation], axis=1).astype(np.float32)
    for i, name in enumerate(C.POSE_COLUMNS):
        columns[name] = pose[:, i]
    return pa.table(columns, schema=TRACKING_FRAMES)


def track_one(store: Store, utterance: dict, procedural_variant: str, rig: VisemeRig, config: TrackingConfig) -> dict:
    """Track one utterance and store its curves and diagnostics; raises TrackError for bad input."""
    uid = utterance[C.UTTERANCE_ID]
    video = utterance[C.VIDEO_PATH]
    if not video:
        raise TrackError(uid, None, "NoVideo", "the utterance has no video")
    try:
        n_frames = int(utterance[C.N_FRAMES])
        track = load_track(utterance, n_frames)
        rig, camera, fit_info = rig_and_camera(utterance, rig, track)
        try:
            procedural = curves_array(store.read_curves(uid, "procedural", procedural_variant))
        except LookupError as exc:
            raise TrackError(uid, None, "NoProceduralCurves", f"{exc}; run the procedural stage first") from exc
        if len(procedural) != n_frames:
            raise TrackError(uid, None, "FrameMismatch",
                             f"procedural curves have {len(procedural)} frames, the video {n_frames}: rerun procedural")
        flow = flow_valid = photo = None
        if (config.use_flow and n_frames > 1) or config.use_rgb:
            frames = read_video_frames(video, 0, n_frames)
            if len(frames) < n_frames:
                raise TrackError(uid, video, "ShortVideo", f"decoded {len(frames)} frames, expected {n_frames}")
            if config.use_flow and n_frames > 1:
                flow, flow_valid = flow_term(frames, rig, track)
            if config.use_rgb:
                photo = PhotoTerm(rig, camera, frames, track.points)
        problem = TrackingProblem(rig, camera, track.points, track.valid, procedural, flow=flow, rgb=photo)
        result = (solve_fast if config.solver == "fast" else solve_faithful)(problem, config)
    except VideoError as exc:
        raise TrackError(uid, video, "UnreadableVideo", str(exc)) from exc
    except FloatingPointError as exc:
        raise TrackError(uid, video, "NonFiniteLoss", str(exc)) from exc
    variant = config.variant
    store.write_curves(curves_table(uid, SOURCE, variant, result.curves, utterance[C.FPS]),
                       provenance=f"{SOURCE}:{utterance[C.CONTENT_HASH]}:{stable_hash(config)}", fps=utterance[C.FPS])
    store.write_tracking_frames(diagnostics_table(uid, variant, result, track, flow_valid))
    return {
        "utterance_id": uid, "frames": n_frames, "seconds": round(result.seconds, 3),
        "mouth_error_px": float(np.nanmean(result.mouth_error_px)) if np.isfinite(result.mouth_error_px).any() else None,
        "variant": variant, **fit_info,
    }


@task(cache_policy=CACHE_POLICY, persist_result=True, task_run_name="track[{utterance[utterance_id]}]")
def track_utterance(
    store_root: str, utterance: dict, procedural_variant: str, procedural_provenance: str, rig_path: str,
    rig_hash: str, config: TrackingConfig,
) -> dict:
    """Track one utterance (cached on its inputs' content hash, the procedural curves, the rig and the config)."""
    rig = load_rig(rig_path)
    report = track_one(Store(store_root), utterance, procedural_variant, rig, config)
    get_run_logger().info("%s: %d frames in %.2f s, mouth error %s px", report["utterance_id"], report["frames"],
                          report["seconds"], report["mouth_error_px"])
    return report
