"""Evaluation tasks: augmented copies of the validation audio (shared by every model), and one model's L1 x 100
on the validation set and on each augmented copy, with the real-speech metrics (closure recall, activation
agreement) of the validation utterances that have phones.

The evaluation task runs its model on the device it is given, in float32; the device is not part of its cache key
(`EVALUATE_CACHE_POLICY`). The reserved model name `phones` is scored like a model (`visemeflow.tasks.models`): its
row in the robustness table is the baseline that needs no training.

Lip metrics: the same predicted curves of the utterances with phones, as the demo character shows them (through the
closure rule `articulation.close_lips`, which the animation stage applies to curves of every source), measured on its
mesh in millimetres (`animation.lips.LipProbe`) and scored per phone (`learning.lipscore`): runs `evaluate.lip_*`
(`lip_rows`). The geometry is computed here, in the task layer: `learning/` may not import `animation/` or `rig/`.
`evaluate.lip_closed_raw` is the closed share of the model's own curves, without the rule."""

from functools import lru_cache
from pathlib import Path

import numpy as np
import pyarrow as pa
import soundfile as sf
from prefect import get_run_logger, task
from prefect.cache_policies import TASK_SOURCE, Inputs

from visemeflow.animation.lips import LipProbe
from visemeflow.hashing import stable_hash
from visemeflow.learning.augment import AugmentConfig, augment_utterance, augmented_id, draw_value
from visemeflow.learning.lipscore import LipScores
from visemeflow.learning.realspeech import RealSpeechScores, Recall, phones_of, scale_phones
from visemeflow.learning.robustness import example_curves, lip_evaluation, realspeech_evaluation
from visemeflow.learning.robustness_table import (
    CLOSURE_METRICS,
    FALSE_CLOSURE_METRICS,
    LIP_RUNS,
    LIP_SUMMARY_KEYS,
    REALSPEECH_METRICS,
    REALSPEECH_RUNS,
)
from visemeflow.learning.train import SAMPLE_RATE, Example, evaluate, resample_curves
from visemeflow.location import local_input
from visemeflow.rig import load_demo_rig
from visemeflow.schemas import METRICS, C
from visemeflow.storage import Store
from visemeflow.tasks.common import CACHE_POLICY, CODE, RESULT_SERIALIZER, DataOnlyCache, result_storage
from visemeflow.tasks.models import load_curve_model
from visemeflow.tasks.train import load_audio, load_examples, metrics_rows

RUN = "evaluate"

# INPUTS + TASK_SOURCE + CODE like every task, without where the model runs
EVALUATE_CACHE_POLICY = Inputs(exclude=["device"]) + TASK_SOURCE + CODE


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


@task(cache_policy=CACHE_POLICY, persist_result=True, result_serializer=RESULT_SERIALIZER,
      task_run_name="augment[{condition}]")
def augment_condition(store_root: str, condition: str, seed: int, config: AugmentConfig, rows: list[dict]) -> list[dict]:
    """Write the augmented copy of every validation utterance under one condition; returns where and how."""
    store = Store(store_root)
    name = augmentation_name(condition, seed, config)
    out = []
    for row in rows:
        uid = row[C.UTTERANCE_ID]
        aug = augment_utterance(load_audio(local_input(row[C.AUDIO_PATH])), SAMPLE_RATE, uid, condition, seed, config)
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


_METRIC_RUNS = {metric: run for run, metric in REALSPEECH_RUNS.items()}


def _recall(scores: RealSpeechScores, metric: str) -> Recall:
    if metric in CLOSURE_METRICS:
        return scores.closure.get(CLOSURE_METRICS[metric], Recall())
    if metric in FALSE_CLOSURE_METRICS:
        return scores.false_closure.get(FALSE_CLOSURE_METRICS[metric], Recall())
    return scores.agreement.overall


