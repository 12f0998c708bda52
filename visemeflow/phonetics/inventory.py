"""Aligner phone labels (ARPAbet, IPA, pinyin) mapped onto the 16 visemes of paper Fig. 2.

The tables live in `phonetics/data/<inventory>.csv` (columns symbol, visemes, origin, note);
docs/phonemes.md explains every rule and every choice that is not in Fig. 2.
"""

from __future__ import annotations

import csv
import io
import math
import re
import unicodedata
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from functools import cache, lru_cache
from importlib import resources
from types import MappingProxyType
from typing import Final

from visemeflow.visemes import VISEMES

INVENTORIES: Final[tuple[str, ...]] = ("arpabet", "ipa", "pinyin")

_SILENCE_BASE = (
    "", "sil", "sp", "spn", "[sil]", "[sp]", "<eps>", "<sil>", "<sp>", "pau", "#",
    "h#", "epi", "silence",
)
# Lower- and upper-case spellings so membership tests work as written; is_silence casefolds anyway.
SILENCE_LABELS: Final[frozenset[str]] = frozenset(_SILENCE_BASE) | {s.upper() for s in _SILENCE_BASE}
_SILENCE_FOLDED: Final[frozenset[str]] = frozenset(s.casefold() for s in SILENCE_LABELS)

Visemes = tuple[tuple[str, float], ...]


class UnknownPhonemeError(ValueError):
    """A phone label that the chosen inventory has no row for."""

    def __init__(self, symbol: str, inventory: str) -> None:
        self.symbol = symbol
        self.inventory = inventory
        super().__init__(
            f"unknown phone {symbol!r} in inventory {inventory!r}; "
            f"add a row to visemeflow/phonetics/data/{inventory}.csv (see docs/phonemes.md)"
        )

    def __reduce__(self):  # keeps the two-argument constructor picklable (Prefect ships exceptions)
        return (type(self), (self.symbol, self.inventory))


@dataclass(frozen=True, slots=True)
class PhonemeMapping:
    """One phone label resolved to its normalised phoneme and weighted viseme sequence."""

    label: str
    phoneme: str
    stress: int | None
    visemes: Visemes
    is_silence: bool


@dataclass(frozen=True, slots=True)
class _Row:
    """One CSV row: the viseme sequence, `paper` or `choice`, and the reason."""

    visemes: Visemes
    origin: str
    note: str


def is_silence(label: str) -> bool:
    """True for pause/silence/noise labels of any aligner, compared case-insensitively."""
    return label.strip().casefold() in _SILENCE_FOLDED


def _parse_visemes(cell: str, where: str) -> Visemes:
    """Parse `AHH:2 UUU:1` into ((AHH, 2.0), (UUU, 1.0)); checks names and weights."""
    out = []
    for item in cell.split():
        name, _, weight = item.partition(":")
        value = float(weight) if weight else 1.0
        if name not in VISEMES or not (math.isfinite(value) and value > 0):
            raise ValueError(f"{where}: bad viseme item {item!r}")
        out.append((name, value))
    return tuple(out)


def _check_inventory(inventory: str) -> None:
    """Raise ValueError for a name outside INVENTORIES."""
    if inventory not in INVENTORIES:
        raise ValueError(f"unknown inventory {inventory!r}; expected one of {', '.join(INVENTORIES)}")


@cache
def _table(inventory: str) -> Mapping[str, _Row]:
    """The inventory's CSV as symbol -> row, read once from the package data."""
    _check_inventory(inventory)
    text = resources.files("visemeflow.phonetics").joinpath("data", f"{inventory}.csv").read_text("utf-8")
    table: dict[str, _Row] = {}
    for n, rec in enumerate(csv.DictReader(io.StringIO(text)), start=2):
        symbol = unicodedata.normalize("NFC", rec["symbol"].strip())
        where = f"{inventory}.csv line {n}"
        if symbol in table or rec["origin"] not in ("paper", "choice"):
            raise ValueError(f"{where}: duplicate symbol or bad origin {rec['origin']!r}")
        table[symbol] = _Row(_parse_visemes(rec["visemes"], where), rec["origin"], rec["note"])
    return MappingProxyType(table)


def inventory_symbols(inventory: str) -> frozenset[str]:
    """Every symbol the inventory's table has a row for."""
    return frozenset(_table(inventory))


# --- ARPAbet ---------------------------------------------------------------------------------

_ARPABET_LABEL = re.compile(r"^([A-Z][A-Z-]*?)([012])?$")


def _map_arpabet(label: str) -> PhonemeMapping | None:
    """ARPAbet: case-insensitive, optional stress digit; a row with the digit (AH0) wins."""
    m = _ARPABET_LABEL.match(label.strip().upper())
    if m is None:
        return None
    base, digit = m.group(1), m.group(2)
    table = _table("arpabet")
    row = table.get(base + (digit or "")) or table.get(base)
    if row is None:
        return None
    return PhonemeMapping(label, base, int(digit) if digit else None, row.visemes, False)


# --- IPA -------------------------------------------------------------------------------------

