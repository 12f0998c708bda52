"""Deterministic sentences for a synthetic speech corpus, and the corpus writer (espeak-ng speech + TextGrid).

- `grid_sentences`: the GRID corpus grammar (Cooke et al. 2006), six words: command colour preposition
  letter digit adverb, e.g. "bin blue at f two now".
- `mandarin_sentences`: toned pinyin syllables drawn from a list of common ones, e.g. "wo3 xue2 zhong1 wen2".
- `write_espeak_corpus`: `<speaker>/<name>.wav` + `<name>.TextGrid` (phones and words tiers) for both, one
  speaker per (voice, rate) combination. Same seed and arguments, same files byte for byte.

Everything here is a pure function of its arguments (a `random.Random(seed)` drawn in a fixed order).
"""

from __future__ import annotations

import itertools
import random
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import soundfile as sf

from visemeflow.atomic import atomic_write, atomic_write_text
from visemeflow.phonetics.textgrid import Tier, format_textgrid
from visemeflow.synth.espeak import SynthResult, parse_pinyin, synthesize

GRID_COMMANDS: Final = ("bin", "lay", "place", "set")
GRID_COLORS: Final = ("blue", "green", "red", "white")
GRID_PREPOSITIONS: Final = ("at", "by", "in", "with")
GRID_LETTERS: Final = tuple("abcdefghijklmnopqrstuvxyz")  # GRID leaves out w (three syllables)
GRID_DIGITS: Final = ("zero", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine")
GRID_ADVERBS: Final = ("again", "now", "please", "soon")
GRID_GRAMMAR: Final = (GRID_COMMANDS, GRID_COLORS, GRID_PREPOSITIONS, GRID_LETTERS, GRID_DIGITS, GRID_ADVERBS)

# GRID speakers say the letter's name. espeak reads every other letter that way, but reads "a" as the
# article (ə), so the letter is given to it as phoneme input: the name [eɪ].
_GRID_ESPEAK_SPELLING: Final = {"a": "[['eI]]"}

# Common Mandarin syllables with a usual tone; every initial (b p m f d t n l g k h j q x zh ch sh r z c
# s, zero initials y w and none) and every final of the pinyin table occurs at least once.
MANDARIN_SYLLABLES: Final = tuple("""
de5 shi4 yi1 bu4 you3 zhe4 wo3 ta1 ren2 men5 lai2 dao4 shang4 ge4 zai4 guo2 zhong1 da4 wei4 ni3 hao3 xue2
sheng1 zi5 le5 kan4 jian4 mei3 xiang3 qu4 shuo1 hua4 yao4 jiu4 ye3 neng2 jia1 er2 nian2 dong1 xi1 nan2 bei3
qian2 hou4 tian1 ri4 yue4 shui3 huo3 mu4 jin1 tu3 shan1 he2 feng1 yu3 ma1 mao1 niu2 yang2 zhu1 gou3 ji1 chi1
cha2 fan4 mian4 bao1 rou4 cai4 chuan2 fu4 xie4 kai1 guan1 che1 lu4 zou3 pao3 fei1 zuo4 zhan4 ting1 xing2 ming2
hong2 lv4 bai2 hei1 huang2 lan2 zhi1 qi3 wan3 kuai4 man4 gao1 di4 chang2 duan3 xiao3 lao3 shao3 duo1 gui4 sun1
lun4 xiong2 quan2 jun1 yun2 yuan3 wen4 weng1 yong4 nv3 lve4 ou1 ai4 an1 ang2 e4 o1 ci2 si4 ce4 peng2 tou2 ren4
jia3 ya2 wa1 wai4 yin1 ying1 yan2 you2 ye4 yo1 niao3 liang3 bing1 pin3 gua1 tuo1 shuai4 zhuang4 chun1 kun4 que4
xuan3 qun2 ju2 lue4 nue4 zen3 ceng2 song4 rang4 keng1 pang4 pou1 miu4 dia3 nin2 tei1 sa3 ca1 za2 sai1 sou1 cou4
zuan4 cuan4 suan4 ruan3 rui4 run4 nuo2 nong2 long2 nuan3 luan4 re4 ru4 zhua1 chuai3 shua1
""".split())


@dataclass(frozen=True, slots=True)
class GridSentence:
    """Six GRID words; `espeak_text` is what espeak is given (the letter a as phoneme input)."""

    words: tuple[str, ...]

    @property
    def text(self) -> str:
        return " ".join(self.words)

    @property
    def espeak_text(self) -> str:
        return " ".join(_GRID_ESPEAK_SPELLING.get(w, w) for w in self.words)


@dataclass(frozen=True, slots=True)
class MandarinSentence:
    """Toned pinyin syllables (ü written v); `espeak_text` is the standard spelling the cmn voice reads."""

    syllables: tuple[str, ...]

    @property
    def text(self) -> str:
        return " ".join(self.syllables)

    @property
    def espeak_text(self) -> str:
        return " ".join(parse_pinyin(s).spelling for s in self.syllables)

    @property
    def labels(self) -> tuple[str, ...]:
        """charsiu-style initial and final labels, in order (`zh`, `ong1`, ...)."""
        return tuple(label for s in self.syllables for label in parse_pinyin(s).labels)


def grid_sentences(n: int, seed: int) -> list[GridSentence]:
    """`n` GRID sentences; the first k of them are the same for any n >= k."""
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    rng = random.Random(seed)
    return [GridSentence(tuple(rng.choice(slot) for slot in GRID_GRAMMAR)) for _ in range(n)]


def mandarin_sentences(n: int, seed: int, min_syllables: int = 4, max_syllables: int = 9) -> list[MandarinSentence]:
    """`n` sentences of `min_syllables`..`max_syllables` syllables from MANDARIN_SYLLABLES."""
    if n < 0 or not 1 <= min_syllables <= max_syllables:
        raise ValueError(f"need n >= 0 and 1 <= min_syllables <= max_syllables, got {n}, {min_syllables}, {max_syllables}")
    rng = random.Random(seed)
    out = []
    for _ in range(n):
        count = rng.randint(min_syllables, max_syllables)
        out.append(MandarinSentence(tuple(rng.choice(MANDARIN_SYLLABLES) for _ in range(count))))
    return out


# --- the corpus ----------------------------------------------------------------------------------

DEFAULT_ENGLISH_VOICES: Final = ("en-us", "en-gb-x-rp", "en+f3", "en-us+m3", "en+f4", "en-us+m2", "en-gb-scotland",
                                 "en-us+f2")
DEFAULT_MANDARIN_VOICES: Final = ("cmn", "cmn+f3", "cmn+m3", "cmn+f4")
DEFAULT_RATES: Final = (130, 160, 200)


def speaker_name(voice: str, rate_wpm: int) -> str:
    """A valid speaker id for a (voice, rate) pair: `en+f3` at 160 wpm is `en-f3_160wpm`."""
    return f"{re.sub(r'[^A-Za-z0-9_.-]', '-', voice.strip())}_{int(rate_wpm)}wpm"


def speaker_plan(voices: Sequence[str], rates: Sequence[int]) -> list[tuple[str, int]]:
    """Every (voice, rate) pair once, ordered so that consecutive utterances change voice and rate."""
    if not voices or not rates:
        raise ValueError("need at least one voice and one rate")
    nv, nr = len(voices), len(rates)
    return [(voices[k % nv], rates[(k // nv + k % nv) % nr]) for k in range(nv * nr)]


def textgrid_of(result: SynthResult) -> str:
    """TextGrid text of a synthesis: a words tier (gaps as empty intervals) and a phones tier."""
    duration = result.duration_s
    words: list[tuple[float, float, str]] = []
    t = 0.0
    for w in result.words:
        if w.start_s > t:
            words.append((t, w.start_s, ""))
        words.append((w.start_s, w.end_s, w.label))
        t = w.end_s
    if t < duration:
        words.append((t, duration, ""))
    phones = tuple((p.start_s, p.end_s, p.label) for p in result.phones)
    return format_textgrid(
        [Tier("words", "IntervalTier", 0.0, duration, tuple(words)), Tier("phones", "IntervalTier", 0.0, duration, phones)],
        0.0, duration,
    )


@dataclass(frozen=True, slots=True)
class _Job:
    utterance_id: str
    text: str
    voice: str
    rate_wpm: int
    language: str
    word_labels: tuple[str, ...]


def write_espeak_corpus(root: Path | str, n_english: int, n_mandarin: int, seed: int,
                        voices: Sequence[str] = DEFAULT_ENGLISH_VOICES, rates: Sequence[int] = DEFAULT_RATES,
                        mandarin_voices: Sequence[str] = DEFAULT_MANDARIN_VOICES, pitch: int = 50) -> list[str]:
    """Write GRID English and pinyin Mandarin utterances under `root`; returns their utterance ids.

    Layout `root/<speaker>/<name>.wav` (22050 Hz mono PCM 16) + `<name>.TextGrid`, speaker = voice and rate
    (`speaker_name`), utterances spread over the pairs of `speaker_plan`. English names are `grid00000...`,
    Mandarin `pinyin00000...`. Existing files of the same names are overwritten.
    """
    root = Path(root)
    jobs: list[_Job] = []
    plan = itertools.cycle(speaker_plan(voices, rates))
    for i, sentence in enumerate(grid_sentences(n_english, seed)):
        voice, rate = next(plan)
        jobs.append(_Job(f"{speaker_name(voice, rate)}/grid{i:05d}", sentence.espeak_text, voice, rate, "en",
                         sentence.words))
    plan = itertools.cycle(speaker_plan(mandarin_voices, rates))
    for i, m in enumerate(mandarin_sentences(n_mandarin, seed)):
        voice, rate = next(plan)
        jobs.append(_Job(f"{speaker_name(voice, rate)}/pinyin{i:05d}", m.espeak_text, voice, rate, "cmn",
                         m.syllables))

    def run(job: _Job) -> str:
        result = synthesize(job.text, job.voice, job.rate_wpm, pitch, job.language, job.word_labels)
        folder = root / job.utterance_id.split("/")[0]
        folder.mkdir(parents=True, exist_ok=True)
        stem = folder / job.utterance_id.split("/")[1]
        atomic_write(stem.with_suffix(".wav"), lambda tmp: sf.write(
            tmp, result.pcm16, result.sample_rate, subtype="PCM_16", format="WAV"))
        atomic_write_text(stem.with_suffix(".TextGrid"), textgrid_of(result))
        return job.utterance_id

    return [run(job) for job in jobs]
