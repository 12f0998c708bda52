"""Ingestion tasks: discover the corpus, ingest one shard of utterances, or one utterance."""

import logging
from dataclasses import asdict

import pyarrow as pa
from prefect import get_run_logger, task
from prefect.cache_policies import NONE

from visemeflow.hashing import stable_hash
from visemeflow.ingest import (
    CorpusEntry,
    IngestConfig,
    IngestError,
    discover_corpus,
    ingest_utterance,
)
from visemeflow.schemas import C, PHONES, REJECTS, UTTERANCES, CurveSource, table_from_rows
from visemeflow.schemas.tables import NO_ALIGNMENT, has_alignment
from visemeflow.storage import Store
from visemeflow.tasks.code_version import code_digest
from visemeflow.tasks.common import (
    CACHE_POLICY,
    MADE_FROM_KEY,
    RESULT_SERIALIZER,
    made_from,
    reject_row,
)

STAGE = "ingest"
CONFIG_KEY = b"visemeflow.ingest_config"


@task(cache_policy=NONE, task_run_name="discover[{corpus}]")
def discover_corpus_task(corpus: str, only: str | None = None) -> dict[str, list[dict]]:
    """Entries and discovery rejects of a corpus, as plain dicts (hashes of the current files), and the notes of
    what discovery chose (logged as warnings: a `take.flac` beside `take.wav` is not read)."""
    found = discover_corpus(corpus, only)
    if found.notes:
        from prefect.exceptions import MissingContextError

        try:
            logger = get_run_logger()
        except MissingContextError:      # called outside a flow run (`discover_corpus_task.fn`)
            logger = logging.getLogger(__name__)
        for note in found.notes[:20]:
            logger.warning("discover: %s", note)
        if len(found.notes) > 20:
            logger.warning("discover: %d more utterances with two files of one kind", len(found.notes) - 20)
    return {
        "entries": [asdict(e) for e in found.entries],
        "rejects": [asdict(r) for r in found.rejects],
        "notes": list(found.notes),
    }


def ingest_entries(
    entries: list[CorpusEntry], config: IngestConfig, previous: dict[str, tuple[str, dict, list[dict]]] | None = None
) -> tuple[list[dict], list[dict], list[dict], int]:
    """(utterance rows, phone rows, reject rows, number reused) for entries, reusing unchanged ones."""
    utterances, phones, rejects, reused = [], [], [], 0
    for entry in entries:
        prior = (previous or {}).get(entry.utterance_id)
        if prior is not None and prior[0] == entry.content_hash:
            utterances.append(prior[1])
            phones.extend(prior[2])
            reused += 1
            continue
        try:
            result = ingest_utterance(entry, config)
        except IngestError as exc:
            rejects.append(reject_row(exc.utterance_id, STAGE, exc.error_type, str(exc), exc.path))
            continue
        except Exception as exc:  # noqa: BLE001 - a fault of one utterance's files is its reject, never its shard's
            path = entry.alignment_path or entry.audio_path
            rejects.append(reject_row(entry.utterance_id, STAGE, type(exc).__name__,
                                      f"{entry.utterance_id}: {path}: {type(exc).__name__}: {exc}", path))
            continue
        utterances.append(result.utterance)
        phones.extend(result.phones)
    return utterances, phones, rejects, reused


def _previous_rows(store: Store, shard: int, config_hash: str) -> dict[str, tuple[str, dict, list[dict]]]:
    """Rows stored for a shard by the same ingest config, by utterance id."""
    metadata = store.shard_metadata("utterances", shard)
    if metadata is None or metadata.get(CONFIG_KEY, b"").decode() != config_hash:
        return {}
    utts = store.read_shard("utterances", shard).to_pylist()
    phone_table = store.read_shard("phones", shard)
    by_id: dict[str, list[dict]] = {}
    for row in phone_table.to_pylist():
        by_id.setdefault(row[C.UTTERANCE_ID], []).append(row)
    return {u[C.UTTERANCE_ID]: (u[C.CONTENT_HASH], u, by_id.get(u[C.UTTERANCE_ID], [])) for u in utts}


def _config_hash(config: IngestConfig) -> str:
    return stable_hash(config, code_digest(__name__))  # rows made by other code are made again


def shard_digest(entries: list[dict], config: IngestConfig) -> str:
    """What an ingest shard's `utterances` file records it was made from (`common.made_from`): its entries (with
    their files' content hashes) and the config."""
    return stable_hash(entries, _config_hash(config))


def shard_current(store: Store, shard: int, entries: list[dict], config: IngestConfig) -> bool:
    """Whether all outputs of an ingest shard are in the store and were made from these entries (else its cache
    record, if any, is stale: the files changed since, or changed and changed back)."""
    return shard_files_present(store, shard) and made_from(store, "utterances", shard, None,
                                                            shard_digest(entries, config))


@task(cache_policy=CACHE_POLICY, persist_result=True, result_serializer=RESULT_SERIALIZER,
      task_run_name="ingest[shard-{shard:02d}]")
