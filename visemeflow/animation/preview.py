"""Preview videos a person can watch: one character's face driven by several curve sources, side by side.

`render_preview(path, character, {"procedural": w1, "tracked": w2, ...}, fps, audio=..., phones=..., title=...)`
writes an H.264 + AAC `.mp4`:

    +-----------------------------------------------+
    |                    title                      |   title band (only with `title`)
    | procedural  |   tracked    |   predicted      |   label band: each source's label above its panel
    |   [face]    |   [face]     |    [face]        |   one `size` x `size` panel per source, no margins
    |                    AH                         |   caption band: the phone under way (only with `phones`)
    |  lips 1.1 mm | lips 14.2 mm |  lips 0.9 mm    |   lip band: each panel's inner-lip gap (characters with
    +-----------------------------------------------+   landmarks: the demo character, transferred characters)

The lip band shows the gap between the inner lips of the mesh as rendered (the three inner-lip landmark pairs of the
68-point layout, in millimetres, `Character.mm_per_unit`): green when closed (below `articulation.CLOSED_MM`), red
when the phone under way is a bilabial (b, p, m) and the lips are not closed, so a failed closure shows at a glance.

Panels are rendered by the synthetic corpus's numpy rasteriser (`visemeflow.render.raster.render_mesh`, Lambert +
ambient shading; the character's vertex colours, or grey; a glTF character's material colours and base-colour
textures, `animation.surface`) from one fixed camera and pose per character, so only the blendshape motion changes.
The default `framing="mouth"` frames the vertices that the shapes move (for a face rig: the lower face, lips, jaw
and chin); `framing="face"` frames the whole neutral mesh.

Memory stays bounded for long takes: vertices are made `chunk_frames` frames at a time
(`neutral + weights @ deltas.reshape(S, -1)`), each frame is composed into one reused canvas and handed to the
encoder at once; no list of frames is ever held. A panel whose weights equal its previous frame's (a held last
frame, a still stretch) or another panel's in the same frame is copied, not rendered again.

Text (title, labels, phones). With Pillow (a declared dependency) text is drawn
with a TrueType font: DejaVu Sans from the system (or matplotlib's bundled copy), which covers Latin, IPA and
pinyin with tone marks, and a CJK font when one of the usual ones is installed (Noto Sans CJK, WenQuanYi, Droid
Sans Fallback, ...). A character that no available font has (e.g. Chinese on a machine without a CJK font, which
is this project's Debian image) is drawn as U+FFFD "�", visibly, never silently dropped or as an empty box; the
characters replaced are listed in `PreviewReport.replaced_characters`. Without Pillow, text goes through
`cv2.putText` (Hershey fonts, ASCII only): printable ASCII is kept and every other character becomes "?".
Text too wide for its band is cut and ends in "...".

Bone panels. A source may instead be a `BoneSource(rig, curves)`: the character's face moved by SSDR bones
(`visemeflow.animation.bones`), the rig's poses blended by the (T, P) curves and linear-blend skinned, which is what
the skinned GLB, the UsdSkel animation and an engine's pose blend play. Put it beside the blendshape panel of the
same curves to see what the bones lose (`visemeflow preview --mode both`).

Source video. With `video=VideoSource(path, landmarks)` (the preview command passes it when `tracked` is among the
sources and the utterance has a video) the first panel, labelled "video", shows the source video's frame cropped to
the face, so a user can judge the tracking against the footage. Frame k shows the decoded frame the tracker used for
grid frame k: the one nearest k / fps on the audio's clock (`tracking.video.iter_timed_frames`), and none when no
frame lies within half a frame step (a variable-rate clip's gap: the nearest frame, dimmed), the rule of
`tracking.utterance.FrameTimeline.video_frame`. The crop is one fixed square for the whole clip (a steady view,
not one that jitters with each detection): the box of the landmarks that `framing` frames (the lower face and mouth,
or the whole face), over all frames, widened as the rig panels are; without landmarks, the frame's central square.
The tracked mouth landmarks are drawn on it (`VideoSource.overlay`). The video is decoded one frame at a time as the
preview is written, never held whole; a missing or unreadable video leaves a panel that says so, and the preview
renders (`PreviewReport.video_problem` says why). A caller that would rather leave the panel out than show such a
message (the animate task's package preview) asks `video_problem(path)` first.

Timing: frame k shows weights row k and the phone under way at time k / fps (`visemeflow.timebase`'s clock).
"""

from __future__ import annotations

import bisect
import functools
import importlib.util
import logging
import math
import os
import time
import unicodedata
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING
from fractions import Fraction
from pathlib import Path

import av
import cv2
import numpy as np

from visemeflow.rig.character import Character
from visemeflow.animation.lips import inner_lip_pairs, is_bilabial, pair_gap_mm
from visemeflow.animation.surface import preview_scene
from visemeflow.articulation import CLOSED_MM
from visemeflow.atomic import atomic_path
from visemeflow.render.raster import Camera, Pose, frontal_pose, render_backdrop, render_mesh
from visemeflow.timebase import frame_count
from visemeflow.tracking.landmarks import LandmarkError, LandmarkTrack, mouth_keypoint_ids, read_landmarks
from visemeflow.tracking.video import VideoError, iter_timed_frames

if TYPE_CHECKING:
    from visemeflow.animation.bones import BoneRig

__all__ = ["BoneSource", "PreviewFrames", "PreviewReport", "TextPainter", "VideoSource", "preview_camera",
           "render_preview", "video_problem", "video_source"]

