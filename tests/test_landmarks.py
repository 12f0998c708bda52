"""visemeflow.tracking.landmarks: landmark readers and writer, the MediaPipe -> 68 map checked against the real
GRID videos, mouth measures, and the Facemark LBF wiring. Tests on ../shared/data fail (not skip) when it is
missing."""

from functools import lru_cache
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from factories import SHARED_DATA
from visemeflow.tracking.landmarks import (
    GROUPS,
    MEDIAPIPE_TO_68,
    N_POINTS,
    LandmarkError,
    LandmarkTrack,
    detect_faces,
    detect_landmarks_lbf,
    load_face_cascade,
    mouth_keypoint_ids,
    mouth_opening,
    read_generic68,
    read_landmarks,
    read_mediapipe478_csv,
    read_openface_csv,
    write_landmarks,
)
from visemeflow.tracking.video import probe_video, read_video_frames

GRID = SHARED_DATA / "grid_s1"
CLIPS = ("bbaf2n", "bgin3a", "bwbg8n", "lbwy6n", "lrik4p", "pbav2n", "pgwe6n", "pwbk1s", "sbwo1s", "srbu6n")


def _need(path: Path) -> Path:
    assert path.is_file(), f"shared test data missing: {path}"
    return path


@lru_cache(maxsize=None)
def grid_track(clip: str) -> LandmarkTrack:
    return read_landmarks(_need(GRID / "landmarks" / f"{clip}.mediapipe478.csv"))


@lru_cache(maxsize=None)
def grid_frames(clip: str) -> np.ndarray:
    return read_video_frames(_need(GRID / "video" / f"{clip}.mpg"))


def grid_words(clip: str) -> list[tuple[float, float, str]]:
    """GRID .align lines as (start_frame, end_frame, word): times are in 1/25000 s, frames are 1/25 s."""
    rows = []
    for line in _need(GRID / "align" / f"{clip}.align").read_text().split("\n"):
        if line.strip():
            start, end, word = line.split()
            rows.append((int(start) / 1000.0, int(end) / 1000.0, word))
    return rows


# ------------------------------------------------------------------------------------------------ GRID (MediaPipe)


@pytest.mark.parametrize("clip", CLIPS)
def test_grid_landmarks_match_the_video_and_the_68_point_layout(clip):
    track = grid_track(clip)
    info = probe_video(_need(GRID / "video" / f"{clip}.mpg"))
    assert track.source == "mediapipe478"
    assert track.points.shape == (info.n_frames, 68, 2) == (75, 68, 2)
    assert track.points.dtype == np.float32
    assert track.fps == info.fps == 25.0
    assert track.valid.all()          # FaceMesh found the face on every GRID frame
    p = track.points
    x, y = p[..., 0], p[..., 1]
    assert (x >= 0).all() and (x < info.width).all() and (y >= 0).all() and (y < info.height).all()

    eyes = p[:, 36:48]
    # Mouth corners below every eye point, on every frame; 48 on the image left of 54.
    assert (p[:, [48, 54], 1].min(axis=1) > eyes[..., 1].max(axis=1)).all()
    assert (p[:, 48, 0] < p[:, 54, 0]).all()
    # Eye corners left to right: 36 < 39 < 42 < 45; brows above their eyes; nose tip below the eyes and
    # between the inner eye corners; chin the lowest jaw point.
    assert (np.diff(p[:, [36, 39, 42, 45], 0], axis=1) > 0).all()
    assert (p[:, 17:22, 1].mean(axis=1) < p[:, 36:42, 1].mean(axis=1)).all()
    assert (p[:, 22:27, 1].mean(axis=1) < p[:, 42:48, 1].mean(axis=1)).all()
    assert (p[:, 30, 1] > eyes[..., 1].max(axis=1)).all()
    assert ((p[:, 30, 0] > p[:, 39, 0]) & (p[:, 30, 0] < p[:, 42, 0])).all()
    assert (p[:, 8, 1] >= p[:, 0:17, 1].max(axis=1) - 0.5).all()
    # Inner lips between the outer lips: corners 60/64 inside 48..54, the midline ordered top to bottom
    # 51 (outer upper) <= 62 (inner upper) <= 66 (inner lower) <= 57 (outer lower), with half a pixel for
    # closed lips, where FaceMesh puts 62 and 66 on top of each other.
    assert (p[:, [60, 64], 0].min(axis=1) >= p[:, 48, 0] - 0.5).all()
    assert (p[:, [60, 64], 0].max(axis=1) <= p[:, 54, 0] + 0.5).all()
    assert (p[:, 51, 1] <= p[:, 62, 1]).all()
    assert (p[:, 62, 1] <= p[:, 66, 1] + 0.5).all()
    assert (p[:, 66, 1] <= p[:, 57, 1]).all()
    # Upper inner lip points (61-63) below the upper outer lip (49-53) and lower inner (65-67) above the lower
    # outer (55-59), on average over each contour.
    assert (p[:, 61:64, 1].mean(axis=1) >= p[:, 49:54, 1].mean(axis=1)).all()
    assert (p[:, 65:68, 1].mean(axis=1) <= p[:, 55:60, 1].mean(axis=1)).all()


