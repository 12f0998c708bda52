"""The static HTML report of a store (`visemeflow dashboard`): one self-contained `index.html`, readable offline.

Sections: what the store holds; per-utterance curves of every source with the phones and the waveform; mouth
keypoint error of each tracked variant; training results; dataset-size sweep plots; the robustness table (in a box
that scrolls sideways, so the page keeps its width); the animation packages, the store's and those written with
`--out` (`dashboards.records`); rejects. Curve-only utterances (`predict`, `speak`) are drawn over their audio when
the store knows it (`curve_only_audio`).

The page fetches nothing: every chart is a PNG inside a `data:` URI, styles are inline, there is no script, and a
Content-Security-Policy (`default-src 'none'`) makes the browser refuse any other load. Every value from the store
(utterance ids, phone labels, reject messages, condition names) is HTML-escaped. Only a bounded number of
utterances is drawn (`max_utterances`, or the ids asked for), so a store of 10,000 utterances stays quick to report,
and of each only a bounded window from its start (`MAX_DRAWN_PHONES`, `MAX_DRAWN_FRAMES`), with a note saying what
was left out, so an utterance of 100k phones does too.
"""

import base64
import contextlib
import csv
import html
import io
import math
import os
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from urllib.parse import quote

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.dataset as ds

from visemeflow.atomic import atomic_write_bytes, atomic_write_text
from visemeflow.hashing import file_hash
from visemeflow.location import local_input
from visemeflow.dashboards import plots
from visemeflow.dashboards.records import recorded_packages, recorded_predicted_audio
# The robustness table is built by the same function as the `evaluate` report, so both show the same cells in the
# same order (DESIGN lets dashboards import schemas and storage; this module is the exception, pure and torch-free).
from visemeflow.learning.robustness_table import (
    COLUMNS,
    LIP_METRICS,
    RUN,
    TABLE_RUNS,
    lip_headline,
    metric_heading,
    table_columns,
    table_metrics,
)
from visemeflow.learning.robustness_table import robustness_table as shared_robustness_table
from visemeflow.schemas import C, TRACKING_FRAMES, CurveSource, curves_array
from visemeflow.schemas.ids import utterance_id_from_path_parts
from visemeflow.schemas.tables import CURVE_SOURCES
from visemeflow.storage import Store
from visemeflow.visemes import VISEMES

DEFAULT_MAX_UTTERANCES = 12
MAX_DRAWN_PHONES = 500
"""Phones one utterance chart draws at most (the first ones; ~40 s of speech, already more labels than its width
shows). Each phone is three matplotlib artists per panel: 100k phones took 201 s and 4.2 GB."""
MAX_DRAWN_FRAMES = 3000
"""Curve frames one panel draws at most (100 s at 30 fps): curves without phones (`predict` on an hour of audio)."""
MAX_REJECT_ROWS = 500
MAX_ANIMATIONS = 50
# Tracking diagnostics read per variant (a fixed sample beyond that): keeps a 10k-utterance store at ~1 s.
MAX_TRACKING_UTTERANCES = 2000
# Robustness conditions in the paper's order (Tables 1-3), as the evaluate report has them; any other follows.
CONDITION_ORDER = COLUMNS
BASELINE_CONDITION = "validation"
# media-src: the preview videos of the animations section, files of the store next to the page (loaded on play)
CSP = "default-src 'none'; img-src data:; style-src 'unsafe-inline'; media-src file: 'self'"

_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 0 auto; max-width: 1300px;
       padding: 0 20px 40px; color: #222; }
