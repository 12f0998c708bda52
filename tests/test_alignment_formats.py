"""Alignment formats other than MFA's text TextGrid: Praat binary and chronological TextGrids, SPPAS .xra,
HTK label files and MLFs. Each is written here from its specification and must give the phone intervals the
TextGrid reader gives, through discovery and ingest; bad files are rejects naming the file and the line."""

import re
import struct
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from factories import textgrid_long, write_wav
from visemeflow.ingest import CorpusEntry, IngestConfig, IngestError, discover_corpus, ingest_utterance
from visemeflow.phonetics.htk import LabelFileError, load_mlf, parse_htk_label, parse_mlf, wildcard_match
from visemeflow.phonetics.textgrid import (
    TextGridData,
    TextGridError,
    Tier,
    parse_textgrid,
    parse_textgrid_binary,
    read_textgrid,
)
from visemeflow.phonetics.xra import XraError, parse_xra
from visemeflow.schemas import C

PRAAT_FILES = Path(__file__).resolve().parent / "data" / "praat"
CONFIG = IngestConfig()

# one utterance, "hello", in ARPAbet: (start, end, label)
PHONES = [(0.0, 0.2, "sil"), (0.2, 0.3, "HH"), (0.3, 0.45, "AH0"), (0.45, 0.55, "L"), (0.55, 0.8, "OW1"),
          (0.8, 1.0, "sil")]
WORDS = [(0.0, 0.2, ""), (0.2, 0.8, "hello"), (0.8, 1.0, "")]


# ---- Praat binary TextGrid, written from the layout --------------------------------------------

def _w16(text: str) -> bytes:
    """Praat's binary string: 16-bit length and ASCII, or 0xFFFF, the character count and UTF-16BE."""
    if text.isascii():
        return struct.pack(">H", len(text)) + text.encode("ascii")
    return b"\xff\xff" + struct.pack(">H", len(text)) + text.encode("utf-16-be")


def binary_textgrid(tiers: list[Tier], xmin: float, xmax: float) -> bytes:
    out = [b"ooBinaryFile", bytes([8]), b"TextGrid", struct.pack(">dd", xmin, xmax)]
    if not tiers:
        return b"".join(out + [b"\x00"])
    out += [b"\x01", struct.pack(">i", len(tiers))]
    for tier in tiers:
        out += [bytes([len(tier.kind)]), tier.kind.encode(), _w16(tier.name),
                struct.pack(">ddi", tier.start_s, tier.end_s, len(tier.items))]
        for a, b, text in tier.items:
            out += [struct.pack(">dd", a, b) if tier.kind == "IntervalTier" else struct.pack(">d", a), _w16(text)]
    return b"".join(out)


BINARY_TIERS = [
    Tier("words", "IntervalTier", 0.0, 1.0, tuple(WORDS)),
    Tier("phones", "IntervalTier", 0.0, 1.0, tuple(PHONES[:2]) + ((0.3, 0.45, "ʃə"),) + tuple(PHONES[3:])),
    Tier("tönes", "TextTier", 0.0, 1.0, ((0.5, 0.5, "H*"), (0.9, 0.9, "𝒜"))),
]


def test_binary_textgrid_from_the_layout():
    grid = parse_textgrid_binary(binary_textgrid(BINARY_TIERS, 0.0, 1.0), "b.TextGrid")
    assert grid == TextGridData(0.0, 1.0, tuple(BINARY_TIERS))
    assert parse_textgrid_binary(binary_textgrid([], 0.0, 2.5)) == TextGridData(0.0, 2.5, ())


