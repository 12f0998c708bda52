"""MediaPipe FaceMesh landmarks of real clips (tracking/facemesh.py) against MediaPipe's reference files.

Data: ../shared/data/grid_s1 (GRID s1 .mpg with reference landmarks/*.mediapipe478.csv) and
../shared/data/talking_heads (1.mp4 variable frame rate, 4.mp4 30 fps, with reference *.mediapipe478.csv). These
tests fail, never skip, when the data is missing.
"""

import os
import re
import sys
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import pytest
from factories import SHARED_DATA

from visemeflow.tracking.facemesh import (
    CSV_COLUMNS,
    LIP_IDS,
    FaceMeshConfig,
    FaceMeshError,
    _landmark_xyz,
    choose_face,
    detect_clip,
    detect_frames,
    detect_video,
    mediapipe478_table,
    read_mediapipe478,
    write_mediapipe478_csv,
)
from visemeflow.tracking.landmarks import MEDIAPIPE_TO_68, read_landmarks, read_mediapipe478_csv
from visemeflow.tracking.video import read_video_frames, write_video

DATA = SHARED_DATA
GRID = DATA / "grid_s1"
HEADS = DATA / "talking_heads"
MOUTH_MEDIAN_PX = 1.5   # the bound on agreement with the reference files (same model)


def data(path: Path) -> Path:
    assert path.is_file(), f"test data {path} is missing (../shared/data must hold grid_s1 and talking_heads)"
    return path


def grid_video(clip: str) -> Path:
    return data(GRID / "video" / f"{clip}.mpg")


def grid_reference(clip: str) -> Path:
    return data(GRID / "landmarks" / f"{clip}.mediapipe478.csv")


