"""Ground-truth camera for the synthetic corpus: pinhole projection and a z-buffered numpy triangle rasteriser.

Not differentiable and not torch: it makes the frames a tracker is tested on, so it has to be exact, not smooth.

Conventions
-----------
* Mesh coordinates are the rig's: x to the subject's left (image right in a frontal view), y up, +z out of the
  face toward a frontal viewer; units as the mesh (the demo rig: centimetres).
* `Pose` maps mesh to camera coordinates, X_cam = R(rotation) X + translation, and camera coordinates keep the
  same axes (x right, y up, the camera looks down -z, OpenGL style). So the zero rotation is a frontal view and
  `Pose(translation=(0, 0, -80))` puts the mesh origin 80 units in front of the camera. `Pose.opencv_extrinsics`
  gives the same pose in OpenCV's convention (y down, z forward) for `cv2.projectPoints`.
* Pixels: u = cx + fx * X / d, v = cy - fy * Y / d with depth d = -Z_cam; integer (u, v) is a pixel's centre
  (OpenCV's convention); images are (height, width, 3) RGB uint8.

Rasterisation samples pixel centres: a pixel belongs to a triangle when its centre lies inside (edges included);
the nearest fragment wins (depth compared as 1/d, which is affine in screen space, so the z-buffer is exact for
planar triangles). Colours are per-vertex, shaded per vertex (Lambert + ambient from area-weighted vertex normals)
and interpolated linearly in screen space (Gouraud); a textured mesh (`MeshTexture`) multiplies that interpolated
light by its face's base colour and bilinearly sampled texel. Triangles with a vertex closer than `near` are dropped, not
clipped. The fast path enumerates every triangle's bounding-box pixels at once in numpy; `rasterize_reference` is
the plain per-triangle loop it is tested and benchmarked against.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from visemeflow.render.camera import Intrinsics

DEFAULT_LIGHT = (0.35, 0.45, 1.0)
"""Light direction in camera coordinates (toward the light): from the viewer's upper right, mostly frontal."""
DEFAULT_BACKGROUND = (60, 62, 70)
NEAR = 1e-3
_EDGE_EPS = 1e-7
_BATCH_PIXELS = 1 << 21


# The same pinhole model as the tracker's (intrinsics are plain data; the renderers stay separate).
Camera = Intrinsics