@pytest.mark.parametrize("clip", ["bbaf2n", "lrik4p", "srbu6n"])
def test_grid_mapped_points_land_on_the_face(clip):
    """The background is saturated blue (B >> R), skin and lips are red-dominant (R >> B): every mapped point of
    the brows, eyes, nose and lips samples a red-dominant colour, so the map is neither mirrored nor offset."""
    frames, track = grid_frames(clip), grid_track(clip)
    assert frames.shape[0] == track.n_frames
    for f in range(0, track.n_frames, 7):
        img = frames[f].astype(np.float64)
        for i in range(17, 68):
            cx, cy = np.round(track.points[f, i]).astype(int)
            r, _, b = img[cy - 1:cy + 2, cx - 1:cx + 2].reshape(-1, 3).mean(axis=0)
            assert r - b > 15, (clip, f, i, r, b)
        cx, cy = np.round(track.points[f, 30]).astype(int)   # nose tip: skin
        r, g, b = img[cy - 1:cy + 2, cx - 1:cx + 2].reshape(-1, 3).mean(axis=0)
        assert r > g > b and r - b > 50
    corner = frames[0, 2:12, 2:12].reshape(-1, 3).mean(axis=0)   # background: blue
    assert corner[2] - corner[0] > 100


@pytest.mark.parametrize("clip", CLIPS)
def test_grid_lips_close_at_bilabial_word_onsets(clip):
    """Every GRID word that starts with /b/ or /p/ (bin, blue, by, place, please) has a closure: the inner-lip
    gap is about zero within the 4 frames before to 2 frames after the aligned word start, while the mouth opens
    wide somewhere in the sentence."""
    ratio = mouth_opening(grid_track(clip)).ratio
    assert np.isfinite(ratio).all()
    words = grid_words(clip)
    bilabial = [(s, w) for s, _, w in words if w[0] in "bp"]
    assert bilabial, f"{clip}: no word with a bilabial onset"
    for start, word in bilabial:
        lo, hi = max(0, int(np.floor(start)) - 4), int(np.ceil(start)) + 2
        assert ratio[lo:hi].min() < 0.02, (clip, word, start, ratio[lo:hi])
    speech = [r for r in range(len(ratio)) if any(s <= r < e and w not in ("sil", "sp") for s, e, w in words)]
    assert ratio[speech].max() > 0.1


def test_haar_face_detector_wiring_on_grid_frames_and_a_blank_image():
    cascade = load_face_cascade()
    for clip in ("bbaf2n", "pgwe6n"):
        frame, track = grid_frames(clip)[0], grid_track(clip)
        boxes = detect_faces(frame, cascade)
        assert boxes.dtype == np.int32 and boxes.shape[1] == 4 and len(boxes) >= 1
        x, y, w, h = boxes[0]
        for i in (30, 48, 54, 36, 45):   # nose tip, mouth and eye corners inside the largest box
            px, py = track.points[0, i]
            assert x <= px <= x + w and y <= py <= y + h, (clip, i)
    blank = np.full((24, 32, 3), 128, dtype=np.uint8)
    assert detect_faces(blank).shape == (0, 4)


# ------------------------------------------------------------------------------------------------ the map


