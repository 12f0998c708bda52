"""Dense optical flow between consecutive video frames and the optical-flow loss L_flow of Eq. 6 (section 4.3).

For each frame j the tracker needs the bi-directional flow between frames j-1 and j and the correspondences that
survive a forward-backward consistency check [Bao et al. 2014]. Eq. 6 then pulls the projection of a vertex in
frame j toward where the flow carries its projection in frame j-1:

    L_flow(X^j) = 1/|K| sum_{k in K} || Proj(s_k^j) - (Proj(s_k^{j-1}) + u_k) ||^2

The flow is OpenCV's DIS (Dense Inverse Search, ``cv2.DISOpticalFlow_create``), computed once per utterance by
:func:`estimate_optical_flow` and kept in a :class:`FlowField`, which answers the correspondence queries of both the forward
pass (flow j-1 -> j) and the backward pass (flow j+1 -> j) of the tracker.

Conventions (those of `visemeflow.render.camera`): points are (x, y) pixel coordinates, x to the right and y
down, pixel centres at integers, so a W x H image covers x in [0, W-1] and y in [0, H-1] for sampling. A flow is an
(H, W, 2) float array whose [y, x] entry is the (dx, dy) displacement of the pixel centre (x, y). Frames are RGB
uint8 (H, W, 3); DIS works on one 8-bit channel, so they are converted to luma first.

Region of interest: the tracker only needs the face, so every flow function takes an optional ``roi`` (x0, y0, w, h)
in full-image pixels (clipped to the image). The flow is then computed on that crop only: the returned array is
(h, w, 2), its [y, x] entry belongs to the full-image pixel (x0 + x, y0 + y), and the displacements are in
full-image pixels (a crop is not rescaled, so a displacement means the same in both). :class:`FlowField` takes and
returns full-image coordinates and treats points outside the ROI as invalid.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np
import torch

Roi = tuple[int, int, int, int]   # x0, y0, w, h in full-image pixels

PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "balanced": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}
"""Each preset's OpenCV base preset (``cv2.DISOPTICAL_FLOW_PRESET_*``); `PRESET_SETTINGS` changes some of its settings."""
PRESET_SETTINGS: dict[str, dict[str, int]] = {
    "balanced": {"VariationalRefinementIterations": 0, "PatchStride": 4, "GradientDescentIterations": 16},
}
"""DIS settings (``cv2.DISOpticalFlow.set<Name>``) a preset changes in its base. `balanced` is medium (the finest scale
1, 8-px patches) without the variational refinement, patches every 4 px instead of 3, 16 descent iterations instead of
25: DIS 2.7x as fast on the talking heads' lower face at 256 px (8.3-8.8 -> 3.1 ms a frame pair, both directions), its
flow 0.13 px from medium's on average. Tracked (bench/end_to_end.py --compare-flow, one core): the same mouth error as medium on GRID
(1.409 px) and the 700x700 talking heads (2.742 -> 2.741 px), MBP 14/14; synthetic takes L1 x 100 to the truth
5.14 -> 5.15, mouth 0.464 -> 0.469 px (112 px with medium: 5.16, 0.471)."""
STORAGE_DTYPES = {"float16": np.float16, "float32": np.float32}


