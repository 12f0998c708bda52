"""Praat TextGrid reader: long/short format, encodings, escapes, point tiers, errors, real files."""

from pathlib import Path

import pytest
import textgrid as reference
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from factories import DEMO_CORPUS, SHARED_DATA, textgrid_long, textgrid_short
from visemeflow.phonetics.textgrid import (
    STYLES,
    TextGridData,
    TextGridError,
    Tier,
    decode_textgrid_bytes,
    format_textgrid,
    parse_textgrid,
    read_textgrid,
)

DATA = SHARED_DATA

PHONES = [(0.0, 0.25, ""), (0.25, 0.31, "HH"), (0.31, 0.52, "AH0"), (0.52, 0.6, "L"), (0.6, 0.9, "OW1"), (0.9, 1.2, "sil")]
WORDS = [(0.0, 0.25, ""), (0.25, 0.9, "hello"), (0.9, 1.2, "")]


def parse_file(path: Path) -> TextGridData:
    grid = parse_textgrid(decode_textgrid_bytes(path.read_bytes()), str(path))
    assert read_textgrid(path) == grid
    return grid


def all_textgrids() -> list[Path]:
    files = sorted(DATA.rglob("*.TextGrid"))
    assert files, f"no TextGrid files under {DATA}: the shared data folder is missing"
    return files


# The older short layout: "ooTextFile short" in the file type, the class alone on the next line (old Praat, P2FA).
OO_SHORT = '''File type = "ooTextFile short"
"TextGrid"

0.0
1.2
<exists>
2
"IntervalTier"
"words"
0.0
1.2
3
0.0
0.25
""
0.25
0.9
"hello"
0.9
1.2
""
"IntervalTier"
"phones"
0.0
1.2
6
0.0
0.25
""
0.25
0.31
"HH"
0.31
0.52
"AH0"
0.52
0.6
"L"
0.6
0.9
"OW1"
0.9
1.2
"sil"
'''


def _reference(path: Path) -> list[tuple[str, str, list[tuple[float, float, str]]]]:
    """What the `textgrid` package reads: (kind, name, items) per tier."""
    grid = reference.TextGrid.fromFile(str(path))
    out = []
    for tier in grid.tiers:
        if isinstance(tier, reference.IntervalTier):
            out.append(("IntervalTier", tier.name, [(iv.minTime, iv.maxTime, iv.mark) for iv in tier]))
        else:
            out.append(("TextTier", tier.name, [(p.time, p.time, p.mark) for p in tier]))
    return out


def _ours_as_reference(grid: TextGridData) -> list[tuple[str, str, list[tuple[float, float, str]]]]:
    """Our result as the package reports it: times rounded to 5 digits, zero-length intervals dropped."""
    out = []
    for tier in grid.tiers:
        items = [(round(a, 5), round(b, 5), s) for a, b, s in tier.items]
        if tier.kind == "IntervalTier":
            items = [x for x in items if x[1] > x[0]]
        out.append((tier.kind, tier.name, items))
    return out


def test_ooTextFile_short_header_is_read(tmp_path):
    path = tmp_path / "p2fa.TextGrid"
    path.write_text(OO_SHORT, encoding="utf-8")
    grid = read_textgrid(path)
    assert [t.name for t in grid.tiers] == ["words", "phones"]
    assert grid.tier(("phones",)).items == tuple(PHONES)
    assert grid.tier(("words",)).items == tuple(WORDS)
    assert grid == parse_textgrid(textgrid_long(PHONES, 1.2, words=WORDS))
    assert _ours_as_reference(grid) == _reference(path)  # the package reads this layout too


def test_ooTextFile_short_header_still_requires_a_textgrid():
    text = OO_SHORT.replace('"TextGrid"', '"PitchTier"', 1)
    with pytest.raises(TextGridError, match=r"old\.TextGrid.*'PitchTier'"):
        parse_textgrid(text, "old.TextGrid")
    with pytest.raises(TextGridError, match=r"old\.TextGrid.*'ooTextFile long'"):
        parse_textgrid(OO_SHORT.replace("ooTextFile short", "ooTextFile long"), "old.TextGrid")