h1 { margin-bottom: 4px; } h2 { border-bottom: 1px solid #ccc; padding-bottom: 4px; margin-top: 36px; }
nav a { margin-right: 14px; } .meta, .note { color: #666; } .empty { color: #a33; font-style: italic; }
table { border-collapse: collapse; margin: 8px 0 16px; font-size: 14px; }
th, td { border: 1px solid #ddd; padding: 4px 8px; text-align: left; vertical-align: top; }
th { background: #f4f6f8; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
td.msg { max-width: 640px; white-space: pre-wrap; word-break: break-word; }
figure { margin: 12px 0 28px; } figcaption { color: #444; font-size: 14px; margin-bottom: 6px; }
img { max-width: 100%; height: auto; border: 1px solid #eee; }
code { background: #f4f6f8; padding: 0 3px; }
.wide { overflow-x: auto; max-width: 100%; }
.wide table { margin-bottom: 4px; }
.wide td:first-child, .wide th:first-child { position: sticky; left: 0; background: #f4f6f8; white-space: nowrap; }
"""


def esc(value: object) -> str:
    """`value` as HTML text or attribute value: `& < > " '` escaped; None as an empty string."""
    return "" if value is None else html.escape(str(value), quote=True)


@dataclass
class DashboardResult:
    path: Path                                   # the index.html written
    utterances: list[str] = field(default_factory=list)   # utterances drawn, in page order
    charts: list[str] = field(default_factory=list)       # ids of the <img> charts on the page
    missing: list[str] = field(default_factory=list)      # requested utterance ids with nothing stored
    empty: bool = False                          # the store holds nothing to report


class _Page:
    """Accumulates HTML and the ids of the charts it holds."""

    def __init__(self) -> None:
        self.parts: list[str] = []
        self.charts: list[str] = []

    def add(self, *parts: str) -> None:
        self.parts.extend(parts)

    def image(self, chart_id: str, png: bytes, alt: str, caption: str = "", mime: str = "image/png") -> None:
        data = base64.b64encode(png).decode("ascii")
        self.charts.append(chart_id)
        self.add(
            "<figure>", f"<figcaption>{caption}</figcaption>" if caption else "",
            f'<img id="{esc(chart_id)}" alt="{esc(alt)}" src="data:{mime};base64,{data}">', "</figure>",
        )


def html_table(headers: Sequence[str], rows: Iterable[Sequence[object]], numeric: Sequence[bool] | None = None,
               table_id: str | None = None, cell_class: Sequence[str] | None = None,
               groups: Sequence[tuple[str, int]] | None = None) -> str:
    """An HTML table; every header and cell escaped; floats with 3 decimals, None as a dash.

    `groups`, (title, columns spanned) pairs, add a header row above `headers`.
    """
    out = [f'<table id="{esc(table_id)}">' if table_id else "<table>", "<thead>"]
    if groups:
        out.append("<tr>" + "".join(f'<th colspan="{int(n)}">{esc(t)}</th>' for t, n in groups if n > 0) + "</tr>")
    out.append("<tr>")
    out += [f"<th>{esc(h)}</th>" for h in headers]
    out.append("</tr></thead><tbody>")
    for row in rows:
        out.append("<tr>")
        for k, cell in enumerate(row):
            classes = []
            if numeric and numeric[k]:
                classes.append("num")
            if cell_class and cell_class[k]:
                classes.append(cell_class[k])
            attr = f' class="{" ".join(classes)}"' if classes else ""
            out.append(f"<td{attr}>{esc(_fmt(cell))}</td>")
        out.append("</tr>")
    out.append("</tbody></table>")
    return "".join(out)


def _fmt(value: object) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return "–" if math.isnan(value) else f"{value:.3f}"
    return str(value)


# ---- utterance selection ---------------------------------------------------------------------------
def curve_index(store: Store) -> dict[str, dict[str, list[str]]]:
    """utterance id -> {source: [variants]} of every stored curve file (a listing, no file is opened)."""
    index: dict[str, dict[str, list[str]]] = {}
    for source in CURVE_SOURCES:
        for variant in store.curve_variants(source):
            for uid in store.curve_ids(source, variant):
                index.setdefault(uid, {}).setdefault(source, []).append(variant)
    return index


def select_utterances(
    known: Sequence[str], index: dict[str, dict[str, list[str]]], requested: Sequence[str] | None, limit: int,
    languages: dict[str, str | None] | None = None, featured: Iterable[str] = (),
) -> tuple[list[str], list[str]]:
    """(utterances to draw, requested ids that are stored nowhere).

    Requested ids are drawn in the order given. Otherwise up to `limit` utterances: first, for each curve source
    in turn, the richest utterance holding it (so every source appears at least once), then the richest of each
    language of `languages` (id -> language: a corpus's one Mandarin utterance among 24 English ones is shown), then
    the rest: `featured` ones first (those with an animation package or a preview: what the user made something
    of), then the richest. Richest: utterances of the `utterances` table before curve-only ones (`predict/...`),
    then the most sources, ties by id. The page shows them in the order of the rest.
    """
    if requested:
        stored = set(known) | set(index)
        chosen = list(dict.fromkeys(requested))
        return [u for u in chosen if u in stored], [u for u in chosen if u not in stored]
    in_table, starred = set(known), set(featured)
    richest = sorted(set(known) | set(index), key=lambda u: (u not in in_table, -len(index.get(u, {})), u))
    candidates = sorted(richest, key=lambda u: u not in starred)    # stable: featured first, then as `richest`
    selected: list[str] = []
    for source in CURVE_SOURCES:
        if len(selected) >= limit:
            break
        if any(source in index.get(u, {}) for u in selected):
            continue
        pick = next((u for u in richest if source in index.get(u, {}) and u not in selected), None)
        if pick is not None:
            selected.append(pick)
    for language in sorted({v for v in (languages or {}).values() if v}):
        if len(selected) >= limit:
            break
        if any((languages or {}).get(u) == language for u in selected):
            continue
        pick = next((u for u in richest if (languages or {}).get(u) == language and u not in selected), None)
        if pick is not None:
            selected.append(pick)
    for u in candidates:
        if len(selected) >= limit:
            break
        if u not in selected:
            selected.append(u)
    order = {u: k for k, u in enumerate(candidates)}
    return sorted(selected, key=order.__getitem__), []


# ---- data of one utterance -------------------------------------------------------------------------
def _read_audio_head(path: str, seconds: float) -> tuple[np.ndarray, int] | None:
    """(mono float32 samples, rate) of the first `seconds` of an audio file, read no further, and checked as
    `read_audio` checks them; None when soundfile cannot read the file (`read_audio` then tries PyAV)."""
    import soundfile as sf

    from visemeflow.ingest.audio import check_finite

    try:
        with sf.SoundFile(path) as fh:
            rate = fh.samplerate
            samples = fh.read(frames=min(fh.frames, math.ceil(seconds * rate)), dtype="float32", always_2d=True)
    except (RuntimeError, OSError):  # soundfile's LibsndfileError is a RuntimeError
        return None
    check_finite(samples, rate, path)
    return samples.mean(axis=1, dtype=np.float32), int(rate)


@dataclass
class CurveOnlyAudio:
    """The audio of an utterance that has curves but no row (`predict/<stem>`, `speak`), as found in the store."""

    path: str | None = None     # the audio file the curves were predicted from (or a package's copy of it)
    same_as: str | None = None  # the utterance of the table whose audio file has the same bytes
    how: str = ""               # where it was found, for the caption


def curve_only_audio(store: Store, uid: str, sources: dict[str, list[str]], rows_by_name: dict[str, list[dict]],
                     packages: dict[str, list[Path]], recorded: dict[str, str],
                     predicted: dict[str, str] | None = None) -> CurveOnlyAudio:
    """Where the audio of a curve-only utterance is: predicted curves record only the audio's content hash, not its
    path, so look in order at (1) the table's utterances of the same name (`predict/LJ001-0002` from
    `LJ001-0002.wav`; a `-<hash>` suffix dropped) whose audio file has that hash: then its phones apply too;
    (2) the audio recorded with a package written outside the store (`speak --out`, `records`); (3) the `.wav`
    the store's animation package of the utterance holds. Hashes at most the few same-named files."""
    hashes: set[str] = set()
    for variant in sources.get(CurveSource.PREDICTED, []):
        hashes.update((store.curves_provenance(CurveSource.PREDICTED, variant, uid) or "").split(":"))
    name = uid.split("/", 1)[-1]
    same_named = rows_by_name.get(name, []) + (rows_by_name.get(name.rsplit("-", 1)[0], []) if "-" in name else [])
    for row in same_named:
        path = row.get(C.AUDIO_PATH)
        try:
            if path and hashes and file_hash(local_input(path)) in hashes:
                return CurveOnlyAudio(path, row[C.UTTERANCE_ID], "the same audio file as")
        except OSError:
            continue
    if recorded.get(uid) and Path(recorded[uid]).is_file():
        return CurveOnlyAudio(recorded[uid], None, "audio recorded by speak/animate")
    path = (predicted or {}).get(uid)
    try:
        if path and hashes and file_hash(path) in hashes:   # the file predict read, unchanged since
            return CurveOnlyAudio(path, None, "audio recorded by predict")
    except OSError:
        pass
    for folder in packages.get(uid, []):
        wav = folder / f"{folder.name}.wav"
        if wav.is_file():
            return CurveOnlyAudio(str(wav), None, "audio of its animation package")
    return CurveOnlyAudio()


def load_waveform(row: dict | None, until_s: float | None = None) -> tuple[tuple[np.ndarray, int] | None, str]:
    """((mono samples, rate), "") of an utterance's audio, up to `until_s` when given, or (None, why not). Videos
    (and what soundfile cannot read) are read whole through `read_audio`, then cut."""
    if row is None:
        return None, "audio unknown: curves only, from a file the store does not record"
    from visemeflow.ingest.audio import is_video_file, read_audio  # the one reader of audio files and videos' tracks

    errors = []
    for path in dict.fromkeys(p for p in (row.get(C.AUDIO_PATH), row.get(C.VIDEO_PATH)) if p):
        try:
            path = local_input(path)   # a corpus on object storage: its local copy
            head = _read_audio_head(path, until_s) if until_s is not None and not is_video_file(path) else None
            if head is not None:
                return head, ""
            samples, rate = read_audio(path)
            return (samples if until_s is None else samples[:math.ceil(until_s * rate)], rate), ""
        except (OSError, ValueError) as exc:  # AudioError is a ValueError
            errors.append(str(exc))
    return None, "audio unreadable: " + ("; ".join(errors) if errors else "no audio path")


def _phones_of(phones: pa.Table, uid: str, limit: int = MAX_DRAWN_PHONES) -> tuple[list[plots.Phone], int]:
    """(the first `limit` phones of `uid` by time, how many it has)."""
    table = phones.filter(pc.equal(phones.column(C.UTTERANCE_ID), uid))
    rows = table.sort_by([(C.START_S, "ascending"), (C.INDEX, "ascending"), (C.PART, "ascending")]).slice(0, limit)
    return [plots.Phone(r[C.START_S], r[C.END_S], r[C.LABEL], r[C.VISEME] is None)
            for r in rows.to_pylist()], table.num_rows


def drawn_until(phones: list[plots.Phone], total_phones: int, panels: Sequence[plots.CurvePanel]) -> float | None:
    """Where one utterance chart stops (seconds): the end of its MAX_DRAWN_PHONES-th phone or the time of a panel's
    MAX_DRAWN_FRAMES-th frame, whichever comes first; None when everything fits."""
    ends = [phones[-1].end_s] if phones and total_phones > len(phones) else []
    ends += [float(p.time_s[MAX_DRAWN_FRAMES - 1]) for p in panels if len(p.time_s) > MAX_DRAWN_FRAMES]
    return min(ends) if ends else None


def _l1_x100(reference: pa.Table, other: pa.Table) -> float:
    """Mean absolute difference x 100 of `other` against `reference`, `other` interpolated at the reference frames."""
    t_ref = reference.column(C.TIME_S).to_numpy()
    t_other = other.column(C.TIME_S).to_numpy()
    if not len(t_ref) or not len(t_other):
        return float("nan")
    a, b = curves_array(reference), curves_array(other)
    resampled = np.stack([np.interp(t_ref, t_other, b[:, i]) for i in range(b.shape[1])], axis=1)
    return float(np.abs(resampled - a).mean() * 100.0)


def _utterance_section(page: _Page, store: Store, n: int, uid: str, row: dict | None,
                       sources: dict[str, list[str]], phones: pa.Table, audio: CurveOnlyAudio | None = None,
                       truth_of: pa.Table | None = None, rejected: bool = False) -> None:
    """One utterance's chart and caption. A curve-only utterance is drawn over `audio` when found (and with the
    phones of the utterance of the same audio file, and its error against that one's ground truth `truth_of`);
    `rejected`: one its last ingest rejected, whose curves of an earlier run the store keeps."""
    panels, tables = [], []
    for source in CURVE_SOURCES:
        for variant in sources.get(source, []):
            try:
                table = store.read_curves(uid, source, variant)
            except (LookupError, OSError, pa.ArrowException):
                continue
            tables.append((source, variant, table))
            panels.append(plots.CurvePanel(f"{source}\n{variant}", table.column(C.TIME_S).to_numpy(),
                                           curves_array(table)))
    duration = float(row[C.DURATION_S]) if row else 0.0
    audio = audio or CurveOnlyAudio()
    phone_list, n_phones = _phones_of(phones, uid if row or not audio.same_as else audio.same_as)
    until = drawn_until(phone_list, n_phones, panels)
    window = ""
    if until is not None:
        total_s = max([duration] + [float(p.time_s[-1]) for p in panels if len(p.time_s)])
        frames = max((len(p.time_s) for p in panels), default=0)
        phone_list = [replace(p, end_s=min(p.end_s, until)) for p in phone_list if p.start_s < until]
        panels = [replace(p, time_s=p.time_s[p.time_s <= until], curves=p.curves[p.time_s <= until]) for p in panels]
        window = (f"drawn: the first {until:.1f} s of {total_s:.1f} s ({len(phone_list)} of {n_phones} phones, "
                  f"{max((len(p.time_s) for p in panels), default=0)} of {frames} curve frames); a chart draws at "
                  f"most {MAX_DRAWN_PHONES} phones and {MAX_DRAWN_FRAMES} frames per panel")
    audio_row = row if row is not None or audio.path is None else {C.AUDIO_PATH: audio.path}
    waveform, note = load_waveform(audio_row, until)
    png = plots.utterance_figure(uid, duration if until is None else until, waveform, note, phone_list, panels)

    facts = []
    if row:
        facts += [f"speaker {esc(row[C.SPEAKER])}", f"language {esc(row[C.LANGUAGE] or '?')}",
                  f"split {esc(row[C.SPLIT])}", f"{row[C.DURATION_S]:.2f} s", f"{row[C.FPS]:g} fps",
                  f"{n_phones} phones"]
    elif audio.same_as:
        facts += [f"curves only (not in the utterances table), from {esc(audio.how)} <code>{esc(audio.same_as)}"
                  f"</code>: its audio and its {n_phones} phones"]
    elif rejected:
        facts.append('rejected at its last run (see <a href="#rejects">Rejects</a>): these curves are of an earlier '
                     "run, kept until it is ingested again")
    elif audio.path:
        facts += [f"curves only (not in the utterances table); {esc(audio.how)}: <code>{esc(audio.path)}</code>"]
    else:
        facts.append("curves only (not in the utterances table)")
    truth = next((t for s, _, t in tables if s == CurveSource.GROUND_TRUTH), None)
    if truth is not None:
        errors = [f"{esc(s)}/{esc(v)} {_l1_x100(truth, t):.2f}" for s, v, t in tables if s != CurveSource.GROUND_TRUTH]
        if errors:
            facts.append("L1 x 100 vs ground truth: " + ", ".join(errors))
    elif truth_of is not None and audio.same_as:
        errors = [f"{esc(s)}/{esc(v)} {_l1_x100(truth_of, t):.2f}" for s, v, t in tables]
        if errors:
            facts.append(f"L1 x 100 vs the ground truth of <code>{esc(audio.same_as)}</code>: " + ", ".join(errors))
    shown = ", ".join(f"{esc(s)}/{esc(v)}" for s, v, _ in tables) or "none"
    caption = (f'<strong class="utterance-id">{esc(uid)}</strong> · ' + " · ".join(facts)
               + f"<br><span class=\"note\">curves: {shown}</span>")
    if window:
        caption += f'<br><span class="note" id="drawn-window-{n}">{esc(window)}</span>'
    if waveform is None:
        caption += f'<br><span class="empty">{esc(note)}</span>'
    page.image(f"chart-curves-{n}", png, f"viseme curves, phones and waveform of {uid}", caption)


# ---- tables from the metrics ------------------------------------------------------------------------
@dataclass
class RobustnessTable:
    """The robustness table of `visemeflow.learning.robustness_table` (the one the `evaluate` report shows), as
    models in the report's order, the conditions present and the non-missing cells."""

    models: list[str]
    conditions: list[str]
    values: dict[tuple[str, str], float]    # (model, condition) -> L1 x 100
    # real-speech metrics (closure recall, activation agreement) and lip metrics on the mesh with any cell, and
    # (model, metric, condition) -> % (lip millimetres and opening ratios in their own units: LIP_UNITS)
    realspeech_metrics: list[str] = field(default_factory=list)
    realspeech: dict[tuple[str, str, str], float] = field(default_factory=dict)
    headline: str = ""          # one line per model: top-viseme closure beside the lips on the mesh (markdown)

    def realspeech_conditions(self, metric: str) -> list[str]:
        """The conditions, in the table's order, where some model has a value of `metric`."""
        return [c for c in self.conditions if any((m, metric, c) in self.realspeech for m in self.models)]

    def ratio(self, model: str, condition: str) -> float | None:
        """L1 under `condition` over L1 on clean validation audio (1.0 = no degradation), None when unknown."""
        base = self.values.get((model, BASELINE_CONDITION))
        value = self.values.get((model, condition))
        if base is None or value is None or base == 0:
            return None
        return value / base


def _condition_key(condition: str) -> tuple[int, str]:
    for k, name in enumerate(CONDITION_ORDER):
        if condition == name or condition.startswith(name):
            return k, condition
    return len(CONDITION_ORDER), condition


def _aggregate_rows(metrics: pa.Table, run: str | Sequence[str]) -> pa.Table:
    runs = pa.array([run] if isinstance(run, str) else list(run), pa.string())
    mask = pc.and_(pc.is_in(metrics.column(C.RUN), value_set=runs), pc.is_null(metrics.column(C.UTTERANCE_ID)))
    return metrics.filter(mask)


def evaluated_labels(store: Store) -> tuple[dict[str, str], dict[str, bool]]:
    """(model -> preset, model -> trained with augmentation) from the last `evaluate` report (`robustness.csv`).

    The metrics table carries no preset, and reading it from the model files would load torch; the report the
    `evaluate` flow wrote from the same table function has it. Models it does not list are grouped as "other".
    """
    presets: dict[str, str] = {}
    augmented: dict[str, bool] = {}
    try:
        text = store.report_path("robustness.csv").read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return presets, augmented
    for row in csv.DictReader(io.StringIO(text)):
        model = row.get("model")
        if model:
            if row.get("preset"):
                presets[model] = row["preset"]
            augmented[model] = row.get("train_augment") == "True"
    return presets, augmented


def robustness_table(metrics: pa.Table, presets: dict[str, str] | None = None,
                     augmented: dict[str, bool] | None = None) -> RobustnessTable:
    """The `evaluate` report's table (`visemeflow.learning.robustness_table.robustness_table`) of these metrics:
    aggregate rows of run `evaluate` and of its real-speech runs, the latest per (model, condition), models in
    the report's order."""
    rows = _aggregate_rows(metrics, [RUN, *TABLE_RUNS])
    rows = rows.select([C.RUN, C.MODEL, C.CONDITION, C.UTTERANCE_ID, C.EPOCH, C.L1, C.L1_X100])
    table = shared_robustness_table(rows.to_pylist(), presets, augmented)
    columns = table_columns(table)
    values = {(r["model"], c): r[c] for r in table for c in columns if not math.isnan(r[c])}
    models = [r["model"] for r in table]
    real = {(r["model"], m, c): r[f"{m}_{c}"] for r in table for m in table_metrics(table) for c in columns
            if not math.isnan(r[f"{m}_{c}"])}
    conditions = [c for c in columns if any((m, c) in values for m in models) or any(k[2] == c for k in real)]
    metrics_shown = [m for m in table_metrics(table) if any(k[1] == m for k in real)]
    return RobustnessTable(models, conditions, values, metrics_shown, real, lip_headline(table))


def robustness_html(table: RobustnessTable) -> str:
    ratios = [c for c in table.conditions if c != BASELINE_CONDITION]
    has_base = BASELINE_CONDITION in table.conditions
    headers = ["model", *table.conditions]
    groups = [("", 1), ("L1 x 100", len(table.conditions))]
    if has_base:
        headers += ratios
        groups.append((f"ratio to {BASELINE_CONDITION} (1.0 = unchanged)", len(ratios)))
    real = {metric: table.realspeech_conditions(metric) for metric in table.realspeech_metrics}
    for metric, conditions in real.items():
        headers += conditions
        kind = "on the mesh" if metric in LIP_METRICS else "real-speech metric"
        groups.append((f"{metric_heading(metric)} ({kind})", len(conditions)))
    rows = []
    for m in table.models:
        row: list[object] = [m] + [table.values.get((m, c)) for c in table.conditions]
        if has_base:
            row += [table.ratio(m, c) for c in ratios]
        for metric, conditions in real.items():
            row += [table.realspeech.get((m, metric, c)) for c in conditions]
        rows.append(row)
    numeric = [False] + [True] * (len(headers) - 1)
    note = "" if has_base else (f'<p class="note">no <code>{BASELINE_CONDITION}</code> condition: '
                                "ratios cannot be computed.</p>")
    return html_table(headers, rows, numeric, table_id="robustness-table", groups=groups) + note


def _headline_html(headline: str) -> str:
    """The report's per-model headline (markdown: a lead line, then `- **model** (preset): ...` items) as HTML."""
    lines = [line for line in headline.splitlines() if line.strip()]
    if not lines:
        return ""
    items = "".join(f"<li>{esc(line.removeprefix('- ').replace('**', ''))}</li>" for line in lines[1:])
    return f'<p class="note">{esc(lines[0])}</p><ul id="lip-headline">{items}</ul>'


def training_html(metrics: pa.Table) -> tuple[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """The table of `final` aggregate rows and the per-epoch validation series of `train` rows, per model."""
    final = _aggregate_rows(metrics, "final").to_pylist()
    train = _aggregate_rows(metrics, "train")
    train = train.filter(pc.equal(train.column(C.CONDITION), BASELINE_CONDITION))
    series: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    epochs: dict[str, int] = {}
    for model in sorted(set(train.column(C.MODEL).to_pylist())):
        rows = train.filter(pc.equal(train.column(C.MODEL), model)).to_pylist()
        pts = sorted((r[C.EPOCH], r[C.L1_X100]) for r in rows if r[C.EPOCH] is not None)
        if pts:
            series[model] = (np.array([p[0] for p in pts]), np.array([p[1] for p in pts]))
            epochs[model] = int(pts[-1][0])
    per_utt = metrics.filter(pc.and_(pc.equal(metrics.column(C.RUN), "final"),
                                     pc.invert(pc.is_null(metrics.column(C.UTTERANCE_ID)))))
    utt_counts: dict[tuple[str, str], int] = {}
    for r in per_utt.select([C.MODEL, C.CONDITION]).to_pylist():
        key = (r[C.MODEL], r[C.CONDITION])
        utt_counts[key] = utt_counts.get(key, 0) + 1
    rows = []
    for r in sorted(final, key=lambda r: (r[C.MODEL], _condition_key(r[C.CONDITION]))):
        # per-viseme columns hold plain L1 (like `l1`); shown x 100
        per_viseme = [(100.0 * r[C.L1_PREFIX + v], v) for v in VISEMES if r.get(C.L1_PREFIX + v) is not None]
        worst = ", ".join(f"{v} {x:.1f}" for x, v in sorted(per_viseme, reverse=True)[:3]) or None
        rows.append([r[C.MODEL], r[C.CONDITION], float(r[C.L1_X100]), epochs.get(r[C.MODEL]),
                     utt_counts.get((r[C.MODEL], r[C.CONDITION])), worst])
    headers = ["model", "condition", "L1 x 100", "epochs", "utterances", "worst visemes (L1 x 100)"]
    return html_table(headers, rows, [False, False, True, True, True, False], table_id="training-table"), series


# ---- the page ---------------------------------------------------------------------------------------
def _count_by(table: pa.Table, column: str) -> list[tuple[str, int]]:
    if table.num_rows == 0:
        return []
    counts = pc.value_counts(table.column(column)).to_pylist()
    return sorted(((str(c["values"]), int(c["counts"])) for c in counts), key=lambda x: x[0])


def tracking_sample(store: Store, limit: int = MAX_TRACKING_UTTERANCES) -> tuple[pa.Table, dict[str, tuple[int, int]]]:
    """Diagnostics of up to `limit` utterances per tracked variant, and per variant (utterances read, stored).

    `Store.read_tracking_frames` opens every file (half a millisecond each: 10 s for a 10k-utterance store); the
    report reads a fixed pseudo-random sample of the files instead (the same in every run), and only the columns
    it shows, listed by the store (`Store.tracking_frame_files`).
    """
    files, counts = [], {}
    for variant in store.tracking_variants():
        found = store.tracking_frame_files(variant)
        found.sort(key=lambda p: (zlib.crc32(store.utterance_id_of(p).encode()), p))
        files += found[:limit]
        counts[variant] = (min(len(found), limit), len(found))
    columns = [C.UTTERANCE_ID, C.VARIANT, C.MOUTH_ERROR_PX, C.LANDMARKS_VALID, C.FLOW_VALID_FRACTION]
    if not files:
        return TRACKING_FRAMES.empty_table().select(columns), counts
    return ds.dataset(files, schema=TRACKING_FRAMES, format="parquet").to_table(columns=columns), counts


def _tracking_section(page: _Page, store: Store) -> bool:
    frames, counts = tracking_sample(store)
    if frames.num_rows == 0:
        return False
    errors: dict[str, np.ndarray] = {}
    rows = []
    for variant in sorted(set(frames.column(C.VARIANT).to_pylist())):
        sub = frames.filter(pc.equal(frames.column(C.VARIANT), variant))
        err = sub.column(C.MOUTH_ERROR_PX).drop_null().to_numpy().astype(np.float64)
        err = err[np.isfinite(err)]
        flow = sub.column(C.FLOW_VALID_FRACTION).drop_null().to_numpy()
        valid = sub.column(C.LANDMARKS_VALID).to_numpy(zero_copy_only=False)
        errors[variant] = err
        q = np.percentile(err, [50, 90]) if err.size else [None, None]
        read, stored = counts.get(variant, (0, 0))
        rows.append([variant, stored if read == stored else f"{read} of {stored} (sample)", sub.num_rows,
                     float(valid.mean() * 100) if valid.size else None,
                     None if q[0] is None else float(q[0]), None if q[1] is None else float(q[1]),
                     float(err.max()) if err.size else None, float(flow.mean()) if flow.size else None])
    page.add(html_table(
        ["variant", "utterances", "frames", "landmarks found %", "mouth error median px", "p90 px", "max px",
         "valid flow fraction"], rows, [False] + [True] * 7, table_id="tracking-table"))
    png = plots.histogram_figure(errors, "mouth keypoint error (px in the video frame, mean over the 20 mouth landmarks)")
    page.image("chart-mouth-error", png, "histogram of mouth keypoint error per tracked variant",
               "Mouth keypoint error per frame, one histogram per tracked variant (dashed: median).")
    return True


def _file_url(path: Path, page_dir: Path) -> str:
    """A link from the page's folder to a store file: relative when it can be, percent-encoded; a file on object
    storage by its URL (what `aws s3 cp` and the bucket's console take; a browser does not open it)."""
    if not isinstance(path, Path):   # a UPath of a store on object storage
        return str(path)
    try:
        target = os.path.relpath(path.resolve(), page_dir.resolve())
    except ValueError:  # another drive (Windows)
        return path.resolve().as_uri()
    return quote(Path(target).as_posix())


def _playable(video, out: Path) -> Path:
    """A preview MP4 the page can play: the file itself in a folder; one on object storage copied next to the page
    (`media/<character>/<speaker>/<name>/`), since a browser does not open s3:// URLs."""
    if isinstance(video, Path):
        return video
    local = out / "media" / Path(*video.parts[-4:])
    if not local.is_file() or local.stat().st_size != video.stat().st_size:
        data = video.read_bytes()
        atomic_write_bytes(local, data)
    return local


@dataclass
class Package:
    """One animation package folder: in the store's `animations/`, or written elsewhere (`--out`) and recorded."""

    folder: Path
    utterance_id: str
    character: str
    outside: bool = False       # written with --out: the folder is named on the page


def animation_packages(store: Store) -> list[Package]:
    """The store's packages (sorted), then the recorded ones written outside it (newest first); a recorded folder
    that is also one of the store's is listed once."""
    found = []
    for folder in store.animation_dirs():
        character, speaker, name = folder.parts[-3:]
        try:
            uid = utterance_id_from_path_parts(speaker, name)
        except ValueError:
            uid = f"{speaker}/{name}"
        found.append(Package(folder, uid, character))
    seen = {p.folder.resolve() for p in found if isinstance(p.folder, Path)}
    for entry in recorded_packages(store):
        folder = entry["folder"].resolve()
        if folder not in seen:
            seen.add(folder)
            found.append(Package(folder, entry["utterance_id"], entry["character"] or "?", outside=True))
    return found


def _animations_section(page: "_Page", packages: Sequence[Package], out: Path, limit: int = MAX_ANIMATIONS) -> None:
    """Each animation package: its files as links, its preview MP4s as <video> elements (no script)."""
    if not packages:
        page.add('<p class="empty" id="no-animations">No animations yet (<code>visemeflow animate</code>, '
                 "<code>visemeflow speak</code>, <code>visemeflow preview</code>).</p>")
        return
    outside = sum(p.outside for p in packages)
    elsewhere = f", {outside} of them written outside the store (<code>--out</code>)" if outside else ""
    page.add(f'<p class="note">{min(len(packages), limit)} of {len(packages)} packages (character, utterance)'
             f"{elsewhere}: the files open in Blender / three.js (GLB), Omniverse / Maya (USD), Unreal (Live Link "
             "CSV); previews play here.</p>")
    for n, package in enumerate(packages[:limit]):
        try:
            files = sorted(p for p in package.folder.iterdir() if p.is_file() and not p.name.startswith("."))
        except OSError as exc:
            page.add(f'<p class="empty">{esc(package.folder)}: {esc(exc.strerror or exc)}</p>')
            continue
        links = " · ".join(f'<a href="{esc(_file_url(p, out))}">{esc(p.name)}</a>' for p in files)
        where = f'<p class="note">in <code>{esc(package.folder)}</code></p>' if package.outside else ""
        page.add(f'<div class="animation" id="animation-{n}"><h3><code>{esc(package.utterance_id)}</code> on '
                 f"{esc(package.character)}</h3>{where}<p>{links}</p>")
        for video in (p for p in files if p.suffix == ".mp4"):
            page.add(f'<video controls preload="none" width="640" src="{esc(_file_url(_playable(video, out), out))}" '
                     f'title="{esc(video.name)}"></video>')
        page.add("</div>")


def build_dashboard(
    store: Store | Path | str, out: Path | str, utterance_ids: Sequence[str] | None = None,
    max_utterances: int = DEFAULT_MAX_UTTERANCES,
) -> DashboardResult:
    """Write `out/index.html`, the report of `store`; returns what it holds."""
    store = store if isinstance(store, Store) else Store(store)
    out = Path(out)
    page = _Page()

    utterances = store.read_table("utterances")
    rows_by_id = {r[C.UTTERANCE_ID]: r for r in utterances.to_pylist()}
    index = curve_index(store)
    metrics = store.read_metrics()
    rejects = store.read_table("rejects")
    sweeps = store.report_files(prefix="sweep-", suffix=".png")
    has_tracking = bool(store.tracking_frame_files())
    empty = not (rows_by_id or index or metrics.num_rows or rejects.num_rows or sweeps or has_tracking)

    packages = animation_packages(store)
    selected, missing = select_utterances(
        list(rows_by_id), index, utterance_ids, max(0, max_utterances),
        languages={u: r[C.LANGUAGE] for u, r in rows_by_id.items()}, featured={p.utterance_id for p in packages})
    # curve-only utterances (predict, speak): their audio, and the utterance of the same audio file when stored
    rows_by_name: dict[str, list[dict]] = {}
    for u, r in rows_by_id.items():
        rows_by_name.setdefault(u.split("/", 1)[-1], []).append(r)
    package_dirs: dict[str, list[Path]] = {}
    for p in packages:
        package_dirs.setdefault(p.utterance_id, []).append(p.folder)
    recorded = {e["utterance_id"]: e["audio"] for e in reversed(recorded_packages(store)) if e.get("audio")}
    predicted = recorded_predicted_audio(store)
    audio = {u: curve_only_audio(store, u, index.get(u, {}), rows_by_name, package_dirs, recorded, predicted)
             for u in selected if u not in rows_by_id}
    # Phones of the drawn utterances only: a filtered dataset scan, not the whole table.
    phone_ids = {u for u in selected if u in rows_by_id} | {a.same_as for a in audio.values() if a.same_as}
    phones = store.read_table("phones", utterance_ids=sorted(phone_ids))

    generated = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    page.add(
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
        f'<meta http-equiv="Content-Security-Policy" content="{esc(CSP)}">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>visemeflow: {esc(store.root.name)}</title><style>{_CSS}</style></head><body>",
        "<h1>visemeflow report</h1>",
        f'<p class="meta">store <code>{esc(store.root)}</code> · generated {esc(generated)}</p>',
        '<nav><a href="#store">store</a><a href="#utterances">utterances</a><a href="#tracking">tracking</a>'
        '<a href="#training">training</a><a href="#sweeps">sweeps</a><a href="#robustness">robustness</a>'
        '<a href="#animations">animations</a><a href="#rejects">rejects</a></nav>',
    )
    if empty:
        page.add('<p id="nothing-yet" class="empty">Nothing yet: this store holds no utterances, curves, metrics '
                 "or rejects. Run <code>visemeflow pipeline CORPUS --store " + esc(store.root) + "</code> first.</p>")

    # -- store summary
    rejected_ids = {u for u in rejects.column(C.UTTERANCE_ID).to_pylist() if u} if rejects.num_rows else set()
    leftover = (set(index) - set(rows_by_id)) & rejected_ids   # rejected at their last run; older curves stay
    curve_only = len(set(index) - set(rows_by_id) - leftover)
    page.add('<section id="store"><h2>Store</h2>')
    summary = [["utterances", len(rows_by_id)]]
    if curve_only:
        summary.append(["curve-only utterances (predict, speak: no row in the utterances table)", curve_only])
    if leftover:
        summary.append(["rejected utterances whose curves of an earlier run stay (see Rejects)", len(leftover)])
    summary += [[f"utterances in split {k}", v] for k, v in _count_by(utterances, C.SPLIT)]
    summary += [["speakers", len(set(utterances.column(C.SPEAKER).to_pylist()))]]
    for source in CURVE_SOURCES:
        for variant in store.curve_variants(source):
            summary.append([f"curves {source}/{variant}", len(store.curve_files(source, variant))])
    summary += [["metrics rows", metrics.num_rows], ["rejects", rejects.num_rows]]
    summary += [[f"rejects at stage {k}", v] for k, v in _count_by(rejects, C.STAGE)]
    page.add(html_table(["what", "count"], summary, [False, True], table_id="store-table"), "</section>")

    # -- utterances
    page.add('<section id="utterances"><h2>Utterances</h2>')
    if missing:
        page.add('<p class="empty" id="missing-utterances">Not in the store: '
                 + ", ".join(f"<code>{esc(u)}</code>" for u in missing) + "</p>")
    if selected:
        total = len(rows_by_id) + curve_only
        split = f" ({len(rows_by_id)} in the utterances table, {curve_only} curve-only)" if curve_only else ""
        page.add(f'<p class="note" id="utterance-count">{len(selected)} of {total} utterances{split}; choose '
                 "others with <code>visemeflow dashboard --utterance SPEAKER/NAME</code> (repeatable) or "
                 "<code>--max-utterances N</code>. Curves: 16 viseme weights per frame, one panel per source and "
                 "variant; phone labels as written in the alignment (grey: no viseme).</p>")
        for n, uid in enumerate(selected):
            found = audio.get(uid)
            truth_of = None
            if found is not None and found.same_as and CurveSource.GROUND_TRUTH in index.get(found.same_as, {}):
                with contextlib.suppress(LookupError, OSError, pa.ArrowException):
                    truth_of = store.read_curves(found.same_as, CurveSource.GROUND_TRUTH,
                                                 index[found.same_as][CurveSource.GROUND_TRUTH][0])
            _utterance_section(page, store, n, uid, rows_by_id.get(uid), index.get(uid, {}), phones, found, truth_of,
                               rejected=uid in leftover)
    else:
        page.add('<p class="empty">No utterances yet.</p>')
    page.add("</section>")

    # -- tracking
    page.add('<section id="tracking"><h2>Tracking</h2>')
    if not _tracking_section(page, store):
        page.add('<p class="empty">No tracking diagnostics yet (<code>visemeflow track</code>).</p>')
    page.add("</section>")

    # -- training
    page.add('<section id="training"><h2>Training</h2>')
    final = _aggregate_rows(metrics, "final")
    table_html, series = training_html(metrics)
    if final.num_rows:
        page.add('<p class="note">Validation L1 x 100 of each trained model (run <code>final</code>).</p>', table_html)
    else:
        page.add('<p class="empty" id="no-training">No trained model yet (no <code>final</code> metrics rows; '
                 "<code>visemeflow train</code>).</p>")
    if series:
        page.image("chart-training", plots.training_figure(series), "validation L1 x 100 by epoch per model",
                   "Validation L1 x 100 after each epoch (run <code>train</code>).")
    page.add("</section>")

    # -- sweeps
    page.add('<section id="sweeps"><h2>Dataset-size sweeps</h2>')
    for n, path in enumerate(sweeps):
        try:
            data = path.read_bytes()
        except OSError as exc:
            page.add(f'<p class="empty">{esc(path.name)}: {esc(exc)}</p>')
            continue
        if not data.startswith(b"\x89PNG\r\n\x1a\n"):
            page.add(f'<p class="empty">{esc(path.name)} is not a PNG file.</p>')
            continue
        page.image(f"chart-sweep-{n}", data, f"sweep plot {path.name}", f"<code>{esc(path.name)}</code>")
    if not sweeps:
        page.add('<p class="empty">No sweep yet (<code>visemeflow sweep</code>).</p>')
    page.add("</section>")

    # -- robustness
    page.add('<section id="robustness"><h2>Robustness</h2>')
    robust = robustness_table(metrics, *evaluated_labels(store))
    if robust.models:
        real = ""
        if robust.realspeech_metrics:
            real = (" Real-speech metrics, from the validation utterances' phone alignment and no curve truth "
                    "(runs <code>evaluate.&lt;metric&gt;</code>): MBP / FFF closure, the % of b/p/m (f/v) phones "
                    "whose top predicted viseme within the phone is MBP (FFF); agreement, the % of non-silent "
                    "phones whose viseme is among the top two predicted at the phone's middle frame.")
        if any(m in LIP_METRICS for m in robust.realspeech_metrics):
            real += (" Lip metrics (runs <code>evaluate.lip_*</code>), what the viewer sees: the same curves through "
                     "the closure rule, measured in millimetres on the demo character's mesh: lips closed, the % of "
                     "b/p/m phones whose smallest inner-lip gap is below 1.5 mm (and the median gap); f/v contact, "
                     "the % of f/v phones whose lower lip comes within 2 mm of the upper teeth; AA/AH opening, the "
                     "median widest gap of open vowels over the widest single shape's (good 0.6-1.1); vowels never "
                     "open, the % of vowels whose gap stays below 1.5 mm; raw curves, without the closure rule.")
        page.add('<p class="note">Validation L1 x 100 on clean audio and under each augmentation (run '
                 "<code>evaluate</code>, aggregate rows), and the ratio to clean audio (1.0 = no degradation); "
                 "the table of <code>reports/robustness.md</code>, in its order, for every evaluated model (a "
                 "wide table scrolls sideways in its box; the model column stays)."
                 f"{real}</p>", _headline_html(robust.headline),
                 f'<div class="wide" id="robustness-scroll">{robustness_html(robust)}</div>')
    else:
        page.add('<p class="empty" id="no-robustness">No robustness evaluation yet (no <code>evaluate</code> '
                 "metrics rows).</p>")
    page.add("</section>")

    # -- animations
    page.add('<section id="animations"><h2>Animations</h2>')
    _animations_section(page, packages, out)
    page.add("</section>")

    # -- rejects
    page.add('<section id="rejects"><h2>Rejects</h2>')
    if rejects.num_rows:
        ordered = rejects.sort_by([(C.TIME, "descending")]).slice(0, MAX_REJECT_ROWS).to_pylist()
        page.add(html_table(
            ["stage", "utterance", "error", "message", "path", "time"],
            [[r[C.STAGE], r[C.UTTERANCE_ID], r[C.ERROR_TYPE], r[C.MESSAGE], r[C.PATH],
              r[C.TIME].strftime("%Y-%m-%d %H:%M:%S") if r[C.TIME] else None] for r in ordered],
            cell_class=["", "", "", "msg", "msg", ""], table_id="rejects-table"))
        if rejects.num_rows > MAX_REJECT_ROWS:
            page.add(f'<p class="note">... and {rejects.num_rows - MAX_REJECT_ROWS} older rejects: '
                     "<code>visemeflow rejects</code>.</p>")
    else:
        page.add('<p class="note" id="no-rejects">No rejects.</p>')
    page.add("</section></body></html>")

    target = atomic_write_text(out / "index.html", "\n".join(page.parts))
    return DashboardResult(target, selected, page.charts, missing, empty)


__all__ = ["DashboardResult", "RobustnessTable", "build_dashboard", "esc", "robustness_table",
           "select_utterances"]