@dataclass(frozen=True)
class FlowConfig:
    """How flow is computed and screened.

    preset: the DIS preset, "ultrafast", "fast", "balanced" (the default: medium with fewer iterations, see
        `PRESET_SETTINGS`) or "medium" (``cv2.DISOPTICAL_FLOW_PRESET_*``; case-insensitive).
    fb_threshold_px: forward-backward consistency threshold in pixels: a pixel p keeps its flow f(p) when
        ||f(p) + b(p + f(p))|| < fb_threshold_px, b the flow in the opposite direction.
    grayscale: convert RGB frames to luma (``cv2.COLOR_RGB2GRAY``) before DIS. DIS only accepts one 8-bit channel,
        so with False the frames must already be single-channel ((H, W) or (H, W, 1) uint8).
    storage_dtype: the dtype :func:`estimate_optical_flow` stores flows in, "float16" (half the memory; about 0.001 px
        resolution below 2 px and 0.03 px at 50 px) or "float32".
    photometric_threshold: None (the paper: forward-backward check only) or a gray-level threshold (0-255) for an
        extra photometric check in :func:`estimate_optical_flow`: p also needs the mean absolute difference between the
        first frame and the flow-warped second frame, over a ``photometric_window`` square around p, below it.
        The forward-backward check alone cannot see content that changes without moving (the inside of the mouth,
        a specular highlight): DIS propagates its neighbours' smooth flow into such a region in both directions
        and the two agree. 20 suits compressed video such as GRID.
    photometric_window: side in pixels (odd) of the box the photometric error is averaged over.
    max_roi_px: the region of interest is shrunk (``cv2.INTER_AREA``) until its longer side is at most this many
        pixels before DIS runs, and the flows are stored at that size (None: never). A face fills a few hundred
        pixels of a GRID or webcam frame, which keeps its full size; in a 4K frame it is over a thousand, and the
        flows of a 2-s clip at full size took gigabytes. Queries still take and give full-image pixels;
        ``fb_threshold_px`` stays in full-image pixels.
    """

    preset: str = "balanced"
    fb_threshold_px: float = 1.0
    grayscale: bool = True
    storage_dtype: str = "float16"
    photometric_threshold: float | None = None
    photometric_window: int = 5
    max_roi_px: int | None = 480

    def __post_init__(self) -> None:
        if self.preset.lower() not in PRESETS:
            raise ValueError(f"preset must be one of {sorted(PRESETS)}, got {self.preset!r}")
        if not np.isfinite(self.fb_threshold_px) or self.fb_threshold_px <= 0:
            raise ValueError(f"fb_threshold_px must be a positive number, got {self.fb_threshold_px}")
        if self.storage_dtype not in STORAGE_DTYPES:
            raise ValueError(f"storage_dtype must be one of {sorted(STORAGE_DTYPES)}, got {self.storage_dtype!r}")
        if self.photometric_threshold is not None and not self.photometric_threshold > 0:
            raise ValueError(f"photometric_threshold must be None or positive, got {self.photometric_threshold}")
        if self.photometric_window < 1 or self.photometric_window % 2 == 0:
            raise ValueError(f"photometric_window must be a positive odd size, got {self.photometric_window}")
        if self.max_roi_px is not None and self.max_roi_px < 16:
            raise ValueError(f"max_roi_px must be None or at least 16, got {self.max_roi_px}")

    @property
    def cv_preset(self) -> int:
        """The OpenCV preset DIS starts from."""
        return PRESETS[self.preset.lower()]

    @property
    def dis_settings(self) -> dict[str, int]:
        """The settings the preset changes in `cv_preset` (`PRESET_SETTINGS`; empty for OpenCV's own presets)."""
        return dict(PRESET_SETTINGS.get(self.preset.lower(), {}))


DEFAULT_CONFIG = FlowConfig()


# ---------------------------------------------------------------------------------------------------------------
# Frames and regions of interest


def clip_roi(roi: Sequence[int] | None, width: int, height: int) -> Roi:
    """``roi`` (x0, y0, w, h) clipped to a width x height image; the whole image when None. Raises ValueError when
    nothing of it lies in the image or its size is not positive."""
    if roi is None:
        return (0, 0, int(width), int(height))
    if len(roi) != 4:
        raise ValueError(f"roi must be (x0, y0, w, h), got {roi!r}")
    x0, y0, w, h = (int(round(float(v))) for v in roi)
    if w <= 0 or h <= 0:
        raise ValueError(f"roi width and height must be positive, got {roi!r}")
    x1, y1 = min(x0 + w, int(width)), min(y0 + h, int(height))
    x0, y0 = max(x0, 0), max(y0, 0)
    if x1 <= x0 or y1 <= y0:
        raise ValueError(f"roi {roi!r} lies outside the {width}x{height} image")
    return (x0, y0, x1 - x0, y1 - y0)


