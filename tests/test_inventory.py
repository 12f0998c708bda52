"""Phone-label inventories (ARPAbet, IPA, pinyin; X-SAMPA in test_xsampa.py) mapped onto the 16 visemes of paper Fig. 2."""

import csv
import io
import math
import pickle
import re
from importlib import resources
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from visemeflow.phonetics.inventory import (
    INVENTORIES,
    VISEME_TABLES,
    SILENCE_LABELS,
    PhonemeMapping,
    UnknownPhonemeError,
    detect_inventory,
    inventory_symbols,
    is_silence,
    map_phone,
    split_interval,
)
from visemeflow.visemes import VISEMES

# Paper Fig. 2, transcribed from the paper's table (not from the CSVs under test).
FIG2_ENGLISH = {
    "AAA": ["æ", "eɪ", "aɪ"],
    "AHH": ["ɒ", "ɑː", "ʌ", "aʊ"],
    "EH": ["ɛ", "h"],
    "FFF": ["f", "v"],
    "GK": ["g", "k"],
    "IEE": ["i", "iː", "j"],
    "LNTD": ["l", "n", "t", "d"],
    "MBP": ["m", "b", "p"],
    "OHH": ["əʊ", "ɔɪ", "oɪ"],
    "RRR": ["r"],
    "SCHWA": ["ə", "ɜː"],
    "SSH": ["tʃ", "ʃ", "ʒ", "dʒ"],
    "SSS": ["ð", "s", "z"],
    "TTH": ["θ"],
    "UUU": ["ʊ", "uː"],
    "WWW": ["w"],
}
FIG2_CHINESE = {
    "AAA": ["ai"],
    "AHH": ["a"],
    "EH": ["ei"],
    "FFF": ["f"],
    "GK": ["g", "k", "h"],
    "IEE": ["i"],
    "LNTD": ["l", "n", "t", "d"],
    "MBP": ["m", "b", "p"],
    "OHH": ["o"],
    "RRR": ["r"],
    "SCHWA": ["e", "er"],
    "SSH": ["zh", "ch", "sh"],
    "SSS": ["z", "c", "s"],
    "TTH": ["j", "q", "x"],
    "UUU": ["iu"],
    "WWW": ["u", "v"],
}


def _pairs(table: dict[str, list[str]]) -> list[tuple[str, str]]:
    return [(symbol, viseme) for viseme, symbols in table.items() for symbol in symbols]


def _names(mapping: PhonemeMapping) -> list[str]:
    return [name for name, _ in mapping.visemes]


def _csv_rows(inventory: str) -> list[dict[str, str]]:
    text = resources.files("visemeflow.phonetics").joinpath("data", f"{inventory}.csv").read_text("utf-8")
    return list(csv.DictReader(io.StringIO(text)))


# --- paper Fig. 2 ----------------------------------------------------------------------------


def test_fig2_transcription_covers_all_16_visemes():
    assert sorted(FIG2_ENGLISH) == sorted(VISEMES) == sorted(FIG2_CHINESE)


@pytest.mark.parametrize(("symbol", "viseme"), _pairs(FIG2_ENGLISH))
def test_fig2_english_ipa_maps_as_listed(symbol, viseme):
    assert map_phone(symbol, "ipa").visemes == ((viseme, 1.0),)


@pytest.mark.parametrize(("symbol", "viseme"), _pairs(FIG2_CHINESE))
def test_fig2_chinese_pinyin_maps_as_listed(symbol, viseme):
    assert map_phone(symbol, "pinyin").visemes == ((viseme, 1.0),)


@pytest.mark.parametrize(("inventory", "fig2"), [("ipa", FIG2_ENGLISH), ("pinyin", FIG2_CHINESE)])
def test_paper_origin_rows_are_exactly_fig2(inventory, fig2):
    paper_rows = {r["symbol"]: r["visemes"] for r in _csv_rows(inventory) if r["origin"] == "paper"}
    assert paper_rows == {symbol: viseme for symbol, viseme in _pairs(fig2)}


@pytest.mark.parametrize("inventory", VISEME_TABLES)
def test_tables_are_well_formed(inventory):
    rows = _csv_rows(inventory)
    assert list(rows[0]) == ["symbol", "visemes", "origin", "note"]
    for row in rows:
        assert row["origin"] in {"paper", "choice"}
        assert row["origin"] == "paper" or row["note"].strip(), f"choice {row['symbol']!r} has no note"
        for item in row["visemes"].split():
            name, _, weight = item.partition(":")
            assert name in VISEMES and (not weight or float(weight) > 0)
    assert inventory_symbols(inventory) == {r["symbol"] for r in rows}


