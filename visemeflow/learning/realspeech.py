"""Metrics of viseme curves on real speech that need no curve truth: only the utterance's phone alignment (and,
where captured curves exist, a comparison with them).

Every learning figure measured against synthetic curve truth says nothing about real speech; these do. Pure:
numpy and pyarrow only, no torch, no Prefect, no files.

Frames and phones. Frame ``k`` of a ``(frames, 16)`` curve array is the time ``k / fps``. A phone
``[start_s, end_s)`` covers the frames with ``start_s <= k / fps < end_s`` (compared in float64 exactly as
written); a phone that covers no frame (shorter than a frame, or falling between two) gets the one frame nearest
its midpoint, ``floor(mid * fps + 0.5)``, clamped to the curves. A phone starting at or after the end of the
curves (``start_s >= frames / fps``) is outside them: not scored, counted in ``skipped``. Silence (viseme null,
as the `phones` table stores silence and transparent phones) is never scored.

The phone's **top viseme** is the viseme with the highest *maximum* weight over the phone's frames, i.e.
``argmax_v max_{k in phone} curves[k, v]``. Why the maximum and not the mean or a majority of per-frame argmaxes:
a bilabial closure is an event of a frame or two inside a phone that the alignment brackets only roughly (forced
aligners place boundaries within ~20 ms, about a frame at 30 fps), and the frames around it belong to the
neighbours' coarticulation. The mean over the phone, or a per-frame vote, would count a closure that does happen,
briefly, as a miss; the maximum asks "did the lips close, as the strongest shape, at some point of the phone".
Equivalently, the phone's viseme wins if, at the frame where it peaks, it is the per-frame argmax and no other
viseme peaks higher anywhere in the phone. A tie for the top is **not** a hit (the rule is strict), so a curve that
is flat or saturated at 1 for several visemes earns nothing.

Metrics:

* **closure recall** of a viseme (``MBP`` for b/p/m, ``FFF`` for f/v): among the scored phones whose viseme it
  is, the share whose top viseme it is. :class:`Recall` keeps ``hits`` and ``total``; ``share`` is ``None`` when
  ``total`` is 0 (no such phone: undefined, not 0 and not 1). Recall alone rewards a face that keeps its lips shut:
  a constant curve whose largest weight is MBP has a recall of 1. Its counterpart, **false closures**
  (``RealSpeechScores.false_closure``), is the share of the *other* scored phones whose top viseme (strictly) is
  the closure viseme; read the two together.
* **activation agreement**: at each scored phone's apex, the frame nearest its midpoint (the same
  ``floor(mid * fps + 0.5)``, clamped into the phone's frames), is the phone's own viseme among the top ``k = 2``
  of the 16 weights? Its rank is the number of *other* visemes whose weight is ``>=`` its own, and it is in the
  top ``k`` when that rank is below ``k`` (so ties count against it, as in closure recall). The share over every
  scored phone, and per viseme.
* **reference comparison** (:func:`compare_curves`), for captured or any other reference curves of the same
  utterance at the same rate: ``L1 x 100`` (mean absolute difference over frames and the 16 visemes, x 100) and
  the Pearson correlation of each viseme's column; a column constant in either array has no correlation (NaN,
  reported as such) and the mean is over the defined ones. Lengths may differ by rounding: the longer is
  truncated to the shorter, unless they differ by more than one frame per second of the shorter (at least one
  frame), which is an error (another rate, or another take).

Pooling over utterances (:func:`pool`) adds hits and totals, so the pooled share weighs every phone alike (a
long utterance counts by its phones, as the evaluation's L1 counts frames), not every utterance alike.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa

from visemeflow.visemes import N_VISEMES, VISEME_INDEX, VISEMES

__all__ = [
    "CLOSURE_VISEMES",
    "TOP_K",
    "Agreement",
    "Phone",
    "PhoneScore",
    "RealSpeechScores",
    "Recall",
    "ReferenceComparison",
    "activation_agreement",
    "closure_recall",
    "compare_curves",
    "phone_frames",
    "phones_of",
    "pool",
    "scale_phones",
    "score_phones",
    "score_utterance",
]

CLOSURE_VISEMES: tuple[str, ...] = ("MBP", "FFF")   # bilabial b/p/m, labiodental f/v
TOP_K = 2


@dataclass(frozen=True)
class Phone:
    """One aligned phone: ``[start_s, end_s)`` and its viseme (None: silence, never scored)."""

    start_s: float
    end_s: float
    viseme: str | None


@dataclass(frozen=True)
class Recall:
    """``hits`` of ``total`` phones; ``share`` is None when there is no phone to judge."""

    hits: int = 0
    total: int = 0

    @property
    def share(self) -> float | None:
        return self.hits / self.total if self.total else None

    def __add__(self, other: Recall) -> Recall:
        return Recall(self.hits + other.hits, self.total + other.total)


@dataclass(frozen=True)
class Agreement:
    """Activation agreement over every scored phone, and per viseme (only visemes that have phones)."""

    overall: Recall = Recall()
    per_viseme: dict[str, Recall] = field(default_factory=dict)

    @property
    def share(self) -> float | None:
        return self.overall.share


@dataclass(frozen=True)
class PhoneScore:
    """How one scored phone fared: its frames, the top viseme within it and its viseme's rank at the apex."""

    viseme: str
    start_s: float
    end_s: float
    first_frame: int
    last_frame: int          # inclusive
    apex_frame: int
    top: str                 # argmax of the per-viseme maxima over the phone (first in VISEMES order on a tie)
    top_unique: bool         # no other viseme's maximum equals the top's
    apex_rank: int           # other visemes whose weight at the apex is >= the phone's viseme's

    @property
    def top_hit(self) -> bool:
        """The phone's viseme is strictly the top: no other viseme's maximum within the phone equals or beats it."""
        return self.top_unique and self.top == self.viseme