log = logging.getLogger(__name__)

BAND_COLOR = (24, 25, 30)
TEXT_COLOR = (235, 235, 240)
CAPTION_COLOR = (255, 214, 120)
CLOSED_COLOR = (120, 230, 140)
OPEN_AT_CLOSURE_COLOR = (255, 90, 90)
FRAMINGS = ("mouth", "face")
_MOVING_FRACTION = 0.1
"""`framing="mouth"` frames the vertices that some shape moves by at least this fraction of the largest move."""
_FILL = 0.86
_FOV_DEG = 18.0
_AUDIO_RATES_PREFERRED = (48000, 44100)
_AUDIO_BIT_RATE = 96_000
VIDEO_LABEL = "video"
LANDMARK_COLOR = (80, 220, 255)
_LOWER_FACE_POINTS = np.r_[2:15, 31:36, 48:68]
"""68-point ids of the lower face (jaw from cheek to cheek, the nose's base, the lips): what `framing="mouth"` crops."""
_GAP_DIM = 0.5
"""Brightness of the video panel where no decoded frame lies within half a frame step (the nearest is shown)."""
_CROP_PERCENTILES = (1.0, 99.0)
"""The crop spans these percentiles of the landmarks' x and y over the clip, so a few stray detections do not
widen it."""


@dataclass(frozen=True)
class PreviewReport:
    """What `render_preview` wrote and how fast."""

    path: Path
    frames: int
    fps: Fraction
    width: int
    height: int
    seconds_render: float
    """Wall-clock seconds of the whole call: deforming, rendering, text, encoding and writing."""
    frames_per_second: float
    """frames / seconds_render."""
    replaced_characters: str = ""
    """Characters of the title, labels or phones that no available font could draw (shown as "�" or "?")."""
    video_problem: str = ""
    """Why the video panel shows a message instead of (some of) the source video's frames; "" when it shows them
    all, or there is no video panel."""


# ----------------------------------------------------------------------------------------------------------- text

_PRIMARY_FONTS = ("DejaVuSans.ttf", "LiberationSans-Regular.ttf", "FreeSans.ttf")
_CJK_FONTS = (
    "NotoSansCJK-Regular.ttc", "NotoSansCJKsc-Regular.otf", "NotoSansSC-Regular.otf", "NotoSansCJKSC-Regular.otf",
    "SourceHanSansSC-Regular.otf", "SourceHanSans-Regular.ttc", "wqy-microhei.ttc", "wqy-zenhei.ttc",
    "DroidSansFallbackFull.ttf", "DroidSansFallback.ttf", "uming.ttc", "ukai.ttc", "arphic/uming.ttc",
)
_MISSING_SENTINEL = "\U0010fffd"  # a private-use code point no font maps: what a missing glyph looks like
_REPLACEMENT = "\ufffd"


def _bundled_dejavu() -> str | None:
    """matplotlib's own copy of DejaVu Sans (located without importing matplotlib), if installed."""
    spec = importlib.util.find_spec("matplotlib")
    if spec is None or not spec.submodule_search_locations:
        return None
    for folder in spec.submodule_search_locations:
        candidate = Path(folder) / "mpl-data" / "fonts" / "ttf" / "DejaVuSans.ttf"
        if candidate.is_file():
            return str(candidate)
    return None


@functools.lru_cache(maxsize=16)
def _pil_fonts(px: int) -> tuple:
    """TrueType fonts at `px` pixels, the primary (Latin/IPA) one first, then any CJK font found; () if none."""
    from PIL import ImageFont

    fonts = []
    primaries = list(_PRIMARY_FONTS)
    bundled = _bundled_dejavu()
    if bundled:
        primaries.append(bundled)
    for name in primaries:
        try:
            fonts.append(ImageFont.truetype(name, px))  # a bare name is searched in the system's font folders
            break
        except OSError:
            continue
    for name in _CJK_FONTS:
        try:
            fonts.append(ImageFont.truetype(name, px))
            break
        except OSError:
            continue
    if not fonts:
        try:
            fonts.append(ImageFont.load_default(px))  # Pillow's built-in font (Latin only)
        except (TypeError, OSError):
            return ()
    return tuple(fonts)


def _pil_available() -> bool:
    return importlib.util.find_spec("PIL") is not None