def test_binary_textgrids_praat_wrote_read_like_its_text_files():
    """Files written by Praat itself (tests/data/praat/make_files.py): binary, chronological, long and short text
    (UTF-16), all the same TextGrid."""
    grids = {name: read_textgrid(PRAAT_FILES / f"{name}.TextGrid")
             for name in ("binary", "chronological", "long_utf16", "short_utf16")}
    assert len(set(grids.values())) == 1, grids
    grid = grids["binary"]
    assert [(t.name, t.kind) for t in grid.tiers] == [("phones", "IntervalTier"), ("wörds", "IntervalTier"),
                                                     ("pitch", "TextTier")]
    assert grid.tiers[0].items == ((0.0, 0.25, ""), (0.25, 0.5, "@"), (0.5, 1.5, "aI"))
    assert grid.tiers[1].items[0][2] == "héllo ʃ" and grid.tiers[2].items == ((0.7, 0.7, "H*"),)
    astral = read_textgrid(PRAAT_FILES / "binary_astral.TextGrid")  # a character outside the BMP counts once
    assert [x[2] for x in astral.tiers[0].items] == ["𝒜x", 'say "hi"']


@pytest.mark.parametrize("cut", [13, 30, 60, -3])
def test_truncated_binary_textgrid_names_the_file(cut):
    data = binary_textgrid(BINARY_TIERS, 0.0, 1.0)
    with pytest.raises(TextGridError, match=r"^spk/cut\.TextGrid: binary TextGrid ends early"):
        parse_textgrid_binary(data[:cut], "spk/cut.TextGrid")


def test_binary_file_of_another_class_or_with_trailing_bytes():
    with pytest.raises(TextGridError, match=r"x\.Pitch: a Praat binary 'Pitch' file, not a TextGrid"):
        parse_textgrid_binary(b"ooBinaryFile\x05Pitch" + bytes(40), "x.Pitch")
    with pytest.raises(TextGridError, match=r"t\.TextGrid: 2 unexpected byte"):
        parse_textgrid_binary(binary_textgrid(BINARY_TIERS, 0.0, 1.0) + b"\x00\x01", "t.TextGrid")


# ---- Praat chronological text TextGrid ---------------------------------------------------------

CHRONOLOGICAL = '''"Praat chronological TextGrid text file"
0 1   ! Time domain.
2   ! Number of tiers.
"IntervalTier" "phones" 0 1
"TextTier" "a ""quoted"" tier!" 0 1

! phones:
1 0 0.2
"sil"

! a "quoted" tier!:
2 0.25
"x ! y"
''' + "".join(f'\n! phones:\n1 {a!r} {b!r}\n"{label}"\n' for a, b, label in PHONES[1:])


def test_chronological_textgrid():
    grid = parse_textgrid(CHRONOLOGICAL, "c.TextGrid")
    assert grid.tier(("phones",)).items == tuple(PHONES)
    assert grid.tiers[1] == Tier('a "quoted" tier!', "TextTier", 0.0, 1.0, ((0.25, 0.25, "x ! y"),))


def test_chronological_textgrid_naming_a_tier_it_does_not_declare():
    with pytest.raises(TextGridError, match=r"c\.TextGrid: entry 2 names tier 3; the file declares 2"):
        parse_textgrid(CHRONOLOGICAL.replace("\n2 0.25\n", "\n3 0.25\n"), "c.TextGrid")


# ---- shared helpers for the label formats ------------------------------------------------------

def reference_rows(tmp_path: Path) -> list[dict]:
    """The phone rows of the same utterance read from a long-format TextGrid (words and phones)."""
    folder = tmp_path / "ref" / "s"
    write_wav(folder / "u.wav", 1.0)
    (folder / "u.TextGrid").write_text(textgrid_long([(a, b, t) for a, b, t in PHONES], 1.0, words=WORDS))
    (entry,) = discover_corpus(tmp_path / "ref").entries
    return ingest_utterance(entry, CONFIG).phones


def comparable(rows: list[dict]) -> list[tuple]:
    return [(r[C.INDEX], r[C.PART], r[C.LABEL], r[C.VISEME], round(r[C.START_S], 9), round(r[C.END_S], 9),
             r[C.WORD], r[C.WORD_INDEX]) for r in rows]


def only_entry(corpus: Path, utterance_id: str = "s/u") -> CorpusEntry:
    found = discover_corpus(corpus)
    assert not found.rejects, found.rejects
    (entry,) = [e for e in found.entries if e.utterance_id == utterance_id]
    return entry


