"""The `landmarks` flow: MediaPipe FaceMesh on every utterance with a video but no landmark file (one task each;
an utterance whose task would be a cache hit is read from its cached record without a task run: `read_cached`)."""


from prefect import flow

from visemeflow.flows.errors import RerunError
from visemeflow.flows.params import LandmarksParams, LandmarksSettings
from visemeflow.flows.common import StageRun, collect_utterance_results, read_cached, replace_stage_rejects
from visemeflow.flows.runners import cpu_thread_pool, on_requested_runner, run_on_runner
from visemeflow.schemas import C
from visemeflow.storage import Store
from visemeflow.tasks.common import reject_row, result_storage
from visemeflow.tasks.landmarks import STAGE, LandmarksError, landmarks_utterance, provenance

LANDMARK_FIELDS = [C.UTTERANCE_ID, C.CONTENT_HASH, C.VIDEO_PATH, C.LANDMARK_PATH, C.FPS, C.N_FRAMES]


def utterances_needing_landmarks(store: Store) -> list[dict]:
    """Utterance rows with a video and no landmark file of their own, longest videos first."""
    rows = [r for r in store.read_table("utterances").select(LANDMARK_FIELDS).to_pylist()
            if r[C.VIDEO_PATH] and not r[C.LANDMARK_PATH]]
    # longest first: with n workers the run then ends on short utterances, not on one long one
    rows.sort(key=lambda r: (-(r[C.N_FRAMES] or 0), r[C.UTTERANCE_ID]))
    return rows


@flow(name="landmarks", flow_run_name="landmarks({params.store})", task_runner=cpu_thread_pool())
def landmarks_flow(params: LandmarksParams) -> dict[str, object]:
    """Detect the landmarks of every utterance with a video but no landmark file; a video without a usable face
    (none, or found on too few frames) or a detector failure becomes a reject and the rest goes on."""
    if not on_requested_runner(params):
        return run_on_runner(landmarks_flow, params)
    config = params.config
    run = StageRun(STAGE, params.store, LandmarksSettings(n_shards=params.n_shards, config=config))
    store = run.store
    rows = utterances_needing_landmarks(store)
    rejected_before = run.rejected_before()
    # a cache hit must not hide a deleted or outdated file: recompute unless this run's file is there
    present = {r[C.UTTERANCE_ID]: store.landmarks_provenance(r[C.UTTERANCE_ID]) == provenance(r, config)
               or r[C.UTTERANCE_ID] in rejected_before for r in rows}
    cached, left = read_cached(STAGE, landmarks_utterance, store.root,
                               [(r[C.UTTERANCE_ID], (str(store.root), r, config), present[r[C.UTTERANCE_ID]])
                                for r in rows], run.logger)
    futures, frames = {}, {}
    for uid, args, _ in left:
        future = landmarks_utterance.with_options(
            result_storage=result_storage(store.root), refresh_cache=not present[uid],
        ).submit(*args)
        futures[future] = uid
        frames[future] = int(args[1][C.N_FRAMES] or 0)
    reports, rejects, unexpected = collect_utterance_results(futures, STAGE, LandmarksError, run.logger, work=frames)
    reports += cached
    replace_stage_rejects(store, STAGE, rejects, params.n_shards)
    summary = {
        "utterances": len(rows), "detected": sum(1 for r in reports if not r["cached"]),
        "cached": sum(r["cached"] for r in reports), "rejected": len(rejects),
        "frames": sum(r["frames"] for r in reports),
        "frames_without_face": sum(r["frames"] - r["detected_frames"] for r in reports),
        "multi_face": sum(r["multi_face"] for r in reports),
    }
    return run.finish(summary, len(rejects), len(rows), unexpected=unexpected,
                      reasons=[r[C.MESSAGE] for r in rejects])


def rerun_one(store: Store, uid: str, last: LandmarksSettings | None, force: bool) -> dict:
    """Detect one utterance's landmarks again (the last landmarks run's settings, else the defaults). The stage's
    rejects keep every other utterance's rows; this one's are replaced by the outcome, so a fixed video leaves no
    stale reject and a still-broken one is listed once."""
    rows = store.read_table("utterances", utterance_ids=[uid]).select(LANDMARK_FIELDS).to_pylist()
    if not rows:
        raise RerunError(f"{uid} is not ingested in {store.root}; see `visemeflow rejects` or rerun --stage ingest")
    if not rows[0][C.VIDEO_PATH]:
        raise RerunError(f"{uid} has no video in {store.root}: there are no landmarks to detect")
    last = last or LandmarksSettings()
    others = [r for r in store.read_table("rejects", STAGE).to_pylist() if r[C.UTTERANCE_ID] != uid]
    task = landmarks_utterance.with_options(result_storage=result_storage(store.root), refresh_cache=force)
    try:
        report = task(str(store.root), rows[0], last.config)
    except LandmarksError as exc:
        replace_stage_rejects(store, STAGE, others + [reject_row(uid, STAGE, exc.error_type, str(exc), exc.path)],
                              last.n_shards)
        raise
    replace_stage_rejects(store, STAGE, others, last.n_shards)
    return report