def mouth_errors(points: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Pixel distance per (frame, lip vertex)."""
    return np.linalg.norm(points[:, list(LIP_IDS)] - reference[:, list(LIP_IDS)], axis=-1)


# ---- agreement with MediaPipe's reference files -------------------------------------------------------------------
@pytest.mark.parametrize("clip", ["bbaf2n", "lrik4p"])
def test_grid_clip_agrees_with_the_reference_and_writes_its_layout(clip, tmp_path):
    out = tmp_path / f"{clip}.mediapipe478.csv"
    track = detect_clip(grid_video(clip), out)
    ref = read_mediapipe478(grid_reference(clip))
    assert track.n_frames == ref.n_frames == 75 and track.detected.all() and not track.multi_face
    assert (track.width, track.height) == (360, 288)
    err = mouth_errors(track.points, ref.points)
    assert np.median(err) < MOUTH_MEDIAN_PX
    # GRID frames are on a 25 fps grid starting with the audio: PTS times equal the reference's frame / fps
    np.testing.assert_allclose(track.times, ref.times, atol=5e-7)

    ours = out.read_text().splitlines()
    theirs = grid_reference(clip).read_text().splitlines()
    assert ours[0] == theirs[0] == ",".join(CSV_COLUMNS)
    assert len(ours) == len(theirs)
    cells = ours[1].split(",")
    assert re.fullmatch(r"0,0\.000000,1", ",".join(cells[:3]))
    assert all(re.fullmatch(r"-?\d+\.\d{4}", c) for c in cells[3:3 + 956])
    assert all(re.fullmatch(r"-?\d+\.\d{6}", c) for c in cells[3 + 956:])
    # our reader reads the file back: the 68 points the tracker uses are the detected ones, to the written decimals
    back = read_mediapipe478_csv(out)
    np.testing.assert_allclose(back.points, track.points[:, list(MEDIAPIPE_TO_68)], atol=6e-5)
    assert back.valid.all()


def test_vfr_clip_keeps_presentation_times_and_agrees_with_the_reference(tmp_path):
    video = data(HEADS / "1.mp4")
    out = tmp_path / "1.mediapipe478.csv"
    track = detect_clip(video, out)
    ref = read_mediapipe478(data(HEADS / "1.mediapipe478.csv"))
    assert track.n_frames == ref.n_frames == 135 and track.detected.all()
    assert np.median(mouth_errors(track.points, ref.points)) < MOUTH_MEDIAN_PX

    # Times are PTS (time base 1/15360) on the audio's clock: the first frame 507 ticks (33 ms) after the audio,
    # then on the 30 fps grid (512 ticks) with gaps, not frame / 22.13 fps as the reference's time_s column.
    ticks = track.times * 15360 - 507
    assert track.times[0] == pytest.approx(float(Fraction(507, 15360)), abs=1e-9)
    np.testing.assert_allclose(ticks / 512, np.round(ticks / 512), atol=1e-6)
    steps = np.diff(np.round(ticks / 512)).astype(int)
    # grid slots 0..182 after the first frame hold 135 frames: 48 missing, each gap one frame long
    assert round(ticks[-1] / 512) == 182 and set(steps) == {1, 2} and (steps == 2).sum() == 183 - 135
    assert abs(track.times[-1] - 93691 / 15360) < 1e-9
    assert np.abs(ref.times - np.arange(135) * 61 / 1350).max() < 1e-6   # what the reference file holds instead
    written = np.loadtxt(out, delimiter=",", skiprows=1, usecols=1)
    np.testing.assert_allclose(written, track.times, atol=5e-7)


def test_detect_video_decodes_once_and_equals_detection_on_the_decoded_frames(monkeypatch):
    """One decoding pass gives the frames and their times; the track is that of `detect_frames` on
    `read_timed_frames`, with the frames' grid rate."""
    import visemeflow.tracking.video as video

    video_path = grid_video("bbaf2n")
    frames, times = video.read_timed_frames(video_path)
    expected = detect_frames(frames, times, name=str(video_path))
    passes = []
    one_pass = video.iter_timed_frames
    monkeypatch.setattr(video, "iter_timed_frames", lambda p: passes.append(p) or one_pass(p))
    monkeypatch.setattr(video, "frame_times", lambda p: pytest.fail("a second decoding pass for the times"))
    track = detect_video(video_path)
    assert len(passes) == 1
    assert np.array_equal(track.points, expected.points, equal_nan=True)
    assert np.array_equal(track.z, expected.z, equal_nan=True)
    assert np.array_equal(track.times, times) and np.array_equal(track.detected, expected.detected)
    assert track.fps == video.grid_rate(times) == 25.0
    assert (track.width, track.height) == (360, 288)


def test_30fps_clip_agrees_with_the_reference_on_its_first_two_seconds():
    frames = read_video_frames(data(HEADS / "4.mp4"), 0, 60)
    track = detect_frames(frames, fps=30, name="4.mp4[:60]")
    ref = read_mediapipe478(data(HEADS / "4.mediapipe478.csv"))
    assert (track.width, track.height) == (700, 700) and track.detected.all()
    err = mouth_errors(track.points, ref.points[:60])
    assert np.median(err) < MOUTH_MEDIAN_PX
    everything = np.linalg.norm(track.points - ref.points[:60], axis=-1)
    assert np.median(everything) < MOUTH_MEDIAN_PX


# ---- clips without a usable face ----------------------------------------------------------------------------------
def test_a_video_of_noise_is_an_error_naming_the_clip(tmp_path):
    noise = np.random.default_rng(0).integers(0, 256, (12, 96, 128, 3), dtype=np.uint8)
    video = write_video(tmp_path / "noise.mp4", noise, 25)
    out = tmp_path / "noise.csv"
    with pytest.raises(FaceMeshError, match=r"noise\.mp4: no face found on any of its 12 frames") as caught:
        detect_clip(video, out)
    assert caught.value.error_type == "NoFace" and caught.value.detected_share == 0.0
    assert not out.exists()


def test_a_file_that_is_no_video_is_an_error_naming_it(tmp_path):
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"\x00not a video" * 100)
    with pytest.raises(FaceMeshError, match=r"junk\.mp4") as caught:
        detect_video(junk)
    assert caught.value.error_type == "UnreadableVideo"


def face_then_blank(n_face: int, n: int) -> np.ndarray:
    frames = read_video_frames(grid_video("bbaf2n"), 0, n).copy()
    frames[n_face:] = 90   # a flat grey frame: the face has left
    return frames


def test_a_face_on_a_minority_of_frames_is_an_error_with_the_share():
    with pytest.raises(FaceMeshError, match=r"clip: a face was found on only 10 of its 25 frames \(40\.0%\); at "
                                            r"least 50% needed") as caught:
        detect_frames(face_then_blank(10, 25), fps=25, name="clip")
    assert caught.value.error_type == "FaceMostlyLost" and caught.value.detected_share == pytest.approx(0.4)