def test_binary_textgrid_is_ingested_like_the_text_one(tmp_path):
    folder = tmp_path / "c" / "s"
    write_wav(folder / "u.wav", 1.0)
    tiers = [Tier("words", "IntervalTier", 0.0, 1.0, tuple(WORDS)), Tier("phones", "IntervalTier", 0.0, 1.0,
                                                                          tuple(PHONES))]
    (folder / "u.TextGrid").write_bytes(binary_textgrid(tiers, 0.0, 1.0))
    entry = only_entry(tmp_path / "c")
    assert entry.alignment_format == "textgrid"
    assert comparable(ingest_utterance(entry, CONFIG).phones) == comparable(reference_rows(tmp_path))


# ---- SPPAS .xra --------------------------------------------------------------------------------

def _xra_annotation(a: float, b: float, label: str, v14: bool = True) -> str:
    if v14:
        return (f'<Annotation><Location><Interval><Begin midpoint="{a!r}" radius="0.005"/>'
                f'<End midpoint="{b!r}" radius="0.005"/></Interval></Location>'
                f'<Label><Tag>{label}</Tag></Label></Annotation>')
    return (f'<Annotation><Location><Localization score="1.0"><Timeinterval><Begin midpoint="{a!r}"/>'
            f'<End midpoint="{b!r}"/></Timeinterval></Localization></Location>'
            f'<Label><Text score="1.0">{label}</Text></Label></Annotation>')


def xra_document(phones, words, v14: bool = True) -> str:
    """An XRA document as SPPAS writes it: format 1.4 (Interval, Tag) or 1.2 (Localization, Timeinterval, Text)."""
    tiers = []
    for tid, name, items in (("t1", "PhonAlign", phones), ("t2", "TokensAlign", words)):
        body = "\n".join(_xra_annotation(a, b, text, v14) for a, b, text in items)
        tiers.append(f'<Tier id="{tid}" tiername="{name}">\n{body}\n</Tier>')
    return (f"<?xml version='1.0' encoding='UTF-8'?>\n<Document author=\"SPPAS\" format=\"{'1.4' if v14 else '1.2'}\">\n"
            "<Metadata><Entry key=\"software_name\">SPPAS</Entry></Metadata>\n" + "\n".join(tiers) +
            '\n<Media id="m1" url="u.wav" mimetype="audio/wav"><Tier id="t1"/><Tier id="t2"/></Media>\n'
            '<Hierarchy><Link type="TimeAlignment" from="t2" to="t1"/></Hierarchy>\n</Document>\n')


@pytest.mark.parametrize("v14", [True, False], ids=["xra-1.4", "xra-1.2"])
def test_xra_is_ingested_like_the_textgrid(tmp_path, v14):
    folder = tmp_path / "c" / "s"
    write_wav(folder / "u.wav", 1.0)
    (folder / "u.xra").write_text(xra_document(PHONES, [w for w in WORDS if w[2]], v14), encoding="utf-8")
    entry = only_entry(tmp_path / "c")
    assert entry.alignment_format == "xra"
    result = ingest_utterance(entry, CONFIG)
    assert comparable(result.phones) == comparable(reference_rows(tmp_path))
    assert result.utterance[C.ALIGNMENT_FORMAT] == "xra" and result.utterance[C.INVENTORY] == "arpabet"


def test_xra_alternatives_by_score_points_and_namespaces():
    doc = b'''<?xml version="1.0"?>
<Document xmlns="http://www.sppas.org/xra" format="1.4">
 <Tier tiername="PhonAlign">
  <Annotation><Location>
    <Interval score="0.2"><Begin midpoint="0.0"/><End midpoint="0.5"/></Interval>
    <Interval score="0.8"><Begin midpoint="0.0"/><End midpoint="0.4"/></Interval>
  </Location><Label><Tag score="0.1">a</Tag><Tag score="0.9">E</Tag></Label></Annotation>
  <Annotation><Location><Interval><Begin midpoint="0.4"/><End midpoint="0.6"/></Interval></Location><Label/></Annotation>
 </Tier>
 <Tier tiername="Intonation">
  <Annotation><Location><Point midpoint="0.3" radius="0.001"/></Location><Label><Tag>H*</Tag></Label></Annotation>
 </Tier>
</Document>'''
    grid = parse_xra(doc, "n.xra")
    assert grid.tier(("PhonAlign",)).items == ((0.0, 0.4, "E"), (0.4, 0.6, ""))
    assert grid.tiers[1] == Tier("Intonation", "TextTier", 0.3, 0.3, ((0.3, 0.3, "H*"),))


