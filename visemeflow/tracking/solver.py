"""Phoneme-guided viseme fitting (paper 4.3): the faithful per-frame solver and the fast whole-utterance solver.

Both minimise Eq. 1, w1 L_lmk + w2 L_rgb + w3 L_sup + w4 L_act + w5 L_flow + w6 L_diff + w7 L_range, over the
16 viseme weights and the 6-DoF head pose of each frame, initialised from the procedural curves, and truncate the
weights to [0, 1] at the end.

- Faithful: the paper's schedule. Frame by frame, Adam for 250 iterations at learning rate 0.1 decaying
  exponentially every 10 iterations; the previous frame's solution is fixed in L_diff and L_flow; a forward pass
  through the frames, then a backward pass in reverse order (the neighbour is then the next frame).
- Fast: the same objective over the whole utterance at once, all frames one batch, L_diff and L_flow linking
  neighbouring frames in both directions, Adam with a cosine-decayed learning rate.

Both keep the weights in [0, 1] by projection after every step by default (`box="projected"`); `box="soft"` is the
paper's L_range penalty with truncation at the end (see `TrackingConfig.box` for why it is not the default).

Pixel errors are measured as if the face were `reference_face_px` tall (brow to chin), so that the paper's loss
weights keep their balance whatever the video's size and framing: landmark and flow residuals are multiplied by
reference_face_px / (the median brow-to-chin height of the detected landmarks).
"""

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field

from visemeflow.rig import VisemeRig, evaluate_rig
from visemeflow.render.camera import Intrinsics, project
from visemeflow.tracking.losses import (
    activation_loss,
    diff_loss,
    flow_loss,
    guidance_sets,
    landmark_loss,
    range_loss,
    suppression_loss,
)
from visemeflow.visemes import N_VISEMES

MOUTH = slice(48, 68)


