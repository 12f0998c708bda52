"""espeak-ng synthesis with exact phone timings, TextGrid writing, sentence generators, the synthetic corpus.

These tests need libespeak-ng (Debian's espeak-ng; `make test` and .ci/run install it first through
scripts/system-deps.sh). Without it they fail with the install command instead of being skipped, so a missing
dependency cannot pass unnoticed.
"""

import hashlib
import math
import os
import subprocess
import sys
import textwrap
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from visemeflow.ingest import IngestConfig, discover_corpus, ingest_utterance
from visemeflow.phonetics.inventory import is_silence, map_phone
from visemeflow.phonetics.textgrid import Tier, TextGridData, format_textgrid, parse_textgrid
from visemeflow.synth.espeak import (
    IPA_TRANSLATIONS,
    EspeakLabelError,
    SynthResult,
    espeak_available,
    parse_pinyin,
    synthesize,
)
from visemeflow.synth.sentences import (
    GRID_GRAMMAR,
    GRID_LETTERS,
    MANDARIN_SYLLABLES,
    GridSentence,
    MandarinSentence,
    grid_sentences,
    mandarin_sentences,
    speaker_name,
    speaker_plan,
    write_espeak_corpus,
)

REPO = Path(__file__).resolve().parents[1]
GRID_WORDS = ("bin", "blue", "at", "a", "one", "again")


@pytest.fixture(scope="module")
def needs_espeak():
    if not espeak_available():
        pytest.fail("libespeak-ng is not installed: run `sh scripts/system-deps.sh` as root "
                    "(or `apt-get install -y espeak-ng`); `make test` and .ci/run run it first")


def grid(words=GRID_WORDS, voice="en-us", rate=160, **kw) -> SynthResult:
    return synthesize(GridSentence(tuple(words)).espeak_text, voice, rate, word_labels=words, **kw)


def check_tiling(result: SynthResult) -> None:
    """Phones cover [0, duration] exactly, in order, with no gap, overlap or empty interval."""
    phones = result.phones
    assert phones[0].start_s == 0.0
    assert phones[-1].end_s == result.duration_s == len(result.audio) / result.sample_rate
    for a, b in zip(phones, phones[1:]):
        assert a.end_s == b.start_s
    assert all(p.end_s > p.start_s for p in phones)
    assert all(not (is_silence(a.label) and is_silence(b.label)) for a, b in zip(phones, phones[1:]))


# --- format_textgrid ---------------------------------------------------------------------------

times = st.floats(allow_nan=False, allow_infinity=False, width=64)
labels = st.text(st.characters(blacklist_categories=("Cs",)), max_size=12)


@st.composite
def tiers(draw):
    kind = draw(st.sampled_from(["IntervalTier", "TextTier"]))
    items = draw(st.lists(st.tuples(times, times, labels), max_size=5))
    if kind == "TextTier":
        items = [(a, a, text) for a, _, text in items]
    return Tier(draw(labels), kind, draw(times), draw(times), tuple(items))


@settings(max_examples=150, deadline=None)
@given(st.lists(tiers(), max_size=4), times, times)
def test_format_textgrid_round_trips_through_parse_textgrid(tier_list, xmin, xmax):
    text = format_textgrid(tier_list, xmin, xmax)
    assert parse_textgrid(text) == TextGridData(xmin, xmax, tuple(tier_list))


def test_format_textgrid_writes_praat_long_format():
    tier = Tier("phones", "IntervalTier", 0.0, 0.5, ((0.0, 0.25, 'say "hi"'), (0.25, 0.5, "sil")))
    points = Tier("marks", "TextTier", 0.0, 0.5, ((0.1, 0.1, "p"),))
    text = format_textgrid([tier, points], 0.0, 0.5)
    assert text.startswith('File type = "ooTextFile"\nObject class = "TextGrid"\n')
    assert 'text = "say ""hi""" ' in text and "points: size = 1" in text and "number = 0.1 " in text
    assert parse_textgrid(format_textgrid([], 0.0, 1.0)) == TextGridData(0.0, 1.0, ())
    with pytest.raises(ValueError, match="unknown class"):
        format_textgrid([Tier("x", "Bogus", 0.0, 1.0, ())], 0.0, 1.0)


