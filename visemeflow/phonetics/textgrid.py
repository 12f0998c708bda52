"""Praat TextGrid reader for every format Praat writes: text (UTF-8 with or without BOM, UTF-16, Latin-1) and binary.

Praat's text format is a stream of values: quoted strings (with "" for a literal quote), numbers and
<flags>; everything else (``xmin =``, ``item [1]:``) is decoration that Praat itself ignores. Reading
the value stream instead of the lines therefore handles the long format, the short format, the older
short header (``File type = "ooTextFile short"`` with ``"TextGrid"`` on its own line, as old Praat and
P2FA write it), the chronological format ("Save as chronological text file": a header string
``"Praat chronological TextGrid text file"``, the tiers declared first, then every interval and point in
time order, each prefixed by its tier number) and any mix of them with one small tokenizer.

The binary format ("Save as binary file", starting with the bytes ``ooBinaryFile``) is read by
`parse_textgrid_binary`; `parse_textgrid_bytes` and `read_textgrid` choose the reader from the first bytes.
The layout was checked against files Praat 6.1.38 wrote (through praat-parselmouth): big-endian IEEE
doubles for times, a 1-byte flag for "tiers exist", 32-bit counts, the object and tier classes as a 1-byte
length and ASCII, tier names and labels as a 16-bit length and 8-bit text, or the length 0xFFFF then a
16-bit count of characters and their UTF-16BE code units (two for a character outside the BMP) when the
text is not ASCII.

Why our own reader rather than the `textgrid` package (measured by ``bench/textgrid_readers.py`` on the
demo corpus, the real TextGrids of ../shared/data and every one of them rewritten in each Praat variant:
ours reads 477 of 477 files, the package 472): the package fails on short-format files with a point tier
(``praatio_examples/mary.TextGrid``, a real file, with an AttributeError that names neither the file nor
the line), rounds every time to 5 digits (exact on 18 of its 472 files), drops zero-length intervals and
ignores tiers beyond the declared count without a word. Speed is no reason either way: ours is 1.1x
faster. The package stays the reference of the tests and the benchmark (a dev dependency).
"""

import math
import os
import re
import struct
from dataclasses import dataclass

from visemeflow.phonetics.types import Seconds

_TOKEN = re.compile(
    r'"((?:[^"]|"")*)"'                          # quoted string
    r"|\[[^\]\n]*\]"                             # bracketed index, ignored: item [1], intervals [3]
    r"|<(exists|absent)>"                        # flags
    r"|(?<![\w.])([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|(?i:nan|[-+]?inf))(?![\w.])"  # number
    # nan/inf (as Python writers put them) are read as numbers, so the interval checks downstream
    # can name the bad interval instead of the stream going out of step.
    r"|![^\n]*"                                  # Praat comment: from ! outside a string to the end of the line
)


_FILE_TYPES = ("ooTextFile", "ooTextFile short")
CHRONOLOGICAL_HEADER = "Praat chronological TextGrid text file"
BINARY_MAGIC = b"ooBinaryFile"


class TextGridError(ValueError):
    """A TextGrid that cannot be read; the message names the file and what was expected."""


@dataclass(frozen=True, slots=True)
class Tier:
    """One tier: intervals as (start, end, text) or points as (time, time, text)."""

    name: str
    kind: str
    start_s: Seconds
    end_s: Seconds
    items: tuple[tuple[Seconds, Seconds, str], ...]


@dataclass(frozen=True, slots=True)
class TextGridData:
    start_s: Seconds
    end_s: Seconds
    tiers: tuple[Tier, ...]

    def tier(self, names: tuple[str, ...]) -> Tier | None:
        """The first interval tier whose name matches one of `names` (case-insensitive, in order)."""
        by_name = {t.name.strip().lower(): t for t in reversed(self.tiers) if t.kind == "IntervalTier"}
        for name in names:
            if name.lower() in by_name:
                return by_name[name.lower()]
        return None


def decode_textgrid_bytes(data: bytes) -> str:
    """Text of a TextGrid file: UTF-16 when it has a byte-order mark (Praat writes it so), else UTF-8."""
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        return data.decode("utf-16")
    if data.startswith(b"\xef\xbb\xbf"):
        return data[3:].decode("utf-8")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return data.decode("latin-1")