# every text layout Praat writes, in every encoding it writes (and UTF-8 with a BOM, as Windows editors save)
ENCODINGS = {
    "utf-8": ("utf-8", b""),
    "utf-8 BOM": ("utf-8", b"\xef\xbb\xbf"),
    "utf-16-be BOM": ("utf-16-be", b"\xfe\xff"),  # Praat's UTF-16
    "utf-16-le BOM": ("utf-16-le", b"\xff\xfe"),
}
INTERVAL_TIERS = (
    Tier("words", "IntervalTier", 0.0, 1.2, tuple(WORDS)),
    Tier("phones", "IntervalTier", 0.0, 1.2, ((0.0, 0.25, ""), (0.25, 0.31, "ʃ"), (0.31, 0.52, 'say ""hi""'),
                                             (0.52, 0.6, "中"), (0.6, 0.6, "zero"), (0.6, 0.9, "OW1"), (0.9, 1.2, "sil"))),
)
POINT_TIER = Tier("pitch", "TextTier", 0.0, 1.2, ((0.3, 0.3, "120"), (0.75, 0.75, "H*")))


@pytest.mark.parametrize("encoding", sorted(ENCODINGS))
@pytest.mark.parametrize("style", STYLES)
def test_every_variant_reads_like_the_textgrid_package(tmp_path, style, encoding):
    codec, bom = ENCODINGS[encoding]
    path = tmp_path / "v.TextGrid"
    path.write_bytes(bom + format_textgrid(INTERVAL_TIERS, 0.0, 1.2, style=style).encode(codec))
    grid = read_textgrid(path)
    assert grid == TextGridData(0.0, 1.2, INTERVAL_TIERS)
    assert _ours_as_reference(grid) == _reference(path)


@pytest.mark.parametrize("encoding", sorted(ENCODINGS))
@pytest.mark.parametrize("style", STYLES)
def test_every_variant_with_a_point_tier(tmp_path, style, encoding):
    """A TextTier next to interval tiers: the package reads it in the long layout only; ours in every layout."""
    codec, bom = ENCODINGS[encoding]
    tiers = (INTERVAL_TIERS[1], POINT_TIER)
    path = tmp_path / "p.TextGrid"
    path.write_bytes(bom + format_textgrid(tiers, 0.0, 1.2, style=style).encode(codec))
    grid = read_textgrid(path)
    assert grid == TextGridData(0.0, 1.2, tiers)
    if style == "long":  # the package cannot read point tiers in the short layouts (bench/textgrid_readers.py)
        assert _ours_as_reference(grid) == _reference(path)


def test_read_textgrid_errors_name_the_file(tmp_path):
    with pytest.raises(TextGridError, match=r"missing\.TextGrid: cannot read"):
        read_textgrid(tmp_path / "missing.TextGrid")
    odd = tmp_path / "odd.TextGrid"
    odd.write_bytes(b"\xff\xfe" + 'File type = "ooTextFile"'.encode("utf-16-le") + b"\x00")  # odd byte count
    with pytest.raises(TextGridError, match=r"odd\.TextGrid.*UTF-16"):
        read_textgrid(odd)
    latin = tmp_path / "latin.TextGrid"
    latin.write_bytes(format_textgrid(INTERVAL_TIERS[:1], 0.0, 1.2, style="short").replace("hello", "é").encode("latin-1"))
    assert read_textgrid(latin).tiers[0].items[1][2] == "é"  # Praat's "try ISO Latin-1" setting


def test_format_textgrid_rejects_an_unknown_style():
    with pytest.raises(ValueError, match="unknown TextGrid style 'binary'"):
        format_textgrid(INTERVAL_TIERS, 0.0, 1.2, style="binary")
    for style in STYLES:
        assert parse_textgrid(format_textgrid((), 0.0, 2.0, style=style)) == TextGridData(0.0, 2.0, ())


def test_long_and_short_format_give_identical_tiers():
    long = parse_textgrid(textgrid_long(PHONES, 1.2, words=WORDS), "long.TextGrid")
    short = parse_textgrid(textgrid_short(PHONES, 1.2, words=WORDS), "short.TextGrid")
    assert long == short
    assert (long.start_s, long.end_s) == (0.0, 1.2)
    assert [t.name for t in long.tiers] == ["words", "phones"]
    assert all(t.kind == "IntervalTier" and (t.start_s, t.end_s) == (0.0, 1.2) for t in long.tiers)
    assert long.tiers[1].items == tuple(PHONES)
    assert long.tiers[0].items == tuple(WORDS)