# --- sentences ---------------------------------------------------------------------------------


def test_grid_sentences_follow_the_grammar_and_the_seed():
    sentences = grid_sentences(300, seed=7)
    assert sentences == grid_sentences(300, seed=7)
    assert sentences[:20] == grid_sentences(20, seed=7)
    assert sentences != grid_sentences(300, seed=8)
    for s in sentences:
        assert len(s.words) == 6 and all(w in slot for w, slot in zip(s.words, GRID_GRAMMAR))
    assert "w" not in GRID_LETTERS and len(GRID_LETTERS) == 25
    used = {w for s in sentences for w in s.words}
    assert all(set(slot) <= used for slot in GRID_GRAMMAR)  # 300 draws reach every word
    assert GridSentence(GRID_WORDS).espeak_text == "bin blue at [['eI]] one again"


def test_mandarin_sentences_follow_the_seed_and_the_syllable_list():
    sentences = mandarin_sentences(100, seed=3, min_syllables=2, max_syllables=5)
    assert sentences == mandarin_sentences(100, seed=3, min_syllables=2, max_syllables=5)
    assert sentences != mandarin_sentences(100, seed=4, min_syllables=2, max_syllables=5)
    assert {len(s.syllables) for s in sentences} == {2, 3, 4, 5}
    assert all(set(s.syllables) <= set(MANDARIN_SYLLABLES) for s in sentences)
    s = MandarinSentence(("lv4", "jue2", "yong3", "zhi1"))
    assert s.espeak_text == "lv4 jue2 yong3 zhi1"
    assert s.labels == ("l", "v4", "j", "ve2", "y", "iong3", "zh", "iii1")


def test_mandarin_syllable_list_covers_every_initial_and_final():
    parsed = [parse_pinyin(s) for s in MANDARIN_SYLLABLES]
    assert len(set(MANDARIN_SYLLABLES)) == len(MANDARIN_SYLLABLES)
    initials = {p.initial for p in parsed}
    assert set("b p m f d t n l g k h j q x zh ch sh r z c s y w".split()) | {""} == initials
    finals = {p.final for p in parsed}
    expected = set("a o e ai ei ao ou an en ang eng ong er i u v ia ie iao iu ian in iang ing iong io ua uo uai ui "
                   "uan un uang ueng ve van vn ii iii".split())
    assert expected == finals


@pytest.mark.parametrize("syllable, initial, final, tone, spelling", [
    ("zhong1", "zh", "ong", 1, "zhong1"), ("shi4", "sh", "iii", 4, "shi4"), ("zi5", "z", "ii", 5, "zi5"),
    ("ri4", "r", "iii", 4, "ri4"), ("jue2", "j", "ve", 2, "jue2"), ("jve2", "j", "ve", 2, "jue2"),
    ("qu4", "q", "v", 4, "qu4"), ("xuan3", "x", "van", 3, "xuan3"), ("lü4", "l", "v", 4, "lv4"),
    ("nüe4", "n", "ve", 4, "nve4"), ("lue4", "l", "ve", 4, "lve4"), ("yu2", "y", "v", 2, "yu2"),
    ("yue4", "y", "ve", 4, "yue4"), ("ya1", "y", "ia", 1, "ya1"), ("you3", "y", "iu", 3, "you3"),
    ("yi1", "y", "i", 1, "yi1"), ("wu3", "w", "u", 3, "wu3"), ("wei4", "w", "ui", 4, "wei4"),
    ("wen2", "w", "un", 2, "wen2"), ("er2", "", "er", 2, "er2"), ("ang2", "", "ang", 2, "ang2"),
    ("Gui4", "g", "ui", 4, "gui4"), ("niu2", "n", "iu", 2, "niu2"),
])
def test_parse_pinyin(syllable, initial, final, tone, spelling):
    p = parse_pinyin(syllable)
    assert (p.initial, p.final, p.tone, p.spelling) == (initial, final, tone, spelling)
    for label in p.labels:
        assert map_phone(label, "pinyin").phoneme in (initial, final)