def test_mediapipe_map_is_68_distinct_face_mesh_vertices():
    assert len(MEDIAPIPE_TO_68) == N_POINTS == 68
    assert len(set(MEDIAPIPE_TO_68)) == 68
    assert all(0 <= v < 468 for v in MEDIAPIPE_TO_68)   # no iris points: 468-point files work too
    assert sum(len(r) for r in GROUPS.values()) == 68
    # MediaPipe's midline vertices sit on the 68-layout midline: chin, nose, lip centres.
    for k, v in {8: 152, 27: 168, 30: 4, 33: 2, 51: 0, 57: 17, 62: 13, 66: 14}.items():
        assert MEDIAPIPE_TO_68[k] == v
    # Mouth corners are MediaPipe 61 / 291, inner corners 78 / 308.
    assert (MEDIAPIPE_TO_68[48], MEDIAPIPE_TO_68[54], MEDIAPIPE_TO_68[60], MEDIAPIPE_TO_68[64]) == (61, 291, 78, 308)


def test_mouth_keypoint_ids():
    ids = mouth_keypoint_ids()
    assert ids.tolist() == list(range(48, 68)) and len(ids) == 20


def _mediapipe_frame(rng: np.random.Generator, n_points: int, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    return rng.uniform(10, 200, n_points) * scale, rng.uniform(10, 200, n_points) * scale


def _write_mediapipe_csv(path: Path, n_points: int, frames: list[int], detected: list[int],
                         normalised: bool = False, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rows, truth = [], []
    for f, d in zip(frames, detected):
        xs, ys = _mediapipe_frame(rng, n_points, 1 / 400 if normalised else 1.0)
        row = {"frame": f, "time_s": f / 25, "detected": d}
        row.update({f"x_{i}": (xs[i] if d else np.nan) for i in range(n_points)})
        row.update({f"y_{i}": (ys[i] if d else np.nan) for i in range(n_points)})
        row.update({f"z_{i}": 0.0 for i in range(n_points)})
        rows.append(row)
        truth.append(np.stack([xs[list(MEDIAPIPE_TO_68)], ys[list(MEDIAPIPE_TO_68)]], axis=1))
    pd.DataFrame(rows).to_csv(path, index=False)
    return np.asarray(truth)


def test_mediapipe_csv_rows_gaps_and_normalised_coordinates(tmp_path):
    path = tmp_path / "a.mediapipe478.csv"
    truth = _write_mediapipe_csv(path, 478, frames=[0, 1, 3], detected=[1, 0, 1])
    track = read_landmarks(path)
    assert track.source == "mediapipe478" and track.n_frames == 4 and track.fps == 25.0
    assert track.valid[0].all() and not track.valid[1].any() and not track.valid[2].any() and track.valid[3].all()
    np.testing.assert_allclose(track.points[3], truth[2], rtol=1e-6)
    assert np.isnan(track.points[2]).all()
    # A 468-point file (no iris refinement) and a file in normalised coordinates.
    p468 = tmp_path / "b.csv"
    truth = _write_mediapipe_csv(p468, 468, frames=[0, 1], detected=[1, 1], normalised=True)
    scaled = read_mediapipe478_csv(p468, image_size=(400, 400))
    np.testing.assert_allclose(scaled.points, truth * 400, rtol=1e-5)


# ------------------------------------------------------------------------------------------------ OpenFace


def _openface_header() -> list[str]:
    cols = ["frame", "face_id", "timestamp", "confidence", "success"]
    cols += [f"gaze_{e}_{a}" for e in (0, 1) for a in "xyz"] + ["gaze_angle_x", "gaze_angle_y"]
    cols += [f"eye_lmk_{a}_{i}" for a in ("x", "y") for i in range(56)]
    cols += [f"pose_{a}" for a in ("Tx", "Ty", "Tz", "Rx", "Ry", "Rz")]
    cols += [f"{a}_{i}" for a in ("x", "y") for i in range(68)]
    cols += [f"{a}_{i}" for a in ("X", "Y", "Z") for i in range(68)]
    cols += ["p_scale", "p_rx", "p_ry", "p_rz", "p_tx", "p_ty"] + [f"p_{i}" for i in range(34)]
    cols += ["AU01_r", "AU12_r", "AU25_r", "AU01_c", "AU12_c", "AU25_c"]
    return cols


def _write_openface_csv(path: Path, success: list[int], face_ids: list[int] | None = None,
                        frames: list[int] | None = None, drop: tuple[str, ...] = ()) -> np.ndarray:
    """An OpenFace 2.0 FeatureExtraction CSV as OpenFace writes it: ", " separators (names with a leading space),
    frames from 1, timestamps at 25 fps. Returns the 2D landmarks written, (rows, 68, 2)."""
    header = [c for c in _openface_header() if c not in drop]
    rng = np.random.default_rng(1)
    frames = frames or list(range(1, len(success) + 1))
    face_ids = face_ids or [0] * len(success)
    lines, truth = [", ".join(header)], []
    for f, ok, fid in zip(frames, success, face_ids):
        pts = rng.uniform(50, 300, size=(68, 2)) if ok else np.zeros((68, 2))
        truth.append(pts)
        values = {"frame": f"{f}", "face_id": f"{fid}", "timestamp": f"{(f - 1) * 0.04:.3f}",
                  "confidence": "0.98" if ok else "0.00", "success": f"{ok}"}
        values.update({f"x_{i}": f"{pts[i, 0]:.1f}" for i in range(68)})
        values.update({f"y_{i}": f"{pts[i, 1]:.1f}" for i in range(68)})
        lines.append(", ".join(values.get(c, "0.5") for c in header))
    path.write_text("\n".join(lines) + "\n")
    return np.round(np.asarray(truth), 1)


def test_openface_csv_with_leading_space_header(tmp_path):
    path = tmp_path / "utt.csv"
    truth = _write_openface_csv(path, success=[1, 1, 0, 1])
    assert path.read_text().startswith("frame, face_id, timestamp, confidence, success, gaze_0_x")
    for track in (read_landmarks(path), read_openface_csv(path)):
        assert track.source == "openface"
        assert track.n_frames == 4 and track.fps == 25.0
        assert track.valid[[0, 1, 3]].all() and not track.valid[2].any()
        np.testing.assert_allclose(track.points[[0, 1, 3]], truth[[0, 1, 3]], atol=1e-4)
        assert np.isnan(track.points[2]).all()


def test_openface_several_faces_keeps_the_most_confident_successful_one(tmp_path):
    path = tmp_path / "two.csv"
    truth = _write_openface_csv(path, success=[0, 1, 1, 0], face_ids=[0, 1, 0, 1], frames=[1, 1, 2, 2])
    track = read_openface_csv(path)
    assert track.n_frames == 2 and track.valid.all()
    np.testing.assert_allclose(track.points, truth[[1, 2]], atol=1e-4)


def test_openface_missing_columns(tmp_path):
    path = tmp_path / "nosuccess.csv"
    _write_openface_csv(path, success=[1], drop=("success",))
    with pytest.raises(LandmarkError, match="nosuccess.csv.*missing columns success"):
        read_openface_csv(path)
    path = tmp_path / "nox.csv"
    _write_openface_csv(path, success=[1], drop=("x_3", "y_60"))
    with pytest.raises(LandmarkError, match=r"nox.csv.*missing columns x_3, y_60"):
        read_landmarks(path)


# ------------------------------------------------------------------------------------------------ generic 68


def _generic_frame(points: np.ndarray, names: str = "x_") -> pd.DataFrame:
    sep = "_" if names == "x_" else ""
    data = {}
    for i in range(68):
        data[f"x{sep}{i}"] = points[:, i, 0]
    for i in range(68):
        data[f"y{sep}{i}"] = points[:, i, 1]
    return pd.DataFrame(data)


@pytest.mark.parametrize("names", ["x_", "x"])
@pytest.mark.parametrize("ext", [".csv", ".parquet"])
def test_generic68_tables(tmp_path, names, ext):
    rng = np.random.default_rng(2)
    pts = rng.uniform(0, 100, size=(5, 68, 2))
    pts[1, 7, 0] = np.nan          # one missing coordinate: that point only is invalid
    df = _generic_frame(pts, names)
    path = tmp_path / f"g{ext}"
    df.to_csv(path, index=False) if ext == ".csv" else df.to_parquet(path, index=False)
    track = read_landmarks(path)
    assert track.source == "generic68" and track.n_frames == 5 and track.fps is None
    assert not track.valid[1, 7] and track.valid.sum() == 5 * 68 - 1
    assert np.isnan(track.points[1, 7]).all()
    np.testing.assert_allclose(track.points[0], pts[0], rtol=1e-6)
    assert read_generic68(path).valid.sum() == 5 * 68 - 1
    assert read_landmarks(path, fps=30).fps == 30.0


def test_generic68_frame_and_valid_columns(tmp_path):
    pts = np.random.default_rng(4).uniform(0, 100, size=(3, 68, 2))
    df = _generic_frame(pts)
    df.insert(0, "frame", [5, 2, 3])           # unordered, with a gap: frames 0, 1, 4 are not listed
    df.insert(1, "valid", [True, False, True])
    path = tmp_path / "g.csv"
    df.to_csv(path, index=False)
    track = read_landmarks(path)
    assert track.n_frames == 6
    assert track.valid.all(axis=1).tolist() == [False, False, False, True, False, True]
    np.testing.assert_allclose(track.points[5], pts[0], rtol=1e-6)
    np.testing.assert_allclose(track.points[3], pts[2], rtol=1e-6)
    one_based = read_generic68(path, frame_base=1)
    assert one_based.n_frames == 5 and one_based.valid[4].all()


def test_generic68_missing_columns_named(tmp_path):
    df = _generic_frame(np.zeros((2, 68, 2))).drop(columns=["x_5", "y_67"])
    path = tmp_path / "short.csv"
    df.to_csv(path, index=False)
    with pytest.raises(LandmarkError) as err:
        read_landmarks(path)
    msg = str(err.value)
    assert "short.csv" in msg and "x_5" in msg and "y_67" in msg and "x_4" not in msg.split("expected")[0]
    # Nothing like a landmark table at all.
    other = tmp_path / "other.parquet"
    pd.DataFrame({"a": [1.0], "b": [2.0]}).to_parquet(other)
    with pytest.raises(LandmarkError, match=r"other.parquet.*x_0, x_1.*\(136 missing in all\)"):
        read_landmarks(other)


def test_mediapipe_missing_mapped_column_named(tmp_path):
    path = tmp_path / "mp.csv"
    _write_mediapipe_csv(path, 478, frames=[0], detected=[1])
    df = pd.read_csv(path).drop(columns=["x_61"])
    df.to_csv(path, index=False)
    with pytest.raises(LandmarkError, match=r"mp.csv.*missing columns x_61"):
        read_mediapipe478_csv(path)


def test_bad_files(tmp_path):
    with pytest.raises(LandmarkError, match="absent.csv.*not found"):
        read_landmarks(tmp_path / "absent.csv")
    empty = tmp_path / "empty.csv"
    empty.write_text(", ".join(f"x_{i}" for i in range(68)) + "\n")
    with pytest.raises(LandmarkError, match="empty.csv.*no rows"):
        read_landmarks(empty)
    text = tmp_path / "text.csv"
    df = _generic_frame(np.zeros((1, 68, 2))).astype(object)
    df.loc[0, "y_3"] = "left"
    df.to_csv(text, index=False)
    with pytest.raises(LandmarkError, match="text.csv.*non-numeric.*y_3"):
        read_landmarks(text)
    dup = tmp_path / "dup.csv"
    df = _generic_frame(np.zeros((2, 68, 2)))
    df.insert(0, "frame", [1, 1])
    df.to_csv(dup, index=False)
    with pytest.raises(LandmarkError, match="dup.csv.*repeated frame"):
        read_landmarks(dup)


def test_a_landmark_file_must_cover_the_video_frames_within_one(tmp_path):
    """5 rows for a 47-frame video is refused, naming the file and both counts; one frame short or long is the
    decoders' disagreement about a last partial frame, and is padded or cut."""
    from visemeflow.tracking.utterance import TrackingInputError, load_track

    def rows(n: int) -> Path:
        path = tmp_path / f"rows{n}.landmarks.csv"
        _generic_frame(np.random.default_rng(n).uniform(0, 100, size=(n, 68, 2))).to_csv(path, index=False)
        return path

    with pytest.raises(TrackingInputError) as err:
        load_track(str(rows(5)), 25.0, 47, "v.mp4")
    assert err.value.error_type == "LandmarkFrameMismatch" and err.value.path == str(rows(5))
    assert "5 landmark frames" in err.value.reason and "47" in err.value.reason
    with pytest.raises(TrackingInputError, match="45 landmark frames"):
        load_track(str(rows(45)), 25.0, 47, "v.mp4")
    for n in (46, 47, 48):
        track = load_track(str(rows(n)), 25.0, 47, "v.mp4")
        assert track.n_frames == 47 and track.valid[: min(n, 47)].all() and not track.valid[min(n, 47):].any()
    with pytest.raises(TrackingInputError, match="49 landmark frames"):
        load_track(str(rows(49)), 25.0, 47, "v.mp4")


# ------------------------------------------------------------------------------------------------ round trip


def test_track_invariants():
    pts = np.ones((2, 68, 2), dtype=np.float64)
    pts[0, 3, 1] = np.nan
    valid = np.ones((2, 68), dtype=bool)
    valid[1, 9] = False
    track = LandmarkTrack(points=pts, valid=valid, fps=25, source="generic68")
    assert track.points.dtype == np.float32 and track.fps == 25.0
    assert not track.valid[0, 3] and not track.valid[1, 9] and track.valid.sum() == 136 - 2
    assert np.isnan(track.points[1, 9]).all() and np.isnan(track.points[0, 3]).all()
    with pytest.raises(ValueError):
        LandmarkTrack(points=np.zeros((2, 67, 2)), valid=np.ones((2, 67), bool), fps=None, source="generic68")
    with pytest.raises(ValueError):
        LandmarkTrack(points=pts, valid=valid, fps=None, source="dlib")
    with pytest.raises(ValueError):
        LandmarkTrack(points=pts, valid=valid, fps=0.0, source="generic68")


def _assert_same_track(a: LandmarkTrack, b: LandmarkTrack) -> None:
    assert a.n_frames == b.n_frames
    np.testing.assert_array_equal(a.valid, b.valid)
    np.testing.assert_array_equal(a.points, b.points)   # NaN == NaN for assert_array_equal


@pytest.mark.parametrize("ext", [".csv", ".parquet"])
def test_write_read_round_trip_of_a_grid_track(tmp_path, ext):
    track = grid_track("pbav2n")
    out = write_landmarks(track, tmp_path / "sub" / f"t{ext}")
    back = read_landmarks(out)
    _assert_same_track(track, back)
    assert back.fps == 25.0
    assert back.source == ("mediapipe478" if ext == ".parquet" else "generic68")
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]
    with pytest.raises(LandmarkError, match="t.json"):
        write_landmarks(track, tmp_path / "t.json")


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    n=st.integers(1, 6),
    seed=st.integers(0, 2**31 - 1),
    fps=st.one_of(st.none(), st.sampled_from([24.0, 25.0, 29.97, 30.0, 50.0, 59.94, 60.0])),
    ext=st.sampled_from([".csv", ".parquet"]),
)
def test_round_trip_property(tmp_path, n, seed, fps, ext):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-50, 2000, size=(n, 68, 2)).astype(np.float32)
    valid = rng.random((n, 68)) > 0.2
    valid[rng.random(n) < 0.3] = False        # some whole frames missing
    track = LandmarkTrack(points=pts, valid=valid, fps=fps, source="lbf")
    back = read_landmarks(write_landmarks(track, tmp_path / f"p{seed}{ext}"))
    _assert_same_track(track, back)
    if ext == ".parquet":
        assert back.fps == fps                      # kept exactly in the file's metadata
    elif fps is None or n == 1:
        assert back.fps is None                     # CSV: estimated from time_s, needs two frames
    else:
        assert back.fps == pytest.approx(fps, abs=1e-3)


