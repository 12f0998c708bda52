"""Marker pairs found without a person: MediaPipe FaceMesh on renders of the template and of the target.

Deformation transfer onto a mesh of another topology needs corresponding points to place the template before the
non-rigid ICP (`visemeflow.authoring.transfer`). Instead of a person clicking them, both neutral meshes are rendered
frontally by the synthetic corpus's rasteriser (grey Lambert shading, `visemeflow.render.raster`), FaceMesh finds
its 468 face points on each render, and each point is read back onto the mesh through the rasteriser's triangle and
barycentric buffers: the visible vertex under the point. Two passes per mesh: the first frames the whole mesh, the
second zooms onto the face it found (the face spans about 60% of the image), which roughly halves the points'
scatter on a full head.

A point becomes a pair when it lands on both meshes, on a surface facing the camera (the vertex normal's z in the
camera frame at least `min_facing`: points on the silhouette slide off it), and, on the template, outside the
regions the transfer carries over rigidly (mouth interior, eyes). The pairs then go through a trimmed similarity
fit: three rounds of Umeyama, each dropping the pairs whose residual exceeds `trim` times the median residual (a
point FaceMesh placed differently on the two faces, e.g. on a jaw line seen at another angle).

Measured on the test face of another topology (the ICT face of another identity, Loop-subdivided, turned 20
degrees, scaled 1.15; tests/test_transfer.py): 352 pairs, their target points 2.4 mm from the true correspondence
(median; 6.5 mm at the 90th percentile, on a 30 cm face), and the transfer with them registers to 0.135% of the
face's size (0.12% with the 68 true landmarks) and passes the same landmark checks.

Limits: the meshes must look like a human face from the front (+z toward the viewer, +y up, as the template);
a stylised face FaceMesh does not recognise gets a TransferError asking for marker pairs. A mesh turned more than
about 30 degrees from the template's facing finds fewer points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from visemeflow.animation.fit import similarity

__all__ = ["AutoMarkers", "NoFaceFound", "automatic_markers", "mesh_face_points"]

N_FACE_POINTS = 468
"""FaceMesh's face points (the 10 iris points after them sit on the eyeballs and are not used)."""


class NoFaceFound(ValueError):
    """FaceMesh found no face on a render of the mesh."""


@dataclass
class AutoMarkers:
    """What `automatic_markers` found."""

    pairs: np.ndarray
    """(n, 2) int64 (template vertex, target vertex)."""
    detected: tuple[int, int]
    """Face points read back onto (template, target)."""
    paired: int
    """Points on both meshes that passed the facing and region filters (before the trimmed fit)."""
    similarity_residual: float
    """Median distance of the kept pairs after the similarity fit, in target units."""

    def note(self) -> str:
        return (f"markers found automatically: {len(self.pairs)} pairs from MediaPipe FaceMesh on renders of both "
                f"meshes ({self.detected[0]} / {self.detected[1]} face points on the template / target, {self.paired} "
                f"on both, similarity residual {self.similarity_residual:.4g}); give --markers to place them yourself")


def _render_camera(size: int):
    from visemeflow.render.raster import Camera

    return Camera.from_fov(size, size, 25.0)


