"""The loss terms of paper Eq. 1-8, each a pure function of tensors.

Shapes: T frames, K landmarks or vertices, 16 visemes. Every term returns one value per frame (shape (T,)),
so the faithful solver (one frame at a time) and the fast solver (all frames at once) share them.
"""

from dataclasses import dataclass

import numpy as np
import torch

from visemeflow.visemes import N_VISEMES


@dataclass(frozen=True)
class GuidanceSets:
    """Per frame: visemes to suppress (Eq. 4) and to activate (Eq. 5), as (T, 16) bool arrays."""

    suppress: np.ndarray
    activate: np.ndarray


def guidance_sets(procedural: np.ndarray, m: int = 3, n: int = 2, radius: int = 1, eps: float = 1e-3) -> GuidanceSets:
    """I_sup and I_act of paper 4.3 from procedural curves (T, 16).

    I_act(j): the top `n` visemes of frame j. I_sup(j): visemes that are not among the top `m` of any frame
    in the neighbourhood j-radius..j+radius (the frame itself and `radius` frames each side; with radius 1,
    the frames j-1, j, j+1). Only visemes with a procedural weight above `eps` count as "top": in silence
    no viseme is activated and all are suppressed, so the face is pulled to neutral.
    """
    curves = np.asarray(procedural, np.float64)
    t = len(curves)
    order = np.argsort(-curves, axis=1, kind="stable")
    rows = np.arange(t)[:, None]
    top_m = np.zeros_like(curves, dtype=bool)
    top_m[rows, order[:, :m]] = True
    top_m &= curves > eps
    activate = np.zeros_like(curves, dtype=bool)
    activate[rows, order[:, :n]] = True
    activate &= curves > eps
    near = top_m.copy()
    for shift in range(1, radius + 1):
        near[shift:] |= top_m[:-shift]
        near[:-shift] |= top_m[shift:]
    return GuidanceSets(suppress=~near, activate=activate)


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of `values` over the last axis where `mask`; 0 (with gradient) where the mask is empty."""
    mask = mask.to(values.dtype)
    count = mask.sum(dim=-1)
    return (values * mask).sum(dim=-1) / count.clamp_min(1.0)


def landmark_loss(projected: torch.Tensor, target: torch.Tensor, valid: torch.Tensor, beta: torch.Tensor) -> torch.Tensor:
    """Eq. 2: sum_k beta_k ||Proj(s_k) - p_k||^2 over detected landmarks P; (T, K, 2) -> (T,).

    Normalised by sum_k beta_k over P rather than |P|, so that points given no weight (beta = 0, such as the jaw
    contour) do not dilute the others; with all beta = 1 it is the paper's 1/|P| mean.
    """
    target = torch.where(valid[..., None], target, projected.detach())  # missing points carry no gradient
    squared = ((projected - target) ** 2).sum(dim=-1)
    weight = beta * valid.to(squared.dtype)
    return (squared * weight).sum(dim=-1) / weight.sum(dim=-1).clamp_min(1e-12)


def suppression_loss(weights: torch.Tensor, suppress: torch.Tensor) -> torch.Tensor:
    """Eq. 4: mean of x_i^2 over I_sup; (T, 16) -> (T,)."""
    return _masked_mean(weights ** 2, suppress)


def activation_loss(weights: torch.Tensor, activate: torch.Tensor) -> torch.Tensor:
    """Eq. 5: minus the mean of x_i^2 over I_act; (T, 16) -> (T,)."""
    return -_masked_mean(weights ** 2, activate)


def flow_loss(proj_cur: torch.Tensor, proj_prev, displacement, valid) -> torch.Tensor:
    """Eq. 6, L_flow: the mean over valid correspondences k of ||proj_cur_k - (proj_prev_k + u_k)||^2.

    proj_cur: (N, 2) projections Proj(s_k^j) of the current frame (the tensor being optimised), or (T, N, 2) for T
        frames at once (any leading batch dims work).
    proj_prev: Proj(s_k^{j-1}), same shape (a tensor or array; pass it detached to keep frame j-1 fixed, as the
        per-frame fitting does; a tensor that requires grad receives gradient too).
    displacement: u_k, same shape, from `FlowField.correspondences` (visemeflow.tracking.optical_flow).
    valid: (N,) or (T, N) bool.
    Returns a scalar for (N, 2) inputs and the (T,) per-frame losses for (T, N, 2). A frame with no valid
    correspondence contributes 0, still connected to the graph (zero gradient). Invalid entries never reach the
    value or the gradient, even when they hold NaN.
    """
    if not isinstance(proj_cur, torch.Tensor):
        raise TypeError("proj_cur must be a torch.Tensor")
    if proj_cur.ndim < 2 or proj_cur.shape[-1] != 2:
        raise ValueError(f"proj_cur must be (..., N, 2), got {tuple(proj_cur.shape)}")
    like = {"dtype": proj_cur.dtype, "device": proj_cur.device}
    prev = torch.as_tensor(proj_prev, **like)
    u = torch.as_tensor(displacement, **like)
    ok = torch.as_tensor(valid, device=proj_cur.device).to(torch.bool)
    for name, t in (("proj_prev", prev), ("displacement", u)):
        if t.shape != proj_cur.shape:
            raise ValueError(f"{name} must have the shape of proj_cur {tuple(proj_cur.shape)}, got {tuple(t.shape)}")
    if ok.shape != proj_cur.shape[:-1]:
        raise ValueError(f"valid must be {tuple(proj_cur.shape[:-1])}, got {tuple(ok.shape)}")
    diff = proj_cur - (prev + u)
    diff = torch.where(ok[..., None], diff, torch.zeros((), **like))
    per_frame = (diff * diff).sum(dim=(-2, -1))
    count = ok.sum(dim=-1).clamp_min(1).to(proj_cur.dtype)
    return per_frame / count


def diff_loss(weights: torch.Tensor, previous: torch.Tensor) -> torch.Tensor:
    """Eq. 7: (1/16) sum_i (x_i^j - x_i^{j-1})^2; (T, 16) -> (T,)."""
    return ((weights - previous) ** 2).sum(dim=-1) / N_VISEMES


def range_loss(weights: torch.Tensor) -> torch.Tensor:
    """Eq. 8: mean (x-1)^2 over x > 1 plus mean x^2 over x < 0, the sets taken from the current values; -> (T,)."""
    upper = (weights > 1).detach()
    lower = (weights < 0).detach()
    return _masked_mean((weights - 1) ** 2, upper) + _masked_mean(weights ** 2, lower)
