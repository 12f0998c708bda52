"""Tracking task: phoneme-guided viseme fitting of one utterance's video into `tracked` curves.

The tracking itself is `visemeflow.tracking.utterance.track_video`; this task reads the procedural curves from the
store, calls it, and writes the curves and per-frame diagnostics back.

An utterance without an alignment (`alignment_format` NO_ALIGNMENT: a video ingested without phones, a captured
take with a video) has no procedural curves: it is tracked without phoneme guidance (no L_sup/L_act) and its
curves are stored under the unguided variant (`unguided-fast` where the config says `guided-fast`), never mixed
with guided ones. Utterances with an alignment stay guided.

Curves are stored on the utterance's grid (frame k at k / fps, the `curves` contract). For a video whose frames are
not that grid (variable frame rate, a late first frame) the tracker solves on the frames' true times and
interpolates onto the grid (see `tracking.utterance`); the `tracking_frames` rows of grid frames the video lacks
have `landmarks_valid` false and every `loss_*` column (and mouth error, flow) null: nothing was measured there.
"""

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from prefect import get_run_logger, task
from prefect.cache_policies import NO_CACHE

from visemeflow.atomic import group_sync
from visemeflow.hashing import stable_hash
from visemeflow.learning.device import resolve_device
from visemeflow.location import local_input
from visemeflow.rig import VisemeRig, load_rig
from visemeflow.schemas import (
    LOSS_TERMS,
    TRACKING_FRAMES,
    C,
    CurveSource,
    Curves,
)
from visemeflow.schemas.tables import has_alignment
from visemeflow.storage import Store
from visemeflow.tasks.code_version import code_digest
from visemeflow.tasks.common import CACHE_POLICY, RESULT_SERIALIZER, results_of
from visemeflow.tasks.progress import step_log
from visemeflow.tracking.solver import TrackingConfig
from visemeflow.tracking.identity import SpeakerIdentity, fit_speaker_identity
from visemeflow.tracking.landmarks import LandmarkError, read_landmarks
from visemeflow.tracking.utterance import (
    CAMERA_SUFFIX,
    TrackedVideo,
    TrackingInputError,
    VideoInput,
    identity_modes_for,
    track_video,
    track_videos,
)

STAGE = "track"
SOURCE = CurveSource.TRACKED
NO_ALIGNMENT_REASON = "no alignment"
GUIDANCE_OFF_REASON = "guidance off in the tracking config"


class TrackError(ValueError):
    """An utterance that cannot be tracked; names the utterance, the file and the reason."""

    def __init__(self, utterance_id: str, path: str | None, error_type: str, reason: str):
        super().__init__(f"{utterance_id}: {path}: {reason}" if path else f"{utterance_id}: {reason}")
        self.utterance_id, self.path, self.error_type, self.reason = utterance_id, path, error_type, reason

    def __reduce__(self):
        return (type(self), (self.utterance_id, self.path, self.error_type, self.reason))


def utterance_config(utterance: dict, config: TrackingConfig) -> TrackingConfig:
    """The config one utterance is tracked with: `config`, unguided for an utterance without an alignment."""
    if config.guidance and not has_alignment(utterance):
        return config.model_copy(update={"guidance": False})
    return config


def tracked_provenance(utterance: dict, config: TrackingConfig, identity: SpeakerIdentity | dict | None) -> str:
    """What the tracked curves of `utterance` record as their making: its content, the whole config it was tracked
    with (`utterance_config`), this code and the speaker identity (or its `to_dict`, as the flow holds it). The
    track flow counts stored curves as done only while they record exactly this (curves of other settings in the
    same variant folder are tracked again)."""
    config = utterance_config(utterance, config)
    if isinstance(identity, dict):
        identity = SpeakerIdentity.from_dict(identity)
    return (f"{SOURCE}:{utterance[C.CONTENT_HASH]}:{stable_hash(config)}:{code_digest(__name__)}"
            + ("" if identity is None else f":identity={identity.digest}"))