@pytest.mark.parametrize("encoding", ["utf-16", "utf-16-le", "utf-16-be", "utf-8-sig"])
def test_unicode_labels_with_byte_order_mark(encoding):
    phones = [(0.0, 0.4, "ʃ"), (0.4, 0.9, "œ̃"), (0.9, 1.0, "ü3")]
    text = textgrid_long(phones, 1.0, tier="phone")
    data = text.encode(encoding)
    if encoding in ("utf-16-le", "utf-16-be"):  # these codecs write no BOM; Praat does
        data = "\ufeff".encode(encoding) + data
    assert data[:2] in (b"\xff\xfe", b"\xfe\xff") or data[:3] == b"\xef\xbb\xbf"
    decoded = decode_textgrid_bytes(data)
    assert not decoded.startswith("\ufeff")
    grid = parse_textgrid(decoded, "bom.TextGrid")
    assert grid.tier(("phone",)).items == tuple(phones)


def test_plain_utf8_and_latin1_fallback():
    text = textgrid_short([(0.0, 1.0, "é")], 1.0)
    assert parse_textgrid(decode_textgrid_bytes(text.encode("utf-8"))).tiers[0].items[0][2] == "é"
    # not valid UTF-8 and no BOM: read as Latin-1 rather than failing
    assert parse_textgrid(decode_textgrid_bytes(text.encode("latin-1"))).tiers[0].items[0][2] == "é"


def test_doubled_quotes_are_literal_quotes():
    text = (
        'File type = "ooTextFile"\nObject class = "TextGrid"\n\n0\n1\n<exists>\n1\n"IntervalTier"\n"phones"\n0\n1\n3\n'
        '0\n0.2\n"say ""hi"""\n0.2\n0.5\n""""\n0.5\n1\n"a ""b"" c"\n'
    )
    items = parse_textgrid(text).tiers[0].items
    assert [label for _, _, label in items] == ['say "hi"', '"', 'a "b" c']
    assert [(a, b) for a, b, _ in items] == [(0.0, 0.2), (0.2, 0.5), (0.5, 1.0)]
    # the factory escapes the same way, in both formats
    labels = [(0.0, 0.5, 'x"'), (0.5, 1.0, '""')]
    assert parse_textgrid(textgrid_long(labels, 1.0)).tiers[0].items == tuple(labels)
    assert parse_textgrid(textgrid_short(labels, 1.0)).tiers[0].items == tuple(labels)


def test_label_spanning_lines_and_looking_like_syntax():
    tricky = [(0.0, 0.5, "xmin = 3\nitem [2]:"), (0.5, 1.0, "<exists> 12 !x")]
    for build in (textgrid_long, textgrid_short):
        assert parse_textgrid(build(tricky, 1.0)).tiers[0].items == tuple(tricky)


POINT_AND_INTERVALS = '''File type = "ooTextFile"
Object class = "TextGrid"

xmin = 0
xmax = 2
tiers? <exists>
size = 3
item []:
    item [1]:
        class = "TextTier"
        name = "phones"
        xmin = 0
        xmax = 2
        points: size = 2
        points [1]:
            number = 0.5
            mark = "peak"
        points [2]:
            number = 1.25
            mark = "low"
    item [2]:
        class = "IntervalTier"
        name = "phones"
        xmin = 0
        xmax = 2
        intervals: size = 2
        intervals [1]:
            xmin = 0
            xmax = 1
            text = "AA1"
        intervals [2]:
            xmin = 1
            xmax = 2
            text = ""
    item [3]:
        class = "IntervalTier"
        name = "words"
        xmin = 0
        xmax = 2
        intervals: size = 1
        intervals [1]:
            xmin = 0
            xmax = 2
            text = "ah"
'''


def test_text_tier_next_to_interval_tiers():
    grid = parse_textgrid(POINT_AND_INTERVALS, "points.TextGrid")
    assert [(t.kind, t.name) for t in grid.tiers] == [("TextTier", "phones"), ("IntervalTier", "phones"), ("IntervalTier", "words")]
    assert grid.tiers[0].items == ((0.5, 0.5, "peak"), (1.25, 1.25, "low"))
    # a point tier is never returned as the interval tier, even when its name matches first
    assert grid.tier(("phones",)) is grid.tiers[1]
    assert grid.tier(("words",)).items == ((0.0, 2.0, "ah"),)


