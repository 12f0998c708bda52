"""The `procedural` flow: JALI-like viseme curves for every ingested utterance."""

from prefect import flow

from visemeflow.flows.common import StageRun, collect, group_by_shard, totals
from visemeflow.flows.errors import RerunError
from visemeflow.flows.params import ProceduralParams, ProceduralSettings
from visemeflow.schemas import C, shard_of
from visemeflow.schemas.tables import has_alignment
from visemeflow.storage import Store
from visemeflow.procedural import ProceduralConfig
from visemeflow.tasks.common import made_from, result_storage
from visemeflow.tasks.procedural import (
    SOURCE,
    STAGE,
    default_variant,
    procedural_one,
    procedural_shard,
    shard_digest,
)

UTTERANCE_FIELDS = [C.UTTERANCE_ID, C.CONTENT_HASH, C.DURATION_S, C.FPS, C.N_FRAMES, C.ALIGNMENT_PATH]


def _outputs_present(store: Store, shard: int, items: list[dict], variant: str, rejected: set[str],
                     config: ProceduralConfig) -> bool:
    """Whether the shard's curve files and rejects file exist and the rejects file was written from these rows
    (`common.made_from`), so a cached result still describes the store."""
    if not made_from(store, "rejects", shard, STAGE, shard_digest(items, config, variant)):
        return False
    ids = [u[C.UTTERANCE_ID] for u in items if u[C.UTTERANCE_ID] not in rejected]
    return len(store.curves_present(SOURCE, variant, ids)) == len(set(ids))


@flow(name="procedural", flow_run_name="procedural({params.store})")
def procedural_flow(params: ProceduralParams) -> dict[str, int]:
    """Generate procedural curves shard by shard; utterances whose inputs and config are unchanged are skipped."""
    variant = params.variant or default_variant(params.config)
    run = StageRun(STAGE, params.store, ProceduralSettings(variant=variant, n_shards=params.n_shards,
                                                          config=params.config))
    store = run.store
    # utterances with no alignment (videos without one, captured takes) have no phones to make curves from
    rows = store.read_table("utterances").select(UTTERANCE_FIELDS + [C.ALIGNMENT_FORMAT]).to_pylist()
    unaligned = sorted(r[C.UTTERANCE_ID] for r in rows if not has_alignment(r))
    utterances = [{k: r[k] for k in UTTERANCE_FIELDS} for r in rows if has_alignment(r)]
    if unaligned:
        run.logger.info(
            "skipped %d utterance(s) without an alignment (no phones to make procedural curves from; a video "
            "without one is tracked unguided): %s%s", len(unaligned), ", ".join(unaligned[:10]),
            " ..." if len(unaligned) > 10 else "")
    rejected = run.rejected_before()
    shards = group_by_shard(utterances, C.UTTERANCE_ID, params.n_shards)
    futures = [
        procedural_shard.with_options(
            result_storage=result_storage(store.root),
            refresh_cache=not _outputs_present(store, shard, items, variant, rejected, params.config),
        ).submit(str(store.root), shard, items, params.config, variant)
        for shard, items in shards.items()
    ]
    reports, errors = collect(futures, STAGE, unit="shards")
    store.delete_shards_except("rejects", set(shards), STAGE)
    if errors:
        raise RuntimeError(f"procedural: {len(errors)} of {len(futures)} shards failed: " + "; ".join(errors[:3]))
    rejected = store.read_table("rejects", STAGE)
    # the rejects the store holds now, cached shards' too (a shard's own count is of the shards that ran)
    summary = {**totals(reports), "rejected": rejected.num_rows, "skipped_unaligned": len(unaligned)}
    return run.finish(summary, rejected.num_rows, sum(len(items) for items in shards.values()),
                      extra={"variant": variant}, rejects=rejected, title=f"procedural ({variant})")


def rerun_one(store: Store, uid: str, last: ProceduralSettings | None, force: bool) -> dict:
    """One utterance's procedural curves again, with the last procedural run's settings (else the defaults)."""
    last = last or ProceduralSettings()
    variant = last.variant or default_variant(last.config)
    rows = store.read_table("utterances", utterance_ids=[uid]).to_pylist()
    if not rows:
        raise RerunError(f"{uid} is not ingested in {store.root}; see `visemeflow rejects` or rerun --stage ingest")
    utterance = {k: rows[0][k] for k in UTTERANCE_FIELDS}
    task = procedural_one.with_options(result_storage=result_storage(store.root), refresh_cache=force)
    return task(str(store.root), shard_of(uid, last.n_shards), utterance, last.config, variant)