@pytest.mark.parametrize("inventory", VISEME_TABLES)
def test_every_choice_is_documented(inventory):
    page = (Path(__file__).resolve().parents[1] / "docs" / "phonemes.md").read_text("utf-8")
    missing = [r["symbol"] for r in _csv_rows(inventory) if r["origin"] == "choice" and f"`{r['symbol']}`" not in page]
    assert not missing, f"docs/phonemes.md does not list these {inventory} choices: {missing}"


# --- ARPAbet ---------------------------------------------------------------------------------

ARPABET = {
    "AA": "AHH", "AE": "AAA", "AH1": "AHH", "AH2": "AHH", "AH0": "SCHWA", "AO": "OHH", "AW": "AHH",
    "AY": "AAA", "B": "MBP", "CH": "SSH", "D": "LNTD", "DH": "SSS", "EH": "EH", "ER": "SCHWA",
    "EY": "AAA", "F": "FFF", "G": "GK", "HH": "EH", "IH": "IEE", "IY": "IEE", "JH": "SSH", "K": "GK",
    "L": "LNTD", "M": "MBP", "N": "LNTD", "NG": "GK", "OW": "OHH", "OY": "OHH", "P": "MBP", "R": "RRR",
    "S": "SSS", "SH": "SSH", "T": "LNTD", "TH": "TTH", "UH": "UUU", "UW": "UUU", "V": "FFF", "W": "WWW",
    "Y": "IEE", "Z": "SSS", "ZH": "SSH",
    "AX": "SCHWA", "AXR": "SCHWA", "IX": "IEE", "UX": "UUU", "DX": "LNTD", "NX": "LNTD", "EL": "LNTD",
    "EM": "MBP", "EN": "LNTD",
}


@pytest.mark.parametrize(("label", "viseme"), ARPABET.items())
def test_arpabet_phone_maps(label, viseme):
    assert map_phone(label, "arpabet").visemes == ((viseme, 1.0),)


def test_arpabet_ah_is_stress_dependent():
    assert _names(map_phone("AH0", "arpabet")) == ["SCHWA"]
    assert _names(map_phone("AH1", "arpabet")) == ["AHH"]
    assert _names(map_phone("AH2", "arpabet")) == ["AHH"]
    assert map_phone("AH0", "arpabet").phoneme == map_phone("AH1", "arpabet").phoneme == "AH"


@pytest.mark.parametrize(("label", "phoneme", "stress"), [
    ("IY1", "IY", 1), ("ER0", "ER", 0), ("EH2", "EH", 2), ("T", "T", None), ("ah0", "AH", 0), ("Iy1", "IY", 1),
])
def test_arpabet_stress_digit_lands_in_stress(label, phoneme, stress):
    mapping = map_phone(label, "arpabet")
    assert (mapping.label, mapping.phoneme, mapping.stress, mapping.is_silence) == (label, phoneme, stress, False)


def test_arpabet_extras():
    assert map_phone("Q", "arpabet").visemes == ()
    assert not map_phone("Q", "arpabet").is_silence
    assert _names(map_phone("PT", "arpabet")) == ["MBP", "LNTD"]
    assert _names(map_phone("IY0", "arpabet")) == _names(map_phone("iy", "arpabet")) == ["IEE"]


@pytest.mark.parametrize("label", ["AH3", "IY12", "XX", "ə", "e4"])
def test_arpabet_rejects_non_arpabet(label):
    with pytest.raises(UnknownPhonemeError):
        map_phone(label, "arpabet")


# --- IPA -------------------------------------------------------------------------------------


