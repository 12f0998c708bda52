"""Procedural-curve tasks: JALI-like curves for a shard of utterances, or for one utterance."""

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from prefect import get_run_logger, task

from visemeflow.atomic import group_sync
from visemeflow.hashing import stable_hash
from visemeflow.phonetics.types import VisemeSegment
from visemeflow.procedural import ProceduralConfig, generate_procedural_curves
from visemeflow.schemas import C, REJECTS, CurveSource, Curves, table_from_rows
from visemeflow.schemas.tables import has_alignment
from visemeflow.storage import Store
from visemeflow.tasks.code_version import code_digest
from visemeflow.tasks.common import CACHE_POLICY, MADE_FROM_KEY, RESULT_SERIALIZER, reject_row
from visemeflow.timebase import frame_count

STAGE = "procedural"
SOURCE = CurveSource.PROCEDURAL


def default_variant(config: ProceduralConfig) -> str:
    """`jali` for the default rules at each utterance's frame rate (`jali-25fps` when fixed); a config hash
    is appended when other constants differ from the defaults."""
    name = "jali" if config.fps is None else f"jali-{config.fps:g}fps"
    if config != ProceduralConfig(fps=config.fps):
        name += "-" + stable_hash(config, size=4)
    return name


def segments_from_phones(phones: pa.Table) -> list[VisemeSegment]:
    """Viseme segments (silence and transparent phones dropped) of one utterance's phone rows, in time order."""
    rows = phones.select([C.VISEME, C.START_S, C.END_S, C.WORD_INDEX, C.PHONEME]).to_pylist()
    rows.sort(key=lambda r: r[C.START_S])
    return [
        VisemeSegment(r[C.VISEME], r[C.START_S], r[C.END_S], r[C.WORD_INDEX], r[C.PHONEME] or "")
        for r in rows if r[C.VISEME] is not None
    ]


def shard_digest(utterances: list[dict], config: ProceduralConfig, variant: str) -> str:
    """What a procedural shard's rejects file records it was made from (`common.made_from`): its utterance rows
    (with their content hashes), the config, the variant and the code."""
    return stable_hash(utterances, config, variant, code_digest(__name__))


def provenance(utterance: dict, config: ProceduralConfig) -> str:
    """What made an utterance's curves: its input files' content hash, its clock (the frame rate and frame count
    ingest gave it, which the curves follow unless `config.fps` is set: a pipeline run again with another --fps
    makes them again), the config and the code."""
    clock = stable_hash(float(utterance[C.FPS]), int(utterance[C.N_FRAMES]), float(utterance[C.DURATION_S]))
    return f"procedural:{utterance[C.CONTENT_HASH]}:{stable_hash(config)}:{clock}:{code_digest(__name__)}"


def generate_for_utterance(
    store: Store, utterance: dict, phones: pa.Table, config: ProceduralConfig, variant: str
) -> None:
    """Generate and store the procedural curves of one ingested utterance."""
    uid = utterance[C.UTTERANCE_ID]
    if config.fps is None:  # the utterance's own clock: its video's frames, or the ingest default rate
        fps, n_frames = float(utterance[C.FPS]), int(utterance[C.N_FRAMES])
    else:
        fps, n_frames = config.fps, frame_count(utterance[C.DURATION_S], config.fps)
    curves = generate_procedural_curves(segments_from_phones(phones), n_frames, fps, config)
    # NaN or infinite curves are refused by the store (NonFiniteValueError, a reject of this utterance)
    store.save_curves(Curves(curves, fps, uid, SOURCE, variant, provenance(utterance, config)))


def _read_phones(store: Store, shard: int, ids: list[str]) -> pa.Table:
    """Phone rows of `ids`: from the same-numbered phones shard when ingest used the same sharding (one
    file read), else by a filtered scan of all phone shards."""
    table = store.read_shard("phones", shard)
    table = table.filter(pc.is_in(table.column(C.UTTERANCE_ID), pa.array(ids, pa.string())))
    missing = sorted(set(ids) - set(pc.unique(table.column(C.UTTERANCE_ID)).to_pylist()))
    if missing:
        table = pa.concat_tables([table, store.read_table("phones", utterance_ids=missing)])
    return table


