"""Preview videos (animation/preview.py): panels per curve source, labels, phone caption, H.264 + AAC MP4.

Videos are reopened with PyAV and checked for what a viewer would see: codecs, frame count, rate, the audio's
length, the layout, and that the pixels move where the weights differ (and only there).
"""

from fractions import Fraction

import av
import cv2
import numpy as np
import pytest

from visemeflow.rig.character import character_from_rig, make_character
from visemeflow.animation.preview import PreviewFrames, TextPainter, render_preview
from visemeflow.rig import load_demo_rig

FPS = 30
SIZE = 96


def grid_character(n: int = 24):
    """A square sheet in the xy plane facing +z; "bump" raises a cone in its middle, "shift" slides its lower half."""
    xs, ys = np.meshgrid(np.linspace(-1.0, 1.0, n), np.linspace(-1.0, 1.0, n))
    neutral = np.stack([xs.ravel(), ys.ravel(), np.zeros(n * n)], axis=1)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            faces += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]  # counter-clockwise seen from +z
    r = np.hypot(neutral[:, 0], neutral[:, 1])
    deltas = np.zeros((2, n * n, 3))
    deltas[0, :, 2] = 1.2 * np.clip(0.7 - r, 0.0, None)
    deltas[1, :, 1] = -0.2 * (neutral[:, 1] < 0)
    return make_character("grid", neutral, np.array(faces), ["bump", "shift"], deltas)


def tone(seconds: float, rate: int) -> np.ndarray:
    t = np.arange(int(round(seconds * rate))) / rate
    return (0.2 * np.sin(2 * np.pi * 330.0 * t)).astype(np.float32)


def decode(path):
    """(RGB frames, video stream facts, audio stream facts) of an MP4."""
    with av.open(str(path)) as container:
        video, audio = container.streams.video[0], container.streams.audio[0]
        facts = {
            "vcodec": video.codec_context.name, "acodec": audio.codec_context.name,
            "rate": video.average_rate, "width": video.codec_context.width, "height": video.codec_context.height,
            "pix_fmt": video.codec_context.pix_fmt, "vframes": video.frames,
            "vseconds": float(video.duration * video.time_base), "aseconds": float(audio.duration * audio.time_base),
            "arate": audio.rate,
        }
        facts["aframe_size"] = audio.codec_context.frame_size
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
        container.seek(0)
        facts["audio"] = np.concatenate([f.to_ndarray().reshape(-1) for f in container.decode(audio=0)])
    return frames, facts


def diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a.astype(np.int16) - b.astype(np.int16)).mean())


PHONES = [(0.0, 0.5, "AA"), (0.5, 1.0, "M"), (1.0, 1.5, "UW")]


@pytest.fixture(scope="module")
def grid_preview(tmp_path_factory):
    ch = grid_character()
    t = 45  # 1.5 s at 30 fps
    bump = np.zeros((t, 2), np.float32)
    bump[:, 0] = 1.0
    still = np.zeros((t, 2), np.float32)
    sources = {"bump": bump, "still": still, "still too": still.copy()}
    path = tmp_path_factory.mktemp("preview") / "grid.mp4"
    report = render_preview(path, ch, sources, FPS, audio=(tone(1.5, 16000), 16000), phones=PHONES,
                            title="grid / utt-1", size=SIZE)
    layout = PreviewFrames(ch, sources, FPS, phones=PHONES, title="grid / utt-1", size=SIZE)
    return report, layout, decode(path)


def test_the_preview_is_h264_and_aac_at_the_given_rate_with_audio_as_long_as_video(grid_preview):
    report, layout, (frames, facts) = grid_preview
    assert report.path.is_file() and report.path.suffix == ".mp4"
    assert facts["vcodec"] == "h264" and facts["acodec"] == "aac" and facts["pix_fmt"] == "yuv420p"
    assert report.frames == 45 and len(frames) == 45 and facts["vframes"] == 45
    assert facts["rate"] == FPS and report.fps == FPS
    assert abs(facts["vseconds"] - 1.5) < 1e-6
    assert abs(facts["aseconds"] - facts["vseconds"]) <= 1 / FPS
    # decoded, the last AAC frame is padded to whole frames (the container's duration above says where it ends)
    samples = facts["audio"]
    assert 0 <= samples.size - 1.5 * facts["arate"] < facts["aframe_size"]
    rms = float(np.sqrt(np.mean(samples[: int(1.5 * facts["arate"])] ** 2)))
    assert rms == pytest.approx(0.2 / np.sqrt(2), rel=0.1)  # the tone is there, at its level
    # three panels side by side, no margins; bands above (title, labels) and below (caption)
    assert facts["width"] == report.width == 3 * SIZE
    assert facts["height"] == report.height == layout.height > SIZE and report.height % 2 == 0
    assert frames[0].shape == (report.height, report.width, 3)
    assert report.seconds_render > 0 and report.frames_per_second == pytest.approx(45 / report.seconds_render)
    assert report.replaced_characters == ""


def test_panels_differ_where_the_weights_differ_and_match_where_they_agree(grid_preview):
    _, layout, (frames, _) = grid_preview
    frame = frames[20]
    bump, still, still_too = (frame[layout.panel_box(k)] for k in range(3))
    assert diff(bump, still) > 8.0  # the cone's shading, over the whole panel
    assert diff(still, still_too) < 1.0  # the same weights: the same picture, up to compression
    # before compression: exactly the same pixels
    composed = [f.copy() for _, f in zip(range(2), layout)]
    assert np.array_equal(composed[1][layout.panel_box(1)], composed[1][layout.panel_box(2)])
    assert not np.array_equal(composed[1][layout.panel_box(0)], composed[1][layout.panel_box(1)])
    # the decoded video shows what was composed
    assert diff(frames[1], composed[1]) < 3.0


