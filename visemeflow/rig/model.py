"""The viseme blendshape rig (paper Sec. 4): a neutral mesh B0 and 16 viseme shapes, S = B0 + sum_i x_i (B_i - B0)."""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field

from typing import TYPE_CHECKING

import numpy as np

from visemeflow.visemes import N_VISEMES, VISEMES

if TYPE_CHECKING:   # torch is imported where a rig is evaluated: commands that only read curves start faster
    import torch

N_LANDMARKS = 68
"""Multi-PIE 68-point landmark order (dlib / OpenFace / iBUG 300-W)."""


class RigError(ValueError):
    """A rig that cannot be used: the message names the file or field and what was expected."""


@dataclass(frozen=True, eq=False)
class VisemeRig:
    """A blendshape rig with the 16 visemes; `eq=False` so a rig hashes by identity (its tensors are cached per rig).

    Build through a loader or call `validate_rig` on a hand-made one: the constructor does not check shapes.
    """

    name: str
    neutral: np.ndarray
    """(V, 3) float32, B0, in mesh units (the demo rig: centimetres, +y up, +z out of the face)."""
    deltas: np.ndarray
    """(16, V, 3) float32, B_i - B0 in VISEMES order."""
    faces: np.ndarray
    """(F, 3) int32 triangles; polygons are split into fans when read."""
    landmark_ids: np.ndarray
    """(68,) int64 vertex ids in Multi-PIE 68-point order; -1 where the rig has no vertex for that landmark."""
    vertex_colors: np.ndarray | None = None
    """(V, 3) float32 RGB in [0, 1], or None."""
    regions: dict[str, np.ndarray] = field(default_factory=dict)
    """Named vertex-id sets, e.g. "mouth_interior", "lips", "teeth"."""

    @property
    def n_vertices(self) -> int:
        return int(self.neutral.shape[0])

    @property
    def valid_landmarks(self) -> np.ndarray:
        """(68,) bool: which landmarks have a vertex."""
        return np.asarray(self.landmark_ids) >= 0

    def viseme_shape(self, name: str) -> np.ndarray:
        """(V, 3) float32 mesh of one viseme at weight 1 (B_i)."""
        return self.neutral + self.deltas[VISEMES.index(name)]