def test_tier_lookup_is_case_insensitive_and_in_order():
    text = textgrid_short(PHONES, 1.2, tier="PHONES", words=WORDS).replace('"words"', '"Words"')
    grid = parse_textgrid(text)
    phones, words = grid.tiers[1], grid.tiers[0]
    assert grid.tier(("phones",)) is phones
    assert grid.tier(("Phones",)) is phones
    assert grid.tier(("WORDS",)) is words
    assert grid.tier(("phone", "words", "phones")) is words  # first name that exists wins
    assert grid.tier(("phones", "words")) is phones
    assert grid.tier(("phone", "phonemes")) is None
    assert grid.tier(()) is None


def test_duplicate_tier_names_return_the_first():
    one = textgrid_short([(0.0, 1.0, "a")], 1.0, tier="phones")
    two = textgrid_short([(0.0, 1.0, "b")], 1.0, tier="phones")
    # splice the second tier into the first file: two tiers named "phones"
    head, tier_a = one.split('"IntervalTier"', 1)
    tier_b = two.split('"IntervalTier"', 1)[1]
    text = head.replace("<exists>\n1\n", "<exists>\n2\n") + '"IntervalTier"' + tier_a + '"IntervalTier"' + tier_b
    grid = parse_textgrid(text)
    assert len(grid.tiers) == 2
    assert grid.tier(("phones",)).items == ((0.0, 1.0, "a"),)


def test_no_tiers():
    grid = parse_textgrid('File type = "ooTextFile"\nObject class = "TextGrid"\n0\n3.5\n<absent>\n')
    assert grid.tiers == () and grid.end_s == 3.5 and grid.tier(("phones",)) is None


@pytest.mark.parametrize("cut", [0.2, 0.5, 0.8, 0.97])
def test_truncated_file_names_the_file(cut):
    text = textgrid_long(PHONES, 1.2, words=WORDS)
    with pytest.raises(TextGridError, match="cut.TextGrid") as info:
        parse_textgrid(text[: int(len(text) * cut)], "/data/cut.TextGrid")
    assert "/data/cut.TextGrid" in str(info.value)


@pytest.mark.parametrize(
    "header",
    [
        'File type = "ooTextFile"\nObject class = "Pitch 1"\n',
        'File type = "ooBinaryFile"\nObject class = "TextGrid"\n',
        "just some text\n",
        "",
    ],
)
def test_wrong_header_names_the_file(header):
    body = textgrid_short(PHONES, 1.2).split("\n", 2)[2]
    with pytest.raises(TextGridError) as info:
        parse_textgrid(header + body, "spk/bad.TextGrid")
    assert "spk/bad.TextGrid" in str(info.value)


def _time_lines(lines: list[str], key: str) -> list[int]:
    return [i for i, line in enumerate(lines) if line.strip().startswith(key + " =")]


# which time line of a long-format file to spoil: (key, occurrence)
TIME_FIELDS = {
    "grid xmax": ("xmax", 0),
    "tier xmin": ("xmin", 1),
    "tier xmax": ("xmax", 1),
    "interval 2 xmin": ("xmin", 3),
    "interval 2 xmax": ("xmax", 3),
    "last interval xmax": ("xmax", -1),
}


@pytest.mark.parametrize("value", ["abc", "0.3.1", "1,5", "5s", "0x10", "--undefined--", ""])
@pytest.mark.parametrize("field", sorted(TIME_FIELDS))
def test_non_numeric_time_names_the_file(value, field):
    lines = textgrid_long(PHONES, 1.2).splitlines()
    key, occurrence = TIME_FIELDS[field]
    target = _time_lines(lines, key)[occurrence]
    lines[target] = f"{lines[target].split('=')[0]}= {value}"
    with pytest.raises(TextGridError) as info:
        parse_textgrid("\n".join(lines), "x/y.TextGrid")
    assert "x/y.TextGrid" in str(info.value)


@pytest.mark.parametrize("count", ["nan", "inf", "-1", "2.5", "abc"])
@pytest.mark.parametrize("which", ["size", "intervals: size"])
def test_bad_counts_name_the_file(count, which):
    lines = textgrid_long(PHONES, 1.2, words=WORDS).splitlines()
    target = [i for i, line in enumerate(lines) if line.strip().startswith(which + " =")][0]
    lines[target] = f"{which} = {count}"
    with pytest.raises(TextGridError, match=r"c\.TextGrid"):
        parse_textgrid("\n".join(lines), "c.TextGrid")