def roi_around(points: np.ndarray, width: int, height: int, margin: float = 0.25) -> Roi:
    """A region of interest (x0, y0, w, h) holding the (N, 2) points (e.g. face landmarks of all frames, NaN rows
    ignored), grown by ``margin`` times its size on every side and clipped to the image."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) == 0:
        raise ValueError("roi_around needs at least one finite point")
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = margin * (hi - lo) + 1.0
    lo, hi = np.floor(lo - pad), np.ceil(hi + pad) + 1
    return clip_roi((lo[0], lo[1], hi[0] - lo[0], hi[1] - lo[1]), width, height)


def _to_channel(frame: np.ndarray, config: FlowConfig) -> np.ndarray:
    """One frame as the contiguous single-channel uint8 image DIS takes."""
    frame = np.asarray(frame)
    if frame.dtype != np.uint8:
        raise ValueError(f"frames must be uint8, got {frame.dtype}")
    if frame.ndim == 3 and frame.shape[2] == 1:
        frame = frame[:, :, 0]
    if frame.ndim == 2:
        return np.ascontiguousarray(frame)
    if frame.ndim == 3 and frame.shape[2] == 3:
        if not config.grayscale:
            raise ValueError("DIS optical flow works on one channel: with grayscale=False pass (H, W) frames")
        return cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2GRAY)
    raise ValueError(f"a frame must be (H, W, 3) RGB or (H, W) gray, got shape {frame.shape}")


def _crop(image: np.ndarray, roi: Roi) -> np.ndarray:
    x0, y0, w, h = roi
    return np.ascontiguousarray(image[y0:y0 + h, x0:x0 + w])


def _make_dis(config: FlowConfig):
    dis = cv2.DISOpticalFlow_create(config.cv_preset)
    for name, value in config.dis_settings.items():
        getattr(dis, f"set{name}")(value)
    return dis


def _calc(dis, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    try:
        flow = dis.calc(a, b, None)   # None: no initial flow (DIS would otherwise start from the given one)
    except cv2.error as exc:
        raise ValueError(f"DIS optical flow failed on {a.shape[1]}x{a.shape[0]} images "
                         f"(too small for the preset?): {exc}") from exc
    return np.asarray(flow, dtype=np.float32)


# ---------------------------------------------------------------------------------------------------------------
# Flow, consistency, sampling


def dis_flow(prev: np.ndarray, nxt: np.ndarray, config: FlowConfig = DEFAULT_CONFIG,
             roi: Sequence[int] | None = None) -> np.ndarray:
    """Forward flow prev -> nxt as (H, W, 2) float32 (x, y) displacements in pixels: prev's pixel (x, y) moves to
    (x, y) + flow[y, x] in nxt. With ``roi`` the flow of that crop only, (h, w, 2) (see the module docstring)."""
    a, b = _to_channel(prev, config), _to_channel(nxt, config)
    if a.shape != b.shape:
        raise ValueError(f"frames differ in size: {a.shape} vs {b.shape}")
    box = clip_roi(roi, a.shape[1], a.shape[0])
    return _calc(_make_dis(config), _crop(a, box), _crop(b, box))


def bidirectional_flow(prev: np.ndarray, nxt: np.ndarray, config: FlowConfig = DEFAULT_CONFIG,
                       roi: Sequence[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(forward prev -> nxt, backward nxt -> prev) flows, each as :func:`dis_flow` returns them."""
    a, b = _to_channel(prev, config), _to_channel(nxt, config)
    if a.shape != b.shape:
        raise ValueError(f"frames differ in size: {a.shape} vs {b.shape}")
    box = clip_roi(roi, a.shape[1], a.shape[0])
    a, b = _crop(a, box), _crop(b, box)
    dis = _make_dis(config)
    return _calc(dis, a, b), _calc(dis, b, a)


_GRIDS: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}


def _pixel_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    key = (height, width)
    grid = _GRIDS.get(key)
    if grid is None:
        xs, ys = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
        xs.setflags(write=False)
        ys.setflags(write=False)
        grid = (xs, ys)
        if len(_GRIDS) < 16:
            _GRIDS[key] = grid
    return grid