@dataclass(frozen=True)
class Pose:
    """Rigid head pose: `rotation` (3,) axis-angle in radians, `translation` (3,) in mesh units (see module doc)."""

    rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    translation: tuple[float, float, float] = (0.0, 0.0, -80.0)

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) rotation matrix of `rotation` (Rodrigues)."""
        return rotation_matrix(self.rotation)

    def opencv_extrinsics(self) -> tuple[np.ndarray, np.ndarray]:
        """(rvec, tvec) for cv2.projectPoints: this pose followed by the flip to y-down, z-forward axes."""
        import cv2

        flip = np.diag([1.0, -1.0, -1.0])
        rvec, _ = cv2.Rodrigues(flip @ self.matrix)
        return rvec.reshape(3), flip @ np.asarray(self.translation, np.float64)


def rotation_matrix(axis_angle) -> np.ndarray:
    """(3, 3) rotation of an axis-angle vector (radians)."""
    r = np.asarray(axis_angle, np.float64).reshape(3)
    angle = float(np.linalg.norm(r))
    if angle < 1e-12:
        return np.eye(3)
    k = r / angle
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * cross + (1.0 - math.cos(angle)) * (cross @ cross)


def to_camera(points: np.ndarray, pose: Pose) -> np.ndarray:
    """(N, 3) mesh points -> (N, 3) camera coordinates (x right, y up, looking down -z)."""
    return np.asarray(points, np.float64) @ pose.matrix.T + np.asarray(pose.translation, np.float64)


def project(points: np.ndarray, camera: Camera, pose: Pose) -> np.ndarray:
    """(N, 3) mesh points -> (N, 2) pixel coordinates (u right, v down); points must lie in front of the camera."""
    cam = to_camera(points, pose)
    depth = -cam[:, 2]
    return np.stack([camera.cx + camera.fx * cam[:, 0] / depth, camera.cy - camera.fy * cam[:, 1] / depth], axis=1)


def frontal_pose(points: np.ndarray, camera: Camera, fill: float = 0.6, rotation=(0.0, 0.0, 0.0)) -> Pose:
    """A pose that centres `points` (N, 3) in the image with their height spanning `fill` of the image height.

    Sized on the unrotated points' bounding box at its middle depth; `rotation` is then applied about the mesh origin.
    """
    points = np.asarray(points, np.float64)
    low, high = points.min(axis=0), points.max(axis=0)
    centre = (low + high) / 2.0
    distance = camera.fy * float(high[1] - low[1]) / (fill * camera.height)
    # the principal point may sit off centre; shift so the bounding-box centre lands on the image centre
    dx = ((camera.width - 1) / 2.0 - camera.cx) * distance / camera.fx
    dy = -((camera.height - 1) / 2.0 - camera.cy) * distance / camera.fy
    rotated_centre = rotation_matrix(rotation) @ centre
    translation = np.array([dx, dy, -distance]) - rotated_centre
    return Pose(tuple(float(r) for r in rotation), tuple(float(t) for t in translation))


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) unit normals: area-weighted sums of the normals of counter-clockwise triangles; 0 for loose vertices."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    face_normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    ids = f.ravel()
    repeated = np.repeat(face_normals, 3, axis=0)
    normals = np.stack([np.bincount(ids, weights=repeated[:, k], minlength=len(v)) for k in range(3)], axis=1)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


def shade_vertices(
    vertices_cam: np.ndarray, faces: np.ndarray, colors: np.ndarray, light_dir=DEFAULT_LIGHT, ambient: float = 0.35
) -> np.ndarray:
    """(V, 3) shaded RGB in [0, 1]: colour * (ambient + (1 - ambient) * max(0, n . l)), n and l in camera space."""
    light = np.asarray(light_dir, np.float64)
    light = light / np.linalg.norm(light)
    lambert = np.clip(vertex_normals(vertices_cam, faces) @ light, 0.0, 1.0)
    intensity = ambient + (1.0 - ambient) * lambert
    return np.asarray(colors, np.float64) * intensity[:, None]


@dataclass(frozen=True)
class Fragments:
    """The visible fragment of every covered pixel: flat pixel index (y * W + x), triangle, barycentrics, depth."""

    pixel: np.ndarray
    """(N,) int64"""
    triangle: np.ndarray
    """(N,) int64 row of `faces`"""
    barycentric: np.ndarray
    """(N, 3) float64, weights of the triangle's three vertices"""
    depth: np.ndarray
    """(N,) float64 distance along the view axis"""


@dataclass(frozen=True)
class Raster:
    """Per-pixel result of `rasterize`: triangle id (-1 = background), barycentrics and depth (inf = background)."""

    triangle_id: np.ndarray
    """(H, W) int64"""
    barycentric: np.ndarray
    """(H, W, 3) float32"""
    depth: np.ndarray
    """(H, W) float32"""