def test_values_after_the_declared_tiers_are_an_error():
    """A tier count smaller than the tiers written would silently drop tiers."""
    text = textgrid_short(PHONES, 1.2, words=WORDS).replace("<exists>\n2\n", "<exists>\n1\n", 1)
    with pytest.raises(TextGridError, match=r"extra\.TextGrid.*after the last of 1 tier"):
        parse_textgrid(text, "extra.TextGrid")
    text = textgrid_short(PHONES, 1.2).replace("\n6\n", "\n5\n", 1)  # one interval more than declared
    with pytest.raises(TextGridError, match=r"extra\.TextGrid"):
        parse_textgrid(text, "extra.TextGrid")
    # comments and blank lines after the end are fine
    assert parse_textgrid(textgrid_short(PHONES, 1.2) + "\n! a comment\n\n").tiers[0].items == tuple(PHONES)


def test_unknown_tier_class_and_bad_count():
    text = textgrid_short(PHONES, 1.2).replace('"IntervalTier"', '"PitchTier"')
    with pytest.raises(TextGridError, match=r"t\.TextGrid.*PitchTier"):
        parse_textgrid(text, "t.TextGrid")
    text = textgrid_short(PHONES, 1.2).replace("\n6\n", "\n2.5\n", 1)
    with pytest.raises(TextGridError, match=r"t\.TextGrid.*count"):
        parse_textgrid(text, "t.TextGrid")


def test_nan_time_is_read_as_a_number():
    """`nan` (as Python writers put it) is kept as a value, so checks downstream can name the interval."""
    text = textgrid_short(PHONES, 1.2).replace("\n0.25\n0.31\n", "\nnan\n0.31\n", 1)
    items = parse_textgrid(text).tiers[0].items
    assert len(items) == len(PHONES)
    assert items[1][0] != items[1][0] and items[1][1:] == (0.31, "HH")


# ---- real files ------------------------------------------------------------------------------

def test_every_shared_textgrid_parses():
    files = all_textgrids()
    assert len(files) >= 28
    for path in files:
        grid = parse_file(path)
        assert grid.tiers, path
        for tier in grid.tiers:
            assert tier.items, (path, tier.name)
            for a, b, _ in tier.items:
                assert grid.start_s - 1e-9 <= a <= b <= grid.end_s + 1e-9, (path, tier.name, a, b)
            if tier.kind == "IntervalTier":  # in order and not overlapping
                assert all(x[1] <= y[0] for x, y in zip(tier.items, tier.items[1:])), (path, tier.name)


def test_shared_textgrids_agree_with_the_textgrid_package():
    compared = 0
    for path in all_textgrids():
        try:
            ref = reference.TextGrid.fromFile(str(path))
        except Exception:  # the reference cannot read every valid file (mary.TextGrid); ours must
            continue
        ours = parse_file(path)
        assert [t.name for t in ours.tiers] == [t.name for t in ref.tiers], path
        for tier, ref_tier in zip(ours.tiers, ref.tiers):
            # the reference drops zero-length intervals and rounds times to 5 digits
            items = [(a, b, s) for a, b, s in tier.items if round(b, 5) > round(a, 5)]
            assert len(items) == len(ref_tier), (path, tier.name)
            for (a, b, label), iv in zip(items, ref_tier):
                assert abs(a - iv.minTime) < 1e-4 and abs(b - iv.maxTime) < 1e-4, (path, tier.name, a, b)
                assert label == iv.mark, (path, tier.name)
        compared += 1
    assert compared >= 27


@pytest.mark.parametrize("style", STYLES)
def test_real_and_demo_files_in_every_variant(tmp_path, style):
    """Every real and demo TextGrid rewritten in each layout (UTF-8 and Praat's UTF-16) reads back the same;
    the package, where it reads the rewritten file, agrees with it."""
    files = [*all_textgrids(), *sorted(DEMO_CORPUS.glob("*/*.TextGrid"))]
    assert len(files) >= 53
    read_by_reference = 0
    for i, path in enumerate(files):
        grid = parse_file(path)
        for codec, bom in (ENCODINGS["utf-8"], ENCODINGS["utf-16-be BOM"]):
            out = tmp_path / f"{i}-{codec}.TextGrid"
            out.write_bytes(bom + format_textgrid(grid.tiers, grid.start_s, grid.end_s, style=style).encode(codec))
            assert read_textgrid(out) == grid, (path, style, codec)
            has_points = any(t.kind == "TextTier" for t in grid.tiers)
            if style == "long" or not has_points:
                assert _ours_as_reference(grid) == _reference(out), (path, style, codec)
                read_by_reference += 1
    assert read_by_reference >= 2 * (len(files) - 1)