@pytest.mark.parametrize("bad", ["zhong", "xx1", "m2", "ng5", "zh1", "hao6", "", "ni 3"])
def test_parse_pinyin_rejects_non_syllables(bad):
    with pytest.raises(ValueError):
        parse_pinyin(bad)


def test_speaker_plan_and_names():
    plan = speaker_plan(["en-us", "en+f3", "en+m3"], [130, 160, 200, 180])
    assert len(set(plan)) == 12
    assert [v for v, _ in plan[:3]] == ["en-us", "en+f3", "en+m3"] and len({r for _, r in plan[:3]}) == 3
    assert speaker_name("en+f3", 160) == "en-f3_160wpm"
    assert speaker_name("en-gb-x-rp", 200) == "en-gb-x-rp_200wpm"


def test_ipa_translations_only_target_symbols_of_the_table():
    for name, parts in IPA_TRANSLATIONS.items():
        with pytest.raises(ValueError):
            map_phone(name, "ipa")  # otherwise the entry is not needed
        for label, weight in parts:
            assert map_phone(label, "ipa").visemes and weight > 0


# --- synthesis ---------------------------------------------------------------------------------


def test_english_phones_tile_the_audio_and_map_under_ipa(needs_espeak):
    r = grid()
    assert r.inventory == "ipa" and r.sample_rate == 22050
    assert r.audio.dtype == np.float32 and r.audio.size > 0.5 * r.sample_rate
    assert np.abs(r.audio).max() <= 1.0 and np.abs(r.audio).max() > 0.1
    check_tiling(r)
    for p in r.phones:
        m = map_phone(p.label, "ipa")
        assert m.is_silence == (p.label == "sil")
    assert [w.label for w in r.words] == list(GRID_WORDS)
    for i, w in enumerate(r.words):
        inside = [p for p in r.phones if p.word_index == i]
        assert inside and inside[0].start_s == w.start_s and inside[-1].end_s == w.end_s
        assert all(p.word == w.label for p in inside)
    assert all(p.word_index is not None for p in r.phones if p.label != "sil")
    spoken = [p.label for p in r.phones if p.label != "sil"]
    assert spoken[:6] == ["b", "ɪ", "n", "b", "l", "uː"]  # bin blue
    assert "eɪ" in [p.label for p in r.phones if p.word == "a"]  # the letter name, not the article


def test_bilabial_closure_is_quieter_than_the_vowel_after_it(needs_espeak):
    r = grid()
    phones = list(r.phones)
    bilabials = [i for i, p in enumerate(phones) if ("MBP", 1.0) in map_phone(p.label, "ipa").visemes]
    assert [phones[i].word for i in bilabials] == ["bin", "blue"]
    first = phones[bilabials[0]]
    assert 0.0 < first.start_s < 0.1 and first.duration_s < 0.1

    def rms(p):
        seg = r.audio[round(p.start_s * r.sample_rate):round(p.end_s * r.sample_rate)]
        return float(np.sqrt(np.mean(seg.astype(np.float64) ** 2)))

    assert rms(first) < 0.5 * rms(phones[bilabials[0] + 1])  # b (closure, burst) vs ɪ


def test_rate_changes_duration_and_voices_differ(needs_espeak):
    slow, fast = grid(rate=130), grid(rate=200)
    assert fast.duration_s < 0.85 * slow.duration_s
    assert [p.label for p in slow.phones if p.label != "sil"] == [p.label for p in fast.phones if p.label != "sil"]
    f3, m3 = grid(voice="en+f3"), grid(voice="en+m3")
    assert f3.audio.shape != m3.audio.shape or not np.array_equal(f3.audio, m3.audio)
    assert not np.array_equal(grid(pitch=20).audio[:5000], grid(pitch=80).audio[:5000])