@pytest.mark.parametrize(("change", "message"), [
    (lambda d: d.replace("</Tier>", "</Tie>", 1), r"line 5, column \d+: malformed XML: mismatched tag"),
    (lambda d: d.replace('<End midpoint="0.2"', '<End midpoint="soon"', 1), r"line 4: End has no numeric midpoint"),
    (lambda d: d.replace("<Document", "<Documents").replace("</Document>", "</Documents>"),
     r"line 2: not an XRA file \(root element 'Documents'"),
])
def test_bad_xra_is_a_reject_naming_file_and_line(tmp_path, change, message):
    folder = tmp_path / "c" / "s"
    write_wav(folder / "u.wav", 1.0)
    doc = xra_document(PHONES, [], True).replace("\n<Annotation>", "<Annotation>")  # line 4: the phone tier
    xra = folder / "u.xra"
    xra.write_text(change(doc), encoding="utf-8")
    with pytest.raises(IngestError) as info:
        ingest_utterance(only_entry(tmp_path / "c"), CONFIG)
    assert info.value.error_type == "BadAlignmentFile" and info.value.utterance_id == "s/u"
    assert info.value.path == str(xra.resolve())
    assert re.search(re.escape(f"s/u: {xra.resolve()}: ") + message, str(info.value)), str(info.value)
    with pytest.raises(XraError, match=r"u\.xra:\d+"):
        parse_xra(change(doc).encode(), "u.xra")


# ---- HTK label files ---------------------------------------------------------------------------

def htk_lines(phones, words: dict[float, str], seconds: bool = False, scores: bool = True) -> str:
    """`start end label [score] [word]` lines; the word on the first phone of each word (HVite -m style)."""
    lines = []
    for a, b, label in phones:
        times = f"{a:.6f} {b:.6f}" if seconds else f"{round(a * 1e7)} {round(b * 1e7)}"
        score = " -123.25" if scores else ""
        word = f" {words[a]}" if a in words else ""
        lines.append(f"{times} {label}{score}{word}")
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize(("seconds", "scores"), [(False, True), (False, False), (True, True)],
                         ids=["100ns+scores", "100ns", "seconds"])
def test_htk_label_file_is_ingested_like_the_textgrid(tmp_path, seconds, scores):
    folder = tmp_path / "c" / "s"
    write_wav(folder / "u.wav", 1.0)
    words = {0.0: "SENT-START", 0.2: "hello", 0.8: "SENT-END"}
    (folder / "u.lab").write_text(htk_lines(PHONES, words, seconds, scores) + "///\n0 100 x\n")
    entry = only_entry(tmp_path / "c")
    assert entry.alignment_format == "htk"
    result = ingest_utterance(entry, CONFIG)
    assert comparable(result.phones) == comparable(reference_rows(tmp_path))


def test_htk_words_run_to_the_next_word_or_silence():
    text = "0 1000000 sil\n1000000 2000000 h hi\n2000000 3000000 aI\n3000000 3500000 sp\n" \
           "3500000 4000000 j you\n4000000 5000000 u:\n5000000 6000000 sil SENT-END\n"
    grid = parse_htk_label(text, "w.lab")
    assert grid.tiers[1].items == ((0.1, 0.3, "hi"), (0.35, 0.5, "you"))
    assert grid.end_s == 0.6 and [x[2] for x in grid.tiers[0].items] == ["sil", "h", "aI", "sp", "j", "u:", "sil"]


@pytest.mark.parametrize(("text", "message"), [
    ("0 100 sil\nHELLO WORLD\n", r"^x\.lab:2: expected 'start end label"),
    ("0 100 sil\n100 200\n", r"^x\.lab:2: no label"),
    ("0 100 sil\n0.00001 0.00002 a\n", r"^x\.lab:2: times in seconds .* mixed with HTK integer times"),
    ("\n\n", r"^x\.lab: no labels"),
    ("#!MLF!#\n", r"^x\.lab:1: a master label file"),
])
def test_bad_label_files_name_file_and_line(text, message):
    with pytest.raises(LabelFileError, match=message):
        parse_htk_label(text, "x.lab")