def test_the_caption_band_changes_with_the_phone(grid_preview):
    _, layout, (frames, _) = grid_preview
    assert [layout.phone_at(k) for k in (0, 14, 15, 29, 30, 44)] == ["AA", "AA", "M", "M", "UW", "UW"]
    band = layout.caption_box()
    assert diff(frames[3][band], frames[12][band]) < 1.0  # "AA" both
    assert diff(frames[12][band], frames[17][band]) > 1.0  # "AA" -> "M"
    assert diff(frames[17][band], frames[35][band]) > 1.0  # "M" -> "UW"
    composed = {k: f[band].copy() for k, f in enumerate(layout) if k in (3, 12, 17, 35)}
    assert np.array_equal(composed[3], composed[12])
    assert not np.array_equal(composed[12], composed[17]) and not np.array_equal(composed[17], composed[35])
    # the labels above the panels and the title are drawn (not blank) and stay put
    for box in (layout.title_box(), layout.label_box(0), layout.label_box(2)):
        assert frames[0][box].std() > 5.0
        assert diff(frames[0][box], frames[40][box]) < 1.0


def test_shorter_sources_hold_their_last_frame_and_chunks_do_not_change_the_frames():
    ch = grid_character(12)
    ramp = np.zeros((10, 2), np.float32)
    ramp[:, 0] = np.linspace(0.0, 1.0, 10)
    long = np.zeros((25, 2), np.float32)
    long[:, 1] = np.linspace(0.0, 1.0, 25)
    frames = [f.copy() for f in PreviewFrames(ch, {"ramp": ramp, "long": long}, FPS, size=32, chunk_frames=64)]
    chunked = [f.copy() for f in PreviewFrames(ch, {"ramp": ramp, "long": long}, FPS, size=32, chunk_frames=3)]
    assert len(frames) == 25
    assert all(np.array_equal(a, b) for a, b in zip(frames, chunked, strict=True))
    layout = PreviewFrames(ch, {"ramp": ramp, "long": long}, FPS, size=32)
    ramp_box, long_box = layout.panel_box(0), layout.panel_box(1)
    assert not np.array_equal(frames[8][ramp_box], frames[9][ramp_box])
    assert all(np.array_equal(frames[9][ramp_box], f[ramp_box]) for f in frames[10:])
    assert not np.array_equal(frames[9][long_box], frames[24][long_box])


def test_audio_longer_than_the_curves_sets_the_length(tmp_path):
    ch = grid_character(12)
    weights = np.zeros((10, 2), np.float32)
    report = render_preview(tmp_path / "long audio.mp4", ch, {"a": weights}, 25, audio=(tone(1.0, 44100), 44100),
                            size=32)
    frames, facts = decode(report.path)
    assert report.frames == len(frames) == 25 and facts["rate"] == 25
    assert report.width == 32 and facts["width"] == 32
    assert abs(facts["aseconds"] - 1.0) <= 1 / 25 and abs(facts["vseconds"] - 1.0) < 1e-6


def test_curves_longer_than_the_audio_pad_it_and_odd_sample_rates_are_resampled(tmp_path):
    ch = grid_character(12)
    weights = np.zeros((36, 2), np.float32)  # 1.2 s at 29.97 fps, audio 0.5 s at 11111 Hz
    report = render_preview(tmp_path / "p.mp4", ch, {"a": weights, "b": weights}, Fraction(30000, 1001),
                            audio=(tone(0.5, 11111), 11111), size=32)
    frames, facts = decode(report.path)
    assert len(frames) == 36 and facts["rate"] == Fraction(30000, 1001) and report.fps == Fraction(30000, 1001)
    assert facts["arate"] in (48000, 44100)
    assert abs(facts["aseconds"] - facts["vseconds"]) <= 1001 / 30000


def test_the_demo_rig_opens_its_mouth_in_the_preview(tmp_path):
    ch = character_from_rig(load_demo_rig())
    t = 12
    neutral = np.zeros((t, ch.n_shapes), np.float32)
    open_ = neutral.copy()
    open_[:, ch.shape_index("AAA")] = 1.0
    sources = {"neutral": neutral, "AAA": open_}
    report = render_preview(tmp_path / "demo.mp4", ch, sources, FPS, audio=(tone(t / FPS, 16000), 16000),
                            phones=[(0.0, 0.2, "AA"), (0.2, 0.4, "")], title=f"{ch.name} demo", size=64)
    frames, facts = decode(report.path)
    assert facts["vcodec"] == "h264" and facts["acodec"] == "aac" and len(frames) == t
    assert report.width == facts["width"] == 2 * 64
    layout = PreviewFrames(ch, sources, FPS, phones=[], title="x", size=64)
    closed, opened = frames[5][layout.panel_box(0)], frames[5][layout.panel_box(1)]
    assert diff(closed, opened) > 4.0
    # the mouth is in the middle of the "mouth" framing: the centre moves more than the panel as a whole
    centre = (slice(16, 48), slice(16, 48))
    assert diff(closed[centre], opened[centre]) > diff(closed, opened)
    # the whole-face framing sees the same rig smaller
    face = PreviewFrames(ch, sources, FPS, size=64, framing="face")
    first = next(iter(face))
    assert diff(first[face.panel_box(0)], first[face.panel_box(1)]) < diff(closed, opened)


def test_text_outside_ascii_is_drawn_or_visibly_replaced():
    painter = TextPainter(18)
    assert painter.uses_pil  # Pillow comes with matplotlib
    blank = painter.band("", 200, 32)
    pinyin, plain = painter.band("nǐ hǎo", 200, 32), painter.band("ni hao", 200, 32)
    assert not np.array_equal(pinyin, plain) and painter.replaced == set()  # DejaVu has the tone marks
    chinese = painter.band("你好", 200, 32)
    assert not np.array_equal(chinese, blank)  # something visible: the glyphs or replacement marks
    if painter.replaced:  # no CJK font here: both characters replaced by the same mark
        assert painter.replaced == {"你", "好"}
        assert np.array_equal(painter.band("你", 60, 32), painter.band("好", 60, 32))
    # without Pillow: ASCII kept, the rest "?"
    ascii_only = TextPainter(18, use_pil=False)
    assert ascii_only.ascii_text("nǐ 你 ok") == "n? ? ok"
    assert ascii_only.replaced == {"ǐ", "你"}
    assert not np.array_equal(ascii_only.band("ni", 80, 32), ascii_only.band("", 80, 32))
    # too long for its band: cut, still within the band
    long = painter.band("x" * 200, 100, 32)
    assert long.shape == (32, 100, 3)


