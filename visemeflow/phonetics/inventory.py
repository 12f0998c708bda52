"""Aligner phone labels (ARPAbet, IPA, X-SAMPA/SAMPA, pinyin) mapped onto the 16 visemes of paper Fig. 2.

The viseme tables live in `phonetics/data/<inventory>.csv` (columns symbol, visemes, origin, note) for
ARPAbet, IPA and pinyin. X-SAMPA has no viseme table of its own: `data/xsampa.csv` (columns xsampa, ipa,
kind, note) turns a label into IPA, and the IPA table maps it. docs/phonemes.md explains every rule and
every choice that is not in Fig. 2.
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

INVENTORIES: Final[tuple[str, ...]] = ("arpabet", "ipa", "xsampa", "pinyin")
"""Every inventory, in the order `detect_inventory` tries them by default."""
VISEME_TABLES: Final[tuple[str, ...]] = ("arpabet", "ipa", "pinyin")
"""Inventories with a viseme table `data/<name>.csv`; X-SAMPA goes through IPA (`data/xsampa.csv`)."""

_SILENCE_BASE = (
    "", "sil", "sp", "spn", "[sil]", "[sp]", "<eps>", "<sil>", "<sp>", "pau", "#",
    "h#", "epi", "silence",
    # SPPAS: pause, short pause, noise, laughter, untranscribed, garbage (its models' names and their output labels)
    "+", "*", "@@", "dummy", "noise", "laugh", "gb", "lg",
    # MAUS input markers of noise and silence; its output markers (<p:>, <usb>, <nib> ...) are <...> labels
    "(.)", "(..)", "(...)",
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


_MARKER = re.compile(r"^<[^<>]*>$")


def is_silence(label: str) -> bool:
    """True for pause/silence/noise labels of any aligner, compared case-insensitively.

    Besides `SILENCE_LABELS`, every label in angle brackets is a marker, not a phone: MAUS writes `<p:>`
    (pause), `<usb>`, `<nib>` and others, Kaldi and HTK `<eps>`, `<sil>`.
    """
    label = label.strip()
    return label.casefold() in _SILENCE_FOLDED or _MARKER.match(label) is not None


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
    if inventory not in VISEME_TABLES:
        raise ValueError(f"inventory {inventory!r} has no viseme table of its own (it maps through IPA)")
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
    """Every symbol the inventory's table has a row for (for X-SAMPA: the symbols of its IPA table)."""
    _check_inventory(inventory)
    if inventory == "xsampa":
        return frozenset(xsampa_table())
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


# --- X-SAMPA ---------------------------------------------------------------------------------

XSAMPA_KINDS: Final[frozenset[str]] = frozenset({"segment", "diacritic", "prosody", "sppas"})


@dataclass(frozen=True, slots=True)
class XsampaSymbol:
    """One row of data/xsampa.csv: the IPA it stands for and what kind of symbol it is."""

    ipa: str
    kind: str
    note: str


@cache
def xsampa_table() -> Mapping[str, XsampaSymbol]:
    """data/xsampa.csv as symbol -> row (lines starting with # are comments), read once."""
    text = resources.files("visemeflow.phonetics").joinpath("data", "xsampa.csv").read_text("utf-8")
    lines = [line for line in text.splitlines(keepends=True) if not line.startswith("#")]
    table: dict[str, XsampaSymbol] = {}
    for n, rec in enumerate(csv.DictReader(lines), start=2):
        symbol, ipa, kind = rec["xsampa"], unicodedata.normalize("NFC", rec["ipa"]), rec["kind"]
        if not symbol or symbol != symbol.strip() or symbol in table or kind not in XSAMPA_KINDS \
                or (kind != "prosody") != bool(ipa):
            raise ValueError(f"xsampa.csv data line {n}: empty, padded or duplicate symbol {symbol!r}, bad kind "
                             f"{kind!r}, or an IPA value that does not fit the kind ({ipa!r})")
        table[symbol] = XsampaSymbol(ipa, kind, rec["note"])
    return MappingProxyType(table)


@cache
def _xsampa_longest() -> int:
    return max(len(symbol) for symbol in xsampa_table())


def xsampa_to_ipa(label: str) -> str | None:
    """The IPA of an X-SAMPA label, read left to right taking the longest symbol that matches (`tS` is t then
    ʃ, `r\\`` one symbol, `aI` a then ɪ); None when some part is no X-SAMPA symbol. Case matters."""
    table, longest = xsampa_table(), _xsampa_longest()
    text, pos, out = label.strip(), 0, []
    while pos < len(text):
        for size in range(min(longest, len(text) - pos), 0, -1):
            row = table.get(text[pos:pos + size])
            if row is not None:
                out.append(row.ipa)
                pos += size
                break
        else:
            return None
    return unicodedata.normalize("NFC", "".join(out))