def _screen(vertices: np.ndarray, camera: Camera, pose: Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    cam = to_camera(vertices, pose)
    depth = -cam[:, 2]
    safe = np.where(depth > NEAR, depth, 1.0)
    uv = np.stack([camera.cx + camera.fx * cam[:, 0] / safe, camera.cy - camera.fy * cam[:, 1] / safe], axis=1)
    return cam, uv, depth


@dataclass(frozen=True)
class _Candidates:
    """Triangles that can cover a pixel centre: ids, corner screen coordinates, signed area, clipped pixel box."""

    tri: np.ndarray
    corners: np.ndarray
    """(3, n) vertex ids"""
    u: np.ndarray
    """(3, n)"""
    v: np.ndarray
    """(3, n)"""
    area: np.ndarray
    x0: np.ndarray
    x1: np.ndarray
    y0: np.ndarray
    y1: np.ndarray


def _candidate_triangles(
    uv: np.ndarray, depth: np.ndarray, faces: np.ndarray, width: int, height: int, cull_backfaces: bool
) -> _Candidates:
    # (3, F) layouts and np.take: column gathers on these are several times faster than fancy indexing
    corners = np.ascontiguousarray(faces.T)
    u = np.take(np.ascontiguousarray(uv[:, 0]), corners)
    v = np.take(np.ascontiguousarray(uv[:, 1]), corners)
    d = np.take(depth, corners)
    # signed doubled area in image coordinates (v down): negative for triangles counter-clockwise in camera space
    area = (u[1] - u[0]) * (v[2] - v[0]) - (u[2] - u[0]) * (v[1] - v[0])
    keep = np.minimum(np.minimum(d[0], d[1]), d[2]) > NEAR
    keep &= (area < -1e-12) if cull_backfaces else (np.abs(area) > 1e-12)
    x0 = np.maximum(np.ceil(np.minimum(np.minimum(u[0], u[1]), u[2])), 0)
    x1 = np.minimum(np.floor(np.maximum(np.maximum(u[0], u[1]), u[2])), width - 1)
    y0 = np.maximum(np.ceil(np.minimum(np.minimum(v[0], v[1]), v[2])), 0)
    y1 = np.minimum(np.floor(np.maximum(np.maximum(v[0], v[1]), v[2])), height - 1)
    keep &= (x0 <= x1) & (y0 <= y1)
    tri = np.flatnonzero(keep)
    box = np.take(np.stack([x0, x1, y0, y1]), tri, axis=1).astype(np.int64)
    return _Candidates(
        tri, np.take(corners, tri, axis=1), np.take(u, tri, axis=1), np.take(v, tri, axis=1), area[tri], *box
    )


def _box_fragments(cand: _Candidates, lo: int, hi: int, depth: np.ndarray, width: int) -> tuple[np.ndarray, ...]:
    """Fragments inside candidates lo..hi: flat pixel, candidate index, barycentrics b1, b2 and 1/depth."""
    u, v = cand.u[:, lo:hi], cand.v[:, lo:hi]
    x0, y0 = cand.x0[lo:hi], cand.y0[lo:hi]
    inv = 1.0 / cand.area[lo:hi]
    # barycentrics of corners 1 and 2 as affine functions of the pixel offset (dx, dy) from the box corner (x0, y0)
    ex, ey = x0 - u[0], y0 - v[0]
    b1_dx, b1_dy = (v[2] - v[0]) * inv, (u[0] - u[2]) * inv
    b2_dx, b2_dy = (v[0] - v[1]) * inv, (u[1] - u[0]) * inv
    b1_at, b2_at = b1_dx * ex + b1_dy * ey, b2_dx * ex + b2_dy * ey

    # every pixel centre of every box, without a division: boxes -> rows (owner, dy) -> pixels (owner, dy, dx)
    box_w, box_h = cand.x1[lo:hi] - x0 + 1, cand.y1[lo:hi] - y0 + 1
    row_owner = np.repeat(np.arange(hi - lo), box_h)
    row_dy = np.arange(row_owner.size) - np.repeat(np.cumsum(box_h) - box_h, box_h)
    row_w = box_w[row_owner]
    owner = np.repeat(row_owner, row_w)
    dy = np.repeat(row_dy, row_w)
    dx = np.arange(owner.size) - np.repeat(np.cumsum(row_w) - row_w, row_w)
    # one gather per coefficient column: faster than gathering rows of a (n, 6) table
    b1 = b1_dx[owner] * dx + b1_dy[owner] * dy + b1_at[owner]
    b2 = b2_dx[owner] * dx + b2_dy[owner] * dy + b2_at[owner]
    inside = np.flatnonzero((b1 >= -_EDGE_EPS) & (b2 >= -_EDGE_EPS) & (b1 + b2 <= 1.0 + _EDGE_EPS))
    owner, b1, b2 = owner[inside], b1[inside], b2[inside]
    pixel = (y0[owner] + dy[inside]) * width + (x0[owner] + dx[inside])
    inv_depth = 1.0 / depth[cand.corners[:, lo:hi]]
    inv_z = (1.0 - b1 - b2) * inv_depth[0, owner] + b1 * inv_depth[1, owner] + b2 * inv_depth[2, owner]
    return pixel, owner + lo, b1, b2, inv_z


def _nearest_per_pixel(pixel: np.ndarray, inv_z: np.ndarray, n_pixels: int) -> np.ndarray:
    """Indices of the nearest fragment of each covered pixel; equal depths go to the earliest fragment."""
    nearest = np.zeros(n_pixels)
    np.maximum.at(nearest, pixel, inv_z)
    win = np.flatnonzero(inv_z >= nearest[pixel])
    if win.size > np.count_nonzero(nearest):
        # equal depths (shared edges and vertices) leave several winners for one pixel: keep the first
        win = win[np.argsort(pixel[win], kind="stable")]
        first = np.ones(win.size, bool)
        first[1:] = pixel[win[1:]] != pixel[win[:-1]]
        win = win[first]
    return win


def rasterize_fragments(
    vertices: np.ndarray, faces: np.ndarray, camera: Camera, pose: Pose, cull_backfaces: bool = True
) -> Fragments:
    """The visible fragment per covered pixel, in no particular pixel order (fast path: the bounding-box pixels of
    many triangles at once).

    Triangles go in batches of at most `_BATCH_PIXELS` box pixels, so memory stays bounded when the camera is close;
    a face at video size is one batch. Later batches merge into a running per-pixel z-buffer. Equal depths go to
    the earlier triangle, as in `rasterize_reference`.
    """
    faces = np.asarray(faces, np.int64)
    _, uv, depth = _screen(vertices, camera, pose)
    width, n_pixels = camera.width, camera.width * camera.height
    cand = _candidate_triangles(uv, depth, faces, camera.width, camera.height, cull_backfaces)
    ends = np.cumsum((cand.x1 - cand.x0 + 1) * (cand.y1 - cand.y0 + 1))
    bounds = [0]
    while bounds[-1] < cand.tri.size:
        start = ends[bounds[-1] - 1] if bounds[-1] else 0
        bounds.append(max(int(np.searchsorted(ends, start + _BATCH_PIXELS, side="right")), bounds[-1] + 1))
    if len(bounds) <= 2:
        pixel, owner, b1, b2, inv_z = _box_fragments(cand, 0, cand.tri.size, depth, width)
        win = _nearest_per_pixel(pixel, inv_z, n_pixels)
        b1, b2 = b1[win], b2[win]
        return Fragments(pixel[win], cand.tri[owner[win]], np.column_stack([1.0 - b1 - b2, b1, b2]), 1.0 / inv_z[win])
    best_z = np.zeros(n_pixels)
    best_tri = np.full(n_pixels, -1, np.int64)
    best_b = np.zeros((n_pixels, 2))
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        pixel, owner, b1, b2, inv_z = _box_fragments(cand, lo, hi, depth, width)
        win = _nearest_per_pixel(pixel, inv_z, n_pixels)
        win = win[inv_z[win] > best_z[pixel[win]]]
        at = pixel[win]
        best_z[at] = inv_z[win]
        best_tri[at] = cand.tri[owner[win]]
        best_b[at, 0], best_b[at, 1] = b1[win], b2[win]
    covered = np.flatnonzero(best_tri >= 0)
    b1, b2 = best_b[covered, 0], best_b[covered, 1]
    return Fragments(covered, best_tri[covered], np.column_stack([1.0 - b1 - b2, b1, b2]), 1.0 / best_z[covered])


def rasterize_reference(
    vertices: np.ndarray, faces: np.ndarray, camera: Camera, pose: Pose, cull_backfaces: bool = True
) -> Fragments:
    """Same result as `rasterize_fragments`, one triangle at a time with a running z-buffer (slow, plain)."""
    faces = np.asarray(faces, np.int64)
    _, uv, depth = _screen(vertices, camera, pose)
    width, height = camera.width, camera.height
    cand = _candidate_triangles(uv, depth, faces, width, height, cull_backfaces)
    nearest = np.zeros((height, width))
    owner = np.full((height, width), -1, np.int64)
    bary = np.zeros((height, width, 3))
    for i, t in enumerate(cand.tri):
        a, b, c = uv[faces[t]]
        area = cand.area[i]
        ys, xs = np.mgrid[cand.y0[i] : cand.y1[i] + 1, cand.x0[i] : cand.x1[i] + 1].astype(np.float64)
        w1 = ((xs - a[0]) * (c[1] - a[1]) - (ys - a[1]) * (c[0] - a[0])) / area
        w2 = ((b[0] - a[0]) * (ys - a[1]) - (b[1] - a[1]) * (xs - a[0])) / area
        w0 = 1.0 - w1 - w2
        inside = (w1 >= -_EDGE_EPS) & (w2 >= -_EDGE_EPS) & (w0 >= -_EDGE_EPS)
        inv_d = 1.0 / depth[faces[t]]
        inv_z = w0 * inv_d[0] + w1 * inv_d[1] + w2 * inv_d[2]
        window = (slice(cand.y0[i], cand.y1[i] + 1), slice(cand.x0[i], cand.x1[i] + 1))
        closer = inside & (inv_z > nearest[window])
        nearest[window][closer] = inv_z[closer]
        owner[window][closer] = t
        bary[window][closer] = np.stack([w0, w1, w2], axis=-1)[closer]
    covered = np.flatnonzero(owner.ravel() >= 0)
    return Fragments(
        pixel=covered,
        triangle=owner.ravel()[covered],
        barycentric=bary.reshape(-1, 3)[covered],
        depth=1.0 / nearest.ravel()[covered],
    )


def rasterize(vertices: np.ndarray, faces: np.ndarray, camera: Camera, pose: Pose, cull_backfaces: bool = True) -> Raster:
    """Per-pixel triangle ids, barycentrics and depth of the visible surface."""
    fragments = rasterize_fragments(vertices, faces, camera, pose, cull_backfaces)
    n = camera.width * camera.height
    ids = np.full(n, -1, np.int64)
    bary = np.zeros((n, 3), np.float32)
    depth = np.full(n, np.inf, np.float32)
    ids[fragments.pixel] = fragments.triangle
    bary[fragments.pixel] = fragments.barycentric
    depth[fragments.pixel] = fragments.depth
    shape = (camera.height, camera.width)
    return Raster(ids.reshape(shape), bary.reshape(shape + (3,)), depth.reshape(shape))


@dataclass(frozen=True, eq=False)
class MeshTexture:
    """What colours a textured mesh: per vertex texture coordinates, per face a base colour and which image (if any)
    multiplies it. Images are sampled bilinearly, wrapping (glTF's default sampler), at the fragment's coordinates
    interpolated in screen space."""

    uv: np.ndarray
    """(V, 2) float32 texture coordinates, origin at the image's top left (glTF's): column u * W, row v * H."""
    face_image: np.ndarray
    """(F,) int64 index into `images`, -1 for a face without one."""
    face_color: np.ndarray
    """(F, 3) float RGB in [0, 1] (display values, as vertex colours): the face's base colour."""
    images: tuple[np.ndarray, ...] = ()
    """(H, W, 3) uint8 RGB images (display values)."""

    def sample(self, triangle: np.ndarray, corners: np.ndarray, w: np.ndarray) -> np.ndarray:
        """(N, 3) float32 colours in [0, 1] of fragments of faces `triangle` with vertices `corners` (N, 3) and
        barycentrics `w` (N, 3)."""
        rgb = np.asarray(self.face_color, np.float32)[triangle]
        which = np.asarray(self.face_image, np.int64)[triangle]
        uv = np.einsum("nk,nkc->nc", w.astype(np.float32), np.asarray(self.uv, np.float32)[corners])
        for k, image in enumerate(self.images):
            mine = np.flatnonzero(which == k)
            if mine.size:
                rgb[mine] *= _bilinear(image, uv[mine])
        return rgb


def _bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N, 3) float32 in [0, 1]: `image` (H, W, 3) uint8 at texture coordinates `uv` (N, 2), bilinear, wrapping at
    the edges (OpenCV's remap: texel centres at (i + 0.5) / W)."""
    import cv2

    h, w = image.shape[:2]
    n = len(uv)
    columns = 1024                              # remap's maps: rows of at most this many points
    rows = -(-n // columns)
    maps = np.zeros((2, rows * columns), np.float32)
    maps[0, :n] = uv[:, 0] * w - 0.5
    maps[1, :n] = uv[:, 1] * h - 0.5
    maps = maps.reshape(2, rows, columns)
    texels = cv2.remap(np.ascontiguousarray(image), maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return texels.reshape(-1, 3)[:n].astype(np.float32) / np.float32(255.0)


@dataclass(frozen=True, eq=False)
class Backdrop:
    """Fixed geometry rendered once (`render_backdrop`): its image and depth, for meshes drawn in front of it frame
    after frame (`render_mesh(..., backdrop=)`) at the cost of the moving mesh alone."""

    image: np.ndarray
    """(H * W, 3) uint8 RGB."""
    depth: np.ndarray
    """(H * W,) float64 distance along the view axis, inf where nothing is."""


def render_backdrop(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None, camera: Camera, pose: Pose,
                    texture: MeshTexture | None = None, **options) -> Backdrop:
    """The Backdrop of a mesh that does not move (arguments as `render_mesh`). Drawing a mesh M over it equals
    drawing M and this mesh as one, M's faces first (equal depths go to M), as long as the two share no vertex:
    each shades with its own normals."""
    depth = np.full(camera.width * camera.height, np.inf)
    image = render_mesh(vertices, faces, colors, camera, pose, texture=texture, _depth=depth, **options)
    return Backdrop(image.reshape(-1, 3), depth)


def render_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    colors: np.ndarray | None,
    camera: Camera,
    pose: Pose,
    light_dir=DEFAULT_LIGHT,
    ambient: float = 0.35,
    background=DEFAULT_BACKGROUND,
    cull_backfaces: bool = True,
    reference: bool = False,
    texture: MeshTexture | None = None,
    backdrop: Backdrop | None = None,
    _depth: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W, 3) uint8 RGB image of the mesh (vertices (V, 3), faces (F, 3), colors (V, 3) in [0, 1] or None = grey).

    `light_dir` is in camera coordinates (x right, y up, z toward the viewer); `reference=True` rasterises with the
    slow per-triangle loop (for checks and benchmarks). With `texture`, each fragment's colour is its face's base
    colour times its image's texel (times the vertex colours, when given), lit by the shading interpolated from the
    vertices. With `backdrop` (`render_backdrop`, same camera and pose), the mesh is drawn over it where it is at
    least as near (`background` is then the backdrop's).
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    image = np.empty((camera.height * camera.width, 3), np.uint8)
    image[:] = np.asarray(background, np.uint8) if backdrop is None else backdrop.image
    raster = rasterize_reference if reference else rasterize_fragments
    fragments = raster(vertices, faces, camera, pose, cull_backfaces)
    if backdrop is not None:
        front = fragments.depth <= backdrop.depth[fragments.pixel]
        fragments = Fragments(fragments.pixel[front], fragments.triangle[front], fragments.barycentric[front],
                              fragments.depth[front])
    if _depth is not None:
        _depth[fragments.pixel] = fragments.depth
    if fragments.pixel.size and texture is not None:
        light = shade_vertices(to_camera(vertices, pose), faces, np.ones((len(vertices), 3)) if colors is None
                               else colors, light_dir, ambient)
        corners = faces[fragments.triangle]
        w = fragments.barycentric
        rgb = np.einsum("nk,nkc->nc", w, light[corners]) * texture.sample(fragments.triangle, corners, w)
        image[fragments.pixel] = np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
    elif fragments.pixel.size:
        if colors is None:
            colors = np.full((len(vertices), 3), 0.75)
        shaded = shade_vertices(to_camera(vertices, pose), faces, colors, light_dir, ambient)
        corners = faces[fragments.triangle]
        w = fragments.barycentric
        rgb = w[:, 0:1] * shaded[corners[:, 0]] + w[:, 1:2] * shaded[corners[:, 1]] + w[:, 2:3] * shaded[corners[:, 2]]
        image[fragments.pixel] = np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return image.reshape(camera.height, camera.width, 3)
