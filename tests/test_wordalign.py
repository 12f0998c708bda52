"""Word-level alignments (GRID `.align`) and their spreading into phone spans with CMUdict."""

from pathlib import Path

import pytest

from visemeflow.phonetics.types import WordInterval
from visemeflow.phonetics.wordalign import (
    GRID_TIME_UNIT_S,
    WordAlignmentError,
    load_cmudict,
    parse_word_alignment,
    spread_words_to_phones,
)

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
ALIGN = DATA / "grid_s1" / "align"


def align_files() -> list[Path]:
    files = sorted(ALIGN.glob("*.align"))
    assert len(files) == 10, f"expected the 10 GRID .align files under {ALIGN}"
    return files


def test_grid_time_unit():
    assert GRID_TIME_UNIT_S == pytest.approx(1 / 25000)
    words = parse_word_alignment("23750 29500 bin\n")
    assert words == (WordInterval("bin", pytest.approx(0.95), pytest.approx(1.18)),)


def test_every_grid_align_file_parses_and_is_pronounceable():
    lexicon = load_cmudict()
    transcripts = dict(
        line.split("\t") for line in (DATA / "grid_s1" / "transcripts.tsv").read_text().splitlines() if line.strip()
    )
    for path in align_files():
        words = parse_word_alignment(path.read_text(), str(path))
        assert words[0].start_s == 0.0
        assert words[-1].end_s == pytest.approx(2.98)
        assert all(a.end_s == pytest.approx(b.start_s) for a, b in zip(words, words[1:])), path
        spoken = [w.label for w in words if w.label not in ("sil", "sp")]
        assert " ".join(spoken) == transcripts[path.stem].strip(), path
        for w in spoken:
            assert w.lower() in lexicon, (path, w)
        phones = spread_words_to_phones(words, lexicon, str(path))
        assert phones[0].start_s == 0.0 and phones[-1].end_s == pytest.approx(2.98)
        assert all(a.end_s == b.start_s for a, b in zip(phones, phones[1:])), path


def test_bwbg8n_first_word():
    words = parse_word_alignment((ALIGN / "bwbg8n.align").read_text(), "bwbg8n.align")
    assert [w.label for w in words] == ["sil", "bin", "white", "by", "g", "eight", "now", "sil"]
    assert (words[1].start_s, words[1].end_s) == (pytest.approx(17250 / 25000), pytest.approx(23000 / 25000))


def test_custom_time_unit():
    words = parse_word_alignment("0 1500 a\n1500 3000 b\n", time_unit_s=1e-3)
    assert [(w.start_s, w.end_s) for w in words] == [(0.0, 1.5), (1.5, 3.0)]


LEXICON = {"bin": [["B", "IH1", "N"]], "at": [["AE1", "T"], ["AH0", "T"]], "oh": [["OW1"]], "st": [["S", "T"]]}


@pytest.mark.parametrize("vowel_weight", [1.0, 2.0, 3.5])
def test_phones_tile_each_word_span_with_vowel_weight(vowel_weight):
    words = (WordInterval("sil", 0.0, 0.5), WordInterval("BIN", 0.5, 1.3), WordInterval("at", 1.3, 1.6),
             WordInterval("sp", 1.6, 1.7), WordInterval("oh", 1.7, 2.0), WordInterval("st", 2.0, 2.2))
    phones = spread_words_to_phones(words, LEXICON, vowel_weight=vowel_weight)
    assert [p.label for p in phones] == ["sil", "B", "IH1", "N", "AE1", "T", "sil", "OW1", "S", "T"]
    # pauses: one `sil` over the whole pause, outside any word
    assert (phones[0].start_s, phones[0].end_s, phones[0].word, phones[0].word_index) == (0.0, 0.5, None, None)
    assert (phones[6].start_s, phones[6].end_s, phones[6].word) == (1.6, 1.7, None)
    # spoken words: phones exactly tile the span, in order
    for word, index, group in ((words[1], 0, phones[1:4]), (words[2], 1, phones[4:6]), (words[4], 2, phones[7:8]),
                               (words[5], 3, phones[8:10])):
        assert group[0].start_s == word.start_s and group[-1].end_s == word.end_s
        assert all(a.end_s == b.start_s for a, b in zip(group, group[1:]))
        assert all(p.word == word.label and p.word_index == index for p in group)
        assert sum(p.duration_s for p in group) == pytest.approx(word.end_s - word.start_s)
    # a vowel gets `vowel_weight` times a consonant's share: B IH1 N over 0.8 s
    b, ih, n = phones[1:4]
    share = 0.8 / (2 + vowel_weight)
    assert b.duration_s == pytest.approx(share) and n.duration_s == pytest.approx(share)
    assert ih.duration_s == pytest.approx(vowel_weight * share)
    assert ih.duration_s / b.duration_s == pytest.approx(vowel_weight)
    # first pronunciation is used; a word of consonants only shares equally
    assert phones[4].duration_s == pytest.approx(0.3 * vowel_weight / (vowel_weight + 1))
    assert phones[8].duration_s == pytest.approx(0.1) and phones[9].duration_s == pytest.approx(0.1)
    assert phones[7].duration_s == pytest.approx(0.3)


def test_zero_length_word_gives_zero_length_phones():
    phones = spread_words_to_phones((WordInterval("bin", 1.0, 1.0),), LEXICON)
    assert [(p.start_s, p.end_s) for p in phones] == [(1.0, 1.0)] * 3


def test_unknown_word_names_file_and_word():
    words = (WordInterval("bin", 0.0, 0.5), WordInterval("zyxxyq", 0.5, 1.0))
    with pytest.raises(WordAlignmentError) as info:
        spread_words_to_phones(words, LEXICON, "grid/s1/x.align")
    assert "zyxxyq" in str(info.value) and "grid/s1/x.align" in str(info.value)
    with pytest.raises(WordAlignmentError, match="zyxxyq"):
        spread_words_to_phones(words, load_cmudict(), "x.align")


@pytest.mark.parametrize(
    "text, line, fragment",
    [
        ("0 100 sil\n100 200\n", 2, "100 200"),
        ("0 100 sil\n100 200 bin extra\n", 2, "extra"),
        ("0 1oo sil\n", 1, "1oo"),
        ("0 100 sil\n\n300 200 bin\n", 3, "bin"),
        ("abc\n", 1, "abc"),
    ],
)
def test_malformed_line_names_file_and_line(text, line, fragment):
    with pytest.raises(WordAlignmentError) as info:
        parse_word_alignment(text, "spk/clip.align")
    message = str(info.value)
    assert message.startswith(f"spk/clip.align:{line}:")
    assert fragment in message


def test_empty_file_is_an_error():
    with pytest.raises(WordAlignmentError, match="empty.align"):
        parse_word_alignment("\n  \n", "empty.align")