class TrackingConfig(BaseModel):
    """Weights of Eq. 1 (paper defaults), guidance sets, solver schedule; ablation switches."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    w_lmk: float = Field(0.8, ge=0, description="w1, landmark loss (Eq. 2).")
    w_rgb: float = Field(1.0, ge=0, description="w2, RGB photo loss (Eq. 3).")
    w_sup: float = Field(800.0, ge=0, description="w3, phoneme-guided suppression (Eq. 4).")
    w_act: float = Field(150.0, ge=0, description="w4, phoneme-guided activation (Eq. 5).")
    w_flow: float = Field(1.0, ge=0, description="w5, optical-flow loss (Eq. 6).")
    w_diff: float = Field(300.0, ge=0, description="w6, temporal consistency (Eq. 7).")
    w_range: float = Field(100.0, ge=0, description="w7, value range (Eq. 8).")
    m: int = Field(3, ge=1, le=N_VISEMES, description="A viseme outside the top m of every neighbouring frame is suppressed.")
    n: int = Field(2, ge=1, le=N_VISEMES, description="The top n visemes of a frame are activated.")
    guidance_radius: int = Field(1, ge=0, description="Neighbouring frames for I_sup: j-radius..j+radius.")
    guidance: bool = Field(True, description="Phoneme guidance on; off sets w3 = w4 = 0 (paper Fig. 3-4 ablation).")
    use_rgb: bool = Field(False, description="Include L_rgb (needs the video frames).")
    use_flow: bool = Field(True, description="Include L_flow (needs the video frames).")
    solver: Literal["fast", "faithful"] = Field("fast", description="Whole-utterance batch, or the paper's per-frame schedule.")
    iterations: int = Field(250, ge=1, description="Faithful: Adam iterations per frame and pass.")
    lr: float = Field(0.1, gt=0, description="Faithful: Adam learning rate.")
    lr_decay: float = Field(0.9, gt=0, le=1, description="Faithful: learning-rate factor applied every 10 iterations.")
    passes: tuple[str, ...] = Field(("forward", "backward"), description="Faithful: passes through the frames.")
    fast_iterations: int = Field(300, ge=1, description="Fast: Adam iterations over the whole utterance.")
    fast_lr: float = Field(0.05, gt=0, description="Fast: peak Adam learning rate (cosine decay).")
    rgb_iterations: int = Field(20, ge=0, description="Fast with L_rgb: refinement iterations including the photo term.")
    mouth_weight: float = Field(1.0, ge=0, description="beta_k of the 20 mouth landmarks (48-67).")
    face_weight: float = Field(0.3, ge=0, description="beta_k of brows, eyes and nose (17-47).")
    jaw_weight: float = Field(0.0, ge=0, description="beta_k of the jaw contour (0-16): 2D silhouette points.")
    pose_iterations: int = Field(200, ge=0, description="Rigid pose initialisation iterations.")
    box: Literal["projected", "soft"] = Field(
        "projected",
        description=(
            "How weights are kept in [0, 1]: 'projected' clamps after every optimiser step (L_range is then zero); "
            "'soft' is the paper's L_range penalty and a truncation at the end. With the paper's weights the soft "
            "form is unbounded below once two activated visemes exceed 1 (L_act gives each -150/2 x^2, L_range only "
            "+100/2 (x-1)^2), so only the landmarks hold the weights back."
        ),
    )
    pose_lr_factor: float = Field(
        0.1, gt=0, description="Learning rate of the head pose (rad, cm) relative to the viseme weights' rate."
    )
    reference_face_px: float = Field(
        1000.0, gt=0, description="Face height (brow to chin) at which pixel residuals are measured (see module doc)."
    )

    def effective(self) -> "TrackingConfig":
        """The config with the ablation switches applied to the weights."""
        updates = {}
        if not self.guidance:
            updates.update(w_sup=0.0, w_act=0.0)
        if not self.use_rgb:
            updates["w_rgb"] = 0.0
        if not self.use_flow:
            updates["w_flow"] = 0.0
        return self.model_copy(update=updates)

    @property
    def variant(self) -> str:
        """Name of the curves this configuration produces, e.g. `guided-fast`, `unguided-faithful-rgb`."""
        parts = ["guided" if self.guidance else "unguided", self.solver]
        if self.use_rgb:
            parts.append("rgb")
        if not self.use_flow:
            parts.append("noflow")
        return "-".join(parts)


@dataclass
class FlowTerm:
    """Optical-flow correspondences for L_flow: vertices tracked and how to get their displacements.

    `correspond(j, points)` gives (displacement (N, 2), valid (N,)) from frame j-1 to frame j for the pixel
    positions `points` (N, 2) in frame j-1; `correspond_back(j, points)` from frame j+1 to frame j.
    """

    vertex_ids: np.ndarray
    correspond: Callable[[int, np.ndarray], tuple[np.ndarray, np.ndarray]]
    correspond_back: Callable[[int, np.ndarray], tuple[np.ndarray, np.ndarray]]


class RgbTerm(Protocol):
    """Photo loss (Eq. 3): `prepare` once a pose estimate exists; then `vertex_ids` (R,) are the rig vertices it
    renders and `loss(j, vertices (R, 3), rotation (3,), translation (3,)) -> scalar` is frame j's term (see
    `visemeflow.tracking.photo.PhotoTerm`)."""

    vertex_ids: np.ndarray

    def prepare(self, curves: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> None: ...

    def loss(self, j: int, vertices: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor: ...


@dataclass
class TrackingProblem:
    """What one utterance gives the tracker."""

    rig: VisemeRig
    camera: Intrinsics
    landmarks: np.ndarray            # (T, 68, 2) pixels, NaN where missing
    valid: np.ndarray                # (T, 68) bool
    procedural: np.ndarray           # (T, 16) procedural curves on the video's frames
    flow: FlowTerm | None = None
    rgb: RgbTerm | None = None
    initial_rotation: np.ndarray | None = None     # (T, 3)
    initial_translation: np.ndarray | None = None  # (T, 3)

    @property
    def n_frames(self) -> int:
        return len(self.procedural)


@dataclass
class TrackingResult:
    curves: np.ndarray               # (T, 16) in [0, 1]
    rotation: np.ndarray             # (T, 3)
    translation: np.ndarray          # (T, 3)
    terms: dict[str, np.ndarray]     # per-frame value of each loss term (unweighted)
    mouth_error_px: np.ndarray       # (T,) mean distance of the 20 mouth landmarks, pixels; NaN without detections
    seconds: float
    iterations: int
    extra: dict[str, object] = field(default_factory=dict)


def flow_vertices(rig: VisemeRig, count: int = 300, seed: int = 0) -> np.ndarray:
    """Face-skin vertices of the lower face (between the nose tip and the chin, within the mouth corners' width
    plus a margin) that face the camera: the points L_flow follows. Up to `count`, spread by a fixed sample."""
    face = np.asarray(rig.regions.get("face", np.arange(rig.n_vertices)))
    lm = np.asarray(rig.landmark_ids)
    neutral = rig.neutral
    top, bottom = neutral[lm[33], 1], neutral[lm[8], 1]
    half_width = 1.6 * abs(neutral[lm[54], 0] - neutral[lm[48], 0]) / 2
    centre_x = 0.5 * (neutral[lm[48], 0] + neutral[lm[54], 0])
    p = neutral[face]
    normals = _vertex_normals(neutral, rig.faces)[face]
    keep = (p[:, 1] <= top) & (p[:, 1] >= bottom) & (np.abs(p[:, 0] - centre_x) <= half_width) & (normals[:, 2] > 0.5)
    ids = face[keep]
    if len(ids) > count:
        ids = np.sort(np.random.default_rng(seed).choice(ids, count, replace=False))
    return ids


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    out = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(out, faces[:, k], n)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)


def landmark_beta(config: TrackingConfig) -> torch.Tensor:
    beta = torch.full((68,), config.face_weight)
    beta[:17] = config.jaw_weight
    beta[MOUTH] = config.mouth_weight
    return beta


def face_height_px(landmarks: np.ndarray, valid: np.ndarray) -> float:
    """Median over frames of the brow-to-chin height of the landmarks (points 17-26 to point 8), pixels."""
    usable = valid[:, 8] & valid[:, 17:27].any(axis=1)
    if not usable.any():
        return float("nan")
    brow = np.where(valid[usable, 17:27], landmarks[usable, 17:27, 1], np.inf).min(axis=1)
    heights = landmarks[usable, 8, 1] - brow
    heights = heights[np.isfinite(heights) & (heights > 0)]
    return float(np.median(heights)) if len(heights) else float("nan")


def residual_scale(problem: TrackingProblem, config: TrackingConfig) -> float:
    """Factor on pixel residuals: reference face height over this video's face height (1 if unknown)."""
    height = face_height_px(problem.landmarks, problem.valid)
    return config.reference_face_px / height if np.isfinite(height) else 1.0


