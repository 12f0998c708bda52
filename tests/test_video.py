"""visemeflow.tracking.video: probing, decoding and encoding video with PyAV, on the real GRID clips and on
synthetic videos written here. Tests on ../shared/data fail (not skip) when the data is missing."""

from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from factories import SHARED_DATA, two_frames_apart
from visemeflow.tracking.video import (
    VideoError,
    choose_audio_codec,
    choose_video_codec,
    iter_video_frames,
    probe_video,
    read_video_audio,
    read_video_frames,
    write_video,
)

GRID = SHARED_DATA / "grid_s1"
CLIPS = ("bbaf2n", "bgin3a", "bwbg8n", "lbwy6n", "lrik4p", "pbav2n", "pgwe6n", "pwbk1s", "sbwo1s", "srbu6n")


def grid_video(clip: str) -> Path:
    path = GRID / "video" / f"{clip}.mpg"
    assert path.is_file(), f"shared test data missing: {path}"
    return path


@pytest.mark.parametrize("clip", CLIPS)
def test_grid_clip_probes_and_decodes(clip):
    path = grid_video(clip)
    info = probe_video(path)
    assert (info.width, info.height) == (360, 288)
    assert info.fps == 25.0
    # MPEG-1 program streams store no frame count (PyAV reports 0): probe counts by decoding.
    assert info.n_frames == 75
    assert info.duration_s == pytest.approx(3.0)
    assert info.container_duration_s == pytest.approx(2.98, abs=0.01)
    assert info.video_codec == "mpeg1video"
    assert info.has_audio and info.audio_rate == 44100 and info.audio_channels == 2
    assert info.audio_codec == "mp2"

    frames = read_video_frames(path)
    assert frames.shape == (75, 288, 360, 3) and frames.dtype == np.uint8
    # GRID's background is a saturated blue: the top-left corner of every frame is blue, not red.
    corner = frames[:, 2:20, 2:20].reshape(-1, 3).mean(axis=0)
    assert corner[2] > 200 and corner[0] < 150
    assert sum(1 for _ in iter_video_frames(path)) == 75

    audio, rate = read_video_audio(path)
    assert rate == 44100 and audio.dtype == np.float32 and audio.ndim == 1
    assert 2.95 <= audio.size / rate <= 3.01
    assert np.abs(audio).max() <= 1.0
    assert np.sqrt(np.mean(audio**2)) > 0.01   # speech, not silence
    stereo, _ = read_video_audio(path, mono=False)
    assert stereo.shape == (audio.size, 2)
    # The two channels are near copies of each other.
    assert np.abs(stereo[:, 0] - stereo[:, 1]).max() < 0.05
    np.testing.assert_allclose(stereo.mean(axis=1), audio, atol=1e-6)


def test_read_video_frames_window_matches_full_decode():
    path = grid_video("bbaf2n")
    full = read_video_frames(path)
    np.testing.assert_array_equal(read_video_frames(path, start=10, count=5), full[10:15])
    np.testing.assert_array_equal(read_video_frames(path, start=70), full[70:])
    assert read_video_frames(path, start=80).shape == (0, 288, 360, 3)
    assert read_video_frames(path, start=3, count=0).shape == (0, 288, 360, 3)
    with pytest.raises(ValueError):
        read_video_frames(path, start=-1)


