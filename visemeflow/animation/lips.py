"""What the viewer sees of the lips: the inner-lip gap and the lower lip's distance to the upper teeth, in millimetres,
measured on a character's mesh frame by frame.

A curve table can say "MBP = 1" while the rendered mouth stands 12-22 mm open (other visemes add their opening), so
closures are judged here, on the deformed mesh:

- **gap**: the mean distance of the three inner-lip landmark pairs of the 68-point layout (61-67, 62-66, 63-65: the
  upper and lower inner lip at the quarter points and the middle); a character without landmarks (a user's GLB) uses
  the three pairs `lipfinder` finds in its geometry, where it finds a mouth. On the ICT demo character: neutral 1.1 mm, MBP
  alone 1.1 mm, AHH alone 29.5 mm. A bilabial is *closed* below `CLOSED_MM` (1.5 mm).
- **teeth**: the shortest distance from the lower lip's midline (lip vertices within 8 mm of the mouth's middle that
  AHH carries down by a fifth of its largest drop or more) to the upper incisors (teeth vertices within 15 mm of the middle that AHH does not move). On the
  demo character: FFF alone 0.3 mm, neutral 1.2 mm, AHH 28 mm. A labiodental touches within `CONTACT_MM` (2 mm).

`LipProbe` holds those vertex ids, the neutral positions of just those vertices and the viseme deltas there, so
measuring (T, 16) curves costs T x (a few hundred vertices), not the whole mesh. `LipProbe.from_rig` builds it from a
16-viseme rig with landmarks and `teeth`/`lips` regions (the demo rig, transferred characters); a character without
them has no probe (`probe_for_character` returns None and says why).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from visemeflow.articulation import CLOSED_MM, CONTACT_MM
from visemeflow.rig import VisemeRig
from visemeflow.visemes import N_VISEMES, viseme_index

__all__ = ["CLOSED_MM", "CONTACT_MM", "LipFrames", "LipProbe"]


_UPPER = (61, 62, 63)
_LOWER = (67, 66, 65)
_MIDLINE_MM = 8.0
_INCISORS_MM = 15.0
_MOVES_MM = 0.05
_MAX_TEETH = 160


@dataclass(frozen=True)
class LipFrames:
    """Per-frame lip measures of one clip, (T,) float32 each, millimetres."""

    gap_mm: np.ndarray
    teeth_mm: np.ndarray | None
    """None when the character has no teeth region to measure against."""


@dataclass(frozen=True, eq=False)
class LipProbe:
    """The few vertices the lip measures need, at rest and per viseme, in millimetres."""

    name: str
    pairs_rest: np.ndarray
    """(2, 3, 3) rest positions of the upper and lower inner-lip points, mm."""
    pairs_delta: np.ndarray
    """(16, 2, 3, 3) viseme deltas at those points, mm."""
    lip_rest: np.ndarray
    """(L, 3) lower-lip midline vertices at rest, mm (L may be 0)."""
    lip_delta: np.ndarray
    """(16, L, 3)."""
    teeth_rest: np.ndarray
    """(M, 3) upper incisor vertices, mm (M may be 0: no teeth measure)."""
    teeth_delta: np.ndarray
    """(16, M, 3)."""

    @classmethod
    def from_arrays(cls, name: str, neutral: np.ndarray, viseme_deltas: np.ndarray, landmark_ids: np.ndarray,
                    regions: dict[str, np.ndarray] | None = None, mm_per_unit: float = 10.0) -> LipProbe:
        """A probe from a mesh: (V, 3) neutral, (16, V, 3) deltas of the 16 visemes in VISEMES order (for a character
        in another convention: the deltas its binding makes of each viseme), 68 landmark vertex ids (-1 = none) and
        optional `lips` / `teeth` regions. `mm_per_unit`: 10 for centimetres (the ICT rig), 1000 for metres (glTF).

        ValueError when an inner-lip landmark is missing."""
        neutral = np.asarray(neutral, np.float64) * mm_per_unit
        deltas = np.asarray(viseme_deltas, np.float64) * mm_per_unit
        if deltas.shape != (N_VISEMES,) + neutral.shape:
            raise ValueError(f"{name}: viseme deltas must be ({N_VISEMES}, {len(neutral)}, 3), got {deltas.shape}")
        ids = np.asarray(landmark_ids, np.int64)
        pair_ids = ids[list(_UPPER) + list(_LOWER)]
        if (pair_ids < 0).any() or len(ids) < 68:
            raise ValueError(f"{name}: the inner-lip landmarks 61-63 and 65-67 are needed to measure the lips")
        pairs = pair_ids.reshape(2, 3)
        neutral = neutral - neutral[pairs].mean(axis=(0, 1))   # centred on the mouth: small numbers, exact distances
        regions = regions or {}
        ahh = deltas[viseme_index("AHH")]
        middle_x = neutral[pairs, 0].mean()
        lips = np.asarray(regions.get("lips", []), np.int64)
        teeth = np.asarray(regions.get("teeth", []), np.int64)
        # the lower lip: lip vertices near the middle that AHH (the jaw opening) carries down by a fifth of its
        # largest drop or more
        drop = -ahh[lips, 1] if lips.size else np.zeros(0)
        lower = lips[(np.abs(neutral[lips, 0] - middle_x) < _MIDLINE_MM)
                     & (drop > max(_MOVES_MM, 0.2 * float(drop.max(initial=0.0))))]
        upper_teeth = teeth[(np.abs(neutral[teeth, 0] - middle_x) < _INCISORS_MM)
                            & (np.linalg.norm(ahh[teeth], axis=1) <= _MOVES_MM)] if teeth.size else teeth
        if not lower.size or not upper_teeth.size:
            lower, upper_teeth = lower[:0], upper_teeth[:0]
        elif len(upper_teeth) > _MAX_TEETH:   # the incisal edge: the teeth vertices nearest the lower lip at rest
            nearest = np.linalg.norm(neutral[upper_teeth][:, None] - neutral[lower][None], axis=-1).min(axis=1)
            upper_teeth = upper_teeth[np.sort(np.argsort(nearest, kind="stable")[:_MAX_TEETH])]
        return cls(name=name, pairs_rest=neutral[pairs].astype(np.float32),
                   pairs_delta=deltas[:, pairs].astype(np.float32),
                   lip_rest=neutral[lower].astype(np.float32), lip_delta=deltas[:, lower].astype(np.float32),
                   teeth_rest=neutral[upper_teeth].astype(np.float32),
                   teeth_delta=deltas[:, upper_teeth].astype(np.float32))

    @classmethod
    def from_rig(cls, rig: VisemeRig, mm_per_unit: float = 10.0) -> LipProbe:
        """The probe of a 16-viseme rig (the demo rig is in centimetres: 10 mm per unit)."""
        return cls.from_arrays(rig.name, rig.neutral, rig.deltas, rig.landmark_ids, rig.regions, mm_per_unit)

    @property
    def has_teeth(self) -> bool:
        return len(self.teeth_rest) > 0

    def measure(self, curves: np.ndarray, chunk_frames: int = 256) -> LipFrames:
        """Gap and lower-lip-to-teeth distance (mm) of every frame of (T, 16) curves, as they would render."""
        c = np.asarray(curves, np.float32)
        if c.ndim != 2 or c.shape[1] != N_VISEMES:
            raise ValueError(f"curves must be (frames, {N_VISEMES}), got {c.shape}")
        pairs = self.pairs_rest[None] + np.tensordot(c, self.pairs_delta, axes=1)        # (T, 2, 3, 3)
        gap = np.linalg.norm(pairs[:, 0] - pairs[:, 1], axis=-1).mean(axis=1).astype(np.float32)
        if not self.has_teeth:
            return LipFrames(gap, None)
        teeth = np.empty(len(c), np.float32)
        for start in range(0, len(c), chunk_frames):
            block = c[start:start + chunk_frames]
            lip = self.lip_rest[None] + np.tensordot(block, self.lip_delta, axes=1)        # (t, L, 3)
            tooth = self.teeth_rest[None] + np.tensordot(block, self.teeth_delta, axes=1)  # (t, M, 3)
            squared = ((lip * lip).sum(-1)[:, :, None] + (tooth * tooth).sum(-1)[:, None]
                       - 2.0 * np.einsum("tlk,tmk->tlm", lip, tooth))
            teeth[start:start + len(block)] = np.sqrt(np.maximum(squared.reshape(len(block), -1).min(axis=1), 0))
        return LipFrames(gap, teeth)

    def single_shape_gap(self, viseme: str) -> float:
        """The gap (mm) of one viseme at full weight alone: `single_shape_gap("AHH")` is the widest opening."""
        one = np.zeros((1, N_VISEMES), np.float32)
        one[0, viseme_index(viseme)] = 1.0
        return float(self.measure(one).gap_mm[0])


# ---- any character with inner-lip landmarks, in its own shapes ---------------------------------------------------
_INNER_LIP_PAIRS = ((61, 67), (62, 66), (63, 65))
_BILABIALS = frozenset({"b", "p", "m", "em", "bh", "ph", "mb"})


def is_bilabial(label: str) -> bool:
    """Whether a phone label (ARPAbet, IPA, X-SAMPA, a pinyin initial) is a bilabial stop or nasal."""
    return label.strip().lower().rstrip("0123456789ːʰ") in _BILABIALS


def inner_lip_pairs(character) -> np.ndarray | None:
    """(3, 2) vertex ids of a `Character`'s inner-lip pairs (upper, lower): its landmark pairs, else the pairs
    `lipfinder` finds in its geometry (a user's own head), else None."""
    ids = character.landmark_ids
    if ids is None or len(ids) < 68:
        from visemeflow.animation.lipfinder import found_inner_lips

        return found_inner_lips(character)
    pairs = np.asarray([[ids[a], ids[b]] for a, b in _INNER_LIP_PAIRS], np.int64)
    return pairs if (pairs >= 0).all() and (pairs < character.n_vertices).all() else None


def character_gap_mm(character, weights: np.ndarray) -> np.ndarray | None:
    """(T,) inner-lip gap (mm) of a `Character` driven by (T, S) weights in its own shape order; None without
    inner-lip landmarks. Only the six lip vertices are deformed."""
    pairs = inner_lip_pairs(character)
    if pairs is None:
        return None
    ids = pairs.ravel()
    at = character.neutral[ids][None] + np.tensordot(np.asarray(weights, np.float32), character.deltas[:, ids], axes=1)
    return pair_gap_mm(at.reshape(len(at), 3, 2, 3), character.mm_per_unit)


def pair_gap_mm(pairs: np.ndarray, mm_per_unit: float) -> np.ndarray:
    """The gap (mm) of (..., 3, 2, 3) inner-lip pair positions (upper, lower): the mean of the three distances."""
    return (np.linalg.norm(pairs[..., 0, :] - pairs[..., 1, :], axis=-1).mean(axis=-1) * mm_per_unit).astype(np.float32)


def closure_report(character, binding, weights: np.ndarray, fps: float,
                   phones: list[tuple[float, float, str]] | None) -> dict:
    """What a user should know of one package's lips: the gap of the character's own MBP (a warning when that does not
    close: the rig cannot show a closure) and, with phones, how many b/p/m closed below `CLOSED_MM` on the mesh.
    {} for a character without inner-lip landmarks."""
    one = np.zeros((1, N_VISEMES), np.float32)
    one[0, viseme_index("MBP")] = 1.0
    own = character_gap_mm(character, binding.weights(one))
    if own is None:
        return {}
    report: dict = {"mbp_shape_gap_mm": round(float(own[0]), 2)}
    if own[0] >= CLOSED_MM:
        report["warning"] = (f"{character.where()}: its MBP shape leaves the lips {own[0]:.1f} mm apart (closed is "
                             f"below {CLOSED_MM} mm); no curve can close this character's mouth")
    gap = character_gap_mm(character, weights)
    if phones and gap is not None and len(gap):
        apexes = []
        for start, end, label in phones:
            if is_bilabial(label):
                first = min(max(int(np.ceil(start * fps - 1e-9)), 0), len(gap) - 1)
                last = min(max(int(np.ceil(end * fps - 1e-9)), first + 1), len(gap))
                apexes.append(float(gap[first:last].min()))
        if apexes:
            report.update(bilabials=len(apexes), closed=int(sum(g < CLOSED_MM for g in apexes)),
                          median_gap_mm=round(float(np.median(apexes)), 2))
    return report
