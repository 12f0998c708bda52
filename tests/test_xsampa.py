"""X-SAMPA / SAMPA phone labels (WebMAUS, SPPAS, praatio's SAMPA tiers) through data/xsampa.csv to IPA and the
visemes, the silence markers of those aligners, and inventory detection that picks X-SAMPA for them and names
every inventory it tried when none fits."""

import csv
import io
import pickle
import shutil
from importlib import resources
from pathlib import Path

import pytest

from factories import SHARED_DATA, textgrid_long, write_wav
from visemeflow.ingest import IngestConfig, IngestError, discover_corpus, ingest_utterance
from visemeflow.phonetics.inventory import (
    INVENTORIES,
    InventoryTrial,
    NoInventoryError,
    choose_inventory,
    detect_inventory,
    inventory_order,
    inventory_symbols,
    is_silence,
    looks_like_sampa,
    map_phone,
    try_inventories,
    xsampa_table,
    xsampa_to_ipa,
)
from visemeflow.phonetics.textgrid import read_textgrid
from visemeflow.schemas import C

REPO = Path(__file__).resolve().parents[1]
DAMON = Path(__file__).resolve().parent / "data" / "praatio"
DAMON_PHONES = "d eI m @ n f r aI d D V A m l @ t".split()


def _names(label: str, inventory: str = "xsampa") -> list[str]:
    return [v for v, _ in map_phone(label, inventory).visemes]


# ---- the table ---------------------------------------------------------------------------------

def test_table_is_csv_with_a_source_comment_and_a_header():
    text = resources.files("visemeflow.phonetics").joinpath("data", "xsampa.csv").read_text("utf-8")
    comments = [line for line in text.splitlines() if line.startswith("#")]
    assert comments and any("Wells" in line and "X-SAMPA" in line for line in comments)
    rows = list(csv.DictReader(io.StringIO("\n".join(line for line in text.splitlines() if not line.startswith("#")))))
    assert list(rows[0]) == ["xsampa", "ipa", "kind", "note"]
    assert len({r["xsampa"] for r in rows}) == len(rows) == len(xsampa_table())
    assert {r["kind"] for r in rows} == {"segment", "diacritic", "prosody", "sppas"}
    assert inventory_symbols("xsampa") == {r["xsampa"] for r in rows}


# From the X-SAMPA chart (J. C. Wells), written out here independently of the CSV.
SPEC = {
    "a": "a", "b": "b", "g": "ɡ", "A": "ɑ", "B": "β", "C": "ç", "D": "ð", "E": "ɛ", "F": "ɱ", "G": "ɣ", "H": "ɥ",
    "I": "ɪ", "J": "ɲ", "K": "ɬ", "L": "ʎ", "M": "ɯ", "N": "ŋ", "O": "ɔ", "P": "ʋ", "Q": "ɒ", "R": "ʁ", "S": "ʃ",
    "T": "θ", "U": "ʊ", "V": "ʌ", "W": "ʍ", "X": "χ", "Y": "ʏ", "Z": "ʒ", "@": "ə", "{": "æ", "}": "ʉ", "1": "ɨ",
    "2": "ø", "3": "ɜ", "4": "ɾ", "5": "ɫ", "6": "ɐ", "7": "ɤ", "8": "ɵ", "9": "œ", "&": "ɶ", "?": "ʔ",
    "r\\": "ɹ", "r\\`": "ɻ", "t`": "ʈ", "d`": "ɖ", "n`": "ɳ", "s`": "ʂ", "z`": "ʐ", "s\\": "ɕ", "z\\": "ʑ",
    "h\\": "ɦ", "j\\": "ʝ", "x\\": "ɧ", "J\\": "ɟ", "G\\": "ɢ", "N\\": "ɴ", "R\\": "ʀ", "X\\": "ħ", "?\\": "ʕ",
    "@\\": "ɘ", "@`": "ɚ", "3`": "ɝ", "I\\": "ɪ̈", "U\\": "ʊ̈", "b_<": "ɓ", "O\\": "ʘ",
    # sequences, length, diacritics and stress as WebMAUS/SAMPA files write them
    "3:": "ɜː", "i:": "iː", "A:": "ɑː", "O:": "ɔː", "aI": "aɪ", "eI": "eɪ", "OI": "ɔɪ", "aU": "aʊ", "@U": "əʊ",
    "I@": "ɪə", "e@": "eə", "U@": "ʊə", "OY": "ɔʏ", "tS": "tʃ", "dZ": "dʒ", "t_S": "t͡ʃ", "p_h": "pʰ",
    "t_w": "tʷ", "k_j": "kʲ", "a~": "ã", "o~": "õ", "n=": "n̩", "l=": "l̩", "e_0": "e̥", "a:\\": "aˑ",
    '"aI': "ˈaɪ", "%e": "ˌe", "d_d": "d̪", "a_H": "á", "a.b": "ab",
}