def check_problem(problem: TrackingProblem) -> None:
    t = problem.n_frames
    if problem.landmarks.shape != (t, 68, 2) or problem.valid.shape != (t, 68):
        raise ValueError(
            f"landmarks must be ({t}, 68, 2) with a ({t}, 68) mask to match {t} frames of procedural curves, "
            f"got {problem.landmarks.shape} and {problem.valid.shape}"
        )
    if not np.isfinite(problem.procedural).all():
        raise ValueError("procedural curves contain non-finite values")


def _landmark_ids(rig: VisemeRig) -> tuple[np.ndarray, np.ndarray]:
    ids = np.asarray(rig.landmark_ids)
    has = ids >= 0
    return ids[has], has


def initial_pose(problem: TrackingProblem, config: TrackingConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-frame head pose fitted to the non-mouth landmarks with the procedural weights held fixed."""
    cam = problem.camera
    ids, has = _landmark_ids(problem.rig)
    target = torch.as_tensor(np.nan_to_num(problem.landmarks[:, has]), dtype=torch.float32)
    valid = torch.as_tensor(problem.valid[:, has])
    beta = landmark_beta(config)[torch.as_tensor(has)]
    beta = torch.where(beta > 0, torch.ones_like(beta), beta)
    beta[torch.as_tensor(np.flatnonzero(has) >= 48)] = 0.2  # the mouth moves: lean on the rigid points
    with torch.no_grad():
        points = evaluate_rig(problem.rig, torch.as_tensor(problem.procedural, dtype=torch.float32), ids)
    if problem.initial_rotation is not None and problem.initial_translation is not None:
        rotation = torch.as_tensor(problem.initial_rotation, dtype=torch.float32).clone()
        translation = torch.as_tensor(problem.initial_translation, dtype=torch.float32).clone()
    else:
        rotation, translation = _pose_guess(points, target, valid, cam, np.flatnonzero(has))
    rotation.requires_grad_(True)
    translation.requires_grad_(True)
    if config.pose_iterations:
        scale = residual_scale(problem, config)
        opt = torch.optim.Adam([rotation, translation], lr=0.02)
        for _ in range(config.pose_iterations):
            opt.zero_grad()
            loss = landmark_loss(project(points, rotation, translation, cam) * scale, target * scale, valid, beta).sum()
            loss.backward()
            opt.step()
    return rotation.detach(), translation.detach()


def _pose_guess(points: torch.Tensor, target: torch.Tensor, valid: torch.Tensor, cam: Intrinsics,
                landmark_index: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-frame head pose by OpenCV's PnP on the rigid landmarks (brows, eyes, nose: 17-47) of the model.

    Frames with too few detections take the nearest solved frame's pose.
    """
    import cv2

    t = len(points)
    rigid = (landmark_index >= 17) & (landmark_index <= 47)
    K = np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])
    flip = np.diag([1.0, -1.0, -1.0])  # OpenCV's camera looks down +z with y down; ours down -z with y up
    rotation = np.full((t, 3), np.nan)
    translation = np.full((t, 3), np.nan)
    pts, tgt, ok_all = points.numpy().astype(np.float64), target.numpy().astype(np.float64), valid.numpy()
    for j in range(t):
        ok = ok_all[j] & rigid
        if ok.sum() < 6:
            continue
        found, rvec, tvec = cv2.solvePnP(pts[j][ok], tgt[j][ok], K, None, flags=cv2.SOLVEPNP_EPNP)
        if not found:
            continue
        found, rvec, tvec = cv2.solvePnP(pts[j][ok], tgt[j][ok], K, None, rvec, tvec, True, cv2.SOLVEPNP_ITERATIVE)
        r_cv, _ = cv2.Rodrigues(rvec)
        r_ours, _ = cv2.Rodrigues(flip @ r_cv)
        rotation[j], translation[j] = r_ours.reshape(3), flip @ tvec.reshape(3)
    solved = np.flatnonzero(np.isfinite(rotation[:, 0]))
    if len(solved) == 0:
        rotation[:] = 0.0
        translation[:] = (0.0, 0.0, -80.0)
    else:
        for j in np.flatnonzero(~np.isfinite(rotation[:, 0])):
            k = solved[np.argmin(np.abs(solved - j))]
            rotation[j], translation[j] = rotation[k], translation[k]
    return torch.as_tensor(rotation, dtype=torch.float32), torch.as_tensor(translation, dtype=torch.float32)


