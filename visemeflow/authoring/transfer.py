"""Deformation transfer (Sumner and Popovic 2004): a template's viseme shapes put on a new character's neutral mesh.

`transfer_visemes(template, target_neutral, target_faces, markers=...)` returns the new character (the target's
neutral with one transferred shape per template shape) and a `TransferReport`; `transfer_command` is the
`visemeflow transfer --template RIG --target NEUTRAL.obj|.glb [--markers CSV] --out CHARACTER.glb` command.

Method (docs/transfer.md has the reasoning and the limits):

1. Source gradients. Each template triangle (v1, v2, v3) gets a fourth vertex v4 = v1 + n / sqrt(|n|) (n = the
   cross product of its edges, so v4 - v1 is the unit normal scaled to the triangle's size), and the frame
   V = [v2 - v1, v3 - v1, v4 - v1]. The deformation gradient of shape k is S_k = V_k V_0^-1 (3 x 3).
2. Correspondence. Same topology (identical triangles): target triangle t takes template triangle t. Different
   topology: marker pairs (template vertex, target vertex) give a similarity transform (Umeyama), the template's
   skin is registered onto the target by non-rigid ICP (Amberg's optimal step, `visemeflow.authoring.nricp`,
   markers as its landmarks), and each target triangle takes the gradient of the registered template triangle its centroid is
   closest to (a closest-triangle map). Gradients are turned into the target's frame: R S R^T.
   Without markers the pairs are found automatically: MediaPipe FaceMesh on frontal renders of both meshes, each
   point read back onto the vertex under it (`visemeflow.authoring.automarkers`).
3. One sparse least-squares system. Unknowns: the target's vertex displacements and one fourth vertex per target
   triangle (Sumner's formulation). Rows: sqrt(area_t) (T_t(x) - S_t) for every target triangle, T_t(x) the target
   triangle's gradient, linear in x; the same matrix A for x, y and z and for every shape. Anchors: the target
   vertices whose mapped template displacement stays below `static_tol` (times the template's size) in every
   shape are fixed (eliminated); a connected part with no such vertex (a lower tooth, a face cut to the mouth)
   gets a weak pull of each vertex toward the mapped template displacement, which fixes its translation. A^T A is
   factorised once (SuperLU) and all shapes x 3 coordinates are solved as one right-hand-side matrix.
4. Parts the target lacks (different topology only): the template's `mouth_interior` and `eyes` regions (the demo
   rig's mouth socket, gums, tongue, teeth and eyeballs) are carried over rigidly by the marker similarity
   transform, their shapes' displacements rotated and scaled with it (`carry_parts=False` leaves them out).

numpy / scipy (and MediaPipe for automatic markers); arrays in, a Character out (and files for the
command).
"""

from __future__ import annotations

import csv
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla

from visemeflow.authoring.automarkers import automatic_markers
from visemeflow.authoring.nricp import nricp
from visemeflow.animation.fit import similarity as _similarity
from visemeflow.rig.character import Character, CharacterError, make_character
from visemeflow.rig import N_LANDMARKS, RigError, VisemeRig
from visemeflow.visemes import VISEMES

__all__ = [
    "TransferError",
    "TransferReport",
    "TransferResult",
    "deformation_gradients",
    "read_markers_csv",
    "transfer_command",
    "transfer_visemes",
]

CARRIED_REGIONS = ("mouth_interior", "eyes")
"""Template regions carried over rigidly onto a different-topology target (the target is assumed to be skin)."""


class TransferError(ValueError):
    """A transfer that cannot be done: the message names the input and what is wrong with it."""


@dataclass
class TransferReport:
    """What a transfer did and how well: printed by the command, kept by the caller."""

    mode: str
    """"same topology" or "different topology"."""
    n_vertices: int
    n_triangles: int
    n_shapes: int
    n_anchors: int = 0
    """Target vertices held at the neutral (the template does not move them)."""
    n_soft_vertices: int = 0
    """Vertices of parts with no anchor, weakly pulled toward the mapped template displacement."""
    gradient_residual: dict[str, float] = field(default_factory=dict)
    """Per shape: ||A x - b|| / ||b|| of the gradient rows (0 when the target can follow the template exactly)."""
    icp_residual: float | None = None
    """Different topology: RMS distance of the registered template skin to the target surface, mesh units."""
    icp_residual_relative: float | None = None
    """The same over the target's bounding-box diagonal."""
    marker_residual: float | None = None
    """Different topology: RMS distance of the registered template markers to the target markers, mesh units."""
    n_markers: int = 0
    carried_vertices: int = 0
    time_s: dict[str, float] = field(default_factory=dict)
    """Seconds per stage: "register", "factorise", "solve", "total"."""
    notes: list[str] = field(default_factory=list)

    def lines(self) -> list[str]:
        out = [f"deformation transfer ({self.mode}): {self.n_shapes} shapes onto {self.n_vertices} vertices, "
               f"{self.n_triangles} triangles; {self.n_anchors} anchored vertices, {self.n_soft_vertices} "
               "weakly pulled"]
        if self.icp_residual is not None:
            out.append(f"registration: {self.n_markers} markers, ICP residual {self.icp_residual:.4g} "
                       f"({100 * self.icp_residual_relative:.3f}% of the target's size), marker residual "
                       f"{self.marker_residual:.4g}")
        if self.gradient_residual:
            worst = max(self.gradient_residual, key=self.gradient_residual.get)
            out.append(f"gradient residual: mean {np.mean(list(self.gradient_residual.values())):.4f}, "
                       f"worst {worst} {self.gradient_residual[worst]:.4f}")
        if self.carried_vertices:
            out.append(f"carried over rigidly from the template: {self.carried_vertices} vertices")
        out.append("time: " + ", ".join(f"{k} {v:.2f} s" for k, v in self.time_s.items()))
        out.extend(f"note: {n}" for n in self.notes)
        return out

    def __str__(self) -> str:
        return "\n".join(self.lines())