def test_truncated_mpeg_counts_the_frames_it_really_has(tmp_path):
    data = grid_video("bgin3a").read_bytes()
    cut = tmp_path / "half.mpg"
    cut.write_bytes(data[: len(data) // 2])
    info = probe_video(cut)
    frames = read_video_frames(cut)
    assert 0 < info.n_frames < 75
    assert info.n_frames == frames.shape[0]


def _synthetic_frames(n: int, height: int = 48, width: int = 64) -> np.ndarray:
    """Smooth colour gradients with a bright square moving right one pixel per frame."""
    yy, xx = np.mgrid[0:height, 0:width]
    frames = np.empty((n, height, width, 3), dtype=np.uint8)
    for i in range(n):
        frames[i, ..., 0] = (xx * 255 // (width - 1)).astype(np.uint8)
        frames[i, ..., 1] = (yy * 255 // (height - 1)).astype(np.uint8)
        frames[i, ..., 2] = 96
        frames[i, 10:22, 5 + i:17 + i] = (250, 250, 30)
    return frames


def _tone(seconds: float, rate: int, freq: float = 440.0, channels: int = 2) -> np.ndarray:
    t = np.arange(int(round(seconds * rate))) / rate
    mono = (0.4 * np.sin(2 * np.pi * freq * t)).astype(np.float32)
    return np.repeat(mono[:, None], channels, axis=1) if channels > 1 else mono


def _dominant_hz(x: np.ndarray, rate: int) -> float:
    spec = np.abs(np.fft.rfft(x * np.hanning(x.size)))
    return float(np.fft.rfftfreq(x.size, 1 / rate)[np.argmax(spec)])


def test_encoder_choice_prefers_h264_then_mpeg4():
    import av

    codec = choose_video_codec("mp4")
    expected = "libx264" if "libx264" in av.codecs_available else (
        "libopenh264" if "libopenh264" in av.codecs_available else "mpeg4")
    assert codec == expected
    assert choose_video_codec("avi") in ("mjpeg", "ffv1")
    assert choose_audio_codec("mp4") == "aac"
    assert choose_audio_codec("avi") == "pcm_s16le"


def test_mp4_round_trip_with_audio(tmp_path):
    frames = _synthetic_frames(40)
    audio = _tone(1.6, 16000)
    out = write_video(tmp_path / "clip.mp4", frames, fps=25, audio=audio, audio_rate=16000)
    assert out == tmp_path / "clip.mp4" and out.is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]   # no temporary file left

    info = probe_video(out)
    assert (info.width, info.height, info.n_frames) == (64, 48, 40)
    assert info.fps == pytest.approx(25.0)
    assert info.duration_s == pytest.approx(1.6)
    assert info.has_audio and info.audio_rate == 16000 and info.audio_channels == 2
    assert info.video_codec in ("h264", "mpeg4") and info.audio_codec == "aac"

    back = read_video_frames(out)
    assert back.shape == frames.shape
    assert np.abs(back.astype(int) - frames).mean() < 4.0
    # The moving square is where it was written, frame by frame.
    for i in (0, 20, 39):
        assert back[i, 12:20, 7 + i:15 + i].mean(axis=(0, 1))[2] < 80   # yellow: low blue

    sound, rate = read_video_audio(out)
    assert rate == 16000
    assert abs(sound.size / rate - 1.6) < 0.1   # AAC pads to whole 1024-sample frames
    assert _dominant_hz(sound, rate) == pytest.approx(440.0, abs=2.0)
    assert np.sqrt(np.mean(sound[1000:20000] ** 2)) == pytest.approx(0.4 / np.sqrt(2), rel=0.1)


def test_avi_round_trip_keeps_pcm_audio_exactly(tmp_path):
    frames = _synthetic_frames(12, 32, 40)
    audio = _tone(0.5, 22050, freq=300.0, channels=1)
    out = write_video(tmp_path / "clip.avi", frames, fps=24, audio=audio, audio_rate=22050)
    info = probe_video(out)
    assert (info.width, info.height, info.n_frames, info.fps) == (40, 32, 12, 24.0)
    assert info.audio_codec == "pcm_s16le" and info.audio_channels == 1
    back = read_video_frames(out)
    assert np.abs(back.astype(int) - frames).mean() < 6.0
    sound, rate = read_video_audio(out)
    assert rate == 22050 and sound.size == audio.size
    np.testing.assert_allclose(sound, audio, atol=1.0 / 32768 + 1e-6)


def test_ffv1_is_lossless_and_odd_sizes_work(tmp_path):
    rng = np.random.default_rng(3)
    frames = rng.integers(0, 256, size=(5, 31, 45, 3), dtype=np.uint8)
    out = write_video(tmp_path / "noise.mkv", iter(frames), fps=12.5, video_codec="ffv1")
    np.testing.assert_array_equal(read_video_frames(out), frames)
    assert probe_video(out).fps == 12.5
    # Odd frame sizes with the default mp4 encoder too.
    odd = write_video(tmp_path / "odd.mp4", frames, fps=10)
    info = probe_video(odd)
    assert (info.width, info.height, info.n_frames) == (45, 31, 5)


def test_ntsc_frame_rate(tmp_path):
    out = write_video(tmp_path / "ntsc.mp4", _synthetic_frames(6), fps=30000 / 1001)
    info = probe_video(out)
    assert info.fps == pytest.approx(float(Fraction(30000, 1001)), abs=1e-3)
    assert info.n_frames == 6


@pytest.mark.parametrize("suffix", [".mp4", ".mpg", ".avi"])
def test_corrupt_video_raises_video_error_naming_the_file(tmp_path, suffix):
    rng = np.random.default_rng(7)
    bad = tmp_path / f"garbage{suffix}"
    bad.write_bytes(rng.bytes(20000))
    for read in (probe_video, read_video_frames, read_video_audio, lambda p: list(iter_video_frames(p))):
        with pytest.raises(VideoError, match=f"garbage{suffix}"):
            read(bad)


def test_missing_file_and_missing_audio(tmp_path):
    with pytest.raises(VideoError, match="nothere.mp4"):
        probe_video(tmp_path / "nothere.mp4")
    silent = write_video(tmp_path / "silent.mp4", _synthetic_frames(3), fps=25)
    assert not probe_video(silent).has_audio
    with pytest.raises(VideoError, match="silent.mp4.*no audio"):
        read_video_audio(silent)


def test_write_video_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="at least one frame"):
        write_video(tmp_path / "a.mp4", [], fps=25)
    frames = list(_synthetic_frames(2))
    with pytest.raises(ValueError, match="size"):
        write_video(tmp_path / "b.mp4", frames + [np.zeros((10, 10, 3), np.uint8)], fps=25)
    with pytest.raises(ValueError, match="uint8"):
        write_video(tmp_path / "c.mp4", [np.zeros((8, 8, 3), np.float32)], fps=25)
    with pytest.raises(VideoError, match="d.gif"):
        write_video(tmp_path / "d.gif", frames, fps=25)
    with pytest.raises(ValueError, match="audio_rate"):
        write_video(tmp_path / "e.mp4", frames, fps=25, audio=np.zeros(100, np.float32))
    assert not (tmp_path / "b.mp4").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


# ---------------------------------------------------------------------------------------------------------------
# bounds on hostile or damaged files: refused before anything is sized by them, naming the file


def test_a_clip_stamped_to_span_days_is_refused_before_anything_is_sized_by_it(tmp_path):
    """34 KB whose second frame is shown 10**6 s after the first gave 25 million grid frames (149 GiB of curves)."""
    import pickle

    from visemeflow.tracking.facemesh import FaceMeshError, detect_video
    from visemeflow.tracking.video import MAX_MEDIA_S, VideoTooLong, iter_timed_frames

    honest = probe_video(two_frames_apart(tmp_path / "honest.mkv", 10.0))
    assert honest.last_frame_s == pytest.approx(10.0) and honest.grid_frames == 251
    days = two_frames_apart(tmp_path / "days.mkv", 1e6)
    assert days.stat().st_size < 50_000 and 1e6 > MAX_MEDIA_S
    with pytest.raises(VideoTooLong, match=r"days\.mkv: the container's header gives 1e\+06 s, more than the 24 h a "
                                           r"clip may span: split the recording") as info:
        probe_video(days)
    assert info.value.error_type == "VideoTooLong" and isinstance(info.value, VideoError)
    assert str(pickle.loads(pickle.dumps(info.value))) == str(info.value)
    frames = iter_timed_frames(days)        # no header read here: the frame's own time stamp is checked
    assert next(frames)[1] == 0.0
    with pytest.raises(VideoTooLong, match=r"days\.mkv: frame 1 is shown at 1e\+06 s"):
        next(frames)
    with pytest.raises(FaceMeshError, match=r"days\.mkv: frame 1 is shown at 1e\+06 s") as info:
        detect_video(days)
    assert info.value.error_type == "VideoTooLong"


def test_frames_over_the_pixel_bound_are_refused_before_they_are_converted(tmp_path, monkeypatch):
    """An 8192 x 8192 H.264 clip of 198 KB decoded to 192 MiB a frame; the bound is lowered here to 48 x 48 so that a
    64 x 64 clip shows it."""
    from visemeflow.tracking import video
    from visemeflow.tracking.video import VideoTooLarge, iter_timed_frames

    clip = two_frames_apart(tmp_path / "wide.mkv", 0.04)
    assert read_video_frames(clip).shape == (2, 64, 64, 3)
    monkeypatch.setattr(video, "MAX_FRAME_PIXELS", 48 * 48)
    for read in (probe_video, read_video_frames, lambda p: list(iter_video_frames(p)),
                 lambda p: list(iter_timed_frames(p))):
        with pytest.raises(VideoTooLarge, match=r"wide\.mkv: frames of 64x64 pixels, more than the 2,304 a frame may "
                                                r"have") as info:
            read(clip)
        assert info.value.error_type == "VideoTooLarge"
    assert read_video_audio(clip)[0].shape == (16000,)     # the sound track is still read
    with pytest.raises(VideoTooLarge):                    # per decoded frame too: a header may not say the size
        list(video._decode_video(_FakeContainer(), None, clip))


class _FakeContainer:
    """Decodes one frame of 64 x 64 whatever the header said."""

    @staticmethod
    def decode(_stream):
        import av

        yield av.VideoFrame(64, 64, "rgb24")


def _stereo_ts(path: Path, seconds: int, rate: int = 16000) -> Path:
    """AAC in MPEG-TS, stereo, samples beyond full scale (-1.3..1.3)."""
    import av

    rng = np.random.default_rng(0)
    with av.open(str(path), "w", format="mpegts") as c:
        stream = c.add_stream("aac", rate=rate, layout="stereo")
        for k in range(seconds):
            frame = av.AudioFrame.from_ndarray(rng.uniform(-1.3, 1.3, (2, rate)).astype(np.float32), format="fltp",
                                               layout="stereo")
            frame.sample_rate, frame.pts, frame.time_base = rate, k * rate, Fraction(1, rate)
            for packet in stream.encode(frame):
                c.mux(packet)
        for packet in stream.encode(None):
            c.mux(packet)
    return path


def test_an_audio_track_decoded_whole_stops_at_its_bound_whatever_its_header_says(tmp_path, monkeypatch):
    from visemeflow.ingest import CorpusEntry, IngestError
    from visemeflow.ingest.audio import AudioError, read_audio
    from visemeflow.ingest.utterance import read_audio_info
    from visemeflow.tracking import video
    from visemeflow.tracking.video import AudioTrackTooLong

    part = _stereo_ts(tmp_path / "part.ts", 3)
    both, rate = read_video_audio(part, mono=False)
    mono, _ = read_video_audio(part)
    assert both.shape[1] == 2 and np.abs(both).max() == 1.0      # clipped to full scale
    np.testing.assert_array_equal(mono, both.mean(axis=1, dtype=np.float32))   # clipped, then the channels' mean
    with pytest.raises(AudioTrackTooLong, match=r"part\.ts: its header gives 3\.07 s of audio, more than the 2 s a "
                                                r"track is decoded for: split the recording, or convert it to WAV"):
        read_video_audio(part, max_seconds=2.0)
    # three files joined: the header still says 3 s (the first one's time stamps), the track holds 9
    joined = tmp_path / "joined.ts"
    joined.write_bytes(part.read_bytes() * 3)
    assert len(read_video_audio(joined)[0]) / rate > 9.0
    with pytest.raises(AudioTrackTooLong, match=r"joined\.ts: more than 5 s of audio decoded \(\d+ samples at 16000 "
                                                r"Hz\)") as info:
        read_video_audio(joined, max_seconds=5.0)
    assert info.value.error_type == "AudioTooLong"
    # read_audio (predict, speak) and ingest's length of a format soundfile cannot read say AudioTooLong
    monkeypatch.setattr(video, "MAX_DECODED_AUDIO_S", 5.0)
    aac = tmp_path / "joined.aac"
    aac.write_bytes(joined.read_bytes())                  # not a video suffix: soundfile first, then PyAV
    for path in (joined, aac):
        with pytest.raises(AudioError, match=r"more than 5 s of audio decoded") as info:
            read_audio(path)
        assert info.value.error_type == "AudioTooLong"
    with pytest.raises(IngestError) as info:
        read_audio_info(CorpusEntry("s/joined", str(aac), ""))
    assert info.value.error_type == "AudioTooLong" and info.value.utterance_id == "s/joined"
    assert read_audio_info(CorpusEntry("s/part", str(part.rename(tmp_path / "part.aac")), ""))[1] == \
        pytest.approx(3.0, abs=0.1)