# ------------------------------------------------------------------------------------------------ mouth


def test_mouth_opening_is_roll_invariant_and_nan_aware():
    pts = np.zeros((1, 68, 2), dtype=np.float64)
    pts[0, :, :] = (100.0, 100.0)
    pts[0, 48], pts[0, 54] = (75.0, 100.0), (125.0, 100.0)       # width 50
    for up, lo in ((61, 67), (62, 66), (63, 65)):
        pts[0, up] = (100.0, 95.0)
        pts[0, lo] = (100.0, 105.0)                               # gap 10
    track = LandmarkTrack(points=pts, valid=np.ones((1, 68), bool), fps=25, source="generic68")
    m = mouth_opening(track)
    assert m.gap[0] == pytest.approx(10.0) and m.width[0] == pytest.approx(50.0) and m.ratio[0] == pytest.approx(0.2)
    angle = np.deg2rad(25)
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    rolled = (pts - 100.0) @ rot.T + 300.0
    m2 = mouth_opening(LandmarkTrack(points=rolled, valid=np.ones((1, 68), bool), fps=25, source="generic68"))
    assert m2.ratio[0] == pytest.approx(0.2, abs=1e-5)
    valid = np.ones((1, 68), bool)
    valid[0, 66] = False
    m3 = mouth_opening(LandmarkTrack(points=pts, valid=valid, fps=25, source="generic68"))
    assert np.isnan(m3.gap[0]) and np.isnan(m3.ratio[0]) and m3.width[0] == pytest.approx(50.0)