@pytest.mark.parametrize(("label", "phoneme", "viseme"), [
    ("ɑː", "ɑː", "AHH"), ("ɑ", "ɑ", "AHH"), ("ɔː", "ɔ", "OHH"), ("ɒː", "ɒ", "AHH"), ("eː", "e", "EH"),
    ("ʉː", "ʉ", "UUU"), ("iˑ", "i", "IEE"), ("i:", "iː", "IEE"), ("uː", "uː", "UUU"),
    ("t͡ʃ", "tʃ", "SSH"), ("d͡ʒ", "dʒ", "SSH"), ("t͜s", "ts", "SSS"), ("ʧ", "tʃ", "SSH"),
    ("n̩", "n", "LNTD"), ("m̩", "m", "MBP"), ("l̩", "l", "LNTD"), ("ɫ̩", "ɫ", "LNTD"), ("n̍", "n", "LNTD"),
    ("tʰ", "t", "LNTD"), ("kʰ", "k", "GK"), ("kʷ", "k", "GK"), ("tʲ", "t", "LNTD"), ("t̪", "t", "LNTD"),
    ("ɡ", "g", "GK"), ("g", "g", "GK"), ("ɡʷ", "g", "GK"), ("ɹ", "ɹ", "RRR"), ("ɾ", "ɾ", "LNTD"),
    ("ɾ̃", "ɾ", "LNTD"), ("ẽ", "e", "EH"), ("ç", "ç", "GK"), ("c", "c", "GK"), ("ɟ", "ɟ", "GK"),
    ("ŋ", "ŋ", "GK"), ("ɪ", "ɪ", "IEE"), ("ɚ", "ɚ", "SCHWA"), ("ɝ", "ɝ", "SCHWA"), ("œ", "œ", "OHH"),
    ("aj", "aj", "AAA"), ("ow", "ow", "OHH"), ("ʍ", "ʍ", "WWW"), ("ɦ", "ɦ", "EH"), ("M", "m", "MBP"),
])
def test_ipa_normalisation(label, phoneme, viseme):
    mapping = map_phone(label, "ipa")
    assert (mapping.phoneme, mapping.visemes, mapping.stress) == (phoneme, ((viseme, 1.0),), None)


def test_ipa_centring_diphthongs_are_sequences():
    assert map_phone("ɪə", "ipa").visemes == (("IEE", 2.0), ("SCHWA", 1.0))
    assert map_phone("ʊə", "ipa").visemes == (("UUU", 2.0), ("SCHWA", 1.0))
    assert _names(map_phone("eə", "ipa")) == ["EH"]


def test_ipa_glottal_stop_is_transparent_not_silence():
    mapping = map_phone("ʔ", "ipa")
    assert mapping.visemes == () and not mapping.is_silence


def test_english_h_and_pinyin_h_differ():
    assert _names(map_phone("h", "ipa")) == _names(map_phone("HH", "arpabet")) == ["EH"]
    assert _names(map_phone("h", "pinyin")) == ["GK"]


# --- pinyin ----------------------------------------------------------------------------------

PINYIN_FINALS = {
    "ao": [("AHH", 2), ("UUU", 1)], "ou": [("OHH", 1)], "iu": [("UUU", 1)], "iou": [("UUU", 1)],
    "an": [("AHH", 2), ("LNTD", 1)], "en": [("SCHWA", 2), ("LNTD", 1)], "ang": [("AHH", 2), ("GK", 1)],
    "eng": [("SCHWA", 2), ("GK", 1)], "ong": [("UUU", 2), ("GK", 1)], "ia": [("IEE", 1), ("AHH", 2)],
    "ie": [("IEE", 1), ("EH", 2)], "iao": [("IEE", 1), ("AHH", 2), ("UUU", 1)],
    "ian": [("IEE", 1), ("EH", 2), ("LNTD", 1)], "in": [("IEE", 2), ("LNTD", 1)],
    "iang": [("IEE", 1), ("AHH", 2), ("GK", 1)], "ing": [("IEE", 2), ("GK", 1)],
    "iong": [("IEE", 1), ("UUU", 2), ("GK", 1)], "ua": [("WWW", 1), ("AHH", 2)], "uo": [("WWW", 1), ("OHH", 2)],
    "uai": [("WWW", 1), ("AAA", 2)], "ui": [("WWW", 1), ("EH", 2)], "uei": [("WWW", 1), ("EH", 2)],
    "uan": [("WWW", 1), ("AHH", 2), ("LNTD", 1)], "un": [("WWW", 1), ("SCHWA", 2), ("LNTD", 1)],
    "uen": [("WWW", 1), ("SCHWA", 2), ("LNTD", 1)], "uang": [("WWW", 1), ("AHH", 2), ("GK", 1)],
    "ueng": [("WWW", 1), ("SCHWA", 2), ("GK", 1)], "ve": [("WWW", 1), ("EH", 2)], "ue": [("WWW", 1), ("EH", 2)],
    "van": [("WWW", 1), ("EH", 2), ("LNTD", 1)], "vn": [("WWW", 2), ("LNTD", 1)], "ii": [("SSS", 1)],
    "iii": [("SSH", 1)], "er": [("SCHWA", 1)], "ê": [("EH", 1)], "y": [("IEE", 1)], "w": [("WWW", 1)],
}


@pytest.mark.parametrize(("final", "expected"), PINYIN_FINALS.items())
def test_pinyin_finals(final, expected):
    assert map_phone(final, "pinyin").visemes == tuple((v, float(w)) for v, w in expected)


