"""Tracking task: phoneme-guided viseme fitting of one utterance's video into `tracked` curves.

The tracking itself is `visemeflow.tracking.utterance.track_video`; this task reads the procedural curves from the
store, calls it, and writes the curves and per-frame diagnostics back.
"""

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
from visemeflow.tracking.solver import TrackingConfig
from visemeflow.tracking.utterance import TrackedVideo, TrackingInputError, VideoInput, track_video

STAGE = "track"
SOURCE = "tracked"


class TrackError(ValueError):
    """An utterance that cannot be tracked; names the utterance, the file and the reason."""

    def __init__(self, utterance_id: str, path: str | None, error_type: str, reason: str):
        super().__init__(f"{utterance_id}: {path}: {reason}" if path else f"{utterance_id}: {reason}")
        self.utterance_id, self.path, self.error_type, self.reason = utterance_id, path, error_type, reason

    def __reduce__(self):
        return (type(self), (self.utterance_id, self.path, self.error_type, self.reason))


def diagnostics_table(uid: str, variant: str, tracked: TrackedVideo) -> pa.Table:
    """The `tracking_frames` rows of one tracked utterance."""
    result, n = tracked.result, len(tracked.result.curves)
    flow_valid = tracked.flow_valid if tracked.flow_valid is not None else np.full(n, np.nan)
    columns = {
        C.UTTERANCE_ID: [uid] * n, C.VARIANT: [variant] * n, C.FRAME: np.arange(n, dtype=np.int32),
        C.MOUTH_ERROR_PX: pa.array(result.mouth_error_px, pa.float32(), from_pandas=True),
        C.LANDMARKS_VALID: tracked.landmarks.valid.any(axis=1),
        C.FLOW_VALID_FRACTION: pa.array(flow_valid, pa.float32(), from_pandas=True),
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
    if not utterance[C.VIDEO_PATH]:
        raise TrackError(uid, None, "NoVideo", "the utterance has no video")
    try:
        procedural = curves_array(store.read_curves(uid, "procedural", procedural_variant))
    except LookupError as exc:
        raise TrackError(uid, None, "NoProceduralCurves", f"{exc}; run the procedural stage first") from exc
    video = VideoInput(utterance[C.VIDEO_PATH], utterance[C.LANDMARK_PATH], utterance[C.FPS],
                       int(utterance[C.N_FRAMES]))
    try:
        tracked = track_video(video, procedural, rig, config)
    except TrackingInputError as exc:
        raise TrackError(uid, exc.path, exc.error_type, exc.reason) from exc
    result, variant = tracked.result, config.variant
    store.write_curves(curves_table(uid, SOURCE, variant, result.curves, utterance[C.FPS]),
                       provenance=f"{SOURCE}:{utterance[C.CONTENT_HASH]}:{stable_hash(config)}", fps=utterance[C.FPS])
    store.write_tracking_frames(diagnostics_table(uid, variant, tracked))
    error = result.mouth_error_px
    return {
        "utterance_id": uid, "frames": video.n_frames, "seconds": round(result.seconds, 3),
        "mouth_error_px": float(np.nanmean(error)) if np.isfinite(error).any() else None,
        "variant": variant, **tracked.camera_info,
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