def ingest_shard(store_root: str, shard: int, entries: list[dict], config: IngestConfig) -> dict[str, int]:
    """Ingest one shard of the corpus into the `utterances`, `phones` and `rejects` tables."""
    store = Store(store_root)
    config_hash = _config_hash(config)
    objs = [CorpusEntry(**e) for e in entries]
    utterances, phones, rejects, reused = ingest_entries(objs, config, _previous_rows(store, shard, config_hash))
    unaligned = sum(not has_alignment(u) for u in utterances)
    corpus_ids = {o.utterance_id for o in objs}
    store.write_shard("phones", shard, table_from_rows(phones, PHONES))
    store.write_shard("rejects", shard, table_from_rows(rejects, REJECTS), stage=STAGE)
    # last: it stamps the shard; the captured takes are those stored when it writes (an import during this run
    # stays), read under the shard's lock
    store.write_shard("utterances", shard, table_from_rows(utterances, UTTERANCES),
                      metadata={CONFIG_KEY: config_hash.encode(),
                                MADE_FROM_KEY: shard_digest(entries, config).encode()},
                      keep=lambda stored: captured_of(store, stored, corpus_ids))
    logger = get_run_logger()
    for r in rejects:
        logger.info("rejected %s", r[C.MESSAGE])
    report = {"shard": shard, "utterances": len(objs), "ingested": len(utterances) - reused,
              "reused": reused, "rejected": len(rejects), "unaligned": unaligned}
    logger.info("shard %02d: %d utterances, %d ingested, %d reused, %d rejected; %d videos without an alignment "
                "(kept without phones)", shard, len(objs), report["ingested"], reused, len(rejects), unaligned)
    return report


@task(cache_policy=CACHE_POLICY, persist_result=True, result_serializer=RESULT_SERIALIZER,
      task_run_name="ingest[{entry[utterance_id]}]")
def ingest_one(store_root: str, shard: int, entry: dict, config: IngestConfig) -> dict[str, int]:
    """Ingest one utterance and replace its rows in its shard (a rerun by hand)."""
    store = Store(store_root)
    obj = CorpusEntry(**entry)
    utterances, phones, rejects, _ = ingest_entries([obj], config)
    uid = obj.utterance_id
    store.replace_utterance_rows("phones", shard, uid, table_from_rows(phones, PHONES))
    store.replace_utterance_rows("rejects", shard, uid, table_from_rows(rejects, REJECTS), stage=STAGE)
    store.replace_utterance_rows("utterances", shard, uid, table_from_rows(utterances, UTTERANCES))
    if rejects:
        get_run_logger().info("rejected %s", rejects[0][C.MESSAGE])
    return {"shard": shard, "utterances": 1, "ingested": len(utterances), "reused": 0, "rejected": len(rejects),
            "unaligned": sum(not has_alignment(u) for u in utterances)}


CAPTURED_SOURCE = CurveSource.CAPTURED


def is_captured(store: Store, row: dict) -> bool:
    """A row that `visemeflow import-curves` wrote: no alignment, and captured curves stored (an import writes
    the curves before the row and removes both on a reject). A corpus video without an alignment has the same
    `alignment_format` but no captured curves: it is the corpus's, and goes when the corpus no longer holds it."""
    return row[C.ALIGNMENT_FORMAT] == NO_ALIGNMENT and bool(store.curve_variants(CAPTURED_SOURCE, row[C.UTTERANCE_ID]))


def captured_of(store: Store, stored: pa.Table, corpus_ids: set[str]) -> pa.Table:
    """The rows of an `utterances` shard (as read: `Store.write_shard`'s `keep`) that no corpus file made (captured
    takes, `visemeflow import-curves`: no alignment) and the corpus does not hold now: an ingest keeps them."""
    captured = [r[C.UTTERANCE_ID] not in corpus_ids and is_captured(store, r) for r in
                stored.select([C.UTTERANCE_ID, C.ALIGNMENT_FORMAT]).to_pylist()]
    return stored.filter(pa.array(captured, pa.bool_())) if stored.num_rows else stored


def captured_shards(store: Store) -> set[int]:
    """Shards holding captured takes' rows (an ingest whose corpus has none in them keeps them alive)."""
    return {shard for shard in store.shards("utterances")
            if any(is_captured(store, r) for r in store.read_shard("utterances", shard)
                   .select([C.UTTERANCE_ID, C.ALIGNMENT_FORMAT]).to_pylist())}


def shard_files_present(store: Store, shard: int) -> bool:
    """Whether all outputs of an ingest shard are in the store (else its cache entry is stale)."""
    return (store.has_shard("utterances", shard) and store.has_shard("phones", shard)
            and store.has_shard("rejects", shard, STAGE))


def remove_stale_shards(store: Store, live: set[int]) -> int:
    """Delete shard files of shards that no longer hold any utterance; returns how many shards went."""
    removed: set[int] = set()
    for table, stage in (("utterances", None), ("phones", None), ("rejects", STAGE)):
        removed.update(store.delete_shards_except(table, live, stage))
    return len(removed)
