"""A small differentiable renderer in torch for the mouth crop of the RGB photo loss L_rgb (paper Sec. 4.3, Eq. 3).

nvdiffrast style, in two stages:

1. `CropRasterizer.rasterize` (no gradient): which triangle is nearest at each pixel centre of the crop grid.
   Triangles are binned into square tiles of the grid by their bounding boxes; every (tile, triangle) pair is
   tested densely against the tile's pixels (edge functions, edges included) and the nearest fragment per pixel
   is kept with one `scatter_reduce(amin)` over a key that packs the fragment's depth above its triangle id.
   Depth is 1 / (interpolated 1 / d), exact for planar triangles; work is chunked to bound memory.
2. `CropRasterizer.interpolate` (differentiable): for every covered pixel the barycentric coordinates of its centre
   are recomputed from the projected corner positions, so gradients reach the 2D positions (hence viseme weights and
   head pose) and the per-vertex attributes (albedo, shading). Interpolation is linear in screen space (as the
   corpus renderer shades): across one triangle of a face a metre or less away the depth varies by well under
   1 %, so perspective correction would change colours by far less than a grey level.

There is no anti-aliasing stage: a pixel's triangle id is piecewise constant, so visibility (silhouette and
occlusion) edges contribute no gradient; the gradient comes from colour varying inside triangles (albedo and
shading between vertices). Keep that in mind when starting far from the answer: landmarks should bring the fit
within a pixel or two first.

Crop geometry: a `Crop` is a window of the full image (columns x0..x0+width-1, rows y0..y0+height-1) resampled
to a fixed `out_width` x `out_height` grid (by default its native size). The renderer works on that grid through a
scaled camera (`Crop.intrinsics`), so its cost does not depend on the video resolution: `mouth_crop` makes a
`size` x `size` grid, and `crop_image` resamples the video frame onto the same grid (pixel centres map as
in OpenCV's `resize`: u_grid = (u - x0 + 0.5) * out_width / width - 0.5).

Conventions are those of `visemeflow.render.camera`: camera looks down -z, pixel v downward, integer pixel
coordinates are pixel centres, images are (height, width, 3) RGB. A triangle is front-facing when it is
counter-clockwise seen from the camera (outward normal toward the viewer), i.e. when its signed area in (u, v)
pixel coordinates, v pointing down, is negative.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from visemeflow.render.camera import Intrinsics, to_camera

MOUTH_LANDMARKS = slice(48, 68)
"""Multi-PIE landmarks of the outer (48-59) and inner (60-67) lip contours."""
NEAR = 1e-3
"""Triangles with a corner nearer than this (mesh units in front of the camera) are dropped, not clipped."""
DEFAULT_LIGHT_DIRECTION = (0.35, 0.45, 1.0)


# ------------------------------------------------------------------------------------------------ crop


@dataclass(frozen=True)
class Crop:
    """A window of the full image, rendered and compared on an `out_width` x `out_height` grid (0: native size)."""

    x0: int
    y0: int
    width: int
    height: int
    out_width: int = 0
    out_height: int = 0

    def __post_init__(self):
        if self.width < 1 or self.height < 1:
            raise ValueError(f"crop must be at least 1x1 pixels, got {self.width}x{self.height}")
        if self.out_width <= 0:
            object.__setattr__(self, "out_width", int(self.width))
        if self.out_height <= 0:
            object.__setattr__(self, "out_height", int(self.height))

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns) of the render grid."""
        return int(self.out_height), int(self.out_width)

    @property
    def scale(self) -> tuple[float, float]:
        """(sx, sy): grid pixels per full-image pixel."""
        return self.out_width / self.width, self.out_height / self.height

    def to_crop(self, pix):
        """(..., 2) full-image pixel coordinates -> grid coordinates (torch stays differentiable; numpy works too)."""
        sx, sy = self.scale
        u = (pix[..., 0] - self.x0 + 0.5) * sx - 0.5
        v = (pix[..., 1] - self.y0 + 0.5) * sy - 0.5
        return torch.stack([u, v], -1) if isinstance(pix, torch.Tensor) else np.stack([u, v], -1)

    def to_image(self, pix):
        """Inverse of `to_crop`: grid coordinates -> full-image pixel coordinates."""
        sx, sy = self.scale
        u = (pix[..., 0] + 0.5) / sx - 0.5 + self.x0
        v = (pix[..., 1] + 0.5) / sy - 0.5 + self.y0
        return torch.stack([u, v], -1) if isinstance(pix, torch.Tensor) else np.stack([u, v], -1)

    def intrinsics(self, camera: Intrinsics) -> Intrinsics:
        """The camera whose image is the render grid: projecting with it == `to_crop` of projecting with `camera`."""
        sx, sy = self.scale
        return Intrinsics(
            camera.fx * sx, camera.fy * sy,
            (camera.cx - self.x0 + 0.5) * sx - 0.5, (camera.cy - self.y0 + 0.5) * sy - 0.5,
            int(self.out_width), int(self.out_height),
        )


