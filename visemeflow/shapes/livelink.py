"""Live Link Face CSV: the take file Epic's iOS Live Link Face app records, which Unreal / MetaHuman import.

Layout, as the app writes it (checked against takes recorded by the app and published with open importers):

    Timecode,BlendShapeCount,EyeBlinkLeft,...,TongueOut,HeadYaw,HeadPitch,HeadRoll,LeftEyeYaw,...,RightEyeRoll
    12:27:47:47.169,61,0.0000000000,...

- 63 columns: `Timecode`, `BlendShapeCount` (always 61), then the 52 ARKit blendshapes capitalised
  (`EyeBlinkLeft`), in the app's order, which is Apple's ARKit order except that it writes JawRight before
  JawLeft and MouthRight before MouthLeft, then the 9 rotations HeadYaw, HeadPitch, HeadRoll, LeftEyeYaw,
  LeftEyePitch, LeftEyeRoll, RightEyeYaw, RightEyePitch, RightEyeRoll (`LIVELINK_COLUMNS`: those 61 names).
- `Timecode` is `HH:MM:SS:FF.fff`: hours, minutes, seconds, the frame within the second, and after the point the
  sub-frame in thousandths of a frame (the app's takes show `...:47.169`, `...:49.169`, `...:51.168`: frames at
  the timecode rate with a slowly drifting sub-frame, not milliseconds). We count frames at the given fps, so
  frame k (time `start_seconds + k / fps`) is `FF` = its frame within the second and `.000` when it falls on the
  frame grid (always, for a whole-number fps and a start on a frame); `parse_timecode` turns it back into seconds.
- Values: the app prints 10 decimals; we print 6 (`DECIMALS`), so a weight reads back within 5e-7 of the input
  (float32 itself resolves 6e-8 near 1), one line per frame, `\\n` line ends. Rotations are written as 0.

`read_livelink_csv` finds every column by its name (exact, else ignoring case), so a file whose columns come in
another order, or that spells them `eyeBlinkLeft`, reads the same; a missing column, a short row or a value that
is not a number is a ValueError naming the file (and the line).

Pure: numpy, the ARKit names from `conventions`, and `atomic` for the write.
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
from pathlib import Path

import numpy as np

from visemeflow.shapes.conventions import ARKIT_52
from visemeflow.atomic import atomic_write_text

__all__ = [
    "BLENDSHAPE_COUNT",
    "DECIMALS",
    "LIVELINK_BLENDSHAPES",
    "LIVELINK_COLUMNS",
    "LIVELINK_ROTATIONS",
    "arkit_from_livelink",
    "format_timecode",
    "parse_timecode",
    "read_livelink_csv",
    "write_livelink_csv",
]

def _app_order() -> tuple[str, ...]:
    """ARKit's names capitalised, in the app's column order: Apple's order with JawRight before JawLeft and
    MouthRight before MouthLeft (the iOS app writes them so; the streaming enum some tools copy does not)."""
    names = [name[0].upper() + name[1:] for name in ARKIT_52]
    for left, right in (("JawLeft", "JawRight"), ("MouthLeft", "MouthRight")):
        i, k = names.index(left), names.index(right)
        names[i], names[k] = names[k], names[i]
    return tuple(names)


LIVELINK_BLENDSHAPES: tuple[str, ...] = _app_order()
"""The 52 ARKit blendshapes as the Live Link Face app names and orders its CSV columns."""

LIVELINK_ROTATIONS: tuple[str, ...] = (
    "HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll",
    "RightEyeYaw", "RightEyePitch", "RightEyeRoll",
)
LIVELINK_COLUMNS: tuple[str, ...] = LIVELINK_BLENDSHAPES + LIVELINK_ROTATIONS
"""The 61 value columns of a Live Link Face CSV, in file order (after `Timecode` and `BlendShapeCount`)."""
BLENDSHAPE_COUNT = len(LIVELINK_COLUMNS)
DECIMALS = 6
TIMECODE = "Timecode"
COUNT = "BlendShapeCount"

_CAPITALISED = {name[0].upper() + name[1:]: name for name in ARKIT_52}
assert set(_CAPITALISED) == set(LIVELINK_BLENDSHAPES) and BLENDSHAPE_COUNT == 61
# Column j of LIVELINK_BLENDSHAPES holds ARKIT_52[_FROM_ARKIT[j]]
_FROM_ARKIT = np.array([ARKIT_52.index(_CAPITALISED[name]) for name in LIVELINK_BLENDSHAPES])
_TIMECODE = re.compile(r"^(\d+):(\d{2}):(\d{2}):(\d+)(?:\.(\d+))?$")


def _check_fps(fps) -> float:
    if isinstance(fps, bool) or not isinstance(fps, (int, float, np.integer, np.floating)) or \
            not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps!r}")
    return float(fps)


def format_timecode(seconds: float, fps: float) -> str:
    """`HH:MM:SS:FF.fff` for a time in seconds (from midnight, or from the take's start), frames counted at `fps`,
    `.fff` the sub-frame in thousandths of a frame."""
    fps = _check_fps(fps)
    if not (math.isfinite(seconds) and seconds >= 0):
        raise ValueError(f"a timecode needs a finite time >= 0 seconds, got {seconds!r}")
    whole = math.floor(seconds + 1e-9)
    thousandths = round((seconds - whole) * fps * 1000)  # position within the second, in 1/1000 frames
    frame, sub = divmod(max(thousandths, 0), 1000)
    if frame >= math.ceil(fps):  # rounding reached the next second
        whole, frame, sub = whole + 1, 0, 0
    hours, rest = divmod(whole, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours:02d}:{minutes:02d}:{secs:02d}:{frame:02d}.{sub:03d}"


def parse_timecode(text: str, fps: float) -> float:
    """Seconds for a `HH:MM:SS:FF[.fff]` timecode whose frames count at `fps` (the inverse of `format_timecode`)."""
    fps = _check_fps(fps)
    match = _TIMECODE.match(text.strip())
    if not match:
        raise ValueError(f"{text!r} is not a HH:MM:SS:FF.fff timecode")
    hours, minutes, secs, frame = (int(match[i]) for i in range(1, 5))
    sub = int(match[5]) / 10 ** len(match[5]) if match[5] else 0.0
    return hours * 3600 + minutes * 60 + secs + (frame + sub) / fps


def write_livelink_csv(path: str | os.PathLike, arkit_weights, fps: float, *, start_seconds: float = 0.0) -> Path:
    """Write a Live Link Face CSV: `arkit_weights` (T, 52) in [0, 1], columns in `ARKIT_52` order, frame k at
    `start_seconds + k / fps` (its timecode); rotations 0. Atomic; returns `path`."""
    path = Path(path)
    fps = _check_fps(fps)
    w = np.asarray(arkit_weights)
    if w.ndim != 2 or w.shape[1] != len(ARKIT_52):
        raise ValueError(f"{path}: ARKit weights must be (frames, {len(ARKIT_52)}), got {w.shape}")
    w = w.astype(np.float64)
    if not np.isfinite(w).all():
        raise ValueError(f"{path}: ARKit weights hold NaN or infinite values")
    if w.size and (w.min() < 0 or w.max() > 1):
        raise ValueError(f"{path}: ARKit weights must lie in [0, 1], got {w.min()} .. {w.max()}")
    if not (math.isfinite(start_seconds) and start_seconds >= 0):
        raise ValueError(f"{path}: start_seconds must be a finite time >= 0, got {start_seconds!r}")

    values = np.zeros((len(w), BLENDSHAPE_COUNT))
    values[:, : len(LIVELINK_BLENDSHAPES)] = w[:, _FROM_ARKIT]
    out = io.StringIO()
    out.write(",".join((TIMECODE, COUNT) + LIVELINK_COLUMNS) + "\n")
    row_format = ",".join([f"%.{DECIMALS}f"] * BLENDSHAPE_COUNT)
    for k, row in enumerate(values):
        timecode = format_timecode(start_seconds + k / fps, fps)
        out.write(f"{timecode},{BLENDSHAPE_COUNT},{row_format % tuple(row)}\n")
    return atomic_write_text(path, out.getvalue())


def _column_index(header: list[str], path: Path) -> dict[str, int]:
    exact: dict[str, int] = {}
    folded: dict[str, int] = {}
    for i, name in enumerate(header):
        if name in exact:
            raise ValueError(f"{path}: the column {name!r} appears twice (columns {exact[name] + 1} and {i + 1})")
        exact[name] = i
        folded.setdefault(name.lower(), i)
    found = {}
    missing = []
    for name in (TIMECODE,) + LIVELINK_COLUMNS:
        i = exact.get(name, folded.get(name.lower()))
        if i is None:
            missing.append(name)
        else:
            found[name] = i
    if missing:
        raise ValueError(f"{path}: not a Live Link Face CSV, missing {len(missing)} column(s): {', '.join(missing)}")
    return found


def read_livelink_csv(path: str | os.PathLike) -> tuple[tuple[str, ...], np.ndarray, list[str]]:
    """Read a Live Link Face CSV: (`LIVELINK_COLUMNS`, (T, 61) float32 values in that order, the T timecodes as
    written). Columns are found by name, whatever their order; ValueError naming the file for a missing column,
    a row of the wrong length or a value that is not a finite number."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read the Live Link Face CSV ({exc})") from None
    rows = csv.reader(io.StringIO(text, newline=""))
    header = next(rows, None)
    if header is None:
        raise ValueError(f"{path}: empty file, expected a Live Link Face CSV header")
    header = [name.strip() for name in header]
    columns = _column_index(header, path)
    value_columns = [columns[name] for name in LIVELINK_COLUMNS]
    timecodes: list[str] = []
    values: list[list[float]] = []
    for line, row in enumerate(rows, start=2):
        if not row or all(not cell.strip() for cell in row):
            continue
        if len(row) != len(header):
            raise ValueError(f"{path}, line {line}: {len(row)} fields, the header has {len(header)}")
        try:
            numbers = [float(row[i]) for i in value_columns]
        except ValueError:
            bad = next(i for i in value_columns if not is_number(row[i]))
            raise ValueError(f"{path}, line {line}: column {header[bad]!r} holds {row[bad]!r}, not a number") from None
        if not all(math.isfinite(x) for x in numbers):
            bad = next(i for i, x in zip(value_columns, numbers) if not math.isfinite(x))
            raise ValueError(f"{path}, line {line}: column {header[bad]!r} holds {row[bad]!r}, not a finite number")
        timecode = row[columns[TIMECODE]].strip()
        if not _TIMECODE.match(timecode):
            raise ValueError(f"{path}, line {line}: {timecode!r} is not a HH:MM:SS:FF.fff timecode")
        timecodes.append(timecode)
        values.append(numbers)
    weights = np.array(values, dtype=np.float32).reshape(len(values), BLENDSHAPE_COUNT)
    return LIVELINK_COLUMNS, weights, timecodes


def is_number(text: str) -> bool:
    """Whether a CSV cell reads as a float (what every per-frame CSV reader checks its cells with)."""
    try:
        float(text)
    except ValueError:
        return False
    return True


def arkit_from_livelink(values) -> np.ndarray:
    """The (T, 52) ARKit weights in `ARKIT_52` order from (T, 61) values in `LIVELINK_COLUMNS` order."""
    values = np.asarray(values)
    if values.ndim != 2 or values.shape[1] != BLENDSHAPE_COUNT:
        raise ValueError(f"Live Link values must be (frames, {BLENDSHAPE_COUNT}), got {values.shape}")
    out = np.empty((len(values), len(ARKIT_52)), dtype=values.dtype)
    out[:, _FROM_ARKIT] = values[:, : len(LIVELINK_BLENDSHAPES)]
    return out
