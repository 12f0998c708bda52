"""Robustness evaluation (paper Section 5.2, Tables 1-3): validation L1 x 100 on the clean validation set and on
augmented copies of it, and the tables that compare models.

Pure domain code (numpy/torch, no Prefect, no files). The augmented copy of a validation utterance under a
condition is deterministic for (utterance, condition, seed) (:func:`visemeflow.learning.augment.augment_utterance`);
its id traces to the source (``spk/utt__pitch_p2.10``) and for ``speed`` its target curves are resampled by the
same factor (:func:`visemeflow.learning.train.resample_curves`), so frames stay aligned.

Tables follow the paper: one row per model, columns ``validation`` and the four conditions, each condition also
as its ratio to ``validation`` (how much the model degrades). Rows are grouped as in the paper's tables: audio
features with the BLSTM decoder (Table 1), decoders (Table 2), baselines and floors (Table 3).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Sequence

from visemeflow.learning.augment import CONDITIONS, DEFAULT_CONFIG, AugmentConfig, augment_utterance
from visemeflow.learning.train import SAMPLE_RATE, Example, resample_curves

__all__ = ["COLUMNS", "augment_examples", "robustness_table", "table_csv", "table_markdown"]

COLUMNS = ("validation", *CONDITIONS)


def augment_examples(
    examples: Sequence[Example], condition: str, seed: int = 0, config: AugmentConfig = DEFAULT_CONFIG
) -> list[Example]:
    """The augmented copy of each (16 kHz) example under ``condition``: new id, audio, and curves (resampled for speed)."""
    out = []
    for ex in examples:
        aug = augment_utterance(ex.audio, SAMPLE_RATE, ex.utterance_id, condition, seed, config)
        out.append(Example(aug.utterance_id, aug.audio, resample_curves(ex.curves, aug.time_factor), ex.fps))
    return out


def _group(preset: str | None) -> tuple[int, str]:
    if preset is None:
        return 3, "other"
    if preset == "mean-curve" or preset.startswith(("karras", "faceformer")):
        return 2, "baselines and floors (Table 3)"
    if preset.partition("-")[2] == "blstm":
        return 0, "features, BLSTM decoder (Table 1)"
    return 1, "decoders (Table 2)"


def robustness_table(
    rows: Iterable[dict], presets: dict[str, str] | None = None, augmented: dict[str, bool] | None = None
) -> list[dict]:
    """One dict per model from aggregate metrics rows (``utterance_id`` None): L1 x 100 per column and ratios.

    ``rows`` are rows of the ``metrics`` table (any run); the aggregate rows' ``condition`` picks the column.
    ``presets`` (model -> preset name) and ``augmented`` (model -> trained with audio augmentation) only order
    and label the rows. Missing cells are NaN; ``ratio_<condition>`` is condition / validation.
    """
    presets, augmented = presets or {}, augmented or {}
    cells: dict[str, dict[str, float]] = {}
    for r in rows:
        if r.get("utterance_id") is not None or r.get("condition") not in COLUMNS:
            continue
        cells.setdefault(r["model"], {})[r["condition"]] = float(r["l1_x100"])
    table = []
    for model, values in cells.items():
        preset = presets.get(model)
        order, group = _group(preset)
        row = {"group": group, "model": model, "preset": preset or "", "train_augment": bool(augmented.get(model)),
               "_order": order}
        val = values.get("validation", math.nan)
        for col in COLUMNS:
            row[col] = values.get(col, math.nan)
        for cond in CONDITIONS:
            row[f"ratio_{cond}"] = row[cond] / val if val and not math.isnan(val) else math.nan
        table.append(row)
    table.sort(key=lambda r: (r["_order"], r["preset"], r["train_augment"], r["model"]))
    for r in table:
        del r["_order"]
    return table


def _num(x: float, digits: int = 2) -> str:
    return "-" if x is None or math.isnan(x) else f"{x:.{digits}f}"


def table_markdown(table: list[dict], title: str = "Validation L1 x 100 (ratio to validation)") -> str:
    """The table as markdown: `value (ratio)` per condition, group headings as in the paper's tables."""
    head = "| model | preset | train aug. | validation | volume | pitch | speed | noise |"
    lines = [f"### {title}", "", head, "|---|---|---|---|---|---|---|---|"]
    group = None
    for r in table:
        if r["group"] != group:
            group = r["group"]
            lines.append(f"| **{group}** | | | | | | | |")
        conds = " | ".join(f"{_num(r[c])} ({_num(r[f'ratio_{c}'])})" for c in CONDITIONS)
        lines.append(f"| {r['model']} | {r['preset'] or '-'} | {'yes' if r['train_augment'] else 'no'} | "
                     f"{_num(r['validation'])} | {conds} |")
    if not table:
        lines.append("| (no evaluated model) | | | | | | | |")
    return "\n".join(lines) + "\n"


def table_csv(table: list[dict]) -> str:
    fields = ["group", "model", "preset", "train_augment", *COLUMNS, *(f"ratio_{c}" for c in CONDITIONS)]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    for r in table:
        writer.writerow({k: (f"{r[k]:.4f}" if isinstance(r[k], float) else r[k]) for k in fields})
    return buf.getvalue()