def mouth_crop(landmarks_2d, size: int = 64, margin: float = 0.6, image_size: tuple[int, int] | None = None) -> Crop:
    """Square window around the mouth landmarks 48-67, rendered on a `size` x `size` grid.

    `landmarks_2d` (68, 2) or (T, 68, 2) full-image pixels (NaN rows ignored); the window covers the union of the
    mouth landmarks over all frames, its side `margin` larger than their larger extent (0.6: 60 % larger). With
    `image_size` (W, H) the window is shifted inside the image, and cut to it only where it is larger; a cut window
    keeps the grid's scale, so its grid is no longer square.
    """
    points = np.asarray(landmarks_2d, np.float64)
    if points.ndim == 2:
        points = points[None]
    if points.ndim != 3 or points.shape[1:] != (68, 2):
        raise ValueError(f"landmarks must have shape (68, 2) or (T, 68, 2), got {points.shape}")
    mouth = points[:, MOUTH_LANDMARKS].reshape(-1, 2)
    mouth = mouth[np.isfinite(mouth).all(axis=1)]
    if len(mouth) == 0:
        raise ValueError("no finite mouth landmark (48-67)")
    lo, hi = mouth.min(axis=0), mouth.max(axis=0)
    centre = (lo + hi) / 2.0
    side = max(math.ceil(float((hi - lo).max()) * (1.0 + margin)), 4)
    x0 = round(float(centre[0]) - (side - 1) / 2.0)
    y0 = round(float(centre[1]) - (side - 1) / 2.0)
    width = height = side
    if image_size is not None:
        img_w, img_h = int(image_size[0]), int(image_size[1])
        x0, width = _fit(x0, side, img_w)
        y0, height = _fit(y0, side, img_h)
    scale = size / side
    return Crop(x0, y0, width, height, max(1, round(width * scale)), max(1, round(height * scale)))


def _fit(start: int, length: int, limit: int) -> tuple[int, int]:
    """Shift [start, start + length) inside [0, limit); cut it to the image only when it is longer."""
    if length >= limit:
        return 0, limit
    return min(max(start, 0), limit - length), length


