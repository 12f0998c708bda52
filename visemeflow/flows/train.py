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


def resolve_variant(store: Store, source: str, variant: str | None) -> str:
    if variant:
        return variant
    variants = store.curve_variants(source)
    if len(variants) != 1:
        raise LookupError(f"{store.root} has {len(variants)} variants of {source} curves ({', '.join(variants) or 'none'}); "
                          "name one with --variant")
    return variants[0]


@flow(name="train", flow_run_name="train[{params.config.preset}]")
def train_flow(params: TrainParams) -> dict:
    """Train one preset on the store's curves; a killed run resumes from its last epoch checkpoint."""
    check_device_here(params.device, params.precision)
    store = Store(params.store)
    variant = resolve_variant(store, params.source, params.variant)
    train, val, lineage = training_rows(store, params.source, variant)
    if not train:
        raise LookupError(f"no utterance in {store.root} has {params.source} curves of variant {variant!r} in the train split")
    name = params.model_name or f"{params.config.preset}-{stable_hash(params.config, lineage, size=4)}"
    lineage = {**lineage, "config": params.config.model_dump(mode="json")}
    report = training_task_for(store, name)(
        str(store.root), name, train, val, params.source, variant, lineage, params.config, params.device,
        params.precision, None if params.encoder_cache_dir is None else str(params.encoder_cache_dir),
    )
    get_run_logger().info("train %s: %s", name, report)
    return report