class TextPainter:
    """Draws one line of text into a band image, with the fallbacks of the module doc.

    `use_pil=None` uses Pillow when it is installed; False forces the cv2 (ASCII-only) path. `replaced` collects
    the characters that could not be drawn. Bands are cached by (text, size, colour, alignment).
    """

    def __init__(self, px: int, use_pil: bool | None = None):
        self.px = int(px)
        fonts = _pil_fonts(self.px) if (use_pil is None and _pil_available()) or use_pil else ()
        if use_pil and not fonts:
            raise RuntimeError("Pillow with a usable font is not available")
        self.fonts = fonts
        self.replaced: set[str] = set()
        self._glyph: dict[tuple[int, str], bool] = {}
        self._missing = [self._mask_key(font, _MISSING_SENTINEL) for font in self.fonts]
        self._cache: dict[tuple, np.ndarray] = {}

    @property
    def uses_pil(self) -> bool:
        return bool(self.fonts)

    @staticmethod
    def _mask_key(font, text: str) -> tuple:
        mask = font.getmask(text)
        return mask.size, bytes(mask)

    def _font_for(self, ch: str) -> int | None:
        """Index of the first font with a glyph for `ch`, or None."""
        for i, font in enumerate(self.fonts):
            key = (i, ch)
            if key not in self._glyph:
                self._glyph[key] = ch.isspace() or self._mask_key(font, ch) != self._missing[i]
            if self._glyph[key]:
                return i
        return None

    def _runs(self, text: str) -> list[tuple[int, str]]:
        """(font index, text) runs covering `text`, missing characters replaced by U+FFFD (or "?")."""
        runs: list[tuple[int, str]] = []
        for ch in unicodedata.normalize("NFC", text):
            if unicodedata.category(ch) in ("Cc", "Cf"):
                continue
            index = self._font_for(ch)
            if index is None:
                self.replaced.add(ch)
                index, ch = 0, (_REPLACEMENT if self._font_for(_REPLACEMENT) == 0 else "?")
            if runs and runs[-1][0] == index:
                runs[-1] = (index, runs[-1][1] + ch)
            else:
                runs.append((index, ch))
        return runs

    def ascii_text(self, text: str) -> str:
        """The cv2 path's text: printable ASCII kept, every other character "?" (and recorded as replaced)."""
        out = []
        for ch in unicodedata.normalize("NFC", text):
            if 32 <= ord(ch) < 127:
                out.append(ch)
            elif unicodedata.category(ch) not in ("Cc", "Cf"):
                self.replaced.add(ch)
                out.append("?")
        return "".join(out)

    def band(self, text: str, width: int, height: int, color=TEXT_COLOR, align: str = "center",
             background=BAND_COLOR) -> np.ndarray:
        """(height, width, 3) uint8 RGB: `text` on one line, vertically centred, cut with "..." when too wide."""
        key = (text, width, height, tuple(color), align, tuple(background))
        if key not in self._cache:
            image = np.empty((height, width, 3), np.uint8)
            image[:] = np.asarray(background, np.uint8)
            if text:
                (self._draw_pil if self.fonts else self._draw_cv2)(image, text, color, align)
            image.flags.writeable = False
            self._cache[key] = image
        return self._cache[key]

    def _draw_pil(self, image: np.ndarray, text: str, color, align: str) -> None:
        from PIL import Image, ImageDraw

        pad = max(2, self.px // 3)
        runs = self._runs(text)

        def width_of(rs) -> float:
            return sum(self.fonts[i].getlength(s) for i, s in rs)

        if width_of(runs) > image.shape[1] - 2 * pad:
            ellipsis = (0, "...")
            while runs and width_of(runs) + width_of([ellipsis]) > image.shape[1] - 2 * pad:
                i, s = runs[-1]
                runs = runs[:-1] + ([(i, s[:-1])] if len(s) > 1 else [])
            runs = runs + [ellipsis]
        total = width_of(runs)
        x = pad if align == "left" else (image.shape[1] - total) / 2.0
        y = image.shape[0] / 2.0
        canvas = Image.fromarray(image)
        draw = ImageDraw.Draw(canvas)
        for i, s in runs:
            # anchor "lm": x at the left, y at the middle of the primary font's ascender..descender
            draw.text((x, y), s, font=self.fonts[i], fill=tuple(int(c) for c in color), anchor="lm")
            x += self.fonts[i].getlength(s)
        image[:] = np.asarray(canvas)

    def _draw_cv2(self, image: np.ndarray, text: str, color, align: str) -> None:
        font, thickness = cv2.FONT_HERSHEY_SIMPLEX, 1
        scale = self.px / 24.0
        pad = max(2, self.px // 3)
        line = self.ascii_text(text)

        def width_of(s: str) -> int:
            return cv2.getTextSize(s, font, scale, thickness)[0][0]

        if width_of(line) > image.shape[1] - 2 * pad:
            while line and width_of(line + "...") > image.shape[1] - 2 * pad:
                line = line[:-1]
            line += "..."
        (w, h), _ = cv2.getTextSize(line, font, scale, thickness)
        x = pad if align == "left" else (image.shape[1] - w) // 2
        y = (image.shape[0] + h) // 2
        cv2.putText(image, line, (int(x), int(y)), font, scale, tuple(int(c) for c in color), thickness, cv2.LINE_AA)


# --------------------------------------------------------------------------------------------------------- camera

def preview_camera(character: Character, size: int, framing: str = "mouth") -> tuple[Camera, Pose]:
    """The fixed camera and frontal pose of a character's panels (`size` x `size` pixels).

    "face": the whole neutral mesh; "mouth": the vertices some shape moves by at least 10 % of the largest move
    (all vertices when no shape moves any). The framed box is made square (its larger side spans 86 % of the
    panel), so wide and tall regions both fit.
    """
    if framing not in FRAMINGS:
        raise ValueError(f"framing must be one of {FRAMINGS}, got {framing!r}")
    points = np.asarray(character.neutral, np.float64)
    if framing == "mouth":
        moves = np.sqrt((np.asarray(character.deltas, np.float64) ** 2).sum(axis=2)).max(axis=0)
        if moves.max() > 0:
            points = points[moves >= _MOVING_FRACTION * moves.max()]
    low, high = points.min(axis=0), points.max(axis=0)
    centre = (low + high) / 2.0
    half = max(float(high[0] - low[0]), float(high[1] - low[1]), 1e-6) / 2.0
    box = np.array([[centre[0] + sx * half, centre[1] + sy * half, z]
                    for sx in (-1, 1) for sy in (-1, 1) for z in (low[2], high[2])])
    camera = Camera.from_fov(size, size, _FOV_DEG)
    return camera, frontal_pose(box, camera, fill=_FILL)


# ------------------------------------------------------------------------------------------------------ validation

def _as_fps(fps) -> Fraction:
    if isinstance(fps, bool) or not isinstance(fps, (int, float, Fraction, np.integer, np.floating)):
        raise ValueError(f"fps must be a positive number, got {fps!r}")
    if not (math.isfinite(float(fps)) and float(fps) > 0):
        raise ValueError(f"fps must be a positive number, got {fps!r}")
    rate = fps if isinstance(fps, Fraction) else Fraction(float(fps)).limit_denominator(1001)
    if rate <= 0:
        raise ValueError(f"fps must be a positive number, got {fps!r}")
    return rate


@dataclass(frozen=True)
class BoneSource:
    """A panel moved by bones rather than blendshapes: `rig`'s poses blended by (T, P) `curves` (one column per
    pose, in `rig.pose_names` order, e.g. the 16 viseme curves), then linear blend skinning (`bones.bone_animation`).
    The rig must be of the previewed character's mesh (same vertex count)."""

    rig: BoneRig
    curves: np.ndarray


@dataclass(frozen=True)
class _Panel:
    label: str
    rows: np.ndarray
    """(T, C) float32: what drives the panel per frame (shape weights, or the bone rig's pose curves)."""
    rig: BoneRig | None = None

    def vertices(self, neutral: np.ndarray, deltas: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(len(rows), V * 3) float32 vertices of the panel for these rows."""
        if self.rig is None:
            return neutral + rows @ deltas
        from visemeflow.animation.bones import bone_animation

        return bone_animation(self.rig, rows).reshape(len(rows), -1).astype(np.float32)


def _check_rows(where: str, label: str, values, columns: tuple[str, ...], what: str) -> np.ndarray:
    w = np.asarray(values)
    if w.ndim != 2 or w.shape[1] != len(columns):
        raise ValueError(f"{where}: source {label!r} has {what} of shape {w.shape}; expected (T, {len(columns)}), "
                         f"one column per {'pose of the bone rig' if what == 'curves' else 'shape of the character'} "
                         f"({', '.join(columns)})")
    if w.shape[0] == 0:
        raise ValueError(f"{where}: source {label!r} has no frames")
    if not np.issubdtype(w.dtype, np.number) or np.iscomplexobj(w):
        raise ValueError(f"{where}: source {label!r} {what} must be real numbers, got {w.dtype}")
    w = np.ascontiguousarray(w, np.float32)
    finite = np.isfinite(w)
    if not finite.all():
        row, col = (int(i) for i in np.argwhere(~finite)[0])
        raise ValueError(f"{where}: source {label!r} has a NaN or infinite {what[:-1]} (first at frame {row}, "
                         f"{'pose' if what == 'curves' else 'shape'} {columns[col]!r})")
    return w


def _check_sources(character: Character, sources: Mapping[str, object]) -> list[_Panel]:
    where = character.where()
    if not isinstance(sources, Mapping) or not sources:
        raise ValueError(f"{where}: no curve sources to preview; give an ordered dict label -> (T, S) weights")
    checked = []
    for label, source in sources.items():
        if not isinstance(label, str):
            raise ValueError(f"{where}: source labels must be strings, got {label!r}")
        if isinstance(source, BoneSource):
            rig = source.rig
            if rig.n_vertices != character.n_vertices:
                raise ValueError(f"{where}: source {label!r} is a bone rig of {rig.name!r} with {rig.n_vertices} "
                                 f"vertices, not of this character ({character.n_vertices} vertices)")
            checked.append(_Panel(label, _check_rows(where, label, source.curves, tuple(rig.pose_names), "curves"),
                                  rig))
        else:
            checked.append(_Panel(label, _check_rows(where, label, source, tuple(character.shape_names),
                                                     "weights")))
    return checked


def _check_audio(audio) -> tuple[np.ndarray, int] | None:
    if audio is None:
        return None
    try:
        samples, rate = audio
    except (TypeError, ValueError):
        raise ValueError("audio must be a (samples, sample_rate) pair") from None
    samples = np.asarray(samples)
    if samples.ndim == 2 and samples.shape[1] == 1:
        samples = samples[:, 0]
    if samples.ndim != 1:
        raise ValueError(f"audio samples must be mono, shape (N,), got {samples.shape}")
    if not np.issubdtype(samples.dtype, np.floating):
        raise ValueError(f"audio samples must be float (in [-1, 1]), got {samples.dtype}")
    if isinstance(rate, bool) or not float(rate).is_integer() or int(rate) <= 0:
        raise ValueError(f"audio sample rate must be a positive whole number of Hz, got {rate!r}")
    samples = np.ascontiguousarray(samples, np.float32)
    if not np.isfinite(samples).all():
        raise ValueError(f"audio has NaN or infinite samples (first at sample {int(np.argmin(np.isfinite(samples)))})")
    return samples, int(rate)


def _check_phones(phones) -> tuple[list[float], list[float], list[str]]:
    if phones is None:
        return [], [], []
    rows = []
    for i, item in enumerate(phones):
        try:
            start, end, label = item
            start, end = float(start), float(end)
        except (TypeError, ValueError):
            raise ValueError(f"phone {i}: expected (start_s, end_s, label), got {item!r}") from None
        if not (math.isfinite(start) and math.isfinite(end) and end >= start):
            raise ValueError(f"phone {i} ({label!r}): needs finite times with end >= start, got {start}..{end}")
        rows.append((start, end, str(label).strip()))
    rows.sort(key=lambda r: r[0])
    return [r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows]


def _phone_at(t: float, starts: list[float], ends: list[float], labels: list[str]) -> str:
    """The label of the latest phone starting at or before t, if it is still under way at t; "" otherwise."""
    i = bisect.bisect_right(starts, t) - 1
    return labels[i] if i >= 0 and t < ends[i] else ""


def _audio_rate_for_encoder(rate: int) -> int:
    """`rate` when the AAC encoder takes it, else 48 kHz (or 44.1 kHz)."""
    supported = av.codec.Codec("aac", "w").audio_rates or ()
    if not supported or rate in supported:
        return rate
    return next((r for r in _AUDIO_RATES_PREFERRED if r in supported), max(supported))


def _even_band(px: float) -> int:
    return int(2 * math.ceil(px / 2.0))


# ---------------------------------------------------------------------------------------------------------- video

@dataclass(frozen=True)
class VideoSource:
    """The source video shown as the first panel: its file (None: the utterance has none that can be found) and the
    tracker's landmarks, one row per decoded frame in decode order (None: crop the frame's central square, no
    overlay). `overlay`: draw the landmarks of the mouth (48-67) on the crop."""

    path: str | os.PathLike | None
    landmarks: LandmarkTrack | None = None
    overlay: bool = True


def video_source(video_path: str | os.PathLike | None, landmark_path: str | os.PathLike | None,
                 fps: float | None = None, overlay: bool = True) -> VideoSource:
    """A `VideoSource` from an utterance's files; a landmark file that cannot be read is logged and left out (the
    panel still shows the video, centre-cropped), since the preview must render whatever the tracking left."""
    landmarks = None
    if landmark_path:
        try:
            landmarks = read_landmarks(landmark_path, fps=fps)
        except (LandmarkError, OSError) as exc:
            log.warning("%s: landmarks not read for the preview's video panel: %s", landmark_path, exc)
    return VideoSource(video_path, landmarks, overlay)


def video_problem(path: str | os.PathLike | None) -> str | None:
    """Why the video at `path` cannot be shown ("no video file", "video not found: <path>", "video unreadable:
    <path>: <reason>"); None when its first frame decodes (only that frame is decoded)."""
    if not path:
        return "no video file"
    path = Path(path)
    if not path.is_file():
        return f"video not found: {path}"
    frames = iter_timed_frames(path)
    try:
        next(frames)
    except (VideoError, OSError, av.FFmpegError) as exc:
        return f"video unreadable: {_naming(path, exc)}"
    finally:
        frames.close()
    return None


def _naming(path: Path, exc: BaseException) -> str:
    """The error's message, starting with the file's name unless it names it already."""
    return str(exc) if str(path) in str(exc) else f"{path}: {exc}"


def _crop_square(landmarks: LandmarkTrack | None, framing: str) -> tuple[float, float, float] | None:
    """(centre x, centre y, side) in video pixels of the fixed face crop; None without any usable landmark."""
    if landmarks is None:
        return None
    ids = _LOWER_FACE_POINTS if framing == "mouth" else np.arange(landmarks.points.shape[1])
    points = landmarks.points[:, ids][landmarks.valid[:, ids]]
    if len(points) == 0:
        return None
    low, high = np.percentile(points, _CROP_PERCENTILES, axis=0)
    centre = (low + high) / 2.0
    side = max(float(high[0] - low[0]), float(high[1] - low[1]), 1.0) / _FILL
    return float(centre[0]), float(centre[1]), side


def _nearest_frames(path: Path, rate: Fraction, n: int):
    """(image, decoded frame index, within) for each grid frame k < n, streamed: the decoded frame nearest k / rate
    (ties go to the earlier) and whether it lies within half a step, i.e. is the frame the tracker used
    (`FrameTimeline.video_frame`'s rule; its index is -1 where not). VideoError (or OSError, av's errors) propagate
    from the decoder."""
    frames = iter_timed_frames(path)
    half = 0.5 / float(rate)
    before = None                        # (image, time, index): the latest frame at or before the grid time
    after = next(frames, None)           # the first frame after it
    after = None if after is None else (after[0], after[1], 0)
    for k in range(n):
        t = k / float(rate)
        while after is not None and after[1] <= t:
            before = after
            item = next(frames, None)
            after = None if item is None else (item[0], item[1], before[2] + 1)
        best = min((c for c in (before, after) if c is not None), key=lambda c: (abs(c[1] - t), c[1]))
        yield best[0], best[2], abs(best[1] - t) < half


class _VideoPanel:
    """Draws the video panel's frames: the fixed face crop scaled to `size`, the mouth landmarks on it."""

    def __init__(self, source: VideoSource, size: int, framing: str, painter: TextPainter):
        self.source, self.size, self.painter = source, size, painter
        self.square = _crop_square(source.landmarks, framing)
        self.mouth = mouth_keypoint_ids()
        self.problem = ""
        """Why the panel shows a message instead of (some) frames; "" while it shows them."""

    def box(self, height: int, width: int) -> tuple[int, int, int]:
        """(left, top, side) in whole pixels of the crop in a `height` x `width` frame (may reach past its edges)."""
        if self.square is None:
            side = min(height, width)
            return (width - side) // 2, (height - side) // 2, side
        cx, cy, side = self.square
        side = max(2, int(round(side)))
        return int(round(cx - side / 2.0)), int(round(cy - side / 2.0)), side

    def crop(self, image: np.ndarray) -> np.ndarray:
        """(size, size, 3) uint8: the crop of one decoded frame (black beyond the frame's edges), scaled."""
        left, top, side = self.box(*image.shape[:2])
        square = np.zeros((side, side, 3), np.uint8)
        y0, y1 = max(top, 0), min(top + side, image.shape[0])
        x0, x1 = max(left, 0), min(left + side, image.shape[1])
        if y1 > y0 and x1 > x0:
            square[y0 - top:y1 - top, x0 - left:x1 - left] = image[y0:y1, x0:x1]
        shrink = side > self.size
        return cv2.resize(square, (self.size, self.size), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)

    def draw(self, image: np.ndarray, index: int) -> np.ndarray:
        panel = self.crop(image)
        track = self.source.landmarks
        if self.source.overlay and track is not None and 0 <= index < track.n_frames:
            left, top, side = self.box(*image.shape[:2])
            scale = self.size / side
            radius = max(1, self.size // 180)
            for point, ok in zip(track.points[index, self.mouth], track.valid[index, self.mouth]):
                if ok:
                    x, y = (point[0] - left + 0.5) * scale - 0.5, (point[1] - top + 0.5) * scale - 0.5
                    cv2.circle(panel, (int(round(x)), int(round(y))), radius, LANDMARK_COLOR, -1, cv2.LINE_AA)
        return panel

    def message(self, text: str) -> np.ndarray:
        """A panel that says why there is no picture."""
        return self.painter.band(text, self.size, self.size)

    def frames(self, rate: Fraction, n: int):
        """The panel for each of the n preview frames, streamed; a message panel where there is no picture."""
        path = self.source.path
        if not path:
            self.problem = "no video file"
            yield from (self.message("no video file") for _ in range(n))
            return
        path = Path(path)
        if not path.is_file():
            log.warning("%s: the preview's video panel has no video (file not found)", path)
            self.problem = f"video not found: {path}"
            yield from (self.message("video not found") for _ in range(n))
            return
        k = 0
        try:
            for image, index, within in _nearest_frames(path, rate, n):
                # a variable-rate clip's gap (the tracker interpolated the curves there): the nearest frame, dimmed
                # and without landmarks, rather than a blank panel that would flicker in and out
                yield self.draw(image, index) if within else (self.crop(image) * _GAP_DIM).astype(np.uint8)
                k += 1
        except (VideoError, OSError, av.FFmpegError) as exc:
            log.warning("%s: the preview's video panel stops at frame %d: %s", path, k, exc)
            self.problem = f"video unreadable from preview frame {k} on: {_naming(path, exc)}"
            yield from (self.message("video unreadable") for _ in range(n - k))


# ----------------------------------------------------------------------------------------------------------- main

class PreviewFrames:
    """The preview's frames, composed one at a time (no encoding): layout, panels, labels, caption.

    Arguments as `render_preview` (validated here, errors naming the character and the source); `n_frames`
    extends the video beyond the longest source (e.g. to the audio's length); `video` adds the source video's
    panel first (see the module doc). Iterating yields the same (height, width, 3) uint8 RGB array every time,
    overwritten in place: copy a frame to keep it.
    """

    def __init__(self, character: Character, sources: Mapping[str, np.ndarray | BoneSource], fps, *,
                 phones: Sequence[tuple[float, float, str]] | None = None, title: str | None = None,
                 size: int = 360, chunk_frames: int = 64, framing: str = "mouth", n_frames: int = 0,
                 painter: TextPainter | None = None, video: VideoSource | None = None):
        self.rate = _as_fps(fps)
        self.character = character
        self.sources = _check_sources(character, sources)
        self._starts, self._ends, self._phones = _check_phones(phones)
        if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 16 or size % 2:
            raise ValueError(f"size must be an even number of pixels >= 16 (H.264 4:2:0 needs even sizes), "
                             f"got {size!r}")
        if isinstance(chunk_frames, bool) or not isinstance(chunk_frames, (int, np.integer)) or chunk_frames < 1:
            raise ValueError(f"chunk_frames must be a positive integer, got {chunk_frames!r}")
        if title is not None and not isinstance(title, str):
            raise ValueError(f"title must be text, got {title!r}")
        self.size, self.chunk_frames, self.title = int(size), int(chunk_frames), title
        self.camera, self.pose = preview_camera(character, self.size, framing)
        # a glTF character's whole scene: its other meshes, their materials and base-colour textures (its skin and
        # hair, not a grey head alone)
        self.scene, notes = preview_scene(character)
        static = self.scene.static
        self.backdrop = None if static is None else render_backdrop(static.vertices, static.faces, None, self.camera,
                                                                    self.pose, texture=static.texture)
        for note in notes:
            log.warning("preview of %s: %s", character.label, note)
        self.frames = max(int(n_frames), max(panel.rows.shape[0] for panel in self.sources))

        # layout: [title band] label band, panels, [caption band]; every band an even number of rows
        px = max(10, round(self.size * 0.05))
        band = _even_band(px * 1.8)
        self.painter = painter or TextPainter(px)
        if video is not None and not isinstance(video, VideoSource):
            raise ValueError(f"video must be a VideoSource, got {video!r}")
        self.video = None if video is None else _VideoPanel(video, self.size, framing, self.painter)
        self.first_rig = 0 if video is None else 1
        """Panel index of the first source's panel (1 after the video panel)."""
        self.n_panels = len(self.sources) + self.first_rig
        self.width = self.n_panels * self.size
        self.title_height = band if title else 0
        self.label_height = band
        self.caption_height = band if phones is not None else 0
        self.lip_pairs = inner_lip_pairs(character)
        if self.lip_pairs is None:
            log.warning("preview of %s: no lip gap under the panels: it has no landmarks and no mouth was found in its "
                        "mesh (a slit its widest viseme opens); check a b/p/m frame by eye", character.label)
        self.lip_height = band if self.lip_pairs is not None else 0
        self.panel_top = self.title_height + self.label_height
        self.caption_top = self.panel_top + self.size
        self.lip_top = self.caption_top + self.caption_height
        self.height = self.lip_top + self.lip_height

    def panel_box(self, k: int) -> tuple[slice, slice]:
        """(rows, columns) of panel k in a frame."""
        return slice(self.panel_top, self.caption_top), slice(k * self.size, (k + 1) * self.size)

    def caption_box(self) -> tuple[slice, slice]:
        """(rows, columns) of the caption band (empty when there are no phones)."""
        return slice(self.caption_top, self.lip_top), slice(0, self.width)

    def lip_box(self, k: int) -> tuple[slice, slice]:
        """(rows, columns) of panel k's lip readout (empty when the character has no inner-lip landmarks)."""
        return slice(self.lip_top, self.height), slice(k * self.size, (k + 1) * self.size)

    def lip_gap_mm(self, vertices: np.ndarray) -> float:
        """The inner-lip gap (mm) of one frame's (V, 3) vertices."""
        return float(pair_gap_mm(vertices[self.lip_pairs], self.character.mm_per_unit))

    def label_box(self, k: int) -> tuple[slice, slice]:
        return slice(self.title_height, self.panel_top), slice(k * self.size, (k + 1) * self.size)

    def title_box(self) -> tuple[slice, slice]:
        return slice(0, self.title_height), slice(0, self.width)

    def phone_at(self, frame: int) -> str:
        """The caption of `frame`: the phone under way at frame / fps ("" in gaps)."""
        return _phone_at(frame / float(self.rate), self._starts, self._ends, self._phones)

    def __len__(self) -> int:
        return self.frames

    def __iter__(self):
        character, size, n, off = self.character, self.size, len(self.sources), self.first_rig
        canvas = np.empty((self.height, self.width, 3), np.uint8)
        if self.title_height:
            canvas[self.title_box()] = self.painter.band(self.title, self.width, self.title_height)
        for k, panel in enumerate(self.sources):
            canvas[self.label_box(k + off)] = self.painter.band(panel.label, size, self.label_height)
        video = None
        if self.video is not None:
            canvas[self.label_box(0)] = self.painter.band(VIDEO_LABEL, size, self.label_height)
            if self.lip_height:
                canvas[self.lip_box(0)] = self.painter.band("", size, self.lip_height)
            video = self.video.frames(self.rate, self.frames)
        deltas = np.ascontiguousarray(character.deltas, np.float32).reshape(character.n_shapes, -1)
        neutral = np.ascontiguousarray(character.neutral, np.float32).reshape(1, -1)
        shown: list[np.ndarray | None] = [None] * n  # the weights row each panel shows now
        readouts: list[tuple | None] = [None] * n     # the lip text and colour each panel shows now
        caption = None
        for start in range(0, self.frames, self.chunk_frames):
            stop = min(self.frames, start + self.chunk_frames)
            # a shorter source holds its last row
            rows = [p.rows[np.minimum(np.arange(start, stop), p.rows.shape[0] - 1)] for p in self.sources]
            # (chunk, V * 3) per source: the bounded memory
            vertices = [p.vertices(neutral, deltas, r) for p, r in zip(self.sources, rows)]
            for i in range(start, stop):
                if video is not None:
                    canvas[self.panel_box(0)] = next(video)
                for k in range(n):
                    row = rows[k][i - start]
                    if shown[k] is not None and np.array_equal(row, shown[k]):
                        continue  # unchanged: the canvas already shows it
                    box = self.panel_box(k + off)
                    twin = next((j for j in range(k) if self.sources[j].rig is self.sources[k].rig
                                 and np.array_equal(row, rows[j][i - start])), None)
                    if twin is not None:
                        canvas[box] = canvas[self.panel_box(twin + off)]
                    else:
                        scene = self.scene
                        canvas[box] = render_mesh(scene.vertices(vertices[k][i - start].reshape(-1, 3)),
                                                  scene.faces, scene.colors, self.camera, self.pose,
                                                  texture=scene.texture, backdrop=self.backdrop)
                    shown[k] = row
                if self.lip_height:
                    phone = self.phone_at(i)
                    for k in range(n):
                        gap = self.lip_gap_mm(vertices[k][i - start].reshape(-1, 3))
                        color = CLOSED_COLOR if gap < CLOSED_MM else \
                            OPEN_AT_CLOSURE_COLOR if is_bilabial(phone) else TEXT_COLOR
                        readout = (f"{phone + '  ' if phone else ''}lips {gap:.1f} mm", color)
                        if readout != readouts[k]:
                            canvas[self.lip_box(k + off)] = self.painter.band(readout[0], size, self.lip_height, color)
                            readouts[k] = readout
                if self.caption_height:
                    text = self.phone_at(i)
                    if text != caption:
                        canvas[self.caption_box()] = self.painter.band(text, self.width, self.caption_height,
                                                                       CAPTION_COLOR)
                        caption = text
                yield canvas


def render_preview(
    path: str | os.PathLike,
    character: Character,
    sources: Mapping[str, np.ndarray | BoneSource],
    fps,
    *,
    audio: tuple[np.ndarray, int] | None = None,
    phones: Sequence[tuple[float, float, str]] | None = None,
    title: str | None = None,
    size: int = 360,
    chunk_frames: int = 64,
    framing: str = "mouth",
    crf: int = 23,
    video: VideoSource | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> PreviewReport:
    """Write an H.264 + AAC `.mp4` preview of `character` driven by each source, side by side (see the module doc).

    sources: ordered mapping label -> (T_i, S) weights in `character.shape_names` order, or a `BoneSource` (a bone
        rig of the character and its (T_i, P) pose curves); one `size` x `size` panel per source, left to right in
        the mapping's order, its label above it. Weights are used as given (no clip).
    fps: frames per second (int, float or Fraction; a float is read as the nearest fraction with denominator
        <= 1001, so 29.97 stays 2997/100 and 30000/1001 can be given as a Fraction).
    audio: optional (samples float mono, sample_rate), muxed as AAC at its own rate when the encoder takes it
        (else resampled to 48 kHz); padded with silence to the video's length when the curves run longer.
    phones: optional (start_s, end_s, label) intervals; frame k's caption is the label of the phone under way at
        k / fps, empty in gaps. Labels are written as given: drop silence intervals beforehand if "sil" should
        not show (`visemeflow.phonetics.inventory.is_silence`).
    title: optional text on a band above the labels.
    size: even panel side in pixels; the video is (n_sources * size) wide, with no margins.
    chunk_frames: frames deformed at once (memory: chunk_frames x vertices x 12 bytes per source).
    framing: "mouth" (the moving region, default) or "face" (the whole neutral mesh); see `preview_camera`.
    crf: libx264 quality (lower: better and larger).
    video: optional `VideoSource`: the source video's face crop as the first panel, labelled "video" (see the
        module doc); a missing or unreadable video gives a panel that says so.
    progress: optional callback ("preview", frames written, frames in all) after each frame.

    Frames: the longest source's length or round(audio seconds x fps), whichever is larger; a shorter source
    holds its last frame to the end. Written atomically: a failure leaves no file and keeps an older one.
    Raises ValueError (naming the character and the source) for weights of the wrong width, non-finite weights,
    no sources, fps <= 0, an odd size, bad audio or phones, a path not ending in .mp4.
    """
    started = time.perf_counter()
    path = Path(path)
    if path.suffix.lower() != ".mp4":
        raise ValueError(f"{path}: the preview is an MP4 video; give a path ending in .mp4")
    rate = _as_fps(fps)
    sound = _check_audio(audio)
    audio_frames = frame_count(sound[0].size / sound[1], float(rate)) if sound is not None and sound[0].size else 0
    frames = PreviewFrames(character, sources, rate, phones=phones, title=title, size=size,
                           chunk_frames=chunk_frames, framing=framing, n_frames=audio_frames, video=video)
    n_frames = frames.frames

    with atomic_path(path, keep_suffix=True) as tmp:
        container = av.open(str(tmp), mode="w", format="mp4", options={"movflags": "+faststart"})
        try:
            video = container.add_stream("libx264", rate=rate)
            video.width, video.height, video.pix_fmt = frames.width, frames.height, "yuv420p"
            video.codec_context.time_base = 1 / rate
            video.options = {"crf": str(int(crf)), "preset": "medium"}
            audio_stream, audio_pos, n_audio = None, 0, 0
            if sound is not None:
                samples, sample_rate = sound
                audio_stream = container.add_stream("aac", rate=_audio_rate_for_encoder(sample_rate), layout="mono")
                audio_stream.bit_rate = _AUDIO_BIT_RATE
                # silence after the audio up to the video's end, so both streams last as long
                n_audio = max(samples.size, int(round(n_frames / rate * sample_rate)))

            def push_audio(upto: int) -> None:
                nonlocal audio_pos
                upto = min(upto, n_audio)
                while audio_pos < upto:
                    stop = min(upto, audio_pos + 8192)
                    chunk = np.zeros(stop - audio_pos, np.float32)
                    have = max(0, min(stop, samples.size) - audio_pos)
                    chunk[:have] = samples[audio_pos:audio_pos + have]
                    frame = av.AudioFrame.from_ndarray(chunk[None, :], format="fltp", layout="mono")
                    frame.sample_rate = sample_rate
                    frame.pts = audio_pos
                    frame.time_base = Fraction(1, sample_rate)
                    container.mux(audio_stream.encode(frame))
                    audio_pos = stop

            for i, canvas in enumerate(frames):
                frame = av.VideoFrame.from_ndarray(canvas, format="rgb24")
                frame.pts = i
                container.mux(video.encode(frame))
                if audio_stream is not None and (i + 1) % 16 == 0:  # interleave: audio up to the video's time
                    push_audio(int(round((i + 1) / rate * sample_rate)))
                if progress is not None:   # a long file says where it is (`tasks.progress.StepLog`)
                    progress("preview", i + 1, n_frames)
            container.mux(video.encode(None))
            if audio_stream is not None:
                push_audio(n_audio)
                container.mux(audio_stream.encode(None))
        finally:
            container.close()

    seconds = time.perf_counter() - started
    replaced = "".join(sorted(frames.painter.replaced))
    if replaced:
        log.info("%s: no font for %r in the preview's text; drawn as replacement marks", path, replaced)
    return PreviewReport(path, n_frames, rate, frames.width, frames.height, seconds,
                         n_frames / seconds if seconds > 0 else 0.0, replaced,
                         frames.video.problem if frames.video is not None else "")