def test_pinyin_every_standard_final_has_a_row():
    finals = ("a o e i u v ai ei ao ou an en ang eng ong er ia ie iao iu iou ian in iang ing iong ua uo uai ui "
              "uei uan un uen uang ueng ve ue van vn ii iii ê").split()
    assert set(finals) <= inventory_symbols("pinyin")


def test_compound_final_iao_in_order():
    assert _names(map_phone("iao4", "pinyin")) == ["IEE", "AHH", "UUU"]


@pytest.mark.parametrize(("label", "phoneme", "tone"), [
    ("e4", "e", 4), ("ve2", "ve", 2), ("ui4", "ui", 4), ("ing2", "ing", 2), ("uang3", "uang", 3),
    ("ou1", "ou", 1), ("iii4", "iii", 4), ("ao5", "ao", 5), ("zh", "zh", None), ("ZH", "zh", None),
    ("Ing2", "ing", 2), ("üe4", "ve", 4), ("ü3", "v", 3), ("ün", "vn", None),
])
def test_pinyin_tone_lands_in_stress(label, phoneme, tone):
    mapping = map_phone(label, "pinyin")
    assert (mapping.phoneme, mapping.stress) == (phoneme, tone)


@pytest.mark.parametrize("label", ["e6", "e0", "xyz", "ə"])
def test_pinyin_rejects_unknown(label):
    with pytest.raises(UnknownPhonemeError):
        map_phone(label, "pinyin")


# --- silence, errors -------------------------------------------------------------------------


@pytest.mark.parametrize("label", ["", " ", "sil", "SIL", "sp", "spn", "[SIL]", "<eps>", "<sil>", "pau", "#", "Sil"])
@pytest.mark.parametrize("inventory", INVENTORIES)
def test_silence_gives_no_viseme(label, inventory):
    mapping = map_phone(label, inventory)
    assert is_silence(label) and mapping.is_silence and mapping.visemes == ()


def test_silence_labels_constant():
    assert {"", "sil", "sp", "spn", "[SIL]", "<eps>", "SIL", "<sil>", "pau", "#"} <= SILENCE_LABELS
    assert not is_silence("AH0") and not is_silence("s")


@pytest.mark.parametrize("inventory", INVENTORIES)
def test_unknown_symbol_raises_naming_symbol_and_inventory(inventory):
    with pytest.raises(UnknownPhonemeError) as info:
        map_phone("QQX7", inventory)
    assert "QQX7" in str(info.value) and inventory in str(info.value)
    assert (info.value.symbol, info.value.inventory) == ("QQX7", inventory)
    assert isinstance(info.value, ValueError)


def test_unknown_phoneme_error_pickles():
    err = pickle.loads(pickle.dumps(UnknownPhonemeError("œ̃", "arpabet")))
    assert (err.symbol, err.inventory, str(err)) == ("œ̃", "arpabet", str(UnknownPhonemeError("œ̃", "arpabet")))


def test_unknown_inventory_is_value_error():
    with pytest.raises(ValueError, match="klingon"):
        map_phone("a", "klingon")
    with pytest.raises(ValueError, match="klingon"):
        inventory_symbols("klingon")


# --- detect_inventory ------------------------------------------------------------------------


def test_detect_arpabet():
    assert detect_inventory(["", "P", "R", "IH1", "N", "T", "IH0", "NG", "sp", "AH0"]) == "arpabet"


def test_detect_ipa():
    assert detect_inventory("m ə r i r o l d θ ə b œ r l".split() + [""]) == "ipa"
    assert detect_inventory(["tʰ", "ɪ", "ŋ", "ɡ", "sil"]) == "ipa"


def test_detect_pinyin():
    labels = ["[SIL]", "zh", "e4", "j", "ve2", "d", "ui4", "b", "u4", "x", "ing2", "[SIL]"]
    assert detect_inventory(labels) == "pinyin"
    assert detect_inventory(labels, language="zh-CN") == "pinyin"


def test_detect_language_hint_puts_pinyin_first():
    ambiguous = ["b", "d", "m", "sil"]  # valid under all three inventories
    assert detect_inventory(ambiguous) == "arpabet"
    assert detect_inventory(ambiguous, language="cmn") == "pinyin"
    assert detect_inventory(ambiguous, language="en") == "arpabet"


def test_detect_falls_back_to_fewest_unknowns():
    labels = ["ə", "ɪ", "ŋ", "BOGUS1"]
    inventory = detect_inventory(labels)
    assert inventory == "ipa"
    with pytest.raises(UnknownPhonemeError, match="BOGUS1"):
        [map_phone(label, inventory) for label in labels]


# --- split_interval --------------------------------------------------------------------------