def test_label_file_running_past_the_audio_is_a_reject_and_ending_early_is_not(tmp_path):
    folder = tmp_path / "c" / "s"
    write_wav(folder / "u.wav", 1.0)
    lab = folder / "u.lab"
    lab.write_text(htk_lines(PHONES + [(1.0, 1.5, "sil")], {}))
    with pytest.raises(IngestError) as info:
        ingest_utterance(only_entry(tmp_path / "c"), CONFIG)
    assert info.value.error_type == "AlignmentAudioMismatch" and info.value.path == str(lab.resolve())
    assert "s/u" in str(info.value) and "run past the end of the audio" in str(info.value)
    # within the tolerance it is fine; a label file may stop before the audio ends (the rest is silence)
    lab.write_text(htk_lines(PHONES[:-1] + [(0.8, 1.05, "sil")], {}))
    assert ingest_utterance(only_entry(tmp_path / "c"), CONFIG).phones[-1][C.END_S] == pytest.approx(1.05)
    lab.write_text(htk_lines(PHONES[:4], {}))
    assert ingest_utterance(only_entry(tmp_path / "c"), CONFIG).phones[-1][C.END_S] == pytest.approx(0.55)
    # a TextGrid says where the file ends: ending 0.45 s early is still a mismatch
    lab.unlink()
    (folder / "u.TextGrid").write_text(textgrid_long(PHONES[:4], 0.55))
    with pytest.raises(IngestError, match="alignment ends at 0.550 s"):
        ingest_utterance(only_entry(tmp_path / "c"), CONFIG)


def test_transcript_lab_is_not_an_alignment_but_a_transcript_to_align(tmp_path):
    folder = tmp_path / "c" / "s"
    write_wav(folder / "t.wav", 1.0)
    (folder / "t.lab").write_text("HELLO WORLD\n")  # MFA's input transcript
    found = discover_corpus(tmp_path / "c")
    (entry,) = found.entries
    assert found.rejects == () and entry.alignment_format == "transcript"
    assert entry.alignment_path == str((folder / "t.lab").resolve())
    with pytest.raises(IngestError, match="transcripts are not aligned") as info:
        ingest_utterance(entry, CONFIG.model_copy(update={"align_transcripts": False}))
    assert info.value.error_type == "MissingAlignment"
    # with a TextGrid beside it (MFA's output) the TextGrid is the alignment
    (folder / "t.TextGrid").write_text(textgrid_long(PHONES, 1.0))
    (entry,) = discover_corpus(tmp_path / "c").entries
    assert entry.alignment_format == "textgrid"


# ---- HTK master label files ----------------------------------------------------------------------

def mlf(entries: dict[str, str]) -> str:
    return "#!MLF!#\n" + "".join(f'"{pattern}"\n{body}.\n' for pattern, body in entries.items())


def test_mlf_layout_and_lookup():
    text = mlf({"*/a01.lab": "0 10 sil\n", "/data/spk2/a01.rec": "0 20 sil\n", "b?.lab": "0 30 sil\n",
                "*.lab": "0 40 sil\n"}) + '"*/far.lab" -> /somewhere/else\n'
    entries = parse_mlf(text, "all.mlf")
    assert [(e.pattern, e.line) for e in entries] == [("*/a01.lab", 2), ("/data/spk2/a01.rec", 5), ("b?.lab", 8),
                                                      ("*.lab", 11), ("*/far.lab", 14)]
    assert entries[-1].redirect == "-> /somewhere/else"
    from visemeflow.phonetics.htk import MlfIndex

    index = MlfIndex(entries, "all.mlf")
    assert index.find("spk1", "a01").line == 2  # the first matching pattern wins, as in HTK
    assert index.find("spk1", "b7").line == 8
    assert index.find("spk1", "zz").line == 11
    assert MlfIndex(entries[1:], "all.mlf").find("spk1", "a01").line == 11  # /data/spk2/ names another folder
    assert MlfIndex(entries[1:], "all.mlf").find("spk2", "a01").line == 5
    with pytest.raises(LabelFileError, match=r"all\.mlf:14: the entry '\*/far\.lab' points elsewhere"):
        MlfIndex(entries[-1:], "all.mlf").tiers("x", "far")
    with pytest.raises(LabelFileError, match=r"all\.mlf: no entry matches x/nothing"):
        MlfIndex(entries[:1], "all.mlf").tiers("x", "nothing")