def _map_xsampa(label: str) -> PhonemeMapping | None:
    """X-SAMPA: converted to IPA, then the IPA table (with its normalisation) decides."""
    ipa = xsampa_to_ipa(label)
    if not ipa:
        return None
    mapping = _map_ipa(ipa)
    if mapping is None:
        return None
    return PhonemeMapping(label, mapping.phoneme, None, mapping.visemes, False)


_MAPPERS = {"arpabet": _map_arpabet, "ipa": _map_ipa, "xsampa": _map_xsampa, "pinyin": _map_pinyin}


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


# X-SAMPA marks that no ARPAbet, IPA or pinyin label holds (':' is left out: pinyin writes u: and IPA a colon)
_SAMPA_MARKS = frozenset('@{}\\`"%=~&|?')


def looks_like_sampa(labels: Iterable[str]) -> bool:
    """Whether phone labels carry X-SAMPA's marks (`@`, `{`, a backslash ...) or mix upper- and lower-case
    ASCII letters (`D V m`, `aI`): X-SAMPA is case-sensitive, while ARPAbet is written in one case and IPA
    and pinyin in lower case. Silence labels are ignored."""
    upper = lower = False
    for label in labels:
        if is_silence(label):
            continue
        if any(ch in _SAMPA_MARKS for ch in label):
            return True
        upper = upper or any("A" <= ch <= "Z" for ch in label)
        lower = lower or any("a" <= ch <= "z" for ch in label)
    return upper and lower


def inventory_order(labels: Sequence[str], language: str | None = None) -> tuple[str, ...]:
    """The order `detect_inventory` tries: pinyin first for a Chinese `language` (zh..., cmn...), X-SAMPA
    first for labels that look like SAMPA (`looks_like_sampa`), else `INVENTORIES`."""
    if language is not None and language.strip().lower().startswith(("zh", "cmn")):
        return ("pinyin", "arpabet", "ipa", "xsampa")
    if looks_like_sampa(labels):
        return ("xsampa", "arpabet", "ipa", "pinyin")
    return INVENTORIES


@dataclass(frozen=True, slots=True)
class InventoryTrial:
    """How one inventory did on an utterance's labels: how many distinct labels it does not know, and the
    first of them (`index` into the labels as given); `first_unknown` is None when it maps them all."""

    inventory: str
    unknown: int
    first_unknown: str | None
    index: int | None


def try_inventories(labels: Sequence[str], language: str | None = None) -> tuple[InventoryTrial, ...]:
    """Each inventory of `inventory_order` in turn, up to the first that maps every (non-silence) label."""
    labels = list(labels)
    trials: list[InventoryTrial] = []
    for inv in inventory_order(labels, language):
        unknown, first = set(), None
        for i, label in enumerate(labels):
            if _try_map(label, inv) is None:
                if first is None:
                    first = i
                unknown.add(label)
        trials.append(InventoryTrial(inv, len(unknown), None if first is None else labels[first], first))
        if first is None:
            break
    return tuple(trials)


class NoInventoryError(ValueError):
    """No inventory maps every label of an utterance; `trials` say what each one tried did not know."""

    def __init__(self, trials: tuple[InventoryTrial, ...]) -> None:
        self.trials = tuple(trials)
        tried = "; ".join(f"{t.inventory}: {t.first_unknown!r} first of {t.unknown} unknown" for t in self.trials)
        super().__init__(f"no phone inventory maps every label (tried {tried})")

    def __reduce__(self):  # one-argument constructor, picklable (Prefect ships exceptions)
        return (type(self), (self.trials,))


def choose_inventory(labels: Sequence[str], language: str | None = None) -> str:
    """The first inventory (in `inventory_order`) that maps every label; NoInventoryError naming each
    inventory tried and its first unknown label when none does."""
    trials = try_inventories(labels, language)
    if trials[-1].first_unknown is None:
        return trials[-1].inventory
    raise NoInventoryError(trials)


def detect_inventory(labels: Iterable[str], language: str | None = None) -> str:
    """The first inventory that maps every label, else the one with the fewest unknown labels (earliest in
    `inventory_order` on ties); `choose_inventory` raises instead, naming what every inventory did not know."""
    trials = try_inventories(list(labels), language)
    return min(trials, key=lambda t: t.unknown).inventory  # min keeps the earliest on ties


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