def test_a_cjk_title_is_reported_when_no_font_can_draw_it(tmp_path):
    ch = grid_character(8)
    w = np.zeros((3, 2), np.float32)
    report = render_preview(tmp_path / "t.mp4", ch, {"a": w}, FPS, title="句子 001 nǐ", size=32)
    has_cjk_font = len(TextPainter(10).fonts) > 1  # the panel's text size at 32 px
    assert report.replaced_characters == ("" if has_cjk_font else "句子")


def test_bad_inputs_are_refused_by_name_and_leave_no_file(tmp_path):
    ch = grid_character(8)
    good = np.zeros((5, 2), np.float32)
    path = tmp_path / "bad.mp4"
    path.write_bytes(b"old preview")
    with pytest.raises(ValueError, match=r"character 'grid'.*'wide'.*\(T, 2\).*bump, shift"):
        render_preview(path, ch, {"ok": good, "wide": np.zeros((5, 3), np.float32)}, FPS, size=32)
    nan = good.copy()
    nan[3, 1] = np.nan
    with pytest.raises(ValueError, match=r"character 'grid'.*'curves'.*NaN.*frame 3.*'shift'"):
        render_preview(path, ch, {"curves": nan}, FPS, size=32)
    with pytest.raises(ValueError, match=r"'empty' has no frames"):
        render_preview(path, ch, {"empty": np.zeros((0, 2), np.float32)}, FPS, size=32)
    with pytest.raises(ValueError, match=r"character 'grid'.*no curve sources"):
        render_preview(path, ch, {}, FPS, size=32)
    for fps in (0, -30, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="fps must be a positive number"):
            render_preview(path, ch, {"ok": good}, fps, size=32)
    with pytest.raises(ValueError, match="even"):
        render_preview(path, ch, {"ok": good}, FPS, size=33)
    with pytest.raises(ValueError, match=r"\.mp4"):
        render_preview(tmp_path / "bad.avi", ch, {"ok": good}, FPS, size=32)
    with pytest.raises(ValueError, match="audio has NaN"):
        render_preview(path, ch, {"ok": good}, FPS, size=32, audio=(np.full(100, np.nan, np.float32), 16000))
    with pytest.raises(ValueError, match="mono"):
        render_preview(path, ch, {"ok": good}, FPS, size=32, audio=(np.zeros((100, 2), np.float32), 16000))
    with pytest.raises(ValueError, match=r"phone 1 \('B'\)"):
        render_preview(path, ch, {"ok": good}, FPS, size=32, phones=[(0.0, 0.1, "A"), (0.2, 0.1, "B")])
    assert path.read_bytes() == b"old preview"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.mp4"]  # no temporary file left


def rigid_and_bump_character(n: int = 12):
    """The grid sheet with the 16 viseme names: AAA slides the lower half down (rigid: bones can play it exactly),
    AHH raises the cone (no rigid bone can), the others rest."""
    from visemeflow.visemes import VISEMES

    sheet = grid_character(n)
    deltas = np.zeros((16, n * n, 3), np.float32)
    deltas[VISEMES.index("AAA")] = sheet.deltas[1] * 2.0
    deltas[VISEMES.index("AHH")] = sheet.deltas[0]
    return make_character("sheet", sheet.neutral, sheet.faces, list(VISEMES), deltas)


def test_a_bone_panel_shows_the_skinned_bones_beside_the_blendshapes():
    """`BoneSource`: the panel is the rig's poses blended by the curves and skinned (pixel for pixel the render of
    `bone_animation`); where the bones can play the shape it looks like the blendshape panel beside it, where they
    cannot (a cone from 2 rigid bones) it differs, and it is never copied from a blendshape panel with equal rows."""
    from visemeflow.animation.bones import bone_animation, solve_bones
    from visemeflow.animation.preview import BoneSource
    from visemeflow.render.raster import render_mesh
    from visemeflow.visemes import VISEMES

    ch = rigid_and_bump_character()
    rig = solve_bones(ch, 2)
    curves = np.zeros((12, 16), np.float32)
    curves[2:6, VISEMES.index("AAA")] = np.linspace(0.25, 1.0, 4)
    curves[8:12, VISEMES.index("AHH")] = 1.0
    layout = PreviewFrames(ch, {"shapes": curves, "2 bones": BoneSource(rig, curves)}, FPS, size=64)
    frames = [f.copy() for f in layout]
    shapes_box, bones_box = layout.panel_box(0), layout.panel_box(1)
    skinned = bone_animation(rig, curves)
    for i in (0, 3, 5, 9):
        expected = render_mesh(skinned[i], np.asarray(ch.faces, np.int64), ch.vertex_colors, layout.camera,
                               layout.pose)
        assert np.array_equal(frames[i][bones_box], expected), i
    assert np.array_equal(frames[0][bones_box], frames[0][shapes_box])       # at rest both show the neutral
    assert diff(frames[0][bones_box], frames[5][bones_box]) > 1.0            # the slide shows on the bones
    assert diff(frames[5][bones_box], frames[5][shapes_box]) < 0.5           # and matches the blendshapes
    assert diff(frames[9][bones_box], frames[9][shapes_box]) > 1.0           # the cone does not