class _Objective:
    """Eq. 1 for any set of frames, with the data of one problem prepared once as tensors."""

    def __init__(self, problem: TrackingProblem, config: TrackingConfig):
        self.problem, self.config = problem, config.effective()
        self.scale = residual_scale(problem, config)
        self.ids, has = _landmark_ids(problem.rig)
        self.target = torch.as_tensor(np.nan_to_num(problem.landmarks[:, has]), dtype=torch.float32)
        self.valid = torch.as_tensor(problem.valid[:, has])
        self.beta = landmark_beta(config)[torch.as_tensor(has)]
        sets = guidance_sets(problem.procedural, config.m, config.n, config.guidance_radius)
        self.suppress = torch.as_tensor(sets.suppress)
        self.activate = torch.as_tensor(sets.activate)
        self.flow_ids = None if problem.flow is None else np.asarray(problem.flow.vertex_ids)

    def points(self, weights: torch.Tensor, ids: np.ndarray) -> torch.Tensor:
        return evaluate_rig(self.problem.rig, weights, ids)

    def weighted(self, terms: dict[str, torch.Tensor]) -> torch.Tensor:
        c = self.config
        w = {"lmk": c.w_lmk, "rgb": c.w_rgb, "sup": c.w_sup, "act": c.w_act, "flow": c.w_flow,
             "diff": c.w_diff, "range": c.w_range}
        return sum(w[k] * v for k, v in terms.items() if w[k] != 0)

    def frame_terms(self, frames: slice | np.ndarray, x: torch.Tensor, rot: torch.Tensor, trans: torch.Tensor) -> dict[str, torch.Tensor]:
        """Per-frame terms that need no neighbour: landmarks, guidance, range; (F,) each."""
        cam = self.problem.camera
        proj = project(self.points(x, self.ids), rot, trans, cam) * self.scale
        terms = {
            "lmk": landmark_loss(proj, self.target[frames] * self.scale, self.valid[frames], self.beta),
            "range": range_loss(x),
        }
        if self.config.w_sup or self.config.w_act:
            terms["sup"] = suppression_loss(x, self.suppress[frames])
            terms["act"] = activation_loss(x, self.activate[frames])
        return terms