# ------------------------------------------------------------------------------------------------ Facemark LBF


def test_lbf_missing_model_names_the_file(tmp_path):
    frames = np.zeros((2, 32, 32, 3), dtype=np.uint8)
    with pytest.raises(LandmarkError, match="lbfmodel.yaml.*not found"):
        detect_landmarks_lbf(frames, tmp_path / "lbfmodel.yaml")


def test_lbf_unreadable_model_names_the_file(tmp_path):
    bad = tmp_path / "broken_lbf.yaml"
    bad.write_bytes(b"\x00\x01 not yaml at all")
    with pytest.raises(LandmarkError, match="broken_lbf.yaml"):
        detect_landmarks_lbf(np.zeros((1, 32, 32, 3), np.uint8), bad)


def test_lbf_wiring_with_a_model_file_that_holds_no_model(tmp_path):
    """A readable YAML without a trained model: frames without a face give invalid rows (the model is never
    asked); a frame with a face reaches Facemark.fit, whose failure becomes a LandmarkError naming the model."""
    empty_model = tmp_path / "empty_lbf.yaml"
    empty_model.write_text("%YAML:1.0\n---\nnote: 1\n")
    blank = np.full((3, 40, 48, 3), 90, dtype=np.uint8)
    track = detect_landmarks_lbf(blank, empty_model, fps=25)
    assert track.source == "lbf" and track.n_frames == 3 and track.fps == 25.0 and not track.valid.any()
    with pytest.raises(LandmarkError, match="empty_lbf.yaml"):
        detect_landmarks_lbf(grid_frames("bbaf2n")[:1], empty_model)
    with pytest.raises(LandmarkError, match="nocascade.xml"):
        detect_landmarks_lbf(blank, empty_model, cascade=tmp_path / "nocascade.xml")