def test_a_bone_source_of_another_mesh_or_width_is_refused_by_name(tmp_path):
    from visemeflow.animation.bones import solve_bones
    from visemeflow.animation.preview import BoneSource

    ch = rigid_and_bump_character()
    rig = solve_bones(ch, 2)
    with pytest.raises(ValueError, match=r"character 'sheet'.*'bones'.*\(T, 16\).*pose of the bone rig.*AAA"):
        render_preview(tmp_path / "a.mp4", ch, {"bones": BoneSource(rig, np.zeros((5, 15), np.float32))}, FPS,
                       size=32)
    nan = np.zeros((5, 16), np.float32)
    nan[2, 7] = np.nan
    with pytest.raises(ValueError, match=r"'bones' has a NaN or infinite curve \(first at frame 2, pose 'MBP'\)"):
        render_preview(tmp_path / "a.mp4", ch, {"bones": BoneSource(rig, nan)}, FPS, size=32)
    with pytest.raises(ValueError, match=r"bone rig of 'sheet' with 144 vertices, not of this character \(64"):
        render_preview(tmp_path / "a.mp4", rigid_and_bump_character(8), {"bones": BoneSource(rig, nan)}, FPS, size=32)
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------------------------------- the source video panel

VIDEO_FPS = 25


def patterned_video(path, n: int = 12, height: int = 120, width: int = 160):
    """A clip whose frames all differ: smooth noise (so a crop shows where it was cut) and a bright bar moving 5 px a
    frame inside the face crop of `corner_landmarks`, with a silent audio track (times on the audio's clock, as the utterances' videos)."""
    from visemeflow.tracking.video import write_video

    rng = np.random.default_rng(3)
    base = cv2.resize(rng.integers(0, 255, (height // 8, width // 8, 3), dtype=np.uint8), (width, height),
                      interpolation=cv2.INTER_CUBIC)
    frames = []
    for k in range(n):
        frame = base.copy()
        frame[:, 36 + 5 * k:42 + 5 * k] = (250, 250, 40)
        frames.append(frame)
    write_video(path, frames, VIDEO_FPS, audio=np.zeros(int(n / VIDEO_FPS * 16000), np.float32), audio_rate=16000)
    return path


def corner_landmarks(n: int, mouth_at=None):
    """A landmark track whose points all sit on the corners of x 40..100, y 30..90 (so the face crop is known: centre
    (70, 60), side 60 / 0.86 = 70 px), the mouth (48-67) at `mouth_at` when given."""
    from visemeflow.tracking.landmarks import LandmarkTrack

    corners = np.array([[40, 30], [100, 30], [40, 90], [100, 90]], np.float32)
    points = np.tile(corners[np.arange(68) % 4], (n, 1, 1))
    if mouth_at is not None:
        points[:, 48:68] = mouth_at
    return LandmarkTrack(points, np.ones((n, 68), bool), VIDEO_FPS, "generic68")


def expected_crop(frame: np.ndarray, left: int, top: int, side: int, size: int) -> np.ndarray:
    """The test's own crop: frame[top:top+side, left:left+side] (black outside the frame), scaled to size."""
    square = np.zeros((side, side, 3), np.uint8)
    y0, y1, x0, x1 = max(top, 0), min(top + side, frame.shape[0]), max(left, 0), min(left + side, frame.shape[1])
    square[y0 - top:y1 - top, x0 - left:x1 - left] = frame[y0:y1, x0:x1]
    return cv2.resize(square, (size, size), interpolation=cv2.INTER_AREA if side > size else cv2.INTER_LINEAR)


def video_panels(layout: PreviewFrames) -> list[np.ndarray]:
    return [canvas[layout.panel_box(0)].copy() for canvas in layout]


def shown_frames(panels, crops) -> list[tuple[int, float]]:
    """For each panel, the decoded frame whose crop it matches best, and how well (mean abs difference)."""
    out = []
    for panel in panels:
        d = [diff(panel, c) for c in crops]
        out.append((int(np.argmin(d)), float(min(d))))
    return out


def test_the_video_panel_shows_the_face_crop_of_the_frame_the_tracker_used(tmp_path):
    """At 30 fps over a 25 fps clip, preview frame k shows the crop of the decoded frame that
    `FrameTimeline.video_frame` gives grid frame k; where it gives none (no frame within half a step), the nearest
    frame dimmed."""
    from visemeflow.animation.preview import VideoSource
    from visemeflow.tracking.utterance import FrameTimeline
    from visemeflow.tracking.video import read_timed_frames

    video = patterned_video(tmp_path / "take.mp4")
    decoded, times = read_timed_frames(video)
    crops = [expected_crop(f, 35, 25, 70, SIZE) for f in decoded]
    n = 14
    layout = PreviewFrames(grid_character(), {"tracked": np.zeros((n, 2), np.float32)}, FPS, size=SIZE,
                           framing="face", video=VideoSource(video, corner_landmarks(len(decoded)), overlay=False))
    assert layout.n_panels == 2 and layout.width == 2 * SIZE
    label = np.asarray(layout.painter.band("video", SIZE, layout.label_height))
    panels, first = [], None
    for canvas in layout:
        panels.append(canvas[layout.panel_box(0)].copy())
        first = canvas[layout.label_box(0)].copy() if first is None else first
    assert np.array_equal(first, label)
    index = FrameTimeline(times, FPS, n).video_frame()
    assert (index < 0).any() and (index >= 0).sum() >= 8   # both cases are exercised
    for k, (panel, want) in enumerate(zip(panels, index)):
        if want >= 0:
            best, error = shown_frames([panel], crops)[0]
            assert best == want and error < 3.0, (k, best, want, error)
            # the crop, not the whole frame or another region: the same frame cut elsewhere is far off
            assert diff(panel, expected_crop(decoded[want], 5, 5, 70, SIZE)) > 10 * max(error, 1.0)
        else:
            t = k / FPS
            nearest = int(np.argmin(np.abs(times - t)))
            assert diff(panel, (crops[nearest] * 0.5).astype(np.uint8)) < 3.0, k


def test_the_tracked_mouth_landmarks_are_drawn_on_the_video_panel(tmp_path):
    from visemeflow.animation.preview import LANDMARK_COLOR, VideoSource

    video = patterned_video(tmp_path / "take.mp4", n=4)
    sources = {"tracked": np.zeros((3, 2), np.float32)}
    plain = video_panels(PreviewFrames(grid_character(), sources, VIDEO_FPS, size=SIZE, framing="face",
                                       video=VideoSource(video, corner_landmarks(4, (70, 60)), overlay=False)))
    marked = video_panels(PreviewFrames(grid_character(), sources, VIDEO_FPS, size=SIZE, framing="face",
                                        video=VideoSource(video, corner_landmarks(4, (70, 60)))))
    centre = SIZE // 2  # (70, 60) is the crop's centre
    for a, b in zip(plain, marked):
        assert np.abs(b[centre, centre].astype(int) - LANDMARK_COLOR).max() < 40
        changed = np.argwhere(np.abs(a.astype(int) - b.astype(int)).max(axis=2) > 30)
        assert len(changed) and np.abs(changed - centre).max() <= 3   # only the dot, nothing else


def test_without_a_video_there_is_no_video_panel_and_a_bad_one_says_so(tmp_path):
    from visemeflow.animation.preview import VideoSource

    ch, sources = grid_character(), {"tracked": np.zeros((3, 2), np.float32)}
    bare = PreviewFrames(ch, sources, FPS, size=SIZE)
    assert bare.n_panels == 1 and bare.width == SIZE
    first = next(iter(bare))
    assert not np.array_equal(first[bare.label_box(0)], bare.painter.band("video", SIZE, bare.label_height))

    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"not a video at all" * 100)
    for path, text in ((tmp_path / "gone.mp4", "video not found"), (broken, "video unreadable"),
                       (None, "no video file")):
        out = tmp_path / "p.mp4"
        report = render_preview(out, ch, sources, FPS, size=SIZE, video=VideoSource(path, corner_landmarks(3)))
        assert report.width == 2 * SIZE and report.frames == 3
        frames, _ = decode_video_only(out)
        layout = PreviewFrames(ch, sources, FPS, size=SIZE, video=VideoSource(path))
        message = layout.painter.band(text, SIZE, SIZE)
        assert all(diff(f[layout.panel_box(0)], message) < 2.0 for f in frames), text
        other = layout.painter.band("video not found" if text != "video not found" else "no video file", SIZE, SIZE)
        assert diff(frames[0][layout.panel_box(0)], other) > diff(frames[0][layout.panel_box(0)], message)


def decode_video_only(path):
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        return [f.to_ndarray(format="rgb24") for f in container.decode(video=0)], stream.codec_context.width


def test_a_real_variable_rate_clip_shows_the_speakers_face_at_each_preview_time():
    """../shared/data/talking_heads/1.mp4 (variable frame rate, MediaPipe landmarks): each panel is the crop of the
    decoded frame the tracker maps to that time, around the landmarks of the lower face."""
    from visemeflow.animation.preview import VideoSource, video_source
    from visemeflow.tracking.utterance import FrameTimeline
    from visemeflow.tracking.video import iter_timed_frames

    from factories import SHARED_DATA

    clip = SHARED_DATA / "talking_heads" / "1.mp4"
    landmarks = SHARED_DATA / "talking_heads" / "1.mediapipe478.csv"
    assert clip.is_file() and landmarks.is_file(), f"{clip}: the shared data is missing"
    n = 30
    source = video_source(clip, landmarks, 30.0, overlay=False)
    assert isinstance(source, VideoSource) and source.landmarks is not None
    layout = PreviewFrames(grid_character(), {"tracked": np.zeros((n, 2), np.float32)}, 30, size=SIZE,
                           video=source)
    panels = video_panels(layout)
    decoded, times = [], []
    for frame, t in iter_timed_frames(clip):
        if t > (n + 1) / 30:
            break
        decoded.append(frame)
        times.append(t)
    # the crop: the lower face's landmarks over the clip (1st..99th percentile), widened by 1 / 0.86
    lower = np.r_[2:15, 31:36, 48:68]
    pts = source.landmarks.points[:, lower][source.landmarks.valid[:, lower]]
    low, high = np.percentile(pts, (1, 99), axis=0)
    side = int(round(max(high - low) / 0.86))
    left, top = (int(round(c - side / 2)) for c in (low + high) / 2)
    mouth = source.landmarks.points[:, 48:68].reshape(-1, 2)
    assert (left < mouth[:, 0].min()) and (mouth[:, 0].max() < left + side)
    assert (top < mouth[:, 1].min()) and (mouth[:, 1].max() < top + side)
    crops = [expected_crop(f, left, top, side, SIZE) for f in decoded]
    index = FrameTimeline(np.asarray(times), 30.0, n).video_frame()
    assert (index < 0).any()  # the clip's gaps
    for k, want in enumerate(index):
        if want >= 0:
            best, error = shown_frames([panels[k]], crops)[0]
            assert error < 3.0 and diff(crops[best], crops[want]) < 1e-9, (k, best, want, error)


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_the_preview_command_puts_the_tracked_videos_face_first_and_leaves_it_out_without_tracked(tmp_path):
    """`visemeflow preview` on an utterance with a video and stored landmarks: with `tracked` among the sources the
    first panel is the video's face crop (labelled "video"); without `tracked`, or for an utterance with no video, it
    is absent."""
    from typer.testing import CliRunner

    from factories import make_curve_store
    from visemeflow.cli import app
    from visemeflow.schemas import UTTERANCES, C, curves_array, curves_table, table_from_rows
    from visemeflow.tracking.landmarks import write_landmarks
    from visemeflow.tracking.video import read_timed_frames

    store = make_curve_store(tmp_path / "store", n=2)
    video = patterned_video(tmp_path / "u0.mp4", n=12)
    marks = write_landmarks(corner_landmarks(12), tmp_path / "u0.landmarks.csv")
    rows = store.read_table("utterances").to_pylist()
    rows[0][C.VIDEO_PATH], rows[0][C.LANDMARK_PATH] = str(video), str(marks)
    store.write_shard("utterances", 0, table_from_rows(rows, UTTERANCES))
    for uid in ("spk/u0", "spk/u1"):
        curves = curves_array(store.read_curves(uid, "ground_truth", "cm"))
        store.write_curves(curves_table(uid, "tracked", "v1", curves, 25.0))
    decoded, _ = read_timed_frames(video)
    # the boxes (the command titles its previews; the panels' place does not depend on the character)
    layout = PreviewFrames(grid_character(), {"x": np.zeros((1, 2), np.float32)}, 25, size=SIZE, title="t")

    def preview(uid: str, sources: str, name: str):
        out = tmp_path / name
        result = CliRunner().invoke(app, ["preview", uid, "--store", str(store.root), "--sources", sources,
                                          "--size", str(SIZE), "--out", str(out)])
        assert result.exit_code == 0, result.output
        frames, width = decode_video_only(out)
        return result.output, frames, width

    output, frames, width = preview("spk/u0", "tracked,ground_truth", "with.mp4")
    assert "video, tracked (v1), ground truth (cm)" in output and width == 3 * SIZE
    label = frames[0][layout.label_box(0)]
    assert diff(label, layout.painter.band("video", SIZE, layout.label_height)) < 3.0
    assert diff(label, layout.painter.band("tracked (v1)", SIZE, layout.label_height)) > 6.0
    for k in (1, 5, 10):   # the curves' 25 fps grid is the clip's: frame k shows decoded frame k
        panel = frames[k][layout.panel_box(0)]
        d = [diff(panel, expected_crop(f, 35, 25, 70, SIZE)) for f in decoded]
        # H.264 at the preview's quality blurs the noise a little, and the mouth dots sit on the crop's corners
        assert int(np.argmin(d)) == k and d[k] < 10.0 and d[k] < 0.5 * min(d[:k] + d[k + 1:]), (k, d)

    output, frames, width = preview("spk/u0", "ground_truth", "without.mp4")
    assert "fps; ground truth (cm); rendered" in output and width == SIZE
    output, frames, width = preview("spk/u1", "tracked,ground_truth", "none.mp4")
    assert "fps; tracked (v1), ground truth (cm); rendered" in output and width == 2 * SIZE


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_the_preview_command_keeps_an_mp4_made_from_the_same_inputs_and_renders_again_when_one_changes(tmp_path):
    """A second `visemeflow preview` with the same curves, character and settings keeps the MP4 (it re-rendered every
    call); other settings, curves rewritten from other inputs, or --force render it again."""
    from typer.testing import CliRunner

    from factories import make_curve_store
    from visemeflow.cli import app
    from visemeflow.schemas import curves_array, curves_table

    store = make_curve_store(tmp_path / "store", n=1)
    out = tmp_path / "u0.mp4"

    def preview(*extra: str) -> tuple[str, int]:
        result = CliRunner().invoke(app, ["preview", "spk/u0", "--store", str(store.root), "--sources", "ground_truth",
                                          "--size", str(SIZE), "--out", str(out), *extra])
        assert result.exit_code == 0, result.output
        return result.output, out.stat().st_mtime_ns

    output, made = preview()
    assert f"wrote {out} (" in output
    output, again = preview()
    assert f"kept {out} (" in output and "--force renders it again" in output and again == made
    for extra in (["--size", str(SIZE + 16)], ["--force"]):
        output, again = preview(*extra)
        assert f"wrote {out} (" in output and again != made, extra
        made = again
    output, _ = preview()   # the record is of the last render (--force, at the first size)
    assert "kept" in output
    curves = curves_array(store.read_curves("spk/u0", "ground_truth", "cm"))
    store.write_curves(curves_table("spk/u0", "ground_truth", "cm", curves[::-1].copy(), 25.0), provenance="other")
    output, again = preview()
    assert f"wrote {out} (" in output and again != made
    # curves written again without a provenance (as these were at first): their bytes decide
    store.write_curves(curves_table("spk/u0", "ground_truth", "cm", curves, 25.0))
    output, made = preview()
    assert f"wrote {out} (" in output
    store.write_curves(curves_table("spk/u0", "ground_truth", "cm", curves * 0.5, 25.0))
    output, again = preview()
    assert f"wrote {out} (" in output and again != made


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_animate_preview_shows_the_utterances_video_beside_the_character_and_the_character_alone_otherwise(
        tmp_path):
    """`animate --preview`: the package MP4 of an utterance with a video has the video's face crop as its first
    panel (the `preview` command's panel, in sync: the curves' 25 fps grid is the clip's), two panels wide; one
    without a video has the character alone, as before; one whose video cannot be read too, with a warning. The
    utterance's content hash is in the task's cache key: a re-ingested video renders the package again."""
    from factories import make_curve_store
    from visemeflow.animation.package import AnimateConfig
    from visemeflow.flows.animate import AnimateParams, animate_flow
    from visemeflow.rig.character import save_character_npz
    from visemeflow.schemas import UTTERANCES, C, curves_array, curves_table, table_from_rows
    from visemeflow.shapes.conventions import OCULUS_15
    from visemeflow.tracking.landmarks import write_landmarks
    from visemeflow.tracking.video import read_timed_frames

    store = make_curve_store(tmp_path / "store", n=3)
    video = patterned_video(tmp_path / "u0.mp4", n=12)
    marks = write_landmarks(corner_landmarks(12), tmp_path / "u0.landmarks.csv")
    broken = tmp_path / "u2.mp4"
    broken.write_bytes(b"not a video at all" * 100)
    rows = store.read_table("utterances").to_pylist()
    rows[0][C.VIDEO_PATH], rows[0][C.LANDMARK_PATH] = str(video), str(marks)
    rows[2][C.VIDEO_PATH] = str(broken)
    store.write_shard("utterances", 0, table_from_rows(rows, UTTERANCES))
    for uid in ("spk/u0", "spk/u1", "spk/u2"):
        curves = curves_array(store.read_curves(uid, "ground_truth", "cm"))[:12]   # as long as the clip
        store.write_curves(curves_table(uid, "tracked", "v1", curves, 25.0))
    grid = grid_character(8)
    deltas = np.random.default_rng(0).normal(0.0, 0.05, (len(OCULUS_15), grid.n_vertices, 3))
    character = save_character_npz(make_character("grid", grid.neutral, grid.faces, list(OCULUS_15), deltas),
                                   tmp_path / "grid.npz")
    params = AnimateParams(store=store.root, characters=[character], source="tracked", variant="v1",
                           config=AnimateConfig(formats=("curves-csv",), preview=True))
    result = animate_flow(params)
    assert result["written"] == 3 and result["rejected"] == 0
    reports = {r["utterance_id"]: r for r in result["packages_written"]}
    size = 360   # the package preview's panel side
    layout = PreviewFrames(grid_character(), {"x": np.zeros((1, 2), np.float32)}, 25, size=size, title="t")

    frames, width = decode_video_only(reports["spk/u0"]["files"]["preview"])
    assert width == 2 * size and len(frames) == 25 and reports["spk/u0"]["warnings"] == []
    label = frames[0][layout.label_box(0)]
    assert diff(label, layout.painter.band("video", size, layout.label_height)) < 3.0
    decoded, _ = read_timed_frames(video)
    for k in (1, 6, 11):   # frame k shows decoded frame k's face crop, the mouth dots on its corners
        panel = frames[k][layout.panel_box(0)]
        d = [diff(panel, expected_crop(f, 35, 25, 70, size)) for f in decoded]
        assert int(np.argmin(d)) == k and d[k] < 10.0 and d[k] < 0.5 * min(d[:k] + d[k + 1:]), (k, d)
    # the character's panel is the right one: nothing of the clip there
    assert min(diff(frames[6][layout.panel_box(1)], expected_crop(f, 35, 25, 70, size)) for f in decoded) > 20.0

    frames, width = decode_video_only(reports["spk/u1"]["files"]["preview"])
    assert width == size and reports["spk/u1"]["warnings"] == []
    frames, width = decode_video_only(reports["spk/u2"]["files"]["preview"])
    (warning,) = reports["spk/u2"]["warnings"]
    assert width == size and "character alone" in warning and str(broken) in warning and "unreadable" in warning

    rows[0][C.CONTENT_HASH] = "re-ingested"   # the others' packages are cache hits, u0's is rendered again
    store.write_shard("utterances", 0, table_from_rows(rows, UTTERANCES))
    again = animate_flow(params)
    assert again["written"] == 1 and [r["utterance_id"] for r in again["packages_written"] if not r["cached"]] == \
        ["spk/u0"]


def test_a_long_preview_reports_each_frame_written_and_its_log_lines_count_frames(tmp_path):
    from visemeflow.tasks.progress import StepLog

    ch = grid_character(12)
    heard = []
    report = render_preview(tmp_path / "p.mp4", ch, {"a": np.zeros((20, 2), np.float32)}, 25, size=32,
                            progress=lambda *a: heard.append(a))
    assert heard == [("preview", k, 20) for k in range(1, 21)] and report.frames == 20
    now, lines = [0.0], []
    log = StepLog("animate[s/x]", lines.append, interval=5.0, clock=lambda: now[0])
    for phase, k, n in heard:
        now[0] = k * 0.5                       # 2 frames a second
        log(phase, k, n)
    assert lines == ["animate[s/x]: preview 10/20 frames, 2/s, about 4 s left",   # the phase began at frame 1
                     "animate[s/x]: preview 20/20 frames, 2/s"]


def test_a_gltf_avatar_shows_its_skin_texture_in_the_preview(tmp_path, monkeypatch, caplog):
    """The avatar of tests/avatar_glb.py (a head textured by a 2x2 skin PNG, teeth and eyes with a plain material):
    the preview shows the head in the skin's colours (red over green over blue, as every texel of it), where it was
    grey; an image too large to decode is left out with a warning naming it, and the head falls back to its base
    colour."""
    import io

    from avatar_glb import make_avatar
    from PIL import Image

    import visemeflow.animation.surface as surface
    import visemeflow.animation.textures as textures
    from visemeflow.animation.load import load_character
    from visemeflow.rig.gltf import GltfScene

    make_avatar(tmp_path / "avatar.glb")
    ch = load_character(tmp_path / "avatar.glb")
    scene, notes = surface.preview_scene(ch)
    texture, notes = scene.texture, list(notes)       # the avatar shows no mesh twice: the character's faces alone
    png = np.asarray(Image.open(io.BytesIO(GltfScene(tmp_path / "avatar.glb").image(0)[0])).convert("RGB"))
    assert notes == [] and len(texture.images) == 1 and np.array_equal(texture.images[0], png)
    head = next(p for p in ch.parts if p.name == "Wolf3D_Head")
    on_head = (ch.faces >= head.start).all(axis=1) & (ch.faces < head.stop).all(axis=1)
    assert (texture.face_image[on_head] == 0).all() and (texture.face_image[~on_head] == -1).all()

    weights = np.zeros((2, ch.n_shapes), np.float32)

    def skin_share(frames: PreviewFrames) -> float:
        panel = next(iter(frames))[frames.panel_box(0)].reshape(-1, 3).astype(int)
        covered = panel[(panel != panel[0]).any(axis=1)]          # the corner is background
        skin = (covered[:, 0] > covered[:, 1] + 10) & (covered[:, 1] > covered[:, 2])
        return float(skin.mean()) if len(covered) else 0.0

    assert skin_share(PreviewFrames(ch, {"speech": weights}, FPS, size=96, framing="face")) > 0.5
    monkeypatch.setattr(textures, "MAX_IMAGE_PIXELS", 3)            # the 2x2 skin is now "too large"
    fresh = load_character(tmp_path / "avatar.glb")     # the texture is made once per character object
    with caplog.at_level("WARNING"):
        plain = PreviewFrames(fresh, {"speech": weights}, FPS, size=96, framing="face")
    assert skin_share(plain) == 0.0
    assert "image 0 is 2x2 pixels, more than the 3 decoded pixels visemeflow reads" in caplog.text


def test_the_preview_draws_the_avatars_other_meshes_behind_and_around_its_driven_ones(tmp_path):
    """The preview drew the driven meshes alone (a Ready Player Me head without its hair). The avatar's hair, a mesh
    no target moves, is now drawn as the file places it, in its material's colour, and the driven eye in front of it
    stays in front; the same avatar without hair shows no hair colour."""
    from avatar_glb import make_avatar

    from visemeflow.animation.load import load_character
    from visemeflow.render.raster import project

    def panel_of(path):
        ch = load_character(path)
        frames = PreviewFrames(ch, {"speech": np.zeros((1, ch.n_shapes), np.float32)}, FPS, size=240, framing="face")
        return ch, frames, next(iter(frames))[frames.panel_box(0)].astype(int)

    def blue(pixels):
        return (pixels[..., 2] > pixels[..., 0] + 40) & (pixels[..., 2] > pixels[..., 1] + 40)

    make_avatar(tmp_path / "hair.glb", hair=True)
    make_avatar(tmp_path / "bald.glb")
    ch, frames, panel = panel_of(tmp_path / "hair.glb")
    _, _, bald = panel_of(tmp_path / "bald.glb")
    assert blue(panel).mean() > 0.05 and blue(bald).sum() == 0
    eye = next(p for p in ch.parts if p.name == "EyeLeft")
    u, v = np.round(project(ch.neutral[eye.start:eye.stop].mean(axis=0, keepdims=True), frames.camera,
                            frames.pose)[0]).astype(int)
    assert not blue(panel[v, u]) and blue(panel[v - 8, u])      # the eye over the hair, the hair around it


def test_a_driven_mesh_that_two_nodes_show_is_drawn_at_both_and_moves_at_both(tmp_path):
    """One eye mesh (a jawOpen target) that two nodes show: the preview drew it at the first node only. Its second
    instance now follows the same curves, placed by its own node."""
    from scene_glb import EYE_AT, make_scene

    from visemeflow.animation.load import load_character
    from visemeflow.animation.surface import preview_scene

    arrays = make_scene(tmp_path / "eyes.glb", eye_targets=True)
    ch = load_character(tmp_path / "eyes.glb")
    scene, notes = preview_scene(ch)
    eye = next(p for p in ch.parts if p.name == "Eye")
    jaw = ch.shape_names.index("jawOpen")
    for weight in (0.0, 0.7):
        driven = ch.neutral + weight * ch.deltas[jaw]
        rows = scene.vertices(driven)
        assert np.array_equal(rows[:ch.n_vertices], driven)
        np.testing.assert_allclose(rows[ch.n_vertices:], arrays["eye"] + np.float32(EYE_AT[1]) + weight * 0.002,
                                   atol=1e-6)
    assert len(scene.faces) == len(ch.faces) + 1 and scene.faces[-1].tolist() == [ch.n_vertices + k for k in range(3)]
    assert scene.texture.face_image.shape == (len(scene.faces),) and eye.n_vertices == 3


def test_a_scene_showing_more_vertices_than_the_bound_leaves_meshes_out_and_says_so(tmp_path, monkeypatch):
    """A small file can make a million nodes show one large mesh: what the preview and the USD place besides the
    driven meshes stops at `MAX_SCENE_VERTICES`, and the rest is named. Here the bound (set to 10) lets the avatar's
    body (9 vertices) in and leaves its hair (16) out."""
    from avatar_glb import make_avatar
    from pxr import Usd, UsdGeom

    import visemeflow.rig.gltf as gltf
    from visemeflow.animation.load import load_character
    from visemeflow.animation.surface import preview_scene
    from visemeflow.animation.usd import write_usd

    make_avatar(tmp_path / "hair.glb", hair=True)
    whole = preview_scene(load_character(tmp_path / "hair.glb"))[0]
    assert len(whole.static.vertices) == 9 + 16
    monkeypatch.setattr(gltf, "MAX_SCENE_VERTICES", 10)
    ch = load_character(tmp_path / "hair.glb")
    scene, notes = preview_scene(ch)
    assert len(scene.static.vertices) == 9
    assert notes == ("the preview: 1 mesh placement left out (Wolf3D_Hair): the scene shows more than 10 vertices "
                     "besides the driven meshes",)
    stage = Usd.Stage.Open(str(write_usd(tmp_path / "take.usda", ch, np.zeros((2, ch.n_shapes), np.float32), 30.0,
                                         name="take")))
    names = {p.GetName() for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)}
    assert "BodyNode" in names and "HairNode" not in names
    assert "1 mesh placement left out (Wolf3D_Hair)" in stage.GetRootLayer().documentation


