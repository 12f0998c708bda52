"""The subject's neutral face (paper Sec. 4.2): fit identity modes of a linear face model to 2D landmarks.

The paper reconstructs the actress's neutral 3D face from a few neutral video frames with a 3DMM fit, then transfers
the template visemes onto it. Here the 3DMM is the rig's own mesh plus PCA identity modes with the same vertices
(the demo: the first 20 ICT Face Model modes, `visemeflow/rig/data/ict_identities.npz`). A subject's face is

    neutral' = scale * (neutral + sum_k c_k mode_k),   c_k ~ N(0, 1) (the modes are one standard deviation each),

and the fit solves for c, the scale, one head pose per frame and, for an unknown camera, the focal length, from the
68 landmarks of closed-mouth frames (`neutral_frames`).

One limit of a single camera: a face `a` times larger and `a` times further away projects to the same pixels, so the
landmarks cannot tell absolute size. The fit therefore holds the scale with a log-normal prior (mean 1), and it comes
out at 1: the head's distance takes up what the modes do not explain. Shape, up to that overall size, is fitted
through c. `apply_identity` still takes a scale, for callers who know the subject's size by other means.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from visemeflow.rig import RigError, VisemeRig, rig_data_path
from visemeflow.render.camera import Intrinsics, cross_matrices, right_jacobian, rotation_matrices, to_camera
from visemeflow.tracking.landmarks import GROUPS, N_POINTS, LandmarkTrack

# Inner-lip pairs facing each other across the mouth (upper, lower) and the mouth corners, Multi-PIE numbering.
_INNER_LIP_PAIRS = ((61, 67), (62, 66), (63, 65))
_MOUTH_CORNERS = (48, 54)
_EYE_CORNERS = (36, 45)


@dataclass(frozen=True)
class IdentityModes:
    """Linear identity modes on a rig's vertices."""

    names: tuple[str, ...]
    """(K,) mode names, e.g. `identity000`."""
    modes: np.ndarray
    """(K, V, 3) float32 vertex offsets from the rig's neutral, each one standard deviation of the identity prior."""

    @property
    def n_modes(self) -> int:
        return int(self.modes.shape[0])

    @property
    def n_vertices(self) -> int:
        return int(self.modes.shape[1])


def demo_identity_path() -> Path:
    """The shipped identity modes of the demo rig, package data `visemeflow/rig/data/ict_identities.npz`."""
    return rig_data_path("ict_identities.npz")


def load_identity_modes(path: Path | str) -> IdentityModes:
    """Identity modes written by `examples/build_demo_identities.py` (`names`, float16 `modes` (K, V, 3))."""
    path = Path(path)
    try:
        archive = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as error:
        raise RigError(f"{path}: cannot read identity modes npz: {error}") from None
    with archive:
        missing = [key for key in ("names", "modes") if key not in archive.files]
        if missing:
            raise RigError(f"{path}: not an identity modes npz (missing {', '.join(missing)})")
        names = tuple(str(name) for name in archive["names"])
        modes = archive["modes"].astype(np.float32)
    if modes.ndim != 3 or modes.shape[2] != 3 or modes.shape[0] == 0:
        raise RigError(f"{path}: modes must have shape (K, V, 3) with K > 0, got {modes.shape}")
    if len(names) != modes.shape[0]:
        raise RigError(f"{path}: {len(names)} mode names for {modes.shape[0]} modes")
    if not np.isfinite(modes).all():
        raise RigError(f"{path}: modes have non-finite values")
    return IdentityModes(names=names, modes=modes)


def _check_modes(rig: VisemeRig, modes: IdentityModes) -> None:
    if modes.n_vertices != rig.n_vertices:
        raise RigError(
            f"rig {rig.name!r}: identity modes have {modes.n_vertices} vertices, the rig has {rig.n_vertices}"
        )