def test_frames_without_the_face_are_undetected_nan_rows_never_zeros(tmp_path):
    frames = face_then_blank(18, 25)
    track = detect_frames(frames, fps=25, name="clip", config=FaceMeshConfig(min_detected_share=0.3))
    assert track.detected.tolist() == [True] * 18 + [False] * 7
    assert np.isnan(track.points[18:]).all() and np.isfinite(track.points[:18]).all()
    ref = read_mediapipe478(grid_reference("bbaf2n"))
    assert np.median(mouth_errors(track.points[:18], ref.points[:18])) < MOUTH_MEDIAN_PX

    out = write_mediapipe478_csv(track, tmp_path / "clip.mediapipe478.csv")
    row = out.read_text().splitlines()[19].split(",")
    assert row[:3] == ["18", "0.720000", "0"] and set(row[3:]) == {""} and len(row) == len(CSV_COLUMNS)
    for lm in (read_landmarks(out), track.to_landmark_track()):
        assert lm.valid[:18].all() and not lm.valid[18:].any() and np.isnan(lm.points[18:]).all()

    # the store's Parquet form holds the same columns; the generic reader maps it to 68 points as well
    import pyarrow.parquet as pq

    pq.write_table(mediapipe478_table(track), tmp_path / "clip.parquet")
    again = read_mediapipe478(tmp_path / "clip.parquet")
    assert again.detected.tolist() == track.detected.tolist()
    np.testing.assert_allclose(again.points, track.points, atol=1e-4)
    lm = read_landmarks(tmp_path / "clip.parquet")
    assert lm.source == "mediapipe478" and not lm.valid[18:].any() and lm.valid[:18].all()


def test_a_detector_exception_is_an_error_naming_the_clip():
    rgba = np.zeros((3, 64, 64, 4), np.uint8)
    with pytest.raises(FaceMeshError, match=r"rgba-clip: MediaPipe FaceMesh failed on frame 0") as caught:
        detect_frames(rgba, fps=25, name="rgba-clip")
    assert caught.value.error_type == "DetectorError"


def test_mediapipe_start_up_lines_are_held_back_and_every_other_stderr_line_is_kept(capfd):
    from visemeflow.tracking import facemesh

    capfd.readouterr()
    track = detect_frames(read_video_frames(grid_video("bbaf2n"), 0, 5), fps=25, name="bbaf2n")
    assert track.detected.all()
    err = capfd.readouterr().err
    assert not re.search(r"inference_feedback_manager|landmark_projection_calculator|XNNPACK", err), err
    with facemesh._quiet_graph_start():
        os.write(2, b"W0000 00:00:1 9 inference_feedback_manager.cc:114] Feedback manager...\n")
        os.write(2, b"E0000 a real problem\n")
        print("a Python warning", file=sys.stderr)
    assert sorted(capfd.readouterr().err.splitlines()) == ["E0000 a real problem", "a Python warning"]


# ---- several faces ------------------------------------------------------------------------------------------------
def two_faces(main_left: bool, n: int = 20) -> tuple[np.ndarray, int]:
    """Frames with GRID bbaf2n at full size and lrik4p at 0.6 scale beside it; the main face's x offset."""
    main = read_video_frames(grid_video("bbaf2n"), 0, n)
    other = read_video_frames(grid_video("lrik4p"), 0, n)
    out = np.full((n, 288, 586, 3), 40, np.uint8)
    offset = 0 if main_left else 226
    for k in range(n):
        small = cv2.resize(other[k], (216, 172), interpolation=cv2.INTER_AREA)
        out[k, :, offset:offset + 360] = main[k]
        x = 370 if main_left else 0
        out[k, 40:212, x:x + 216] = small
    return out, offset


@pytest.mark.parametrize("main_left", [True, False])
def test_of_two_faces_the_largest_most_central_one_is_followed(main_left, tmp_path):
    frames, offset = two_faces(main_left)
    video = write_video(tmp_path / "two.mp4", frames, 25)
    track = detect_video(video)
    assert track.multi_face and track.faces == 2 and track.detected.all()
    ref = read_mediapipe478(grid_reference("bbaf2n"))
    expected = ref.points[:20] + np.array([offset, 0.0])
    assert np.median(mouth_errors(track.points, expected)) < MOUTH_MEDIAN_PX
    # always the same person: every frame's face lies on the main face's side
    xs = track.points[:, :, 0]
    assert ((xs > offset) & (xs < offset + 360)).all()


