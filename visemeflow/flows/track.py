"""The `track` flow: phoneme-guided viseme tracking of every utterance with a video (one task each).

Utterances without an alignment are tracked unguided (variant `unguided-...`, see tasks/track.py); the summary
counts them (`unguided`) and says why (`unguided_why`)."""

from pathlib import Path

from prefect import flow

from visemeflow.flows.common import StageRun, collect_utterance_results, last_settings, replace_stage_rejects
from visemeflow.flows.errors import RerunError
from visemeflow.flows.params import TrackParams, TrackSettings
from visemeflow.flows.runners import cpu_thread_pool, on_requested_runner, run_on_runner
from visemeflow.hashing import file_hash
from visemeflow.rig import demo_rig_path
from visemeflow.schemas import C
from visemeflow.storage import Store
from visemeflow.tasks.common import result_storage
from visemeflow.tasks.procedural import SOURCE as PROCEDURAL
from visemeflow.tasks.procedural import default_variant
from visemeflow.tasks.track import SOURCE, STAGE, TrackError, track_utterance, utterance_config

LANDMARKS_KEY = "stored_landmarks"
"""Key of the stored landmarks' provenance in a task's utterance row (part of the task's cache key)."""
TRACK_FIELDS = [C.UTTERANCE_ID, C.CONTENT_HASH, C.VIDEO_PATH, C.LANDMARK_PATH, C.AUDIO_PATH, C.ALIGNMENT_PATH,
                C.ALIGNMENT_FORMAT, C.FPS, C.N_FRAMES]


def rig_and_hash(rig: Path | None) -> tuple[Path, str]:
    path = (rig or demo_rig_path()).resolve()
    return path, file_hash(path)


def procedural_variant_of(store: Store, given: str | None) -> str:
    """The procedural curves that guide tracking: as given, else those the procedural stage last wrote."""
    if given:
        return given
    last = last_settings(store, "procedural")
    if last is not None and last.variant:
        return last.variant
    from visemeflow.procedural import ProceduralConfig

    return default_variant(ProceduralConfig())


def unguided_why(unguided: list[dict]) -> str | None:
    """'N: reason; M: reason' over the reports of utterances tracked without phoneme guidance; None if none."""
    counts: dict[str, int] = {}
    for r in unguided:
        reason = r.get("unguided_reason") or "unknown"
        counts[reason] = counts.get(reason, 0) + 1
    return "; ".join(f"{n}: {reason}" for reason, n in sorted(counts.items())) or None


@flow(name="track", flow_run_name="track[{params.store}]", task_runner=cpu_thread_pool())
def track_flow(params: TrackParams) -> dict[str, object]:
    """Track every utterance that has a video; failures become rejects and the rest goes on."""
    if not on_requested_runner(params):  # e.g. a deployment run asking for Dask: run on it as a subflow
        return run_on_runner(track_flow, params)
    rig_path, rig_hash = rig_and_hash(params.rig)
    procedural_variant = procedural_variant_of(Store(params.store), params.procedural_variant)
    config = params.config
    run = StageRun(STAGE, params.store, TrackSettings(rig=str(rig_path), procedural_variant=procedural_variant,
                                                      n_shards=params.n_shards, config=config))
    store = run.store
    rows = [r for r in store.read_table("utterances").select(TRACK_FIELDS).to_pylist() if r[C.VIDEO_PATH]]
    # longest videos first: with n workers the run then ends on short utterances, not on one long one
    rows.sort(key=lambda r: (-(r[C.N_FRAMES] or 0), r[C.UTTERANCE_ID]))
    rejected_before = run.rejected_before()
    futures, frames = {}, {}
    for row in rows:
        uid = row[C.UTTERANCE_ID]
        present = store.has_curves(SOURCE, utterance_config(row, config).variant, uid) or uid in rejected_before
        provenance = store.curves_provenance(PROCEDURAL, procedural_variant, uid) or ""
        if not row[C.LANDMARK_PATH]:    # landmarks from the `landmarks` stage: new ones invalidate the cache
            row = {**row, LANDMARKS_KEY: store.landmarks_provenance(uid)}
        future = track_utterance.with_options(
            result_storage=result_storage(store.root), refresh_cache=not present,
        ).submit(str(store.root), row, procedural_variant, provenance, str(rig_path), rig_hash, config)
        futures[future] = uid
        frames[future] = int(row[C.N_FRAMES] or 0)
    reports, rejects, unexpected = collect_utterance_results(futures, STAGE, TrackError, run.logger, work=frames)
    replace_stage_rejects(store, STAGE, rejects, params.n_shards)
    errors = [r["mouth_error_px"] for r in reports if r.get("mouth_error_px") is not None]
    unguided = [r for r in reports if not r.get("guided", True)]
    summary = {
        "utterances": len(rows), "tracked": sum(1 for r in reports if not r["cached"]),
        "cached": sum(r["cached"] for r in reports), "rejected": len(rejects),
        "frames": sum(r["frames"] for r in reports), "unguided": len(unguided),
        "interpolated_frames": sum(r.get("interpolated_frames", 0) for r in reports),
    }
    extra = {"variant": config.variant,
             "variants": ", ".join(sorted({r["variant"] for r in reports})) or None,
             "unguided_why": unguided_why(unguided),
             "mean_mouth_error_px": round(sum(errors) / len(errors), 3) if errors else None}
    return run.finish(summary, len(rejects), len(rows), extra=extra, unexpected=unexpected,
                      title=f"track ({extra['variants'] or config.variant})")  # the modes used, not the one asked


def rerun_one(store: Store, uid: str, last: TrackSettings | None, force: bool) -> dict:
    """Track one utterance again, with the last track run's settings (else the defaults)."""
    rows = store.read_table("utterances", utterance_ids=[uid]).select(TRACK_FIELDS).to_pylist()
    if not rows:
        raise RerunError(f"{uid} is not ingested in {store.root}; see `visemeflow rejects` or rerun --stage ingest")
    last = last or TrackSettings()
    rig_path, rig_hash = rig_and_hash(Path(last.rig) if last.rig else None)
    variant = procedural_variant_of(store, last.procedural_variant)
    provenance = store.curves_provenance(PROCEDURAL, variant, uid) or ""
    task = track_utterance.with_options(result_storage=result_storage(store.root), refresh_cache=force)
    return task(str(store.root), rows[0], variant, provenance, str(rig_path), rig_hash, last.config)
