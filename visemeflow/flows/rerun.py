"""The `rerun` flow: one utterance through one stage, by hand, even when its cache is valid."""

from collections.abc import Callable
from pathlib import Path

from prefect import flow, get_run_logger

from visemeflow.flows.params import RerunParams
from visemeflow.flows.procedural import UTTERANCE_FIELDS
from visemeflow.flows.track import TRACK_FIELDS, procedural_variant_of, rig_and_hash
from visemeflow.ingest import IngestConfig
from visemeflow.procedural import ProceduralConfig
from visemeflow.schemas import CurveSource, shard_of
from visemeflow.storage import Store
from visemeflow.tasks import ingest as ingest_tasks
from visemeflow.tasks import procedural as procedural_tasks
from visemeflow.tasks.common import result_storage
from visemeflow.tasks.track import track_utterance
from visemeflow.tracking.solver import TrackingConfig


class RerunError(LookupError):
    """The utterance or the stage's earlier run cannot be found; the message says what to run first."""


def _rerun_animate(store: Store, uid: str, run: dict | None, force: bool) -> dict:
    """Every character of the last animate run, for one utterance; AnimateError for bad input."""
    from visemeflow.animation.package import AnimateConfig
    from visemeflow.hashing import file_hash
    from visemeflow.schemas import C
    from visemeflow.tasks.animate import animate_one, character_keys, content_hash

    if run is None:
        raise RerunError(f"{store.root} has no animate run to repeat; run `visemeflow animate` first")
    if not store.has_curves(run["source"], run["variant"], uid):
        raise RerunError(f"{uid} has no {run['source']} curves of variant {run['variant']!r} in {store.root}")
    config = AnimateConfig(**run["config"])
    rows = store.read_table("utterances", utterance_ids=[uid]).select([C.AUDIO_PATH]).to_pylist()
    audio = rows[0][C.AUDIO_PATH] if rows and rows[0][C.AUDIO_PATH] and Path(rows[0][C.AUDIO_PATH]).is_file() else None
    mapping = run.get("mapping")
    task = animate_one.with_options(result_storage=result_storage(store.root), refresh_cache=force)
    packages = [task(str(store.root), uid, run["source"], run["variant"],
                     store.curves_provenance(run["source"], run["variant"], uid) or "", path, content_hash(path),
                     key, mapping, file_hash(mapping) if mapping else None, config, audio,
                     file_hash(audio) if audio else None, run.get("out"))
                for path, key in zip(run["characters"], character_keys(run["characters"])) if Path(path).exists()]
    return {"packages": len(packages), "files": sum(len(p["files"]) for p in packages)}


def _rerun_landmarks(store: Store, uid: str, run: dict | None, force: bool) -> dict:
    """Detect one utterance's landmarks again (the last landmarks run's settings, else the defaults). The stage's
    rejects keep every other utterance's rows; this one's are replaced by the outcome, so a fixed video leaves no
    stale reject and a still-broken one is listed once."""
    from visemeflow.flows.common import replace_stage_rejects
    from visemeflow.flows.landmarks import LANDMARK_FIELDS
    from visemeflow.schemas import C
    from visemeflow.tasks.common import reject_row
    from visemeflow.tasks.landmarks import STAGE, LandmarksError, landmarks_utterance
    from visemeflow.tracking.facemesh import FaceMeshConfig

    rows = store.read_table("utterances", utterance_ids=[uid]).select(LANDMARK_FIELDS).to_pylist()
    if not rows:
        raise RerunError(f"{uid} is not ingested in {store.root}; see `visemeflow rejects` or rerun --stage ingest")
    if not rows[0][C.VIDEO_PATH]:
        raise RerunError(f"{uid} has no video in {store.root}: there are no landmarks to detect")
    run = run or {"n_shards": 8, "config": FaceMeshConfig().model_dump(mode="json")}
    others = [r for r in store.read_table("rejects", STAGE).to_pylist() if r[C.UTTERANCE_ID] != uid]
    task = landmarks_utterance.with_options(result_storage=result_storage(store.root), refresh_cache=force)
    try:
        report = task(str(store.root), rows[0], FaceMeshConfig(**run["config"]))
    except LandmarksError as exc:
        replace_stage_rejects(store, STAGE, others + [reject_row(uid, STAGE, exc.error_type, str(exc), exc.path)],
                              run["n_shards"])
        raise
    replace_stage_rejects(store, STAGE, others, run["n_shards"])
    return report