def unguided_reason(utterance: dict, config: TrackingConfig) -> str | None:
    """Why an utterance is tracked without phoneme guidance; None when it is guided."""
    if not config.guidance:
        return GUIDANCE_OFF_REASON
    return None if has_alignment(utterance) else NO_ALIGNMENT_REASON


def landmark_file(store: Store, utterance: dict) -> str | None:
    """The utterance's landmark file: the one beside its video, else what the `landmarks` stage stored."""
    uid = utterance[C.UTTERANCE_ID]
    if utterance[C.LANDMARK_PATH]:
        return local_input(utterance[C.LANDMARK_PATH])
    return store.local_file(store.landmark_path(uid)) if store.has_landmarks(uid) else None


def alignment_end_s(store: Store, uid: str) -> float | None:
    """Where the utterance's phones end (s); None without phone rows."""
    ends = store.read_table("phones", utterance_ids=[uid]).column(C.END_S)
    return float(pc.max(ends).as_py()) if len(ends) else None


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


def _video_input(store: Store, utterance: dict, procedural_variant: str,
                 config: TrackingConfig) -> tuple[VideoInput, np.ndarray | None, TrackingConfig]:
    """What `track_video` takes for one utterance: its video, its procedural curves (None: unguided) and its
    config (`utterance_config`); TrackError for an utterance without video or procedural curves."""
    uid = utterance[C.UTTERANCE_ID]
    if not utterance[C.VIDEO_PATH]:
        raise TrackError(uid, None, "NoVideo", "the utterance has no video")
    config = utterance_config(utterance, config)
    procedural = end_s = None
    if has_alignment(utterance):
        try:
            procedural = store.load_curves(uid, CurveSource.PROCEDURAL, procedural_variant).values
        except LookupError as exc:
            raise TrackError(uid, None, "NoProceduralCurves", f"{exc}; run the procedural stage first") from exc
        end_s = alignment_end_s(store, uid)
    video = VideoInput(local_input(utterance[C.VIDEO_PATH], beside=(CAMERA_SUFFIX,)), landmark_file(store, utterance), utterance[C.FPS],
                       int(utterance[C.N_FRAMES]), audio_path=local_input(utterance.get(C.AUDIO_PATH)),
                       alignment_path=local_input(utterance.get(C.ALIGNMENT_PATH) or None), alignment_end_s=end_s)
    return video, procedural, config


def _stored(store: Store, utterance: dict, config: TrackingConfig, tracked: TrackedVideo, why: str | None,
            identity: SpeakerIdentity | None) -> dict:
    """Store one tracked utterance's curves and diagnostics; its report."""
    uid = utterance[C.UTTERANCE_ID]
    result, variant = tracked.result, config.variant
    store.save_curves(Curves(result.curves, utterance[C.FPS], uid, SOURCE, variant,
                             tracked_provenance(utterance, config, identity)))
    store.write_tracking_frames(diagnostics_table(uid, variant, tracked))
    error = result.mouth_error_px
    n_frames = int(utterance[C.N_FRAMES])
    return {
        "utterance_id": uid, "frames": n_frames, "seconds": round(result.seconds, 3),
        "mouth_error_px": float(np.nanmean(error)) if np.isfinite(error).any() else None,
        "variant": variant, "guided": why is None, "unguided_reason": why,
        "video_frames": int(len(tracked.frame_times)) if tracked.frame_times is not None else n_frames,
        "interpolated_frames": int(tracked.interpolated.sum()), **tracked.camera_info,
    }