def apply_identity(
    rig: VisemeRig, modes: IdentityModes, coefficients, scale: float = 1.0, name: str | None = None
) -> VisemeRig:
    """The rig with a subject's neutral: scale * (neutral + sum_k c_k mode_k), and the viseme deltas times `scale`.

    The visemes are carried over by the simplest deformation transfer: each viseme keeps its per-vertex offset from
    the neutral (scaled with the face), so only the rest shape changes. That holds for identity changes that are
    small against the size of the viseme motion; a full deformation transfer (Sumner and Popovic 2004) would also
    rotate and stretch the offsets with the local surface. `coefficients` is (K,) in units of one standard deviation.
    """
    _check_modes(rig, modes)
    c = np.asarray(coefficients, dtype=np.float64).reshape(-1)
    if c.shape != (modes.n_modes,):
        raise ValueError(f"coefficients must have shape ({modes.n_modes},), got {np.shape(coefficients)}")
    if not (np.isfinite(c).all() and math.isfinite(scale) and scale > 0):
        raise ValueError(f"coefficients must be finite and scale positive, got scale {scale!r}")
    offset = np.tensordot(c, modes.modes.astype(np.float64), axes=1)
    neutral = (scale * (rig.neutral.astype(np.float64) + offset)).astype(np.float32)
    deltas = (scale * rig.deltas.astype(np.float64)).astype(np.float32)
    return replace(rig, name=rig.name if name is None else name, neutral=neutral, deltas=deltas)