def _tokens(text: str) -> tuple[list[object], list[int]]:
    """(the values, the offset in `text` where each one's token starts)."""
    out: list[object] = []
    starts: list[int] = []
    for m in _TOKEN.finditer(text):
        string, flag, number = m.group(1), m.group(2), m.group(3)
        if string is not None:
            out.append(_Str(string.replace('""', '"')))
        elif flag is not None:
            out.append(_Flag(flag))
        elif number is not None:
            out.append(float(number))
        else:
            continue
        starts.append(m.start())
    return out, starts


_ASSIGNMENT = re.compile(r"^\s*[A-Za-z]+\s*=\s*(\S.*)$")
_VALUE = re.compile(r'-?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|".*"|<\w+>')
_SWALLOWED = re.compile(r"\n\s*(?:xmin|xmax|text|number|mark|intervals|points)\s*[=\[]")


class _Str(str):
    pass


class _Flag(str):
    pass


class _Cursor:
    def __init__(self, tokens: list[object], source: str, starts: list[int] | None = None, text: str = ""):
        self.tokens, self.pos, self.source = tokens, 0, source
        self.starts, self.text = starts, text

    def _next(self, expected: str) -> object:
        if self.pos >= len(self.tokens):
            raise TextGridError(f"{self.source}: file ends early, expected {expected}{self._unread_value()}")
        tok = self.tokens[self.pos]
        self.pos += 1
        return tok

    def _unread_value(self) -> str:
        """Where a value the format skips (`xmax = oops`: neither a number nor a quoted string) shifted the values
        after it, so that the file seemed to end early; empty when there is none."""
        for number, line in enumerate(self.text.splitlines(), 1):
            m = _ASSIGNMENT.match(line)
            if m and not _VALUE.fullmatch(m.group(1).strip()):
                return f" (line {number}, {line.strip()!r}: not a number or a quoted string)"
        return ""

    def _line(self, offset: int) -> int:
        return self.text.count("\n", 0, offset) + 1

    def _found(self, tok: object) -> str:
        """Where the value was expected and what stood there: the line after the previous value, with its text
        (`xmax = abc`: a word the format skips), and the value found instead (an unclosed quote swallows lines)."""
        if not self.starts:
            return f"found {tok!r}"
        i = self.pos - 1
        gap_from = self.starts[i - 1] if i > 0 else 0
        if i > 0:   # past the previous value's own text
            gap_from = self.text.find("\n", gap_from)
            gap_from = self.starts[i] if gap_from < 0 or gap_from > self.starts[i] else gap_from + 1
        here = self.text[gap_from:self.starts[i]].strip().splitlines()
        where = f"line {self._line(gap_from)}" + (f" ({here[0].strip()!r})" if here and here[0].strip() else "")
        assigned = _ASSIGNMENT.match(here[0]) if here else None
        if assigned and assigned.group(1).strip() and not _VALUE.fullmatch(assigned.group(1).strip()):
            # `xmax = 0.4OO`: the format skips what is not a value, so the value "found" is the next line's
            return f"at {where}: {assigned.group(1).strip()!r} is not a number"
        if isinstance(tok, _Str) and "\n" in tok:
            shown = (f"a quoted string running over {tok.count(chr(10)) + 1} lines from line "
                     f"{self._line(self.starts[i])} (a quote left open?)")
        else:
            shown = f"{tok!r} at line {self._line(self.starts[i])}"
        return f"at {where}, found {shown}"

    def number(self, what: str) -> float:
        tok = self._next(what)
        if not isinstance(tok, float):
            raise TextGridError(f"{self.source}: expected a number for {what} {self._found(tok)}")
        return tok

    def count(self, what: str) -> int:
        value = self.number(what)
        if not (math.isfinite(value) and value >= 0 and value == int(value)):
            raise TextGridError(f"{self.source}: {what} must be a whole number >= 0, found {value}")
        return int(value)

    def string(self, what: str) -> str:
        tok = self._next(what)
        if not isinstance(tok, _Str):
            raise TextGridError(f"{self.source}: expected a quoted string for {what} {self._found(tok)}")
        if _SWALLOWED.search(tok) and self.starts:   # a label that holds the next interval's lines: an open quote
            start = self.starts[self.pos - 1]
            raise TextGridError(f"{self.source}: {what} opens a quote at line {self._line(start)} that runs "
                                f"over {tok.count(chr(10)) + 1} lines into the next entries (a quote left open?)")
        return str(tok)

    def flag(self, what: str) -> str:
        tok = self._next(what)
        if not isinstance(tok, _Flag):
            raise TextGridError(f"{self.source}: expected <exists> or <absent> for {what} {self._found(tok)}")
        return str(tok)


