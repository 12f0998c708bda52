"""Import task: one captured take (audio + captured animation) into the store as an utterance with `captured` curves.

The take's `utterances` row has no alignment (`alignment_format` "none", `alignment_path` ""); it is written into its
shard under the shard's lock (`Store.replace_utterance_rows`), so the rows of other utterances stay. When the id is
already an utterance ingested from a corpus (with an alignment), its row is kept and only the curves are added, if the
take's audio is the same sound; other audio under that id is a reject. Bad input (unreadable or mismatched files,
unknown channels, NaN) is a reject of stage `import_curves` naming the take and the file; the take's earlier curves
of this variant and its captured row are removed then, so the store never keeps curves of files that are now bad.
"""

from __future__ import annotations

import numpy as np
import pyarrow.compute as pc
from prefect import get_run_logger, task

from visemeflow.shapes.capture import load_arkit_to_visemes
from visemeflow.hashing import file_hash, stable_hash
from visemeflow.location import local_input
from visemeflow.ingest.captured import (
    BAD_INPUT_ERRORS,
    CAPTURED_ALIGNMENT_FORMAT,
    CaptureConfig,
    CaptureReadError,
    Take,
    import_take,
)
from visemeflow.schemas import C, UTTERANCES, CurveSource, Curves, shard_of, table_from_rows
from visemeflow.storage import Store
from visemeflow.tasks.code_version import code_digest
from visemeflow.tasks.common import CACHE_POLICY, RESULT_SERIALIZER, reject_row, result_storage

STAGE = "import_curves"
SOURCE = CurveSource.CAPTURED


def provenance(take: Take, config: CaptureConfig, solver_digest: str) -> str:
    """What made a take's curves: its files' content hash, the conversion table, the config and the code."""
    return (f"{SOURCE}:{take.format or 'auto'}:{take.content_hash}:{solver_digest}:{stable_hash(config)}:"
            f"{code_digest(__name__)}")


def ingested_rows(store: Store, utterance_ids: list[str]) -> dict[str, dict]:
    """Rows of `utterances` with these ids that came from a corpus (with an alignment), by id."""
    table = store.read_table("utterances", utterance_ids=utterance_ids)
    table = table.filter(pc.not_equal(table.column(C.ALIGNMENT_FORMAT), CAPTURED_ALIGNMENT_FORMAT))
    return {row[C.UTTERANCE_ID]: row for row in table.select([C.UTTERANCE_ID, C.AUDIO_PATH]).to_pylist()}


def _forget(store: Store, shard: int, take: Take, variant: str, keep_row: bool) -> None:
    """Remove what an earlier import of this take stored (its curves of `variant`, its captured row)."""
    path = store.curve_path(SOURCE, variant, take.utterance_id)
    if path.exists():
        store.delete_path(path)
    if not keep_row:
        shard_table = store.read_shard("utterances", shard)
        mine = shard_table.filter(pc.equal(shard_table.column(C.UTTERANCE_ID), take.utterance_id))
        if mine.num_rows:
            store.replace_utterance_rows("utterances", shard, take.utterance_id, UTTERANCES.empty_table())


def outputs_present(store: Store, take: dict, variant: str, rejected: set[str]) -> bool:
    """Whether a take's curves are stored, or it is a stored reject (else its cached result no longer describes
    the store)."""
    return take["utterance_id"] in rejected or store.has_curves(SOURCE, variant, take["utterance_id"])


@task(cache_policy=CACHE_POLICY, persist_result=True, result_serializer=RESULT_SERIALIZER,
      task_run_name="import_curves[{take[utterance_id]}]")
def import_take_task(store_root: str, n_shards: int, take: dict, config: CaptureConfig, solver_digest: str,
                     ingested_audio: str | None = None) -> dict:
    """Import one take; returns its report (`reject` holds the reject row when its input is bad).

    `solver_digest` (the conversion table's digest) and `ingested_audio` (the audio of a corpus utterance with this
    id, if any) are inputs so that a new table or a changed corpus row recomputes the take."""
    store = Store(store_root)
    obj = Take(**take)
    uid, shard = obj.utterance_id, shard_of(obj.utterance_id, n_shards)
    report = {"utterance_id": uid, "capture": obj.capture_path, "audio": obj.audio_path, "rejected": 0}
    solver = load_arkit_to_visemes()
    try:
        if solver.digest != solver_digest:
            raise RuntimeError(f"the ARKit-to-viseme table changed while the flow ran ({solver_digest} -> "
                               f"{solver.digest}); run it again")
        if ingested_audio is not None and ingested_audio != obj.audio_path and \
                file_hash(local_input(ingested_audio)) != file_hash(obj.audio_path):
            raise CaptureReadError(obj.audio_path, "IdInUse",
                                   f"{uid} is already an utterance ingested from a corpus with other audio "
                                   f"({ingested_audio}); give the take another id")
        imported = import_take(obj, config, solver)
    except BAD_INPUT_ERRORS as exc:
        _forget(store, shard, obj, config.variant, keep_row=ingested_audio is not None)
        message = f"{uid}: {exc}" if not str(exc).startswith(f"{uid}: ") else str(exc)
        get_run_logger().info("rejected %s", message)
        return {**report, "rejected": 1, "reject": reject_row(uid, STAGE, exc.error_type, message, exc.path)}
    store.save_curves(Curves(imported.curves, imported.fps, uid, SOURCE, config.variant,
                             provenance(obj, config, solver_digest)))
    if ingested_audio is None:
        store.replace_utterance_rows("utterances", shard, uid, table_from_rows([imported.utterance], UTTERANCES))
    fit = imported.fit
    residual, moving = fit.residual, fit.residual[fit.moving]
    report.update({
        "frames": int(len(imported.curves)), "fps": float(imported.fps),
        "duration_s": float(imported.utterance[C.DURATION_S]), "drift_frames": round(imported.drift_frames, 3),
        "residual_mean": float(residual.mean()) if len(residual) else 0.0,
        "residual_median": float(np.median(residual)) if len(residual) else 0.0,
        "residual_mean_moving": float(moving.mean()) if len(moving) else 0.0,
        "residual_median_moving": float(np.median(moving)) if len(moving) else 0.0,
        "residual_sum": float(residual.sum()), "moving_frames": int(len(moving)),
        "bounded_frames": int(fit.bounded), "silent_frames": int(fit.silent),
        "filled_frames": int(imported.capture.filled_frames), "unmapped_channels": list(imported.capture.unmapped),
        "attached_to_ingested": ingested_audio is not None,
    })
    get_run_logger().info("%s: %d frames at %g fps, residual mean %.4f (median %.4f), %d bounded, unmapped %s", uid,
                          report["frames"], report["fps"], report["residual_mean"], report["residual_median"],
                          fit.bounded, ", ".join(imported.capture.unmapped) or "none")
    return report


def take_task_for(store: Store, take: dict, variant: str, rejected: set[str]):
    """`import_take_task` with the store's result storage; recomputed when the take's outputs are missing."""
    return import_take_task.with_options(result_storage=result_storage(store.root),
                                         refresh_cache=not outputs_present(store, take, variant, rejected))

