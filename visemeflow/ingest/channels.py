"""Channel tables: how the channels of a captured take (a rig's own blendshape names, FACEGOOD's "shirley" rig)
become ARKit-52 weights, read from a CSV or an `.xlsx` spreadsheet (a reader of our own, bounded: a table is a few
hundred rows, and a hostile file cannot unpack to more than a few MB), in one of two forms:

- `arkit,expression[,status]`: each ARKit name from an expression of channels, `name` or `max(a, b, ...)`; rows whose
  status is `invalid` (any case) and rows without an expression drive nothing (FACEGOOD's
  `Voice2Face_blendshape2ARkit.xlsx` is this form; `examples/facegood/voice2face_arkit.csv` is it as CSV);
- `channel,arkit,weight`: each ARKit weight is the sum of weight x channel over its rows.

ARKit names in a table are matched ignoring case (`browDownleft` is `browDownLeft`). A table that cannot be used is a
`CaptureReadError` naming the file and line. The takes that use a table: `visemeflow.ingest.captured`."""

from __future__ import annotations

import csv
import io
import math
import re
import xml.etree.ElementTree as ET
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visemeflow.atomic import atomic_write_text
from visemeflow.hashing import stable_hash
from visemeflow.shapes.conventions import ARKIT_52

_MAX_XLSX_FILE = 16 << 20
"""The largest .xlsx channel table read (FACEGOOD's is 25 KB; a table names channels, a few hundred rows)."""
_MAX_XLSX_PART = 4 << 20
"""The most bytes one part of it (workbook, shared strings, sheet) may unpack to: 200 times FACEGOOD's sheet, and
an XML tree of that size stays in the hundreds of MB."""
_MAX_XLSX_RATIO = 100
"""The most a part may have been compressed (unpacked / packed bytes) when it unpacks to more than 1 MiB:
spreadsheet XML packs 2-10 times (FACEGOOD's parts 1.8-7.9), deflate at most about 1032 times."""
_ARKIT_FOLDED = {name.lower(): name for name in ARKIT_52}
_ARKIT_INDEX = {name: i for i, name in enumerate(ARKIT_52)}
_MAX_CALL = re.compile(r"^max\s*\((.*)\)$", re.IGNORECASE | re.DOTALL)


class CaptureReadError(ValueError):
    """A captured take or table that cannot be used; names the file, a short error type and the reason."""

    def __init__(self, path: str, error_type: str, reason: str):
        super().__init__(f"{path}: {reason}")
        self.path, self.error_type, self.reason = str(path), error_type, reason

    def __reduce__(self):  # picklable with its three-argument constructor (Prefect ships exceptions)
        return (type(self), (self.path, self.error_type, self.reason))


# ---- channel tables --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ExpressionRow:
    """One row of an `arkit,expression,status` table as written (line: the file's line or the sheet's row)."""

    line: int
    arkit: str
    expression: str
    status: str


@dataclass(frozen=True)
class ChannelTable:
    """Channels -> ARKit weights: for each driven ARKit name, `op` ('max' or 'sum') over (channel, weight) terms."""

    source: str
    rules: tuple[tuple[str, str, tuple[tuple[str, float], ...]], ...]
    """(ARKit name, op, ((channel, weight), ...)) per driven ARKit name."""
    ignored: tuple[str, ...] = ()
    """ARKit names the table marks invalid or leaves without an expression."""

    @property
    def channels(self) -> tuple[str, ...]:
        """The channels the table reads, in first-use order."""
        seen: dict[str, None] = {}
        for _, _, terms in self.rules:
            for channel, _ in terms:
                seen.setdefault(channel, None)
        return tuple(seen)

    def apply(self, names: tuple[str, ...], values: np.ndarray) -> np.ndarray:
        """(T, 52) float32 ARKit weights from (T, channels) `values` named `names` (all the table's channels in it)."""
        index = {n: i for i, n in enumerate(names)}
        out = np.zeros((len(values), len(ARKIT_52)), np.float64)
        for arkit, op, terms in self.rules:
            cols = np.stack([values[:, index[c]] * w for c, w in terms], axis=1)
            out[:, _ARKIT_INDEX[arkit]] = cols.max(axis=1) if op == "max" else cols.sum(axis=1)
        return out.astype(np.float32)

    @property
    def digest(self) -> str:
        return stable_hash([list(r[:2]) + [list(map(list, r[2]))] for r in self.rules])


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _column_number(ref: str) -> int | None:
    letters = "".join(ch for ch in ref if ch.isalpha())
    if not letters:
        return None
    n = 0
    for ch in letters.upper():
        n = n * 26 + ord(ch) - ord("A") + 1
    return n - 1