def parse_textgrid(text: str, source: str = "<string>") -> TextGridData:
    """Parse TextGrid text in Praat's long or short format into tiers of (start, end, label)."""
    tokens, starts = _tokens(text)
    cur = _Cursor(tokens, source, starts, text)
    file_type = cur.string("the file type")
    if file_type == CHRONOLOGICAL_HEADER:
        return _parse_chronological(cur)
    object_class = cur.string("the object class")
    # "ooTextFile short" is the older short-format header: the class follows as a bare "TextGrid" line
    if file_type not in _FILE_TYPES or object_class != "TextGrid":
        raise TextGridError(
            f"{source}: not a Praat TextGrid text file (file type {file_type!r}, class {object_class!r})"
        )
    start, end = cur.number("xmin"), cur.number("xmax")
    tiers: list[Tier] = []
    if cur.flag("tiers") == "exists":
        n_tiers = cur.count("the tier count")
        for t in range(n_tiers):
            tiers.append(_parse_tier(cur, t + 1))
    if cur.pos < len(cur.tokens):
        # values left over mean the stream went out of step (e.g. a non-numeric time was skipped)
        raise TextGridError(
            f"{source}: unexpected value {cur.tokens[cur.pos]!r} after the last of {len(tiers)} tier(s); "
            "a time, count or label is missing or not a number"
        )
    return TextGridData(start, end, tuple(tiers))


def _parse_tier(cur: _Cursor, number: int) -> Tier:
    kind = cur.string(f"the class of tier {number}")
    name = cur.string(f"the name of tier {number}")
    start, end = cur.number(f"xmin of tier {name!r}"), cur.number(f"xmax of tier {name!r}")
    count = cur.count(f"the item count of tier {name!r}")
    items: list[tuple[float, float, str]] = []
    if kind == "IntervalTier":
        for i in range(count):
            a = cur.number(f"xmin of interval {i + 1} in tier {name!r}")
            b = cur.number(f"xmax of interval {i + 1} in tier {name!r}")
            items.append((a, b, cur.string(f"the text of interval {i + 1} in tier {name!r}")))
    elif kind == "TextTier":
        for i in range(count):
            a = cur.number(f"the time of point {i + 1} in tier {name!r}")
            items.append((a, a, cur.string(f"the mark of point {i + 1} in tier {name!r}")))
    else:
        raise TextGridError(f"{cur.source}: tier {name!r} has unknown class {kind!r}")
    return Tier(name, kind, start, end, tuple(items))


def _parse_chronological(cur: _Cursor) -> TextGridData:
    """The chronological text format: tier headers first, then `tier number, time(s), text` in time order."""
    start, end = cur.number("xmin"), cur.number("xmax")
    n_tiers = cur.count("the tier count")
    headers: list[tuple[str, str, float, float]] = []
    for t in range(n_tiers):
        kind = cur.string(f"the class of tier {t + 1}")
        name = cur.string(f"the name of tier {t + 1}")
        if kind not in ("IntervalTier", "TextTier"):
            raise TextGridError(f"{cur.source}: tier {name!r} has unknown class {kind!r}")
        headers.append((kind, name, cur.number(f"xmin of tier {name!r}"), cur.number(f"xmax of tier {name!r}")))
    items: list[list[tuple[float, float, str]]] = [[] for _ in headers]
    entry = 0
    while cur.pos < len(cur.tokens):
        entry += 1
        number = cur.number(f"the tier number of entry {entry}")
        if not (number == int(number) and 1 <= number <= n_tiers):
            raise TextGridError(f"{cur.source}: entry {entry} names tier {number:g}; the file declares {n_tiers} tier(s)")
        kind, name = headers[int(number) - 1][:2]
        if kind == "IntervalTier":
            a = cur.number(f"xmin of entry {entry} (tier {name!r})")
            b = cur.number(f"xmax of entry {entry} (tier {name!r})")
        else:
            a = b = cur.number(f"the time of entry {entry} (tier {name!r})")
        items[int(number) - 1].append((a, b, cur.string(f"the text of entry {entry} (tier {name!r})")))
    tiers = tuple(Tier(name, kind, a, b, tuple(its)) for (kind, name, a, b), its in zip(headers, items))
    return TextGridData(start, end, tiers)