@dataclass(frozen=True)
class RealSpeechScores:
    """Closure recall per closure viseme and activation agreement of one utterance, or pooled over several."""

    closure: dict[str, Recall]
    agreement: Agreement
    skipped: int = 0         # phones outside the curves (start at or after their end)
    # per closure viseme: of the scored phones of other visemes, those whose top (strictly) it is
    false_closure: dict[str, Recall] = field(default_factory=dict)


# ---- inputs -------------------------------------------------------------------------------------------------
def phones_of(phones: pa.Table | Iterable[Mapping[str, object] | Phone]) -> list[Phone]:
    """Phones from a `phones` table (one utterance's rows; columns ``start_s``, ``end_s``, ``viseme``), row
    mappings with those keys, or :class:`Phone` objects; checked: finite times, ``end_s >= start_s``, a viseme
    among the 16 or null. Rows of several utterances are refused (their times would interleave)."""
    if isinstance(phones, pa.Table):
        if "utterance_id" in phones.column_names and len(set(phones.column("utterance_id").to_pylist())) > 1:
            raise ValueError("phones of several utterances given; score one utterance at a time")
        rows: Iterable[Mapping[str, object] | Phone] = phones.select(["start_s", "end_s", "viseme"]).to_pylist()
    else:
        rows = phones
    out = []
    for n, row in enumerate(rows):
        if isinstance(row, Phone):
            start, end, viseme = row.start_s, row.end_s, row.viseme
        else:
            start, end, viseme = row["start_s"], row["end_s"], row.get("viseme")
        start, end = float(start), float(end)
        if not (math.isfinite(start) and math.isfinite(end)):
            raise ValueError(f"phone {n}: times must be finite, got {start}..{end}")
        if end < start:
            raise ValueError(f"phone {n}: ends before it starts ({start}..{end})")
        if viseme is not None and viseme not in VISEME_INDEX:
            raise ValueError(f"phone {n}: unknown viseme {viseme!r}; expected one of {', '.join(VISEMES)} or null")
        out.append(Phone(start, end, viseme))
    return out


def scale_phones(phones: Sequence[Phone], time_factor: float) -> list[Phone]:
    """Phones of the same audio played ``time_factor`` times faster (speed augmentation): times divided by it."""
    if not time_factor > 0:
        raise ValueError(f"time_factor must be positive, got {time_factor}")
    return [Phone(p.start_s / time_factor, p.end_s / time_factor, p.viseme) for p in phones]


def _check_curves(curves: np.ndarray, fps: float, what: str = "curves") -> np.ndarray:
    curves = np.asarray(curves)
    if curves.ndim != 2 or curves.shape[1] != N_VISEMES:
        raise ValueError(f"{what} must have shape (frames, {N_VISEMES}), got {curves.shape}")
    if not np.isfinite(curves).all():
        frame = int(np.flatnonzero(~np.isfinite(curves).all(axis=1))[0])
        raise ValueError(f"{what} hold NaN or infinity (first at frame {frame})")
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps}")
    return curves.astype(np.float64, copy=False)


