"""Closures judged on recordings of single syllables whose text is known ("BA", "MA", "DO", "ЛЮ", "AAP"): real
voices in any language written in Latin or Cyrillic letters, no alignment needed. What the lips must do follows
from the letters; when follows from the recording's loudness.

Pure: numpy and the standard library, no torch, no files but the sounds.xml that :func:`klettres_syllables` reads.

- **The speech** (:func:`speech_span`): from the first to the last 10-ms frame (RMS over 25 ms, median of 5 frames)
  within 30 dB of the recording's loudest and above the middle, in dB, between its noise floor (10th percentile)
  and its loudest (some recordings hiss within 30 dB of their speech).
- **A closure frame**: MBP is the top viseme and at least ``min_weight`` (0.2: below it the curves are near rest
  and the top viseme is noise).
- **Labial** syllables (a letter B, P or M; Б, П or М): closed when a closure frame lies where that letter is
  spoken. A first letter: from ``BEFORE_S`` (0.2 s) before the speech (a /p/'s closure is silent; its burst starts
  the speech) to ``ONSET_S`` (0.12 s) into it. A last letter: from ``OFFSET_S`` (0.1 s) before the speech ends to
  ``AFTER_S`` (0.2 s) after. A letter inside: within the speech. A mouth closing as the voice stops, which the
  models do after many vowels, is not an onset's closure.
- **Other** syllables (none of those letters, nor F, V, W, Ф, В, whose lips are labiodental or rounded and could
  fairly close): a *false closure* when a closure frame lies in the nucleus, the speech less its first
  ``ONSET_S`` (the consonant) and its last ``OFFSET_S`` (the mouth may close as the voice stops); *mesh closed*
  when the rendered lips are below ``CLOSED_MM`` at a nucleus frame, whatever the viseme; and the median rendered
  lip gap over the nucleus (the mouth must open for the vowel). A syllable whose nucleus holds no frame is left
  out of these. The onset window on these syllables gives the chance of an onset "closure" without a labial
  (the mouth closed before speaking, or a model that closes at every onset): read the labial figure against it.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visemeflow.articulation import CLOSED_MM
from visemeflow.learning.realspeech import Recall
from visemeflow.visemes import VISEME_INDEX

LABIAL = frozenset("BPMБПМ")
LIP_SHAPED = frozenset("FVWФВ")
BEFORE_S = AFTER_S = 0.2
ONSET_S, OFFSET_S = 0.12, 0.1
MIN_WEIGHT = 0.2
_MBP = VISEME_INDEX["MBP"]


def labial_at(text: str) -> str | None:
    """Where the text's first labial letter is: "onset", "coda", "inside", or None."""
    upper = text.upper()
    at = next((i for i, ch in enumerate(upper) if ch in LABIAL), None)
    if at is None:
        return None
    return "onset" if at == 0 else "coda" if at == len(upper) - 1 else "inside"


def kind_of(text: str) -> str:
    """"labial", "lip-shaped" (f/v/w letters and no labial: judged neither way) or "other"."""
    letters = set(text.upper())
    if letters & LABIAL:
        return "labial"
    return "lip-shaped" if letters & LIP_SHAPED else "other"


def speech_span(audio: np.ndarray, sample_rate: int) -> tuple[float, float]:
    """(first, last) second of the speech in a recording of one syllable (see the module docstring)."""
    audio = np.asarray(audio, np.float64).reshape(-1)
    hop, win = sample_rate // 100, max(1, sample_rate // 40)
    if len(audio) < win:
        raise ValueError(f"a recording of {len(audio)} samples is shorter than one 25-ms window")
    power = np.convolve(audio ** 2, np.ones(win) / win, mode="same")[::hop]
    db = 10 * np.log10(power + 1e-12)
    db = np.array([np.median(db[max(0, i - 2):i + 3]) for i in range(len(db))])
    floor = np.percentile(db, 10)
    loud = np.flatnonzero(db > max(db.max() - 30.0, floor + 0.5 * (db.max() - floor)))
    return loud[0] / 100.0, (loud[-1] + 1) / 100.0


