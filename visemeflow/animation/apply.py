"""Curves applied to characters: checks, resampling to another frame rate, and chunked deformation.

`deform` turns (T, S) shape weights into (T, V, 3) vertices in chunks of frames, so a one-hour take (108,000
frames at 30 fps) never needs more than `chunk_frames` x V x 3 floats at once.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from visemeflow.articulation import contact_keys
from visemeflow.rig.character import Character
from visemeflow.visemes import VISEMES

RANGE_TOLERANCE = 1e-3
"""How far outside [0, 1] a curve may stray (float rounding of a model's output) before it is an error."""


class CurvesError(ValueError):
    """Curves that cannot drive a character: the message names the utterance, frame and viseme."""


def check_curves(curves: np.ndarray, where: str, names: tuple[str, ...] | list[str] = VISEMES) -> np.ndarray:
    """Float32 curves clipped to [0, 1]; CurvesError for NaN/inf or values beyond [0, 1] by more than the tolerance.

    `where` names the utterance (and file) in the message; `names` are the columns' names."""
    curves = np.asarray(curves, dtype=np.float32)
    if curves.ndim != 2 or curves.shape[1] != len(names):
        raise CurvesError(f"{where}: curves must be (frames, {len(names)}), got {curves.shape}")
    if len(curves) == 0:
        raise CurvesError(f"{where}: no frames")
    bad = ~np.isfinite(curves)
    if bad.any():
        frame, column = map(int, np.argwhere(bad)[0])
        raise CurvesError(f"{where}: {names[column]} is {curves[frame, column]} at frame {frame} "
                          f"({int(bad.sum())} non-finite values)")
    out = (curves < -RANGE_TOLERANCE) | (curves > 1 + RANGE_TOLERANCE)
    if out.any():
        frame, column = map(int, np.argwhere(out)[0])
        raise CurvesError(f"{where}: {names[column]} is {curves[frame, column]:.4f} at frame {frame}, outside "
                          f"[0, 1] ({int(out.sum())} values outside); weights of a blendshape rig live in [0, 1]")
    return np.clip(curves, 0.0, 1.0)


def resampled_frame_count(n_frames: int, fps_from: float, fps_to: float) -> int:
    """Frames at `fps_to` that cover the span of `n_frames` frames at `fps_from` (frame 0 at time 0)."""
    span = (n_frames - 1) / fps_from
    return int(np.floor(span * fps_to + 1e-9)) + 1


def resample(curves: np.ndarray, fps_from: float, fps_to: float, keys: np.ndarray | None = None) -> np.ndarray:
    """Curves at `fps_to` by linear interpolation in time (never a stretch: the duration is kept, frame k at k/fps).

    `keys`: source frames to keep whole, each on the new frame nearest its time, in order of priority (a new frame
    takes the first key that lands on it). Returns the input (as float32) when the rates are equal."""
    curves = np.asarray(curves, np.float32)
    if fps_from <= 0 or fps_to <= 0:
        raise ValueError(f"frame rates must be > 0, got {fps_from} and {fps_to}")
    if abs(fps_from - fps_to) < 1e-9 or len(curves) < 2:
        return curves
    t_from = np.arange(len(curves)) / fps_from
    t_to = np.arange(resampled_frame_count(len(curves), fps_from, fps_to)) / fps_to
    out = np.stack([np.interp(t_to, t_from, column) for column in curves.T], axis=1).astype(np.float32)
    if keys is not None:
        taken = np.zeros(len(out), bool)
        for k in np.asarray(keys, np.int64):
            j = min(int(np.rint(k / fps_from * fps_to)), len(out) - 1)   # a key past the last new frame: on it
            if 0 <= k < len(curves) and 0 <= j and not taken[j]:
                out[j], taken[j] = curves[k], True
    return out


def resample_visemes(curves: np.ndarray, fps_from: float, fps_to: float) -> np.ndarray:
    """Viseme curves (T, 16) at `fps_to`: linear in time, except that each contact's key pose (a closure's or an
    f/v's peak frame, `articulation.contact_keys`) is kept whole on the nearest new frame, the strongest first.

    Linear resampling alone loses the short closures a learned model makes: on the 148 English telephone prompts the
    demo head's lips met at 91.0% of the b/p/m at 30 fps and at 82.2% once resampled to 24 fps (80.4% at 25). A key
    moves by at most half a new frame (21 ms at 24 fps); one on the last frames, by at most one new frame."""
    curves = np.asarray(curves, np.float32)
    if abs(fps_from - fps_to) < 1e-9 or len(curves) < 2:
        return resample(curves, fps_from, fps_to)
    return resample(curves, fps_from, fps_to, keys=contact_keys(curves))


def deform(character: Character, weights: np.ndarray, chunk_frames: int = 256) -> Iterator[tuple[int, np.ndarray]]:
    """Yield (first frame, (n, V, 3) float32 vertices) chunks of neutral + weights @ deltas, n <= chunk_frames."""
    weights = np.asarray(weights, np.float32)
    if weights.ndim != 2 or weights.shape[1] != character.n_shapes:
        raise ValueError(f"{character.where()}: weights must be (frames, {character.n_shapes}), got {weights.shape}")
    if chunk_frames < 1:
        raise ValueError("chunk_frames must be >= 1")
    basis = character.deltas.reshape(character.n_shapes, -1)
    offset = character.neutral.reshape(1, -1)
    for start in range(0, len(weights), chunk_frames):
        block = weights[start:start + chunk_frames]
        yield start, (block @ basis + offset).reshape(len(block), character.n_vertices, 3)


def deform_all(character: Character, weights: np.ndarray, chunk_frames: int = 256) -> np.ndarray:
    """(T, V, 3) float32 vertices of every frame (for short clips; long takes should iterate `deform`)."""
    weights = np.asarray(weights, np.float32)
    out = np.empty((len(weights), character.n_vertices, 3), np.float32)
    for start, block in deform(character, weights, chunk_frames):
        out[start:start + len(block)] = block
    return out