def track_one(store: Store, utterance: dict, procedural_variant: str, rig: VisemeRig, config: TrackingConfig,
              on_step=None, identity: SpeakerIdentity | None = None) -> dict:
    """Track one utterance and store its curves and diagnostics; raises TrackError for bad input. `on_step(phase,
    done, total)`: progress inside the video (`tracking.utterance.track_video`). `identity`: the speaker's face
    and camera (`speaker_identity`); None fits them to this clip."""
    uid = utterance[C.UTTERANCE_ID]
    why = unguided_reason(utterance, config)
    video, procedural, config = _video_input(store, utterance, procedural_variant, config)
    try:
        extra = {} if identity is None else {"identity": identity}
        tracked = track_video(video, procedural, rig, config, on_step, **extra)
    except TrackingInputError as exc:
        raise TrackError(uid, exc.path, exc.error_type, exc.reason) from exc
    return _stored(store, utterance, config, tracked, why, identity)


def track_many(store: Store, utterances: list[dict], procedural_variant: str, rig: VisemeRig,
               config: TrackingConfig, identities: list[SpeakerIdentity | None] | None = None,
               on_step=None, device: str = "cpu") -> list[dict | TrackError]:
    """`track_one` of several utterances with one joint solve per tracking config (`tracking.utterance.
    track_videos`: the same curves as one by one, less solver time). A report or a TrackError per utterance, in
    order; a bad utterance never stops the others. `on_step(index, phase, done, total)` as `track_videos`."""
    identities = list(identities) if identities is not None else [None] * len(utterances)
    out: list[dict | TrackError | None] = [None] * len(utterances)
    ready = []          # (index, video, procedural curves or None: unguided, the utterance's config)
    for i, utterance in enumerate(utterances):
        try:
            ready.append((i, *_video_input(store, utterance, procedural_variant, config)))
        except TrackError as exc:
            out[i] = exc
    # track_videos solves guided and unguided videos apart (no procedural curves: guidance off, as
    # utterance_config says for an utterance without an alignment)
    tracked = track_videos([(video, procedural) for _, video, procedural, _ in ready], rig, config,
                           [identities[i] for i, *_ in ready],
                           None if on_step is None else (lambda k, *rest: on_step(k if k < 0 else ready[k][0], *rest)),
                           device)
    with group_sync():   # the group's files flushed once, before track_jointly records any of them as done
        for (i, _, _, cfg), done in zip(ready, tracked):
            utterance = utterances[i]
            if isinstance(done, TrackingInputError):
                out[i] = TrackError(utterance[C.UTTERANCE_ID], done.path, done.error_type, done.reason)
            else:
                out[i] = _stored(store, utterance, cfg, done, unguided_reason(utterance, config), identities[i])
    return out  # type: ignore[return-value]


@task(cache_policy=CACHE_POLICY, persist_result=True, result_serializer=RESULT_SERIALIZER,
      task_run_name="track[{utterance[utterance_id]}]")
def track_utterance(
    store_root: str, utterance: dict, procedural_variant: str, procedural_provenance: str, rig_path: str,
    rig_hash: str, config: TrackingConfig, identity: dict | None = None,
) -> dict:
    """Track one utterance (cached on its inputs' content hash, the procedural curves, the rig, the config and
    the speaker's identity: `SpeakerIdentity.to_dict`, None to fit one to this clip)."""
    rig = load_rig(rig_path)
    logger = get_run_logger()
    steps = step_log(f"track[{utterance[C.UTTERANCE_ID]}]", logger)   # a long clip says where it is
    report = track_one(Store(store_root), utterance, procedural_variant, rig, config, steps,
                       None if identity is None else SpeakerIdentity.from_dict(identity))
    error = report["mouth_error_px"]  # None where no frame had a mouth to measure
    logger.info("%s: %d frames (%s) in %.1f s, mouth error %s", report["utterance_id"], report["frames"],
                          report["variant"], report["seconds"], "-" if error is None else f"{error:.2f} px")
    return report