@dataclass(frozen=True)
class TransferResult:
    character: Character
    """The target's neutral (plus carried parts) with one transferred shape per template shape."""
    landmark_ids: np.ndarray
    """(68,) int64 Multi-PIE landmark vertex ids on the new character, -1 where none."""
    report: TransferReport


# ---- template ---------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Template:
    name: str
    neutral: np.ndarray          # (V, 3) float64
    faces: np.ndarray            # (F, 3) int64
    shape_names: tuple[str, ...]
    deltas: np.ndarray           # (K, V, 3) float64
    landmark_ids: np.ndarray     # (68,) int64, -1 = none
    regions: dict[str, np.ndarray]
    colors: np.ndarray | None


def _as_template(template: VisemeRig | Character, landmark_ids=None, regions=None) -> _Template:
    if isinstance(template, VisemeRig):
        names, lm, regs = tuple(VISEMES), np.asarray(template.landmark_ids, np.int64), dict(template.regions)
        colors = template.vertex_colors
    elif isinstance(template, Character):
        names, lm, regs, colors = template.shape_names, np.full(N_LANDMARKS, -1, np.int64), {}, template.vertex_colors
    else:
        raise TransferError(f"the template must be a VisemeRig or a Character, got {type(template).__name__}")
    if landmark_ids is not None:
        lm = np.asarray(landmark_ids, np.int64)
    if regions is not None:
        regs = dict(regions)
    neutral = np.asarray(template.neutral, np.float64)
    if lm.shape != (N_LANDMARKS,) or lm.min() < -1 or lm.max() >= len(neutral):
        raise TransferError(f"template {template.name!r}: landmark ids must be {N_LANDMARKS} vertex ids or -1")
    return _Template(template.name, neutral, np.asarray(template.faces, np.int64), tuple(names),
                     np.asarray(template.deltas, np.float64), lm, {k: np.asarray(v, np.int64) for k, v in regs.items()},
                     None if colors is None else np.asarray(colors, np.float32))


# ---- gradients --------------------------------------------------------------------------------------------------
def _frames(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(..., F, 3, 3) frames [v2 - v1, v3 - v1, n / sqrt|n|] as columns (Sumner's fourth vertex)."""
    v1, v2, v3 = (vertices[..., faces[:, i], :] for i in range(3))
    e1, e2 = v2 - v1, v3 - v1
    n = np.cross(e1, e2)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    e3 = n / np.sqrt(np.maximum(length, 1e-300))
    return np.stack([e1, e2, e3], axis=-1)


def deformation_gradients(neutral, faces, shapes) -> np.ndarray:
    """(K, F, 3, 3) deformation gradients S_k = V_k V_0^-1 of neutral -> each of the K `shapes` ((K, V, 3) meshes),
    with Sumner's fourth vertex per triangle; identity for triangles degenerate in the neutral."""
    neutral = np.asarray(neutral, np.float64)
    faces = np.asarray(faces, np.int64)
    v0 = _frames(neutral, faces)
    ok = np.abs(np.linalg.det(v0)) > 1e-12 * max(np.ptp(neutral, axis=0).max(), 1e-30) ** 3
    inv = np.zeros_like(v0)
    inv[ok] = np.linalg.inv(v0[ok])
    grads = _frames(np.asarray(shapes, np.float64), faces) @ inv
    grads[:, ~ok] = np.eye(3)
    return grads


# ---- target checks ----------------------------------------------------------------------------------------------
def _check_target(vertices, faces, notes: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) float64 vertices and (F', 3) int64 triangles with degenerate and duplicate ones removed (noted);
    TransferError for bad arrays or a non-manifold mesh."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3:
        raise TransferError(f"target: the neutral mesh must be (V >= 3, 3) vertices, got {v.shape}")
    if not np.isfinite(v).all():
        raise TransferError(f"target: vertex {int(np.flatnonzero(~np.isfinite(v).all(1))[0])} has NaN or infinite "
                            "coordinates")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer):
        raise TransferError(f"target: faces must be (F >= 1, 3) integer triangles, got {f.dtype} {f.shape}")
    f = f.astype(np.int64)
    if f.min() < 0 or f.max() >= len(v):
        raise TransferError(f"target: face vertex ids must lie in [0, {len(v)}), got {f.min()}..{f.max()}")
    size = float(np.linalg.norm(np.ptp(v, axis=0)))
    area2 = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    degenerate = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2]) | (area2 <= 1e-12 * size**2)
    if degenerate.any():
        notes.append(f"target: removed {int(degenerate.sum())} degenerate triangle(s) (repeated vertex or zero "
                     f"area), first {int(np.flatnonzero(degenerate)[0])}")
        f = f[~degenerate]
    _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    if len(first) < len(f):
        notes.append(f"target: removed {len(f) - len(first)} duplicate triangle(s)")
        f = f[np.sort(first)]
    if len(f) == 0:
        raise TransferError("target: no triangle left after removing degenerate ones")
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    if counts.max() > 2:
        bad = unique[counts.argmax()]
        raise TransferError(f"target: the mesh is not manifold: {int((counts > 2).sum())} edge(s) are shared by more "
                            f"than two triangles (e.g. edge {bad[0]}-{bad[1]}, {counts.max()} triangles); repair it "
                            "in a modelling tool (split or delete the extra faces) and try again")
    return v, f


