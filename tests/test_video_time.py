"""Video time from presentation time stamps (tracking/video.frame_times): the real variable-frame-rate clip
`../shared/data/talking_heads/1.mp4`, constant-rate GRID and talking_heads/4.mp4, synthetic videos with known time
stamps. Tests on ../shared/data fail (not skip) when it is missing."""

from fractions import Fraction

import av
import numpy as np
import pytest
from factories import SHARED_DATA

from visemeflow.tracking.video import (
    VideoError,
    frame_times,
    grid_rate,
    iter_timed_frames,
    packet_frame_times,
    probe_video,
    read_timed_frames,
    read_video_frames,
    write_video,
)

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


def zeroed_video(path):
    """A video whose container, stream and frame index are intact but whose frame data are all zero bytes."""
    write_video(path, [np.full((48, 64, 3), 20 * k, np.uint8) for k in range(10)], 25)
    data = bytearray(path.read_bytes())
    at = data.index(b"mdat")
    size = int.from_bytes(data[at - 4:at], "big")
    data[at + 4:at - 4 + size] = bytes(size - 8)
    path.write_bytes(bytes(data))
    return path


def test_no_decodable_frames_is_an_error_naming_the_file(tmp_path):
    path = zeroed_video(tmp_path / "zeroed.mp4")
    with pytest.raises(VideoError, match=r"zeroed\.mp4: video decoding failed"):
        frame_times(path)
    bad = tmp_path / "junk.mp4"
    bad.write_bytes(b"\x00" * 4096)
    for fn in (frame_times, probe_video):
        with pytest.raises(VideoError, match=r"junk\.mp4: not a readable video"):
            fn(bad)


def test_mpeg4_encoder_writes_readable_video(tmp_path):
    frames = [np.full((48, 64, 3), 20 * k, np.uint8) for k in range(6)]
    path = write_video(tmp_path / "m4.mp4", frames, 25, video_codec="mpeg4")
    assert probe_video(path).video_codec == "mpeg4"
    got = read_video_frames(path)
    assert got.shape == (6, 48, 64, 3) and np.abs(got.astype(int) - np.stack(frames)).mean() < 3


def test_probe_reports_the_frame_grid():
    assert VFR_CLIP.is_file() and GRID_CLIP.is_file() and CFR_CLIP.is_file(), "missing test data"
    vfr = probe_video(VFR_CLIP)
    assert vfr.grid_fps == 30.0 and vfr.nominal_fps == 30.0 and vfr.variable_rate
    assert vfr.first_frame_s == pytest.approx(0.033, abs=1e-3)
    assert vfr.last_frame_s == pytest.approx(93691 / 15360, abs=1e-9)
    assert vfr.grid_frames == 184            # 0 .. 6.1 s at 30 fps: the 135 frames and 49 the clip lacks
    assert np.array_equal(np.round(frame_times(VFR_CLIP) * 30).astype(int) == 0, np.zeros(135, bool))
    for clip, fps, n in ((GRID_CLIP, 25.0, 75), (CFR_CLIP, 30.0, 199)):
        info = probe_video(clip)
        assert (info.fps, info.grid_fps, info.n_frames, info.grid_frames) == (fps, fps, n, n)
        assert not info.variable_rate and info.first_frame_s == 0.0


def test_grid_rate_picks_the_lowest_stream_rate_holding_every_frame():
    on_30 = np.array([0, 1, 3, 4, 6, 7, 9], float) / 30 + 0.033
    assert grid_rate(on_30, [1350 / 61, 30.0]) == 30.0
    assert grid_rate(np.arange(10) / 25, [50.0, 25.0]) == 25.0
    jitter = np.cumsum(np.r_[0, np.random.default_rng(0).uniform(0.030, 0.037, 40)])
    assert 27 < grid_rate(jitter, [30.0]) < 33            # no stream rate holds it: 1 / the median interval
    assert grid_rate(np.array([0.5])) is None


def test_read_timed_frames_is_one_pass_of_frames_and_times():
    assert VFR_CLIP.is_file(), f"missing test data {VFR_CLIP}"
    frames, times = read_timed_frames(VFR_CLIP)
    assert frames.shape == (135, 700, 700, 3) and frames.dtype == np.uint8
    assert np.array_equal(times, frame_times(VFR_CLIP))
    assert np.array_equal(frames[[0, 77, 134]], read_video_frames(VFR_CLIP)[[0, 77, 134]])


@pytest.mark.parametrize("clip", [VFR_CLIP, CFR_CLIP, GRID_CLIP], ids=["vfr", "cfr", "grid"])
def test_iter_timed_frames_is_frames_and_frame_times_in_one_pass(clip):
    assert clip.is_file(), f"missing test data {clip}"
    pairs = list(iter_timed_frames(clip))
    times = np.array([t for _, t in pairs])
    assert np.array_equal(times, frame_times(clip))
    frames = read_video_frames(clip)
    assert len(pairs) == len(frames)
    assert all(np.array_equal(f, frames[i]) for i, (f, _) in enumerate(pairs))


@pytest.mark.parametrize("clip", [VFR_CLIP, GRID_CLIP], ids=["vfr", "grid"])
def test_frame_times_are_the_time_stamps_minus_the_audio_start_to_the_bit(clip):
    """The one-pass decoder keeps the rule bit for bit: pts x time_base minus the audio stream's start."""
    with av.open(str(clip)) as container:
        audio = container.streams.audio[0]
        start = float(audio.start_time * audio.time_base)
        stamps = [float(f.pts * f.time_base) for f in container.decode(container.streams.video[0])]
    assert np.array_equal(frame_times(clip), np.array(stamps) - start)


def test_iter_timed_frames_on_a_file_without_frames_is_an_error_naming_it(tmp_path):
    path = zeroed_video(tmp_path / "zeroed.mp4")
    with pytest.raises(VideoError, match=r"zeroed\.mp4: video decoding failed"):
        list(iter_timed_frames(path))


def test_packet_frame_times_are_the_decoded_times_to_the_bit(tmp_path):
    """Read from the packets without decoding where the container vouches for them: the variable-rate and the
    constant-rate clips and our own writer's MP4 with audio; exactly frame_times."""
    assert VFR_CLIP.is_file() and CFR_CLIP.is_file(), "missing test data under ../shared/data"
    frames = [np.full((48, 64, 3), 10 * k, np.uint8) for k in range(12)]
    ours = write_video(tmp_path / "cfr.mp4", frames, 25, audio=np.zeros(16000, np.float32), audio_rate=16000)
    for clip in (VFR_CLIP, CFR_CLIP, ours):
        quick = packet_frame_times(clip)
        assert quick is not None and np.array_equal(quick, frame_times(clip)), clip


def test_packet_frame_times_are_none_where_the_container_stores_no_frame_count(tmp_path):
    """GRID's MPEG-1 program stream and a Matroska file store no frame count: their times must be decoded."""
    assert GRID_CLIP.is_file(), f"missing test data {GRID_CLIP}"
    assert packet_frame_times(GRID_CLIP) is None
    assert packet_frame_times(_write_timed(tmp_path / "vfr.mkv", [2, 3, 5, 6, 7, 10])) is None