def crop_image(frame: np.ndarray, crop: Crop) -> torch.Tensor:
    """(H, W, 3) uint8 frame -> (out_height, out_width, 3) float32 tensor in [0, 1] on the crop's grid.

    Parts of the window outside the frame are black. Downsampling averages areas (INTER_AREA), upsampling is
    bilinear; both map pixel centres as `Crop.to_crop`.
    """
    frame = np.asarray(frame)
    if frame.ndim != 3 or frame.shape[2] != 3:
        raise ValueError(f"frame must have shape (H, W, 3), got {frame.shape}")
    patch = np.zeros((crop.height, crop.width, 3), frame.dtype)
    ys0, xs0 = max(crop.y0, 0), max(crop.x0, 0)
    ys1, xs1 = min(crop.y0 + crop.height, frame.shape[0]), min(crop.x0 + crop.width, frame.shape[1])
    if ys1 > ys0 and xs1 > xs0:
        patch[ys0 - crop.y0:ys1 - crop.y0, xs0 - crop.x0:xs1 - crop.x0] = frame[ys0:ys1, xs0:xs1]
    if (crop.out_width, crop.out_height) != (crop.width, crop.height):
        shrink = crop.out_width * crop.out_height < crop.width * crop.height
        patch = cv2.resize(patch, (crop.out_width, crop.out_height),
                           interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    scale = 255.0 if frame.dtype == np.uint8 else 1.0
    return torch.from_numpy(np.ascontiguousarray(patch, np.float32) / np.float32(scale))


# ------------------------------------------------------------------------------------------ triangles


def select_triangles(faces: np.ndarray, vertex_ids) -> np.ndarray:
    """(K,) int64 ids of the triangles of `faces` (F, 3) whose three corners all lie in `vertex_ids`."""
    faces = np.asarray(faces)
    keep = np.zeros(int(faces.max()) + 1 if faces.size else 0, bool)
    ids = np.asarray(vertex_ids, np.int64).reshape(-1)
    ids = ids[(ids >= 0) & (ids < keep.size)]
    keep[ids] = True
    return np.flatnonzero(keep[faces].all(axis=1)).astype(np.int64) if faces.size else np.zeros(0, np.int64)


def vertices_near(points: np.ndarray, anchors: np.ndarray, radius: float) -> np.ndarray:
    """(K,) ids of the `points` (V, 3) within `radius` of the box around `anchors` (N, 3): e.g. the mouth landmarks."""
    points = np.asarray(points, np.float64)
    anchors = np.asarray(anchors, np.float64).reshape(-1, 3)
    lo, hi = anchors.min(axis=0), anchors.max(axis=0)
    gap = np.maximum(lo - points, 0.0) + np.maximum(points - hi, 0.0)
    return np.flatnonzero(np.linalg.norm(gap, axis=1) <= radius).astype(np.int64)


def mouth_triangles(rig, radius: float = 4.0, regions=("face", "mouth_interior")) -> np.ndarray:
    """Triangle ids of a `VisemeRig` near the mouth: corners in `regions` and within `radius` (mesh units) of the
    box around the neutral lip landmarks (the demo rig is in centimetres: 4 covers the lips, the mouth interior and
    the skin next to them). A pose-free first cut; for a given crop and poses `triangles_in_crop` is exact."""
    ids = np.asarray(rig.landmark_ids)[MOUTH_LANDMARKS]
    anchors = np.asarray(rig.neutral)[ids[ids >= 0]]
    near = vertices_near(rig.neutral, anchors, radius)
    if regions:
        allowed = np.unique(np.concatenate([np.asarray(rig.regions[name]) for name in regions if name in rig.regions]))
        near = np.intersect1d(near, allowed)
    return select_triangles(rig.faces, near)


def triangles_in_crop(faces: np.ndarray, pix, crop: Crop, margin: float = 2.0) -> np.ndarray:
    """(K,) int64 ids of the triangles of `faces` (F, 3) whose bounding box, at grid coordinates `pix` (V, 2) or
    (T, V, 2) (`Crop.to_crop` of projected vertices, e.g. over the frames of a clip), comes within `margin` grid
    pixels of `crop`'s grid in any frame: the triangles a rasteriser for that crop needs (hidden ones included)."""
    faces = np.asarray(faces, np.int64)
    pix = np.asarray(torch.as_tensor(pix).detach(), np.float64)
    if pix.ndim == 2:
        pix = pix[None]
    height, width = crop.shape
    keep = np.zeros(len(faces), bool)
    for frame in pix:
        corners = frame[faces]  # (F, 3, 2)
        lo, hi = corners.min(axis=1), corners.max(axis=1)
        keep |= ((hi[:, 0] >= -margin) & (lo[:, 0] <= width - 1 + margin)
                 & (hi[:, 1] >= -margin) & (lo[:, 1] <= height - 1 + margin))
    return np.flatnonzero(keep).astype(np.int64)


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(V, 3) unit area-weighted vertex normals of the triangles `faces` (K, 3) (zero for unused vertices)."""
    corners = vertices[faces]
    face_n = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], dim=-1)
    normals = torch.zeros_like(vertices).index_add(0, faces.reshape(-1), face_n.repeat_interleave(3, dim=0))
    return normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-12)


# ------------------------------------------------------------------------------------------ rasteriser


@dataclass
class Fragments:
    """What `CropRasterizer.rasterize` found at each pixel centre of the grid (no gradient)."""

    triangle: torch.Tensor
    """(H, W) int64 index into the rasteriser's `faces`, -1 for background."""
    depth: torch.Tensor
    """(H, W) distance in front of the camera of the visible surface, +inf for background."""
    n_candidates: int = 0
    """Triangles that survived culling (bounding box on the grid, near plane, orientation)."""
    n_tests: int = 0
    """Pixel-triangle inside tests made."""

    @property
    def mask(self) -> torch.Tensor:
        return self.triangle >= 0


@dataclass(eq=False)
class CropRasterizer:
    """Rasterise and interpolate the triangles `faces` (F, 3) (vertex ids of the full mesh) on `crop`'s grid.

    Per-vertex inputs (`pix`, `depth`, `attributes`) may have a row per vertex of the full mesh (at least
    max(faces) + 1 rows) or only the rows `vertex_ids` (the vertices `faces` uses, ascending), e.g.
    `evaluate_rig(rig, w, rasterizer.vertex_ids)`: the second is cheaper. Either way `Fragments.triangle` indexes
    the rows of `faces`. `tile` is the side of the square pixel bins (4 suits triangles of a few pixels); `chunk`
    bounds the pixel-triangle tests held at once.
    """

    faces: np.ndarray
    crop: Crop
    cull_backfaces: bool = True
    tile: int = 4
    chunk: int = 1 << 20
    vertex_ids: np.ndarray = field(init=False)
    _global: tuple = field(init=False, repr=False)
    _local: tuple = field(init=False, repr=False)
    _n_global: int = field(init=False, repr=False, default=0)

    def __post_init__(self):
        faces = np.asarray(self.faces)
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"faces must have shape (F, 3), got {faces.shape}")
        if faces.size and faces.min() < 0:
            raise ValueError("faces must hold vertex ids >= 0")
        self.faces = faces
        self.vertex_ids, local = np.unique(faces.astype(np.int64), return_inverse=True)
        self._n_global = int(faces.max()) + 1 if faces.size else 0
        self._global = self._tensors(faces.astype(np.int64))
        self._local = self._tensors(local.reshape(-1, 3))

    @staticmethod
    def _tensors(faces: np.ndarray) -> tuple[torch.Tensor, list[torch.Tensor]]:
        faces_t = torch.as_tensor(np.ascontiguousarray(faces, np.int64))
        return faces_t, [faces_t[:, k].contiguous() for k in range(3)]

    def faces_for(self, n_rows: int) -> torch.Tensor:
        """(F, 3) int64 tensor of `faces` in the indexing of per-vertex inputs with `n_rows` rows."""
        return self._indexing(n_rows)[0]

    def _indexing(self, n_rows: int) -> tuple[torch.Tensor, list[torch.Tensor]]:
        if n_rows >= self._n_global:
            return self._global
        if n_rows == len(self.vertex_ids):
            return self._local
        raise ValueError(f"per-vertex inputs must have >= {self._n_global} rows (full mesh) or "
                         f"{len(self.vertex_ids)} (the rasteriser's vertex_ids), got {n_rows}")

    def rasterize(self, pix: torch.Tensor, depth: torch.Tensor) -> Fragments:
        """Nearest triangle per pixel centre: `pix` (V, 2) grid coordinates (`Crop.to_crop`), `depth` (V,) > 0."""
        height, width = self.crop.shape
        empty = torch.iinfo(torch.int64).max
        key = torch.full((height * width,), empty, dtype=torch.int64)
        n_cand = n_tests = 0
        with torch.no_grad():
            pix = pix.detach()
            dtype = pix.dtype
            px_all, py_all = pix[:, 0].contiguous(), pix[:, 1].contiguous()
            depth = depth.detach().to(dtype).contiguous()
            f = self._indexing(len(pix))[1]
            x = [px_all.index_select(0, f[k]) for k in range(3)]
            y = [py_all.index_select(0, f[k]) for k in range(3)]
            c0 = torch.ceil(torch.minimum(torch.minimum(x[0], x[1]), x[2])).clamp_min(0)
            c1 = torch.floor(torch.maximum(torch.maximum(x[0], x[1]), x[2])).clamp_max(width - 1)
            r0 = torch.ceil(torch.minimum(torch.minimum(y[0], y[1]), y[2])).clamp_min(0)
            r1 = torch.floor(torch.maximum(torch.maximum(y[0], y[1]), y[2])).clamp_max(height - 1)
            keep = (c0 <= c1) & (r0 <= r1)  # False for NaN corners too
            cand = torch.nonzero(keep).reshape(-1)
            if len(cand):
                x = [v.index_select(0, cand) for v in x]
                y = [v.index_select(0, cand) for v in y]
                d = [depth.index_select(0, f[k].index_select(0, cand)) for k in range(3)]
                area2 = (x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0])
                keep = (d[0] > NEAR) & (d[1] > NEAR) & (d[2] > NEAR)
                keep &= (area2 < 0) if self.cull_backfaces else (area2 != 0)
                sub = torch.nonzero(keep).reshape(-1)
                cand = cand.index_select(0, sub)
                x = [v.index_select(0, sub) for v in x]
                y = [v.index_select(0, sub) for v in y]
                inv_d = torch.stack([1.0 / v.index_select(0, sub) for v in d], dim=1)  # (K, 3)
                area2 = area2.index_select(0, sub)
                c0, c1, r0, r1 = (v.index_select(0, cand) for v in (c0, c1, r0, r1))
                n_cand = len(cand)
            if n_cand:
                t = self.tile
                tx0, tx1 = (c0 / t).floor().long(), (c1 / t).floor().long()
                ty0, ty1 = (r0 / t).floor().long(), (r1 / t).floor().long()
                nx = tx1 - tx0 + 1
                counts = nx * (ty1 - ty0 + 1)
                owner = torch.repeat_interleave(torch.arange(n_cand), counts)
                local = torch.arange(len(owner)) - (torch.cumsum(counts, 0) - counts).index_select(0, owner)
                nx_o = nx.index_select(0, owner)
                tile_y = torch.div(local, nx_o, rounding_mode="floor")
                tile_x = tx0.index_select(0, owner) + local - tile_y * nx_o
                tile_y += ty0.index_select(0, owner)
                # barycentric weight k at (u, v) is affine: coef[:, k] . (1, u, v) (signed sub-area over area)
                rows_k = []
                for k in range(3):
                    i, j = (k + 1) % 3, (k + 2) % 3
                    rows_k.append(torch.stack([x[i] * y[j] - x[j] * y[i], y[i] - y[j], x[j] - x[i]], dim=1))
                coef = torch.stack(rows_k, dim=1) / area2[:, None, None]  # (K, 3 corners, 3)
                offs = torch.arange(t * t)
                basis = torch.stack([torch.ones(t * t, dtype=dtype), (offs % t).to(dtype),
                                     torch.div(offs, t, rounding_mode="floor").to(dtype)])  # (3, t*t)
                per_chunk = max(1, self.chunk // (3 * t * t))
                for lo in range(0, len(owner), per_chunk):
                    o = owner[lo:lo + per_chunk]
                    bx, by = tile_x[lo:lo + per_chunk] * t, tile_y[lo:lo + per_chunk] * t
                    cf = coef.index_select(0, o)  # (P, 3, 3)
                    # move the origin to the tile's first pixel centre
                    origin = cf[:, :, 0] + cf[:, :, 1] * bx[:, None].to(dtype) + cf[:, :, 2] * by[:, None].to(dtype)
                    cf = torch.cat([origin[:, :, None], cf[:, :, 1:]], dim=2)
                    bary = (cf.reshape(-1, 3) @ basis).reshape(len(o), 3, t * t)
                    inside = (bary[:, 0] >= 0) & (bary[:, 1] >= 0) & (bary[:, 2] >= 0)
                    n_tests += inside.numel()
                    pair, slot = torch.nonzero(inside, as_tuple=True)
                    if len(pair) == 0:
                        continue
                    u = bx.index_select(0, pair) + slot % t
                    v = by.index_select(0, pair) + torch.div(slot, t, rounding_mode="floor")
                    ok = (u < width) & (v < height)
                    pair, slot, u, v = pair[ok], slot[ok], u[ok], v[ok]
                    tri = o.index_select(0, pair)
                    b = bary[pair, :, slot]  # (N, 3)
                    frag_depth = 1.0 / (b * inv_d.index_select(0, tri)).sum(dim=1)
                    bits = frag_depth.to(torch.float32).clamp_min(0).view(torch.int32).to(torch.int64)
                    key.scatter_reduce_(0, v * width + u, (bits << 32) | cand.index_select(0, tri), reduce="amin")
            hit = key != empty
            triangle = torch.where(hit, key & 0xFFFFFFFF, torch.full_like(key, -1))
            zbuf = torch.full((height * width,), math.inf, dtype=torch.float32)
            zbuf[hit] = (key[hit] >> 32).to(torch.int32).view(torch.float32)
        return Fragments(triangle.reshape(height, width), zbuf.reshape(height, width), n_cand, n_tests)

    def interpolate(self, fragments: Fragments, pix: torch.Tensor, attributes: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(H, W, C) per-vertex `attributes` (V, C) interpolated at the covered pixel centres, 0 elsewhere; and the
        (H, W) bool coverage mask. Barycentrics are recomputed from `pix` (V, 2) grid coordinates with autograd,
        so both `pix` and `attributes` receive gradients."""
        height, width = fragments.triangle.shape
        flat = fragments.triangle.reshape(-1)
        index = torch.nonzero(flat >= 0).reshape(-1)
        corners = self.faces_for(len(pix))[flat[index]]  # (N, 3)
        qx = (index % width).to(pix.dtype)
        qy = torch.div(index, width, rounding_mode="floor").to(pix.dtype)
        p0, p1, p2 = pix[corners[:, 0]], pix[corners[:, 1]], pix[corners[:, 2]]
        e1, e2 = p1 - p0, p2 - p0
        rx, ry = qx - p0[:, 0], qy - p0[:, 1]
        area2 = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        b1 = (rx * e2[:, 1] - ry * e2[:, 0]) / area2
        b2 = (e1[:, 0] * ry - e1[:, 1] * rx) / area2
        b0 = 1.0 - b1 - b2
        attributes = attributes.to(pix.dtype) if attributes.dtype != pix.dtype else attributes
        values = (b0[:, None] * attributes[corners[:, 0]] + b1[:, None] * attributes[corners[:, 1]]
                  + b2[:, None] * attributes[corners[:, 2]])
        image = torch.zeros(height * width, attributes.shape[1], dtype=values.dtype).index_copy(0, index, values)
        return image.reshape(height, width, -1), fragments.mask


# ------------------------------------------------------------------------------------------ rendering


@dataclass(frozen=True)
class Light:
    """Lambert + ambient: colour * (ambient + (1 - ambient) * max(0, n . l)), `direction` (toward the light) in
    camera coordinates (x right, y up, z toward the viewer)."""

    direction: tuple[float, float, float] = DEFAULT_LIGHT_DIRECTION
    ambient: float = 0.35


def project_camera(points_cam: torch.Tensor, camera: Intrinsics) -> tuple[torch.Tensor, torch.Tensor]:
    """(V, 3) camera coordinates -> (V, 2) pixels of `camera` and (V,) depth in front of it (as `camera.project`)."""
    depth = -points_cam[:, 2]
    safe = depth.clamp_min(1e-6)
    u = camera.cx + camera.fx * points_cam[:, 0] / safe
    v = camera.cy - camera.fy * points_cam[:, 1] / safe
    return torch.stack([u, v], dim=-1), depth


def project_to_crop(vertices: torch.Tensor, rotation, translation, camera: Intrinsics, crop: Crop
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """(V, 3) mesh points in pose (rotation (3,), translation (3,)) -> (V, 2) grid coordinates of `crop` and (V,)
    depth, differentiable (what `render_crop` rasterises)."""
    vertices = torch.as_tensor(vertices)
    dtype = vertices.dtype if vertices.is_floating_point() else torch.float32
    cam = to_camera(vertices.to(dtype)[None], torch.as_tensor(rotation, dtype=dtype).reshape(1, 3),
                    torch.as_tensor(translation, dtype=dtype).reshape(1, 3))[0]
    return project_camera(cam, crop.intrinsics(camera))


def render_crop(vertices_mesh: torch.Tensor, rotation, translation, camera: Intrinsics, crop: Crop,
                faces_subset: np.ndarray | None, albedo, light: Light | None = None,
                rasterizer: CropRasterizer | None = None, return_fragments: bool = False,
                fragments: Fragments | None = None):
    """Render the triangles `faces_subset` (K, 3) of a mesh (V, 3) in pose (rotation (3,) axis-angle, translation
    (3,)) on `crop`'s grid: (image (H, W, 3), mask (H, W) bool) [, fragments]; background pixels are 0.

    `albedo` (V, 3) in [0, 1]; with a `light`, times the Lambert + ambient term of the vertex normals (computed from
    `faces_subset` only). Differentiable w.r.t. vertices, pose and albedo. Pass a `rasterizer` made for the same
    faces and crop to reuse it (`faces_subset` is then ignored); then `vertices_mesh` and `albedo` may also hold
    only the rows `rasterizer.vertex_ids` (faster: e.g. `evaluate_rig(rig, w, rasterizer.vertex_ids)`).
    Full-mesh inputs are cut to those rows before any work. `fragments` from an earlier call (same rasteriser)
    skip the rasterisation: within an optimisation the visibility changes little between iterations, and the
    barycentrics are still recomputed, so gradients stay exact for the given fragments.
    """
    vertices = torch.as_tensor(vertices_mesh)
    dtype = vertices.dtype if vertices.is_floating_point() else torch.float32
    vertices = vertices.to(dtype)
    rotation = torch.as_tensor(rotation, dtype=dtype).reshape(1, 3)
    translation = torch.as_tensor(translation, dtype=dtype).reshape(1, 3)
    albedo = torch.as_tensor(albedo, dtype=dtype)
    if rasterizer is None:
        rasterizer = CropRasterizer(np.asarray(faces_subset), crop)
    if len(vertices) != len(rasterizer.vertex_ids) or len(albedo) != len(rasterizer.vertex_ids):
        rows = torch.as_tensor(rasterizer.vertex_ids)
        if len(vertices) != len(rasterizer.vertex_ids):
            vertices = vertices.index_select(0, rows)
        if len(albedo) != len(rasterizer.vertex_ids):
            albedo = albedo.index_select(0, rows)
    cam = to_camera(vertices[None], rotation, translation)[0]
    pix, depth = project_camera(cam, crop.intrinsics(camera))
    if fragments is None:
        fragments = rasterizer.rasterize(pix, depth)
    colors = albedo
    if light is not None:
        direction = torch.as_tensor(light.direction, dtype=dtype)
        direction = direction / direction.norm()
        lambert = (vertex_normals(cam, rasterizer.faces_for(len(cam))) @ direction).clamp(0.0, 1.0)
        colors = albedo * (light.ambient + (1.0 - light.ambient) * lambert)[:, None]
    image, mask = rasterizer.interpolate(fragments, pix, colors)
    return (image, mask, fragments) if return_fragments else (image, mask)


def rgb_loss(rendered: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Eq. 3: mean over the pixels of `mask` (H, W) of ||I_p - I'_p||^2 (squared RGB distance, values in [0, 1])."""
    weight = mask.to(rendered.dtype)
    squared = ((rendered - target.to(rendered.dtype)) ** 2).sum(dim=-1)
    return (squared * weight).sum() / weight.sum().clamp_min(1.0)


# ------------------------------------------------------------------------------------------ albedo


def visible_vertices(fragments: Fragments, pix, depth, tolerance: float = 0.005) -> np.ndarray:
    """(V,) bool: vertices whose colour can be read from a rendered or real image at `pix` (V, 2) grid coordinates.

    A vertex (depth (V,) in front of the camera) counts as seen when the 2 x 2 pixels a bilinear sample at its
    position reads all lie in the grid, are covered, and show a surface within `tolerance` x its depth of the
    vertex's own depth: it is not hidden (a nearer surface would fail the test), and the sample mixes in neither
    background nor a surface behind a silhouette. Per-vertex inputs in either indexing of the rasteriser.
    """
    pix = np.asarray(torch.as_tensor(pix).detach(), np.float64)
    depth = np.asarray(torch.as_tensor(depth).detach(), np.float64)
    zbuf = fragments.depth.numpy().astype(np.float64)  # +inf where not covered
    height, width = zbuf.shape
    ok = np.isfinite(pix).all(axis=1) & np.isfinite(depth) & (depth > NEAR)
    safe = np.where(ok[:, None], pix, -10.0).clip(-10.0, 1e9)
    col0, row0 = np.floor(safe[:, 0]).astype(np.int64), np.floor(safe[:, 1]).astype(np.int64)
    # an exact integer coordinate reads one pixel (weights 1, 0): allow the pair to step back inside the grid
    col0 = np.where(col0 == width - 1, col0 - 1, col0)
    row0 = np.where(row0 == height - 1, row0 - 1, row0)
    ok &= (col0 >= 0) & (col0 + 1 < width) & (row0 >= 0) & (row0 + 1 < height)
    ids = np.flatnonzero(ok)
    seen = np.ones(len(ids), bool)
    limit = tolerance * depth[ids]
    for dr_, dc in ((0, 0), (0, 1), (1, 0), (1, 1)):
        z = zbuf[row0[ids] + dr_, col0[ids] + dc]
        seen &= np.abs(z - depth[ids]) <= limit
    visible = np.zeros(len(pix), bool)
    visible[ids[seen]] = True
    return visible


def sample_bilinear(image: np.ndarray, pix: np.ndarray) -> np.ndarray:
    """(N, C) float colours of `image` (H, W, C) at (N, 2) pixel coordinates (edge pixels repeated outside)."""
    image = np.asarray(image, np.float32)
    height, width = image.shape[:2]
    u = np.clip(pix[:, 0], 0, width - 1)
    v = np.clip(pix[:, 1], 0, height - 1)
    u0 = np.clip(np.floor(u).astype(np.int64), 0, max(width - 2, 0))
    v0 = np.clip(np.floor(v).astype(np.int64), 0, max(height - 2, 0))
    u1, v1 = np.minimum(u0 + 1, width - 1), np.minimum(v0 + 1, height - 1)
    fu, fv = (u - u0)[:, None], (v - v0)[:, None]
    top = image[v0, u0] * (1 - fu) + image[v0, u1] * fu
    bottom = image[v1, u0] * (1 - fu) + image[v1, u1] * fu
    return top * (1 - fv) + bottom * fv


def estimate_albedo(frames, pix_per_frame, visible, faces: np.ndarray | None = None,
                    default=(0.5, 0.5, 0.5), fill_rounds: int = 50) -> np.ndarray:
    """(V, 3) float32 per-vertex albedo in [0, 1]: the median over frames of the (bilinear) image colour at the
    vertex's projected position, over the frames where `visible` says it is seen.

    `frames` (H, W, 3) uint8 (or float in [0, 1]); `pix_per_frame` (V, 2) pixel coordinates in those images (full
    frames: `project`; crop images: `Crop.to_crop` of it); `visible` (V,) bool (see `visible_vertices`). Vertices
    never seen take the mean of their seen neighbours over `faces` (spreading up to `fill_rounds` rings), then the
    median of all seen vertices (or `default` when none was seen).
    """
    if not (len(frames) == len(pix_per_frame) == len(visible)):
        raise ValueError("frames, pix_per_frame and visible must have one entry per frame")
    if len(frames) == 0:
        raise ValueError("no frames")
    n_vertices = len(pix_per_frame[0])
    samples = np.full((len(frames), n_vertices, 3), np.nan, np.float32)
    for k, (frame, pix, seen) in enumerate(zip(frames, pix_per_frame, visible)):
        frame = np.asarray(frame)
        scale = 255.0 if frame.dtype == np.uint8 else 1.0
        pix = np.asarray(pix, np.float64)
        seen = np.asarray(seen, bool) & np.isfinite(pix).all(axis=1)
        ids = np.flatnonzero(seen)
        samples[k, ids] = sample_bilinear(frame, pix[ids]) / scale
    known = ~np.isnan(samples[..., 0]).all(axis=0)
    albedo = np.zeros((n_vertices, 3), np.float32)
    if known.any():
        albedo[known] = np.nanmedian(samples[:, known], axis=0)
    if faces is not None and known.any() and not known.all():
        faces = np.asarray(faces, np.int64)
        a = faces.reshape(-1)
        b = np.roll(faces, -1, axis=1).reshape(-1)
        src, dst = np.concatenate([a, b]), np.concatenate([b, a])
        for _ in range(fill_rounds):
            if known.all():
                break
            use = known[src] & ~known[dst]
            if not use.any():
                break
            total = np.zeros((n_vertices, 3), np.float64)
            count = np.zeros(n_vertices, np.float64)
            np.add.at(total, dst[use], albedo[src[use]])
            np.add.at(count, dst[use], 1.0)
            new = count > 0
            albedo[new] = (total[new] / count[new, None]).astype(np.float32)
            known = known | new
    if not known.all():
        fallback = np.median(albedo[known], axis=0) if known.any() else np.asarray(default, np.float32)
        albedo[~known] = fallback
    return np.clip(albedo, 0.0, 1.0).astype(np.float32)
