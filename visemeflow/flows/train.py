"""The `train` flow: an audio-to-curves model from the store's curves (tracked by default) and audio.

`params.device` and `params.precision` say where and how the model is computed, not what it is: they enter neither
the model's default name nor the task's cache key. A device this machine does not have fails first, in one line
(`visemeflow.learning.device.DeviceError`), before the store is read.
"""

from prefect import flow, get_run_logger

from visemeflow.flows.params import TrainParams
from visemeflow.hashing import stable_hash
from visemeflow.learning.device import check_device_here
from visemeflow.schemas import C
from visemeflow.storage import Store
from visemeflow.tasks.train import training_task_for

ROW_FIELDS = [C.UTTERANCE_ID, C.CONTENT_HASH, C.AUDIO_PATH, C.FPS, C.SPLIT]


def training_rows(store: Store, source: str, variant: str) -> tuple[list[dict], list[dict], dict]:
    """Train and validation rows (by the `split` column) that have curves of `source`/`variant`, and the lineage."""
    rows = [r for r in store.read_table("utterances").select(ROW_FIELDS).to_pylist()
            if store.has_curves(source, variant, r[C.UTTERANCE_ID])]
    rows.sort(key=lambda r: r[C.UTTERANCE_ID])
    train = [r for r in rows if r[C.SPLIT] != "val"]
    val = [r for r in rows if r[C.SPLIT] == "val"]
    lineage = {
        "source": source, "variant": variant,
        "train": {r[C.UTTERANCE_ID]: store.curves_provenance(source, variant, r[C.UTTERANCE_ID]) for r in train},
        "val": {r[C.UTTERANCE_ID]: store.curves_provenance(source, variant, r[C.UTTERANCE_ID]) for r in val},
    }
    return train, val, lineage


def no_training_reason(store: Store, source: str, variant: str) -> str | None:
    """Why `train` has nothing to learn from (no utterance in the train split has these curves), with what to do;
    None when it has. Only the listing of curve files is read (the CLI checks this before any flow starts)."""
    rows = store.read_table("utterances").select([C.UTTERANCE_ID, C.SPLIT]).to_pylist()
    held = [r for r in rows if store.has_curves(source, variant, r[C.UTTERANCE_ID])]
    if any(r[C.SPLIT] != "val" for r in held):
        return None
    why = (f"the {_count(len(held), 'utterance')} that {'has' if len(held) == 1 else 'have'} them "
           f"{'is' if len(held) == 1 else 'are'} in the `val` split (ingest puts about 10% of the ids there by a hash "
           "of each id; a manifest's `split` column chooses)" if held else "none has them")
    others = [f"--source {other} ({_count(n, 'utterance')})" for other in ("procedural", "tracked", "ground_truth")
              if other != source and (n := _trainable(store, other, rows))]
    return (f"no utterance in {store.root} has {source} curves of variant {variant!r} in the train split: {why}"
            + (f"; train on other curves: {', '.join(others)}" if others else ""))


def _trainable(store: Store, source: str, rows: list[dict]) -> int:
    """Utterances of the train split with curves of `source` of its one variant (0 with none or several)."""
    variants = store.curve_variants(source)
    if len(variants) != 1:
        return 0
    return sum(r[C.SPLIT] != "val" and store.has_curves(source, variants[0], r[C.UTTERANCE_ID]) for r in rows)


def _count(n: int, word: str) -> str:
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def resolve_variant(store: Store, source: str, variant: str | None) -> str:
    if variant:
        return variant
    variants = store.curve_variants(source)
    if len(variants) != 1:
        raise LookupError(f"{store.root} has {len(variants)} variants of {source} curves ({', '.join(variants) or 'none'}); "
                          "name one with --variant")
    return variants[0]


@flow(name="train", flow_run_name="train({params.config.preset})")
def train_flow(params: TrainParams) -> dict:
    """Train one preset on the store's curves; a killed run resumes from its last epoch checkpoint."""
    check_device_here(params.device, params.precision)
    store = Store(params.store)
    variant = resolve_variant(store, params.source, params.variant)
    train, val, lineage = training_rows(store, params.source, variant)
    if not train:
        raise LookupError(no_training_reason(store, params.source, variant))
    name = params.model_name or f"{params.config.preset}-{stable_hash(params.config, lineage, size=4)}"
    lineage = {**lineage, "config": params.config.model_dump(mode="json")}
    report = training_task_for(store, name)(
        str(store.root), name, train, val, params.source, variant, lineage, params.config, params.device,
        params.precision, None if params.encoder_cache_dir is None else str(params.encoder_cache_dir),
    )
    get_run_logger().info("train %s: %s", name, report)
    return report