@pytest.mark.parametrize(("label", "ipa"), SPEC.items())
def test_xsampa_to_ipa_follows_the_specification(label, ipa):
    assert xsampa_to_ipa(label) == ipa


def test_unknown_or_empty_symbols():
    assert xsampa_to_ipa("a$") is None and xsampa_to_ipa("ə") is None  # not ASCII X-SAMPA
    with pytest.raises(ValueError, match=r"unknown phone '\$' in inventory 'xsampa'"):
        map_phone("$", "xsampa")
    with pytest.raises(ValueError):
        map_phone(".", "xsampa")  # a syllable break alone is no phone


def test_every_segment_maps_like_its_ipa():
    """X-SAMPA adds no viseme choices of its own: a segment's visemes are those of its IPA."""
    for symbol, row in xsampa_table().items():
        if row.kind in ("segment", "sppas"):
            assert map_phone(symbol, "xsampa").visemes == map_phone(row.ipa, "ipa").visemes, symbol
        elif row.kind == "prosody":
            assert row.ipa == ""


@pytest.mark.parametrize(("label", "visemes"), [
    ("@", ["SCHWA"]), ("{", ["AAA"]), ("Q", ["AHH"]), ("V", ["AHH"]), ("3:", ["SCHWA"]), ("aI", ["AAA"]),
    ("OI", ["OHH"]), ("tS", ["SSH"]), ("dZ", ["SSH"]), ("D", ["SSS"]), ("T", ["TTH"]), ("S", ["SSH"]),
    ("N", ["GK"]), ("I", ["IEE"]), ("U", ["UUU"]), ("E", ["EH"]), ("A:", ["AHH"]), ("@U", ["OHH"]),
    ("I@", ["IEE", "SCHWA"]), ("r\\", ["RRR"]), ("?", []), ("p_h", ["MBP"]), ('"{', ["AAA"]),
])
def test_webmaus_sampa_labels(label, visemes):
    assert _names(label) == visemes
    assert not map_phone(label, "xsampa").is_silence


def test_case_matters():
    assert _names("D") == ["SSS"] and _names("D", "arpabet") == ["LNTD"]
    assert _names("S") == ["SSH"] and _names("s") == ["SSS"]
    assert _names("T") == ["TTH"] and _names("t") == ["LNTD"]


@pytest.mark.parametrize("label", ["<p:>", "<p>", "<usb>", "<nib>", "<ähm>", "(...)", "(.)", "+", "*", "#",
                                   "@@", "dummy", "noise", "laugh", "gb", "sil", "sp", ""])
@pytest.mark.parametrize("inventory", INVENTORIES)
def test_aligner_silence_and_noise_markers(label, inventory):
    assert is_silence(label)
    mapping = map_phone(label, inventory)
    assert mapping.is_silence and mapping.visemes == ()


@pytest.mark.parametrize(("label", "visemes"), [
    ("A/", ["AAA"]), ("O/", ["OHH"]), ("E/", ["EH"]), ("U~/", ["EH"]), ("a~", ["AAA"]), ("O~", ["OHH"]),
    ("fp", ["SCHWA"]), ("3:r", ["SCHWA"]), ("H", ["WWW"]), ("R", ["GK"]), ("9", ["OHH"]), ("2", ["OHH"]),
])
def test_sppas_labels(label, visemes):
    assert _names(label) == visemes


# ---- detection ---------------------------------------------------------------------------------