def test_synthesis_is_deterministic_in_any_order_and_thread(needs_espeak):
    first = grid(voice="en+f3")
    grid(voice="en-us+m3", rate=200)
    synthesize("ni3 hao3", "cmn")
    again = grid(voice="en+f3")
    assert np.array_equal(again.audio, first.audio) and again.phones == first.phones and again.words == first.words
    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(lambda _: grid(voice="en+f3"), range(4)))
    assert all(np.array_equal(x.audio, first.audio) and x.phones == first.phones for x in results)


ENGLISH_VOICES = ["en-us", "en", "en-gb-x-rp", "en-gb-scotland", "en-029", "en-us-nyc", "en-gb-x-gbclan",
                  "en-gb-x-gbcwmd"]
RICH_TEXT = ("The quick brown fox jumps over the lazy dog near the square; our poor cure, a fire in the car park. "
             "Thin this ship, measure church judge sing yes; bottle, roses, hour, tour, wii, bath, goat, mouth.")


@pytest.mark.parametrize("voice", ENGLISH_VOICES)
def test_every_english_voice_yields_mappable_labels(needs_espeak, voice):
    r = synthesize(RICH_TEXT, voice, 300)
    check_tiling(r)
    for p in r.phones:
        map_phone(p.label, "ipa")  # raises on an unknown symbol
    assert len(r.words) >= 35


def test_every_grid_letter_is_one_word(needs_espeak):
    words = tuple(GRID_LETTERS)
    r = synthesize(GridSentence(words).espeak_text, "en-gb-x-rp", 250, word_labels=words)
    assert [w.label for w in r.words] == list(words)


def test_mandarin_labels_are_pinyin_initials_and_toned_finals(needs_espeak):
    sentence = MandarinSentence(("wo3", "xue2", "zhong1", "wen2", "lv4", "er2", "shi4"))
    r = synthesize(sentence.espeak_text, "cmn", 160, word_labels=sentence.syllables)
    assert r.inventory == "pinyin"
    check_tiling(r)
    assert [p.label for p in r.phones if p.label != "sil"] == list(sentence.labels)
    assert [w.label for w in r.words] == list(sentence.syllables)
    tones = [map_phone(p.label, "pinyin").stress for p in r.phones if p.label != "sil"]
    assert tones == [None, 3, None, 2, None, 1, None, 2, None, 4, 2, None, 4]
    for p in r.phones:
        if p.label != "sil":
            assert r.words[p.word_index].label == p.word


def test_every_mandarin_syllable_aligns_to_initial_and_final(needs_espeak):
    folded_glides = set()
    for voice, start in (("cmn", 0), ("cmn+f3", 1)):
        chunk_size = 16
        for i in range(start * 8, len(MANDARIN_SYLLABLES), chunk_size):
            chunk = MANDARIN_SYLLABLES[i:i + chunk_size]
            r = synthesize(" ".join(chunk), voice, 220)
            check_tiling(r)
            for j, syllable in enumerate(chunk):
                got = tuple(p.label for p in r.phones if p.word_index == j)
                expected = parse_pinyin(syllable).labels
                if got != expected:  # espeak may fold the y/w glide into the vowel (yong: [yu ŋ])
                    assert expected[0] in ("y", "w") and got == expected[1:], (syllable, got)
                    folded_glides.add(syllable)
                for label in got:
                    stress = map_phone(label, "pinyin").stress
                    assert stress == (int(label[-1]) if label[-1].isdigit() else None)
    assert folded_glides <= {"yong4", "yuan3", "yue4", "yun2", "yu3", "you3", "yan2", "ye3", "ye4", "ya2"}


