"""The lip rules every viseme curve obeys before it reaches a face: closures that survive blending, bounded opening.

Blendshapes add. A bilabial at full weight (MBP = 1) co-active with a rounded vowel (OHH = 0.6) renders a mouth 12-22
mm open on the demo character, though the curve table says "closed"; a JALI animator would never let that through:
bilabials and labiodentals close the lips whatever the co-articulation (Edwards et al. 2016, section 4). So:

1. **Bilabial closure.** During MBP every other viseme yields: w_v <- min(w_v, 1 - MBP). At MBP = 1 the mouth is
   exactly the MBP shape (closed); at MBP = 0 nothing changes; in between the blend is continuous.
2. **Labiodental contact.** Then, during FFF, every viseme but MBP and FFF yields the same way: w_v <- min(w_v,
   1 - FFF), so the lower lip reaches the upper teeth at an f or v however open the vowel around it.
3. **Bounded opening.** The mouth never opens past the rig's widest single shape. Each viseme's lip opening is
   roughly linear in its weight; `OPENING` holds it relative to AHH's (the widest). When sum_v w_v OPENING[v] > 1 the
   opening visemes other than FFF are scaled down together until the sum is 1, so no blend opens wider than AHH.

`close_lips(curves)` applies the three in that order and leaves curves in [0, 1]. It is idempotent: curves that already
obey it (procedural curves, stored with the rule) pass through the animation stage's application unchanged. The procedural stage applies it to the curves it stores (`ProceduralConfig.closure_rule`)
and the animation stage to curves of every source before they drive a character (`AnimateConfig.closure_rule`), so
tracked and learned curves and a user's CSV get it too. Both switches default to on.
"""

from __future__ import annotations

import numpy as np

from visemeflow.visemes import N_VISEMES, VISEMES, viseme_index

__all__ = ["CLOSED_MM", "CONTACT_MM", "OPENING", "close_lips", "contact_keys", "opening"]

CLOSED_MM = 1.5
"""The lips are closed when the inner-lip gap on the mesh is below this (the demo character rests at 1.1 mm)."""
CONTACT_MM = 2.0
"""A labiodental touches when the lower lip is within this of the upper teeth."""

_OPENING_BY_VISEME = {
    "AAA": 0.62, "AHH": 1.00, "EH": 0.48, "FFF": 0.08, "GK": 0.37, "IEE": 0.16, "LNTD": 0.28, "MBP": 0.0,
    "OHH": 0.76, "RRR": 0.31, "SCHWA": 0.31, "SSH": 0.43, "SSS": 0.22, "TTH": 0.33, "UUU": 0.32, "WWW": 0.08,
}
OPENING: np.ndarray = np.array([_OPENING_BY_VISEME[v] for v in VISEMES], np.float32)
"""(16,) lip opening of each viseme shape relative to AHH's: the vertical inner-lip displacement of the shape on the
ICT demo rig (mean over the three inner-lip landmark pairs; MBP, which presses the lips, counts as 0), rounded to two
places. tests/test_articulation.py checks it against the shipped rig."""

_MBP = viseme_index("MBP")
_FFF = viseme_index("FFF")
_ALL_BUT_MBP = np.array([i for i in range(N_VISEMES) if i != _MBP])
_ALL_BUT_LIPS = np.array([i for i in range(N_VISEMES) if i not in (_MBP, _FFF)])


def opening(curves: np.ndarray) -> np.ndarray:
    """(T,) the blend's lip opening relative to AHH's, by the linear `OPENING` table."""
    return np.asarray(curves, np.float32) @ OPENING


def close_lips(curves: np.ndarray, *, bilabial: bool = True, labiodental: bool = True,
               bound_opening: bool = True) -> np.ndarray:
    """(T, 16) curves with the closure rules of the module applied; a new float32 array in [0, 1].

    Each rule can be switched off on its own (for measurements); the input is not modified."""
    out = np.array(curves, dtype=np.float32, copy=True)
    if out.ndim != 2 or out.shape[1] != N_VISEMES:
        raise ValueError(f"curves must be (frames, {N_VISEMES}), got {out.shape}")
    np.clip(out, 0.0, 1.0, out=out)
    if bilabial:
        out[:, _ALL_BUT_MBP] = np.minimum(out[:, _ALL_BUT_MBP], (1.0 - out[:, _MBP])[:, None])
    if labiodental:
        out[:, _ALL_BUT_LIPS] = np.minimum(out[:, _ALL_BUT_LIPS], (1.0 - out[:, _FFF])[:, None])
    if bound_opening:
        lips = out[:, _FFF] * OPENING[_FFF]
        rest = out[:, _ALL_BUT_LIPS] @ OPENING[_ALL_BUT_LIPS]
        over = lips + rest > 1.0
        if over.any():
            scale = np.ones(len(out), np.float32)
            scale[over] = (1.0 - lips[over]) / rest[over]
            out[:, _ALL_BUT_LIPS] *= scale[:, None]
    return out


def contact_keys(curves: np.ndarray) -> np.ndarray:
    """(K,) frames of `curves` (T, 16) that are a contact's key pose: MBP or FFF is the frame's largest weight there
    and at a peak in time (above the frame before, not below the frame after), ordered from the strongest contact down.

    A retimed animation must keep these frames whole: resampled linearly, a closure that lasts one frame at 30 fps
    falls between two frames at 24 fps and the lips stay apart (`animation.apply.resample_visemes`)."""
    c = np.asarray(curves, np.float32)
    if c.ndim != 2 or c.shape[1] != N_VISEMES:
        raise ValueError(f"curves must be (frames, {N_VISEMES}), got {c.shape}")
    if len(c) == 0:
        return np.zeros(0, np.int64)
    top = c.argmax(axis=1)
    keys = []
    for ch in (_MBP, _FFF):
        x = c[:, ch]
        before = np.concatenate([[-np.inf], x[:-1]])
        after = np.concatenate([x[1:], [-np.inf]])
        peak = (x > before) & (x >= after) & (top == ch) & (x > 0)   # a plateau's first frame
        keys.append(np.flatnonzero(peak))
    k = np.concatenate(keys)
    strength = c[k, top[k]]
    return k[np.argsort(-strength, kind="stable")].astype(np.int64)
