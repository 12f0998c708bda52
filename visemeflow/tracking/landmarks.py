"""2D facial landmarks in the 68-point Multi-PIE (iBUG 300-W / dlib) layout, from files or OpenCV Facemark LBF.

Every source ends up as one :class:`LandmarkTrack`: ``points`` (frames, 68, 2) float32 pixel coordinates of the
decoded video frame (origin top-left, x right, y down), ``valid`` (frames, 68) bool, NaN wherever a point is not
valid. Row ``i`` of a track is video frame ``i`` (0-based); frames a file does not list are invalid rows.

Readers (``read_landmarks`` dispatches on the columns):

- OpenFace 2.0 ``FeatureExtraction`` CSV: ``frame`` (1-based), ``timestamp``, ``confidence``, ``success``,
  ``x_0..x_67``, ``y_0..y_67`` (OpenFace writes ``", x_0"``: names are stripped). ``success == 0`` rows are invalid.
- MediaPipe FaceMesh CSV (the ``grid_s1`` format): ``frame`` (0-based), ``time_s``, ``detected``,
  ``x_0..x_477``, ``y_0..y_477`` in pixels (468-point files without iris points work too), mapped to 68 points with
  :data:`MEDIAPIPE_TO_68`. ``detected == 0`` rows are invalid.
- generic 68-point CSV or Parquet: ``x_0..x_67``, ``y_0..y_67`` (or ``x0..x67``, ``y0..y67``), optional
  ``frame`` (0-based), ``time_s``, ``valid``. This is what :func:`write_landmarks` writes.

The MediaPipe -> 68 map, why each vertex was chosen and how it was checked is in ``docs/landmarks.md``.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from visemeflow.atomic import atomic_path

N_POINTS = 68
SOURCES = ("openface", "mediapipe478", "generic68", "lbf")

# 68-point Multi-PIE index -> MediaPipe FaceMesh (canonical 468/478 topology) vertex id. "Left"/"right" below are
# image left/right for a frontal face (Multi-PIE numbers start on the image left, the subject's right side).
# Choices (details and the check against the GRID videos in docs/landmarks.md):
#   jaw 0-16: vertices of the FaceMesh face oval from 127 (face edge just below the outer eye corner) down to the
#     chin 152 and up to 356, picked so the 17 points are close to evenly spaced in arc length, mirror-symmetric.
#   brows 17-26: the upper brow contour, outer to inner (70 63 105 66 107), inner to outer (336 296 334 293 300).
#   nose 27-35: bridge 168 (between the eyes) 197 5 and the tip 4 (most forward vertex: min z); base along the
#     nostril bottoms 98 97 2 (subnasale) 326 327.
#   eyes 36-47: corners 33/133 and 362/263; lids at about 1/3 and 2/3 of the eye width: upper 160 158 / 385 387,
#     lower 153 144 / 373 380 (each pair mirror-symmetric).
#   outer lips 48-59: corners 61/291, upper 39 37 0 267 269 (37/267 the Cupid's-bow peaks, 0 the midline),
#     lower 405 314 17 84 181 (17 the midline); the same ring positions on upper and lower lip.
#   inner lips 60-67: corners 78/308, upper 81 13 311, lower 402 14 178 (quarter points of the inner contour;
#     13/14 the midline points MediaPipe's own docs use for the inner lips).
MEDIAPIPE_TO_68: tuple[int, ...] = (
    # jaw 0-16
    127, 234, 93, 132, 58, 172, 150, 176, 152, 400, 379, 397, 288, 361, 323, 454, 356,
    # right brow 17-21 (image left), left brow 22-26
    70, 63, 105, 66, 107, 336, 296, 334, 293, 300,
    # nose bridge 27-30, nose base 31-35
    168, 197, 5, 4, 98, 97, 2, 326, 327,
    # right eye 36-41 (image left), left eye 42-47
    33, 160, 158, 133, 153, 144, 362, 385, 387, 263, 373, 380,
    # outer lips 48-59
    61, 39, 37, 0, 267, 269, 291, 405, 314, 17, 84, 181,
    # inner lips 60-67
    78, 81, 13, 311, 308, 402, 14, 178,
)
assert len(MEDIAPIPE_TO_68) == N_POINTS and len(set(MEDIAPIPE_TO_68)) == N_POINTS

# Named groups of the 68-point layout (half-open index ranges).
GROUPS: dict[str, range] = {
    "jaw": range(0, 17),
    "brows": range(17, 27),
    "nose": range(27, 36),
    "eyes": range(36, 48),
    "outer_lips": range(48, 60),
    "inner_lips": range(60, 68),
}

DEFAULT_CASCADE = "haarcascade_frontalface_alt2.xml"

_PARQUET_EXT = {".parquet", ".pq"}
_CSV_EXT = {".csv", ".txt"}
_META_FPS = b"visemeflow.fps"
_META_SOURCE = b"visemeflow.source"
# Refuse frame numbering so sparse that the dense track would be mostly empty rows (a corrupt frame column).
_MAX_SPARSITY = 16


class LandmarkError(ValueError):
    """A landmark file or model that cannot be used; the message names the file and what was expected."""


@dataclass(frozen=True)
class LandmarkTrack:
    """68 landmarks per video frame. Invariant (enforced on construction): ``points`` is float32 (frames, 68, 2),
    ``valid`` bool (frames, 68), and a point is valid exactly when it is flagged valid and both coordinates are
    finite; invalid points are NaN."""

    points: np.ndarray
    valid: np.ndarray
    fps: float | None
    source: str

    def __post_init__(self) -> None:
        points = np.array(self.points, dtype=np.float32, copy=True)
        if points.ndim != 3 or points.shape[1:] != (N_POINTS, 2):
            raise ValueError(f"points must have shape (frames, {N_POINTS}, 2), got {points.shape}")
        valid = np.array(self.valid, dtype=bool, copy=True)
        if valid.shape != points.shape[:2]:
            raise ValueError(f"valid must have shape {points.shape[:2]}, got {valid.shape}")
        valid &= np.isfinite(points).all(axis=2)
        points[~valid] = np.nan
        if self.source not in SOURCES:
            raise ValueError(f"source must be one of {SOURCES}, got {self.source!r}")
        fps = None if self.fps is None else float(self.fps)
        if fps is not None and not (np.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be positive or None, got {self.fps!r}")
        points.setflags(write=False)
        valid.setflags(write=False)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "valid", valid)
        object.__setattr__(self, "fps", fps)

    @property
    def n_frames(self) -> int:
        return int(self.points.shape[0])

    def times(self) -> np.ndarray:
        """Frame times in seconds (frame / fps); needs fps."""
        if self.fps is None:
            raise ValueError("this landmark track has no fps")
        return np.arange(self.n_frames, dtype=np.float64) / self.fps


# ---------------------------------------------------------------------------------------------------------------
# reading


def read_landmarks(path: str | os.PathLike, fps: float | None = None) -> LandmarkTrack:
    """Read any supported landmark file; the layout is told apart by its columns.

    ``success`` column -> OpenFace; ``detected`` column or more than 68 points (``x_467``) -> MediaPipe FaceMesh;
    otherwise generic 68-point. ``fps``, when given, replaces what the file's time column says.
    """
    path = Path(path)
    df = _load_table(path, only_used=True)
    cols = set(df.columns)
    if "success" in cols:
        track = _from_openface(df, path)
    elif "detected" in cols or "x_467" in cols:
        track = _from_mediapipe(df, path)
    else:
        track = _from_generic(df, path, *_parquet_meta(path))
    return _with_fps(track, fps)


def read_openface_csv(path: str | os.PathLike) -> LandmarkTrack:
    """OpenFace 2.0 ``FeatureExtraction`` CSV (column names with or without OpenFace's leading space)."""
    path = Path(path)
    return _from_openface(_load_table(path), path)


def read_mediapipe478_csv(path: str | os.PathLike,
                          image_size: tuple[int, int] | None = None) -> LandmarkTrack:
    """MediaPipe FaceMesh CSV (``frame, time_s, detected, x_0.., y_0.., z_..``) mapped to 68 points.

    Coordinates are expected in pixels (as in ``grid_s1``). For a file holding MediaPipe's normalised [0, 1]
    coordinates pass ``image_size=(width, height)`` to scale them to pixels.
    """
    path = Path(path)
    return _from_mediapipe(_load_table(path), path, image_size=image_size)


def read_generic68(path: str | os.PathLike, frame_base: int = 0) -> LandmarkTrack:
    """CSV or Parquet with ``x_0..x_67, y_0..y_67`` (or ``x0..x67, y0..y67``) and optional ``frame``, ``time_s``,
    ``valid``. ``frame_base`` is the number of the first video frame in the ``frame`` column (0 or 1)."""
    path = Path(path)
    return _from_generic(_load_table(path), path, *_parquet_meta(path), frame_base=frame_base)


_POINT_COLUMN = re.compile(r"[xyz]_\d+")
_MEDIAPIPE_USED = frozenset(f"{axis}_{i}" for i in MEDIAPIPE_TO_68 for axis in "xy")


def _mediapipe_columns(names: list[str]) -> list[str] | None:
    """For a MediaPipe FaceMesh table (the landmarks stage's Parquet files), the columns reading it needs: every
    column but the per-point ones, and x, y of the 68 points used, 141 of its 1,437. None: any other layout."""
    if "success" in names or not ("detected" in names or "x_467" in names):
        return None
    return [n for n in names if not _POINT_COLUMN.fullmatch(n) or n in _MEDIAPIPE_USED]


def _load_table(path: Path, only_used: bool = False) -> pd.DataFrame:
    """The file as a table; `only_used`: of a MediaPipe Parquet file only the columns `read_landmarks` uses (the
    footer parsed once; reading every column took 70 ms of a 75-frame clip's tracking, these take a third)."""
    if not path.is_file():
        raise LandmarkError(f"{path}: landmark file not found")
    ext = path.suffix.lower()
    try:
        if ext in _PARQUET_EXT:
            import pyarrow.parquet as pq

            parquet = pq.ParquetFile(path)
            columns = _mediapipe_columns(parquet.schema_arrow.names) if only_used else None
            df = parquet.read(columns=columns, use_pandas_metadata=True).to_pandas()
        else:
            # OpenFace separates with ", ": skipinitialspace strips the space from names and values alike.
            df = pd.read_csv(path, skipinitialspace=True)
    except (ValueError, OSError, pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        kind = "Parquet" if ext in _PARQUET_EXT else "CSV"
        raise LandmarkError(f"{path}: not a readable {kind} landmark table ({exc})") from exc
    df.columns = [str(c).strip() for c in df.columns]
    if df.columns.duplicated().any():
        dup = sorted(set(df.columns[df.columns.duplicated()]))
        raise LandmarkError(f"{path}: duplicate columns {dup}")
    if len(df) == 0:
        raise LandmarkError(f"{path}: landmark table has no rows")
    return df


def _parquet_meta(path: Path) -> tuple[float | None, str]:
    """fps and source that :func:`write_landmarks` stores in a Parquet file's schema metadata."""
    if path.suffix.lower() not in _PARQUET_EXT:
        return None, "generic68"
    import pyarrow.parquet as pq

    meta = pq.read_schema(path).metadata or {}
    fps = None
    if _META_FPS in meta:
        try:
            fps = float(meta[_META_FPS].decode())
        except ValueError:
            fps = None
    source = meta.get(_META_SOURCE, b"generic68").decode(errors="replace")
    return fps, source if source in SOURCES else "generic68"


def _missing_message(path: Path, missing: Sequence[str], expected: str) -> LandmarkError:
    shown = ", ".join(missing[:12]) + (f", ... ({len(missing)} missing in all)" if len(missing) > 12 else "")
    return LandmarkError(f"{path}: missing columns {shown}; expected {expected}")


def _numeric(df: pd.DataFrame, cols: Sequence[str], path: Path) -> np.ndarray:
    try:
        return df[list(cols)].to_numpy(dtype=np.float64, na_value=np.nan)
    except (ValueError, TypeError) as exc:
        bad = [c for c in cols if not pd.api.types.is_numeric_dtype(df[c])]
        raise LandmarkError(f"{path}: non-numeric values in columns {bad[:6]}") from exc


def _coords(df: pd.DataFrame, path: Path, ids: Sequence[int], prefix: str, expected: str) -> np.ndarray:
    xs = [f"x{prefix}{i}" for i in ids]
    ys = [f"y{prefix}{i}" for i in ids]
    missing = [c for c in xs + ys if c not in df.columns]
    if missing:
        raise _missing_message(path, missing, expected)
    x = _numeric(df, xs, path)
    y = _numeric(df, ys, path)
    return np.stack([x, y], axis=-1)


def _flag(df: pd.DataFrame, col: str, path: Path) -> np.ndarray:
    """A 0/1 (or bool) column as bool; an empty cell counts as 0."""
    s = df[col]
    if pd.api.types.is_bool_dtype(s):
        return s.fillna(False).to_numpy(dtype=bool)
    if s.dtype == object:
        lowered = s.astype(str).str.strip().str.lower()
        mapped = lowered.map({"true": 1.0, "false": 0.0, "1": 1.0, "0": 0.0, "1.0": 1.0, "0.0": 0.0,
                              "nan": 0.0, "": 0.0})
        if mapped.isna().any():
            raise LandmarkError(f"{path}: column {col!r} must hold 0/1 or true/false values")
        return mapped.to_numpy(dtype=float) > 0.5
    vals = _numeric(df, [col], path)[:, 0]
    return np.nan_to_num(vals, nan=0.0) > 0.5


def _frame_index(df: pd.DataFrame, path: Path, base: int) -> np.ndarray | None:
    if "frame" not in df.columns:
        return None
    f = _numeric(df, ["frame"], path)[:, 0]
    if not np.isfinite(f).all() or (f != np.round(f)).any():
        raise LandmarkError(f"{path}: column 'frame' must hold whole frame numbers")
    idx = f.astype(np.int64) - base
    if (idx < 0).any():
        raise LandmarkError(f"{path}: frame numbers below the first frame ({base}) in column 'frame'")
    if len(np.unique(idx)) != len(idx):
        raise LandmarkError(f"{path}: repeated frame numbers in column 'frame'")
    if idx.max() + 1 > _MAX_SPARSITY * len(idx) + 1024:
        raise LandmarkError(f"{path}: frame numbers up to {idx.max() + base} for only {len(idx)} rows")
    return idx


def _estimate_fps(idx: np.ndarray, times: np.ndarray) -> float | None:
    """fps from per-row times: 1 / median seconds per frame, rounded to 1e-3 (files round times)."""
    order = np.argsort(idx)
    di = np.diff(idx[order]).astype(np.float64)
    dt = np.diff(times[order])
    ok = (di > 0) & np.isfinite(dt) & (dt > 0)
    if not ok.any():
        return None
    fps = 1.0 / float(np.median(dt[ok] / di[ok]))
    return round(fps, 3) if np.isfinite(fps) and fps > 0 else None


def _assemble(coords: np.ndarray, row_valid: np.ndarray, idx: np.ndarray | None,
              times: np.ndarray | None, source: str, fps: float | None = None) -> LandmarkTrack:
    rows = coords.shape[0]
    if idx is None:
        idx = np.arange(rows, dtype=np.int64)
    n = int(idx.max()) + 1
    points = np.full((n, N_POINTS, 2), np.nan, dtype=np.float32)
    valid = np.zeros((n, N_POINTS), dtype=bool)
    points[idx] = coords
    valid[idx] = row_valid[:, None] & np.isfinite(coords).all(axis=2)
    if fps is None and times is not None:
        fps = _estimate_fps(idx, times)
    return LandmarkTrack(points=points, valid=valid, fps=fps, source=source)


def _times(df: pd.DataFrame, path: Path, *names: str) -> np.ndarray | None:
    for name in names:
        if name in df.columns:
            return _numeric(df, [name], path)[:, 0]
    return None


def _from_openface(df: pd.DataFrame, path: Path) -> LandmarkTrack:
    expected = "an OpenFace 2.0 FeatureExtraction CSV with frame, success, x_0..x_67, y_0..y_67"
    need = [c for c in ("frame", "success") if c not in df.columns]
    if need:
        raise _missing_message(path, need, expected)
    if "face_id" in df.columns and df["face_id"].nunique() > 1:
        # Several faces: keep, per frame, the successful row with the highest confidence.
        key = _flag(df, "success", path) * 2.0
        if "confidence" in df.columns:
            key = key + np.nan_to_num(_numeric(df, ["confidence"], path)[:, 0])
        order = np.lexsort((-key, _numeric(df, ["frame"], path)[:, 0]))
        df = df.iloc[order]
        df = df[~df["frame"].duplicated()].reset_index(drop=True)
    coords = _coords(df, path, range(N_POINTS), "_", expected)
    frames = _numeric(df, ["frame"], path)[:, 0]
    base = 1 if np.nanmin(frames) >= 1 else 0   # OpenFace numbers frames from 1
    idx = _frame_index(df, path, base)
    return _assemble(coords, _flag(df, "success", path), idx, _times(df, path, "timestamp"), "openface")


def _from_mediapipe(df: pd.DataFrame, path: Path, image_size: tuple[int, int] | None = None) -> LandmarkTrack:
    expected = "a MediaPipe FaceMesh CSV with frame, detected, x_0..x_467, y_0..y_467 (pixels)"
    coords = _coords(df, path, MEDIAPIPE_TO_68, "_", expected)
    if image_size is not None:
        w, h = image_size
        coords = coords * np.array([w, h], dtype=np.float64)
    row_valid = _flag(df, "detected", path) if "detected" in df.columns else np.ones(len(df), dtype=bool)
    idx = _frame_index(df, path, 0)
    return _assemble(coords, row_valid, idx, _times(df, path, "time_s", "timestamp"), "mediapipe478")


_GENERIC_PREFIXES = ("_", "")


def _from_generic(df: pd.DataFrame, path: Path, meta_fps: float | None = None, source: str = "generic68",
                  frame_base: int = 0) -> LandmarkTrack:
    expected = "a 68-point landmark table with x_0..x_67, y_0..y_67 (or x0..x67, y0..y67)"
    # Pick the naming with the most columns present, so the error lists what that naming lacks.
    best = max(_GENERIC_PREFIXES, key=lambda p: sum(f"x{p}{i}" in df.columns for i in range(N_POINTS)))
    coords = _coords(df, path, range(N_POINTS), best, expected)
    row_valid = _flag(df, "valid", path) if "valid" in df.columns else np.ones(len(df), dtype=bool)
    idx = _frame_index(df, path, frame_base)
    times = _times(df, path, "time_s", "timestamp")
    return _assemble(coords, row_valid, idx, times, source, fps=meta_fps)


def _with_fps(track: LandmarkTrack, fps: float | None) -> LandmarkTrack:
    if fps is None:
        return track
    return LandmarkTrack(points=track.points, valid=track.valid, fps=fps, source=track.source)


# ---------------------------------------------------------------------------------------------------------------
# writing


def landmark_table(track: LandmarkTrack) -> pd.DataFrame:
    """The generic68 table of a track: frame, [time_s], valid (any point valid), x_0..x_67, y_0..y_67."""
    n = track.n_frames
    data: dict[str, np.ndarray] = {"frame": np.arange(n, dtype=np.int64)}
    if track.fps is not None:
        data["time_s"] = np.arange(n, dtype=np.float64) / track.fps
    data["valid"] = track.valid.any(axis=1)
    for i in range(N_POINTS):
        data[f"x_{i}"] = track.points[:, i, 0]
    for i in range(N_POINTS):
        data[f"y_{i}"] = track.points[:, i, 1]
    return pd.DataFrame(data)


def write_landmarks(track: LandmarkTrack, path: str | os.PathLike) -> Path:
    """Write ``track`` as a generic68 table (Parquet for ``.parquet``/``.pq``, else CSV for ``.csv``), atomically.

    Invalid points are written as empty cells / nulls; :func:`read_landmarks` reads the file back to an equal
    track (Parquet also keeps fps and source exactly; CSV keeps fps through ``time_s``).
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in _PARQUET_EXT | {".csv"}:
        raise LandmarkError(f"{path}: landmark files are written as .csv or .parquet, not {ext or 'no extension'}")
    df = landmark_table(track)
    with atomic_path(path) as tmp:  # a uniquely named hidden temporary file, renamed over `path` when whole
        if ext in _PARQUET_EXT:
            import pyarrow as pa
            import pyarrow.parquet as pq

            table = pa.Table.from_pandas(df, preserve_index=False)
            meta = dict(table.schema.metadata or {})
            meta[_META_SOURCE] = track.source.encode()
            if track.fps is not None:
                meta[_META_FPS] = repr(track.fps).encode()
            pq.write_table(table.replace_schema_metadata(meta), tmp)
        else:
            df.to_csv(tmp, index=False)
    return path


# ---------------------------------------------------------------------------------------------------------------
# mouth measures


def mouth_keypoint_ids() -> np.ndarray:
    """The 20 mouth points of the 68-point layout: outer lips 48-59, inner lips 60-67."""
    return np.arange(48, 68)


# Inner-lip point pairs facing each other across the mouth opening: (upper, lower).
INNER_LIP_PAIRS: tuple[tuple[int, int], ...] = ((61, 67), (62, 66), (63, 65))


@dataclass(frozen=True)
class MouthOpening:
    """Per frame: ``gap`` the inner-lip opening in pixels, ``width`` the outer mouth-corner distance 48-54 in
    pixels, ``ratio`` = gap / width (scale free; about 0 for closed lips, the MBP closures). NaN where a needed point
    is invalid."""

    gap: np.ndarray
    width: np.ndarray
    ratio: np.ndarray


def mouth_opening(track: LandmarkTrack) -> MouthOpening:
    """Inner-lip gap and mouth width per frame.

    The gap is the mean, over the pairs 61-67, 62-66, 63-65, of the lower point minus the upper point measured
    along the normal of the mouth-corner line 48->54 (so head roll does not count as opening). It is signed: a
    slightly negative value means the tracker put the lower inner lip above the upper one (pressed lips).
    """
    p = track.points.astype(np.float64)
    left, right = p[:, 48], p[:, 54]
    axis = right - left
    width = np.linalg.norm(axis, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = axis / width[:, None]
        normal = np.stack([-unit[:, 1], unit[:, 0]], axis=1)   # points image-down for a level mouth
        gaps = [np.einsum("ij,ij->i", p[:, lo] - p[:, up], normal) for up, lo in INNER_LIP_PAIRS]
        gap = np.mean(gaps, axis=0)
        ratio = gap / width
    need = [48, 54] + [i for pair in INNER_LIP_PAIRS for i in pair]
    ok = track.valid[:, need].all(axis=1) & (width > 0)
    gap = np.where(ok, gap, np.nan)
    width = np.where(track.valid[:, [48, 54]].all(axis=1), width, np.nan)
    ratio = np.where(ok, ratio, np.nan)
    return MouthOpening(gap=gap.astype(np.float32), width=width.astype(np.float32), ratio=ratio.astype(np.float32))


# ---------------------------------------------------------------------------------------------------------------
# OpenCV Facemark LBF


def load_face_cascade(cascade: str | os.PathLike | object | None = None):
    """A ``cv2.CascadeClassifier``: the given one, one loaded from a file path, or by default OpenCV's shipped
    ``haarcascade_frontalface_alt2.xml`` (from ``cv2.data.haarcascades``)."""
    import cv2

    if cascade is not None and not isinstance(cascade, (str, os.PathLike)):
        if not hasattr(cascade, "detectMultiScale"):
            raise TypeError("cascade must be a path or a cv2.CascadeClassifier")
        return cascade
    if cascade is None:
        path = Path(cv2.data.haarcascades) / DEFAULT_CASCADE
    else:
        path = Path(cascade)
    if not path.is_file():
        raise LandmarkError(f"{path}: face detector cascade file not found; expected an OpenCV Haar cascade XML")
    clf = cv2.CascadeClassifier(str(path))
    if clf.empty():
        raise LandmarkError(f"{path}: not a usable OpenCV Haar cascade XML")
    return clf


def _gray(frame: np.ndarray) -> np.ndarray:
    import cv2

    frame = np.asarray(frame)
    if frame.dtype != np.uint8:
        raise ValueError(f"frames must be uint8, got {frame.dtype}")
    if frame.ndim == 2:
        return frame
    if frame.ndim == 3 and frame.shape[2] == 3:
        return cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY)
    raise ValueError(f"a frame must be (H, W) or (H, W, 3) RGB, got shape {frame.shape}")


def detect_faces(frame: np.ndarray, cascade=None, min_size: int | None = None) -> np.ndarray:
    """Face boxes in one RGB (or gray) uint8 frame as an int32 array (n, 4) of x, y, w, h, largest first."""
    import cv2

    clf = load_face_cascade(cascade)
    gray = cv2.equalizeHist(_gray(frame))
    side = min_size if min_size is not None else max(24, min(gray.shape) // 8)
    boxes = clf.detectMultiScale(gray, scaleFactor=1.1, minNeighbors=4, minSize=(side, side))
    boxes = np.asarray(boxes, dtype=np.int32).reshape(-1, 4)
    order = np.argsort(-(boxes[:, 2].astype(np.int64) * boxes[:, 3]), kind="stable")
    return boxes[order]


def _load_lbf(model_path: Path):
    import cv2

    if not model_path.is_file():
        raise LandmarkError(
            f"{model_path}: Facemark LBF model file not found; expected OpenCV's trained 68-point LBF model "
            "(lbfmodel.yaml), which the user supplies")
    facemark = cv2.face.createFacemarkLBF()
    try:
        facemark.loadModel(str(model_path))
    except cv2.error as exc:
        raise LandmarkError(f"{model_path}: not a readable Facemark LBF model ({exc.err})") from exc
    return facemark


def detect_landmarks_lbf(frames: Iterable[np.ndarray], model_path: str | os.PathLike, cascade=None,
                         fps: float | None = None) -> LandmarkTrack:
    """68 landmarks per frame with OpenCV Facemark LBF, faces found by a Haar cascade.

    ``frames``: RGB uint8 frames (an array (frames, H, W, 3) or any iterable of (H, W, 3)). Per frame the largest
    detected face is fitted; frames without a face are invalid rows. ``model_path`` is a trained LBF model file
    (OpenCV's ``lbfmodel.yaml``); a missing or unusable file raises :class:`LandmarkError` naming it.
    """
    import cv2

    model_path = Path(model_path)
    facemark = _load_lbf(model_path)
    clf = load_face_cascade(cascade)
    rows: list[np.ndarray] = []
    for frame in frames:
        frame = np.asarray(frame)
        out = np.full((N_POINTS, 2), np.nan, dtype=np.float32)
        boxes = detect_faces(frame, clf)
        if len(boxes):
            image = frame if frame.ndim == 3 else cv2.cvtColor(frame, cv2.COLOR_GRAY2RGB)
            try:
                ok, landmarks = facemark.fit(np.ascontiguousarray(image), boxes[:1])
            except cv2.error as exc:
                raise LandmarkError(f"{model_path}: Facemark LBF model could not fit a face ({exc.err})") from exc
            if ok and len(landmarks):
                pts = np.asarray(landmarks[0], dtype=np.float32).reshape(-1, 2)
                if pts.shape[0] != N_POINTS:
                    raise LandmarkError(f"{model_path}: model gives {pts.shape[0]} points, expected {N_POINTS}")
                out = pts
        rows.append(out)
    points = np.stack(rows) if rows else np.zeros((0, N_POINTS, 2), dtype=np.float32)
    return LandmarkTrack(points=points, valid=np.isfinite(points).all(axis=2), fps=fps, source="lbf")


__all__ = [
    "DEFAULT_CASCADE", "GROUPS", "INNER_LIP_PAIRS", "MEDIAPIPE_TO_68", "N_POINTS", "SOURCES",
    "LandmarkError", "LandmarkTrack", "MouthOpening",
    "detect_faces", "detect_landmarks_lbf", "landmark_table", "load_face_cascade", "mouth_keypoint_ids",
    "mouth_opening", "read_generic68", "read_landmarks", "read_mediapipe478_csv", "read_openface_csv",
    "write_landmarks",
]


def track_from_mediapipe478(points: np.ndarray, detected: np.ndarray, fps: float | None = None) -> LandmarkTrack:
    """The 68-point track of MediaPipe FaceMesh points ((frames, 468 or 478, 2) pixels) with a per-frame detected
    flag ((frames,) bool), mapped with :data:`MEDIAPIPE_TO_68` as :func:`read_mediapipe478_csv` maps a file."""
    points = np.asarray(points, dtype=np.float32)
    detected = np.asarray(detected, dtype=bool)
    if points.ndim != 3 or points.shape[1] < 468 or points.shape[2] != 2:
        raise ValueError(f"points must have shape (frames, 468 or 478, 2), got {points.shape}")
    if detected.shape != points.shape[:1]:
        raise ValueError(f"detected must have shape {points.shape[:1]}, got {detected.shape}")
    coords = points[:, list(MEDIAPIPE_TO_68)]
    valid = detected[:, None] & np.isfinite(coords).all(axis=2)
    return LandmarkTrack(points=coords, valid=valid, fps=fps, source="mediapipe478")