def test_without_probes_the_multi_face_run_makes_the_same_choice():
    frames, offset = two_faces(True, n=10)
    probed = detect_frames(frames, fps=25)
    always = detect_frames(frames, fps=25, config=FaceMeshConfig(probe_every=0))
    assert probed.multi_face and always.multi_face
    np.testing.assert_allclose(always.points, probed.points, atol=1e-6)


def test_a_single_face_clip_runs_one_face_and_matches_the_multi_face_run():
    frames = read_video_frames(grid_video("bbaf2n"), 0, 10)
    single = detect_frames(frames, fps=25)
    multi = detect_frames(frames, fps=25, config=FaceMeshConfig(probe_every=0))
    assert not single.multi_face and multi.multi_face and multi.faces == 1
    np.testing.assert_allclose(multi.points, single.points, atol=1e-6)


def box_face(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    """A fake FaceMesh face: 478 points spread over a box (only its bounding box matters to choose_face)."""
    t = np.linspace(0, 1, 478)
    return np.stack([x0 + (x1 - x0) * t, y0 + (y1 - y0) * t[::-1], np.zeros(478)], axis=1)


def test_choose_face_links_faces_over_frames_whatever_their_order():
    big = [box_face(150, 100, 250, 220), box_face(152, 101, 252, 221), box_face(155, 102, 255, 222)]
    small = [box_face(10, 10, 60, 70), box_face(11, 10, 61, 70), box_face(12, 11, 62, 71)]
    frames = [[small[0], big[0]], [big[1], small[1]], [small[2]], [small[2], big[2]]]
    assert choose_face(frames, 400, 300) == [1, 0, None, 1]
    # a larger face far off centre loses to a smaller one in the middle
    corner = [box_face(0, 0, 150, 150)] * 3
    middle = [box_face(160, 110, 260, 210)] * 3
    assert choose_face([[corner[k], middle[k]] for k in range(3)], 400, 300) == [1, 1, 1]
    assert choose_face([[], []], 400, 300) == [None, None]


def test_without_refinement_the_iris_cells_are_empty_and_the_file_still_reads(tmp_path):
    frames = read_video_frames(grid_video("bbaf2n"), 0, 5)
    track = detect_frames(frames, fps=25, config=FaceMeshConfig(refine_landmarks=False))
    assert track.detected.all() and np.isfinite(track.points[:, :468]).all() and np.isnan(track.points[:, 468:]).all()
    out = write_mediapipe478_csv(track, tmp_path / "plain.csv")
    header, row = out.read_text().splitlines()[:2]
    cells = dict(zip(header.split(","), row.split(",")))
    assert cells["x_467"] and cells["x_468"] == cells["y_477"] == cells["z_470"] == ""
    lm = read_landmarks(out)
    assert lm.valid.all()


def test_landmarks_read_from_the_message_bytes_equal_the_loop_over_the_message_and_odd_messages_fall_back():
    from mediapipe.framework.formats import landmark_pb2

    rng = np.random.default_rng(3)
    values = rng.uniform(-1.0, 2.0, (478, 3)).astype(np.float32)
    values[5] = (1e-30, -3.4e38, 7.0)                    # tiny, huge: any float32 survives
    face = landmark_pb2.NormalizedLandmarkList()
    for x, y, z in values:
        face.landmark.add(x=x, y=y, z=z)
    assert len(face.SerializeToString()) == 17 * 478     # the fast path's layout
    fast = _landmark_xyz(face)
    assert fast.dtype == np.float64 and fast.shape == (478, 3)
    np.testing.assert_array_equal(fast, values.astype(np.float64))
    loop = np.array([(p.x, p.y, p.z) for p in face.landmark], dtype=np.float64)
    np.testing.assert_array_equal(fast, loop)

    face.landmark[7].x = 0.0                             # proto3 leaves a 0.0 out: 16 bytes for that landmark
    face.landmark[9].visibility = 0.5                    # an extra field
    odd = _landmark_xyz(face)
    expected = values.astype(np.float64)
    expected[7, 0] = 0.0
    np.testing.assert_array_equal(odd, expected)
    assert _landmark_xyz(landmark_pb2.NormalizedLandmarkList()).shape == (0, 3)
