"""The `ingest` flow: corpus to the `utterances`, `phones` and `rejects` tables."""

from dataclasses import asdict
from pathlib import Path

import pyarrow as pa
from prefect import flow, get_run_logger
from prefect.states import Failed, State

from visemeflow.logs import SUMMARISED
from visemeflow.flows.common import StageRun, collect, group_by_shard, last_settings, totals
from visemeflow.flows.errors import RerunError, StageFailed
from visemeflow.flows.params import IngestParams, IngestSettings
from visemeflow.ingest import IngestConfig, discover_corpus
from visemeflow.ingest.corpus import CORPUS_LAYOUT, check_corpus
from visemeflow.ingest.hints import reject_advice, reject_lines
from visemeflow.location import as_text, is_url
from visemeflow.schemas import REJECTS, C, shard_of, table_from_rows
from visemeflow.storage import Store
from visemeflow.tasks.common import reject_row, result_storage
from visemeflow.tasks.ingest import (
    STAGE,
    captured_shards,
    discover_corpus_task,
    ingest_one,
    ingest_shard,
    is_captured,
    remove_stale_shards,
    shard_current,
)

DISCOVER_STAGE = "discover"


@flow(name="ingest", flow_run_name="ingest({params.corpus})")
def ingest_flow(params: IngestParams) -> dict[str, int]:
    """Discover the corpus and ingest it shard by shard; unchanged shards are cache hits.

    A path that is no corpus (one audio file, a flat folder of wavs) and a corpus where nothing is found end the
    flow Failed with one line saying what was found and what a corpus is: zero utterances is never "all done"."""
    problem = check_corpus(params.corpus)
    if problem is not None:
        return _no_corpus(problem)
    before = Store(params.store)
    last = last_settings(before, STAGE)   # read before this run records its own
    found = discover_corpus_task(as_text(params.corpus))
    if not found["entries"] and not found["rejects"]:
        return _no_corpus(f"no utterances found in {params.corpus}; {CORPUS_LAYOUT}")
    if last is not None and not params.replace:
        problem = would_drop(before, last.corpus, as_text(params.corpus), found["entries"])
        if problem is not None:
            return _no_corpus(problem)
    run = StageRun(STAGE, params.store, IngestSettings(corpus=as_text(params.corpus), n_shards=params.n_shards,
                                                       config=params.config))
    store = run.store
    changed = settings_changed(last.config if last is not None else None, params.config)
    if changed:   # `pipeline` without `--tolerance` after `ingest --tolerance 0.5` is the default again: say so
        run.logger.warning("ingest: settings changed since the last ingest of this store (%s): every utterance is "
                           "read again with them", changed)
    shards = group_by_shard(found["entries"], "utterance_id", params.n_shards)
    futures = [
        ingest_shard.with_options(
            result_storage=result_storage(store.root),
            refresh_cache=not shard_current(store, shard, entries, params.config),
        ).submit(str(store.root), shard, entries, params.config)
        for shard, entries in shards.items()
    ]
    reports, errors = collect(futures, STAGE, unit="shards")
    removed = remove_stale_shards(store, set(shards) | captured_shards(store))
    discovery_rejects = [
        reject_row(r["utterance_id"], DISCOVER_STAGE, r["error_type"], r["message"], r["path"]) for r in found["rejects"]
    ]
    store.write_shard("rejects", 0, table_from_rows(discovery_rejects, REJECTS), stage=DISCOVER_STAGE)
    ingest_rejects = store.read_table("rejects", STAGE)
    # the rejects the store holds now, cached shards' too (a shard's own count is of the shards that ran)
    summary = {**totals(reports), "rejected": ingest_rejects.num_rows, "discovery_rejected": len(discovery_rejects),
               "stale_shards_removed": removed}
    rejected = pa.concat_tables([store.read_table("rejects", DISCOVER_STAGE), ingest_rejects])
    total = len(found["entries"]) + len(discovery_rejects)
    if rejected.num_rows and (errors or rejected.num_rows >= total):
        # a run that ends Failed: the command prints no list of its own, so the reasons and hints are logged here
        rows = rejected.to_pylist()
        run.logger.warning("ingest: %d rejected:\n%s", len(rows),
                           "\n".join(reject_lines(rows) + [f"hint: {a}" for a in reject_advice(rows)]))
    elif rejected.num_rows:
        # the ingest tasks logged their own rejects, discovery's are logged here once; the command lists them all,
        # with hints, at its end
        found_lines = reject_lines([r for r in rejected.to_pylist() if r["stage"] == DISCOVER_STAGE])
        run.logger.warning("ingest: %d of %d rejected (`visemeflow rejects --store %s`)%s", rejected.num_rows, total,
                           store.root, "".join("\n" + line for line in found_lines), extra=SUMMARISED)
    if errors:
        raise RuntimeError(f"ingest: {len(errors)} of {len(futures)} shards failed: " + "; ".join(errors[:3]))
    return run.finish(summary, rejected.num_rows, total, rejects=rejected)