def _generate_many(
    store: Store, shard: int, utterances: list[dict], config: ProceduralConfig, variant: str, force: bool
) -> tuple[int, int, list[dict]]:
    ids = [u[C.UTTERANCE_ID] for u in utterances]
    phones = _read_phones(store, shard, ids)
    phones = phones.sort_by([(C.UTTERANCE_ID, "ascending"), (C.START_S, "ascending")])
    id_col = phones.column(C.UTTERANCE_ID).to_numpy(zero_copy_only=False)
    bounds = {}
    if len(id_col):
        change = np.flatnonzero(id_col[1:] != id_col[:-1]) + 1
        starts = np.concatenate([[0], change])
        ends = np.concatenate([change, [len(id_col)]])
        bounds = {id_col[s]: (s, e) for s, e in zip(starts, ends)}
    generated, reused, rejects = 0, 0, []
    with group_sync():   # one flush for the shard's curve files, before the caller records anything (atomic.py)
        for u in utterances:
            uid = u[C.UTTERANCE_ID]
            if not has_alignment(u):  # no phones (a video without an alignment, a captured take): nothing to make
                get_run_logger().info("%s has no alignment: no procedural curves (it has no phones)", uid)
                continue
            if not force and store.curves_provenance(SOURCE, variant, uid) == provenance(u, config):
                reused += 1
                continue
            s, e = bounds.get(uid, (0, 0))
            try:
                generate_for_utterance(store, u, phones.slice(s, e - s), config, variant)
            except (ValueError, FloatingPointError, MemoryError) as exc:   # one utterance's fault, not the shard's
                rejects.append(reject_row(uid, STAGE, type(exc).__name__, f"{uid}: {exc}" if isinstance(exc, MemoryError)
                                          else str(exc), u[C.ALIGNMENT_PATH]))
                continue
            generated += 1
    return generated, reused, rejects


@task(cache_policy=CACHE_POLICY, persist_result=True, result_serializer=RESULT_SERIALIZER,
      task_run_name="procedural[shard-{shard:02d}]")
def procedural_shard(
    store_root: str, shard: int, utterances: list[dict], config: ProceduralConfig, variant: str
) -> dict[str, int]:
    """Procedural curves for one shard; utterances whose stored curves match are left as they are."""
    store = Store(store_root)
    generated, reused, rejects = _generate_many(store, shard, utterances, config, variant, force=False)
    store.write_shard("rejects", shard, table_from_rows(rejects, REJECTS), stage=STAGE,     # last: the shard's stamp
                      metadata={MADE_FROM_KEY: shard_digest(utterances, config, variant).encode()})
    logger = get_run_logger()
    for r in rejects:
        logger.info("rejected %s", r[C.MESSAGE])
    logger.info("shard %02d: %d generated, %d reused, %d rejected", shard, generated, reused, len(rejects))
    return {"shard": shard, "utterances": len(utterances), "generated": generated, "reused": reused,
            "rejected": len(rejects)}


@task(cache_policy=CACHE_POLICY, persist_result=True, result_serializer=RESULT_SERIALIZER,
      task_run_name="procedural[{utterance[utterance_id]}]")
def procedural_one(
    store_root: str, shard: int, utterance: dict, config: ProceduralConfig, variant: str
) -> dict[str, int]:
    """Regenerate the procedural curves of one utterance (a rerun by hand), whatever is stored."""
    store = Store(store_root)
    generated, _, rejects = _generate_many(store, shard, [utterance], config, variant, force=True)
    uid = utterance[C.UTTERANCE_ID]
    store.replace_utterance_rows("rejects", shard, uid, table_from_rows(rejects, REJECTS), stage=STAGE)
    if rejects:
        get_run_logger().info("rejected %s", rejects[0][C.MESSAGE])
    return {"shard": shard, "utterances": 1, "generated": generated, "reused": 0, "rejected": len(rejects)}