@task(cache_policy=NO_CACHE, task_run_name="track-joint[{label}]")
def track_jointly(store_root: str, label: str, utterances: list[dict], procedural_variant: str, rig_path: str,
                  config: TrackingConfig, identities: list[dict | None], keys: list[str | None],
                  device: str = "cpu") -> dict[str, object]:
    """Several utterances tracked with one joint solve (`track_many`). Each one tracked is stored, and its report
    written as the cached result of its own `track_utterance` call (its key in `keys`, `common.cache_key_of`): a
    later run, `rerun` or a run with one task per utterance finds it. Not cached itself: its work is kept per
    utterance. Returns each utterance's report, or the error type of one that failed (the flow then runs it alone
    in its own task, which rejects it with the whole message). `device`: where the joint solve runs (the results do
    not depend on it beyond float rounding, so it is not part of any cache key)."""
    logger = get_run_logger()
    steps = step_log(f"track-joint[{label}]", logger)
    done = track_many(Store(store_root), utterances, procedural_variant, load_rig(rig_path), config,
                      [None if i is None else SpeakerIdentity.from_dict(i) for i in identities],
                      lambda index, phase, k, n: steps(phase, k, n), resolve_device(device))
    results = results_of(store_root)
    outcome: dict[str, object] = {}
    for utterance, key, report in zip(utterances, keys, done):
        uid = utterance[C.UTTERANCE_ID]
        if isinstance(report, TrackError):
            outcome[uid] = report.error_type
            continue
        if key is not None:
            results.write(obj=report, key=key)
        outcome[uid] = report
    tracked = [r for r in done if not isinstance(r, TrackError)]
    logger.info("track-joint[%s]: %d of %d utterances, %d frames, solve %.1f s", label, len(tracked),
                len(utterances), sum(r["frames"] for r in tracked), sum(r["seconds"] for r in tracked))
    return outcome


def speaker_identity(clips: list[dict], image_size: tuple[int, int], rig: VisemeRig,
                     total_frames: int) -> SpeakerIdentity | None:
    """The identity of one speaker at one image size, fitted on the neutral frames of `clips` (`utterances` rows
    with `landmark_path` filled in, the clips chosen by `identity_clips`); None when the rig has no identity modes
    or no clip has a readable landmark file with a neutral frame (each clip is then fitted on its own)."""
    modes = identity_modes_for(rig)
    if modes is None:
        return None
    tracks = []
    for row in clips:
        try:
            tracks.append((row[C.UTTERANCE_ID], read_landmarks(row[C.LANDMARK_PATH], fps=row[C.FPS])))
        except (LandmarkError, OSError, ValueError):
            continue        # the clip's own track task rejects it
    return fit_speaker_identity(rig, modes, tracks, image_size, total_frames)


def identity_clips(rows: list[dict], k: int) -> list[dict]:
    """The clips a speaker's identity is fitted on: the first `k` by utterance id of those with a landmark file
    (whatever order `rows` come in)."""
    return sorted((r for r in rows if r.get(C.LANDMARK_PATH)), key=lambda r: r[C.UTTERANCE_ID])[:k]


@task(cache_policy=CACHE_POLICY, persist_result=True, result_serializer=RESULT_SERIALIZER,
      task_run_name="identity[{speaker}:{image_size[0]}x{image_size[1]}]")
def fit_speaker_identity_task(
    speaker: str, image_size: list[int], clips: list[dict], rig_path: str, rig_hash: str,
    total_frames: int,
) -> dict | None:
    """A speaker's identity (`SpeakerIdentity.to_dict`, None: fit each clip on its own), cached on the chosen
    clips' rows (content hashes, stored landmarks' provenance), the rig and the number of frames."""
    identity = speaker_identity(clips, (int(image_size[0]), int(image_size[1])),
                                load_rig(rig_path), total_frames)
    logger = get_run_logger()
    if identity is None:
        logger.info("identity[%s]: no neutral frame in %d clip(s); each clip is fitted on its own", speaker, len(clips))
        return None
    logger.info("identity[%s %dx%d]: %d frames of %d clip(s), %.2f px", speaker, *identity.image_size,
                identity.frames, len(identity.clips), identity.rms_px)
    return identity.to_dict()