# ---- frames of a phone --------------------------------------------------------------------------------------
def _nearest_frame(t: float, fps: float) -> int:
    return int(math.floor(t * fps + 0.5))


def phone_frames(start_s: float, end_s: float, fps: float, n_frames: int) -> np.ndarray | None:
    """Frames ``k < n_frames`` with ``start_s <= k / fps < end_s``; the frame nearest the midpoint when none is;
    None when the phone starts at or after the end of the curves (``start_s >= n_frames / fps``)."""
    if n_frames <= 0 or start_s >= n_frames / fps:
        return None
    lo = max(0, math.floor(start_s * fps) - 1)
    hi = min(n_frames, math.ceil(end_s * fps) + 2)
    k = np.arange(lo, hi, dtype=np.int64)
    t = k / float(fps)
    covered = k[(t >= start_s) & (t < end_s)]
    if covered.size:
        return covered
    mid = min(max(_nearest_frame(0.5 * (start_s + end_s), fps), 0), n_frames - 1)
    return np.array([mid], dtype=np.int64)


# ---- scores -------------------------------------------------------------------------------------------------
def score_phones(curves: np.ndarray, fps: float,
                 phones: pa.Table | Iterable[Mapping[str, object] | Phone]) -> tuple[list[PhoneScore], int]:
    """(:class:`PhoneScore` of every scored phone in order, number of non-silent phones outside the curves)."""
    c = _check_curves(curves, fps)
    scored, skipped = [], 0
    for p in phones_of(phones):
        if p.viseme is None:
            continue
        frames = phone_frames(p.start_s, p.end_s, fps, c.shape[0])
        if frames is None:
            skipped += 1
            continue
        v = VISEME_INDEX[p.viseme]
        peaks = c[frames].max(axis=0)
        top = int(np.argmax(peaks))
        apex = min(max(_nearest_frame(0.5 * (p.start_s + p.end_s), fps), int(frames[0])), int(frames[-1]))
        at_apex = c[apex]
        rank = int((np.delete(at_apex, v) >= at_apex[v]).sum())
        scored.append(PhoneScore(p.viseme, p.start_s, p.end_s, int(frames[0]), int(frames[-1]), apex,
                                 VISEMES[top], bool((np.delete(peaks, top) < peaks[top]).all()), rank))
    return scored, skipped


def _closure(scores: Sequence[PhoneScore], visemes: Sequence[str]) -> dict[str, Recall]:
    out = {}
    for name in visemes:
        mine = [s for s in scores if s.viseme == name]
        out[name] = Recall(sum(s.top_hit for s in mine), len(mine))
    return out


def _false_closure(scores: Sequence[PhoneScore], visemes: Sequence[str]) -> dict[str, Recall]:
    out = {}
    for name in visemes:
        others = [s for s in scores if s.viseme != name]
        out[name] = Recall(sum(s.top == name and s.top_unique for s in others), len(others))
    return out


def _agreement(scores: Sequence[PhoneScore], k: int) -> Agreement:
    per: dict[str, Recall] = {}
    for s in scores:
        per[s.viseme] = per.get(s.viseme, Recall()) + Recall(int(s.apex_rank < k), 1)
    per = {v: per[v] for v in VISEMES if v in per}
    return Agreement(sum(per.values(), Recall()), per)


def closure_recall(curves: np.ndarray, fps: float, phones: pa.Table | Iterable[Mapping[str, object] | Phone],
                   visemes: Sequence[str] = CLOSURE_VISEMES) -> dict[str, Recall]:
    """Per viseme of ``visemes``: of its phones, how many have it as their top viseme (strictly). See the module."""
    for name in visemes:
        if name not in VISEME_INDEX:
            raise ValueError(f"unknown viseme {name!r}")
    return _closure(score_phones(curves, fps, phones)[0], visemes)


def activation_agreement(curves: np.ndarray, fps: float,
                         phones: pa.Table | Iterable[Mapping[str, object] | Phone], k: int = TOP_K) -> Agreement:
    """Of the non-silent phones, how many have their viseme among the top ``k`` weights at their apex frame."""
    if k < 1:
        raise ValueError(f"k must be at least 1, got {k}")
    return _agreement(score_phones(curves, fps, phones)[0], k)


