"""The robustness table (paper Tables 1-3) from rows of the `metrics` table: the one definition of its cells, rows
and columns, used by the `evaluate` flow's report and by the HTML dashboard alike.

Kept apart from `learning/robustness.py` (which augments audio and imports torch) so that the dashboard can build
the same table without loading torch: it imports nothing of ours but the augmentation condition names.

Which metrics rows make a cell: the aggregate row (``utterance_id`` null) of run ``evaluate`` for that (model,
condition). That row is the mean L1 over every frame and viseme of the condition's utterances, the number the paper
reports and the one training reports as validation L1; averaging the per-utterance rows instead would weigh a
one-second utterance like a ten-second one and give another number. Should a (model, condition) have several
aggregate rows (the store keeps one evaluation per model, but rows can be gathered from several reads), the latest
wins: the highest epoch, then the last row given, as a new evaluation replaces the old one in the store.
Averaging them would mix a stale evaluation into a fresh one.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable

from visemeflow.learning.augment import CONDITIONS

__all__ = ["COLUMNS", "RUN", "robustness_table", "table_columns", "table_csv", "table_markdown"]

RUN = "evaluate"
COLUMNS = ("validation", *CONDITIONS)
_FIXED_KEYS = {"group", "model", "preset", "train_augment"}


def _group(preset: str | None) -> tuple[int, str]:
    if not preset:
        return 3, "other"
    if preset == "mean-curve" or preset.startswith(("karras", "faceformer")):
        return 2, "baselines and floors (Table 3)"
    if preset.partition("-")[2] == "blstm":
        return 0, "features, BLSTM decoder (Table 1)"
    return 1, "decoders (Table 2)"


def robustness_table(
    rows: Iterable[dict], presets: dict[str, str] | None = None, augmented: dict[str, bool] | None = None
) -> list[dict]:
    """One dict per model from aggregate rows of run ``evaluate``: L1 x 100 per column and ratios to validation.

    ``rows`` are rows of the ``metrics`` table, any run (only ``evaluate`` aggregates are used; a row without a
    ``run`` counts as one). The columns are ``validation`` and the four paper conditions, then any other condition
    found, by name. ``presets`` (model -> preset name) and ``augmented`` (model -> trained with audio augmentation)
    order and label the rows: grouped as the paper's tables (features with BLSTM, decoders, baselines, other),
    then by preset, augmentation and name. Missing cells are NaN; ``ratio_<condition>`` is condition / validation.
    """
    presets, augmented = presets or {}, augmented or {}
    cells: dict[str, dict[str, tuple[int, float]]] = {}
    for r in rows:
        if r.get("run", RUN) != RUN or r.get("utterance_id") is not None or r.get("condition") is None:
            continue
        epoch = r.get("epoch")
        rank = -1 if epoch is None else int(epoch)
        model_cells = cells.setdefault(r["model"], {})
        old = model_cells.get(r["condition"])
        if old is None or rank >= old[0]:  # the latest evaluation of a cell wins
            model_cells[r["condition"]] = (rank, float(r["l1_x100"]))
    extra = sorted({c for values in cells.values() for c in values} - set(COLUMNS))
    table = []
    for model, values in cells.items():
        preset = presets.get(model)
        order, group = _group(preset)
        row = {"group": group, "model": model, "preset": preset or "", "train_augment": bool(augmented.get(model)),
               "_order": order}
        for col in (*COLUMNS, *extra):
            row[col] = values[col][1] if col in values else math.nan
        val = row["validation"]
        for cond in (*CONDITIONS, *extra):
            row[f"ratio_{cond}"] = row[cond] / val if val and not math.isnan(val) else math.nan
        table.append(row)
    table.sort(key=lambda r: (r["_order"], r["preset"], r["train_augment"], r["model"]))
    for r in table:
        del r["_order"]
    return table


def table_columns(table: list[dict]) -> list[str]:
    """The condition columns of a table in order: ``validation``, the paper's four, then any other."""
    extra = sorted({k for r in table for k in r if k not in _FIXED_KEYS and not k.startswith("ratio_")} - set(COLUMNS))
    return [*COLUMNS, *extra]


def _num(x: float, digits: int = 2) -> str:
    return "-" if x is None or math.isnan(x) else f"{x:.{digits}f}"


def table_markdown(table: list[dict], title: str = "Validation L1 x 100 (ratio to validation)") -> str:
    """The table as markdown: `value (ratio)` per condition, group headings as in the paper's tables."""
    conditions = table_columns(table)[1:]
    blank = " |" * (3 + len(conditions))
    head = "| model | preset | train aug. | validation | " + " | ".join(conditions) + " |"
    lines = [f"### {title}", "", head, "|---" * (4 + len(conditions)) + "|"]
    group = None
    for r in table:
        if r["group"] != group:
            group = r["group"]
            lines.append(f"| **{group}** |" + blank)
        conds = " | ".join(f"{_num(r[c])} ({_num(r[f'ratio_{c}'])})" for c in conditions)
        lines.append(f"| {r['model']} | {r['preset'] or '-'} | {'yes' if r['train_augment'] else 'no'} | "
                     f"{_num(r['validation'])} | {conds} |")
    if not table:
        lines.append("| (no evaluated model) |" + blank)
    return "\n".join(lines) + "\n"


def table_csv(table: list[dict]) -> str:
    columns = table_columns(table)
    fields = ["group", "model", "preset", "train_augment", *columns, *(f"ratio_{c}" for c in columns[1:])]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    for r in table:
        writer.writerow({k: (f"{r[k]:.4f}" if isinstance(r[k], float) else r[k]) for k in fields})
    return buf.getvalue()