def _xlsx_part(archive: zipfile.ZipFile, name: str, path: Path) -> ET.Element:
    """Part `name` parsed, its declared sizes checked before it is unpacked and its unpacking capped by them
    (zipfile stops at the declared size and then checks the CRC, so a size that lies cannot unpack more)."""
    try:
        info = archive.getinfo(name)
    except KeyError:
        raise CaptureReadError(str(path), "BadXlsx", f"not a spreadsheet: no {name} inside") from None
    if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
        raise CaptureReadError(str(path), "BadXlsx", f"{name} is packed with zip compression method "
                               f"{info.compress_type}; an .xlsx part is stored or deflated")
    if info.file_size > _MAX_XLSX_PART:
        raise CaptureReadError(str(path), "BadXlsx", f"{name} unpacks to {info.file_size} bytes; too large for a "
                               f"table (at most {_MAX_XLSX_PART})")
    if info.file_size > max(_MAX_XLSX_RATIO * info.compress_size, 1 << 20):
        raise CaptureReadError(str(path), "BadXlsx", f"{name} declares {info.file_size} bytes packed into "
                               f"{info.compress_size}, a compression ratio over {_MAX_XLSX_RATIO}:1 that no "
                               "spreadsheet has")
    try:
        # a size keeps each inflate step bounded: read() without one asks zlib for up to 2 GiB at once
        with archive.open(info) as member:
            data = member.read(info.file_size)
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, RuntimeError) as exc:  # RuntimeError: encrypted
        raise CaptureReadError(str(path), "BadXlsx", f"{name} cannot be unpacked ({exc}); the file is damaged or "
                               f"its zip directory's size ({info.file_size} bytes) lies") from None
    try:
        return ET.fromstring(data)
    except ET.ParseError as exc:
        raise CaptureReadError(str(path), "BadXlsx", f"{name} is not well-formed XML ({exc})") from None