def mesh_face_points(vertices, faces, *, size: int = 512, min_facing: float = 0.3, name: str = "mesh") -> np.ndarray:
    """(468,) int64: the mesh vertex under each FaceMesh face point on a frontal render (-1 where a point is off
    the mesh, on a surface turned away from the camera, or not found). NoFaceFound when FaceMesh sees no face."""
    from visemeflow.render.raster import Camera, frontal_pose, rasterize, render_mesh, to_camera, vertex_normals
    from visemeflow.tracking.facemesh import FaceMeshError, detect_frames

    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    camera = _render_camera(size)
    pose = frontal_pose(vertices, camera, fill=0.8)
    points = None
    for zoom in (False, True):
        image = render_mesh(vertices, faces, None, camera, pose)
        try:
            track = detect_frames(image[None], times=[0.0], name=name)
        except FaceMeshError:
            track = None
        if track is None or not track.detected[0]:
            raise NoFaceFound(f"{name}: MediaPipe FaceMesh found no face on a frontal render of the mesh")
        points = track.points[0, :N_FACE_POINTS]
        if not zoom:   # frame the face found: a crop of the image, as intrinsics (same pose)
            low, high = np.nanmin(points, axis=0), np.nanmax(points, axis=0)
            side = 1.6 * float(np.max(high - low))
            x0, y0 = (low + high) / 2.0 - side / 2.0
            s = size / side
            camera = Camera(camera.fx * s, camera.fy * s, (camera.cx - x0) * s, (camera.cy - y0) * s, size, size)
    raster = rasterize(vertices, faces, camera, pose)
    facing = vertex_normals(to_camera(vertices, pose), faces)[:, 2]
    out = np.full(N_FACE_POINTS, -1, np.int64)
    finite = np.isfinite(points).all(axis=1)
    xy = np.full((N_FACE_POINTS, 2), -1, np.int64)
    xy[finite] = np.rint(points[finite]).astype(np.int64)
    inside = finite & (xy[:, 0] >= 0) & (xy[:, 0] < size) & (xy[:, 1] >= 0) & (xy[:, 1] < size)
    for i in np.flatnonzero(inside):
        x, y = xy[i]
        triangle = raster.triangle_id[y, x]
        if triangle < 0:
            continue
        vertex = faces[triangle][int(np.argmax(raster.barycentric[y, x]))]
        if facing[vertex] >= min_facing:
            out[i] = vertex
    return out


def automatic_markers(template_vertices, template_faces, target_vertices, target_faces, *, exclude=(),
                      size: int = 512, trim: float = 3.0, min_pairs: int = 20, max_residual: float = 0.02,
                      target_name: str = "target", template_name: str = "template") -> AutoMarkers:
    """Marker pairs (template vertex, target vertex) from FaceMesh on renders of both meshes (see the module doc).

    `exclude`: template vertex ids that may not be markers (the regions carried over rigidly). ValueError naming
    the mesh when FaceMesh finds no face on it, when fewer than `min_pairs` pairs survive, or when the pairs do not
    fit one similarity transform: a median residual above `max_residual` of the target's size (its bounding-box
    diagonal) means FaceMesh placed its face on something that is not the template's face (it finds a "face" on
    a plain sphere: residual 3.3%; the test face of another identity: 1.0%)."""
    template_vertices = np.asarray(template_vertices, np.float64)
    target_vertices = np.asarray(target_vertices, np.float64)
    on_template = mesh_face_points(template_vertices, template_faces, size=size, name=template_name)
    on_target = mesh_face_points(target_vertices, target_faces, size=size, name=target_name)
    both = (on_template >= 0) & (on_target >= 0)
    both &= ~np.isin(on_template, np.asarray(exclude, np.int64))
    pairs = np.stack([on_template[both], on_target[both]], axis=1)
    paired = len(pairs)
    residual = float("nan")
    for _ in range(3):
        if len(pairs) < min_pairs:
            break
        s, r, t = similarity(template_vertices[pairs[:, 0]], target_vertices[pairs[:, 1]])
        distance = np.linalg.norm(s * template_vertices[pairs[:, 0]] @ r.T + t - target_vertices[pairs[:, 1]], axis=1)
        residual = float(np.median(distance))
        pairs = pairs[distance <= trim * residual]
    if len(pairs) < min_pairs:
        raise ValueError(f"{target_name}: only {len(pairs)} automatic marker pairs (FaceMesh points found on both "
                         f"faces: {paired}); at least {min_pairs} are needed: give marker pairs")
    extent = float(np.linalg.norm(np.ptp(target_vertices, axis=0)))
    if residual > max_residual * extent:
        raise ValueError(f"{target_name}: the {len(pairs)} automatic marker pairs do not fit one similarity "
                         f"transform (median residual {residual:.4g}, {100 * residual / extent:.1f}% of the mesh's "
                         f"size; limit {100 * max_residual:.1f}%): FaceMesh did not find the template's face on it; "
                         "give marker pairs")
    pairs = np.unique(pairs, axis=0)
    return AutoMarkers(pairs.astype(np.int64), (int((on_template >= 0).sum()), int((on_target >= 0).sum())), paired,
                       residual)