@settings(max_examples=400, deadline=None)
@given(st.text("ab*?%.", max_size=8), st.text("ab.%*?", max_size=8))
def test_mlf_wildcards_match_as_the_regex_translation_does(pattern, name):
    """The step-bounded matcher agrees with the obvious (backtracking) regex on short patterns and names."""
    regex = "".join({"*": ".*", "?": ".", "%": "."}.get(ch, re.escape(ch)) for ch in pattern)
    assert wildcard_match(pattern, name) == bool(re.fullmatch(regex, name, re.DOTALL))


@pytest.mark.parametrize(("text", "message"), [
    ('"*/a.lab"\n0 1 sil\n.\n', r"^m\.mlf:1: not an HTK master label file"),
    ('#!MLF!#\n"*/a.lab"\n0 1 sil\n', r"^m\.mlf:2: the entry '\*/a\.lab' does not end with a line holding '\.'"),
    ('#!MLF!#\n"*/a.lab"\n0 1 sil\n"*/b.lab"\n0 1 sil\n.\n', r"^m\.mlf:4: a new pattern before the '\.'"),
    ("#!MLF!#\n*/a.lab\n0 1 sil\n.\n", r"^m\.mlf:2: expected a quoted file name pattern"),
])
def test_malformed_mlf_names_file_and_line(text, message):
    with pytest.raises(LabelFileError, match=message):
        parse_mlf(text, "m.mlf")


def test_mlf_entries_are_found_per_utterance_and_priorities(tmp_path):
    corpus = tmp_path / "c"
    s = corpus / "s"
    for stem in ("u", "v", "w", "x", "y"):
        write_wav(s / f"{stem}.wav", 1.0)
    words = {0.2: "hello"}
    body = htk_lines(PHONES, words)
    other = htk_lines([(0.0, 0.5, "sil"), (0.5, 1.0, "AA1")], {})
    (s / "u.TextGrid").write_text(textgrid_long(PHONES, 1.0, words=WORDS))   # TextGrid beats .lab
    (s / "u.lab").write_text(other)
    (s / "v.xra").write_text(xra_document(PHONES, [w for w in WORDS if w[2]]))  # .xra beats .lab
    (s / "v.lab").write_text(other)
    (s / "w.lab").write_text(body)                                         # a .lab beats the MLF
    (s / "speaker.mlf").write_text(mlf({"*/w.lab": other, "*/x.lab": body, "*/y.lab": other}))
    (corpus / "corpus.mlf").write_text(mlf({"*/x.lab": other, "s/y.rec": body, "z.lab": other}))
    found = discover_corpus(corpus)
    assert found.rejects == ()
    by_id = {e.utterance_id: e for e in found.entries}
    assert {k: (Path(e.alignment_path).name, e.alignment_format) for k, e in by_id.items()} == {
        "s/u": ("u.TextGrid", "textgrid"), "s/v": ("v.xra", "xra"), "s/w": ("w.lab", "htk"),
        "s/x": ("speaker.mlf", "mlf"), "s/y": ("speaker.mlf", "mlf")}
    assert by_id["s/x"].alignment_key == "s/x"
    expected = comparable(reference_rows(tmp_path))
    for uid in ("s/u", "s/v", "s/w", "s/x"):
        assert comparable(ingest_utterance(by_id[uid], CONFIG).phones) == expected, uid
    assert [r[C.LABEL] for r in ingest_utterance(by_id["s/y"], CONFIG).phones] == ["sil", "AA1"]
    # the hash of an MLF utterance covers its own entry only: another entry's edit leaves it alone
    (s / "speaker.mlf").write_text(mlf({"*/w.lab": other, "*/x.lab": body, "*/y.lab": body}))
    again = {e.utterance_id: e for e in discover_corpus(corpus).entries}
    assert again["s/x"].content_hash == by_id["s/x"].content_hash
    assert again["s/y"].content_hash != by_id["s/y"].content_hash
    # without the speaker's MLF, the corpus-wide one serves (s/y.rec names the folder)
    (s / "speaker.mlf").unlink()
    again = {e.utterance_id: e for e in discover_corpus(corpus).entries}
    assert Path(again["s/y"].alignment_path).name == "corpus.mlf"
    assert comparable(ingest_utterance(again["s/y"], CONFIG).phones) == expected
    assert [r[C.LABEL] for r in ingest_utterance(again["s/x"], CONFIG).phones] == ["sil", "AA1"]
    # rerunning one utterance finds its MLF entry too
    (only,) = discover_corpus(corpus, only="s/y").entries
    assert only == again["s/y"]