def read_xlsx_rows(path: str | Path) -> list[tuple[int, list[str]]]:
    """The rows of the first worksheet of an .xlsx file as (row number, cell texts), empty rows left out.

    A small reader of the Office Open XML spreadsheet parts (workbook, its relationships, shared strings and the
    sheet), enough for tables of names and numbers; numbers come back as the text stored in the file."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > _MAX_XLSX_FILE:
            raise CaptureReadError(str(path), "BadXlsx", f"{size} bytes; a channel table .xlsx has at most "
                                   f"{_MAX_XLSX_FILE}")
        archive = zipfile.ZipFile(path)
    except (OSError, zipfile.BadZipFile) as exc:
        raise CaptureReadError(str(path), "BadXlsx", f"cannot open as an .xlsx spreadsheet ({exc})") from None
    with archive:
        workbook = _xlsx_part(archive, "xl/workbook.xml", path)
        sheets = [el for el in workbook.iter() if _local(el.tag) == "sheet"]
        if not sheets:
            raise CaptureReadError(str(path), "BadXlsx", "the workbook has no sheet")
        rel_id = next((v for k, v in sheets[0].attrib.items() if _local(k) == "id"), None)
        rels = _xlsx_part(archive, "xl/_rels/workbook.xml.rels", path)
        target = next((el.get("Target") for el in rels.iter()
                       if _local(el.tag) == "Relationship" and el.get("Id") == rel_id), None)
        if not target:
            raise CaptureReadError(str(path), "BadXlsx", f"the first sheet's part ({rel_id}) is not listed")
        sheet_name = target.lstrip("/") if target.startswith("/") else f"xl/{target}"
        shared: list[str] = []
        if "xl/sharedStrings.xml" in archive.namelist():
            for si in _xlsx_part(archive, "xl/sharedStrings.xml", path):
                if _local(si.tag) == "si":
                    shared.append("".join(t.text or "" for t in si.iter() if _local(t.tag) == "t"))
        sheet = _xlsx_part(archive, sheet_name, path)
    rows: list[tuple[int, list[str]]] = []
    for number, row in enumerate((el for el in sheet.iter() if _local(el.tag) == "row"), start=1):
        number = int(row.get("r", number))
        cells: dict[int, str] = {}
        column = 0
        for cell in row:
            if _local(cell.tag) != "c":
                continue
            ref = _column_number(cell.get("r", ""))
            column = ref if ref is not None else column
            kind = cell.get("t", "n")
            value = next((el for el in cell if _local(el.tag) == "v"), None)
            if kind == "inlineStr":
                text = "".join(t.text or "" for t in cell.iter() if _local(t.tag) == "t")
            elif value is None or value.text is None:
                text = ""
            elif kind == "s":
                try:
                    text = shared[int(value.text)]
                except (ValueError, IndexError):
                    raise CaptureReadError(str(path), "BadXlsx", f"row {number}: shared string {value.text!r} "
                                                                 "does not exist") from None
            elif kind == "b":
                text = "TRUE" if value.text.strip() == "1" else "FALSE"
            else:
                text = value.text
            if text.strip():
                cells[column] = text.strip()
            column += 1
        if cells:
            rows.append((number, [cells.get(i, "") for i in range(max(cells) + 1)]))
    return rows


def _canonical_arkit(name: str) -> str | None:
    return name if name in _ARKIT_INDEX else _ARKIT_FOLDED.get(name.lower())


def _expression_rows_from(records: list[tuple[int, list[str]]], where: str, sheet: bool) -> list[ExpressionRow]:
    """`arkit,expression[,status]` rows from (line, cells) records whose first one is the header."""
    if not records:
        raise CaptureReadError(where, "BadChannelTable", "empty table")
    header_line, header = records[0]
    lowered = [h.strip().lower() for h in header]
    if "arkit" not in lowered:
        raise CaptureReadError(where, "BadChannelTable",
                               f"line {header_line}: no 'arkit' column in the header {header}")
    arkit_col = lowered.index("arkit")
    status_col = lowered.index("status") if "status" in lowered else None
    if "expression" in lowered:
        expr_col = lowered.index("expression")
    else:
        others = [i for i, h in enumerate(lowered) if h and i not in (arkit_col, status_col)]
        if not sheet or len(others) != 1:
            raise CaptureReadError(where, "BadChannelTable",
                                   f"line {header_line}: expected the columns arkit,expression[,status]; got {header}")
        expr_col = others[0]  # a sheet names it as it likes (FACEGOOD: 'Voice2Face')

    def cell(cells: list[str], i: int | None) -> str:
        return cells[i].strip() if i is not None and i < len(cells) else ""

    return [ExpressionRow(line, cell(cells, arkit_col), cell(cells, expr_col), cell(cells, status_col))
            for line, cells in records[1:]]


def _text_records(path: Path) -> list[tuple[int, list[str]]]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise CaptureReadError(str(path), "UnreadableChannelTable", f"cannot read ({exc})") from None
    records = []
    for line, cells in enumerate(csv.reader(io.StringIO(text, newline="")), start=1):
        if not cells or all(not c.strip() for c in cells) or cells[0].lstrip().startswith("#"):
            continue
        records.append((line, cells))
    return records


def read_expression_rows(path: str | Path) -> list[ExpressionRow]:
    """The rows of an `arkit,expression[,status]` table, CSV or .xlsx (first sheet; its header row is the first
    with an `ARKIT` cell), as written."""
    path = Path(path)
    if path.suffix.lower() == ".xlsx":
        records = read_xlsx_rows(path)
        start = next((k for k, (_, cells) in enumerate(records) if any(c.strip().lower() == "arkit" for c in cells)),
                     None)
        if start is None:
            raise CaptureReadError(str(path), "BadChannelTable", "no header row with an 'ARKIT' cell in the first sheet")
        return _expression_rows_from(records[start:], str(path), sheet=True)
    return _expression_rows_from(_text_records(path), str(path), sheet=False)


def _parse_expression(text: str, source: str, line: int) -> tuple[str, ...]:
    """`name` or `max(a, b, ...)` -> the channel names."""
    match = _MAX_CALL.match(text)
    names = [n.strip() for n in match[1].split(",")] if match else [text.strip()]
    if any(not n or any(ch in n for ch in "(),") for n in names):
        raise CaptureReadError(source, "BadChannelTable",
                               f"line {line}: {text!r} is not a channel name or max(a, b, ...)")
    return tuple(names)


def _table_from_expressions(rows: list[ExpressionRow], source: str) -> ChannelTable:
    rules, ignored, seen = [], [], {}
    for row in rows:
        status = row.status.lower()
        if status not in ("", "valid", "invalid"):
            raise CaptureReadError(source, "BadChannelTable",
                                   f"line {row.line}: status {row.status!r} is neither valid nor invalid")
        if not row.expression and not status:
            continue  # a note or an empty line
        arkit = _canonical_arkit(row.arkit)
        if arkit is None:
            raise CaptureReadError(source, "BadChannelTable",
                                   f"line {row.line}: {row.arkit!r} is not an ARKit-52 blendshape name")
        if status == "invalid" or not row.expression:
            ignored.append(arkit)
            continue
        if arkit in seen:
            raise CaptureReadError(source, "BadChannelTable",
                                   f"line {row.line}: {arkit} is driven twice (also line {seen[arkit]})")
        seen[arkit] = row.line
        channels = _parse_expression(row.expression, source, row.line)
        rules.append((arkit, "max", tuple((c, 1.0) for c in channels)))
    if not rules:
        raise CaptureReadError(source, "BadChannelTable", "no valid row: the table drives no ARKit shape")
    return ChannelTable(source, tuple(rules), tuple(ignored))


def _table_from_weights(records: list[tuple[int, list[str]]], source: str) -> ChannelTable:
    terms: dict[str, list[tuple[str, float]]] = {}
    for line, cells in records[1:]:
        if len(cells) < 3:
            raise CaptureReadError(source, "BadChannelTable", f"line {line}: expected channel,arkit,weight")
        channel, name, weight_text = (c.strip() for c in cells[:3])
        arkit = _canonical_arkit(name)
        if not channel:
            raise CaptureReadError(source, "BadChannelTable", f"line {line}: no channel name")
        if arkit is None:
            raise CaptureReadError(source, "BadChannelTable", f"line {line}: {name!r} is not an ARKit-52 blendshape name")
        try:
            weight = float(weight_text)
        except ValueError:
            raise CaptureReadError(source, "BadChannelTable", f"line {line}: weight {weight_text!r} is not a number") from None
        if not math.isfinite(weight):
            raise CaptureReadError(source, "BadChannelTable", f"line {line}: weight {weight_text!r} is not finite")
        if any(c == channel for c, _ in terms.get(arkit, [])):
            raise CaptureReadError(source, "BadChannelTable", f"line {line}: {channel} -> {arkit} listed twice")
        terms.setdefault(arkit, []).append((channel, weight))
    if not terms:
        raise CaptureReadError(source, "BadChannelTable", "no rows")
    return ChannelTable(source, tuple((a, "sum", tuple(t)) for a, t in terms.items()))


def read_channel_table(path: str | Path) -> ChannelTable:
    """A channel -> ARKit table: `arkit,expression[,status]` (CSV or .xlsx) or `channel,arkit,weight` (CSV)."""
    path = Path(path)
    if not path.is_file():
        raise CaptureReadError(str(path), "MissingChannelTable", "channel table not found")
    if path.suffix.lower() == ".xlsx":
        return _table_from_expressions(read_expression_rows(path), str(path))
    records = _text_records(path)
    header = [h.strip().lower() for h in records[0][1]] if records else []
    if header[:3] == ["channel", "arkit", "weight"]:
        return _table_from_weights(records, str(path))
    if header[:1] == ["arkit"] or "arkit" in header and "expression" in header:
        return _table_from_expressions(_expression_rows_from(records, str(path), sheet=False), str(path))
    raise CaptureReadError(str(path), "BadChannelTable",
                           f"expected the header 'arkit,expression[,status]' or 'channel,arkit,weight', got {header}")


def write_expression_csv(rows: list[ExpressionRow], path: str | Path, comments: tuple[str, ...] = ()) -> Path:
    """An `arkit,expression,status` CSV of `rows` (ARKit names as Apple spells them; notes left out), atomically."""
    out = io.StringIO()
    for comment in comments:
        out.write(f"# {comment}\n")
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(("arkit", "expression", "status"))
    for row in rows:
        if not row.expression and not row.status:
            continue
        writer.writerow((_canonical_arkit(row.arkit) or row.arkit, row.expression, row.status))
    return atomic_write_text(Path(path), out.getvalue())
