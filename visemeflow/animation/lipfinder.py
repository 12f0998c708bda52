"""The inner lips of a character that has no landmarks (a user's ARKit, Ready Player Me or VRM head), found from its
geometry, so that its closures too are measured in millimetres on the mesh.

A mouth is a slit in the skin: the upper and lower inner lip lie millimetres apart, yet the surface joins them only
around the mouth's corners (or through a mouth bag), a long way round. Opening the mouth pulls them apart by most of
the opening. So, with the character's own shapes bound to the visemes (its convention, detected from its names):

1. `open` = the neutral plus the shapes of AHH (the widest viseme) at 1; the lower lip, jaw and chin move, the upper
   lip hardly;
2. slit pairs: a vertex i that AHH moves by at least 30% of its largest displacement, and a vertex j of the same
   connected mesh piece (the teeth, a separate piece, never pair with the lips) within `RADII_MM` of it at rest
   (4 mm, then 8 and 12 for a mouth that rests open), such that AHH pulls them apart by more than half its largest
   displacement and the mesh joins them by no path of fewer than `hops` edges (`hops` spans three times the radius in
   the mesh's median edge length, at least 3, at most 48): i's nearest such j among its 48 nearest vertices. The one that AHH moves less is the upper lip;
3. the slit's lateral axis is the principal axis of the pairs' midpoints; at its centre and at 40% of its half
   width to either side (where the 68-point layout's inner-lip landmarks 61-67, 62-66 and 63-65 sit), the pair
   with the smallest gap at rest within a window of 12% of the half width: the inner lip line, not the outer lip.

The searches for "joined nearby" expand at most `_VISITS` vertices in all; a mesh that needs more (no mouth has
such neighbourhoods: a random cloud, a hostile file) has no lip measure. Copies of a vertex (an exporter splits vertices along flat-shaded edges and UV seams: a flat-shaded head
exported by Blender has 3.8 times the vertices, every triangle its own) are welded first, where they sit within
`_WELD_MM` of each other both at rest and opened. Accepted only when it looks like a mouth: at least `MIN_PAIRS` slit pairs, and the three pairs' mean gap under AHH at
least `MIN_OPENING_MM` more than at rest. Otherwise None: the character has no lip measure, as before (a sealed
mouth, a mesh with no opening shape, names no convention binds).

Checked on the ICT head (demo rig and the ARKit-named GLB of `examples/build_arkit_character.py`, whose landmarks
are known): the middle pair found is landmarks 62-66 themselves; over 216 curve frames the gap of the found pairs
follows the landmark pairs' with r = 1.000, within 2.3 mm (at the widest shapes; 1.0 against 1.1 mm at MBP), and
calls the same frames closed (below 1.5 mm) at every frame (tests/test_lipfinder.py).
"""

from __future__ import annotations

import functools
from collections import deque

import numpy as np

from visemeflow.visemes import N_VISEMES, viseme_index

__all__ = ["MIN_OPENING_MM", "MIN_PAIRS", "RADII_MM", "find_inner_lips", "found_inner_lips"]

RADII_MM = (4.0, 8.0, 12.0)
MIN_PAIRS = 5
MIN_OPENING_MM = 5.0
_MOVES = 0.3            # share of AHH's largest displacement that makes a vertex a lip candidate
_SEPARATES = 0.5        # share of it by which a slit pair must come apart
_CENTRES = (-0.4, 0.0, 0.4)
_WINDOW = 0.12
_NEIGHBOURS = 48        # partners looked at per candidate (nearest first)
_MAX_HOPS = 48          # the "joined nearby" search stops this many edges out
_WELD_MM = 1e-3         # copies of a vertex closer than this (at rest and opened) are one
_VISITS = 200_000       # vertices those searches may expand in all (the ICT head's lips take about 8,000)


def _adjacency(faces: np.ndarray, n: int):
    from scipy.sparse import coo_matrix

    f = np.asarray(faces, np.int64)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
    return coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n, n)).tocsr()


class _Budget:
    """Vertices the "joined nearby" searches may visit in all (`_VISITS`): a mesh whose neighbourhoods are huge (a
    random cloud, a hostile file) is given up on, not searched for minutes."""

    def __init__(self, visits: int):
        self.left = visits


def _within_hops(adj, source: int, limit: int, budget: _Budget) -> set[int] | None:
    """The vertices at most `limit` edges from `source`; None when the budget runs out."""
    seen, todo = {source: 0}, deque([source])
    while todo:
        u = todo.popleft()
        if seen[u] >= limit:
            continue
        for w in adj.indices[adj.indptr[u]:adj.indptr[u + 1]]:
            if w not in seen:
                seen[int(w)] = seen[u] + 1
                todo.append(int(w))
        budget.left -= 1
        if budget.left <= 0:
            return None
    return set(seen)


