"""HTK label files (`.lab`, `.rec`) and master label files (`.mlf`) as phone and word tiers.

An HTK label line is `[start [end]] name [score] [auxname [auxscore]] ...` with times in units of 100 ns
(HTK book, "Label files"): `0 2300000 sil`, `2300000 3100000 h -512.3 hello` (HVite's phone alignment, the
word on the first phone of each word). A line `///` starts an alternative transcription: only the first is
read. WaveSurfer and other `.lab` writers put times in seconds (`0.000000 0.230000 sil`): a time with a
decimal point or an exponent makes the whole file seconds; a file mixing both is refused.

A master label file (MLF) starts with `#!MLF!#` and holds one entry per utterance: a quoted file-name
pattern (`"*/a01.lab"`, `"a01.rec"`, `"/data/spk1/a01.lab"`), its label lines, and a line holding only `.`.
`*` and `?` (and HTK's `%`, one character) are wildcards, matched without backtracking (`wildcard_match`:
at most pattern x name steps, whatever the pattern); an utterance is found by its file stem (the
pattern's last component without extension) and, when the pattern names a folder that is not a wildcard,
its folder (the speaker); the first matching entry wins, as in HTK. Entries that point elsewhere
(`"*/a.lab" -> dir`, `=> file`) are not followed: an utterance that needs one is a reject.

Both give the same tiers the TextGrid reader gives: a `phones` interval tier and a `words` tier built from
the word names (a word runs from its first phone to the last phone before the next word or silence).
Every error names the file and the line.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from visemeflow.phonetics.inventory import is_silence
from visemeflow.phonetics.textgrid import TextGridData, Tier

HTK_UNITS_PER_S = 10_000_000
"""HTK times are integers in units of 100 ns."""
MLF_HEADER = "#!MLF!#"
# word names that mark sentence ends or null words in HTK dictionaries, never spoken words
NON_WORDS = frozenset({"SENT-START", "SENT-END", "!ENTER", "!EXIT", "!NULL", "<s>", "</s>"})

_FLOAT = re.compile(r"^[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?$")


class LabelFileError(ValueError):
    """A label file or MLF that cannot be read; the message names the file and the line."""


@dataclass(frozen=True, slots=True)
class _Line:
    number: int
    start: str
    end: str
    label: str
    word: str | None


def _unquote(token: str) -> str:
    if len(token) >= 2 and token[0] == token[-1] and token[0] in "'\"":
        return token[1:-1]
    return token


def _split_line(line: str, number: int, source: str) -> _Line:
    tokens = line.split()
    times = 0
    while times < min(2, len(tokens)) and _FLOAT.match(tokens[times]):
        times += 1
    if times < 2:
        raise LabelFileError(
            f"{source}:{number}: expected 'start end label [score] [word]', found {line.strip()!r}; a label "
            "without both times (a transcription) cannot be used as an alignment")
    if len(tokens) < 3:
        raise LabelFileError(f"{source}:{number}: no label after the times in {line.strip()!r}")
    rest = tokens[3:]
    if rest and _FLOAT.match(rest[0]):
        rest = rest[1:]  # the score
    word = _unquote(rest[0]) if rest else None
    return _Line(number, tokens[0], tokens[1], _unquote(tokens[2]), word)


def _tiers(lines: list[_Line], source: str) -> TextGridData:
    """Phone and word tiers of label lines (in seconds or 100 ns units, decided for the whole file)."""
    if not lines:
        raise LabelFileError(f"{source}: no labels")
    seconds = [("." in t or "e" in t.lower()) for x in lines for t in (x.start, x.end)]
    if any(seconds) and not all(seconds):
        first = next(x for x in lines if any("." in t or "e" in t.lower() for t in (x.start, x.end)))
        raise LabelFileError(f"{source}:{first.number}: times in seconds (with a decimal point) mixed with HTK "
                             "integer times in 100 ns units in one file")
    # 100 ns integers divided by 10**7 (one correctly rounded operation: 1000000 -> 0.1, not 0.09999999999999999)
    to_s = float if all(seconds) else (lambda t: int(t) / HTK_UNITS_PER_S)
    phones: list[tuple[float, float, str]] = []
    words: list[tuple[float, float, str]] = []
    open_word: list | None = None  # [start, end, name]
    for x in lines:
        try:
            start, end = to_s(x.start), to_s(x.end)
        except OverflowError:
            raise LabelFileError(f"{source}:{x.number}: time out of range in {x.start} {x.end}") from None
        if not (math.isfinite(start) and math.isfinite(end)):
            raise LabelFileError(f"{source}:{x.number}: time out of range in {x.start} {x.end}")
        phones.append((start, end, x.label))
        word = x.word if x.word is not None and x.word not in NON_WORDS and not is_silence(x.word) else None
        if word is not None or is_silence(x.label) or (x.word is not None and word is None):
            if open_word is not None:
                words.append(tuple(open_word))
                open_word = None
        if word is not None:
            open_word = [start, end, word]
        elif open_word is not None:
            open_word[1] = end
    if open_word is not None:
        words.append(tuple(open_word))
    end_s = max(b for _, b, _ in phones)
    return TextGridData(0.0, end_s, (Tier("phones", "IntervalTier", 0.0, end_s, tuple(phones)),
                                     Tier("words", "IntervalTier", 0.0, end_s, tuple(words))))


def _label_lines(lines: list[str], first_number: int, source: str) -> list[_Line]:
    out: list[_Line] = []
    for offset, line in enumerate(lines):
        text = line.strip()
        if not text:
            continue
        if text == "///":
            break  # an alternative transcription follows; the first one is the alignment
        out.append(_split_line(text, first_number + offset, source))
    return out


def parse_htk_label(text: str, source: str = "<string>") -> TextGridData:
    """Tiers `phones` and `words` of an HTK label file (or a WaveSurfer-style `.lab` in seconds)."""
    lines = text.splitlines()
    if lines and lines[0].strip() == MLF_HEADER:
        raise LabelFileError(f"{source}:1: a master label file (#!MLF!#), not a single label file")
    return _tiers(_label_lines(lines, 1, source), source)


def looks_like_htk_label(path: str | os.PathLike) -> bool:
    """Whether a `.lab` file starts with a `start end label` line (else it is a transcript, as MFA's .lab)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return True  # unreadable: let ingest report it, naming the file
    for line in head.decode("utf-8", errors="replace").splitlines():
        tokens = line.split()
        if tokens:
            return len(tokens) >= 3 and bool(_FLOAT.match(tokens[0])) and bool(_FLOAT.match(tokens[1]))
    return False


# --- master label files ------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class MlfEntry:
    """One entry of an MLF: its pattern, the line the pattern is on, its label lines, or where it points."""

    pattern: str
    line: int
    lines: tuple[str, ...]
    redirect: str | None = None

    @property
    def text(self) -> str:
        return "\n".join(self.lines)


_PATTERN_LINE = re.compile(r'^"((?:[^"\\]|\\.)*)"\s*(?:(->|=>)\s*(\S.*?))?\s*$')


def parse_mlf(text: str, source: str = "<string>") -> tuple[MlfEntry, ...]:
    """The entries of an MLF, checked for layout (header, quoted patterns, a `.` ending every entry)."""
    lines = text.splitlines()
    n = 0
    while n < len(lines) and not lines[n].strip():
        n += 1
    if n >= len(lines) or lines[n].strip() != MLF_HEADER:
        raise LabelFileError(f"{source}:{n + 1}: not an HTK master label file (the first line must be {MLF_HEADER})")
    n += 1
    entries: list[MlfEntry] = []
    while n < len(lines):
        text_line = lines[n].strip()
        if not text_line:
            n += 1
            continue
        m = _PATTERN_LINE.match(text_line)
        if m is None:
            raise LabelFileError(f"{source}:{n + 1}: expected a quoted file name pattern (\"*/name.lab\"), found "
                                 f"{text_line!r}")
        pattern, arrow, target = m.group(1).replace('\\"', '"'), m.group(2), m.group(3)
        if arrow:
            entries.append(MlfEntry(pattern, n + 1, (), f"{arrow} {target}"))
            n += 1
            continue
        start = n + 1
        n += 1
        while n < len(lines) and lines[n].strip() != ".":
            if _PATTERN_LINE.match(lines[n].strip()):
                raise LabelFileError(f"{source}:{n + 1}: a new pattern before the '.' that ends the entry "
                                     f"{pattern!r} of line {start}")
            n += 1
        if n >= len(lines):
            raise LabelFileError(f"{source}:{start}: the entry {pattern!r} does not end with a line holding '.'")
        entries.append(MlfEntry(pattern, start, tuple(lines[start:n])))
        n += 1
    return tuple(entries)


def wildcard_match(pattern: str, name: str) -> bool:
    """Whether `name` matches HTK's pattern syntax whole: * any run, ? and % one character, all else literal.

    Greedy, remembering only the last `*`: at most len(pattern) x len(name) steps. A regex translation
    backtracks over every way of splitting the name between the stars: a crafted MLF pattern ("*a*a*...*b"
    against a 60-character name) then runs for hours.
    """
    p = n = 0
    star, resume = -1, 0  # the last `*` seen and the name position it has swallowed up to
    while n < len(name):
        if p < len(pattern) and pattern[p] != "*" and pattern[p] in ("?", "%", name[n]):
            p, n = p + 1, n + 1
        elif p < len(pattern) and pattern[p] == "*":
            star, resume = p, n
            p += 1
        elif star >= 0:
            resume += 1
            p, n = star + 1, resume
        else:
            return False
    return all(ch == "*" for ch in pattern[p:])


@dataclass(frozen=True, slots=True)
class _Key:
    stem: str
    folder: str | None
    literal_stem: str | None


def _key(pattern: str) -> _Key:
    parts = re.split(r"[/\\]", pattern)
    base = parts[-1]
    stem = base.rsplit(".", 1)[0] if "." in base else base
    folder = parts[-2] if len(parts) >= 2 and parts[-2] not in ("", "*") else None
    literal = stem if not any(ch in stem for ch in "*?%") else None
    return _Key(stem, folder, literal)


class MlfIndex:
    """An MLF's entries, looked up by (folder, stem) as HTK would: the first matching pattern wins."""

    def __init__(self, entries: tuple[MlfEntry, ...], source: str):
        self.entries, self.source = entries, source
        self._keys = [_key(e.pattern) for e in entries]
        self._by_stem: dict[str, list[int]] = {}
        self._wild: list[int] = []
        for i, key in enumerate(self._keys):
            if key.literal_stem is not None:
                self._by_stem.setdefault(key.literal_stem, []).append(i)
            else:
                self._wild.append(i)

    def find(self, folder: str, stem: str) -> MlfEntry | None:
        for i in sorted(self._by_stem.get(stem, []) + self._wild):
            key = self._keys[i]
            if wildcard_match(key.stem, stem) and (key.folder is None or wildcard_match(key.folder, folder)):
                return self.entries[i]
        return None

    def tiers(self, folder: str, stem: str) -> TextGridData:
        """The phone and word tiers of the utterance `folder/stem`; LabelFileError when it has no usable entry."""
        entry = self.find(folder, stem)
        if entry is None:
            raise LabelFileError(f"{self.source}: no entry matches {folder}/{stem} (patterns such as "
                                 f"\"*/{stem}.lab\" or \"{stem}.rec\")")
        if entry.redirect is not None:
            raise LabelFileError(f"{self.source}:{entry.line}: the entry {entry.pattern!r} points elsewhere "
                                 f"({entry.redirect}); put the labels into the MLF itself")
        return _tiers(_label_lines(list(entry.lines), entry.line + 1, self.source), self.source)


@lru_cache(maxsize=8)
def _load(path: str, mtime_ns: int, size: int) -> MlfIndex:
    data = Path(path).read_bytes()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        text = data.decode("latin-1")
    return MlfIndex(parse_mlf(text, path), path)


def load_mlf(path: str | os.PathLike) -> MlfIndex:
    """The index of an MLF file, parsed once per process while the file is unchanged (a large MLF serves many
    utterances); LabelFileError naming the file and line when it is malformed, OSError when unreadable."""
    path = os.fspath(path)
    st = os.stat(path)
    return _load(path, st.st_mtime_ns, st.st_size)