def test_sampa_labels_are_detected_as_xsampa():
    """praatio's damon_set_test phone tier: rejected before this with "unknown pinyin phoneme '@'"."""
    assert looks_like_sampa(DAMON_PHONES)
    assert inventory_order(DAMON_PHONES) == ("xsampa", "arpabet", "ipa", "pinyin")
    assert detect_inventory(DAMON_PHONES + [""]) == choose_inventory(DAMON_PHONES) == "xsampa"
    assert try_inventories(DAMON_PHONES) == (InventoryTrial("xsampa", 0, None, None),)
    # mixed case alone is enough: "D V m" is X-SAMPA, though ARPAbet would read D and V too
    assert choose_inventory(["D", "V", "m", "sil"]) == "xsampa"
    assert choose_inventory(["<p:>", "T", "I", "N", "k", "<p:>"]) == "xsampa"


def test_other_inventories_keep_their_detection():
    assert not looks_like_sampa(["P", "R", "IH1", "N", "T", "sil", ""])
    assert choose_inventory(["P", "R", "IH1", "N", "T", "sil"]) == "arpabet"
    assert choose_inventory("m ə r i r o l d θ ə b œ r l".split()) == "ipa"
    assert choose_inventory(["zh", "e4", "j", "ve2", "[SIL]"]) == "pinyin"
    assert choose_inventory(["b", "d", "m", "sil"]) == "arpabet"  # valid everywhere: the default order decides
    assert choose_inventory(["b", "d", "@"], language="zh") == "xsampa"  # pinyin first, then the others
    assert inventory_order(["b"], language="cmn")[0] == "pinyin"


def test_no_inventory_names_every_inventory_tried_and_its_first_unknown():
    labels = ["sil", "m", "@", "QX7", "ə"]
    with pytest.raises(NoInventoryError) as info:
        choose_inventory(labels)
    trials = {t.inventory: t for t in info.value.trials}
    assert set(trials) == set(INVENTORIES)  # all four were tried
    assert trials["xsampa"] == InventoryTrial("xsampa", 2, "QX7", 3)
    assert trials["arpabet"] == InventoryTrial("arpabet", 3, "@", 2)
    assert trials["ipa"].first_unknown == "@" and trials["pinyin"].first_unknown == "@"
    message = str(info.value)
    for inventory in INVENTORIES:
        assert inventory in message
    assert "'QX7'" in message and "'@'" in message
    again = pickle.loads(pickle.dumps(info.value))
    assert again.trials == info.value.trials and str(again) == message
    assert detect_inventory(labels) == "xsampa"  # the fewest unknown labels


# ---- through ingest --------------------------------------------------------------------------------

def test_real_sampa_textgrid_is_ingested(tmp_path):
    """The real praatio SAMPA file (tests/data/praatio, MIT) with its recording, as a corpus utterance."""
    folder = tmp_path / "c" / "damon"
    folder.mkdir(parents=True)
    for name in ("damon_set_test.TextGrid", "damon_set_test.wav"):
        shutil.copyfile(DAMON / name, folder / name)
    (entry,) = discover_corpus(tmp_path / "c").entries
    result = ingest_utterance(entry, IngestConfig())
    assert result.utterance[C.INVENTORY] == "xsampa" and result.utterance[C.LANGUAGE] is None
    spoken = [r for r in result.phones if r[C.VISEME] is not None]
    assert [r[C.LABEL] for r in spoken] == DAMON_PHONES
    by_label = {r[C.LABEL]: r[C.VISEME] for r in spoken}
    assert (by_label["D"], by_label["V"], by_label["@"], by_label["eI"], by_label["aI"]) == \
        ("SSS", "AHH", "SCHWA", "AAA", "AAA")
    words = {r[C.WORD] for r in spoken}
    assert words == {"damon", "fried", "the", "omelet"}


def test_every_praatio_textgrid_maps():
    """The shared praatio examples (must be present) and the shipped SAMPA one: each detected inventory maps every
    phone label, and the three files need three different inventories."""
    assert (SHARED_DATA / "praatio_examples").is_dir(), f"shared data missing: {SHARED_DATA / 'praatio_examples'}"
    files = sorted((SHARED_DATA / "praatio_examples").glob("*.TextGrid")) + [DAMON / "damon_set_test.TextGrid"]
    config = IngestConfig()
    seen = {}
    for path in files:
        tier = read_textgrid(path).tier(config.phone_tiers)
        if tier is None:
            continue
        labels = [label for _, _, label in tier.items]
        inventory = choose_inventory(labels)
        assert all(map_phone(label, inventory) for label in labels)
        seen[path.name] = inventory
    assert seen == {"bobby_phones.TextGrid": "arpabet", "mary.TextGrid": "ipa",
                    "damon_set_test.TextGrid": "xsampa"}