def test_a_mesh_of_lines_in_the_scene_is_left_out_of_the_preview_and_the_usd_not_the_rest(tmp_path):
    """A scene mesh the reader refuses (here the hair drawn as LINES, as a helper or a rig display may be) failed the
    USD export with a RigError and took every material out of the preview. It is now left out of both, named."""
    import pygltflib as gl
    from avatar_glb import make_avatar
    from pxr import Usd, UsdGeom

    from visemeflow.animation.load import load_character
    from visemeflow.animation.surface import preview_scene
    from visemeflow.animation.usd import write_usd

    make_avatar(tmp_path / "hair.glb", hair=True)
    g = gl.GLTF2().load(str(tmp_path / "hair.glb"))
    g.meshes[5].primitives[0].mode = gl.LINES
    g.save_binary(str(tmp_path / "lines.glb"))
    ch = load_character(tmp_path / "lines.glb")
    scene, notes = preview_scene(ch)
    assert len(scene.static.vertices) == 9 and len(scene.texture.images) == 1        # the body, the skin
    assert len(notes) == 1 and "'Wolf3D_Hair') primitive 0 draws LINES" in notes[0]
    assert notes[0].endswith("left out of the preview")
    stage = Usd.Stage.Open(str(write_usd(tmp_path / "take.usda", ch, np.zeros((2, ch.n_shapes), np.float32), 30.0,
                                         name="take")))
    names = {p.GetName() for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)}
    assert "BodyNode" in names and "HairNode" not in names
    assert "draws LINES; only triangles (TRIANGLES, TRIANGLE_STRIP, TRIANGLE_FAN) are read: left out" in \
        stage.GetRootLayer().documentation