def realspeech_rows(model: str, condition: str, pooled: RealSpeechScores,
                    per_utterance: dict[str, RealSpeechScores]) -> list[dict]:
    """Rows of the `metrics` table for the real-speech metrics of one (model, condition), runs
    `evaluate.mbp_closure`, `evaluate.fff_closure`, `evaluate.mbp_false_closure`, `evaluate.fff_false_closure`,
    `evaluate.agreement` (same schema as the L1 rows).

    `l1` holds the share (0..1) and `l1_x100` the percentage; the aggregate (pooled over phones) and one row per
    utterance, each only where defined (an utterance without b/p/m phones has no `evaluate.mbp_closure` row, a
    validation set without any has none at all: the store refuses NaN). The aggregate row of
    `evaluate.agreement` also holds each viseme's agreement in `l1_<VISEME>` (null where it has no phone).
    """
    rows = []
    for metric in REALSPEECH_METRICS:
        base = {C.RUN: _METRIC_RUNS[metric], C.MODEL: model, C.CONDITION: condition, C.EPOCH: None}
        share = _recall(pooled, metric).share
        if share is None:
            continue
        aggregate = {**base, C.UTTERANCE_ID: None, C.L1: share, C.L1_X100: 100.0 * share}
        if metric == "agreement":
            aggregate.update({C.L1_PREFIX + v: r.share for v, r in pooled.agreement.per_viseme.items()})
        rows.append(aggregate)
        for uid, scores in sorted(per_utterance.items()):
            one = _recall(scores, metric).share
            if one is not None:
                rows.append({**base, C.UTTERANCE_ID: uid, C.L1: one, C.L1_X100: 100.0 * one})
    return rows


@lru_cache(maxsize=1)
def demo_lip_probe() -> LipProbe:
    """The lip probe of the shipped demo character (ICT face, centimetres), built once per process."""
    return LipProbe.from_rig(load_demo_rig())


def lip_scores(curves: dict[str, np.ndarray], fps: dict[str, float], phones: dict, probe: LipProbe | None = None,
               closure_rule: bool = True) -> tuple[LipScores, dict[str, LipScores]]:
    """(pooled, per utterance) lip scores of curves on a character's mesh (default: the demo character), through
    the closure rule unless `closure_rule` is False."""
    probe = probe or demo_lip_probe()

    def measure(c: np.ndarray):
        frames = probe.measure(c)
        return frames.gap_mm, frames.teeth_mm

    return lip_evaluation(curves, fps, phones, measure, probe.single_shape_gap("AHH"), closure_rule)


_LIP_METRIC_RUNS = {metric: run for run, metric in LIP_RUNS.items()}


def lip_rows(model: str, condition: str, pooled: LipScores, per_utterance: dict[str, LipScores],
             pooled_raw: LipScores, per_raw: dict[str, LipScores]) -> list[dict]:
    """Rows of the `metrics` table for the lip metrics of one (model, condition): runs `evaluate.lip_closed`,
    `evaluate.lip_gap_mm`, `evaluate.fv_contact`, `evaluate.vowel_opening`, `evaluate.lip_false_closed` (curves
    through the closure rule) and `evaluate.lip_closed_raw` (without it).

    `l1` holds the share (0..1), the median gap in mm or the median vowel opening (a ratio to the widest single
    shape), `l1_x100` is 100 x `l1`; the aggregate (pooled over phones) and one row per utterance, each only where
    defined (no b/p/m phone: no `lip_closed` row)."""
    rows = []
    for metric, key in LIP_SUMMARY_KEYS.items():
        base = {C.RUN: _LIP_METRIC_RUNS[metric], C.MODEL: model, C.CONDITION: condition, C.EPOCH: None}
        raw = metric.endswith("_raw")
        pooled_scores, per = (pooled_raw, per_raw) if raw else (pooled, per_utterance)
        for uid, scores in [(None, pooled_scores), *sorted(per.items())]:
            value = scores.summary()[key]
            if value is None:
                continue
            rows.append({**base, C.UTTERANCE_ID: uid, C.L1: float(value), C.L1_X100: 100.0 * float(value)})
    return rows


def _lip_counts(pooled: LipScores) -> dict:
    summary = pooled.summary()
    return {m: summary[k] for m, k in LIP_SUMMARY_KEYS.items() if not m.endswith("_raw")} | {
        "bilabials": summary["bilabials"], "labiodentals": summary["labiodentals"], "vowels": summary["vowels"]}


