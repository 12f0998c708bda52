"""SPPAS `.xra` annotation files (XML) as the tiers the TextGrid reader gives.

XRA (SPPAS's own format, versions 1.1 to 1.5) is a `Document` holding `Tier` elements named by their
`tiername` attribute (SPPAS's phone alignment is `PhonAlign`, its words `TokensAlign`). Each `Annotation`
has a `Location` and a `Label`:

- version 1.3 and later: `Location/Interval/Begin|End` or `Location/Point`, each time a `midpoint`
  attribute in seconds (`radius`, the vagueness, is ignored); `Label/Tag` holds the text;
- versions 1.1 and 1.2: `Location/Localization/TimeInterval|Timeinterval/Begin|End` or `.../TimePoint|Timepoint`,
  and `Label/Text`.

Several `Interval`/`Localization` alternatives, or several `Tag`/`Text`s, each carry a `score`: the
highest-scored one is read (the first on ties). Several `Label`s in one annotation are joined with a space.
A tier with points only is a point tier (`TextTier`). `Tier` elements without `tiername` (references inside
`Media`, `Vocabulary`) are not tiers. The file is read with the standard library (xml.etree's pull parser, so
that every error names the file and the line of the element it is about). XRA has no file end time: the end
is the last annotation's end.
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET

from visemeflow.phonetics.textgrid import TextGridData, Tier


class XraError(ValueError):
    """An XRA file that cannot be read; the message names the file and the line."""


def _local(tag: str) -> str:
    """The tag without an XML namespace."""
    return tag.rsplit("}", 1)[-1]


def _children(element: ET.Element, *names: str) -> list[ET.Element]:
    return [c for c in element if _local(c.tag) in names]


def _score(element: ET.Element, source: str, line: int) -> float:
    raw = element.get("score")
    if raw is None:
        return 1.0
    try:
        return float(raw)
    except ValueError:
        raise XraError(f"{source}:{line}: score {raw!r} is not a number") from None


def _best(elements: list[ET.Element], source: str, lines: dict[int, int]) -> ET.Element:
    """The highest-scored element (the first on ties)."""
    return max(enumerate(elements), key=lambda ie: (_score(ie[1], source, lines.get(id(ie[1]), 0)), -ie[0]))[1]


def _parse_tree(data: bytes, source: str) -> tuple[ET.Element, dict[int, int]]:
    """The document root and the line of every element (the line being fed when its start tag was read)."""
    parser = ET.XMLPullParser(events=("start",))
    lines: dict[int, int] = {}
    root = None
    line = 1
    try:
        for chunk in data.splitlines(keepends=True):
            parser.feed(chunk)
            for _, element in parser.read_events():
                lines[id(element)] = line
                if root is None:
                    root = element
            line += 1
        parser.close()
        for _, element in parser.read_events():
            lines.setdefault(id(element), line)
    except ET.ParseError as exc:
        at, column = exc.position
        raise XraError(f"{source}:{at}:{column}: malformed XML: {exc}") from exc
    if root is None:
        raise XraError(f"{source}:1: empty file, no XML document")
    return root, lines


def _time(element: ET.Element | None, what: str, source: str, line: int) -> float:
    if element is None:
        raise XraError(f"{source}:{line}: {what} is missing")
    raw = element.get("midpoint")
    try:
        value = float(raw)
    except (TypeError, ValueError):
        raise XraError(f"{source}:{line}: {what} has no numeric midpoint (found {raw!r})") from None
    if not math.isfinite(value):
        raise XraError(f"{source}:{line}: {what} midpoint {raw!r} is not finite")
    return value


def _location(annotation: ET.Element, source: str, lines: dict[int, int]) -> tuple[float, float, bool]:
    """(start, end, is_point) of an annotation's best-scored localization."""
    where = lines.get(id(annotation), 0)
    location = _children(annotation, "Location")
    if not location:
        raise XraError(f"{source}:{where}: annotation without a Location")
    options = _children(location[0], "Interval", "Point", "Localization")
    if not options:
        raise XraError(f"{source}:{where}: Location without an Interval, Point or Localization")
    best = _best(options, source, lines)
    if _local(best.tag) == "Localization":  # XRA 1.1/1.2
        inner = _children(best, "TimeInterval", "Timeinterval", "TimePoint", "Timepoint")
        if not inner:
            raise XraError(f"{source}:{lines.get(id(best), where)}: Localization without a time interval or point")
        best = inner[0]
    line = lines.get(id(best), where)
    if _local(best.tag) in ("Point", "TimePoint", "Timepoint"):
        t = _time(best, "the point", source, line)
        return t, t, True
    begin = next(iter(_children(best, "Begin")), None)
    end = next(iter(_children(best, "End")), None)
    return _time(begin, "Begin", source, line), _time(end, "End", source, line), False


def _label(annotation: ET.Element, source: str, lines: dict[int, int]) -> str:
    texts = []
    for label in _children(annotation, "Label"):
        tags = _children(label, "Tag", "Text")
        if tags:
            texts.append((_best(tags, source, lines).text or "").strip())
    return " ".join(t for t in texts if t)


def parse_xra(data: bytes, source: str = "<bytes>") -> TextGridData:
    """The tiers of an XRA document (any version SPPAS writes), by name, in file order."""
    root, lines = _parse_tree(data, source)
    if _local(root.tag) != "Document":
        raise XraError(f"{source}:{lines.get(id(root), 1)}: not an XRA file (root element {_local(root.tag)!r}, "
                       "expected Document)")
    tiers: list[Tier] = []
    for tier in _children(root, "Tier"):
        name = tier.get("tiername")
        if name is None:
            continue
        items: list[tuple[float, float, str]] = []
        points = 0
        for annotation in _children(tier, "Annotation"):
            start, end, is_point = _location(annotation, source, lines)
            points += is_point
            items.append((start, end, _label(annotation, source, lines)))
        if points and points != len(items):
            raise XraError(f"{source}:{lines.get(id(tier), 0)}: tier {name!r} mixes points and intervals")
        kind = "TextTier" if items and points == len(items) else "IntervalTier"
        start = min((a for a, _, _ in items), default=0.0)
        end = max((b for _, b, _ in items), default=0.0)
        tiers.append(Tier(name, kind, start, end, tuple(items)))
    if not tiers:
        raise XraError(f"{source}: no tier (no Tier element with a tiername)")
    end_s = max(t.end_s for t in tiers)
    return TextGridData(0.0, end_s, tuple(tiers))


def read_xra(path: str | os.PathLike) -> TextGridData:
    path = os.fspath(path)
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError as exc:
        raise XraError(f"{path}: cannot read: {exc.strerror}") from exc
    return parse_xra(data, path)