class _BinaryReader:
    """Big-endian values of a binary Praat file, with errors naming the file and the byte offset."""

    def __init__(self, data: bytes, source: str):
        self.data, self.pos, self.source = data, 0, source

    def take(self, n: int, what: str) -> bytes:
        if self.pos + n > len(self.data):
            raise TextGridError(f"{self.source}: binary TextGrid ends early at byte {len(self.data)}, expected {what}")
        chunk = self.data[self.pos:self.pos + n]
        self.pos += n
        return chunk

    def double(self, what: str) -> float:
        return struct.unpack(">d", self.take(8, what))[0]

    def int32(self, what: str) -> int:
        value = struct.unpack(">i", self.take(4, what))[0]
        if value < 0:
            raise TextGridError(f"{self.source}: {what} is negative ({value}) at byte {self.pos - 4}")
        return value

    def short_ascii(self, what: str) -> str:
        """A 1-byte length and ASCII text (Praat's class names)."""
        n = self.take(1, what)[0]
        return self.take(n, what).decode("latin-1")

    def text(self, what: str) -> str:
        """A 16-bit length and 8-bit text, or 0xFFFF, a 16-bit character count and UTF-16BE code units."""
        n = struct.unpack(">H", self.take(2, what))[0]
        if n != 0xFFFF:
            return self.take(n, what).decode("latin-1")
        n = struct.unpack(">H", self.take(2, what))[0]
        start = self.pos
        for _ in range(n):  # n counts characters: one outside the BMP takes two code units (a surrogate pair)
            if 0xD800 <= struct.unpack(">H", self.take(2, what))[0] <= 0xDBFF:
                self.take(2, what)
        try:
            return self.data[start:self.pos].decode("utf-16-be")
        except UnicodeDecodeError as exc:
            raise TextGridError(f"{self.source}: {what} is not valid UTF-16 (before byte {self.pos}): {exc}") from exc


def parse_textgrid_binary(data: bytes, source: str = "<bytes>") -> TextGridData:
    """Parse a TextGrid in Praat's binary format ("Save as binary file")."""
    r = _BinaryReader(data, source)
    if r.take(len(BINARY_MAGIC), "the ooBinaryFile header") != BINARY_MAGIC:
        raise TextGridError(f"{source}: not a Praat binary file (no ooBinaryFile header)")
    object_class = r.short_ascii("the object class")
    if object_class != "TextGrid":
        raise TextGridError(f"{source}: a Praat binary {object_class!r} file, not a TextGrid")
    start, end = r.double("xmin"), r.double("xmax")
    tiers: list[Tier] = []
    if r.take(1, "the tiers-exist flag")[0]:
        for t in range(r.int32("the tier count")):
            kind = r.short_ascii(f"the class of tier {t + 1}")
            name = r.text(f"the name of tier {t + 1}")
            a, b = r.double(f"xmin of tier {name!r}"), r.double(f"xmax of tier {name!r}")
            count = r.int32(f"the item count of tier {name!r}")
            items: list[tuple[float, float, str]] = []
            if kind == "IntervalTier":
                for i in range(count):
                    x0 = r.double(f"xmin of interval {i + 1} in tier {name!r}")
                    x1 = r.double(f"xmax of interval {i + 1} in tier {name!r}")
                    items.append((x0, x1, r.text(f"the text of interval {i + 1} in tier {name!r}")))
            elif kind == "TextTier":
                for i in range(count):
                    x = r.double(f"the time of point {i + 1} in tier {name!r}")
                    items.append((x, x, r.text(f"the mark of point {i + 1} in tier {name!r}")))
            else:
                raise TextGridError(f"{source}: tier {name!r} has unknown class {kind!r}")
            tiers.append(Tier(name, kind, a, b, tuple(items)))
    if r.pos != len(data):
        raise TextGridError(f"{source}: {len(data) - r.pos} unexpected byte(s) after the last of {len(tiers)} tier(s)")
    return TextGridData(start, end, tuple(tiers))


def parse_textgrid_bytes(data: bytes, source: str = "<bytes>") -> TextGridData:
    """A TextGrid file's content in any format Praat writes: binary, or text in any encoding Praat uses."""
    if data.startswith(BINARY_MAGIC):
        return parse_textgrid_binary(data, source)
    try:
        text = decode_textgrid_bytes(data)
    except UnicodeDecodeError as exc:
        raise TextGridError(f"{source}: not UTF-16 text although it starts with a UTF-16 byte-order mark: {exc}") from exc
    return parse_textgrid(text, source)


STYLES = ("long", "short", "ooTextFile short")