def test_language_voice_and_argument_errors(needs_espeak):
    with pytest.raises(ValueError, match="unknown espeak-ng voice"):
        synthesize("hello", "xx-nonexistent")
    for mbrola in ("mb-us2", "mb-en1+f2"):   # refused whether or not the MBROLA voices are installed
        with pytest.raises(ValueError, match=r"is an MBROLA voice: .* its alignments would be wrong"):
            synthesize("hello", mbrola)
    with pytest.raises(ValueError, match="variant"):
        synthesize("hello", "en+nosuchvariant")
    with pytest.raises(ValueError, match="Mandarin"):
        synthesize("ni3 hao3", "cmn", language="en")
    with pytest.raises(ValueError, match="not a Mandarin voice"):
        synthesize("ni3 hao3", "en-us", language="zh")
    with pytest.raises(ValueError, match="pinyin"):
        synthesize("hello world", "cmn")
    with pytest.raises(ValueError, match="rate_wpm"):
        synthesize("hello", rate_wpm=20)
    with pytest.raises(ValueError, match="empty"):
        synthesize("   ")
    with pytest.raises(ValueError, match="word labels"):
        synthesize("hello world", word_labels=["hello"])


def test_unmapped_phoneme_names_the_translation_table(needs_espeak, monkeypatch):
    monkeypatch.delitem(IPA_TRANSLATIONS, "iə")
    with pytest.raises(EspeakLabelError, match="IPA_TRANSLATIONS"):
        synthesize("near", "en")


def run_python(code: str, **env) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=REPO, capture_output=True, text=True,
                          env={**os.environ, **env}, timeout=120)


def test_private_pinyin_voice_file_reads_pinyin(needs_espeak):
    proc = run_python("""
        import visemeflow.synth.espeak as E
        r = E.synthesize("ni3 hao3 lv4", "cmn+f3")
        engine = E._engine()
        print(engine.private, engine.data_dir.startswith("/usr"), " ".join(p.label for p in r.phones))
    """, VISEMEFLOW_ESPEAK_PRIVATE_PINYIN="1")
    assert proc.returncode == 0, proc.stderr
    private, system, phone_labels = proc.stdout.split(maxsplit=2)
    assert (private, system) == ("True", "False")
    assert [x for x in phone_labels.split() if x != "sil"] == ["n", "i3", "h", "ao3", "l", "v4"]


def test_missing_library_is_a_clear_error():
    proc = run_python("""
        import visemeflow.synth.espeak as E
        print(E.espeak_available())
        try:
            E.synthesize("hello")
        except E.EspeakUnavailableError as exc:
            print(exc)
    """, VISEMEFLOW_ESPEAK_LIBRARY="/nonexistent/libespeak-ng.so.1")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("False\n") and "apt-get install espeak-ng" in proc.stdout


# --- the corpus --------------------------------------------------------------------------------


def tree_digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*"))
            if p.is_file()}


def test_espeak_corpus_ingests_and_is_byte_identical_on_rerun(needs_espeak, tmp_path):
    ids = write_espeak_corpus(tmp_path / "a", 6, 4, seed=1)
    assert len(ids) == len(set(ids)) == 10
    discovery = discover_corpus(tmp_path / "a")
    assert not discovery.rejects and sorted(e.utterance_id for e in discovery.entries) == sorted(ids)
    assert len({e.speaker for e in discovery.entries}) == 10  # each utterance its own voice/rate so far
    inventories = {}
    for entry in discovery.entries:
        ingested = ingest_utterance(entry, IngestConfig())
        u = ingested.utterance
        inventories[entry.utterance_id] = u["inventory"]
        assert u["sample_rate"] == 22050 and u["duration_s"] > 0.5
        assert ingested.phones and all(math.isfinite(row["start_s"]) for row in ingested.phones)
    assert sorted(inventories.values()) == ["ipa"] * 6 + ["pinyin"] * 4
    assert all(inventories[i] == ("pinyin" if "/pinyin" in i else "ipa") for i in ids)

    before = tree_digest(tmp_path / "a")
    assert write_espeak_corpus(tmp_path / "a", 6, 4, seed=1) == ids
    assert tree_digest(tmp_path / "a") == before
    write_espeak_corpus(tmp_path / "b", 6, 4, seed=1)
    assert tree_digest(tmp_path / "b") == before
    write_espeak_corpus(tmp_path / "c", 6, 4, seed=2)
    assert tree_digest(tmp_path / "c") != before
