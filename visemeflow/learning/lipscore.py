"""Lip scores judged where the viewer sees them: per aligned phone, from the per-frame lip measures of the mesh.

The per-frame measures (inner-lip gap and lower-lip-to-upper-teeth distance, millimetres) come from
`animation.lips.LipProbe.measure`; this module turns them into per-phone figures, using the same phone frames as the
top-viseme scores (`realspeech.phone_frames`: the frames whose time lies inside the phone, else the frame nearest its
middle). The *apex* of a phone is its frame of extreme articulation:

- **b/p/m** (viseme MBP): the smallest gap within the phone; *closed* when below `CLOSED_MM` (1.5 mm).
- **f/v** (viseme FFF): the smallest lower-lip-to-upper-teeth distance; *contact* when within `CONTACT_MM` (2 mm).
- **open vowels** (visemes AAA, AHH: ARPAbet AA, AH, AE, AY, AW ...): the largest gap, as a share of the character's
  widest single shape (AHH alone); good between 0.6 and 1.1.
- **false closures**: vowels (AAA AHH EH IEE OHH UUU SCHWA) whose largest gap stays below `CLOSED_MM`: a mouth that
  never opened. A model that predicts one curve for any audio can close every b/p/m only by never opening.

Silence (viseme None) is never scored; phones past the end of the curves are counted as skipped.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa

from visemeflow.articulation import CLOSED_MM, CONTACT_MM
from visemeflow.learning.realspeech import Phone, Recall, phone_frames, phones_of

__all__ = ["LipScores", "OPEN_VOWELS", "VOWELS", "pool_lips", "score_lips"]

OPEN_VOWELS = frozenset({"AAA", "AHH"})
VOWELS = frozenset({"AAA", "AHH", "EH", "IEE", "OHH", "UUU", "SCHWA"})
VOWEL_LOW, VOWEL_HIGH = 0.6, 1.1


@dataclass(frozen=True)
class LipScores:
    """Per-phone lip figures of one utterance, or pooled over several."""

    bilabial_gap_mm: tuple[float, ...] = ()
    """Smallest inner-lip gap within each b/p/m phone."""
    labiodental_mm: tuple[float, ...] = ()
    """Smallest lower-lip-to-upper-teeth distance within each f/v phone (empty without a teeth measure)."""
    vowel_opening: tuple[float, ...] = ()
    """Largest gap within each open vowel, over the widest single shape's gap."""
    vowel_gap_mm: tuple[float, ...] = ()
    """Largest gap within each vowel (for false closures)."""
    skipped: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def closed(self) -> Recall:
        return Recall(int(sum(g < CLOSED_MM for g in self.bilabial_gap_mm)), len(self.bilabial_gap_mm))

    @property
    def contact(self) -> Recall:
        return Recall(int(sum(d <= CONTACT_MM for d in self.labiodental_mm)), len(self.labiodental_mm))

    @property
    def false_closed(self) -> Recall:
        return Recall(int(sum(g < CLOSED_MM for g in self.vowel_gap_mm)), len(self.vowel_gap_mm))

    @property
    def vowel_in_range(self) -> Recall:
        return Recall(int(sum(VOWEL_LOW <= r <= VOWEL_HIGH for r in self.vowel_opening)), len(self.vowel_opening))

    @staticmethod
    def _median(values: Sequence[float]) -> float | None:
        return float(np.median(values)) if len(values) else None

    @property
    def median_gap_mm(self) -> float | None:
        return self._median(self.bilabial_gap_mm)

    @property
    def median_labiodental_mm(self) -> float | None:
        return self._median(self.labiodental_mm)

    @property
    def median_vowel_opening(self) -> float | None:
        return self._median(self.vowel_opening)

    @property
    def max_vowel_opening(self) -> float | None:
        return float(max(self.vowel_opening)) if self.vowel_opening else None

    def summary(self) -> dict[str, float | int | None]:
        """The figures of the lip table: shares, medians and counts (None where there is nothing to judge)."""
        return {
            "bilabials": self.closed.total, "closed": self.closed.share, "median_gap_mm": self.median_gap_mm,
            "labiodentals": self.contact.total, "fv_contact": self.contact.share,
            "median_fv_mm": self.median_labiodental_mm,
            "open_vowels": len(self.vowel_opening), "vowel_opening": self.median_vowel_opening,
            "vowel_in_range": self.vowel_in_range.share, "max_vowel_opening": self.max_vowel_opening,
            "vowels": self.false_closed.total, "false_closed": self.false_closed.share,
        }


def score_lips(gap_mm: np.ndarray, teeth_mm: np.ndarray | None, fps: float,
               phones: pa.Table | Iterable[Mapping[str, object] | Phone], widest_mm: float) -> LipScores:
    """Per-phone lip figures from per-frame measures at `fps` and the aligned phones; `widest_mm` is the gap of the
    character's widest single shape (`LipProbe.single_shape_gap("AHH")`)."""
    gap = np.asarray(gap_mm, np.float64)
    teeth = None if teeth_mm is None else np.asarray(teeth_mm, np.float64)
    if gap.ndim != 1 or (teeth is not None and teeth.shape != gap.shape):
        raise ValueError(f"gap and teeth measures must be (frames,) alike, got {gap.shape} and "
                         f"{None if teeth is None else teeth.shape}")
    if not np.isfinite(gap).all() or (teeth is not None and not np.isfinite(teeth).all()):
        raise ValueError("lip measures hold NaN or infinity")
    if not widest_mm > 0:
        raise ValueError(f"the widest shape's gap must be positive, got {widest_mm}")
    bilabial, labiodental, opening, vowel_gap, skipped = [], [], [], [], 0
    for p in phones_of(phones):
        if p.viseme is None:
            continue
        frames = phone_frames(p.start_s, p.end_s, fps, len(gap))
        if frames is None:
            skipped += 1
            continue
        if p.viseme == "MBP":
            bilabial.append(float(gap[frames].min()))
        elif p.viseme == "FFF" and teeth is not None:
            labiodental.append(float(teeth[frames].min()))
        if p.viseme in VOWELS:
            widest = float(gap[frames].max())
            vowel_gap.append(widest)
            if p.viseme in OPEN_VOWELS:
                opening.append(widest / widest_mm)
    return LipScores(tuple(bilabial), tuple(labiodental), tuple(opening), tuple(vowel_gap), skipped)


def pool_lips(scores: Iterable[LipScores]) -> LipScores:
    """The phones of several utterances as one set."""
    scores = list(scores)
    return LipScores(*(tuple(x for s in scores for x in getattr(s, name))
                       for name in ("bilabial_gap_mm", "labiodental_mm", "vowel_opening", "vowel_gap_mm")),
                     skipped=sum(s.skipped for s in scores))