def format_textgrid(
    tiers: tuple[Tier, ...] | list[Tier], xmin: float, xmax: float, style: str = "long"
) -> str:
    """Praat TextGrid text of `tiers` (interval and point tiers); `parse_textgrid` reads it back exactly.

    `style` is one of the text layouts Praat writes: "long" (``xmin = 0`` lines, "Save as text file"),
    "short" ("Save as short text file": bare values) or "ooTextFile short" (the older short layout whose
    header is ``File type = "ooTextFile short"`` and then ``"TextGrid"``). Times are written with `repr`,
    the shortest text that reads back as the same float; quotes in labels are doubled as Praat does. A
    point tier ("TextTier") writes the first time of each (time, time, mark) item.
    """
    if style not in STYLES:
        raise ValueError(f"unknown TextGrid style {style!r}; expected one of {', '.join(STYLES)}")

    def num(value: float) -> str:
        return repr(float(value))

    def quoted(text: str) -> str:
        return '"' + str(text).replace('"', '""') + '"'

    for tier in tiers:
        if tier.kind not in ("IntervalTier", "TextTier"):
            raise ValueError(f"tier {tier.name!r} has unknown class {tier.kind!r}; expected IntervalTier or TextTier")
    if style != "long":
        header = ['File type = "ooTextFile short"', '"TextGrid"'] if style == "ooTextFile short" else [
            'File type = "ooTextFile"', 'Object class = "TextGrid"']
        lines = [*header, "", num(xmin), num(xmax)]
        if not tiers:
            return "\n".join([*lines, "<absent>"]) + "\n"
        lines += ["<exists>", str(len(tiers))]
        for tier in tiers:
            lines += [quoted(tier.kind), quoted(tier.name), num(tier.start_s), num(tier.end_s), str(len(tier.items))]
            for a, b, text in tier.items:
                lines += [num(a), num(b), quoted(text)] if tier.kind == "IntervalTier" else [num(a), quoted(text)]
        return "\n".join(lines) + "\n"

    lines = ['File type = "ooTextFile"', 'Object class = "TextGrid"', "", f"xmin = {num(xmin)} ", f"xmax = {num(xmax)} "]
    if not tiers:
        lines.append("tiers? <absent> ")
        return "\n".join(lines) + "\n"
    lines += ["tiers? <exists> ", f"size = {len(tiers)} ", "item []: "]
    for t, tier in enumerate(tiers, start=1):
        interval = tier.kind == "IntervalTier"
        lines += [
            f"    item [{t}]:", f"        class = {quoted(tier.kind)} ", f"        name = {quoted(tier.name)} ",
            f"        xmin = {num(tier.start_s)} ", f"        xmax = {num(tier.end_s)} ",
            f"        {'intervals' if interval else 'points'}: size = {len(tier.items)} ",
        ]
        for i, (a, b, text) in enumerate(tier.items, start=1):
            if interval:
                lines += [f"        intervals [{i}]:", f"            xmin = {num(a)} ", f"            xmax = {num(b)} ",
                          f"            text = {quoted(text)} "]
            else:
                lines += [f"        points [{i}]:", f"            number = {num(a)} ", f"            mark = {quoted(text)} "]
    return "\n".join(lines) + "\n"


# The largest alignment file read (TextGrid, XRA, HTK label, word alignment): about 600,000 intervals, 11 hours of
# phones. Parsing holds about 5 times the file in memory (a 20-MB TextGrid of 200,000 intervals: 105 MB, 3.5 s).
MAX_ALIGNMENT_BYTES = 64 << 20


def alignment_size_error(path: str, size: int) -> str | None:
    """Why an alignment file of `size` bytes is not read, or None."""
    if size <= MAX_ALIGNMENT_BYTES:
        return None
    return (f"{size} bytes, more than the {MAX_ALIGNMENT_BYTES} an alignment file may have (hours of phones): split "
            "the recording into utterances, or the file is not an alignment")


def read_textgrid(path: str | os.PathLike) -> TextGridData:
    """Read a TextGrid file in any format Praat writes (text variants and binary); errors name the file."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as fh:
            too_big = alignment_size_error(path, os.fstat(fh.fileno()).st_size)
            if too_big:
                raise TextGridError(f"{path}: {too_big}")
            data = fh.read(MAX_ALIGNMENT_BYTES + 1)
    except OSError as exc:
        raise TextGridError(f"{path}: cannot read: {exc.strerror}") from exc
    if len(data) > MAX_ALIGNMENT_BYTES:     # grew while read, or a pipe
        raise TextGridError(f"{path}: {alignment_size_error(path, len(data))}")
    return parse_textgrid_bytes(data, path)