_CEDILLA = "\u0327"  # kept: NFD splits ç into c + cedilla, and ç is its own symbol
_MODIFIERS_STRIPPED = frozenset(
    "ʰʱʷʲˠˤⁿˡˑˈˌ˞ʼ"  # aspiration, labial./palatal./velar./pharyngealisation, releases, half-long, stress, rhotic hook, ejective
)
_LIGATURES = {"ʧ": "tʃ", "ʤ": "dʒ", "ʦ": "ts", "ʣ": "dz", "ʨ": "tɕ", "ʥ": "dʑ", "ɡ": "g", ":": "ː"}


def _strip_ipa_char(ch: str) -> bool:
    """True for a diacritic that does not change the viseme (tie bars, syllabic, nasal, ...)."""
    if ch in _MODIFIERS_STRIPPED:
        return True
    return unicodedata.combining(ch) != 0 and ch != _CEDILLA


def normalize_ipa(label: str) -> str:
    """NFD, drop viseme-neutral diacritics, expand ligatures, ɡ -> g, ':' -> 'ː', NFC, lower case."""
    decomposed = unicodedata.normalize("NFD", label.strip())
    kept = "".join(_LIGATURES.get(ch, ch) for ch in decomposed if not _strip_ipa_char(ch))
    return unicodedata.normalize("NFC", kept).lower()


def _map_ipa(label: str) -> PhonemeMapping | None:
    """IPA: the normalised symbol with its length mark first, then without it."""
    symbol = normalize_ipa(label)
    table = _table("ipa")
    for candidate in (symbol, symbol.replace("ː", "")):
        if candidate and candidate in table:
            return PhonemeMapping(label, candidate, None, table[candidate].visemes, False)
    return None


# --- pinyin ----------------------------------------------------------------------------------

_PINYIN_LABEL = re.compile(r"^(\D+?)([1-5])?$")


def _normalize_pinyin(label: str) -> str:
    """NFC, lower case, ü / u: written as v."""
    text = unicodedata.normalize("NFC", label.strip()).lower()
    return text.replace("ü", "v").replace("u:", "v")


def _map_pinyin(label: str) -> PhonemeMapping | None:
    """Pinyin: initials and finals, an optional tone digit 1-5 that goes to `stress`."""
    m = _PINYIN_LABEL.match(_normalize_pinyin(label))
    if m is None or m.group(1) not in _table("pinyin"):
        return None
    tone = int(m.group(2)) if m.group(2) else None
    return PhonemeMapping(label, m.group(1), tone, _table("pinyin")[m.group(1)].visemes, False)


_MAPPERS = {"arpabet": _map_arpabet, "ipa": _map_ipa, "pinyin": _map_pinyin}


@lru_cache(maxsize=65536)
def _try_map(label: str, inventory: str) -> PhonemeMapping | None:
    """The mapping, a silence mapping, or None when the symbol is unknown (memoised: corpora reuse few labels)."""
    _check_inventory(inventory)
    if is_silence(label):
        return PhonemeMapping(label, "", None, (), True)
    return _MAPPERS[inventory](label)


def map_phone(label: str, inventory: str) -> PhonemeMapping:
    """Map one aligner label; raises UnknownPhonemeError when the inventory has no row for it."""
    mapping = _try_map(label, inventory)
    if mapping is None:
        raise UnknownPhonemeError(label, inventory)
    return mapping


def detect_inventory(labels: Iterable[str], language: str | None = None) -> str:
    """The first inventory that maps every label, else the one with the fewest unknown labels."""
    labels = [label for label in labels if not is_silence(label)]
    chinese = language is not None and language.strip().lower().startswith(("zh", "cmn"))
    order = ("pinyin", "arpabet", "ipa") if chinese else INVENTORIES
    distinct = set(labels)
    unknowns: dict[str, int] = {}
    for inv in order:
        unknowns[inv] = sum(_try_map(label, inv) is None for label in distinct)
        if unknowns[inv] == 0:
            return inv
    return min(order, key=lambda inv: unknowns[inv])  # min keeps the earliest on ties


def split_interval(start_s: float, end_s: float, weights: Sequence[float]) -> list[tuple[float, float]]:
    """Contiguous sub-spans of [start_s, end_s] proportional to `weights`, covering it exactly."""
    if not weights or any(not (math.isfinite(w) and w > 0) for w in weights):
        raise ValueError(f"weights must be a non-empty sequence of positive numbers, got {list(weights)!r}")
    if not end_s >= start_s:
        raise ValueError(f"interval end {end_s} is before its start {start_s}")
    start_s, end_s = float(start_s), float(end_s)
    total = math.fsum(weights)
    span = end_s - start_s
    cuts, acc = [start_s], 0.0
    for w in weights[:-1]:
        acc += w
        # min() keeps rounding from pushing a cut past end_s; cuts stay non-decreasing
        cuts.append(min(max(start_s + span * (acc / total), cuts[-1]), end_s))
    cuts.append(end_s)
    return list(zip(cuts[:-1], cuts[1:]))