def mouth_errors(problem: TrackingProblem, curves: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(T,) mean pixel distance between the tracked and the detected mouth landmarks (48-67); NaN without any."""
    ids, has = _landmark_ids(problem.rig)
    with torch.no_grad():
        proj = project(evaluate_rig(problem.rig, torch.as_tensor(curves, dtype=torch.float32), ids),
                       torch.as_tensor(rotation, dtype=torch.float32), torch.as_tensor(translation, dtype=torch.float32),
                       problem.camera).numpy()
    full = np.full((len(curves), 68, 2), np.nan)
    full[:, has] = proj
    dist = np.linalg.norm(full[:, MOUTH] - problem.landmarks[:, MOUTH], axis=2)
    dist[~problem.valid[:, MOUTH]] = np.nan
    with np.errstate(all="ignore"):
        counts = np.isfinite(dist).sum(axis=1)
        return np.where(counts > 0, np.nansum(dist, axis=1) / np.maximum(counts, 1), np.nan)


def _finish(problem, x, rot, trans, terms, started, iterations, extra=None) -> TrackingResult:
    curves = np.clip(x.detach().numpy(), 0.0, 1.0).astype(np.float32)
    rotation, translation = rot.detach().numpy(), trans.detach().numpy()
    if not (np.isfinite(curves).all() and np.isfinite(rotation).all() and np.isfinite(translation).all()):
        raise FloatingPointError("the tracking objective diverged (non-finite weights or pose)")
    return TrackingResult(
        curves, rotation, translation, {k: v.astype(np.float32) for k, v in terms.items()},
        mouth_errors(problem, curves, rotation, translation), time.perf_counter() - started, iterations, extra or {},
    )


def solve_fast(problem: TrackingProblem, config: TrackingConfig = TrackingConfig()) -> TrackingResult:
    """All frames as one batch: Adam with cosine decay on (T, 16) weights and (T, 6) poses."""
    check_problem(problem)
    started = time.perf_counter()
    obj = _Objective(problem, config)
    rot, trans = initial_pose(problem, config)
    x = torch.tensor(problem.procedural, dtype=torch.float32, requires_grad=True)
    rot.requires_grad_(True)
    trans.requires_grad_(True)
    t = problem.n_frames
    all_frames = slice(0, t)
    opt = torch.optim.Adam([{"params": [x], "lr": config.fast_lr},
                            {"params": [rot, trans], "lr": config.fast_lr * config.pose_lr_factor}])
    base = [g["lr"] for g in opt.param_groups]
    flow_state = _FastFlow(obj, problem) if obj.config.w_flow and problem.flow is not None and t > 1 else None
    total_iterations = config.fast_iterations + (config.rgb_iterations if obj.config.w_rgb and problem.rgb else 0)
    for it in range(total_iterations):
        for g, lr in zip(opt.param_groups, base):
            g["lr"] = lr * 0.5 * (1 + math.cos(math.pi * it / total_iterations))
        opt.zero_grad()
        terms = obj.frame_terms(all_frames, x, rot, trans)
        if t > 1 and obj.config.w_diff:
            d = diff_loss(x[1:], x[:-1])
            terms["diff"] = torch.cat([d, d.new_zeros(1)]) + torch.cat([d.new_zeros(1), d])
        if flow_state is not None:
            if it % 50 == 0:
                flow_state.refresh(x, rot, trans)
            terms["flow"] = flow_state.loss(x, rot, trans)
        if it >= config.fast_iterations and obj.config.w_rgb and problem.rgb is not None:
            if it == config.fast_iterations:
                problem.rgb.prepare(x.detach().numpy(), rot.detach().numpy(), trans.detach().numpy())
            terms["rgb"] = _rgb_all(problem, obj, x, rot, trans)
        loss = obj.weighted(terms).sum()
        if not torch.isfinite(loss):
            raise FloatingPointError(f"non-finite tracking loss at iteration {it}")
        loss.backward()
        opt.step()
        if config.box == "projected":
            with torch.no_grad():
                x.clamp_(0.0, 1.0)
    with torch.no_grad():
        final = obj.frame_terms(all_frames, x, rot, trans)
        if t > 1:
            final["diff"] = torch.cat([x.new_zeros(1), diff_loss(x[1:], x[:-1])])
    terms_np = {k: v.detach().numpy() for k, v in final.items()}
    return _finish(problem, x, rot, trans, terms_np, started, total_iterations)


def _rgb_all(problem, obj, x, rot, trans) -> torch.Tensor:
    # only the vertices the photo term renders, split once: per-frame indexing of one (T, V, 3) tensor would
    # make every frame's backward pass touch all T frames
    vertices = evaluate_rig(problem.rig, x, problem.rgb.vertex_ids).unbind(0)
    rots, transes = rot.unbind(0), trans.unbind(0)
    return torch.stack([problem.rgb.loss(j, vertices[j], rots[j], transes[j]) for j in range(problem.n_frames)])


class _FastFlow:
    """L_flow over all neighbouring pairs, with correspondences refreshed from the current estimate."""

    def __init__(self, obj: _Objective, problem: TrackingProblem):
        self.obj, self.problem = obj, problem
        self.ids = obj.flow_ids
        self.disp = self.valid = None

    def _project(self, x, rot, trans):
        return project(self.obj.points(x, self.ids), rot, trans, self.problem.camera)

    def refresh(self, x, rot, trans) -> None:
        with torch.no_grad():
            proj = self._project(x, rot, trans).numpy()
        disp, valid = [], []
        for j in range(1, self.problem.n_frames):
            d, v = self.problem.flow.correspond(j, proj[j - 1])
            disp.append(d)
            valid.append(v)
        self.disp = torch.as_tensor(np.stack(disp), dtype=torch.float32)
        self.valid = torch.as_tensor(np.stack(valid))

    def loss(self, x, rot, trans) -> torch.Tensor:
        proj = self._project(x, rot, trans) * self.obj.scale
        pair = flow_loss(proj[1:], proj[:-1], self.disp * self.obj.scale, self.valid)
        return torch.cat([pair.new_zeros(1), pair])


def solve_faithful(problem: TrackingProblem, config: TrackingConfig = TrackingConfig()) -> TrackingResult:
    """The paper's schedule: per frame, Adam (lr 0.1, x0.9 every 10 iterations), forward then backward pass."""
    check_problem(problem)
    started = time.perf_counter()
    obj = _Objective(problem, config)
    rot0, trans0 = initial_pose(problem, config)
    t = problem.n_frames
    x_all = torch.tensor(problem.procedural, dtype=torch.float32)
    rot_all, trans_all = rot0.clone(), trans0.clone()
    if obj.config.w_rgb and problem.rgb is not None:
        problem.rgb.prepare(x_all.numpy(), rot_all.numpy(), trans_all.numpy())
    terms_all: dict[str, np.ndarray] = {}
    for direction in config.passes:
        order = range(t) if direction == "forward" else range(t - 1, -1, -1)
        prev_j = None
        for j in order:
            frame_terms = _solve_frame(problem, obj, config, j, prev_j, x_all, rot_all, trans_all, direction)
            for k, v in frame_terms.items():
                terms_all.setdefault(k, np.zeros(t, np.float32))[j] = v
            prev_j = j
    return _finish(problem, x_all, rot_all, trans_all, terms_all, started, config.iterations * t * len(config.passes))


def _solve_frame(problem, obj, config, j, prev_j, x_all, rot_all, trans_all, direction) -> dict[str, float]:
    """Optimise frame j in place (x_all, rot_all, trans_all hold the current solution of every frame)."""
    frames = np.array([j])
    x = x_all[j:j + 1].clone().requires_grad_(True)
    if prev_j is not None:
        # start the pose from the neighbour already solved in this pass: it moved little
        rot_init, trans_init = rot_all[prev_j:prev_j + 1], trans_all[prev_j:prev_j + 1]
    else:
        rot_init, trans_init = rot_all[j:j + 1], trans_all[j:j + 1]
    rot = rot_init.clone().requires_grad_(True)
    trans = trans_init.clone().requires_grad_(True)
    prev_x = None if prev_j is None else x_all[prev_j:prev_j + 1]
    flow = None
    if prev_j is not None and obj.config.w_flow and problem.flow is not None:
        with torch.no_grad():
            prev_proj = project(obj.points(prev_x, obj.flow_ids), rot_all[prev_j:prev_j + 1],
                                trans_all[prev_j:prev_j + 1], problem.camera)
        fn = problem.flow.correspond if direction == "forward" else problem.flow.correspond_back
        disp, valid = fn(j, prev_proj[0].numpy())
        flow = (prev_proj, torch.as_tensor(disp[None], dtype=torch.float32), torch.as_tensor(valid[None]))
    opt = torch.optim.Adam([{"params": [x], "lr": config.lr}, {"params": [rot, trans], "lr": config.lr * config.pose_lr_factor}])
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=10, gamma=config.lr_decay)
    for _ in range(config.iterations):
        opt.zero_grad()
        terms = _frame_objective(problem, obj, frames, x, rot, trans, prev_x, flow)
        loss = obj.weighted(terms).sum()
        if not torch.isfinite(loss):
            raise FloatingPointError(f"non-finite tracking loss at frame {j}")
        loss.backward()
        opt.step()
        sched.step()
        if config.box == "projected":
            with torch.no_grad():
                x.clamp_(0.0, 1.0)
    with torch.no_grad():
        x_all[j] = x[0]
        rot_all[j] = rot[0]
        trans_all[j] = trans[0]
        terms = _frame_objective(problem, obj, frames, x, rot, trans, prev_x, flow)
    return {k: float(v[0]) for k, v in terms.items()}


def _frame_objective(problem, obj, frames, x, rot, trans, prev_x, flow) -> dict[str, torch.Tensor]:
    terms = obj.frame_terms(frames, x, rot, trans)
    if prev_x is not None and obj.config.w_diff:
        terms["diff"] = diff_loss(x, prev_x)
    if flow is not None:
        prev_proj, disp, valid = flow
        proj = project(obj.points(x, obj.flow_ids), rot, trans, problem.camera)
        terms["flow"] = flow_loss(proj * obj.scale, prev_proj * obj.scale, disp * obj.scale, valid)
    if obj.config.w_rgb and problem.rgb is not None:
        vertices = evaluate_rig(problem.rig, x, problem.rgb.vertex_ids)
        terms["rgb"] = problem.rgb.loss(int(frames[0]), vertices[0], rot[0], trans[0])[None]
    return terms