def _rerun_ingest(store: Store, uid: str, run: dict | None, force: bool) -> dict:
    if run is None:
        raise RerunError(f"{store.root} has no ingest run to repeat; run `visemeflow ingest CORPUS` first")
    config = IngestConfig(**run["config"])
    found = ingest_tasks.discover_corpus_task(run["corpus"], only=uid)
    if not found["entries"]:
        reasons = "; ".join(r["message"] for r in found["rejects"]) or "no files for it"
        raise RerunError(f"{uid} is not in the corpus {run['corpus']}: {reasons}")
    task = ingest_tasks.ingest_one.with_options(result_storage=result_storage(store.root), refresh_cache=force)
    return task(str(store.root), shard_of(uid, run["n_shards"]), found["entries"][0], config)


def _rerun_track(store: Store, uid: str, run: dict | None, force: bool) -> dict:
    rows = store.read_table("utterances", utterance_ids=[uid]).select(TRACK_FIELDS).to_pylist()
    if not rows:
        raise RerunError(f"{uid} is not ingested in {store.root}; see `visemeflow rejects` or rerun --stage ingest")
    run = run or {"rig": None, "procedural_variant": None, "config": TrackingConfig().model_dump(mode="json")}
    rig_path, rig_hash = rig_and_hash(Path(run["rig"]) if run.get("rig") else None)
    variant = procedural_variant_of(store, run.get("procedural_variant"))
    provenance = store.curves_provenance(CurveSource.PROCEDURAL, variant, uid) or ""
    task = track_utterance.with_options(result_storage=result_storage(store.root), refresh_cache=force)
    return task(str(store.root), rows[0], variant, provenance, str(rig_path), rig_hash, TrackingConfig(**run["config"]))


def _rerun_procedural(store: Store, uid: str, run: dict | None, force: bool) -> dict:
    run = run or {"n_shards": 8, "config": ProceduralConfig().model_dump(mode="json"), "variant": None}
    config = ProceduralConfig(**run["config"])
    variant = run["variant"] or procedural_tasks.default_variant(config)
    rows = store.read_table("utterances", utterance_ids=[uid]).to_pylist()
    if not rows:
        raise RerunError(f"{uid} is not ingested in {store.root}; see `visemeflow rejects` or rerun --stage ingest")
    utterance = {k: rows[0][k] for k in UTTERANCE_FIELDS}
    task = procedural_tasks.procedural_one.with_options(result_storage=result_storage(store.root), refresh_cache=force)
    return task(str(store.root), shard_of(uid, run["n_shards"]), utterance, config, variant)


RERUNS: dict[str, Callable[[Store, str, dict | None, bool], dict]] = {
    "ingest": _rerun_ingest, "procedural": _rerun_procedural, "landmarks": _rerun_landmarks, "track": _rerun_track,
    "animate": _rerun_animate,
}
"""The stages one utterance can be rerun through (RerunParams.stage): each repeats that stage's last settings."""


@flow(name="rerun", flow_run_name="rerun[{params.utterance_id}:{params.stage}]")
def rerun_flow(params: RerunParams) -> dict[str, int]:
    """Rerun exactly one utterance through one stage with the settings that stage last ran with."""
    store = Store(params.store)
    uid = params.utterance_id
    report = RERUNS[params.stage](store, uid, store.read_run_config(params.stage), params.force)
    get_run_logger().info("rerun %s %s: %s", params.stage, uid, report)
    return report
