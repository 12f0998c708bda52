"""Transforms fitted to corresponding points: Umeyama's similarity (rotation, translation and, optionally, scale)."""

from __future__ import annotations

import numpy as np

__all__ = ["similarity"]


def similarity(src: np.ndarray, dst: np.ndarray, *, scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama: s, R, t minimising sum ||s R src + t - dst||^2 over (n, 3) point pairs; `scale=False` fixes s = 1
    (a rigid fit, Kabsch)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sigma, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        d[2, 2] = -1
    r = u @ d @ vt
    var = (a**2).sum() / len(src)
    s = float(np.trace(np.diag(sigma) @ d) / var) if scale and var > 0 else 1.0
    return s, r, mu_d - s * r @ mu_s