def frame_visemes(phones: pa.Table | Iterable[Mapping[str, object] | Phone], n_frames: int, fps: float) -> np.ndarray:
    """(n_frames,) int64: the index (``VISEME_INDEX``) of the viseme of the phone at each frame (frame k at k / fps;
    a phone covers ``[start_s, end_s)``, the later phone wins on an overlap), -1 where there is none (silence, a gap,
    past the last phone): the labels of the auxiliary viseme loss (``TrainConfig.viseme_loss_weight``)."""
    out = np.full(int(n_frames), -1, np.int64)
    t = np.arange(int(n_frames)) / float(fps)
    for p in sorted(phones_of(phones), key=lambda p: p.start_s):
        if p.viseme is not None:
            out[(t >= p.start_s) & (t < p.end_s)] = VISEME_INDEX[p.viseme]
    return out


def score_utterance(curves: np.ndarray, fps: float, phones: pa.Table | Iterable[Mapping[str, object] | Phone],
                    visemes: Sequence[str] = CLOSURE_VISEMES, k: int = TOP_K) -> RealSpeechScores:
    """Closure recall and activation agreement of one utterance's curves, its phones scored once."""
    scores, skipped = score_phones(curves, fps, phones)
    return RealSpeechScores(_closure(scores, visemes), _agreement(scores, k), skipped, _false_closure(scores, visemes))


def pool(scores: Iterable[RealSpeechScores]) -> RealSpeechScores:
    """Several utterances' scores as one: hits and totals added (each phone weighs the same)."""
    closure: dict[str, Recall] = {}
    false: dict[str, Recall] = {}
    overall, per, skipped = Recall(), {}, 0
    for s in scores:
        for name, r in s.closure.items():
            closure[name] = closure.get(name, Recall()) + r
        for name, r in s.false_closure.items():
            false[name] = false.get(name, Recall()) + r
        overall = overall + s.agreement.overall
        for name, r in s.agreement.per_viseme.items():
            per[name] = per.get(name, Recall()) + r
        skipped += s.skipped
    return RealSpeechScores(closure, Agreement(overall, {v: per[v] for v in VISEMES if v in per}), skipped, false)


# ---- against reference curves -------------------------------------------------------------------------------
@dataclass(frozen=True)
class ReferenceComparison:
    """Curves against reference curves of the same utterance, over their first ``frames`` frames."""

    frames: int
    l1_x100: float
    pearson: dict[str, float]    # per viseme, NaN where either column is constant
    mean_pearson: float          # over the defined ones; NaN when none is

    @property
    def defined(self) -> int:
        return sum(not math.isnan(r) for r in self.pearson.values())


def compare_curves(curves: np.ndarray, reference: np.ndarray, fps: float) -> ReferenceComparison:
    """L1 x 100 and per-viseme Pearson correlation of ``curves`` against ``reference`` (both at ``fps``).

    The longer array is truncated to the shorter; a length difference of more than one frame per second of the
    shorter (at least one frame) is a ValueError, as is an empty overlap.
    """
    a = _check_curves(curves, fps)
    b = _check_curves(reference, fps, "reference curves")
    n = min(len(a), len(b))
    allowed = max(1.0, n / fps)
    if abs(len(a) - len(b)) > allowed:
        raise ValueError(f"curves have {len(a)} frames and the reference {len(b)} at {fps} fps: more than one "
                         f"frame per second apart ({allowed:.2f} allowed); another rate or another take?")
    if n == 0:
        raise ValueError("no frame to compare")
    a, b = a[:n], b[:n]
    l1 = 100.0 * float(np.abs(a - b).mean())
    pearson = {}
    for i, name in enumerate(VISEMES):
        x, y = a[:, i], b[:, i]
        # constant: every value equal (np.ptp == 0), judged on the values, not on a float std that rounding
        # can leave at 1e-17 for a constant column
        if n < 2 or np.ptp(x) == 0 or np.ptp(y) == 0:
            pearson[name] = math.nan
            continue
        dx, dy = x - x.mean(), y - y.mean()
        r = float((dx * dy).sum() / math.sqrt(float((dx * dx).sum()) * float((dy * dy).sum())))
        pearson[name] = min(1.0, max(-1.0, r))
    defined = [r for r in pearson.values() if not math.isnan(r)]
    return ReferenceComparison(n, l1, pearson, float(np.mean(defined)) if defined else math.nan)
