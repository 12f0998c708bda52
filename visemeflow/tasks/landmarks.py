"""Landmarks task: MediaPipe FaceMesh on one utterance's video, its 478 points per frame written to the store.

The detection itself is `visemeflow.tracking.facemesh.detect_video`; this task runs it and writes
`Store.landmark_path(utterance)` (frame, time_s, detected, x_i, y_i, z_i; `read_landmarks` maps it to the 68
points the tracker uses). Frames without the face are written undetected with null points.
"""

import time

from prefect import get_run_logger, task

from visemeflow.hashing import stable_hash
from visemeflow.location import local_input
from visemeflow.schemas import C
from visemeflow.storage import Store
from visemeflow.tasks.code_version import code_digest
from visemeflow.tasks.common import CACHE_POLICY, RESULT_SERIALIZER
from visemeflow.tracking.facemesh import FaceMeshConfig, FaceMeshError, detect_video, mediapipe478_table

STAGE = "landmarks"


class LandmarksError(ValueError):
    """An utterance whose video gives no usable landmarks; names the utterance, the file and the reason."""

    def __init__(self, utterance_id: str, path: str | None, error_type: str, reason: str):
        super().__init__(f"{utterance_id}: {path}: {reason}" if path else f"{utterance_id}: {reason}")
        self.utterance_id, self.path, self.error_type, self.reason = utterance_id, path, error_type, reason

    def __reduce__(self):
        return (type(self), (self.utterance_id, self.path, self.error_type, self.reason))


def provenance(utterance: dict, config: FaceMeshConfig) -> str:
    """What made an utterance's stored landmarks: the stage, the utterance's content hash, the settings and the code."""
    return f"{STAGE}:{utterance[C.CONTENT_HASH]}:{stable_hash(config)}:{code_digest(__name__)}"


def landmarks_one(store: Store, utterance: dict, config: FaceMeshConfig) -> dict:
    """Detect one utterance's landmarks and store them; raises LandmarksError for a video without a usable face."""
    uid = utterance[C.UTTERANCE_ID]
    video = utterance[C.VIDEO_PATH]
    if not video:
        raise LandmarksError(uid, None, "NoVideo", "the utterance has no video")
    start = time.perf_counter()
    try:
        track = detect_video(local_input(video), config)
    except FaceMeshError as exc:
        raise LandmarksError(uid, exc.path, exc.error_type, exc.reason) from exc
    seconds = time.perf_counter() - start
    store.write_landmarks(uid, mediapipe478_table(track), provenance=provenance(utterance, config))
    return {
        "utterance_id": uid, "frames": track.n_frames, "detected_frames": int(track.detected.sum()),
        "detected_share": round(track.detected_share, 4), "faces": track.faces, "multi_face": int(track.multi_face),
        "seconds": round(seconds, 3), "frames_per_s": round(track.n_frames / seconds, 1) if seconds > 0 else None,
    }


@task(cache_policy=CACHE_POLICY, persist_result=True, result_serializer=RESULT_SERIALIZER,
      task_run_name="landmarks[{utterance[utterance_id]}]")
def landmarks_utterance(store_root: str, utterance: dict, config: FaceMeshConfig) -> dict:
    """Landmarks of one utterance's video (cached on its content hash and the settings)."""
    report = landmarks_one(Store(store_root), utterance, config)
    get_run_logger().info("%s: face on %d of %d frames in %.2f s", report["utterance_id"], report["detected_frames"],
                          report["frames"], report["seconds"])
    return report