def validate_rig(rig: VisemeRig) -> None:
    """Raise RigError naming the first thing wrong with the rig's arrays; return None when it is usable."""
    where = f"rig {rig.name!r}"
    neutral = np.asarray(rig.neutral)
    if neutral.ndim != 2 or neutral.shape[1] != 3 or neutral.shape[0] == 0:
        raise RigError(f"{where}: neutral must have shape (V, 3) with V > 0, got {neutral.shape}")
    n_vertices = neutral.shape[0]
    if neutral.dtype != np.float32:
        raise RigError(f"{where}: neutral must be float32, got {neutral.dtype}")
    if not np.isfinite(neutral).all():
        bad = int(np.flatnonzero(~np.isfinite(neutral).all(axis=1))[0])
        raise RigError(f"{where}: neutral has non-finite coordinates (first at vertex {bad})")

    deltas = np.asarray(rig.deltas)
    if deltas.ndim != 3 or deltas.shape[0] != N_VISEMES:
        raise RigError(f"{where}: deltas must have shape ({N_VISEMES}, V, 3), one per viseme, got {deltas.shape}")
    if deltas.shape[1:] != (n_vertices, 3):
        raise RigError(f"{where}: deltas have {deltas.shape[1]} vertices per viseme, the neutral has {n_vertices}")
    if deltas.dtype != np.float32:
        raise RigError(f"{where}: deltas must be float32, got {deltas.dtype}")
    finite = np.isfinite(deltas).reshape(N_VISEMES, -1).all(axis=1)
    if not finite.all():
        raise RigError(f"{where}: viseme {VISEMES[int(np.flatnonzero(~finite)[0])]} has non-finite coordinates")

    faces = np.asarray(rig.faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise RigError(f"{where}: faces must have shape (F, 3) triangles, got {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer):
        raise RigError(f"{where}: faces must be integer vertex ids, got {faces.dtype}")
    if faces.size and (faces.min() < 0 or faces.max() >= n_vertices):
        raise RigError(
            f"{where}: face vertex ids must lie in [0, {n_vertices}), got {faces.min()}..{faces.max()}"
        )

    landmarks = np.asarray(rig.landmark_ids)
    if landmarks.shape != (N_LANDMARKS,):
        raise RigError(f"{where}: landmark_ids must hold {N_LANDMARKS} ids (Multi-PIE order), got shape {landmarks.shape}")
    if not np.issubdtype(landmarks.dtype, np.integer):
        raise RigError(f"{where}: landmark_ids must be integers, got {landmarks.dtype}")
    if landmarks.min() < -1 or landmarks.max() >= n_vertices:
        raise RigError(
            f"{where}: landmark_ids must lie in [0, {n_vertices}) or be -1 for none, "
            f"got {landmarks.min()}..{landmarks.max()}"
        )

    if rig.vertex_colors is not None:
        colors = np.asarray(rig.vertex_colors)
        if colors.shape != (n_vertices, 3):
            raise RigError(f"{where}: vertex_colors must have shape ({n_vertices}, 3), got {colors.shape}")
        if not (np.isfinite(colors).all() and colors.min() >= 0.0 and colors.max() <= 1.0):
            raise RigError(f"{where}: vertex_colors must be finite RGB in [0, 1]")

    for region, ids in rig.regions.items():
        ids = np.asarray(ids)
        if ids.ndim != 1 or not np.issubdtype(ids.dtype, np.integer):
            raise RigError(f"{where}: region {region!r} must be a 1-D array of vertex ids, got {ids.dtype} {ids.shape}")
        if ids.size and (ids.min() < 0 or ids.max() >= n_vertices):
            raise RigError(f"{where}: region {region!r} has vertex ids outside [0, {n_vertices})")


class RigTensors:
    """Torch copies of one rig's arrays, flattened for one matmul per evaluation; made once per rig and device."""

    _max_subsets = 8

    def __init__(self, rig: VisemeRig, device: torch.device | str = "cpu"):
        import torch

        self.n_vertices = rig.n_vertices
        self.device = torch.device(device)
        self.neutral = torch.as_tensor(np.ascontiguousarray(rig.neutral, np.float32), device=self.device)
        self.deltas = torch.as_tensor(np.ascontiguousarray(rig.deltas, np.float32), device=self.device)
        self._basis = self.deltas.reshape(N_VISEMES, -1)
        self._offset = self.neutral.reshape(-1)
        self._subsets: dict[bytes, tuple[torch.Tensor, torch.Tensor]] = {}

    def basis(self, vertex_ids: np.ndarray | None) -> tuple[torch.Tensor, torch.Tensor]:
        """(16, 3V') delta basis and (3V',) neutral offset for all vertices or a subset (subsets cached)."""
        if vertex_ids is None:
            return self._basis, self._offset
        key = vertex_ids.tobytes()
        hit = self._subsets.get(key)
        if hit is None:
            import torch

            index = torch.as_tensor(vertex_ids, device=self.device)
            hit = (
                self.deltas[:, index].reshape(N_VISEMES, -1).contiguous(),
                self.neutral[index].reshape(-1).contiguous(),
            )
            if len(self._subsets) >= self._max_subsets:
                self._subsets.pop(next(iter(self._subsets)))
            self._subsets[key] = hit
        return hit


_TENSORS: weakref.WeakKeyDictionary[VisemeRig, dict[torch.device, RigTensors]] = weakref.WeakKeyDictionary()


def rig_tensors(rig: VisemeRig, device: torch.device | str = "cpu") -> RigTensors:
    """The cached RigTensors of `rig` on `device` (built on first use, dropped with the rig)."""
    import torch

    device = torch.device(device)
    per_device = _TENSORS.setdefault(rig, {})
    tensors = per_device.get(device)
    if tensors is None:
        tensors = per_device[device] = RigTensors(rig, device)
    return tensors


def evaluate_rig(rig: VisemeRig, weights, vertex_ids=None) -> torch.Tensor:
    """Meshes for viseme weights: (T, 16) -> (T, V', 3) float32, S = B0 + sum_i x_i (B_i - B0); (16,) -> (V', 3).

    Differentiable w.r.t. `weights` (a tensor keeps its graph; arrays are converted). `vertex_ids` (V',) picks a
    subset, e.g. `rig.landmark_ids` (every id must be a real vertex: filter -1 first). Weights are not clamped.
    """
    import torch

    w = torch.as_tensor(weights)
    single = w.ndim == 1
    if single:
        w = w.unsqueeze(0)
    if w.ndim != 2 or w.shape[1] != N_VISEMES:
        raise ValueError(f"weights must have shape (T, {N_VISEMES}) or ({N_VISEMES},), got {tuple(w.shape)}")
    if not w.is_floating_point() or w.dtype != torch.float32:
        w = w.to(torch.float32)
    ids = None
    if vertex_ids is not None:
        ids = np.asarray(vertex_ids, dtype=np.int64).reshape(-1)
        if ids.size and (ids.min() < 0 or ids.max() >= rig.n_vertices):
            raise RigError(
                f"rig {rig.name!r}: vertex_ids must lie in [0, {rig.n_vertices}), got {ids.min()}..{ids.max()} "
                "(landmark ids of -1 mean 'no vertex': drop them before evaluating)"
            )
    basis, offset = rig_tensors(rig, w.device).basis(ids)
    out = torch.addmm(offset, w, basis).reshape(w.shape[0], -1, 3)
    return out[0] if single else out