@dataclass(frozen=True)
class SyllableScore:
    kind: str
    closed: bool
    """A closure frame where the labial letter is spoken (False without a labial letter)."""
    onset_closed: bool
    """A closure frame in the onset window."""
    false: bool | None
    """A closure frame in the nucleus (None: no nucleus)."""
    mesh_closed: bool | None
    """The rendered lips below CLOSED_MM at a nucleus frame (None: no nucleus or no gap given)."""
    open_mm: float | None
    """The median rendered lip gap over the nucleus."""


def score_syllable(text: str, curves: np.ndarray, fps: float, span: tuple[float, float],
                   gap_mm: np.ndarray | None = None, min_weight: float = MIN_WEIGHT) -> SyllableScore:
    """One recording's score from its (frames, 16) curves at `fps`, its speech span and, when given, the rendered
    lip gap per frame (mm)."""
    curves = np.asarray(curves, np.float32)
    closure = (curves.argmax(axis=1) == _MBP) & (curves[:, _MBP] >= min_weight)
    times = np.arange(len(curves)) / fps
    on, off = span
    at = labial_at(text)
    onset = (times >= on - BEFORE_S) & (times <= on + ONSET_S)
    near = (onset if at == "onset"
            else (times >= off - OFFSET_S) & (times <= off + AFTER_S) if at == "coda"
            else (times >= on) & (times <= off) if at == "inside"
            else np.zeros(len(times), bool))
    nucleus = (times >= on + ONSET_S) & (times <= off - OFFSET_S)
    kind = kind_of(text)
    if not nucleus.any():
        return SyllableScore(kind, bool(closure[near].any()), bool(closure[onset].any()), None, None, None)
    mesh = None if gap_mm is None else bool((gap_mm[nucleus] < CLOSED_MM).any())
    opened = None if gap_mm is None else float(np.median(gap_mm[nucleus]))
    return SyllableScore(kind, bool(closure[near].any()), bool(closure[onset].any()), bool(closure[nucleus].any()),
                         mesh, opened)


@dataclass(frozen=True)
class SyllableSummary:
    labial_closed: Recall
    """Labial syllables closed where the letter is spoken."""
    other_onset: Recall
    """Other syllables with a closure frame in the onset window (chance)."""
    other_false: Recall
    """Other syllables with a closure frame in the nucleus."""
    other_mesh_closed: Recall
    median_open_mm: float | None


def summarise(scores: Iterable[SyllableScore]) -> SyllableSummary:
    scores = list(scores)
    labial = [s for s in scores if s.kind == "labial"]
    other = [s for s in scores if s.kind == "other"]
    nucleus = [s for s in other if s.false is not None]
    meshed = [s for s in nucleus if s.mesh_closed is not None]
    opened = [s.open_mm for s in meshed]
    return SyllableSummary(
        Recall(sum(s.closed for s in labial), len(labial)),
        Recall(sum(s.onset_closed for s in other), len(other)),
        Recall(sum(bool(s.false) for s in nucleus), len(nucleus)),
        Recall(sum(bool(s.mesh_closed) for s in meshed), len(meshed)),
        float(np.median(opened)) if opened else None,
    )


def klettres_syllables(root: str | Path, language: str) -> list[tuple[str, Path]]:
    """(text, recording) of each syllable a KLettres language folder names in its sounds.xml and holds (Debian's
    `klettres-data` installs them under /usr/share/klettres; GPL-2+). `root`: that folder."""
    root = Path(root)
    out = []
    for block in ET.parse(root / language / "sounds.xml").getroot().iter("syllables"):
        for sound in block.iter("sound"):
            path = root / sound.get("file", "")
            if sound.get("file") and path.is_file():
                out.append((sound.get("name", ""), path))
    return out
