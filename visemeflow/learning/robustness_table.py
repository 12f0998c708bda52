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

Real-speech metrics (:mod:`visemeflow.learning.realspeech`: they need the phone alignment, not curve truth) are
rows of runs ``evaluate.mbp_closure``, ``evaluate.fff_closure``, ``evaluate.mbp_false_closure``,
``evaluate.fff_false_closure`` and ``evaluate.agreement`` (:data:`REALSPEECH_RUNS`)
in the same schema: ``l1`` holds the share (0..1), ``l1_x100`` the percentage, and, on the aggregate rows of
``evaluate.agreement``, ``l1_<VISEME>`` the share of that viseme's phones (null where it has none). A metric
that is undefined (no b/p/m phone among the validation utterances) has no row. The same latest-wins rule picks
the cell. A table gains the columns ``<metric>_<condition>`` (percent) only for the metrics some row has, so a
store evaluated without phones gives the table it always gave.

Lip metrics (:mod:`visemeflow.learning.lipscore`): what the viewer sees of the same phones, measured in millimetres
on the demo character's mesh by the `evaluate` task (the geometry is computed there: this package imports no rig).
Rows of runs ``evaluate.lip_closed``, ``evaluate.lip_gap_mm``, ``evaluate.fv_contact``, ``evaluate.vowel_opening``,
``evaluate.lip_false_closed`` and ``evaluate.lip_closed_raw`` (:data:`LIP_RUNS`), same schema: shares as above
(``l1`` 0..1, ``l1_x100`` percent), millimetres and the vowel opening (a ratio to the widest single shape) in
``l1`` (with ``l1_x100`` = 100 x ``l1``, as everywhere). A cell holds ``l1_x100`` for a share and ``l1`` for the
others (:data:`LIP_UNITS`). Unlike the top-viseme closure recall, a constant curve cannot win here: it closes no
b/p/m (the mean curve's MBP weight is small) unless it never opens at all (then ``lip_false_closed`` is high).
:func:`lip_headline` gives one line per model.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable

from visemeflow.learning.augment import CONDITIONS
from visemeflow.learning.realspeech import CLOSURE_VISEMES, TOP_K

__all__ = ["CLOSURE_METRICS", "COLUMNS", "FALSE_CLOSURE_METRICS", "LIP_LABELS", "LIP_METRICS", "LIP_RUNS",
           "LIP_SUMMARY_KEYS", "LIP_UNITS", "REALSPEECH_LABELS", "REALSPEECH_METRICS", "REALSPEECH_RUNS", "RUN",
           "TABLE_METRICS", "TABLE_RUNS", "lip_headline", "lip_metrics", "lip_note", "metric_heading",
           "realspeech_metrics", "realspeech_note", "robustness_table", "table_columns", "table_csv",
           "table_markdown", "table_metrics"]

RUN = "evaluate"
COLUMNS = ("validation", *CONDITIONS)
_FIXED_KEYS = {"group", "model", "preset", "train_augment"}
# metric name -> the viseme whose closure it counts: mbp_closure (b/p/m), fff_closure (f/v)
CLOSURE_METRICS = {f"{v.lower()}_closure": v for v in CLOSURE_VISEMES}
# mbp_false_closure, fff_false_closure: the share of the *other* phones whose top viseme is MBP / FFF (recall alone
# rewards a mouth kept shut; read the two together)
FALSE_CLOSURE_METRICS = {f"{v.lower()}_false_closure": v for v in CLOSURE_VISEMES}
REALSPEECH_METRICS = (*CLOSURE_METRICS, *FALSE_CLOSURE_METRICS, "agreement")
REALSPEECH_LABELS = {**{m: f"{v} closure" for m, v in CLOSURE_METRICS.items()},
                     **{m: f"false {v} closure" for m, v in FALSE_CLOSURE_METRICS.items()}, "agreement": "agreement"}
REALSPEECH_RUNS = {f"{RUN}.{m}": m for m in REALSPEECH_METRICS}   # run name in `metrics` -> metric

# lip metrics on the mesh (curves through the closure rule, `visemeflow.articulation.close_lips`, as a character
# shows them; `lip_closed_raw`: the model's own curves without the rule) -> the `LipScores.summary()` key
LIP_SUMMARY_KEYS = {"lip_closed": "closed", "lip_gap_mm": "median_gap_mm", "fv_contact": "fv_contact",
                    "vowel_opening": "vowel_opening", "lip_false_closed": "false_closed", "lip_closed_raw": "closed"}
LIP_METRICS = tuple(LIP_SUMMARY_KEYS)
LIP_UNITS = {"lip_closed": "%", "lip_gap_mm": "mm", "fv_contact": "%", "vowel_opening": "x AHH",
             "lip_false_closed": "%", "lip_closed_raw": "%"}
LIP_LABELS = {"lip_closed": "lips closed at b/p/m", "lip_gap_mm": "b/p/m lip gap",
              "fv_contact": "f/v lip-teeth contact", "vowel_opening": "AA/AH opening",
              "lip_false_closed": "vowels never open", "lip_closed_raw": "lips closed at b/p/m, raw curves"}
LIP_RUNS = {f"{RUN}.{m}": m for m in LIP_METRICS}
TABLE_METRICS = (*REALSPEECH_METRICS, *LIP_METRICS)
TABLE_RUNS = {**REALSPEECH_RUNS, **LIP_RUNS}   # every run besides `evaluate` whose aggregate rows make cells


def metric_heading(metric: str) -> str:
    """A metric column's heading with its unit: `MBP closure %`, `b/p/m lip gap mm`, `AA/AH opening x AHH`."""
    if metric in LIP_LABELS:
        return f"{LIP_LABELS[metric]} {LIP_UNITS[metric]}"
    return f"{REALSPEECH_LABELS[metric]} %"


def _cell(metric: str, row: dict) -> float:
    """The cell of a metric row: percent for shares, the value itself (mm, ratio) for the others."""
    if LIP_UNITS.get(metric, "%") == "%":
        return float(row["l1_x100"])
    return float(row["l1"]) if row.get("l1") is not None else float(row["l1_x100"]) / 100.0


def _is_realspeech_key(key: str) -> bool:
    return any(key.startswith(f"{m}_") for m in TABLE_METRICS)


def _group(preset: str | None) -> tuple[int, str]:
    if not preset:
        return 3, "other"
    if preset == "mean-curve" or preset.startswith(("karras", "faceformer")):
        return 2, "baselines and floors (Table 3)"
    if preset.endswith("-blstm"):   # any feature under the BLSTM decoder (whisper-base-blstm too)
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
    Aggregate rows of the real-speech runs (:data:`REALSPEECH_RUNS`) add ``<metric>_<condition>`` cells (percent,
    NaN where missing) for each metric that has any; a model with only such rows still gets a row. The lip runs
    (:data:`LIP_RUNS`) add cells the same way, in their units (:data:`LIP_UNITS`).
    """
    presets, augmented = presets or {}, augmented or {}
    cells: dict[str, dict[str, tuple[int, float]]] = {}
    extra_cells: dict[str, dict[tuple[str, str], tuple[int, float]]] = {}   # model -> (metric, condition) -> cell
    for r in rows:
        run = r.get("run", RUN)
        if run != RUN and run not in TABLE_RUNS:
            continue
        if r.get("utterance_id") is not None or r.get("condition") is None:
            continue
        epoch = r.get("epoch")
        rank = -1 if epoch is None else int(epoch)
        if run == RUN:
            model_cells, key = cells.setdefault(r["model"], {}), r["condition"]
        else:
            cells.setdefault(r["model"], {})
            model_cells, key = extra_cells.setdefault(r["model"], {}), (TABLE_RUNS[run], r["condition"])
        old = model_cells.get(key)
        if old is None or rank >= old[0]:  # the latest evaluation of a cell wins
            model_cells[key] = (rank, float(r["l1_x100"]) if run == RUN else _cell(TABLE_RUNS[run], r))
    conditions = {c for values in cells.values() for c in values}
    conditions |= {c for values in extra_cells.values() for _, c in values}
    extra = sorted(conditions - set(COLUMNS))
    metrics = [m for m in TABLE_METRICS if any(m == k[0] for values in extra_cells.values() for k in values)]
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
        mine = extra_cells.get(model, {})
        for metric in metrics:
            for col in (*COLUMNS, *extra):
                row[f"{metric}_{col}"] = mine[(metric, col)][1] if (metric, col) in mine else math.nan
        table.append(row)
    table.sort(key=lambda r: (r["_order"], r["preset"], r["train_augment"], r["model"]))
    for r in table:
        del r["_order"]
    return table


def table_columns(table: list[dict]) -> list[str]:
    """The condition columns of a table in order: ``validation``, the paper's four, then any other."""
    extra = sorted({k for r in table for k in r
                    if k not in _FIXED_KEYS and not k.startswith("ratio_") and not _is_realspeech_key(k)} - set(COLUMNS))
    return [*COLUMNS, *extra]


def realspeech_metrics(table: list[dict]) -> list[str]:
    """The real-speech metrics the table has columns for (some model has a row of them), in a fixed order."""
    return [m for m in REALSPEECH_METRICS if any(f"{m}_validation" in r for r in table)]


def lip_metrics(table: list[dict]) -> list[str]:
    """The lip metrics the table has columns for, in a fixed order."""
    return [m for m in LIP_METRICS if any(f"{m}_validation" in r for r in table)]


def table_metrics(table: list[dict]) -> list[str]:
    """Every metric column group of the table: the real-speech metrics, then the lip metrics."""
    return [*realspeech_metrics(table), *lip_metrics(table)]


def lip_note() -> str:
    """What the lip columns of :func:`table_markdown` hold."""
    return ("Lip columns: measured on the demo character's mesh (ICT face, millimetres) for the same phones, the "
            "curves passed through the closure rule (`articulation.close_lips`) as a character shows them: lips "
            "closed = % of b/p/m phones whose smallest inner-lip gap is below 1.5 mm (the median of those gaps "
            "in mm beside it); f/v contact = % of f/v phones whose lower lip comes within 2 mm of the upper teeth; "
            "AA/AH opening = median widest gap of open vowels over the widest single shape's (AHH alone; good "
            "0.6-1.1); vowels never open = % of vowels whose gap stays below 1.5 mm; raw curves = the model's "
            "curves without the closure rule. The mouth at rest (1.1 mm on the demo character) counts as closed: a "
            "curve that never opens closes every b/p/m, and its vowels never open; a constant curve closes b/p/m "
            "only that way.")


def lip_headline(table: list[dict]) -> str:
    """One line per model on clean validation audio: the top-viseme closure recall beside what the mesh shows
    (empty when the table has no lip columns). The top-viseme recall alone is won by a constant curve whose
    largest weight is MBP; the mesh gap is not."""
    if not lip_metrics(table):
        return ""

    def pct(r: dict, m: str) -> str:
        v = r.get(f"{m}_validation", math.nan)
        return "-" if v is None or math.isnan(v) else f"{v:.1f}%"

    def num(r: dict, m: str, unit: str) -> str:
        v = r.get(f"{m}_validation", math.nan)
        return "-" if v is None or math.isnan(v) else f"{v:.2f}{unit}"

    lines = ["On clean validation audio, per model (top-viseme score, then what the demo character's lips do):"]
    for r in table:
        kind = r["preset"] or "-"
        if r["group"].startswith("baselines"):
            kind += ", baseline"
        lines.append(f"- **{r['model']}** ({kind}): MBP top-viseme closure {pct(r, 'mbp_closure')}; on the mesh "
                     f"lips closed at {pct(r, 'lip_closed')} of b/p/m (median gap {num(r, 'lip_gap_mm', ' mm')}; "
                     f"raw curves {pct(r, 'lip_closed_raw')}), f/v contact {pct(r, 'fv_contact')}, AA/AH opening "
                     f"{num(r, 'vowel_opening', ' x AHH')}, vowels never open {pct(r, 'lip_false_closed')}")
    return "\n".join(lines)


def realspeech_note(conditions: list[str]) -> str:
    """What the real-speech columns of :func:`table_markdown` hold."""
    closures = ", ".join(f"{v} closure" for v in CLOSURE_METRICS.values())
    after = f"; in brackets under {' / '.join(conditions)}" if conditions else ""
    return (f"{closures}: % of the phones of that viseme (b/p/m, f/v) whose top predicted viseme within the phone "
            f"(highest peak, strictly) is it; false closure: % of the other non-silent phones whose top is it "
            f"(read with the closure: a mouth kept shut closes every b/p/m); agreement: % of non-silent phones whose viseme is among the top "
            f"{TOP_K} predicted at the phone's middle frame. On clean validation audio{after}; "
            "- where undefined (no such phone).")


def _num(x: float, digits: int = 2) -> str:
    return "-" if x is None or math.isnan(x) else f"{x:.{digits}f}"


def table_markdown(table: list[dict], title: str = "Validation L1 x 100 (ratio to validation)",
                   note: str | None = None) -> str:
    """The table as markdown: `value (ratio)` per condition, group headings as in the paper's tables.

    Real-speech metrics, when the table has them, follow as one column each: `validation (volume / pitch / ...)`
    in percent, and a line under the table says what they are (``note`` is added to it).
    """
    conditions = table_columns(table)[1:]
    metrics = table_metrics(table)
    blank = " |" * (3 + len(conditions) + len(metrics))
    head = "| model | preset | train aug. | validation | " + " | ".join(conditions) + " |"
    head += "".join(f" {metric_heading(m)} |" for m in metrics)
    headline = lip_headline(table)
    lines = [f"### {title}", "", *([headline, ""] if headline else []), head,
             "|---" * (4 + len(conditions) + len(metrics)) + "|"]
    group = None
    for r in table:
        if r["group"] != group:
            group = r["group"]
            lines.append(f"| **{group}** |" + blank)
        conds = " | ".join(f"{_num(r[c])} ({_num(r[f'ratio_{c}'])})" for c in conditions)
        real = "".join(
            f" {_num(r[f'{m}_validation'], _digits(m))}"
            + (f" ({' / '.join(_num(r[f'{m}_{c}'], _digits(m)) for c in conditions)})" if conditions else "") + " |"
            for m in metrics)
        lines.append(f"| {r['model']} | {r['preset'] or '-'} | {'yes' if r['train_augment'] else 'no'} | "
                     f"{_num(r['validation'])} | {conds} |{real}")
    if not table:
        lines.append("| (no evaluated model) |" + blank)
    if metrics:
        notes = [realspeech_note(conditions)] if realspeech_metrics(table) else []
        notes += [lip_note()] if lip_metrics(table) else []
        lines += ["", " ".join(notes) + (f" {note}" if note else "")]
    return "\n".join(lines) + "\n"


def _digits(metric: str) -> int:
    return 2 if LIP_UNITS.get(metric, "%") != "%" else 1


def table_csv(table: list[dict]) -> str:
    columns = table_columns(table)
    fields = ["group", "model", "preset", "train_augment", *columns, *(f"ratio_{c}" for c in columns[1:])]
    fields += [f"{m}_{c}" for m in table_metrics(table) for c in columns]   # percent; lip mm and ratio: LIP_UNITS
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    for r in table:
        writer.writerow({k: (f"{r[k]:.4f}" if isinstance(r[k], float) else r[k]) for k in fields})
    return buf.getvalue()