def test_mary_textgrid_with_point_tier():
    grid = parse_file(DATA / "praatio_examples" / "mary.TextGrid")  # short format with a point tier
    assert [(t.kind, t.name) for t in grid.tiers] == [("IntervalTier", "phone"), ("IntervalTier", "word"), ("TextTier", "pitch")]
    assert grid.end_s == pytest.approx(1.869687)
    phone = grid.tier(("phones", "phone"))
    assert len(phone.items) == 16
    assert [x[2] for x in phone.items[:4]] == ["", "m", "ə", "r"]
    assert [x[2] for x in grid.tiers[1].items] == ["", "mary", "rolled", "the", "barrel", ""]
    assert grid.tiers[2].items[0] == (pytest.approx(0.5978689404359245), pytest.approx(0.5978689404359245), "120")
    assert [x[2] for x in grid.tiers[2].items] == ["120", "85", "97", "104"]
    assert grid.tier(("pitch",)) is None


def test_charsiu_short_format():
    grid = parse_file(DATA / "charsiu_mandarin" / "SSB16240001.TextGrid")
    labels = [x[2] for x in grid.tier(("phones",)).items]
    assert labels[:5] == ["[SIL]", "zh", "e4", "j", "ve2"]
    assert labels[-2:] == ["ing2", "[SIL]"]


# ---- round trip --------------------------------------------------------------------------------

_label = st.lists(
    st.one_of(
        st.sampled_from(['"', '""', " ", "\n", "ə", "ʃ", "ü", "中", "!x", "<exists>", "[1]", "= ", "1.5", "nan"]),
        st.characters(blacklist_categories=("Cs", "Cc")),
    ),
    max_size=6,
).map("".join)


@st.composite
def _intervals(draw):
    n = draw(st.integers(1, 12))
    cuts = sorted(draw(st.lists(st.floats(0.0, 100.0, allow_nan=False, width=64), min_size=n + 1, max_size=n + 1)))
    return [(cuts[i], cuts[i + 1], draw(_label)) for i in range(n)]


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_intervals(), st.sampled_from(["phones", "Phone tier", 'q"t']))
def test_round_trip_long_and_short(intervals, tier_name):
    xmax = intervals[-1][1]
    for build in (textgrid_long, textgrid_short):
        grid = parse_textgrid(build(intervals, xmax, tier=tier_name, words=intervals[:1]), "rt.TextGrid")
        assert grid.end_s == xmax
        assert [t.name for t in grid.tiers] == ["words", tier_name]
        assert grid.tiers[1].items == tuple(intervals)
        assert grid.tiers[0].items == tuple(intervals[:1])


def test_a_hand_edited_textgrid_error_names_the_line_and_what_stands_there():
    """A word where a number belongs is skipped by the format (as Praat skips labels), so the error used to quote
    the next value ('B', then 'HH' on the next line): it now names the word; an open quote swallowed the lines after it and was quoted whole, newlines and all."""
    good = textgrid_long(PHONES, 1.2)
    lines = good.splitlines()
    at = next(i for i, line in enumerate(lines) if line.strip().startswith("xmax = 0.31"))
    bad_number = "\n".join(lines[:at] + ["            xmax = abc "] + lines[at + 1:])
    # the word is named as what is wrong: the value "found" after it is the next line's (it said: found 'HH')
    with pytest.raises(TextGridError, match=rf"^x\.TextGrid: expected a number for xmax of interval 2 in tier "
                                            rf"'phones' at line {at + 1} \('xmax = abc'\): 'abc' is not a number$"):
        parse_textgrid(bad_number, "x.TextGrid")
    text_line = at + 1
    assert lines[text_line].strip() == 'text = "HH"'
    open_quote = "\n".join(lines[:text_line] + ['            text = "HH '] + lines[text_line + 1:])
    with pytest.raises(TextGridError, match=rf"^x\.TextGrid: the text of interval 2 in tier 'phones' opens a quote "
                                            rf"at line {text_line + 1} that runs over \d+ lines into the next "
                                            rf"entries \(a quote left open\?\)$"):
        parse_textgrid(open_quote, "x.TextGrid")
