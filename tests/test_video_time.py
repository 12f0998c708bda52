"""Video time from presentation time stamps (tracking/video.frame_times): the real variable-frame-rate clip
`../shared/data/talking_heads/1.mp4`, constant-rate GRID and talking_heads/4.mp4, synthetic videos with known time
stamps. Tests on ../shared/data fail (not skip) when it is missing."""

from fractions import Fraction

import av
import numpy as np
import pytest
from factories import SHARED_DATA

from visemeflow.tracking.video import VideoError, frame_times, probe_video, read_video_frames, write_video

TALKING = SHARED_DATA / "talking_heads"
VFR_CLIP = TALKING / "1.mp4"
CFR_CLIP = TALKING / "4.mp4"
GRID_CLIP = SHARED_DATA / "grid_s1" / "video" / "bbaf2n.mpg"


def _write_timed(path, pts, rate=30, size=(64, 48)):
    """A silent MPEG-4 video whose frame k has presentation time pts[k] / rate."""
    width, height = size
    with av.open(str(path), mode="w") as out:
        stream = out.add_stream("mpeg4", rate=rate)
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.codec_context.time_base = Fraction(1, rate)
        for k, p in enumerate(pts):
            img = np.full((height, width, 3), (37 * k) % 256, np.uint8)
            frame = av.VideoFrame.from_ndarray(img, format="rgb24")
            frame.pts, frame.time_base = int(p), Fraction(1, rate)
            out.mux(stream.encode(frame))
        out.mux(stream.encode(None))
    return path


def test_real_vfr_clip_times_come_from_pts():
    assert VFR_CLIP.is_file(), f"missing test data {VFR_CLIP}"
    times = frame_times(VFR_CLIP)
    info = probe_video(VFR_CLIP)
    assert times.dtype == np.float64
    assert len(times) == info.n_frames == 135
    assert np.all(np.diff(times) > 0)
    # the first frame is shown 33 ms after the audio starts (PTS 507 / 15360 s)
    assert times[0] == pytest.approx(507 / 15360, abs=1e-9)
    # every gap is a whole number of 1/30 s steps: 1 (shown frames) or 2 (a dropped frame between)
    steps = np.diff(times) * 30
    assert np.allclose(steps, np.round(steps), atol=1e-3)
    assert set(np.round(steps).astype(int)) == {1, 2}
    assert int(np.sum(np.round(steps) == 2)) == 48
    # frame/fps at the container's average rate (22.13 fps), which the reference CSV's time_s column holds, is
    # not the time the frame is shown: by the end it is 45 ms early, at the start 33 ms
    assert info.fps == pytest.approx(1350 / 61)
    assert times[-1] == pytest.approx(93691 / 15360, abs=1e-9)
    ref = np.loadtxt(TALKING / "1.mediapipe478.csv", delimiter=",", skiprows=1, usecols=(0, 1))
    assert len(ref) == len(times)
    assert np.allclose(ref[:, 1], ref[:, 0] / info.fps, atol=1e-5)
    assert np.max(np.abs(ref[:, 1] - times)) > 0.03


def test_constant_rate_videos_are_frame_over_fps():
    assert GRID_CLIP.is_file() and CFR_CLIP.is_file(), "missing test data under ../shared/data"
    grid = frame_times(GRID_CLIP)
    assert np.array_equal(grid, np.arange(75) / 25.0)      # exactly: tracking of GRID must not change
    cfr = frame_times(CFR_CLIP)
    assert len(cfr) == probe_video(CFR_CLIP).n_frames == 199
    assert np.allclose(cfr, np.arange(199) / 30.0, atol=1e-9)


def test_synthetic_gaps_and_no_audio(tmp_path):
    pts = [2, 3, 5, 6, 7, 10]
    path = _write_timed(tmp_path / "vfr.mkv", pts)
    times = frame_times(path)
    assert len(times) == len(read_video_frames(path)) == len(pts)
    # no audio: relative to the first frame (Matroska stores times in whole milliseconds)
    assert np.allclose(times, (np.array(pts) - pts[0]) / 30.0, atol=1e-3)


def test_audio_start_is_time_zero(tmp_path):
    frames = [np.full((48, 64, 3), 10 * k, np.uint8) for k in range(12)]
    path = write_video(tmp_path / "cfr.mp4", frames, 25, audio=np.zeros(16000, np.float32), audio_rate=16000)
    times = frame_times(path)
    assert len(times) == 12
    assert np.allclose(times, np.arange(12) / 25.0, atol=2e-3)


def test_no_decodable_frames_is_an_error_naming_the_file(tmp_path):
    path = _write_timed(tmp_path / "empty.mkv", [])
    with pytest.raises(VideoError, match="empty.mkv"):
        frame_times(path)
    bad = tmp_path / "junk.mp4"
    bad.write_bytes(b"\x00" * 4096)
    with pytest.raises(VideoError, match="junk.mp4"):
        frame_times(bad)
