"""MBROLA voices as training speakers for bench/domain_gap.py (issue 14): speech concatenated from real people's
diphones, with alignments exact by construction.

espeak-ng's own voices are formant synthesis; MBROLA voices (Dutoit et al. 1996) join diphones cut from recordings
of real speakers, so their closures, bursts and nasal murmurs are recorded ones. espeak-ng drives them (text ->
phonemes, durations and pitch) and writes what it sends to MBROLA with `--pho`: one line per phone, its X-SAMPA
name and its duration in ms. MBROLA renders each phone with exactly that duration, so the .pho file is the
alignment (checked on "Bob paid me five big apples": the b closures, the silence before each burst, sit where the
.pho puts them). The library's phoneme events cannot be used: for MBROLA voices they lag the audio by about one
phone, which is why `visemeflow.synth.espeak` refuses mb-* voices.

The voices are Debian non-free packages (`mbrola`, `mbrola-us1`, `mbrola-us2`, `mbrola-us3`, `mbrola-en1`; enable
the contrib and non-free components), not installed by `make`: their licence allows non-commercial use only, so
nothing made from them is shipped, and the default model does not train on them. Without them `available()` is
False and the recipes that need them are skipped with a note.

Layout: `bench/out/learning/mbrola-en<N>-s<seed>/<voice>_<rate>wpm/gridNNNNN.{wav,TextGrid}` (16 kHz), the GRID
grammar sentences of the espeak corpus (another seed), ingested by the product's ingest like any corpus.
"""

from __future__ import annotations

import itertools
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import soundfile as sf

from visemeflow.phonetics.inventory import xsampa_to_ipa
from visemeflow.phonetics.textgrid import Tier, format_textgrid
from visemeflow.synth.sentences import grid_sentences, speaker_name, speaker_plan

OUT = Path(__file__).resolve().parent / "out" / "learning"
VOICES = ("mb-us1", "mb-us2", "mb-us3", "mb-en1")
RATES = (130, 160, 200)
MBROLA_DIR = Path("/usr/share/mbrola")
# MBROLA's English voices spell two diphthongs their own way; "_" is a pause
SPELLINGS = {"EI": "eɪ", "AI": "aɪ", "_": ""}


def available() -> bool:
    """Whether espeak-ng, the mbrola program and the four voices are installed."""
    return bool(shutil.which("espeak-ng") and shutil.which("mbrola")) and \
        all((MBROLA_DIR / v.removeprefix("mb-")).is_dir() for v in VOICES)


def read_pho(path: Path) -> list[tuple[str, float]]:
    """(X-SAMPA label, seconds) per phone of an MBROLA .pho file (comments and blank lines skipped)."""
    phones = []
    for line in path.read_text().splitlines():
        fields = line.split()
        if not fields or line.startswith(";"):
            continue
        phones.append((fields[0], float(fields[1]) / 1000.0))
    return phones


def ipa_of(label: str) -> str:
    """The IPA label of an MBROLA English phone ('' for a pause); ValueError for one we cannot read."""
    if label in SPELLINGS:
        return SPELLINGS[label]
    ipa = xsampa_to_ipa(label)
    if ipa is None:
        raise ValueError(f"MBROLA phone {label!r} has no X-SAMPA reading")
    return ipa


def synthesize(text: str, voice: str, rate: int, stem: Path) -> float:
    """Write `stem`.wav (MBROLA's rate) and `stem`.TextGrid (phones from the .pho, one words interval over the
    speech); returns the duration in seconds."""
    stem.parent.mkdir(parents=True, exist_ok=True)
    wav = stem.with_suffix(".wav")
    base = ["espeak-ng", "-v", voice, "-s", str(rate)]
    subprocess.run(base + ["-w", str(wav), text], check=True, capture_output=True)
    with tempfile.TemporaryDirectory() as tmp:
        pho = Path(tmp) / "x.pho"
        subprocess.run(base + ["-q", "--pho", f"--phonout={pho}", text], check=True, capture_output=True)
        phones = read_pho(pho)
    info = sf.info(str(wav))
    duration = info.frames / info.samplerate
    intervals, t = [], 0.0
    for label, seconds in phones:
        if t >= duration:
            break
        end = min(duration, t + seconds)
        ipa = ipa_of(label)
        if intervals and ipa == "" and intervals[-1][2] == "":
            intervals[-1] = (intervals[-1][0], end, "")
        else:
            intervals.append((t, end, ipa))
        t = end
    speech_end = t
    if t < duration:
        intervals.append((t, duration, ""))
    if abs(speech_end - sum(s for _, s in phones)) > 0.05:
        raise ValueError(f"{wav}: {duration:.3f} s of audio for {sum(s for _, s in phones):.3f} s of phones")
    speech = [iv for iv in intervals if iv[2]]
    words = [(0.0, speech[0][0], ""), (speech[0][0], speech[-1][1], "utterance"), (speech[-1][1], duration, "")]
    words = tuple(w for w in words if w[1] > w[0])
    stem.with_suffix(".TextGrid").write_text(format_textgrid(
        [Tier("words", "IntervalTier", 0.0, duration, words),
         Tier("phones", "IntervalTier", 0.0, duration, tuple(intervals))], 0.0, duration), encoding="utf-8")
    return duration


def ensure_corpus(n: int, seed: int = 1) -> Path:
    """The MBROLA corpus of `n` GRID-grammar sentences spread over VOICES x RATES (made once, then reused)."""
    root = OUT / f"mbrola-en{n}-s{seed}"
    done = root / ".complete"
    if done.exists():
        return root
    if not available():
        raise RuntimeError("the MBROLA voices are not installed (see bench/mbrola_data.py)")
    started = time.perf_counter()
    plan = itertools.cycle(speaker_plan(VOICES, RATES))
    total = 0.0
    for i, sentence in enumerate(grid_sentences(n, seed)):
        voice, rate = next(plan)
        total += synthesize(sentence.espeak_text, voice, rate, root / speaker_name(voice, rate) / f"grid{i:05d}")
    done.write_text(f"{n} utterances, {total:.0f} s\n")
    print(f"MBROLA corpus: {n} utterances ({total:.0f} s of speech) in {time.perf_counter() - started:.0f} s",
          flush=True)
    return root