def test_a_mediapipe_parquet_file_reads_only_the_68_points_and_equals_the_whole_table(tmp_path):
    """The track stage reads the landmarks stage's Parquet files through a column projection (141 of 1,437
    columns); the track is the one the whole table gives, the CSV's too, and a file missing a used column still
    names it."""
    from visemeflow.tracking.landmarks import _from_mediapipe, _load_table, _mediapipe_columns

    source = _need(GRID / "landmarks" / "bbaf2n.mediapipe478.csv")
    table = pd.read_csv(source)
    path = tmp_path / "bbaf2n.mediapipe478.parquet"
    table.to_parquet(path, index=False)
    used = _mediapipe_columns(list(table.columns))
    assert len(table.columns) == 1437 and len(used) == 3 + 136
    assert {"frame", "time_s", "detected"} <= set(used) and not any(c.startswith("z_") for c in used)
    projected = read_landmarks(path)
    whole = _from_mediapipe(_load_table(path), path)
    from_csv = read_landmarks(source)
    for other in (whole, from_csv):
        np.testing.assert_array_equal(projected.points, other.points)
        np.testing.assert_array_equal(projected.valid, other.valid)
        assert projected.fps == other.fps and projected.source == other.source == "mediapipe478"
    # as the landmarks stage stores it: no column statistics or dictionaries, snappy; the same track back
    import pyarrow.parquet as pq

    from visemeflow.storage import Store
    from visemeflow.tracking.facemesh import mediapipe478_table, read_mediapipe478

    store = Store(tmp_path / "store")
    stored = store.write_landmarks("s1/bbaf2n", mediapipe478_table(read_mediapipe478(source)), provenance="test")
    chunk = pq.ParquetFile(stored).metadata.row_group(0).column(5)
    assert chunk.compression == "SNAPPY" and not chunk.is_stats_set and not chunk.has_dictionary_page
    back = read_landmarks(stored)
    np.testing.assert_array_equal(back.points, projected.points)
    np.testing.assert_array_equal(back.valid, projected.valid)
    broken = tmp_path / "broken.mediapipe478.parquet"
    table.drop(columns=["y_13"]).to_parquet(broken, index=False)       # y of the upper lip's middle
    with pytest.raises(LandmarkError, match=r"broken.mediapipe478.parquet.*y_13"):
        read_landmarks(broken)
