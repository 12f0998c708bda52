"""Curve exports: one utterance's viseme curves as CSV (one row per frame) or JSON (one list per viseme).

CSV: a header ``"frame","time_s","AAA",...`` (the 16 visemes in their fixed order), then one line per frame: the
frame number, its time in seconds (the shortest text that reads back as the same float64) and each weight as the
shortest text that reads back as the same float32, so a reader gets exactly the stored values.

JSON: ``{"utterance_id", "source", "variant", "fps", "visemes", "time_s", "curves": {viseme: [weights]}}`` with
weights rounded to 6 decimals (well below what a rig shows) and ``fps`` derived from the frame times (null for
fewer than two frames).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visemeflow.atomic import atomic_write_text
from visemeflow.visemes import N_VISEMES, VISEMES

FORMATS = ("csv", "json")


@dataclass(frozen=True)
class CurveTrack:
    """One utterance's curves: (T, 16) weights in the order of `visemes.VISEMES`, frame numbers and times."""

    utterance_id: str
    source: str
    variant: str
    curves: np.ndarray   # (T, 16) float32
    time_s: np.ndarray   # (T,) float64
    frame: np.ndarray    # (T,) int

    def __post_init__(self) -> None:
        curves = np.asarray(self.curves)
        if curves.ndim != 2 or curves.shape[1] != N_VISEMES:
            raise ValueError(f"{self.utterance_id}: curves must be (frames, {N_VISEMES}), got {curves.shape}")
        if len(self.time_s) != len(curves) or len(self.frame) != len(curves):
            raise ValueError(f"{self.utterance_id}: {len(curves)} frames of curves but {len(self.time_s)} times "
                             f"and {len(self.frame)} frame numbers")

    @property
    def fps(self) -> float | None:
        """Frames per second from the frame times; None for fewer than two frames."""
        t = np.asarray(self.time_s, dtype=np.float64)
        return float((len(t) - 1) / t[-1]) if len(t) > 1 and t[-1] > 0 else None


def _float32_text(value: np.float32) -> str:
    """The shortest digits that read back as the same float32, positional from 1e-6 on (as Arrow's CSV writer)."""
    if value == 0 or 1e-6 <= abs(value) < 1e21:
        return np.format_float_positional(value, unique=True, trim="-")
    return np.format_float_scientific(value, unique=True, trim="-", exp_digits=1)


def _float64_text(value: float) -> str:
    text = repr(float(value))
    return text[:-2] if text.endswith(".0") else text


def curves_csv(track: CurveTrack) -> str:
    """The CSV text of `track` (header quoted, values unquoted, "\\n" line ends)."""
    header = ",".join(f'"{name}"' for name in ("frame", "time_s", *VISEMES))
    curves = np.asarray(track.curves, dtype=np.float32)
    lines = [header]
    for k in range(len(curves)):
        values = ",".join(_float32_text(v) for v in curves[k])
        lines.append(f"{int(track.frame[k])},{_float64_text(track.time_s[k])},{values}")
    return "\n".join(lines) + "\n"


def curves_json(track: CurveTrack) -> str:
    """The JSON text of `track`; weights rounded to 6 decimals."""
    curves = np.asarray(track.curves, dtype=np.float32)
    for name, column in zip(VISEMES, curves.T):
        if not np.isfinite(column).all():
            raise ValueError(f"{track.utterance_id}: {name} has NaN or infinite weights; JSON cannot hold them")
    return json.dumps({
        "utterance_id": track.utterance_id, "source": track.source, "variant": track.variant, "fps": track.fps,
        "visemes": list(VISEMES), "time_s": [float(t) for t in np.asarray(track.time_s, dtype=np.float64)],
        "curves": {name: [round(float(x), 6) for x in column] for name, column in zip(VISEMES, curves.T)},
    })


def export_text(track: CurveTrack, fmt: str) -> str:
    """`track` as `fmt` ("csv" or "json") text."""
    if fmt == "csv":
        return curves_csv(track)
    if fmt == "json":
        return curves_json(track)
    raise ValueError(f"unknown format {fmt!r}; use {' or '.join(FORMATS)}")


def write_export(track: CurveTrack, path: str | os.PathLike, fmt: str | None = None) -> Path:
    """Write `track` to `path` atomically as `fmt` (default: the file's suffix, .csv or .json); returns the path."""
    path = Path(path)
    fmt = fmt or path.suffix.lower().lstrip(".")
    return atomic_write_text(path, export_text(track, fmt))