@task(cache_policy=DataOnlyCache(policy=EVALUATE_CACHE_POLICY), persist_result=True,
      result_serializer=RESULT_SERIALIZER,
      task_run_name="evaluate[{model_name}]")
def evaluate_model(
    store_root: str, model_name: str, model_hash: str, val_rows: list[dict], augmented: dict[str, list[dict]],
    source: str, variant: str, targets: dict[str, str | None], phones: dict[str, list[dict]] | None = None,
    device: str = "auto",
) -> dict:
    """L1 x 100 of one model on the validation set and each augmented copy; rows into `metrics` (run 'evaluate').

    `phones` (validation utterance id -> its phone rows: `start_s`, `end_s`, `viseme`) adds the real-speech
    metrics of those utterances on every condition (runs `evaluate.<metric>`, see `realspeech_rows`); the phones
    of a speed copy are scaled by its time factor; and the lip metrics of the same curves on the demo character's
    mesh, through the closure rule (runs `evaluate.lip_*`, see `lip_rows`). `model_hash` (the model file's
    content hash), `targets` (the target curves' provenance) and `phones` are inputs so that the cache is
    invalidated by a retrained model, changed curves or a changed alignment. `device` (auto, cpu, cuda, cuda:N):
    where the model runs (float32).
    """
    store = Store(store_root)
    model, preset, train_augment = load_curve_model(store, model_name, device)
    val = load_examples(store, val_rows, source, variant)
    by_id = {ex.utterance_id: ex for ex in val}
    aligned = {uid: phones_of(rows) for uid, rows in (phones or {}).items() if uid in by_id}
    sets = {"validation": val}
    set_phones = {"validation": aligned}
    for condition, items in augmented.items():
        sets[condition] = [
            Example(item["utterance_id"], load_audio(store.local_file_at(item["path"])),
                    resample_curves(by_id[item["source_id"]].curves, item["time_factor"]), by_id[item["source_id"]].fps)
            for item in items
        ]
        set_phones[condition] = {item["utterance_id"]: scale_phones(aligned[item["source_id"]], item["time_factor"])
                                 for item in items if item["source_id"] in aligned}
    rows, summary, real, lips = [], {}, {}, {}
    for condition, examples in sets.items():
        overall, per_utt, per_vis = evaluate(model, examples)
        rows += metrics_rows(RUN, model_name, condition, overall, per_utt, per_vis)
        summary[condition] = overall
        if set_phones[condition]:
            with_phones = [ex for ex in examples if ex.utterance_id in set_phones[condition]]
            curves = {ex.utterance_id: example_curves(model, ex) for ex in with_phones}   # predicted once
            pooled, per = realspeech_evaluation(model, examples, set_phones[condition], curves=curves)
            rows += realspeech_rows(model_name, condition, pooled, per)
            real[condition] = {m: [_recall(pooled, m).hits, _recall(pooled, m).total] for m in REALSPEECH_METRICS}
            fps = {ex.utterance_id: ex.fps for ex in with_phones}
            lip, lip_per = lip_scores(curves, fps, set_phones[condition])
            raw, raw_per = lip_scores(curves, fps, set_phones[condition], closure_rule=False)
            rows += lip_rows(model_name, condition, lip, lip_per, raw, raw_per)
            lips[condition] = _lip_counts(lip) | {"lip_closed_raw": raw.closed.share}
    store.write_metrics(model_name, RUN, pa.Table.from_pylist(rows, schema=METRICS))
    get_run_logger().info("%s: L1 x 100 %s; real speech (hits, phones) %s; lips on the demo character %s",
                          model_name, {k: round(v, 3) for k, v in summary.items()}, real, lips.get("validation"))
    return {"model": model_name, "preset": preset, "train_augment": train_augment, "l1_x100": summary,
            "realspeech": real, "lips": lips}


def evaluation_task_for(store: Store, model_name: str):
    """`evaluate_model` with the store's result storage; recomputed when its metrics file is missing."""
    return evaluate_model.with_options(
        result_storage=result_storage(store.root),
        refresh_cache=not store.has_metrics(model_name, RUN),
    )