def test_bad_mlf_is_a_discovery_reject_and_bad_entry_an_ingest_reject(tmp_path):
    corpus = tmp_path / "c"
    write_wav(corpus / "s" / "a.wav", 1.0)
    write_wav(corpus / "s" / "b.wav", 1.0)
    broken = corpus / "s" / "broken.mlf"
    broken.write_text('#!MLF!#\n"*/a.lab"\n0 10000000 sil\n')
    found = discover_corpus(corpus)
    bad = [r for r in found.rejects if r.error_type == "BadAlignmentFile"]
    assert len(bad) == 1 and bad[0].path == str(broken) and f"{broken}:2:" in bad[0].message
    assert {r.utterance_id for r in found.rejects if r.error_type == "MissingAlignment"} == {"s/a", "s/b"}
    # a well-formed MLF with a bad label line: the utterance is a reject naming the file and the line
    broken.write_text(mlf({"*/a.lab": htk_lines(PHONES, {}), "*/b.lab": "0 10000000 sil\nten twenty sil\n"}))
    by_id = {e.utterance_id: e for e in discover_corpus(corpus).entries}
    ingest_utterance(by_id["s/a"], CONFIG)
    with pytest.raises(IngestError) as info:
        ingest_utterance(by_id["s/b"], CONFIG)
    assert info.value.error_type == "BadAlignmentFile" and info.value.path == str(broken.resolve())
    assert "s/b" in str(info.value) and "line 12: expected 'start end label" in str(info.value)


def test_mlf_named_in_a_manifest(tmp_path):
    write_wav(tmp_path / "audio" / "take1.wav", 1.0)
    write_wav(tmp_path / "audio" / "take2.wav", 1.0)
    (tmp_path / "labels.mlf").write_text(mlf({"*/take1.rec": htk_lines(PHONES, {0.2: "hello"})}))
    (tmp_path / "m.csv").write_text("utterance_id,audio,alignment\nA/one,audio/take1.wav,labels.mlf\n"
                                    "A/two,audio/take2.wav,labels.mlf\n")
    found = discover_corpus(tmp_path / "m.csv")
    (entry,) = found.entries
    (reject,) = found.rejects
    assert entry.utterance_id == "A/one" and entry.alignment_key == "audio/take1"
    assert reject.utterance_id == "A/two" and reject.error_type == "MissingAlignment"
    assert "has no entry for audio/take2" in reject.message
    assert comparable(ingest_utterance(entry, CONFIG).phones) == comparable(reference_rows(tmp_path))


def test_load_mlf_rereads_a_changed_file(tmp_path):
    path = tmp_path / "a.mlf"
    path.write_text(mlf({"*/a.lab": "0 1 sil\n"}))
    assert [e.pattern for e in load_mlf(path).entries] == ["*/a.lab"]
    path.write_text(mlf({"*/a.lab": "0 1 sil\n", "*/bb.lab": "0 1 sil\n"}))
    assert [e.pattern for e in load_mlf(path).entries] == ["*/a.lab", "*/bb.lab"]