def test_split_interval_proportional_and_exact():
    assert split_interval(1.0, 2.0, [1, 2, 1]) == [(1.0, 1.25), (1.25, 1.75), (1.75, 2.0)]
    assert split_interval(0.3, 0.7, [1]) == [(0.3, 0.7)]
    assert split_interval(0.5, 0.5, [1, 2]) == [(0.5, 0.5), (0.5, 0.5)]


def test_split_interval_with_mapping_weights():
    mapping = map_phone("iao3", "pinyin")
    parts = split_interval(0.0, 0.4, [w for _, w in mapping.visemes])
    assert [t for part in parts for t in part] == pytest.approx([0.0, 0.1, 0.1, 0.3, 0.3, 0.4])
    assert parts[-1][1] == 0.4


@pytest.mark.parametrize(("start", "end", "weights"), [(0, 1, []), (0, 1, [1, 0]), (0, 1, [-1]),
                                                       (0, 1, [math.nan]), (1, 0, [1])])
def test_split_interval_rejects_bad_input(start, end, weights):
    with pytest.raises(ValueError):
        split_interval(start, end, weights)


@given(
    start=st.floats(-1e4, 1e4),
    duration=st.floats(0, 1e4),
    weights=st.lists(st.floats(1e-3, 1e3), min_size=1, max_size=8),
)
def test_split_interval_property(start, duration, weights):
    end = start + duration
    parts = split_interval(start, end, weights)
    assert len(parts) == len(weights)
    assert parts[0][0] == start and parts[-1][1] == end
    assert all(a[1] == b[0] for a, b in zip(parts, parts[1:]))
    assert all(lo <= hi for lo, hi in parts)
    tolerance = 1e-9 * (abs(start) + abs(end) + 1)
    for (lo, hi), w in zip(parts, weights):
        assert abs((hi - lo) - (end - start) * w / sum(weights)) <= tolerance


# --- real data -------------------------------------------------------------------------------

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
# A string (Praat doubles inner quotes), a bracketed index of the long format, or a bare number.
_TOKEN = re.compile(r'"((?:[^"]|"")*)"|\[[^\]\n]*\]|(?<![\w.])(-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?)(?![\w.])')


def _read_text(path: Path) -> str:
    raw = path.read_bytes()
    return raw.decode("utf-16") if raw[:2] in (b"\xff\xfe", b"\xfe\xff") else raw.decode("utf-8-sig")


def _phone_labels(path: Path) -> list[str] | None:
    """Labels of the `phones`/`phone` interval tier (long or short Praat text format), None if absent."""
    tokens = [m.group(1).replace('""', '"') if m.group(1) is not None else float(m.group(2))
              for m in _TOKEN.finditer(_read_text(path)) if m.group(1) is not None or m.group(2)]
    assert tokens[:2] == ["ooTextFile", "TextGrid"], path
    pos, n_tiers = 5, int(tokens[4])
    for _ in range(n_tiers):
        kind, name, count = tokens[pos], tokens[pos + 1], int(tokens[pos + 4])
        width = 3 if kind == "IntervalTier" else 2
        items = tokens[pos + 5: pos + 5 + width * count]
        if kind == "IntervalTier" and name in ("phones", "phone"):
            return [str(label) for label in items[2::3]]
        pos += 5 + width * count
    return None


@pytest.mark.parametrize(("pattern", "expected", "min_files"), [
    ("ljspeech_mfa/TextGrid/*.TextGrid", {"arpabet"}, 20),
    ("praatio_examples/*.TextGrid", {"arpabet", "ipa"}, 2),
    ("charsiu_mandarin/*.TextGrid", {"pinyin"}, 1),
])
def test_real_textgrid_phones_all_map(pattern, expected, min_files):
    assert DATA.is_dir(), f"shared data folder missing: {DATA}"
    tiers = {path.name: _phone_labels(path) for path in sorted(DATA.glob(pattern))}
    tiers = {name: labels for name, labels in tiers.items() if labels is not None}
    assert len(tiers) >= min_files, f"expected >= {min_files} files with a phone tier under {pattern}"
    seen = set()
    for name, labels in tiers.items():
        assert any(not is_silence(label) for label in labels), name
        inventory = detect_inventory(labels)
        unknown = sorted({label for label in labels if not _maps(label, inventory)})
        assert not unknown, f"{name}: unknown {inventory} symbols {unknown}"
        seen.add(inventory)
    assert seen == expected


def _maps(label: str, inventory: str) -> bool:
    try:
        return all(v in VISEMES for v, _ in map_phone(label, inventory).visemes)
    except UnknownPhonemeError:
        return False