def mouth_opening(points: np.ndarray) -> np.ndarray:
    """(T, 68, 2) landmarks -> (T,) inner-lip gap over mouth width (0 closed, 0.1-0.2 in open speech on GRID)."""
    points = np.asarray(points, dtype=np.float64)
    gap = np.mean([np.linalg.norm(points[:, upper] - points[:, lower], axis=1) for upper, lower in _INNER_LIP_PAIRS],
                  axis=0)
    width = np.linalg.norm(points[:, _MOUTH_CORNERS[0]] - points[:, _MOUTH_CORNERS[1]], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return gap / width


def neutral_frames(
    track: LandmarkTrack,
    n: int = 10,
    silence: np.ndarray | None = None,
    speech_penalty: float = 0.1,
    width_weight: float = 0.5,
) -> np.ndarray:
    """(n,) sorted frame indices most likely showing the neutral face, fewer when fewer frames qualify.

    A frame qualifies when all its non-jaw landmarks are valid. Frames are ranked by a score, smallest first:
    the inner-lip opening relative to mouth width (`mouth_opening`), plus `width_weight` times how far the mouth
    width (relative to the outer eye-corner distance) strays from the track's median in log units, which demotes
    closed but puckered or smiling mouths, plus `speech_penalty` for frames outside silence when `silence`
    ((T,) bool, True in pauses, e.g. from the phone alignment) is given. With the default penalty a silent frame
    loses to a speech frame only when its mouth is clearly more open (by a tenth of the mouth width).
    """
    if n < 1:
        raise ValueError(f"n must be at least 1, got {n}")
    points = np.asarray(track.points, dtype=np.float64)
    jaw = np.zeros(N_POINTS, bool)
    jaw[list(GROUPS["jaw"])] = True
    usable = track.valid[:, ~jaw].all(axis=1)
    if not usable.any():
        raise ValueError("no frame of the landmark track has all non-jaw landmarks valid")
    score = mouth_opening(points)
    eyes = np.linalg.norm(points[:, _EYE_CORNERS[0]] - points[:, _EYE_CORNERS[1]], axis=1)
    mouth = np.linalg.norm(points[:, _MOUTH_CORNERS[0]] - points[:, _MOUTH_CORNERS[1]], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        log_width = np.log(mouth / eyes)
    score = score + width_weight * np.abs(log_width - np.median(log_width[usable]))
    if silence is not None:
        silence = np.asarray(silence, dtype=bool)
        if silence.shape != (track.n_frames,):
            raise ValueError(f"silence must have shape ({track.n_frames},), one flag per frame, got {silence.shape}")
        score = score + speech_penalty * ~silence
    candidates = np.flatnonzero(usable)
    order = candidates[np.argsort(score[candidates], kind="stable")]
    return np.sort(order[:n])


@dataclass(frozen=True)
class IdentityFit:
    """The result of `fit_identity`; row i of the pose arrays belongs to video frame `frames[i]`."""

    coefficients: np.ndarray
    """(K,) identity coefficients in standard deviations."""
    scale: float
    """Global scale of the face (see the module docstring: held near 1 by its prior)."""
    rotation: np.ndarray
    """(T_n, 3) axis-angle head rotation per frame (rad), the convention of `render.camera`."""
    translation: np.ndarray
    """(T_n, 3) head translation per frame, in rig units (centimetres for the demo rig)."""
    camera: Intrinsics
    """The camera given, or the one fitted (square pixels, principal point at the image centre)."""
    rms_px: float
    """Root mean square reprojection distance in pixels over the valid used landmarks, weighted by landmark weight."""
    frames: np.ndarray
    """(T_n,) the video frames used."""
    residuals_px: np.ndarray
    """(T_n, 68) reprojection distance per landmark in pixels; NaN where not valid or the rig has no vertex."""

    def rms_over(self, landmarks) -> float:
        """Plain RMS reprojection distance in pixels over the given landmark indices (valid ones only)."""
        chosen = self.residuals_px[:, np.asarray(landmarks)]
        return float(np.sqrt(np.nanmean(chosen**2)))


def landmark_weights(jaw_weight: float = 0.1) -> np.ndarray:
    """(68,) default landmark weights: 1, and `jaw_weight` for the jaw contour 0-16, which a detector places on
    the face's silhouette as seen from the camera rather than on fixed points of the skin."""
    weights = np.ones(N_POINTS)
    weights[list(GROUPS["jaw"])] = jaw_weight
    return weights


class _Problem:
    """The fit as a vector of weighted residuals r(theta), so Gauss-Newton minimises |r|^2."""

    def __init__(self, base, basis, observed, mask, weights, camera, focal0, fit_focal, prior):
        self.base = base  # (L, 3) neutral landmark vertices
        self.basis = basis  # (K, L, 3) modes at those vertices
        self.observed = observed  # (T, L, 2) pixels (0 where not valid)
        self.sqrt_w = torch.sqrt(weights)[None, :, None] * mask[..., None]  # (T, L, 1)
        self.camera = camera
        self.log_focal0 = math.log(focal0)
        self.fit_focal = fit_focal
        self.sigma_px, self.scale_sigma, self.focal_sigma = prior
        self.n_frames, self.n_modes = observed.shape[0], basis.shape[0]
        self.sqrt_frames = math.sqrt(self.n_frames)

    def split(self, theta: torch.Tensor):
        k, t = self.n_modes, self.n_frames
        c = theta[:k]
        log_scale = theta[k]
        rotation = theta[k + 1 : k + 1 + 3 * t].reshape(t, 3)
        translation = theta[k + 1 + 3 * t : k + 1 + 6 * t].reshape(t, 3)
        log_focal = theta[k + 1 + 6 * t] if self.fit_focal else torch.as_tensor(self.log_focal0, dtype=theta.dtype)
        return c, log_scale, rotation, translation, log_focal

    def pack(self, c, log_scale, rotation, translation, log_focal) -> torch.Tensor:
        parts = [c.reshape(-1), log_scale.reshape(1), rotation.reshape(-1), translation.reshape(-1)]
        if self.fit_focal:
            parts.append(log_focal.reshape(1))
        return torch.cat(parts)

    def pixels(self, theta: torch.Tensor) -> torch.Tensor:
        c, log_scale, rotation, translation, log_focal = self.split(theta)
        shape = torch.exp(log_scale) * (self.base + torch.einsum("k,kld->ld", c, self.basis))
        cam = to_camera(shape.expand(self.n_frames, -1, -1), rotation, translation)
        depth = (-cam[..., 2]).clamp_min(1e-6)
        focal = torch.exp(log_focal)
        u = self.camera.cx + focal * cam[..., 0] / depth
        v = self.camera.cy - focal * cam[..., 1] / depth
        return torch.stack([u, v], dim=-1)

    def residuals(self, theta: torch.Tensor, identity: bool = True) -> torch.Tensor:
        c, log_scale, _, _, log_focal = self.split(theta)
        data = ((self.pixels(theta) - self.observed) * self.sqrt_w / self.sigma_px).reshape(-1) / self.sqrt_frames
        prior = [log_scale.reshape(1) / self.scale_sigma]
        if identity:
            prior.append(c)
        if self.fit_focal:
            prior.append(((log_focal - self.log_focal0) / self.focal_sigma).reshape(1))
        return torch.cat([data, *prior])


    def jacobian(self, theta: torch.Tensor, identity: bool = True) -> torch.Tensor:
        """d residuals(theta, identity) / d theta, written out: (rows of `residuals`, len(theta)).

        Each frame's residuals depend on the shared entries (coefficients, scale, focal) and on that frame's pose
        alone, so the matrix is built block by block; equal to forward-mode AD through `residuals` to float64
        rounding (tests/test_identity.py), at a tenth of its cost (`torch.func.jacfwd` pushed one tangent per
        entry of theta, 6 per frame, through the whole model)."""
        c, log_scale, rotation, translation, log_focal = self.split(theta)
        k, t = self.n_modes, self.n_frames
        n_points = self.base.shape[0]
        scale = torch.exp(log_scale)
        shape = self.base + torch.einsum("k,kld->ld", c, self.basis)              # (L, 3) before the scale
        rmat = rotation_matrices(rotation)                                          # (T, 3, 3)
        mesh = scale * shape
        cam = mesh @ rmat.transpose(1, 2) + translation[:, None, :]                # (T, L, 3)
        depth = (-cam[..., 2]).clamp_min(1e-6)
        in_front = (-cam[..., 2] > 1e-6).to(cam.dtype)                            # where the clamp passes z on
        focal = torch.exp(log_focal)
        inv = 1.0 / depth
        d = cam.new_zeros(t, n_points, 2, 3)                                       # d pixel / d camera point
        d[..., 0, 0] = focal * inv
        d[..., 0, 2] = focal * cam[..., 0] * inv * inv * in_front
        d[..., 1, 1] = -focal * inv
        d[..., 1, 2] = -focal * cam[..., 1] * inv * inv * in_front
        d = d * (self.sqrt_w / self.sigma_px / self.sqrt_frames)[..., None]       # as the residuals weigh them
        d_mesh = d @ rmat[:, None]                                                 # (T, L, 2, 3) per mesh offset
        d_rot = -d_mesh @ cross_matrices(mesh)[None] @ right_jacobian(rotation)[:, None]
        rows_data = t * n_points * 2
        n_prior = 1 + (k if identity else 0) + (1 if self.fit_focal else 0)
        jac = theta.new_zeros(rows_data + n_prior, theta.shape[0])
        data = jac[:rows_data].view(t, n_points, 2, -1)
        data[..., :k] = scale * torch.einsum("tlpd,kld->tlpk", d_mesh, self.basis)
        data[..., k] = torch.einsum("tlpd,ld->tlp", d_mesh, mesh)
        # frame j's rows get its own pose's columns only: rotation at k + 1 + 3j.., translation 3T further
        frames = torch.arange(t)
        rot_cols = k + 1 + 3 * frames[:, None] + torch.arange(3)[None]              # (T, 3)
        data[frames[:, None, None, None], torch.arange(n_points)[None, :, None, None],
             torch.arange(2)[None, None, :, None], rot_cols[:, None, None, :]] = d_rot
        data[frames[:, None, None, None], torch.arange(n_points)[None, :, None, None],
             torch.arange(2)[None, None, :, None], (rot_cols + 3 * t)[:, None, None, :]] = d
        if self.fit_focal:
            pixels = torch.stack([focal * cam[..., 0] * inv, -focal * cam[..., 1] * inv], dim=-1)
            data[..., -1] = pixels * (self.sqrt_w / self.sigma_px / self.sqrt_frames)
        row = rows_data
        jac[row, k] = 1.0 / self.scale_sigma
        row += 1
        if identity:
            jac[row:row + k, :k] = torch.eye(k, dtype=theta.dtype)
            row += k
        if self.fit_focal:
            jac[row, -1] = 1.0 / self.focal_sigma
        return jac


def _gauss_newton(residual_fn, jacobian_fn, theta: torch.Tensor, free: torch.Tensor, iterations: int) -> torch.Tensor:
    """Levenberg-Marquardt on the entries of `theta` where `free` is True; returns the improved theta."""
    damping = 1e-3
    r = residual_fn(theta)
    cost = float(r @ r)
    for _ in range(iterations):
        jacobian = jacobian_fn(theta)[:, free]
        hessian = jacobian.T @ jacobian
        gradient = jacobian.T @ r
        diagonal = torch.diag(hessian).clamp_min(1e-9)
        improved = False
        while damping < 1e10:
            step = torch.linalg.solve(hessian + damping * torch.diag(diagonal), -gradient)
            trial = theta.clone()
            trial[free] += step
            r_trial = residual_fn(trial)
            cost_trial = float(r_trial @ r_trial)
            if math.isfinite(cost_trial) and cost_trial < cost:
                improved = True
                break
            damping *= 4.0
        if not improved:
            break
        decrease = (cost - cost_trial) / max(cost, 1e-12)
        theta, r, cost = trial, r_trial, cost_trial
        damping = max(damping / 3.0, 1e-9)
        if decrease < 1e-10:
            break
    return theta


def fit_identity(
    rig: VisemeRig,
    modes: IdentityModes,
    track: LandmarkTrack,
    frames,
    camera: Intrinsics | None = None,
    image_size: tuple[int, int] | None = None,
    regularisation: float = 4.0,
    iterations: int = 50,
    jaw_weight: float = 0.1,
    scale_sigma: float = 0.1,
    focal_sigma: float = 0.5,
    fov_deg: float = 25.0,
) -> IdentityFit:
    """Identity coefficients, scale, per-frame head pose and (camera None) focal length from neutral frames.

    Minimises  mean_frames sum_landmarks w_l |proj(landmark vertex) - landmark|^2  +  lambda |c|^2
    + lambda (log scale / scale_sigma)^2  [+ lambda (log(f / f0) / focal_sigma)^2]  with lambda = `regularisation`
    (px^2): for one frame, the negative log posterior (times 2 lambda) for landmark noise of sqrt(lambda) pixels per
    coordinate and the identity prior c ~ N(0, 1). The data term is a mean over frames, not a sum, because a
    detector's disagreement with the model's landmark vertices repeats in every frame of one face: more frames pin
    the pose down but should not overrule the prior. A larger `regularisation` keeps the face nearer the mean. Weights w_l are 1, `jaw_weight` on the jaw contour
    (see `landmark_weights`); missing landmarks and landmarks the rig has no vertex for are left out.

    `frames` (T_n,) are video frame indices of `track` (e.g. from `neutral_frames`). With `camera` None the focal
    length is fitted (square pixels, principal point at the image centre), starting from, and drawn towards,
    `Intrinsics.from_fov(*image_size, fov_deg)`; `image_size` = (width, height) is then required.

    Solver: the pose of each frame is first fitted to the mean face from a frontal start at the landmark centroid,
    at the depth where the face's size matches the landmark spread; then everything together. Both stages are
    Levenberg-Marquardt (Gauss-Newton with adaptive damping) on exact Jacobians (written out, float64).
    """
    _check_modes(rig, modes)
    if regularisation <= 0 or scale_sigma <= 0 or focal_sigma <= 0:
        raise ValueError("regularisation, scale_sigma and focal_sigma must be positive")
    if camera is None:
        if image_size is None:
            raise ValueError("fit_identity needs image_size=(width, height) when the camera is unknown")
        camera = Intrinsics.from_fov(int(image_size[0]), int(image_size[1]), fov_deg)
        fit_focal = True
    else:
        fit_focal = False
    frames = np.asarray(frames, dtype=np.int64).reshape(-1)
    if frames.size == 0 or frames.min() < 0 or frames.max() >= track.n_frames:
        raise ValueError(f"frames must be indices into the track's {track.n_frames} frames, got {frames.tolist()}")

    weights = landmark_weights(jaw_weight) * rig.valid_landmarks
    landmarks = np.flatnonzero(weights > 0)
    vertex_ids = np.asarray(rig.landmark_ids)[landmarks]
    valid = track.valid[frames][:, landmarks]
    keep = valid.sum(axis=1) >= 6
    if not keep.any():
        raise ValueError(f"none of frames {frames.tolist()} has 6 or more valid landmarks to fit")
    frames, valid = frames[keep], valid[keep]
    observed = np.nan_to_num(track.points[frames][:, landmarks].astype(np.float64))

    dtype = torch.float64
    base = torch.as_tensor(rig.neutral[vertex_ids], dtype=dtype)
    problem = _Problem(
        base=base,
        basis=torch.as_tensor(modes.modes[:, vertex_ids], dtype=dtype),
        observed=torch.as_tensor(observed, dtype=dtype),
        mask=torch.as_tensor(valid, dtype=dtype),
        weights=torch.as_tensor(weights[landmarks], dtype=dtype),
        camera=camera,
        focal0=camera.fx,
        fit_focal=fit_focal,
        prior=(math.sqrt(regularisation), float(scale_sigma), float(focal_sigma)),
    )
    translation = _initial_translation(base.numpy(), observed, valid, weights[landmarks], camera)
    theta = problem.pack(
        torch.zeros(modes.n_modes, dtype=dtype),
        torch.zeros((), dtype=dtype),
        torch.zeros(len(frames), 3, dtype=dtype),
        torch.as_tensor(translation, dtype=dtype),
        torch.as_tensor(math.log(camera.fx), dtype=dtype),
    )
    pose_only = torch.zeros_like(theta, dtype=torch.bool)
    pose_only[modes.n_modes + 1 : modes.n_modes + 1 + 6 * len(frames)] = True
    theta = _gauss_newton(lambda th: problem.residuals(th, identity=False),
                          lambda th: problem.jacobian(th, identity=False), theta, pose_only, iterations)
    theta = _gauss_newton(problem.residuals, problem.jacobian, theta, torch.ones_like(pose_only), iterations)

    c, log_scale, rotation, translation, log_focal = problem.split(theta)
    if fit_focal:
        focal = float(torch.exp(log_focal))
        camera = replace(camera, fx=focal, fy=focal)
    with torch.no_grad():
        distance = torch.linalg.norm(problem.pixels(theta) - problem.observed, dim=-1).numpy()
    distance[~valid] = np.nan
    residuals = np.full((len(frames), N_POINTS), np.nan)
    residuals[:, landmarks] = distance
    w = np.broadcast_to(weights[landmarks], distance.shape)[valid]
    rms = float(np.sqrt(np.sum(w * distance[valid] ** 2) / np.sum(w)))
    return IdentityFit(
        coefficients=c.detach().numpy().astype(np.float32),
        scale=float(torch.exp(log_scale)),
        rotation=rotation.detach().numpy().copy(),
        translation=translation.detach().numpy().copy(),
        camera=camera,
        rms_px=rms,
        frames=frames,
        residuals_px=residuals,
    )


def _initial_translation(
    vertices: np.ndarray, observed: np.ndarray, valid: np.ndarray, weights: np.ndarray, camera: Intrinsics
) -> np.ndarray:
    """(T, 3) translations that put the unrotated face's landmark centroid on the observed centroid, at the depth
    where the face's spread in x, y matches the landmarks' spread in pixels."""
    out = np.zeros((len(observed), 3))
    focal = 0.5 * (camera.fx + camera.fy)
    for t in range(len(observed)):
        w = weights * valid[t]
        w = w / w.sum()
        centre_3d = w @ vertices
        centre_2d = w @ observed[t]
        spread_3d = math.sqrt(w @ np.sum((vertices[:, :2] - centre_3d[:2]) ** 2, axis=1))
        spread_2d = math.sqrt(w @ np.sum((observed[t] - centre_2d) ** 2, axis=1))
        depth = focal * spread_3d / max(spread_2d, 1e-6)
        x = (centre_2d[0] - camera.cx) * depth / camera.fx
        y = -(centre_2d[1] - camera.cy) * depth / camera.fy
        out[t] = (x - centre_3d[0], y - centre_3d[1], -depth - centre_3d[2])
    return out


# ---- one identity per speaker (and image size), fitted once on neutral frames pooled from a few of its clips -------

@dataclass(frozen=True)
class SpeakerIdentity:
    """A speaker's face and camera fitted once on neutral frames pooled from a few of their clips (`clips`), used
    for every clip of that speaker with frames of `image_size` (a camera of another size gets its own fit).

    Plain values only (JSON-able: it is a task's cached result and part of the per-clip tracking tasks' cache keys,
    by `digest`). The camera is one per speaker and image size: square pixels, principal point at the image
    centre, focal length `focal` (px)."""

    coefficients: tuple[float, ...]
    scale: float
    focal: float
    image_size: tuple[int, int]
    clips: tuple[str, ...]
    """The clips (utterance ids, sorted) whose neutral frames were fitted: those of the chosen clips that had one."""
    frames: int
    """Neutral frames fitted, over all those clips."""
    rms_px: float

    def to_dict(self) -> dict:
        return {"coefficients": [float(c) for c in self.coefficients], "scale": float(self.scale),
                "focal": float(self.focal), "image_size": [int(v) for v in self.image_size],
                "clips": list(self.clips), "frames": int(self.frames), "rms_px": float(self.rms_px)}

    @classmethod
    def from_dict(cls, data: dict) -> "SpeakerIdentity":
        return cls(tuple(float(c) for c in data["coefficients"]), float(data["scale"]), float(data["focal"]),
                   (int(data["image_size"][0]), int(data["image_size"][1])), tuple(str(c) for c in data["clips"]),
                   int(data["frames"]), float(data["rms_px"]))

    @property
    def digest(self) -> str:
        from visemeflow.hashing import stable_hash

        return stable_hash(self.to_dict())

    def camera(self, fov_deg: float = 25.0) -> Intrinsics:
        camera = Intrinsics.from_fov(self.image_size[0], self.image_size[1], fov_deg)
        return replace(camera, fx=self.focal, fy=self.focal)

    def apply(self, rig: VisemeRig, modes: IdentityModes) -> VisemeRig:
        return apply_identity(rig, modes, np.asarray(self.coefficients), self.scale)


def pooled_neutral_track(clips, total_frames: int = 10) -> tuple[LandmarkTrack, tuple[str, ...]] | None:
    """The neutral frames of several clips as one track, and the clips they come from; None when no clip has one.

    `clips`: (clip id, LandmarkTrack) pairs, taken in sorted id order whatever order they come in. Each clip gives
    its ceil(`total_frames` / number of clips) best neutral frames (`neutral_frames`); a clip with no usable frame
    gives none. With one clip this is that clip's `neutral_frames(track, total_frames)`: the per-clip fit."""
    clips = sorted(clips, key=lambda c: c[0])
    if not clips:
        return None
    per_clip = max(1, math.ceil(total_frames / len(clips)))
    points, valid, used = [], [], []
    for clip_id, track in clips:
        try:
            frames = neutral_frames(track, n=per_clip)
        except ValueError:      # no frame with every non-jaw landmark
            continue
        points.append(np.asarray(track.points)[frames])
        valid.append(np.asarray(track.valid)[frames])
        used.append(clip_id)
    if not used:
        return None
    return (LandmarkTrack(np.concatenate(points), np.concatenate(valid), clips[0][1].fps, clips[0][1].source),
            tuple(used))


def fit_speaker_identity(rig: VisemeRig, modes: IdentityModes, clips, image_size: tuple[int, int],
                         total_frames: int = 10, **fit_options) -> SpeakerIdentity | None:
    """`fit_identity` (unknown camera) on the neutral frames pooled from `clips` ((clip id, LandmarkTrack) pairs of
    one speaker, frames of `image_size` = (width, height)) by `pooled_neutral_track`; None when no clip has a
    neutral frame (the caller then fits each clip on its own, as without a speaker identity). The same clips give
    the same identity in whatever order they come."""
    pooled = pooled_neutral_track(clips, total_frames)
    if pooled is None:
        return None
    track, used = pooled
    try:
        fit = fit_identity(rig, modes, track, np.arange(track.n_frames), camera=None,
                           image_size=(int(image_size[0]), int(image_size[1])), **fit_options)
    except ValueError:          # no pooled frame with 6 valid landmarks
        return None
    return SpeakerIdentity(tuple(float(c) for c in fit.coefficients), float(fit.scale), float(fit.camera.fx),
                           (int(image_size[0]), int(image_size[1])), used, int(len(fit.frames)), float(fit.rms_px))
