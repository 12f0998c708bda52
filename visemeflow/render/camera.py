"""Pinhole camera and per-frame head pose in torch, in the convention of `visemeflow.render.raster`.

Camera coordinates: p_cam = R(rotation) p_mesh + translation, x right, y up, the camera looking down -z.
Pixels: u = cx + fx x / (-z) to the right, v = cy - fy y / (-z) downward; pixel centres at integers.
"""

import math
from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def from_fov(cls, width: int = 360, height: int = 288, fov_deg: float = 25.0) -> "Intrinsics":
        """Square pixels, centred principal point, `fov_deg` the vertical field of view (a guess for unknown cameras)."""
        focal = 0.5 * height / math.tan(math.radians(fov_deg) / 2.0)
        return cls(focal, focal, (width - 1) / 2.0, (height - 1) / 2.0, int(width), int(height))

    default = from_fov

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) intrinsic matrix K (OpenCV layout)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @classmethod
    def from_record(cls, record: dict) -> "Intrinsics":
        """From a `<name>.camera.json` record (as `visemeflow synth` writes)."""
        return cls(float(record["fx"]), float(record["fy"]), float(record["cx"]), float(record["cy"]),
                   int(record["width"]), int(record["height"]))


def rotation_matrices(rotation: torch.Tensor) -> torch.Tensor:
    """(T, 3) axis-angle (rad) -> (T, 3, 3) rotation matrices, differentiable (also at zero).

    Rodrigues in closed form, R = I + sin(t)/t K + (1 - cos t)/t^2 K^2 (K the cross-product matrix of the axis-angle
    r, t = |r|), with both coefficients written through `torch.sinc`, which is smooth at 0; t is taken as
    sqrt(|r|^2 + 1e-12) so that its gradient stays finite at r = 0, where R and dR/dr are exactly kornia's. kornia's
    `axis_angle_to_rotation_matrix` (the same matrices within 1.2e-7) evaluates a Taylor branch and a full branch on
    every call and picks one per row: twice the time of this, forward and backward, inside every solver step."""
    theta = torch.sqrt((rotation * rotation).sum(-1, keepdim=True) + 1e-12)
    a = torch.sinc(theta / math.pi)                          # sin(t) / t
    b = 0.5 * torch.sinc(theta / (2.0 * math.pi)) ** 2       # (1 - cos t) / t^2 = 2 sin^2(t/2) / t^2
    k = cross_matrices(rotation)
    eye = torch.eye(3, dtype=rotation.dtype, device=rotation.device).expand_as(k)
    return eye + a[..., None] * k + b[..., None] * (k @ k)


def right_jacobian(rotation: torch.Tensor) -> torch.Tensor:
    """(T, 3) axis-angle -> (T, 3, 3) right Jacobian J of SO(3): R(r + dr) = R(r) exp([J dr]_x) to first order,
    J = I - (1 - cos t)/t^2 K + (t - sin t)/t^3 K^2 (K the cross-product matrix of r, t = |r|; a Taylor series
    below 0.1 rad, where float32 would lose t - sin t to cancellation). The derivative of a rotated point is then
    d(R(r) p)/dr = -R [p]_x J: the solvers' gradients and Jacobians use it instead of differentiating through
    `rotation_matrices`."""
    theta2 = (rotation * rotation).sum(-1, keepdim=True)
    small = theta2 < 1e-2
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    safe = torch.sqrt(safe2)
    t4 = theta2 * theta2
    a = torch.where(small, 0.5 - theta2 / 24.0 + t4 / 720.0, (1.0 - torch.cos(safe)) / safe2)
    b = torch.where(small, 1.0 / 6.0 - theta2 / 120.0 + t4 / 5040.0, (safe - torch.sin(safe)) / (safe2 * safe))
    k = cross_matrices(rotation)
    eye = torch.eye(3, dtype=rotation.dtype, device=rotation.device).expand_as(k)
    return eye - a[..., None] * k + b[..., None] * (k @ k)


def cross_matrices(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) cross-product matrices [v]_x ([v]_x w = v x w)."""
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*v.shape[:-1], 3, 3)


def to_camera(points: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """(T, N, 3) mesh points, (T, 3) axis-angle, (T, 3) translation -> (T, N, 3) camera coordinates."""
    return points @ rotation_matrices(rotation).transpose(1, 2) + translation[:, None, :]


def project(points: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor, camera: Intrinsics) -> torch.Tensor:
    """(T, N, 3) mesh points -> (T, N, 2) pixels (u right, v down)."""
    cam = to_camera(points, rotation, translation)
    depth = (-cam[..., 2]).clamp_min(1e-6)
    u = camera.cx + camera.fx * cam[..., 0] / depth
    v = camera.cy - camera.fy * cam[..., 1] / depth
    return torch.stack([u, v], dim=-1)