def find_inner_lips(neutral: np.ndarray, faces: np.ndarray, opening: np.ndarray, mm_per_unit: float
                    ) -> np.ndarray | None:
    """(3, 2) vertex ids (upper, lower) of the inner lips at the quarter points and the middle, or None (see the
    module doc). `opening` (V, 3): the displacement of the widest open mouth (AHH) in the mesh's units."""

    rest = np.asarray(neutral, np.float64)
    opened = rest + np.asarray(opening, np.float64)
    faces = np.asarray(faces, np.int64)
    if not len(rest) or not len(faces):
        return None
    # weld the copies an exporter makes of a vertex (flat shading, UV seams: the same place, moved the same way by
    # the opening), so that the surface's connections are the surface's; lips that touch at rest stay apart, since
    # the opening moves them differently
    key = np.round(np.concatenate([rest, opened], axis=1) * (mm_per_unit / _WELD_MM))
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    found = _find(rest[first], opened[first], inverse[faces], mm_per_unit)
    return None if found is None else first[found]


def _find(rest: np.ndarray, opened: np.ndarray, faces: np.ndarray, mm_per_unit: float) -> np.ndarray | None:
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    moved = np.linalg.norm(opened - rest, axis=1)
    top = float(moved.max()) if len(moved) else 0.0
    if top * mm_per_unit < MIN_OPENING_MM:
        return None
    adj = _adjacency(faces, len(rest))
    _, piece = connected_components(adj, directed=False)
    edges = np.linalg.norm(rest[faces[:, [0, 1, 2]]] - rest[faces[:, [1, 2, 0]]], axis=2)
    edge = float(np.median(edges)) or 1e-9
    candidates = np.flatnonzero(moved > _MOVES * top)
    tree = cKDTree(rest)
    budget = _Budget(_VISITS)
    for radius_mm in RADII_MM:
        radius = radius_mm / mm_per_unit
        hops = min(_MAX_HOPS, max(3, int(np.ceil(3 * radius / edge))))
        pairs = set()
        # each candidate's nearest `_NEIGHBOURS` within the radius, all at once (bounded: a mesh packed into a few
        # millimetres asks no more than this of each vertex)
        distance, found = tree.query(rest[candidates], k=min(_NEIGHBOURS, len(rest)), distance_upper_bound=radius)
        distance, found = distance.reshape(len(candidates), -1), found.reshape(len(candidates), -1)
        within = np.isfinite(distance)
        lone = np.repeat(candidates, within.sum(axis=1))
        near = found[within].astype(np.int64)
        apart = np.linalg.norm(opened[near] - opened[lone], axis=1) - np.linalg.norm(rest[near] - rest[lone], axis=1)
        keep = (near != lone) & (piece[near] == piece[lone]) & (apart > _SEPARATES * top)
        lone, near = lone[keep], near[keep]
        order = np.lexsort((np.linalg.norm(rest[near] - rest[lone], axis=1), lone))   # by candidate, nearest first
        lone, near = lone[order], near[order]
        starts = np.flatnonzero(np.r_[True, lone[1:] != lone[:-1]]) if len(lone) else np.zeros(0, np.int64)
        for first, stop in zip(starts, np.r_[starts[1:], len(lone)]):
            i = int(lone[first])
            joined = _within_hops(adj, i, hops, budget)
            if joined is None:
                return None
            j = next((int(j) for j in near[first:stop] if int(j) not in joined), None)   # the nearest not joined
            if j is not None:
                pairs.add((j, i) if moved[j] < moved[i] else (i, j))
        if len(pairs) >= MIN_PAIRS:
            break
    if len(pairs) < MIN_PAIRS:
        return None
    pairs = np.asarray(sorted(pairs), np.int64)
    middle = (rest[pairs[:, 0]] + rest[pairs[:, 1]]) / 2
    centred = middle - middle.mean(axis=0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    axis = axis if axis[np.argmax(np.abs(axis))] > 0 else -axis     # a sign of its own, not the solver's
    along = centred @ axis
    centre, half = (along.min() + along.max()) / 2, (along.max() - along.min()) / 2
    if half <= 0:
        return None
    gap_rest = np.linalg.norm(rest[pairs[:, 0]] - rest[pairs[:, 1]], axis=1)
    chosen = []
    for offset in _CENTRES:
        window = np.flatnonzero(np.abs(along - (centre + offset * half)) <= _WINDOW * half)
        if not window.size:
            return None
        chosen.append(pairs[window[np.argmin(gap_rest[window])]])
    chosen = np.asarray(chosen, np.int64)
    gap = lambda points: np.linalg.norm(points[chosen[:, 0]] - points[chosen[:, 1]], axis=1).mean()  # noqa: E731
    if (gap(opened) - gap(rest)) * mm_per_unit < MIN_OPENING_MM:
        return None
    return chosen


@functools.lru_cache(maxsize=16)
def found_inner_lips(character) -> np.ndarray | None:
    """`find_inner_lips` on a `Character` through its detected convention's AHH (None when no convention binds its
    names); computed once per character object."""
    from visemeflow.shapes.conventions import bind

    try:
        binding = bind(character)
    except (ValueError, KeyError):
        return None
    one = np.zeros((1, N_VISEMES), np.float32)
    one[0, viseme_index("AHH")] = 1.0
    weights = np.asarray(binding.weights(one)[0], np.float32)
    opening = np.tensordot(weights, np.asarray(character.deltas, np.float32), axes=1)
    return find_inner_lips(character.neutral, character.faces, opening, character.mm_per_unit)