def settings_changed(before: IngestConfig | None, now: IngestConfig) -> str:
    """`alignment_tolerance_s 0.5 -> 0.1, ...`: the config fields that differ from the last run's; "" when none (or
    no run before)."""
    if before is None:
        return ""
    old, new = before.model_dump(), now.model_dump()
    return ", ".join(f"{k} {old[k]!r} -> {new[k]!r}" for k in new if old.get(k) != new[k])


def _same_place(a: str, b: str) -> bool:
    if is_url(a) or is_url(b):
        return a.rstrip("/") == b.rstrip("/")
    return Path(a).expanduser().resolve() == Path(b).expanduser().resolve()


def would_drop(store: Store, before: str, now: str, entries: list[dict]) -> str | None:
    """Why this ingest must not run: the store was last ingested from another corpus, and this one lacks utterances
    the store holds (the store mirrors its corpus, so they would go from its tables); None when it may run. The
    same corpus losing files, and captured takes (kept by any ingest), drop nothing here."""
    if _same_place(before, now):
        return None
    kept = {e["utterance_id"] for e in entries}
    rows = store.read_table("utterances").select([C.UTTERANCE_ID, C.ALIGNMENT_FORMAT]).to_pylist()
    dropped = sorted(r[C.UTTERANCE_ID] for r in rows if r[C.UTTERANCE_ID] not in kept and not is_captured(store, r))
    if not dropped:
        return None
    shown = ", ".join(dropped[:3]) + (f" and {len(dropped) - 3} more" if len(dropped) > 3 else "")
    return (f"{store.root} was ingested from {before}; {now} lacks {len(dropped)} of its utterances ({shown}), "
            f"which this ingest would drop from the store's tables. Use another --store, `visemeflow rerun UID` "
            f"for one utterance, or --replace to make {now} the store's corpus")


def _no_corpus(message: str) -> State:
    """The Failed end of a run that found no corpus: nothing ingested, the message logged and raised to callers."""
    get_run_logger().error("ingest: %s", message)
    summary = {"utterances": 0, "discovery_rejected": 0, "refused": True}   # `refused`: the pipeline stops here
    return Failed(message=message, data=StageFailed(f"ingest: {message}", summary))


def corpus_change_refusal(store: Store, corpus: str) -> str | None:
    """What `would_drop` says of ingesting `corpus` into `store` (None when it may run), for the command to check
    before any flow starts; discovery runs only when the store was last ingested from elsewhere (its file hashes
    are memoised, so the flow's own discovery then costs little)."""
    last = last_settings(store, STAGE)
    if last is None or _same_place(last.corpus, corpus):
        return None
    found = discover_corpus(corpus)
    return would_drop(store, last.corpus, corpus, [asdict(e) for e in found.entries])


def rerun_entry(store: Store, uid: str, last: IngestSettings | None) -> dict:
    """`uid`'s entry (a dict) in the corpus of the last ingest run (`last`, its settings) for `visemeflow rerun
    --stage ingest`; RerunError when the store was never ingested or its corpus has no such utterance (what the CLI
    checks before any flow starts)."""
    if last is None:
        raise RerunError(f"{store.root} has no ingest run to repeat; run `visemeflow ingest CORPUS` first")
    found = discover_corpus(last.corpus, only=uid)
    if not found.entries:
        reasons = "; ".join(r.message for r in found.rejects) or "no files for it"
        raise RerunError(f"{uid} is not in the corpus {last.corpus}: {reasons}")
    return asdict(found.entries[0])


def rerun_one(store: Store, uid: str, last: IngestSettings | None, force: bool) -> dict:
    """Ingest one utterance of the last ingest run's corpus again, with its settings (`visemeflow rerun`)."""
    entry = rerun_entry(store, uid, last)
    task = ingest_one.with_options(result_storage=result_storage(store.root), refresh_cache=force)
    return task(str(store.root), shard_of(uid, last.n_shards), entry, last.config)