def _targets(flow: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(map_x, map_y, inside): where each pixel's flow lands, clamped to (0, 0) where it leaves the image."""
    h, w = flow.shape[:2]
    xs, ys = _pixel_grid(h, w)
    map_x = xs + flow[..., 0]
    map_y = ys + flow[..., 1]
    inside = (map_x >= 0) & (map_x <= w - 1) & (map_y >= 0) & (map_y <= h - 1)   # False for NaN too
    return (np.where(inside, map_x, 0).astype(np.float32), np.where(inside, map_y, 0).astype(np.float32), inside)


def consistency_mask(forward: np.ndarray, backward: np.ndarray, threshold_px: float) -> np.ndarray:
    """(H, W) bool: pixels p of the first frame whose forward flow f passes the forward-backward check
    ||f(p) + b(p + f(p))|| < threshold_px, b sampled bilinearly (``cv2.remap``) at p + f(p). A pixel whose target
    p + f(p) leaves the image [0, W-1] x [0, H-1], or whose flows are not finite, fails."""
    fwd = np.asarray(forward, dtype=np.float32)
    bwd = np.asarray(backward, dtype=np.float32)
    if fwd.ndim != 3 or fwd.shape[2] != 2 or bwd.shape != fwd.shape:
        raise ValueError(f"forward and backward must both be (H, W, 2), got {fwd.shape} and {bwd.shape}")
    if not threshold_px > 0:
        raise ValueError(f"threshold_px must be positive, got {threshold_px}")
    map_x, map_y, inside = _targets(fwd)
    back = cv2.remap(np.ascontiguousarray(bwd), map_x, map_y, interpolation=cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
    err = np.square(fwd[..., 0] + back[..., 0]) + np.square(fwd[..., 1] + back[..., 1])
    return inside & (err < np.float32(threshold_px) ** 2)   # NaN err compares False


def photometric_mask(prev: np.ndarray, nxt: np.ndarray, forward: np.ndarray, threshold: float,
                     window: int = 5) -> np.ndarray:
    """(H, W) bool: pixels p where the mean absolute difference between ``prev`` and ``nxt`` warped back by the
    flow (nxt sampled bilinearly at p + forward(p)), averaged over a ``window`` x ``window`` box, is below
    ``threshold`` gray levels. prev / nxt: (H, W) uint8 single-channel images of the flow's size. Pixels whose
    target leaves the image fail."""
    fwd = np.asarray(forward, dtype=np.float32)
    a, b = np.asarray(prev), np.asarray(nxt)
    if a.shape != fwd.shape[:2] or b.shape != fwd.shape[:2]:
        raise ValueError(f"prev and nxt must be single-channel {fwd.shape[:2]}, got {a.shape} and {b.shape}")
    map_x, map_y, inside = _targets(fwd)
    warped = cv2.remap(b.astype(np.float32), map_x, map_y, interpolation=cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE)
    err = np.abs(warped - a.astype(np.float32))
    if window > 1:
        err = cv2.blur(err, (int(window), int(window)), borderType=cv2.BORDER_REPLICATE)
    return inside & (err < np.float32(threshold))


def flow_masks(prev: np.ndarray, nxt: np.ndarray, forward: np.ndarray, backward: np.ndarray,
               config: FlowConfig = DEFAULT_CONFIG) -> tuple[np.ndarray, np.ndarray]:
    """The validity masks :func:`estimate_optical_flow` keeps for one pair: (forward on prev's pixels, backward on nxt's
    pixels), the forward-backward check and, when ``config.photometric_threshold`` is set, the photometric one.
    prev / nxt: frames as given to :func:`bidirectional_flow`, already cropped to the flows' region."""
    fmask = consistency_mask(forward, backward, config.fb_threshold_px)
    bmask = consistency_mask(backward, forward, config.fb_threshold_px)
    if config.photometric_threshold is not None:
        a, b = _to_channel(prev, config), _to_channel(nxt, config)
        fmask &= photometric_mask(a, b, forward, config.photometric_threshold, config.photometric_window)
        bmask &= photometric_mask(b, a, backward, config.photometric_threshold, config.photometric_window)
    return fmask, bmask


def _as_points(points) -> np.ndarray:
    if isinstance(points, torch.Tensor):
        points = points.detach().cpu().numpy()
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points must be (N, 2) pixel coordinates, got shape {pts.shape}")
    return pts


def sample_flow(flow: np.ndarray, valid: np.ndarray | None, points) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear sample of an (H, W, 2) flow at (N, 2) points (x, y): ((N, 2) float32 displacements, (N,) bool).

    A point is valid when it is finite, lies inside the image ([0, W-1] x [0, H-1]) and its 4 neighbouring pixels
    (clamped at the last row / column) all pass ``valid`` (all pixels count as passing when ``valid`` is None).
    Invalid points get a displacement of 0."""
    flow = np.asarray(flow)
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f"flow must be (H, W, 2), got {flow.shape}")
    h, w = flow.shape[:2]
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != (h, w):
            raise ValueError(f"valid must be {(h, w)}, got {valid.shape}")
    out, ok = _sample_flows(flow[None], None if valid is None else valid[None], _as_points(points)[None])
    return out[0], ok[0]


def _sample_flows(flows: np.ndarray, valid: np.ndarray | None, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`sample_flow` of P flows (P, H, W, 2) at their own points (P, N, 2) float64 in one pass (the same
    arithmetic): ((P, N, 2) float32, (P, N) bool). The four neighbours are read by flat index (`take`) rather than
    by three index arrays: 2.5x as fast on the talking heads' groups (334 flows of 200x240 at 300 points each, 105
    -> 41 ms a refresh of the fast solver's correspondences), the same values."""
    p, n = pts.shape[:2]
    h, w = flows.shape[1:3]
    out = np.zeros((p, n, 2), dtype=np.float32)
    x, y = pts[..., 0], pts[..., 1]
    ok = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)     # False for NaN
    sel = np.flatnonzero(ok)
    if len(sel) == 0:
        return out, ok
    xs, ys = x.reshape(-1)[sel], y.reshape(-1)[sel]
    x0 = np.minimum(xs.astype(np.intp), w - 1)                 # the floor: xs >= 0
    y0 = np.minimum(ys.astype(np.intp), h - 1)
    dx = (x0 < w - 1).astype(np.intp)                          # the next column / row, or the last again
    dy = np.where(y0 < h - 1, w, 0)
    i00 = ((sel // n) * h + y0) * w + x0
    ax, ay = (xs - x0)[:, None], (ys - y0)[:, None]
    flat = flows.reshape(-1, 2)
    f00 = flat.take(i00, axis=0).astype(np.float64)
    f01 = flat.take(i00 + dx, axis=0).astype(np.float64)
    f10 = flat.take(i00 + dy, axis=0).astype(np.float64)
    f11 = flat.take(i00 + dy + dx, axis=0).astype(np.float64)
    val = (1 - ay) * ((1 - ax) * f00 + ax * f01) + ay * ((1 - ax) * f10 + ax * f11)
    good = np.isfinite(val).all(axis=1)
    if valid is not None:
        v = valid.reshape(-1)
        good &= v.take(i00) & v.take(i00 + dx) & v.take(i00 + dy) & v.take(i00 + dy + dx)
    val[~good] = 0
    out.reshape(-1, 2)[sel] = val
    ok.reshape(-1)[sel] = good
    return out, ok


# ---------------------------------------------------------------------------------------------------------------
# Per-utterance flow


@dataclass(frozen=True, eq=False)
class FlowField:
    """The flows of all consecutive frame pairs of one utterance, on its region of interest.

    Pair i (0 <= i < T-1) is frames (i, i+1): ``forward[i]`` is the flow i -> i+1 on frame i's pixels and
    ``backward[i]`` the flow i+1 -> i on frame i+1's pixels, each (h, w, 2) in ``storage_dtype`` (see FlowConfig),
    with its mask ``forward_valid[i]`` / ``backward_valid[i]`` (h, w) bool (see :func:`flow_masks`). The arrays cover
    ``roi`` (x0, y0, w, h) of the (width x height) frames, sampled at ``scale`` array pixels per image pixel (1, or
    less where the ROI was shrunk: FlowConfig.max_roi_px), the flows in array pixels; queries take and give
    full-image pixels.

    ``backward_mask`` None: the backward masks are made on first use, by the forward-backward check on the stored
    flows (threshold ``fb_threshold_px`` in array pixels). Only the faithful solver's backward pass asks for them;
    the fast solver follows the forward flow alone, so tracking does not pay for a check it never reads (the mask
    step on the talking heads' lower face: 1.66 -> 0.68 ms a frame).
    """

    forward: np.ndarray
    backward: np.ndarray
    forward_valid: np.ndarray
    backward_mask: np.ndarray | None
    roi: Roi
    width: int
    height: int
    scale: float = 1.0
    fb_threshold_px: float = 1.0

    @property
    def backward_valid(self) -> np.ndarray:
        """(T-1, h, w) bool: the backward flow's masks, made from the stored flows on first use when not given."""
        if self.backward_mask is None:
            mask = np.empty(self.forward_valid.shape, dtype=bool)
            for i in range(self.n_pairs):
                mask[i] = consistency_mask(self.backward[i].astype(np.float32), self.forward[i].astype(np.float32),
                                           self.fb_threshold_px)
            object.__setattr__(self, "backward_mask", mask)
        return self.backward_mask

    @property
    def n_pairs(self) -> int:
        return int(self.forward.shape[0])

    @property
    def n_frames(self) -> int:
        return self.n_pairs + 1

    @property
    def nbytes(self) -> int:
        return int(self.forward.nbytes + self.backward.nbytes + self.forward_valid.nbytes
                   + (0 if self.backward_mask is None else self.backward_mask.nbytes))

    def _pair(self, i: int, what: str) -> int:
        if not 0 <= i < self.n_pairs:
            raise IndexError(f"{what}: no frame pair ({i}, {i + 1}) in a field of {self.n_frames} frames")
        return int(i)

    def _sampled(self, sample, flow: np.ndarray, valid: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`sample(flow, valid, array pixels)` at image pixels `pts` (..., 2), its displacements back in image
        pixels: image pixel p covers array pixel (p - roi corner + 0.5) * scale - 0.5 (pixel centres)."""
        shift = np.array(self.roi[:2], dtype=np.float64)
        if self.scale == 1.0:
            return sample(flow, valid, pts - shift)
        u, ok = sample(flow, valid, (pts - shift + 0.5) * self.scale - 0.5)
        return (u / self.scale).astype(np.float32), ok

    def _query(self, flow: np.ndarray, valid: np.ndarray, points) -> tuple[np.ndarray, np.ndarray]:
        return self._sampled(sample_flow, flow, valid, _as_points(points))

    def all_correspondences(self, points) -> tuple[np.ndarray, np.ndarray]:
        """`correspondences(j, points[j - 1])` for every frame j >= 1 at once: points (T-1, N, 2) of frames 0..T-2
        (full-image pixels) -> ((T-1, N, 2) float32 displacements, (T-1, N) bool), equal to the per-frame calls (one
        pass of NumPy instead of T-1: the fast solver asks at every refresh of its correspondences)."""
        pts = np.asarray(points.detach().cpu().numpy() if isinstance(points, torch.Tensor) else points,
                         dtype=np.float64)
        if pts.ndim != 3 or pts.shape[0] != self.n_pairs or pts.shape[2] != 2:
            raise ValueError(f"points must be ({self.n_pairs}, N, 2), one row of points per frame pair, got "
                             f"{pts.shape}")
        return self._sampled(_sample_flows, self.forward, self.forward_valid, pts)

    def correspondences(self, j: int, points_prev) -> tuple[np.ndarray, np.ndarray]:
        """Forward pass, frame j >= 1: the flow displacement u_k (N, 2) float32 carrying the (N, 2) points of frame
        j-1 (full-image pixels) into frame j, and (N,) bool validity (inside the ROI, forward-backward consistent).
        ``points_prev + u`` are the flow targets of Eq. 6."""
        i = self._pair(j - 1, f"correspondences(j={j})")
        return self._query(self.forward[i], self.forward_valid[i], points_prev)

    def backward_correspondences(self, j: int, points_next) -> tuple[np.ndarray, np.ndarray]:
        """Backward pass, frame j <= T-2: the displacement (N, 2) carrying points of frame j+1 into frame j (the
        backward flow of pair (j, j+1)), and (N,) bool validity."""
        i = self._pair(j, f"backward_correspondences(j={j})")
        return self._query(self.backward[i], self.backward_valid[i], points_next)

    def forward_flow(self, j: int) -> np.ndarray:
        """The float32 flow j-1 -> j on the ROI as stored, (h, w, 2) in array pixels (see ``scale``)."""
        return self.forward[self._pair(j - 1, f"forward_flow(j={j})")].astype(np.float32)

    def valid_fraction(self, j: int) -> float:
        """Fraction of the ROI pixels of frame j-1 whose flow to frame j passes the forward-backward check."""
        return float(self.forward_valid[self._pair(j - 1, f"valid_fraction(j={j})")].mean())


_CONVERT_FP16 = getattr(cv2, "convertFp16", None)


def as_storage(flow: np.ndarray, dtype: type) -> np.ndarray:
    """An (h, w, 2) float32 flow in the storage dtype. float16 goes through OpenCV's vectorised conversion when it
    has one: the same values as NumPy's (both round to nearest even), which took 0.9 ms per flow of 200x157 on this
    machine against 0.05 ms, a fifth of the whole flow step on the 700x700 talking heads."""
    if dtype is np.float16 and _CONVERT_FP16 is not None and flow.dtype == np.float32 and flow.ndim == 3:
        h = flow.shape[0]
        return _CONVERT_FP16(np.ascontiguousarray(flow).reshape(h, -1)).view(np.float16).reshape(flow.shape)
    return np.asarray(flow, dtype=dtype)


def roi_scale(roi: Roi, config: FlowConfig = DEFAULT_CONFIG) -> float:
    """Array pixels per image pixel of the flows on ``roi``: 1, or less so that its longer side fits
    ``config.max_roi_px``."""
    longer = max(roi[2], roi[3])
    return 1.0 if config.max_roi_px is None or longer <= config.max_roi_px else config.max_roi_px / longer


def estimate_optical_flow(frames: Iterable[np.ndarray] | np.ndarray, config: FlowConfig = DEFAULT_CONFIG,
               roi: Sequence[int] | None = None, scale_roi: Sequence[int] | None = None) -> FlowField:
    """Bi-directional DIS flow and forward-backward masks for every consecutive pair of ``frames`` ((T, H, W, 3)
    uint8 RGB, or an iterable of such frames, e.g. frames decoded one at a time), on ``roi`` (x0, y0, w, h; the
    whole frame when None), computed once per utterance. Each frame is converted to gray, cropped to the ROI and
    shrunk as it comes, so only the crops are held; one DIS instance serves all pairs. The shrink is the one that
    fits ``scale_roi`` (default: ``roi`` itself) into ``config.max_roi_px``: a part of a face, e.g., keeps the
    whole face's resolution."""
    crops: list[np.ndarray] = []
    height = width = 0
    box: Roi = (0, 0, 0, 0)
    scale = 1.0
    for t, f in enumerate(frames):   # an array iterates over its first (time) axis
        f = np.asarray(f)
        if f.ndim < 2:
            raise ValueError(f"a frame must be (H, W, 3) RGB or (H, W) gray, got shape {f.shape}")
        if t == 0:
            height, width = f.shape[:2]
            box = clip_roi(roi, width, height)
            scale = roi_scale(box if scale_roi is None else clip_roi(scale_roi, width, height), config)
        elif f.shape[:2] != (height, width):
            raise ValueError(f"frame {t} is {f.shape[1]}x{f.shape[0]}, frame 0 is {width}x{height}")
        x0, y0, w, h = box
        crop = _to_channel(f[y0:y0 + h, x0:x0 + w], config)   # gray is per pixel: the crop's gray is the gray's crop
        if scale != 1.0:
            crop = cv2.resize(crop, (max(1, round(box[2] * scale)), max(1, round(box[3] * scale))),
                              interpolation=cv2.INTER_AREA)
        crops.append(crop)
    if not crops:
        raise ValueError("estimate_optical_flow needs at least one frame")
    if scale != 1.0:
        config = dataclasses.replace(config, fb_threshold_px=config.fb_threshold_px * scale)
    n_pairs = len(crops) - 1
    h, w = crops[0].shape[:2]
    dtype = STORAGE_DTYPES[config.storage_dtype]
    forward = np.empty((n_pairs, h, w, 2), dtype=dtype)
    backward = np.empty((n_pairs, h, w, 2), dtype=dtype)
    fvalid = np.empty((n_pairs, h, w), dtype=bool)
    # the photometric check needs the frames, so with it both masks are made now; without it the backward masks wait
    # for a solver that asks (FlowField.backward_valid)
    bvalid = np.empty((n_pairs, h, w), dtype=bool) if config.photometric_threshold is not None else None
    dis = _make_dis(config)
    for i in range(n_pairs):
        fwd = _calc(dis, crops[i], crops[i + 1])
        bwd = _calc(dis, crops[i + 1], crops[i])
        if bvalid is None:
            fvalid[i] = consistency_mask(fwd, bwd, config.fb_threshold_px)
        else:
            fvalid[i], bvalid[i] = flow_masks(crops[i], crops[i + 1], fwd, bwd, config)
        forward[i] = as_storage(fwd, dtype)
        backward[i] = as_storage(bwd, dtype)
    return FlowField(forward, backward, fvalid, bvalid, box, int(width), int(height), scale, config.fb_threshold_px)