def _check_markers(markers, n_template: int, n_target: int) -> np.ndarray:
    m = np.asarray(markers)
    if m.ndim != 2 or m.shape[1] != 2 or len(m) == 0 or not np.issubdtype(m.dtype, np.integer):
        raise TransferError(f"markers must be (n, 2) integer pairs (template vertex, target vertex), got {m.dtype} "
                            f"{m.shape}")
    m = m.astype(np.int64)
    for column, n, what in ((0, n_template, "template"), (1, n_target, "target")):
        bad = np.flatnonzero((m[:, column] < 0) | (m[:, column] >= n))
        if bad.size:
            raise TransferError(f"marker {int(bad[0])}: {what} vertex {int(m[bad[0], column])} does not exist (the "
                                f"{what} has vertices 0..{n - 1}); {bad.size} marker(s) out of range")
    return m


# ---- correspondence (different topology) ------------------------------------------------------------------------
def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(n, 3) barycentric coordinates of the closest point to each p on triangle (a, b, c) (Ericson, Real-Time
    Collision Detection 5.1.5, vectorised); all arrays (n, 3)."""
    dot = lambda u, v: np.einsum("ij,ij->i", u, v)  # noqa: E731
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v, w = vb / denom, vc / denom                                   # inside the face
        out = np.stack([1 - v - w, v, w], axis=1)
        cases = [
            ((d1 <= 0) & (d2 <= 0), np.zeros_like(d1), np.zeros_like(d1)),                       # vertex a
            ((d3 >= 0) & (d4 <= d3), np.ones_like(d1), np.zeros_like(d1)),                        # vertex b
            ((d6 >= 0) & (d5 <= d6), np.zeros_like(d1), np.ones_like(d1)),                        # vertex c
            ((vc <= 0) & (d1 >= 0) & (d3 <= 0), d1 / (d1 - d3), np.zeros_like(d1)),              # edge ab
            ((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.zeros_like(d1), d2 / (d2 - d6)),              # edge ac
            ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
             1 - (d4 - d3) / ((d4 - d3) + (d5 - d6)), (d4 - d3) / ((d4 - d3) + (d5 - d6))),      # edge bc
        ]
    done = np.zeros(len(p), bool)
    for mask, v_, w_ in cases:
        mask = mask & ~done
        out[mask] = np.stack([1 - v_[mask] - w_[mask], v_[mask], w_[mask]], axis=1)
        done |= mask
    return np.nan_to_num(out, nan=1.0 / 3.0)


def _closest(vertices, faces, points, normals=None, candidates: int = 16):
    """Closest points on a triangle mesh: (points, distances, triangle ids, barycentric (n, 3)).

    Candidate triangles are the `candidates` whose centroids are nearest (a k-d tree; trimesh's exact query needs
    the rtree package, which is not installed), then the exact point-triangle distance picks among them. With
    `normals` (n, 3), a triangle facing away (normals more than 90 degrees apart, Sumner and Popovic's
    compatibility test) is taken only when no candidate faces the same way: so the upper lip's underside is not
    matched to the lower lip's top where the lips nearly touch.
    """
    from scipy.spatial import cKDTree

    vertices, faces, points = np.asarray(vertices, np.float64), np.asarray(faces), np.asarray(points, np.float64)
    k = min(candidates, len(faces))
    _, near = cKDTree(vertices[faces].mean(axis=1)).query(points, k=k)
    near = near.reshape(len(points), k)
    tri = vertices[faces[near]]                                             # (n, k, 3 corners, 3)
    flat = lambda x: x.reshape(-1, 3)  # noqa: E731
    bary = _closest_on_triangles(flat(np.repeat(points[:, None], k, axis=1)), flat(tri[:, :, 0]),
                                 flat(tri[:, :, 1]), flat(tri[:, :, 2])).reshape(len(points), k, 3)
    closest = np.einsum("nkc,nkcd->nkd", bary, tri)
    distance = np.linalg.norm(closest - points[:, None], axis=2)
    score = distance
    if normals is not None:
        tri_normals = np.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])
        facing = np.einsum("nkd,nd->nk", tri_normals, np.asarray(normals, np.float64)) > 0
        score = np.where(facing, distance, distance + 1e6 * (1.0 + distance.max()))
    best = score.argmin(axis=1)
    rows = np.arange(len(points))
    return closest[rows, best], distance[rows, best], near[rows, best], bary[rows, best]


@dataclass
class _Registration:
    skin_faces: np.ndarray        # template face ids of the registered skin
    registered: np.ndarray        # (V_template, 3) registered template positions (skin vertices meaningful)
    s: float
    r: np.ndarray
    t: np.ndarray
    residual: float
    marker_residual: float


def _register(tpl: _Template, skin_vertices: np.ndarray, target_v, target_f, markers, max_residual: float,
              steps) -> _Registration:
    in_skin = np.zeros(len(tpl.neutral), bool)
    in_skin[skin_vertices] = True
    skin_faces = np.flatnonzero(in_skin[tpl.faces].all(axis=1))
    outside = markers[~in_skin[markers[:, 0]], 0]
    if outside.size:
        raise TransferError(f"markers: template vertex {int(outside[0])} is not on the template's skin (it is in "
                            f"{', '.join(CARRIED_REGIONS)}); place markers on the face surface")
    src_points, dst_points = tpl.neutral[markers[:, 0]], target_v[markers[:, 1]]
    if np.linalg.matrix_rank(src_points - src_points.mean(0), tol=1e-6 * np.ptp(src_points).max()) < 3 and len(
            markers) < 3:
        raise TransferError(f"markers: {len(markers)} pair(s) cannot place the template; give at least 3 that are "
                            "not on one line (the 68 landmarks, or 5+ spread over the face)")
    s, r, t = _similarity(src_points, dst_points)
    aligned = tpl.neutral @ (s * r).T + t
    # register only the template skin that the target covers (within 5% of the target's size after the marker
    # alignment): the rest has nothing to match and would slow the ICP down
    from scipy.spatial import cKDTree

    size = float(np.linalg.norm(np.ptp(target_v, axis=0)))
    near = cKDTree(target_v).query(aligned, distance_upper_bound=0.05 * size)[0] < np.inf
    is_marker = np.zeros(len(tpl.neutral), bool)
    is_marker[markers[:, 0]] = True
    corners = tpl.faces[skin_faces]
    skin_faces = skin_faces[near[corners].all(axis=1) | is_marker[corners].any(axis=1)]
    used = np.unique(tpl.faces[skin_faces])
    local = np.full(len(tpl.neutral), -1, np.int64)
    local[used] = np.arange(len(used))
    if (local[markers[:, 0]] < 0).any():
        raise TransferError(f"markers: template vertex {int(markers[local[markers[:, 0]] < 0, 0][0])} is on no "
                            "template triangle near the target")
    if steps is None:   # trimesh's default schedule, 3 iterations a step instead of 10, landmarks kept to the end
        steps = [[0.01, 10, 0.5, 3], [0.02, 5, 0.5, 3], [0.03, 2.5, 0.5, 3], [0.01, 1, 0.0, 3]]
    registered_skin = nricp(aligned[used], local[tpl.faces[skin_faces]], target_v, target_f,
                            landmarks=local[markers[:, 0]], landmark_positions=dst_points, steps=steps,
                            distance_threshold=0.05)
    registered = aligned.copy()
    registered[used] = registered_skin
    _, distance, _, _ = _closest(target_v, target_f, registered_skin)
    residual = float(np.sqrt(np.mean(distance**2)))
    marker_residual = float(np.sqrt(np.mean(np.sum((registered[markers[:, 0]] - dst_points) ** 2, axis=1))))
    if not np.isfinite(residual) or residual > max_residual * size or marker_residual > 4 * max_residual * size:
        raise TransferError(f"the non-rigid ICP did not converge: the registered template lies {residual:.4g} "
                            f"(RMS, {100 * residual / size:.2f}% of the target's size; limit "
                            f"{100 * max_residual:.2f}%) from the target surface and its markers {marker_residual:.4g} "
                            "from the target's; check that the markers name the same points on both meshes and "
                            "that the target is a face like the template's")
    return _Registration(skin_faces, registered, s, r, t, residual, marker_residual)


# ---- the solve --------------------------------------------------------------------------------------------------
def _solve(target_v: np.ndarray, target_f: np.ndarray, grads: np.ndarray, mapped: np.ndarray, static_tol: float,
           soft_weight: float, report: TransferReport, names) -> np.ndarray:
    """(K, V, 3) displacements of the target making its triangle gradients closest to `grads` (K, F, 3, 3), with
    vertices whose mapped displacement `mapped` (K, V, 3) stays below `static_tol` anchored at 0."""
    n_v, n_f, n_k = len(target_v), len(target_f), grads.shape[0]
    frames = _frames(target_v, target_f)
    q = np.linalg.inv(frames)                                             # (F, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(frames[:, :, 0], frames[:, :, 1]), axis=1)
    w = np.sqrt(area / area.mean())
    # row 3f + c: T[r, c] = sum_k (x_{k+2} - x_1)[r] Q[k, c], x_4 the triangle's fourth vertex. x_4 appears in its
    # triangle's 3 rows only, as column q = Q[2, :]: minimising over it in closed form projects those rows onto the
    # complement of q (rows -> (I - q q^T / q^T q) rows), which leaves a V x V system with the sparsity of the mesh
    # Laplacian and exactly Sumner's minimum.
    qt = q.transpose(0, 2, 1) * w[:, None, None]                          # [f, c, k] = w Q[k, c]
    coeff = np.concatenate([-qt.sum(axis=2, keepdims=True), qt[:, :, :2]], axis=2)   # (F, 3 rows, x1 x2 x3)
    fourth = qt[:, :, 2]                                                  # (F, 3): x4's column
    project = np.eye(3) - fourth[:, :, None] * fourth[:, None, :] / (fourth**2).sum(1)[:, None, None]
    vals = project @ coeff                                                # (F, 3, 3)
    rows = np.repeat(np.arange(3 * n_f), 3)
    cols = np.repeat(target_f[:, None, :], 3, axis=1).reshape(-1)
    a = sp.csr_matrix((vals.reshape(-1), (rows, cols)), shape=(3 * n_f, n_v))
    # right-hand sides: rows of w (S - I), projected likewise, one column per (shape, coordinate)
    rhs = (grads - np.eye(3)).transpose(0, 1, 3, 2) * w[None, :, None, None]          # (K, F, c, r)
    rhs = (project[None] @ rhs).reshape(n_k, 3 * n_f, 3)
    rhs = rhs.transpose(1, 0, 2).reshape(3 * n_f, 3 * n_k)

    on_triangle = np.zeros(n_v, bool)
    on_triangle[target_f.ravel()] = True
    moves = np.abs(mapped).max(axis=(0, 2))
    anchored = (moves <= static_tol) & on_triangle
    adjacency = sp.coo_matrix((np.ones(3 * n_f), (target_f.ravel(), np.roll(target_f, 1, axis=1).ravel())),
                              shape=(n_v, n_v))
    _, label = csgraph.connected_components(adjacency, directed=False)
    anchored_parts = np.unique(label[anchored])
    soft = on_triangle & ~np.isin(label, anchored_parts)
    report.n_anchors, report.n_soft_vertices = int(anchored.sum()), int(soft.sum())
    if not on_triangle.all():
        report.notes.append(f"{int((~on_triangle).sum())} target vertices are on no triangle: they take the mapped "
                            "template displacement")
    if soft.any():
        report.notes.append(f"{int(soft.sum())} vertices in {len(np.unique(label[soft]))} connected part(s) that the "
                            "template moves everywhere have no anchor: each is weakly pulled toward the mapped "
                            f"template displacement (weight {soft_weight:g}) to fix its translation")
    free = np.flatnonzero(on_triangle & ~anchored)
    a_free = a[:, free].tocsc()
    normal = (a_free.T @ a_free).tocsc()
    b = a_free.T @ rhs
    if soft.any():
        edge = np.mean(np.linalg.norm(frames[:, :, 0], axis=1))
        weight = soft_weight * np.sqrt(area.mean()) / edge        # a displacement row on the scale of a gradient row
        position = np.full(n_v, -1)
        position[free] = np.arange(len(free))
        soft_ids = np.flatnonzero(soft)
        diagonal = np.zeros(len(free))
        diagonal[position[soft_ids]] = weight**2
        normal = (normal + sp.diags(diagonal)).tocsc()
        pulled = mapped[:, soft_ids].transpose(1, 0, 2).reshape(len(soft_ids), 3 * n_k)
        b[position[soft_ids]] += weight**2 * pulled
    t0 = time.perf_counter()
    try:
        # symmetric positive definite: a symmetric ordering and no pivoting (what a Cholesky factorisation would do)
        lu = spla.splu(normal, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                       options={"SymmetricMode": True})
    except RuntimeError as exc:       # exactly singular: a part with nothing to fix its translation
        raise TransferError(f"the deformation-transfer system is singular ({exc}); the target has a part that "
                            "neither anchors nor the template's motion place") from None
    t1 = time.perf_counter()
    x = lu.solve(np.asarray(b))
    t2 = time.perf_counter()
    report.time_s["factorise"] = t1 - t0
    report.time_s["solve"] = t2 - t1
    full = np.zeros((n_v, 3 * n_k))
    full[free] = x
    residual = a @ full - rhs
    for k, name in enumerate(names):
        cols_k = slice(3 * k, 3 * k + 3)
        norm = np.linalg.norm(rhs[:, cols_k])
        report.gradient_residual[name] = float(np.linalg.norm(residual[:, cols_k]) / norm) if norm > 0 else 0.0
    out = full.reshape(n_v, n_k, 3).transpose(1, 0, 2)
    out[:, ~on_triangle] = mapped[:, ~on_triangle]
    return out


# ---- the transfer -----------------------------------------------------------------------------------------------
def transfer_visemes(template: VisemeRig | Character, target_neutral, target_faces, markers=None, *,
                     target_landmarks=None, name: str = "character", carry_parts: bool = True,
                     static_tol: float = 1e-5, soft_weight: float = 0.1, max_icp_residual: float = 0.01,
                     icp_steps=None, template_landmarks=None, template_regions=None) -> TransferResult:
    """Transfer every shape of `template` (a 16-viseme rig, or any Character) onto the target neutral mesh.

    Same topology (the target's triangles equal the template's): triangle-for-triangle; `markers` are not needed.
    Different topology: `markers` (n, 2) pairs (template vertex, target vertex), or `target_landmarks` (68,) target
    vertex ids in Multi-PIE order (-1 = none) paired with the template's landmark ids, place the template before the
    non-rigid ICP; with neither (or `markers="auto"`) the pairs are found by FaceMesh on renders of both meshes
    (`visemeflow.authoring.automarkers`, noted in the report). `static_tol` (a fraction of the template's size) says which vertices count as not moved (anchors);
    `max_icp_residual` (a fraction of the target's size) rejects a registration that did not converge.
    """
    start = time.perf_counter()
    tpl = _as_template(template, template_landmarks, template_regions)
    notes: list[str] = []
    raw_faces = np.asarray(target_faces)
    same = raw_faces.shape == tpl.faces.shape and np.array_equal(raw_faces, tpl.faces) and \
        np.shape(target_neutral) == tpl.neutral.shape
    target_v, target_f = _check_target(target_neutral, target_faces, notes)
    n_k = len(tpl.shape_names)
    size = float(np.linalg.norm(np.ptp(tpl.neutral, axis=0)))
    report = TransferReport("same topology" if same else "different topology", len(target_v), len(target_f), n_k)
    report.notes.extend(notes)
    shapes = tpl.neutral[None] + tpl.deltas
    template_grads = deformation_gradients(tpl.neutral, tpl.faces, shapes)          # (K, F_t, 3, 3)
    colors = tpl.colors
    carried_v = np.zeros((0, 3))
    carried_f = np.zeros((0, 3), np.int64)
    carried_d = np.zeros((n_k, 0, 3))
    carried_c = None
    landmarks = np.full(N_LANDMARKS, -1, np.int64)
    if same:
        if markers is not None or target_landmarks is not None:
            report.notes.append("same topology as the template: markers are not needed and were not used")
        face_ids = np.arange(len(tpl.faces))
        if len(target_f) < len(tpl.faces):            # degenerate target triangles were removed
            keep = {tuple(t) for t in np.sort(target_f, axis=1)}
            face_ids = np.array([i for i, t in enumerate(np.sort(tpl.faces, axis=1)) if tuple(t) in keep])
        grads = template_grads[:, face_ids]
        mapped = tpl.deltas * _scale_between(tpl.neutral, target_v)
        landmarks = tpl.landmark_ids.copy()
        rotation, scale = np.eye(3), 1.0
    else:
        if markers is None and target_landmarks is not None:
            lm = np.asarray(target_landmarks, np.int64).reshape(-1)
            if lm.shape != (N_LANDMARKS,):
                raise TransferError(f"target landmarks must be {N_LANDMARKS} vertex ids (Multi-PIE order), got "
                                    f"{lm.shape}")
            both = (lm >= 0) & (tpl.landmark_ids >= 0)
            markers = np.stack([tpl.landmark_ids[both], lm[both]], axis=1)
            if not both.any():
                raise TransferError("the template or the target has no landmark vertex; give marker pairs")
        if markers is None or isinstance(markers, str):
            if markers not in (None, "auto"):
                raise TransferError(f"markers: {markers!r} is neither marker pairs nor 'auto'")
            carried_ids = np.concatenate([np.asarray(tpl.regions[r], np.int64) for r in CARRIED_REGIONS
                                          if r in tpl.regions] or [np.zeros(0, np.int64)])
            try:
                auto = automatic_markers(tpl.neutral, tpl.faces, target_v, target_f, exclude=carried_ids,
                                         target_name=name)
            except ValueError as exc:
                raise TransferError(f"the target's topology differs from the template's ({len(target_v)} vs "
                                    f"{len(tpl.neutral)} vertices, or other triangles) and no markers could be found "
                                    f"automatically ({exc}): give marker pairs (template vertex, target vertex) or "
                                    "the target's 68 landmark vertex ids") from None
            markers = auto.pairs
            report.notes.append(auto.note())
        markers = _check_markers(markers, len(tpl.neutral), len(target_v))
        if len(markers) < 5:
            raise TransferError(f"markers: {len(markers)} pair(s); give at least 5 spread over the face (eyes, nose, "
                                "mouth corners, chin), better the 68 landmarks")
        report.n_markers = len(markers)
        carried = np.zeros(len(tpl.neutral), bool)
        for region in CARRIED_REGIONS:
            if region in tpl.regions:
                carried[tpl.regions[region]] = True
        skin = np.flatnonzero(~carried)
        t0 = time.perf_counter()
        reg = _register(tpl, skin, target_v, target_f, markers, max_icp_residual, icp_steps)
        report.time_s["register"] = time.perf_counter() - t0
        report.icp_residual, report.marker_residual = reg.residual, reg.marker_residual
        report.icp_residual_relative = reg.residual / float(np.linalg.norm(np.ptp(target_v, axis=0)))
        rotation, scale = reg.r, reg.s
        # closest-triangle map: each target triangle's centroid on the registered skin
        skin_tris = tpl.faces[reg.skin_faces]
        centroids = target_v[target_f].mean(axis=1)
        target_normals = np.cross(target_v[target_f[:, 1]] - target_v[target_f[:, 0]],
                                  target_v[target_f[:, 2]] - target_v[target_f[:, 0]])
        _, _, tri, _ = _closest(reg.registered, skin_tris, centroids, target_normals)
        grads = template_grads[:, reg.skin_faces[tri]]
        grads = rotation @ grads @ rotation.T                                           # into the target's frame
        # each target vertex's template displacement (rotated, scaled), colour and landmarks, by closest point
        from visemeflow.animation.gltf import vertex_normals

        _, _, vtri, bary = _closest(reg.registered, skin_tris, target_v, vertex_normals(target_v, target_f))
        corners = skin_tris[vtri]                                                       # (V, 3)
        mapped = np.einsum("vc,kvcd->kvd", bary, tpl.deltas[:, corners]) @ (scale * rotation).T
        if colors is not None:
            colors = np.clip(np.einsum("vc,vcd->vd", bary, colors[corners]), 0, 1)
        valid = tpl.landmark_ids >= 0
        if valid.any():
            from scipy.spatial import cKDTree

            _, nearest = cKDTree(target_v).query(reg.registered[tpl.landmark_ids[valid]])
            landmarks[valid] = nearest
        for template_vertex, target_vertex in markers:
            hit = np.flatnonzero(tpl.landmark_ids == template_vertex)
            landmarks[hit] = target_vertex
        if target_landmarks is not None:
            given = np.asarray(target_landmarks, np.int64)
            landmarks[given >= 0] = given[given >= 0]
        if carried.any() and carry_parts:
            ids = np.flatnonzero(carried)
            local = np.full(len(tpl.neutral), -1, np.int64)
            local[ids] = len(target_v) + np.arange(len(ids))
            part_faces = carried[tpl.faces].all(axis=1)
            carried_v = tpl.neutral[ids] @ (scale * rotation).T + reg.t
            carried_f = local[tpl.faces[part_faces]]
            carried_d = tpl.deltas[:, ids] @ (scale * rotation).T
            carried_c = None if tpl.colors is None else tpl.colors[ids]
            report.carried_vertices = len(ids)
            report.notes.append(f"the template's {', '.join(r for r in CARRIED_REGIONS if r in tpl.regions)} "
                                f"({len(ids)} vertices) were carried over rigidly by the marker similarity "
                                f"transform (scale {scale:.3f}); they are not fitted to the target's mouth or eyes")
        elif carried.any():
            report.notes.append(f"the template's {', '.join(r for r in CARRIED_REGIONS if r in tpl.regions)} were "
                                "left out (carry_parts=False): the new character has no mouth interior or eyes")
    static = static_tol * size * scale
    deltas = _solve(target_v, target_f, grads, mapped, static, soft_weight, report, tpl.shape_names)
    neutral = np.concatenate([target_v, carried_v])
    faces = np.concatenate([target_f, carried_f])
    deltas = np.concatenate([deltas, carried_d], axis=1)
    if colors is not None and not same:
        colors = np.concatenate([colors, carried_c if carried_c is not None else np.full((len(carried_v), 3), 0.7)])
    report.n_vertices, report.n_triangles = len(neutral), len(faces)
    report.time_s["total"] = time.perf_counter() - start
    try:
        character = make_character(name, neutral, faces, tpl.shape_names, deltas, vertex_colors=colors)
    except CharacterError as exc:
        raise TransferError(str(exc)) from None
    return TransferResult(character, landmarks, report)


def _scale_between(template_v: np.ndarray, target_v: np.ndarray) -> float:
    """Ratio of the targets's size to the template's (RMS distance to the centroid), for same-topology meshes."""
    a = np.sqrt(np.mean(np.sum((template_v - template_v.mean(0)) ** 2, axis=1)))
    b = np.sqrt(np.mean(np.sum((target_v - target_v.mean(0)) ** 2, axis=1)))
    return float(b / a) if a > 0 else 1.0


# ---- files and the command ---------------------------------------------------------------------------------------
def read_markers_csv(path: str | os.PathLike) -> np.ndarray:
    """(n, 2) int64 marker pairs from a CSV `template_vertex,target_vertex` (header optional, 0-based ids)."""
    path = Path(path)
    try:
        text = path.read_text("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise TransferError(f"{path}: cannot read the marker CSV: {exc}") from None
    pairs = []
    for line, row in enumerate(csv.reader(text.splitlines()), start=1):
        cells = [c.strip() for c in row]
        if not cells or not any(cells) or cells[0].startswith("#"):
            continue
        if line == 1 and cells[:2] == ["template_vertex", "target_vertex"]:
            continue
        if len(cells) != 2:
            raise TransferError(f"{path} line {line}: expected 'template_vertex,target_vertex', got {row}")
        try:
            pairs.append((int(cells[0]), int(cells[1])))
        except ValueError:
            raise TransferError(f"{path} line {line}: vertex ids must be integers, got {row}") from None
    if not pairs:
        raise TransferError(f"{path}: no marker pairs (rows 'template_vertex,target_vertex')")
    return np.array(pairs, np.int64)


def _load_template(path: Path) -> VisemeRig | Character:
    from visemeflow.animation.load import load_character
    from visemeflow.rig import load_rig

    try:
        return load_rig(path)
    except RigError as rig_error:
        try:
            return load_character(path)
        except CharacterError as exc:
            raise TransferError(f"{path}: not a viseme rig ({rig_error}) nor a character ({exc})") from None


def transfer_command(template_path, target_path, markers_path, out_path, *, carry_parts: bool = True,
                     fps: float = 2.0) -> TransferReport:
    """`visemeflow transfer`: the template rig or character onto the target's neutral mesh (.obj/.ply/.glb),
    written as a GLB at `out_path` whose animation shows each shape in turn (neutral, shape 1, neutral, shape 2,
    ..., one key every 1 / fps s). Markers: `markers_path` (CSV), else `<target stem>.landmarks.json` beside the
    target (68 ids). When the shapes are the 16 visemes, `<out stem>.landmarks.json` is written beside the GLB (the
    name `visemeflow.rig.load_rig_glb` looks for). Returns the report; TransferError for any bad input."""
    from visemeflow.animation.gltf import write_glb
    from visemeflow.rig import read_landmarks_json, read_mesh

    template_path, target_path, out_path = Path(template_path), Path(target_path), Path(out_path)
    if out_path.suffix.lower() != ".glb":
        raise TransferError(f"{out_path}: the output must be a .glb")
    template = _load_template(template_path)
    try:
        mesh = read_mesh(target_path)
    except RigError as exc:
        raise TransferError(str(exc)) from None
    markers = target_landmarks = None
    if markers_path is not None:
        markers = read_markers_csv(markers_path)
    else:
        sidecar = target_path.with_name(f"{target_path.name.split('.')[0]}.landmarks.json")
        if sidecar.is_file():
            try:
                target_landmarks = read_landmarks_json(sidecar)
            except RigError as exc:
                raise TransferError(str(exc)) from None
    try:
        result = transfer_visemes(template, mesh.vertices, mesh.faces, markers, target_landmarks=target_landmarks,
                                  name=out_path.name.split(".")[0], carry_parts=carry_parts)
    except TransferError as exc:
        raise TransferError(f"{target_path}: {exc}") from None
    character = result.character
    n = character.n_shapes
    tour = np.zeros((2 * n + 1, n), np.float32)
    tour[2 * np.arange(n) + 1, np.arange(n)] = 1.0
    write_glb(out_path, character, tour, fps)
    if tuple(character.shape_names) == tuple(VISEMES):
        sidecar = out_path.with_name(f"{out_path.name.split('.')[0]}.landmarks.json")
        sidecar.write_text(json.dumps({"landmark_ids": [int(i) for i in result.landmark_ids]}) + "\n", "utf-8")
    return result.report