def _corpus(tmp_path: Path, phones: list[tuple[float, float, str]]) -> Path:
    folder = tmp_path / "c" / "s"
    write_wav(folder / "u.wav", 1.0)
    tg = folder / "u.TextGrid"
    tg.write_text(textgrid_long(phones, 1.0))
    return tg


def test_unknown_labels_in_ingest_name_label_file_and_every_inventory(tmp_path):
    tg = _corpus(tmp_path, [(0.0, 0.2, "<p:>"), (0.2, 0.4, "m"), (0.4, 0.6, "@"), (0.6, 0.8, "QX7"),
                            (0.8, 1.0, "<p:>")])
    (entry,) = discover_corpus(tmp_path / "c").entries
    with pytest.raises(IngestError) as info:
        ingest_utterance(entry, IngestConfig())
    message = str(info.value)
    assert info.value.error_type == "UnknownPhoneme" and info.value.path == str(tg.resolve())
    assert message.startswith(f"s/u: {tg.resolve()}: no phone inventory knows every label")
    assert "xsampa: 'QX7' at 0.600 s (interval 4; 1 unknown label)" in message
    assert "arpabet: '@' at 0.400 s (interval 3; 2 unknown labels)" in message
    assert "ipa: '@'" in message and "pinyin: '@'" in message
    # with the inventory set, the one label is named, and that no other inventory was tried
    with pytest.raises(IngestError, match=r"unknown xsampa phoneme 'QX7' at 0\.600 s \(interval 4\); inventory "
                                          r"xsampa was set in the ingest config, no other was tried"):
        ingest_utterance(entry, IngestConfig(inventory="xsampa"))


def test_webmaus_textgrid_tiers_are_found(tmp_path):
    """WebMAUS names its tiers ORT-MAU (words), KAN-MAU (canonical) and MAU (phones, SAMPA, <p:> pauses)."""
    folder = tmp_path / "c" / "s"
    write_wav(folder / "u.wav", 1.0)
    mau = [(0.0, 0.2, "<p:>"), (0.2, 0.3, "h"), (0.3, 0.45, "@"), (0.45, 0.55, "l"), (0.55, 0.8, "@U"),
           (0.8, 1.0, "<p:>")]
    from visemeflow.phonetics.textgrid import Tier, format_textgrid

    tiers = (Tier("ORT-MAU", "IntervalTier", 0.0, 1.0, ((0.0, 0.2, ""), (0.2, 0.8, "hello"), (0.8, 1.0, ""))),
             Tier("KAN-MAU", "IntervalTier", 0.0, 1.0, ((0.0, 0.2, ""), (0.2, 0.8, "h@l@U"), (0.8, 1.0, ""))),
             Tier("MAU", "IntervalTier", 0.0, 1.0, tuple(mau)))
    (folder / "u.TextGrid").write_text(format_textgrid(tiers, 0.0, 1.0))
    (entry,) = discover_corpus(tmp_path / "c").entries
    result = ingest_utterance(entry, IngestConfig())
    assert result.utterance[C.INVENTORY] == "xsampa"
    assert [(r[C.LABEL], r[C.VISEME], r[C.WORD]) for r in result.phones] == [
        ("<p:>", None, None), ("h", "EH", "hello"), ("@", "SCHWA", "hello"), ("l", "LNTD", "hello"),
        ("@U", "OHH", "hello"), ("<p:>", None, None)]


def test_docs_list_the_table_and_every_sppas_row():
    page = (REPO / "docs" / "phonemes.md").read_text("utf-8")
    assert "xsampa.csv" in page and "X-SAMPA" in page
    missing = [s for s, row in xsampa_table().items() if row.kind == "sppas" and f"`{s}`" not in page]
    assert not missing, missing
