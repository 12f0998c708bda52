"""Web-avatar JSON: blendshape weights over time as an animation template of the TalkingHead library
(met4citizen/TalkingHead), which `head.speakAudio({audio, anim})` plays in sync with the audio.

    {"name": "hello", "fps": 30.0, "frames": 3, "delay": 0,
     "dt": [0, 33.333333333333336, 33.333333333333336],
     "vs": {"viseme_PP": [0.0, 0.25, 1.0], "viseme_aa": [...], ...}}

How TalkingHead reads a template (`animFactory` in modules/talkinghead.mjs): key times start at 0 and each `dt`
entry (milliseconds) adds one, `ts[i+1] = ts[i] + dt[i]`; the values of `vs[name]` are the targets reached at
`ts[1], ts[2], ...` (the value at `ts[0]` is whatever the morph target had), linearly interpolated in between.
So `vs[name][i]` is reached at `dt[0] + ... + dt[i]` ms. To put frame k exactly at k / fps, `dt[0]` is 0 (frame 0
at the start; TalkingHead treats a zero step as a jump) and every later step is 1000 / fps ms: `sum(dt)` is the
time of the last frame, (T - 1) * 1000 / fps. (Its README's `dt: [33, 33, ...]` puts every frame one step late.)

- `vs` holds one list per shape, in the given (character's) order and with its exact names, one value per frame,
  rounded to 4 decimals (`DECIMALS`: a step of 1e-4 of the full weight, invisible on a web avatar, and a third
  smaller file than full float32 text).
- `fps` and `frames` say what the lists are (TalkingHead ignores keys it does not know); `delay` 0 is what its
  streaming path (`anims`, which adds the audio start to `delay`) needs to be present.
- `dt` entries are written at full double precision, so their sum does not drift over a long clip.

`read_web_json` gives back (names, (T, S) float32 weights, fps), from `fps` or, without it, from `dt`.
Pure: numpy and `atomic` only.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from visemeflow.atomic import atomic_write_text

__all__ = ["DECIMALS", "read_web_json", "web_json", "write_web_json"]

DECIMALS = 4


def _check_fps(fps, where: str) -> float:
    if isinstance(fps, bool) or not isinstance(fps, (int, float, np.integer, np.floating)) or \
            not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"{where}: fps must be a positive number, got {fps!r}")
    return float(fps)


def web_json(shape_names, weights, fps: float, *, name: str, where: str = "web JSON") -> dict:
    """The TalkingHead animation template (a dict ready for `json.dumps`) for (T, S) `weights` in [0, 1], columns
    in `shape_names` order, frame k at k / fps."""
    names = list(shape_names)
    if not names or any(not isinstance(n, str) or not n for n in names):
        raise ValueError(f"{where}: shape names must be non-empty strings, got {names!r}")
    if len(set(names)) != len(names):
        twice = sorted({n for n in names if names.count(n) > 1})
        raise ValueError(f"{where}: shape names used twice: {', '.join(twice)}")
    fps = _check_fps(fps, where)
    w = np.asarray(weights)
    if w.ndim != 2 or w.shape[1] != len(names) or w.shape[0] == 0:
        raise ValueError(f"{where}: weights must be (frames > 0, {len(names)}), got {w.shape}")
    w = w.astype(np.float64)
    if not np.isfinite(w).all():
        raise ValueError(f"{where}: weights hold NaN or infinite values")
    if w.min() < 0 or w.max() > 1:
        raise ValueError(f"{where}: weights must lie in [0, 1], got {w.min()} .. {w.max()}")
    step = 1000.0 / fps
    columns = np.round(w, DECIMALS).T.tolist()
    return {
        "name": str(name),
        "fps": fps,
        "frames": int(w.shape[0]),
        "delay": 0,
        "dt": [0] + [step] * (w.shape[0] - 1),
        "vs": dict(zip(names, columns)),
    }


def write_web_json(path: str | os.PathLike, shape_names, weights, fps: float, *, name: str) -> Path:
    """Write the TalkingHead animation template (see the module doc) to `path`, atomically; returns `path`."""
    path = Path(path)
    template = web_json(shape_names, weights, fps, name=name, where=str(path))
    return atomic_write_text(path, json.dumps(template, ensure_ascii=False, separators=(",", ":")) + "\n")


def _number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def read_web_json(path: str | os.PathLike) -> tuple[tuple[str, ...], np.ndarray, float]:
    """(shape names in file order, (T, S) float32 weights, fps) from a template `write_web_json` wrote (or any
    TalkingHead template whose `vs` lists hold one number per `dt` step); ValueError naming the file otherwise."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a readable JSON file ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("vs"), dict) or not isinstance(data.get("dt"), list):
        raise ValueError(f"{path}: not a TalkingHead animation template (an object with a \"dt\" list and a "
                         "\"vs\" object)")
    dt = data["dt"]
    if not all(_number(x) and x >= 0 for x in dt):
        raise ValueError(f"{path}: \"dt\" must hold durations >= 0 in milliseconds")
    n_frames = len(dt)
    if "frames" in data and data["frames"] != n_frames:
        raise ValueError(f"{path}: \"frames\" says {data['frames']!r} but \"dt\" has {n_frames} steps")
    if "fps" in data:
        fps = _check_fps(data["fps"], str(path))
    elif n_frames >= 2 and dt[1] > 0:
        fps = 1000.0 / dt[1]
    else:
        raise ValueError(f"{path}: no \"fps\" and too few \"dt\" steps to tell the frame rate")
    names = tuple(data["vs"])
    if not names:
        raise ValueError(f"{path}: \"vs\" names no shape")
    weights = np.empty((n_frames, len(names)), np.float32)
    for j, shape in enumerate(names):
        values = data["vs"][shape]
        if not isinstance(values, list) or len(values) != n_frames:
            got = len(values) if isinstance(values, list) else type(values).__name__
            raise ValueError(f"{path}: \"vs\".{shape} must hold {n_frames} values (one per \"dt\" step), got {got}")
        if not all(_number(x) for x in values):
            bad = next(x for x in values if not _number(x))
            raise ValueError(f"{path}: \"vs\".{shape} holds {bad!r}, not a finite number")
        weights[:, j] = values
    return names, weights, fps
