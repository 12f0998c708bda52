"""Evaluation tasks: augmented copies of the validation audio (shared by every model), and one model's L1 x 100
on the validation set and on each augmented copy."""

from pathlib import Path

import numpy as np
import pyarrow as pa
import soundfile as sf
from prefect import get_run_logger, task

from visemeflow.hashing import stable_hash
from visemeflow.learning.augment import AugmentConfig, augment_utterance, augmented_id, draw_value
from visemeflow.learning.train import SAMPLE_RATE, Example, evaluate, load_model, resample_curves
from visemeflow.schemas import METRICS, C
from visemeflow.storage import Store
from visemeflow.tasks.common import CACHE_POLICY, result_storage
from visemeflow.tasks.train import load_audio, load_examples, metrics_rows

RUN = "evaluate"


def augmentation_name(condition: str, seed: int, config: AugmentConfig) -> str:
    """Folder of one augmentation set: `pitch-s0`, plus a hash when the ranges differ from the paper's."""
    name = f"{condition}-s{seed}"
    if config != AugmentConfig():
        name += "-" + stable_hash(config, size=4)
    return name


def expected_augmented_ids(rows: list[dict], condition: str, seed: int, config: AugmentConfig) -> list[str]:
    """Ids of the augmented copies of `rows` (the drawn values are known without computing any audio)."""
    return [augmented_id(r[C.UTTERANCE_ID], condition, draw_value(condition, r[C.UTTERANCE_ID], seed, config))
            for r in rows]


def _write_wav(store: Store, path: Path, audio: np.ndarray) -> None:
    # float samples: a +10 dB copy may exceed [-1, 1] and must reach the model unclipped
    store.write_file(path, lambda tmp: sf.write(tmp, audio, SAMPLE_RATE, subtype="FLOAT", format="WAV"))


@task(cache_policy=CACHE_POLICY, persist_result=True, task_run_name="augment[{condition}]")
def augment_condition(store_root: str, condition: str, seed: int, config: AugmentConfig, rows: list[dict]) -> list[dict]:
    """Write the augmented copy of every validation utterance under one condition; returns where and how."""
    store = Store(store_root)
    name = augmentation_name(condition, seed, config)
    out = []
    for row in rows:
        uid = row[C.UTTERANCE_ID]
        aug = augment_utterance(load_audio(row[C.AUDIO_PATH]), SAMPLE_RATE, uid, condition, seed, config)
        path = store.augmented_audio_path(name, aug.utterance_id)
        _write_wav(store, path, aug.audio)
        out.append({"source_id": uid, "utterance_id": aug.utterance_id, "path": str(path),
                    "time_factor": aug.time_factor, "value": aug.value})
    get_run_logger().info("%s: %d augmented utterances in %s", condition, len(out), name)
    return out


def augmented_task_for(store: Store, rows: list[dict], condition: str, seed: int, config: AugmentConfig):
    """`augment_condition` with the store's result storage; recomputed when an augmented file is missing."""
    name = augmentation_name(condition, seed, config)
    missing = not all(store.has_augmented_audio(name, a) for a in expected_augmented_ids(rows, condition, seed, config))
    return augment_condition.with_options(result_storage=result_storage(store.root), refresh_cache=missing)


@task(cache_policy=CACHE_POLICY, persist_result=True, task_run_name="evaluate[{model_name}]")
def evaluate_model(
    store_root: str, model_name: str, model_hash: str, val_rows: list[dict], augmented: dict[str, list[dict]],
    source: str, variant: str, targets: dict[str, str | None],
) -> dict:
    """L1 x 100 of one model on the validation set and each augmented copy; rows into `metrics` (run 'evaluate').

    `model_hash` (the model file's content hash) and `targets` (the target curves' provenance) are inputs so
    that the cache is invalidated by a retrained model or changed curves.
    """
    store = Store(store_root)
    model, config, _ = load_model(store.model_path(model_name))
    val = load_examples(store, val_rows, source, variant)
    by_id = {ex.utterance_id: ex for ex in val}
    sets = {"validation": val}
    for condition, items in augmented.items():
        sets[condition] = [
            Example(item["utterance_id"], load_audio(item["path"]),
                    resample_curves(by_id[item["source_id"]].curves, item["time_factor"]), by_id[item["source_id"]].fps)
            for item in items
        ]
    rows, summary = [], {}
    for condition, examples in sets.items():
        overall, per_utt, per_vis = evaluate(model, examples)
        rows += metrics_rows(RUN, model_name, condition, overall, per_utt, per_vis)
        summary[condition] = overall
    store.write_metrics(model_name, RUN, pa.Table.from_pylist(rows, schema=METRICS))
    get_run_logger().info("%s: %s", model_name, {k: round(v, 3) for k, v in summary.items()})
    return {"model": model_name, "preset": config.preset, "train_augment": config.train_augment, "l1_x100": summary}


def evaluation_task_for(store: Store, model_name: str):
    """`evaluate_model` with the store's result storage; recomputed when its metrics file is missing."""
    return evaluate_model.with_options(
        result_storage=result_storage(store.root),
        refresh_cache=not store.has_metrics(model_name, RUN),
    )
