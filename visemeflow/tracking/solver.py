"""Phoneme-guided viseme fitting (paper 4.3): the faithful per-frame solver and the fast whole-utterance solver.

Both minimise Eq. 1, w1 L_lmk + w2 L_rgb + w3 L_sup + w4 L_act + w5 L_flow + w6 L_diff + w7 L_range, over the
16 viseme weights and the 6-DoF head pose of each frame, initialised from the procedural curves, and truncate the
weights to [0, 1] at the end.

- Faithful: the paper's schedule. Frame by frame, Adam for 250 iterations at learning rate 0.1 decaying
  exponentially every 10 iterations; the previous frame's solution is fixed in L_diff and L_flow; a forward pass
  through the frames, then a backward pass in reverse order (the neighbour is then the next frame).
- Fast: the same objective over the whole utterance at once, all frames one batch, L_diff and L_flow linking
  neighbouring frames in both directions. By default Adam with a cosine-decayed learning rate (50 pose + 200
  joint steps, their gradient written out, `_Gradient`; autograd with L_rgb; also the only method for
  box="soft" and with L_rgb); `fast_method="lm"`: Levenberg-Marquardt on the
  block-tridiagonal least squares (analytic Jacobians in NumPy, a banded Cholesky per step, a convergence stop:
  tens of steps, see `_solve_fast_lm`). LM's solver is 1.8x (GRID, real video) to 20x (synthetic, no flow) faster
  and reaches a lower objective and keypoint error, but on the synthetic benchmark its curves are further from the
  truth (bench/tracking.py: guided L1 x 100 5.88 -> 6.58, top-2 87% -> 82%): Adam's 300 steps stop near the
  procedural start, LM goes to the objective's minimum, which the paper's weights put further from the truth. So
  Adam stays the default until the objective's weights are tuned.

Both keep the weights in [0, 1] by projection after every step by default (`box="projected"`); `box="soft"` is the
paper's L_range penalty with truncation at the end (see `TrackingConfig.box` for why it is not the default).

Pixel errors are measured as if the face were `reference_face_px` tall (brow to chin), so that the paper's loss
weights keep their balance whatever the video's size and framing: landmark and flow residuals are multiplied by
reference_face_px / (the median brow-to-chin height of the detected landmarks).
"""

import functools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import torch

from visemeflow.rig import VisemeRig, evaluate_rig
from visemeflow.render.camera import Intrinsics, project, right_jacobian, rotation_matrices
from visemeflow.tracking.config import TrackingConfig
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


@dataclass
class FlowTerm:
    """Optical-flow correspondences for L_flow: vertices tracked and how to get their displacements.

    `correspond(j, points)` gives (displacement (N, 2), valid (N,)) from frame j-1 to frame j for the pixel
    positions `points` (N, 2) in frame j-1; `correspond_back(j, points)` from frame j+1 to frame j.
    `correspond_all(points)`, where given, is `correspond` of every frame j >= 1 at once: points (T-1, N, 2) of
    frames 0..T-2 -> ((T-1, N, 2), (T-1, N)) (`FlowField.all_correspondences`).
    """

    vertex_ids: np.ndarray
    correspond: Callable[[int, np.ndarray], tuple[np.ndarray, np.ndarray]]
    correspond_back: Callable[[int, np.ndarray], tuple[np.ndarray, np.ndarray]]
    correspond_all: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None


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
    if t == 0:
        raise ValueError("no frames to track")
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
    return _Joined([problem], config).initial_pose()


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
    curves = np.clip(x.detach().cpu().numpy(), 0.0, 1.0).astype(np.float32)
    rotation, translation = rot.detach().cpu().numpy(), trans.detach().cpu().numpy()
    if not (np.isfinite(curves).all() and np.isfinite(rotation).all() and np.isfinite(translation).all()):
        raise FloatingPointError("the tracking objective diverged (non-finite weights or pose)")
    return TrackingResult(
        curves, rotation, translation, {k: v.astype(np.float32) for k, v in terms.items()},
        mouth_errors(problem, curves, rotation, translation), time.perf_counter() - started, iterations, extra or {},
    )


OnStep = Callable[[int, int], None]
"""`on_step(done, total)`: progress of a solve (iterations, or frames of the faithful schedule), for a caller that
reports it; it must be cheap (it is called at every step)."""


def solve_fast(problem: TrackingProblem, config: TrackingConfig = TrackingConfig(),
               on_step: OnStep | None = None) -> TrackingResult:
    """All frames as one batch on (T, 16) weights and (T, 6) poses: Levenberg-Marquardt (`fast_method="lm"`, not the
    default), or Adam with cosine decay (`"adam"`, the default; also used for box="soft" and for L_rgb,
    whose renderer has no Jacobian here)."""
    check_problem(problem)
    cfg = config.effective()
    if config.fast_method == "lm" and config.box == "projected" and not (cfg.w_rgb and problem.rgb is not None):
        return _solve_fast_lm(problem, config, on_step)
    return _solve_fast_adam(problem, config, on_step)


def _solve_fast_adam(problem: TrackingProblem, config: TrackingConfig, on_step: OnStep | None = None) -> TrackingResult:
    """Adam with cosine decay on all frames at once (50 + 200 steps)."""
    check_problem(problem)
    return _adam_joined([problem], config, on_step)[0]


def solve_fast_many(problems: Sequence[TrackingProblem], config: TrackingConfig = TrackingConfig(),
                    on_step: OnStep | None = None,
                    device: str | torch.device = "cpu") -> list[TrackingResult | FloatingPointError]:
    """`solve_fast` of several utterances in one run of the optimiser: their frames one after the other, no term
    linking two utterances.

    Why: an Adam step on one clip's tiny tensors costs mostly torch's per-operation overhead, so ten clips solved
    together cost far less than ten solves. The result equals solving each
    problem alone (to float rounding): the loss is a sum of per-frame terms, L_diff and L_flow are cut at the joins,
    and Adam's update is element-wise, so no clip's weights see another's gradient.

    One result per problem, in order; a problem whose objective diverges gets its FloatingPointError in its place
    (the others are then solved one by one, so one bad clip never costs the rest). Problems the joint path does not
    cover (Levenberg-Marquardt, L_rgb, rigs with different landmark sets) are solved one by one.
    `on_step(done, total)` hears the joint iterations (or each problem's in turn when solved one by one).
    `device`: where the joint Adam path runs (e.g. "cuda": a GPU runs the same few hundred steps on thousands of
    frames at once; the pose's PnP start and the flow's correspondences stay on the CPU). Problems solved one by
    one run on the CPU.
    """
    problems = list(problems)
    for problem in problems:
        check_problem(problem)
    cfg = config.effective()
    joint = (len(problems) > 1 and joins(config)
             and not any(cfg.w_rgb and p.rgb is not None for p in problems)
             and len({np.asarray(p.rig.landmark_ids).tobytes() for p in problems}) == 1)
    if joint:
        try:
            return list(_adam_joined(problems, config, on_step, torch.device(device)))
        except FloatingPointError:
            pass                        # find the clip: each on its own
    out: list[TrackingResult | FloatingPointError] = []
    for problem in problems:
        try:
            out.append(solve_fast(problem, config, on_step))
        except FloatingPointError as exc:
            out.append(exc)
    return out


def joins(config: TrackingConfig) -> bool:
    """Whether `solve_fast_many` solves problems under `config` together: the fast Adam path without L_rgb (the
    photo term renders each clip's frames; Levenberg-Marquardt solves each clip's banded system)."""
    return (config.solver == "fast" and not (config.use_rgb and config.w_rgb)
            and not (config.fast_method == "lm" and config.box == "projected"))


class _JoinedCamera:
    """The intrinsics of each frame of joined problems as (T, 1) tensors, for `project` (which reads only these)."""

    def __init__(self, cameras: list[Intrinsics], lengths: list[int], device: torch.device):
        def column(name: str) -> torch.Tensor:
            return torch.cat([torch.full((n, 1), float(getattr(c, name))) for c, n in zip(cameras, lengths)]
                             ).to(device)

        self.fx, self.fy, self.cx, self.cy = column("fx"), column("fy"), column("cx"), column("cy")


class _Joined:
    """Eq. 1 over the frames of several problems laid one after the other (frame k of the whole is frame k - start
    of its problem); each problem keeps its rig, camera, pixel scale and guidance, and nothing links two."""

    def __init__(self, problems: list[TrackingProblem], config: TrackingConfig,
                 device: torch.device = torch.device("cpu")):
        self.problems, self.device = problems, device
        self.objs = [_Objective(p, config) for p in problems]
        self.config = self.objs[0].config       # effective: guidance off zeroes w_sup and w_act
        self.lengths = [p.n_frames for p in problems]
        self.starts = np.concatenate([[0], np.cumsum(self.lengths)]).astype(int)
        self.n_frames = int(self.starts[-1])
        self.camera = problems[0].camera if len(problems) == 1 else _JoinedCamera(
            [p.camera for p in problems], self.lengths, device)
        self.scale = (self.objs[0].scale if len(problems) == 1 else
                      torch.cat([torch.full((n, 1, 1), o.scale) for o, n in zip(self.objs, self.lengths)]).to(device))
        self.ids = self.objs[0].ids
        self.target = self._cat(o.target for o in self.objs).to(device)
        self.valid = self._cat(o.valid for o in self.objs).to(device)
        self.beta = self.objs[0].beta.to(device)
        self.suppress = self._cat(o.suppress for o in self.objs).to(device)
        self.activate = self._cat(o.activate for o in self.objs).to(device)
        # L_diff and L_flow pairs (k, k+1) inside one problem: 1; across a join: 0
        pairs = np.ones(max(self.n_frames - 1, 0), np.float32)
        pairs[self.starts[1:-1] - 1] = 0.0
        self.inside = None if pairs.all() else torch.as_tensor(pairs, device=device)
        self.one_rig = all(p.rig is problems[0].rig for p in problems)

    def _cat(self, parts) -> torch.Tensor:
        parts = list(parts)
        return parts[0] if len(parts) == 1 else torch.cat(parts)

    def slices(self) -> list[slice]:
        return [slice(int(s), int(e)) for s, e in zip(self.starts[:-1], self.starts[1:])]

    def points(self, x: torch.Tensor, ids: list[np.ndarray] | np.ndarray) -> torch.Tensor:
        """Rig vertices `ids` (one array for all problems, or one per problem of equal length) for the weights x."""
        if isinstance(ids, np.ndarray) and self.one_rig:
            return evaluate_rig(self.problems[0].rig, x, ids)
        per = ids if isinstance(ids, list) else [ids] * len(self.problems)
        return torch.cat([evaluate_rig(p.rig, x[sl], i) for p, sl, i in zip(self.problems, self.slices(), per)])

    def frame_terms(self, x: torch.Tensor, rot: torch.Tensor, trans: torch.Tensor) -> dict[str, torch.Tensor]:
        """Per-frame terms that need no neighbour: landmarks, guidance, range; (T,) each."""
        proj = project(self.points(x, self.ids), rot, trans, self.camera) * self.scale
        terms = {"lmk": landmark_loss(proj, self.target * self.scale, self.valid, self.beta), "range": range_loss(x)}
        if self.config.w_sup or self.config.w_act:
            terms["sup"] = suppression_loss(x, self.suppress)
            terms["act"] = activation_loss(x, self.activate)
        return terms

    def diff(self, x: torch.Tensor) -> torch.Tensor:
        """L_diff of each pair (k, k+1), 0 across a join; (T - 1,)."""
        d = diff_loss(x[1:], x[:-1])
        return d if self.inside is None else d * self.inside

    def initial_pose(self, gradient: str = "analytic") -> tuple[torch.Tensor, torch.Tensor]:
        """Per-frame head pose fitted to the non-mouth landmarks with the procedural weights held fixed
        (`gradient`: "analytic", `_Gradient.pose_only`, or "autograd")."""
        config, has = self.config, _landmark_ids(self.problems[0].rig)[1]
        beta = landmark_beta(config)[torch.as_tensor(has)]
        beta = torch.where(beta > 0, torch.ones_like(beta), beta)
        beta[torch.as_tensor(np.flatnonzero(has) >= 48)] = 0.2  # the mouth moves: lean on the rigid points
        beta = beta.to(self.device)
        with torch.no_grad():
            points = self.points(torch.as_tensor(np.concatenate([p.procedural for p in self.problems]),
                                                 dtype=torch.float32, device=self.device), self.ids)
            points_cpu = points.cpu()
        rotations, translations = [], []
        for problem, obj, sl in zip(self.problems, self.objs, self.slices()):
            if problem.initial_rotation is not None and problem.initial_translation is not None:
                rotations.append(torch.as_tensor(problem.initial_rotation, dtype=torch.float32).clone())
                translations.append(torch.as_tensor(problem.initial_translation, dtype=torch.float32).clone())
            else:
                r, t = _pose_guess(points_cpu[sl], obj.target, obj.valid, problem.camera, np.flatnonzero(has))
                rotations.append(r)
                translations.append(t)
        rotation, translation = self._cat(rotations).to(self.device), self._cat(translations).to(self.device)
        rotation.requires_grad_(True)
        translation.requires_grad_(True)
        if config.pose_iterations and gradient == "analytic":
            written, planar = _Gradient(self), points.transpose(1, 2).contiguous()
            adam = _Adam([rotation, translation])            # torch.optim.Adam(lr=0.02)'s steps
            with torch.no_grad():
                for _ in range(config.pose_iterations):
                    _, g_rot, g_trans = written.pose_only(planar, beta, rotation, translation)
                    adam.step([g_rot, g_trans], [0.02, 0.02])
        elif config.pose_iterations:
            opt = torch.optim.Adam([rotation, translation], lr=0.02)
            target = self.target * self.scale
            for _ in range(config.pose_iterations):
                opt.zero_grad()
                projected = project(points, rotation, translation, self.camera) * self.scale
                loss = landmark_loss(projected, target, self.valid, beta).sum()
                loss.backward()
                opt.step()
        return rotation.detach(), translation.detach()


class _Workspace:
    """Arrays a solve's steps reuse, by name, so that a step allocates none of its (T, N) and (T, 3, N) arrays.

    Why: a step of the fast path allocated some 5 MB of temporaries (bench/end_to_end.py's talking heads: 334
    frames x 368 vertices) and freed them again, and depending on the heap's state the C allocator gave that memory
    back to the system at every step and had it faulted in anew at the next: on GRID's groups of 5 clips ~3,000
    page faults a step, half of its time."""

    def __init__(self) -> None:
        self.arrays: dict[str, torch.Tensor] = {}

    def __call__(self, name: str, shape: tuple[int, ...], like: torch.Tensor, dtype: torch.dtype | None = None
                 ) -> torch.Tensor:
        dtype = like.dtype if dtype is None else dtype
        out = self.arrays.get(name)
        if out is None or out.shape != shape or out.dtype != dtype or out.device != like.device:
            out = self.arrays[name] = torch.empty(shape, dtype=dtype, device=like.device)
        return out


def _empty(work: _Workspace | None, name: str, shape: tuple[int, ...], like: torch.Tensor,
           dtype: torch.dtype | None = None) -> torch.Tensor:
    """`work`'s array `name`, or a new one without a workspace."""
    if work is None:
        return torch.empty(shape, dtype=like.dtype if dtype is None else dtype, device=like.device)
    return work(name, shape, like, dtype)


class _Planar:
    """Rig vertices in planar layout for the written-out gradient: (T, 3, N), the x, y and z of N vertices each a
    contiguous row, so that the pose is one (3, 3) @ (3, N) product per frame and every element-wise step runs
    over contiguous memory (slicing the last axis of (T, N, 3) made each of them several times slower)."""

    def __init__(self, parts: list[tuple[VisemeRig, np.ndarray, slice]], device: torch.device):
        """`parts`: (rig, vertex ids, the frames it holds) for each run of frames sharing a rig."""
        from visemeflow.rig.model import rig_tensors

        self.parts, self.slices = [], [sl for _, _, sl in parts]
        for rig, ids, _ in parts:
            basis, offset = rig_tensors(rig, device).basis(np.asarray(ids, dtype=np.int64).reshape(-1))
            n = basis.shape[1] // 3
            self.parts.append((basis.reshape(N_VISEMES, n, 3).transpose(1, 2).reshape(N_VISEMES, 3 * n).contiguous(),
                               offset.reshape(n, 3).T.reshape(-1).contiguous()))
        self.n = self.parts[0][0].shape[1] // 3

    @classmethod
    def of(cls, joined: "_Joined", ids: list[np.ndarray] | np.ndarray) -> "_Planar":
        """The vertices `ids` (one array for all problems, or one per problem) of joined problems."""
        if isinstance(ids, np.ndarray) and joined.one_rig:
            return cls([(joined.problems[0].rig, ids, slice(0, joined.n_frames))], joined.device)
        per = ids if isinstance(ids, list) else [ids] * len(joined.problems)
        return cls([(p.rig, i, sl) for p, i, sl in zip(joined.problems, per, joined.slices())], joined.device)

    def points(self, x: torch.Tensor, work: _Workspace | None = None) -> torch.Tensor:
        """(T, 3, N) vertices for the weights x (T, 16); each run of frames written in its place (no torch.cat)."""
        out = _empty(work, "points", (len(x), 3 * self.n), x)
        for (basis, offset), sl in zip(self.parts, self.slices):
            torch.addmm(offset, x[sl], basis, out=out[sl])
        return out.view(-1, 3, self.n)

    def weights_gradient(self, g_points: torch.Tensor) -> torch.Tensor:
        """(T, 16) from the vertices' gradient (T, 3, N)."""
        flat = g_points.reshape(len(g_points), -1)
        if len(self.parts) == 1:
            return flat @ self.parts[0][0].T
        out = flat.new_empty(len(flat), N_VISEMES)
        for (basis, _), sl in zip(self.parts, self.slices):
            torch.mm(flat[sl], basis.T, out=out[sl])
        return out


# 3 x 3 matrices as rows of 9: [r]_x = r[_CROSS_INDEX] * _CROSS_SIGN, r r^T = r[_OUTER_ROWS] * r[_OUTER_COLS]
_CROSS_INDEX = np.array([0, 2, 1, 2, 0, 0, 1, 0, 0])
_CROSS_SIGN = np.array([0.0, -1.0, 1.0, 1.0, 0.0, -1.0, -1.0, 1.0, 0.0])
_OUTER_ROWS, _OUTER_COLS = np.repeat(np.arange(3), 3), np.tile(np.arange(3), 3)
_EYE9 = np.eye(3).reshape(9)


def _rotations(rotation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(`rotation_matrices`, `right_jacobian`) of the axis-angles (T, 3): on the CPU in NumPy (float64, rounded to
    float32: the same matrices to float rounding, within 3e-7), elsewhere by those functions.

    Why: both are some 60 torch operations on (T, 3) and (T, 3, 3) arrays, each paying torch's per-operation
    overhead (~8 us here): 0.5 ms of each fast-path step, against 0.05 ms in NumPy. R = I + a K + b K^2 and
    J = I - b K + c K^2 (K the cross-product matrix of r, t = |r|, K^2 = r r^T - t^2 I) with a = sin(t)/t,
    b = (1 - cos t)/t^2, c = (t - sin t)/t^3: their Taylor series below t^2 = 0.01 (the first term left out is
    below 1e-9 there), as `right_jacobian`."""
    if rotation.device.type != "cpu":
        return rotation_matrices(rotation), right_jacobian(rotation)
    r = rotation.detach().numpy().astype(np.float64)
    theta2 = np.einsum("ti,ti->t", r, r)
    small = theta2 < 1e-2
    t = np.sqrt(np.where(small, 1.0, theta2))
    sin, cos = np.sin(t), np.cos(t)
    t4 = theta2 * theta2
    a = np.where(small, 1.0 - theta2 / 6.0 + t4 / 120.0, sin / t)[:, None]
    b = np.where(small, 0.5 - theta2 / 24.0 + t4 / 720.0, (1.0 - cos) / (t * t))[:, None]
    c = np.where(small, 1.0 / 6.0 - theta2 / 120.0 + t4 / 5040.0, (t - sin) / (t * t * t))[:, None]
    k = r[:, _CROSS_INDEX] * _CROSS_SIGN                               # (T, 9): K row by row
    kk = r[:, _OUTER_ROWS] * r[:, _OUTER_COLS]                         # r r^T - t^2 I
    kk[:, ::4] -= theta2[:, None]
    rmat = (_EYE9 + a * k + b * kk).reshape(-1, 3, 3)
    jacobian = (_EYE9 - b * k + c * kk).reshape(-1, 3, 3)
    # C order: NumPy's fancy indexing above leaves (T, 9) in Fortran order, and torch.bmm on a (T, 3, 3) of other
    # strides falls back to one matrix product per frame (10x slower)
    return (torch.from_numpy(np.ascontiguousarray(rmat, np.float32)),
            torch.from_numpy(np.ascontiguousarray(jacobian, np.float32)))


class _Adam:
    """torch.optim.Adam's update (its defaults, as its single-tensor CPU path computes it: the same operations in the
    same order, so the same bits: tests/test_tracking.py) on tensors whose gradients `step` is handed, without the
    optimiser's bookkeeping (param groups, state, checks): 0.22 ms a step instead of 0.44 on the fast path's
    (334, 16) weights and (334, 3) poses, one pinned core."""

    def __init__(self, params: list[torch.Tensor], beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-8):
        self.params, self.beta1, self.beta2, self.eps = params, beta1, beta2, eps
        self.exp_avg = [torch.zeros_like(p) for p in params]
        self.exp_avg_sq = [torch.zeros_like(p) for p in params]
        self.steps = 0

    def step(self, grads: list[torch.Tensor], lrs: list[float]) -> None:
        self.steps += 1
        step, beta1, beta2 = float(self.steps), self.beta1, self.beta2
        bias_correction1 = 1 - beta1**step
        bias_correction2_sqrt = (1 - beta2**step) ** 0.5
        for param, grad, exp_avg, exp_avg_sq, lr in zip(self.params, grads, self.exp_avg, self.exp_avg_sq, lrs):
            exp_avg.lerp_(grad, 1 - beta1)
            exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
            denom = (exp_avg_sq.sqrt() / bias_correction2_sqrt).add_(self.eps)
            param.addcdiv_(exp_avg, denom, value=-(lr / bias_correction1))


class _Projection:
    """Planar vertices (T, 3, N) through the head pose to pixels u, v (T, N) each (`render.camera.project`'s
    arithmetic), keeping what the way back needs. `jacobian`: `right_jacobian(rotation)` where the caller has it
    (the fast path's step projects once per step and computes it once).

    The arithmetic is the same as written plainly (same operations in the same order, so the same bits), done in
    place into fewer temporaries: at 700x700 (334 frames x 368 vertices) the step's passes over (T, N) arrays and
    their allocations were most of its time."""

    def __init__(self, points: torch.Tensor, rotation: torch.Tensor, rmat: torch.Tensor, translation: torch.Tensor,
                 camera, jacobian: torch.Tensor | None = None, work: _Workspace | None = None):
        self.points, self.rotation, self.rmat, self.camera = points, rotation, rmat, camera
        self.jacobian, self.work = jacobian, work
        t, _, n = points.shape
        cam = torch.baddbmm(translation[:, :, None], rmat, points, out=_empty(work, "cam", (t, 3, n), points))
        depth = torch.neg(cam[:, 2], out=_empty(work, "inv", (t, n), points))
        # where `clamp_min` passes the gradient on: None where that is everywhere (the rule; NaN is not in front)
        self.in_front = None if depth.numel() == 0 or float(depth.min()) > 1e-6 else depth > 1e-6
        self.inv = depth.clamp_min_(1e-6).reciprocal_()
        self.x_over_z = torch.mul(cam[:, 0], self.inv, out=_empty(work, "x_over_z", (t, n), points))
        self.y_over_z = torch.mul(cam[:, 1], self.inv, out=_empty(work, "y_over_z", (t, n), points))
        # cx + fx x/z and cy - fy y/z, in place (the same operations: a + b = b + a, a - b = -b + a)
        self.u = torch.mul(self.x_over_z, camera.fx, out=_empty(work, "u", (t, n), points)).add_(camera.cx)
        self.v = torch.mul(self.y_over_z, camera.fy, out=_empty(work, "v", (t, n), points)).neg_().add_(camera.cy)

    def pull(self, g_u: torch.Tensor, g_v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(gradient of the vertices (T, 3, N), of the axis-angle rotation (T, 3), of the translation (T, 3)) for
        the pixels' gradients g_u, g_v (T, N). The rotation's: d(R(r) p)/dr = -R [p]_x J_r(r), so with g the
        vertices' gradient, dL/dr = J_r^T sum_n p_n x g_n. With a workspace, the vertices' gradient is its array,
        valid until the next pull."""
        work, (t, n) = self.work, g_u.shape
        fu = torch.mul(g_u, self.camera.fx, out=_empty(work, "fu", (t, n), g_u))
        fv = torch.mul(g_v, self.camera.fy, out=_empty(work, "fv", (t, n), g_u))
        g_cam = _empty(work, "g_cam", (t, 3, n), g_u)
        torch.mul(fu, self.inv, out=g_cam[:, 0])
        torch.mul(fv, self.inv, out=g_cam[:, 1]).neg_()
        g_z = torch.mul(fu, self.x_over_z, out=g_cam[:, 2]).sub_(fv.mul_(self.y_over_z)).mul_(self.inv)
        if self.in_front is not None:                                  # (fu x/z - fv y/z) / z, 0 behind
            g_z.masked_fill_(~self.in_front, 0.0)
        g_points = torch.bmm(self.rmat.transpose(1, 2), g_cam, out=_empty(work, "g_points", (t, 3, n), g_u))
        m = torch.bmm(g_points, self.points.transpose(1, 2))      # (T, 3, 3): m[a, b] = sum_n g_a p_b
        moment = (m - m.transpose(1, 2))[:, (2, 0, 1), (1, 2, 0)]   # m21 - m12, m02 - m20, m10 - m01
        jacobian = _rotations(self.rotation)[1] if self.jacobian is None else self.jacobian
        g_rot = torch.bmm(moment[:, None, :], jacobian)[:, 0]
        return g_points, g_rot, g_cam.sum(-1)


def _weights_of(c: TrackingConfig, beta: torch.Tensor, valid: torch.Tensor, suppress: torch.Tensor,
                activate: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Per frame and point, w_lmk times L_lmk's normalised weights (T, K); per frame and viseme, the factor g of
    w_sup L_sup + w_act L_act = sum g x^2 (T, 16), None without guidance."""
    weight = beta * valid.to(beta.dtype)
    lmk = c.w_lmk * weight / weight.sum(-1, keepdim=True).clamp_min(1e-12)
    if not (c.w_sup or c.w_act):
        return lmk, None
    sup, act = suppress.float(), activate.float()
    return lmk, (c.w_sup * sup / sup.sum(-1, keepdim=True).clamp_min(1.0)
                 - c.w_act * act / act.sum(-1, keepdim=True).clamp_min(1.0))


def _landmark_term(proj: _Projection, scale, target_u: torch.Tensor, target_v: torch.Tensor, weight: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(value, g_u, g_v) of w_lmk L_lmk: pixels times `scale` against the scaled targets (T, K) each, with the
    per-point weights `weight` (T, K) from `_weights_of`, zero where a landmark is missing."""
    res_u = proj.u * scale - target_u
    res_v = proj.v * scale - target_v
    twice = 2.0 * weight * scale
    return (weight * (res_u * res_u + res_v * res_v)).sum(), twice * res_u, twice * res_v


def _range_term(w_range: float, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(value, d/dx) of w_range L_range, or None where every weight lies in [0, 1] (both are then exactly 0: under
    the projected box, every step but the first)."""
    low, high = torch.aminmax(x)
    if float(low) >= 0.0 and float(high) <= 1.0:
        return None
    upper, lower = (x > 1).float(), (x < 0).float()
    n_up, n_low = upper.sum(-1, keepdim=True).clamp_min(1.0), lower.sum(-1, keepdim=True).clamp_min(1.0)
    return (w_range * ((upper * (x - 1) ** 2 / n_up).sum() + (lower * x * x / n_low).sum()),
            2.0 * w_range * (upper * (x - 1) / n_up + lower * x / n_low))


def _weight_terms(c: TrackingConfig, x: torch.Tensor, guide: torch.Tensor | None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """(value, d/dx) of the terms on the weights alone: guidance (`guide` from `_weights_of`) and w_range L_range."""
    value, gx = x.new_zeros(()), torch.zeros_like(x)
    if guide is not None:
        value, gx = (guide * x * x).sum(), 2.0 * guide * x
    ranged = _range_term(c.w_range, x) if c.w_range else None
    if ranged is not None:
        value, gx = value + ranged[0], gx + ranged[1]
    return value, gx


class _Gradient:
    """Eq. 1 of joined problems and its gradient written out (no autograd): the fast Adam path's step.

    The sum of the same per-frame terms as `_Joined.frame_terms`, `_Joined.diff` and `_FastFlow.loss`, weighted as
    `_Objective.weighted`, equal to autograd through them to float rounding (tests/test_tracking.py). Why: the
    autograd engine's bookkeeping was half of each of the solver's 250 small steps.

    The landmark and flow vertices go through the pose as one set (`_vertices`): one product with the rig's basis,
    one projection and one way back per step rather than two, each term writing its pixels' gradient into its
    columns of one (T, N) array (no torch.cat). Factors constant over a solve (the landmarks' 2 w scale, the
    guidance's 2 g) are made once, the flow's (its scaled displacements, masks and pair weights) once per refresh.
    This sums the landmark and flow parts of the pose's and weights' gradients in another order, and `_rotations`
    rounds otherwise: float rounding (the curves of bench/end_to_end.py's GRID and talking-heads groups within 4e-6
    of the separate passes). With `_rotations`, `_Adam` and `_Workspace`, on one pinned core: a step 1.6x cheaper
    on the talking heads (9.4 -> 5.9 ms), 1.8-3x on GRID's groups of 5 clips (whose steps also page-faulted);
    whole solves 7.7 -> 5.8 ms per frame (talking heads) and 8.0 -> 5.1 (GRID)."""

    def __init__(self, joined: _Joined):
        self.joined = joined
        c = joined.config
        self.c = c
        scale = joined.scale
        self.scale = scale if isinstance(scale, float) else scale[:, :, 0]              # (T, 1) or a float
        self.lmk_w, self.guide = _weights_of(c, joined.beta, joined.valid, joined.suppress, joined.activate)
        target = joined.target * joined.scale
        self.target_u, self.target_v = target[..., 0].contiguous(), target[..., 1].contiguous()
        self.twice = 2.0 * self.lmk_w * self.scale                    # `_landmark_term`'s factor on the residuals
        self.twice_guide = None if self.guide is None else 2.0 * self.guide
        self._sets: dict[object, _Planar] = {}        # by the flow (None: the landmarks alone)
        self._flow_of: tuple | None = None            # (the `_FastFlow.planar` it was made from, its factors)
        self._pose_weight: tuple | None = None        # (beta, `pose_only`'s normalised weights)
        self.work = _Workspace()

    def _vertices(self, flow: "_FastFlow | None") -> _Planar:
        """The landmark vertices, then (with `flow`) the flow's, as one planar set."""
        if flow not in self._sets:
            joined, ids = self.joined, self.joined.ids
            if flow is None:
                both = ids
            elif isinstance(flow.ids, np.ndarray):
                both = np.concatenate([ids, flow.ids])
            else:
                both = [np.concatenate([ids, i]) for i in flow.ids]
            self._sets[flow] = _Planar.of(joined, both)
        return self._sets[flow]

    def pose_only(self, planar: torch.Tensor, beta: torch.Tensor, rot: torch.Tensor, trans: torch.Tensor
                  ) -> tuple[float, torch.Tensor, torch.Tensor]:
        """The rigid start's objective (landmarks with weights `beta`, the vertices `planar` (T, 3, K) fixed) and
        its pose gradients."""
        if self._pose_weight is None or self._pose_weight[0] is not beta:
            weight = beta * self.joined.valid.to(beta.dtype)
            self._pose_weight = (beta, weight / weight.sum(-1, keepdim=True).clamp_min(1e-12))
        rmat, jacobian = _rotations(rot)
        proj = _Projection(planar, rot, rmat, trans, self.joined.camera, jacobian, self.work)
        value, g_u, g_v = _landmark_term(proj, self.scale, self.target_u, self.target_v, self._pose_weight[1])
        _, g_rot, g_trans = proj.pull(g_u, g_v)
        return float(value), g_rot, g_trans

    def __call__(self, x: torch.Tensor, rot: torch.Tensor, trans: torch.Tensor, flow: "_FastFlow | None"
                 ) -> tuple[float, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(objective, d/dx (T, 16), d/drot (T, 3), d/dtrans (T, 3))."""
        joined, c = self.joined, self.c
        vertices = self._vertices(flow)
        k = len(self.joined.ids)
        work = self.work
        rmat, jacobian = _rotations(rot)
        proj = _Projection(vertices.points(x, work), rot, rmat, trans, joined.camera, jacobian, work)
        u, v = proj.u.mul_(self.scale), proj.v.mul_(self.scale)      # all vertices' pixels, scaled, in place
        g_u, g_v = work("g_u", u.shape, u), work("g_v", u.shape, u)
        # w_lmk L_lmk (`_landmark_term`), its pixels' gradient into the first k columns
        res_u = u[:, :k] - self.target_u
        res_v = v[:, :k] - self.target_v
        torch.mul(self.twice, res_u, out=g_u[:, :k])
        torch.mul(self.twice, res_v, out=g_v[:, :k])
        value = float((self.lmk_w * (res_u * res_u + res_v * res_v)).sum())
        if flow is not None:
            value += self._flow(flow, u[:, k:], v[:, k:], g_u[:, k:], g_v[:, k:])
        g_points, g_rot, g_trans = proj.pull(g_u, g_v)
        w_value, w_gx = self._weight_terms(x)
        value, gx = value + w_value, vertices.weights_gradient(g_points)
        if w_gx is not None:
            gx.add_(w_gx)
        if joined.n_frames > 1 and c.w_diff:
            step = x[1:] - x[:-1]
            if joined.inside is not None:
                step = step * joined.inside[:, None]
            # every pair is in both of its frames' L_diff (as `_adam_joined` sums it)
            value += float(2.0 * c.w_diff * (step * step).sum() / N_VISEMES)
            g_step = 4.0 * c.w_diff * step / N_VISEMES
            gx[:-1].sub_(g_step)
            gx[1:].add_(g_step)
        return value, gx, g_rot, g_trans

    def _weight_terms(self, x: torch.Tensor) -> tuple[float, torch.Tensor | None]:
        """`_weight_terms` with the guidance's factor made once; None for a gradient of 0."""
        if self.guide is None:
            value, gx = 0.0, None
        else:
            value, gx = float((self.guide * x * x).sum()), self.twice_guide * x
        ranged = _range_term(self.c.w_range, x) if self.c.w_range else None
        if ranged is not None:
            value += float(ranged[0])
            gx = ranged[1] if gx is None else gx + ranged[1]
        return value, gx

    def _flow(self, flow: "_FastFlow", u, v, g_u, g_v) -> float:
        """w_flow times the sum of `_FastFlow.loss` for the flow vertices' scaled pixels u, v (T, F); their
        gradients written into g_u, g_v (T, F)."""
        planar = flow.planar()
        if self._flow_of is None or self._flow_of[0] is not planar:
            scale = self.scale
            next_scale = scale if isinstance(scale, float) else scale[1:]
            per_pair = self.c.w_flow / flow.valid.sum(-1, keepdim=True).clamp_min(1).to(u.dtype)  # (T - 1, 1)
            self._flow_of = (planar, planar[0] * next_scale, planar[1] * next_scale, flow.valid.to(u.dtype),
                             2.0 * per_pair)
        _, disp_u, disp_v, ok, twice = self._flow_of
        work, shape = self.work, ok.shape
        diff_u = torch.sub(u[1:], u[:-1], out=work("diff_u", shape, u)).sub_(disp_u).mul_(ok)
        diff_v = torch.sub(v[1:], v[:-1], out=work("diff_v", shape, u)).sub_(disp_v).mul_(ok)
        # d/d(u[k + 1]) of pair k's term; -that for u[k]
        pair_u = torch.mul(twice, diff_u, out=work("pair_u", shape, u))
        pair_v = torch.mul(twice, diff_v, out=work("pair_v", shape, u))
        value = 0.5 * float(torch.dot(pair_u.view(-1), diff_u.view(-1)) + torch.dot(pair_v.view(-1), diff_v.view(-1)))
        for pair, g in ((pair_u, g_u), (pair_v, g_v)):
            torch.sub(pair[:-1], pair[1:], out=g[1:-1])
            torch.neg(pair[0], out=g[0])
            g[-1] = pair[-1]
            g.mul_(self.scale)
        return value


def _adam_joined(problems: list[TrackingProblem], config: TrackingConfig, on_step: OnStep | None = None,
                 device: torch.device = torch.device("cpu"), gradient: str = "analytic") -> list[TrackingResult]:
    """Adam with cosine decay on all frames of `problems` at once (see `solve_fast_many`); `gradient`: "analytic"
    (`_Gradient`, the default) or "autograd" (through the loss terms: the reference it is tested against)."""
    if gradient not in ("analytic", "autograd"):
        raise ValueError(f"gradient must be analytic or autograd, got {gradient!r}")
    started = time.perf_counter()
    joined = _Joined(problems, config, device)
    cfg = joined.objs[0].config
    rot, trans = joined.initial_pose(gradient)
    x = torch.tensor(np.concatenate([p.procedural for p in problems]), dtype=torch.float32, device=device,
                     requires_grad=True)
    rot.requires_grad_(True)
    trans.requires_grad_(True)
    t = joined.n_frames
    base = [config.fast_lr, config.fast_lr * config.pose_lr_factor]       # of x; of the pose
    with_flow = [p.flow is not None and p.n_frames > 1 for p in problems]
    flow_state = _FastFlow(joined, with_flow) if cfg.w_flow and any(with_flow) else None
    rgb = problems[0].rgb if len(problems) == 1 and cfg.w_rgb else None
    total_iterations = config.fast_iterations + (config.rgb_iterations if rgb is not None else 0)
    written = _Gradient(joined) if gradient == "analytic" and rgb is None else None
    if written is not None:
        adam = _Adam([x, rot, trans])
        with torch.no_grad():
            for it in range(total_iterations):
                if on_step is not None:
                    on_step(it, total_iterations)
                lr_x, lr_pose = (lr * 0.5 * (1 + math.cos(math.pi * it / total_iterations)) for lr in base)
                if flow_state is not None and it % 50 == 0:
                    flow_state.refresh(x, rot, trans)
                value, g_x, g_rot, g_trans = written(x, rot, trans, flow_state)
                if not math.isfinite(value):
                    raise FloatingPointError(f"non-finite tracking loss at iteration {it}")
                adam.step([g_x, g_rot, g_trans], [lr_x, lr_pose, lr_pose])
                if config.box == "projected":
                    x.clamp_(0.0, 1.0)
    else:                               # autograd (the reference), and L_rgb's refinement
        opt = torch.optim.Adam([{"params": [x], "lr": base[0]}, {"params": [rot, trans], "lr": base[1]}])
        for it in range(total_iterations):
            if on_step is not None:
                on_step(it, total_iterations)
            for g, lr in zip(opt.param_groups, base):
                g["lr"] = lr * 0.5 * (1 + math.cos(math.pi * it / total_iterations))
            opt.zero_grad()
            terms = joined.frame_terms(x, rot, trans)
            if t > 1 and cfg.w_diff:
                d = joined.diff(x)
                terms["diff"] = torch.cat([d, d.new_zeros(1)]) + torch.cat([d.new_zeros(1), d])
            if flow_state is not None:
                if it % 50 == 0:
                    flow_state.refresh(x, rot, trans)
                terms["flow"] = flow_state.loss(x, rot, trans)
            if it >= config.fast_iterations and rgb is not None:
                if it == config.fast_iterations:
                    rgb.prepare(x.detach().cpu().numpy(), rot.detach().cpu().numpy(), trans.detach().cpu().numpy())
                terms["rgb"] = _rgb_all(problems[0], joined.objs[0], x, rot, trans)
            loss = joined.objs[0].weighted(terms).sum()
            if not torch.isfinite(loss):
                raise FloatingPointError(f"non-finite tracking loss at iteration {it}")
            loss.backward()
            opt.step()
            if config.box == "projected":
                with torch.no_grad():
                    x.clamp_(0.0, 1.0)
    with torch.no_grad():
        final = joined.frame_terms(x, rot, trans)
        if t > 1:
            final["diff"] = torch.cat([x.new_zeros(1), joined.diff(x)])
    seconds = time.perf_counter() - started
    results = []
    for problem, sl in zip(problems, joined.slices()):
        terms_np = {k: v[sl].detach().cpu().numpy() for k, v in final.items()
                    if k != "diff" or problem.n_frames > 1}
        result = _finish(problem, x[sl], rot[sl], trans[sl], terms_np, started, total_iterations,
                         {"joined": len(problems)} if len(problems) > 1 else None)
        result.seconds = seconds * problem.n_frames / max(t, 1)   # its share of the joint solve
        results.append(result)
    return results


# ---- fast solver, Levenberg-Marquardt -----------------------------------------------------------------------------
#
# Why: the objective of the fast solver is a small least-squares problem (22 unknowns per frame) whose only couplings
# are between neighbouring frames (L_diff, L_flow), so its Gauss-Newton matrix is block tridiagonal. Adam needed 500
# steps of an autograd graph of tiny tensors, each one costing the same ~4 ms whatever the number of frames (the
# engine's per-op overhead); Levenberg-Marquardt with the Jacobian written out in NumPy converges in tens of steps,
# each a few batched einsums and one banded Cholesky solve. The objective is the same as the Adam path's, term by
# term (L_diff counted for both frames of a pair, as there), with the box [0, 1] kept by a projected step whose
# bound-held weights are removed from the system (projected Newton); the concave L_act enters the gradient but not
# the matrix (its curvature is negative), which keeps the matrix positive definite and the step a descent direction.

_NP = 22  # unknowns per frame: 16 weights, 3 rotation (a local increment), 3 translation


def _rodrigues(r: np.ndarray) -> np.ndarray:
    """(T, 3) axis-angle -> (T, 3, 3) rotation matrices (closed form, the Taylor series near zero)."""
    theta2 = (r * r).sum(axis=1)
    theta = np.sqrt(theta2)
    small = theta2 < 1e-12
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    k = _skew(r)
    return np.eye(3) + a[:, None, None] * k + b[:, None, None] * (k @ k)


def _log_rotation(m: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rotation matrices -> (T, 3) axis-angle (angles below pi; head poses are far from it)."""
    cos = np.clip((np.trace(m, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    vee = np.stack([m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]], axis=1)
    sin = np.sin(theta)
    small = theta < 1e-6
    factor = np.where(small, 0.5 + theta * theta / 12.0, theta / (2.0 * np.where(small, 1.0, sin)))
    return vee * factor[:, None]


def _skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices [v]_x."""
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1), np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


class _Points:
    """A subset of rig vertices as NumPy (float64): neutral (K, 3) and delta basis (16, K, 3)."""

    def __init__(self, rig: VisemeRig, ids: np.ndarray):
        from visemeflow.rig.model import rig_tensors

        basis, offset = rig_tensors(rig, torch.device("cpu")).basis(np.asarray(ids, dtype=np.int64).reshape(-1))
        self.flat = basis.double().numpy()                                   # (16, 3K)
        self.basis = self.flat.reshape(N_VISEMES, -1, 3)
        self.per_point = np.ascontiguousarray(self.basis.transpose(1, 2, 0))  # (K, 3, 16)
        self.offset = offset.double().numpy().reshape(-1, 3)

    def project(self, x: np.ndarray, rot: np.ndarray, trans: np.ndarray, cam: Intrinsics, jacobian: bool = True):
        """Pixels (T, K, 2) of the points for weights x (T, 16) and poses, and with `jacobian` their derivatives
        (T, K, 2, 22) w.r.t. (x, a right-multiplied rotation increment, translation)."""
        mesh = self.offset[None] + (x @ self.flat).reshape(len(x), -1, 3)
        rmat = _rodrigues(rot)
        cam_pts = mesh @ rmat.transpose(0, 2, 1) + trans[:, None, :]
        depth = np.maximum(-cam_pts[..., 2], 1e-6)
        inv = 1.0 / depth
        u = cam.cx + cam.fx * cam_pts[..., 0] * inv
        v = cam.cy - cam.fy * cam_pts[..., 1] * inv
        pix = np.stack([u, v], axis=-1)
        if not jacobian:
            return pix, None
        d = np.zeros(cam_pts.shape[:-1] + (2, 3))
        d[..., 0, 0] = cam.fx * inv
        d[..., 0, 2] = cam.fx * cam_pts[..., 0] * inv * inv
        d[..., 1, 1] = -cam.fy * inv
        d[..., 1, 2] = -cam.fy * cam_pts[..., 1] * inv * inv
        t, k = d.shape[:2]
        # pixels per mesh-space offset (T, K, 2, 3), then per weight (T, K, 2, 16): matmuls batched so that each
        # multiplies large matrices (one per frame, then one per point), not a 2x3 by 3x3 per point and frame
        d_cam = (d.reshape(t, 2 * k, 3) @ rmat).reshape(t, k, 2, 3)
        d_x = (d_cam.transpose(1, 0, 2, 3).reshape(k, 2 * t, 3) @ self.per_point).reshape(k, t, 2, -1)
        d_x = d_x.transpose(1, 0, 2, 3)
        # right increment: d(R exp(w) p)/dw = -R [p]_x, and for a row g of d_cam, -g [p]_x = p x g
        d_rot = np.cross(mesh[:, :, None, :], d_cam)
        return pix, np.concatenate([d_x, d_rot, d], axis=-1)


class _LeastSquares:
    """The fast solver's objective as weighted residuals with their Jacobians, for Levenberg-Marquardt."""

    def __init__(self, obj: _Objective, problem: TrackingProblem, beta: torch.Tensor, guidance: bool,
                 w_lmk: float | None = None):
        c = obj.config
        self.problem, self.cam, self.scale = problem, problem.camera, obj.scale
        beta_np = beta.double().numpy()
        keep = beta_np > 0                                   # weightless points (the jaw) cost nothing
        self.lmk = _Points(problem.rig, obj.ids[keep])
        self.target = obj.target.double().numpy()[:, keep]
        valid = obj.valid.numpy()[:, keep]
        weight = beta_np[keep][None] * valid
        self.lmk_w = (c.w_lmk if w_lmk is None else w_lmk) * weight / np.maximum(weight.sum(axis=1, keepdims=True), 1e-12)   # (T, K)
        t = problem.n_frames
        if guidance and (c.w_sup or c.w_act):
            sup, act = obj.suppress.numpy(), obj.activate.numpy()
            self.sup_w = c.w_sup * sup / np.maximum(sup.sum(axis=1, keepdims=True), 1)
            self.act_w = c.w_act * act / np.maximum(act.sum(axis=1, keepdims=True), 1)
        else:
            self.sup_w = self.act_w = np.zeros((t, N_VISEMES))
        self.diff_w = 2.0 * c.w_diff / N_VISEMES if t > 1 else 0.0   # each pair is in both frames' L_diff
        self.flow = _Points(problem.rig, obj.flow_ids) if (
            c.w_flow and problem.flow is not None and t > 1) else None
        self.w_flow = c.w_flow
        self.disp = self.flow_w = None

    def refresh_flow(self, x: np.ndarray, rot: np.ndarray, trans: np.ndarray) -> None:
        """Correspondences from frame j-1's current projections, as `_FastFlow.refresh` makes them."""
        proj, _ = self.flow.project(x, rot, trans, self.cam, jacobian=False)
        proj = proj.astype(np.float32).astype(np.float64)
        flow = self.problem.flow
        if flow.correspond_all is not None:
            d, ok = flow.correspond_all(proj[:-1])
            self.disp = np.where(ok[..., None], d, 0.0).astype(np.float64)
            ok = ok.astype(np.float64)
        else:
            disp, valid = [], []
            for j in range(1, self.problem.n_frames):
                d, ok = flow.correspond(j, proj[j - 1])
                disp.append(np.where(ok[:, None], d, 0.0))
                valid.append(ok)
            self.disp = np.stack(disp).astype(np.float64)
            ok = np.stack(valid).astype(np.float64)
        self.flow_w = self.w_flow * ok / np.maximum(ok.sum(axis=1, keepdims=True), 1)      # (T-1, N)

    def value(self, x: np.ndarray, rot: np.ndarray, trans: np.ndarray) -> float:
        return self._evaluate(x, rot, trans, False)[0]

    def _evaluate(self, x, rot, trans, jacobian: bool):
        s = self.scale
        pix, jac = self.lmk.project(x, rot, trans, self.cam, jacobian)
        res = (pix - self.target) * s
        total = float((self.lmk_w * (res * res).sum(-1)).sum())
        total += float((self.sup_w * x * x).sum() - (self.act_w * x * x).sum())
        if self.diff_w:
            step = x[1:] - x[:-1]
            total += self.diff_w * float((step * step).sum())
        fpix = fjac = None
        if self.flow is not None:
            fpix, fjac = self.flow.project(x, rot, trans, self.cam, jacobian)
            fres = (fpix[1:] - fpix[:-1] - self.disp) * s
            total += float((self.flow_w * (fres * fres).sum(-1)).sum())
        if not jacobian:
            return total, None, None, None
        t = len(x)
        # Gauss-Newton matrix (halved: F = sum r^2, H = J^T J, g = J^T r) as diagonal and sub-diagonal blocks
        jw = (jac * (s * np.sqrt(self.lmk_w))[..., None, None]).reshape(t, -1, _NP)
        diag = np.einsum("tki,tkj->tij", jw, jw, optimize=True)
        grad = (jw.transpose(0, 2, 1) @ (res * np.sqrt(self.lmk_w)[..., None]).reshape(t, -1, 1))[..., 0]
        idx = np.arange(N_VISEMES)
        diag[:, idx, idx] += self.sup_w
        grad[:, :N_VISEMES] += (self.sup_w - self.act_w) * x
        off = np.zeros((t, _NP, _NP))                        # off[j]: rows of frame j-1, columns of frame j
        if self.diff_w:
            diag[1:, idx, idx] += self.diff_w
            diag[:-1, idx, idx] += self.diff_w
            off[1:, idx, idx] -= self.diff_w
            grad[1:, :N_VISEMES] += self.diff_w * step
            grad[:-1, :N_VISEMES] -= self.diff_w * step
        if self.flow is not None:
            root = np.sqrt(self.flow_w)[..., None]
            cur = (fjac[1:] * (s * root)[..., None]).reshape(t - 1, -1, _NP)
            prev = (fjac[:-1] * (s * root)[..., None]).reshape(t - 1, -1, _NP)
            r = (fres * root).reshape(t - 1, -1, 1)
            # einsum's BLAS path: a batched matmul of transposed views runs several times slower here
            diag[1:] += np.einsum("tki,tkj->tij", cur, cur, optimize=True)
            diag[:-1] += np.einsum("tki,tkj->tij", prev, prev, optimize=True)
            off[1:] -= np.einsum("tki,tkj->tij", prev, cur, optimize=True)
            grad[1:] += np.einsum("tki,tk->ti", cur, r[..., 0], optimize=True)
            grad[:-1] -= np.einsum("tki,tk->ti", prev, r[..., 0], optimize=True)
        return total, grad, diag, off


@functools.lru_cache(maxsize=8)
def _band_index(t: int):
    """Where the upper triangles of the diagonal blocks and the sub-diagonal blocks go in LAPACK's upper band
    storage (ab[u + i - j, j] = A[i, j]) for t frames."""
    u = 2 * _NP - 1
    a, b = np.triu_indices(_NP)
    frames = np.arange(t)[:, None]
    diagonal = ((u + a - b)[None].repeat(t, 0), frames * _NP + b[None], a, b)
    a2, b2 = (m.reshape(-1) for m in np.meshgrid(np.arange(_NP), np.arange(_NP), indexing="ij"))
    frames = np.arange(1, t)[:, None]
    sub = ((u + a2 - _NP - b2)[None].repeat(t - 1, 0), frames * _NP + b2[None], a2, b2)
    return diagonal, sub


def _banded_solve(diag: np.ndarray, off: np.ndarray, rhs: np.ndarray) -> np.ndarray | None:
    """Solve the symmetric block-tridiagonal system (blocks _NP x _NP) by a banded Cholesky; None if not PD."""
    from scipy.linalg import solveh_banded

    t = len(diag)
    u = 2 * _NP - 1
    ab = np.zeros((u + 1, t * _NP))
    (rows, cols, a, b), (rows2, cols2, a2, b2) = _band_index(t)
    ab[rows, cols] = diag[:, a, b]
    if t > 1:
        ab[rows2, cols2] = off[1:, a2, b2]
    try:
        return solveh_banded(ab, rhs.reshape(-1), check_finite=False).reshape(t, _NP)
    except np.linalg.LinAlgError:
        return None


def _levenberg_marquardt(ls: _LeastSquares, x, rot, trans, iterations: int, free_weights: bool,
                         tol: float = 1e-5) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Projected Levenberg-Marquardt on (x, pose); weights held at a bound by the gradient leave the system."""
    lam = 1e-3
    value, grad, diag, off = ls._evaluate(x, rot, trans, True)
    steps = 0
    for _ in range(iterations):
        steps += 1
        fixed = np.zeros((len(x), _NP), dtype=bool)
        if free_weights:
            g = grad[:, :N_VISEMES]
            fixed[:, :N_VISEMES] = ((x <= 0.0) & (g > 0)) | ((x >= 1.0) & (g < 0))
        else:
            fixed[:, :N_VISEMES] = True
        accepted = False
        while lam < 1e10:
            d = diag.copy()
            k = np.arange(_NP)
            d[:, k, k] += lam * (np.diagonal(diag, axis1=1, axis2=2) + 1e-6)
            o = off.copy()
            o[fixed[:, None, :].repeat(_NP, 1)] = 0.0                          # columns: frame j
            o[np.roll(fixed, 1, axis=0)[:, :, None].repeat(_NP, 2)] = 0.0      # rows: frame j-1
            d[fixed[:, :, None] | fixed[:, None, :]] = 0.0
            tt, kk = np.nonzero(fixed)
            d[tt, kk, kk] = 1.0
            delta = _banded_solve(d, o, -np.where(fixed, 0.0, grad))
            if delta is None:
                lam *= 10.0
                continue
            x_new = np.clip(x + delta[:, :N_VISEMES], 0.0, 1.0) if free_weights else x
            rot_new = _log_rotation(_rodrigues(rot) @ _rodrigues(delta[:, 16:19]))
            trans_new = trans + delta[:, 19:]
            new = ls.value(x_new, rot_new, trans_new)
            if new < value:
                accepted = True
                break
            lam *= 4.0
        if not accepted:
            break
        x, rot, trans = x_new, rot_new, trans_new
        lam = max(lam / 3.0, 1e-7)
        decrease = (value - new) / max(abs(value), 1e-12)
        value, grad, diag, off = ls._evaluate(x, rot, trans, True)
        if decrease < tol:
            break
    return x, rot, trans, steps


def _solve_fast_lm(problem: TrackingProblem, config: TrackingConfig, on_step: OnStep | None = None) -> TrackingResult:
    started = time.perf_counter()
    obj = _Objective(problem, config)
    t = problem.n_frames
    # rigid start: PnP, then the pose alone on the landmarks with the mouth down-weighted (as `initial_pose`)
    ids, has = _landmark_ids(problem.rig)
    with torch.no_grad():
        points = evaluate_rig(problem.rig, torch.as_tensor(problem.procedural, dtype=torch.float32), ids)
    if problem.initial_rotation is not None and problem.initial_translation is not None:
        rot0, trans0 = problem.initial_rotation, problem.initial_translation
    else:
        rot0, trans0 = _pose_guess(points, obj.target, obj.valid, problem.camera, np.flatnonzero(has))
        rot0, trans0 = rot0.numpy(), trans0.numpy()
    rot, trans = np.asarray(rot0, np.float64), np.asarray(trans0, np.float64)
    x = np.clip(np.asarray(problem.procedural, np.float64), 0.0, 1.0)
    pose_beta = landmark_beta(config)[torch.as_tensor(has)]
    pose_beta = torch.where(pose_beta > 0, torch.ones_like(pose_beta), pose_beta)
    pose_beta[torch.as_tensor(np.flatnonzero(has) >= 48)] = 0.2
    used = 0
    if config.pose_iterations:
        rigid = _LeastSquares(obj, problem, pose_beta, guidance=False, w_lmk=1.0)
        rigid.sup_w = rigid.act_w = np.zeros_like(rigid.sup_w)
        rigid.diff_w, rigid.flow = 0.0, None
        x_fixed = np.asarray(problem.procedural, np.float64)
        _, rot, trans, n = _levenberg_marquardt(rigid, x_fixed, rot, trans, config.lm_pose_iterations, False)
        used += n
    ls = _LeastSquares(obj, problem, obj.beta, guidance=True)
    rounds = config.lm_flow_rounds if ls.flow is not None else 1
    for done in range(rounds):
        if on_step is not None:
            on_step(done, rounds)
        if ls.flow is not None:
            ls.refresh_flow(x, rot, trans)
        x, rot, trans, n = _levenberg_marquardt(ls, x, rot, trans, config.lm_iterations, True)
        used += n
    xt = torch.as_tensor(x, dtype=torch.float32)
    rt, tt = torch.as_tensor(rot, dtype=torch.float32), torch.as_tensor(trans, dtype=torch.float32)
    with torch.no_grad():
        final = obj.frame_terms(slice(0, t), xt, rt, tt)
        if t > 1:
            final["diff"] = torch.cat([xt.new_zeros(1), diff_loss(xt[1:], xt[:-1])])
    terms_np = {k: v.numpy() for k, v in final.items()}
    return _finish(problem, xt, rt, tt, terms_np, started, used, {"method": "lm"})


def _rgb_all(problem, obj, x, rot, trans) -> torch.Tensor:
    # only the vertices the photo term renders, split once: per-frame indexing of one (T, V, 3) tensor would
    # make every frame's backward pass touch all T frames
    vertices = evaluate_rig(problem.rig, x, problem.rgb.vertex_ids).unbind(0)
    rots, transes = rot.unbind(0), trans.unbind(0)
    return torch.stack([problem.rgb.loss(j, vertices[j], rots[j], transes[j]) for j in range(problem.n_frames)])


class _FastFlow:
    """L_flow over all neighbouring pairs of joined problems, with correspondences refreshed from the current
    estimate; pairs across a join, and of problems without flow, carry none. Each problem follows its own flow
    vertices, padded to the longest list (padding is never valid)."""

    def __init__(self, joined: _Joined, with_flow: list[bool]):
        self.joined, self.with_flow = joined, with_flow
        lists = [np.asarray(p.flow.vertex_ids) if on else np.zeros(0, np.int64)
                 for p, on in zip(joined.problems, with_flow)]
        self.n_ids = [len(i) for i in lists]
        width = max(self.n_ids)
        self.ids = [np.concatenate([i, np.zeros(width - len(i), np.int64)]).astype(np.int64) for i in lists]
        if joined.one_rig and all(np.array_equal(i, self.ids[0]) for i in self.ids):
            self.ids = self.ids[0]
        self.disp = self.valid = self._planar = None

    def _project(self, x, rot, trans):
        return project(self.joined.points(x, self.ids), rot, trans, self.joined.camera)

    def refresh(self, x, rot, trans) -> None:
        with torch.no_grad():
            proj = self._project(x, rot, trans).cpu().numpy()
        t, width = self.joined.n_frames, proj.shape[1]
        disp = np.zeros((t - 1, width, 2), np.float32)
        valid = np.zeros((t - 1, width), bool)
        for problem, sl, on, n in zip(self.joined.problems, self.joined.slices(), self.with_flow, self.n_ids):
            if not on:
                continue
            if problem.flow.correspond_all is not None:   # pairs (k, k + 1) of the whole for k in the problem
                disp[sl.start:sl.stop - 1, :n], valid[sl.start:sl.stop - 1, :n] = problem.flow.correspond_all(
                    proj[sl.start:sl.stop - 1, :n])
                continue
            for j in range(1, problem.n_frames):
                k = sl.start + j - 1            # the pair (k, k + 1) of the whole
                disp[k, :n], valid[k, :n] = problem.flow.correspond(j, proj[k, :n])
        self.disp = torch.as_tensor(disp, device=self.joined.device)
        self.valid = torch.as_tensor(valid, device=self.joined.device)
        self._planar = None

    def planar(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The displacements' u and v (T - 1, N), each contiguous and 0 where not valid (a correspondence may
        hold NaN there), for `_Gradient`; made once per refresh."""
        if self._planar is None:
            disp = torch.where(self.valid[..., None], self.disp, torch.zeros_like(self.disp))
            self._planar = (disp[..., 0].contiguous(), disp[..., 1].contiguous())
        return self._planar

    def loss(self, x, rot, trans) -> torch.Tensor:
        scale = self.joined.scale
        proj = self._project(x, rot, trans) * scale
        pair = flow_loss(proj[1:], proj[:-1], self.disp * (scale if isinstance(scale, float) else scale[1:]),
                         self.valid)
        return torch.cat([pair.new_zeros(1), pair])


def solve_faithful(problem: TrackingProblem, config: TrackingConfig = TrackingConfig(),
                   on_step: OnStep | None = None, gradient: str = "analytic") -> TrackingResult:
    """The paper's schedule: per frame, Adam (lr 0.1, x0.9 every 10 iterations), forward then backward pass.
    `gradient`: "analytic" (`_FrameGradient`; with L_rgb autograd) or "autograd" (the reference)."""
    if gradient not in ("analytic", "autograd"):
        raise ValueError(f"gradient must be analytic or autograd, got {gradient!r}")
    check_problem(problem)
    started = time.perf_counter()
    obj = _Objective(problem, config)
    written = (_FrameGradient(problem, obj)
               if gradient == "analytic" and not (obj.config.w_rgb and problem.rgb is not None) else None)
    rot0, trans0 = initial_pose(problem, config)
    t = problem.n_frames
    x_all = torch.tensor(problem.procedural, dtype=torch.float32)
    rot_all, trans_all = rot0.clone(), trans0.clone()
    if obj.config.w_rgb and problem.rgb is not None:
        problem.rgb.prepare(x_all.numpy(), rot_all.numpy(), trans_all.numpy())
    terms_all: dict[str, np.ndarray] = {}
    solved = 0
    for direction in config.passes:
        order = range(t) if direction == "forward" else range(t - 1, -1, -1)
        prev_j = None
        for j in order:
            if on_step is not None:
                on_step(solved, t * len(config.passes))
            solved += 1
            frame_terms = _solve_frame(problem, obj, config, j, prev_j, x_all, rot_all, trans_all, direction,
                                       written)
            for k, v in frame_terms.items():
                terms_all.setdefault(k, np.zeros(t, np.float32))[j] = v
            prev_j = j
    return _finish(problem, x_all, rot_all, trans_all, terms_all, started, config.iterations * t * len(config.passes))


class _FrameGradient:
    """`_frame_objective` of one frame without L_rgb, weighted and summed, and its gradient written out (no
    autograd): the faithful solver's 250 steps per frame, each on one frame's tiny tensors, were all autograd
    bookkeeping. Equal to autograd through `_frame_objective` to float rounding (tests/test_tracking.py)."""

    def __init__(self, problem: TrackingProblem, obj: _Objective):
        self.problem, self.obj, c = problem, obj, obj.config
        self.c = c
        self.landmarks = _Planar([(problem.rig, obj.ids, slice(0, 1))], torch.device("cpu"))
        self.flow_points = None if obj.flow_ids is None else _Planar(
            [(problem.rig, obj.flow_ids, slice(0, 1))], torch.device("cpu"))
        self.lmk_w, self.guide = _weights_of(c, obj.beta, obj.valid, obj.suppress, obj.activate)
        target = obj.target * obj.scale
        self.target_u, self.target_v = target[..., 0].contiguous(), target[..., 1].contiguous()

    def __call__(self, j: int, x, rot, trans, prev_x, flow) -> tuple[float, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(objective, d/dx (1, 16), d/drot (1, 3), d/dtrans (1, 3)) of frame j; `prev_x` and `flow` as
        `_frame_objective` takes them (the neighbour held fixed)."""
        c, s, camera = self.c, self.obj.scale, self.problem.camera
        rmat = rotation_matrices(rot)
        proj = _Projection(self.landmarks.points(x), rot, rmat, trans, camera)
        value, g_u, g_v = _landmark_term(proj, s, self.target_u[j:j + 1], self.target_v[j:j + 1],
                                         self.lmk_w[j:j + 1])
        g_points, g_rot, g_trans = proj.pull(g_u, g_v)
        w_value, w_gx = _weight_terms(c, x, None if self.guide is None else self.guide[j:j + 1])
        value, gx = value + w_value, self.landmarks.weights_gradient(g_points) + w_gx
        if prev_x is not None and c.w_diff:
            step = x - prev_x
            value = value + c.w_diff * (step * step).sum() / N_VISEMES
            gx = gx + 2.0 * c.w_diff * step / N_VISEMES
        if flow is not None and c.w_flow:
            prev_proj, disp, valid = flow                     # (1, N, 2) each, (1, N)
            fproj = _Projection(self.flow_points.points(x), rot, rmat, trans, camera)
            ok = valid.to(fproj.u.dtype)
            du = torch.nan_to_num(disp[..., 0]) * ok
            dv = torch.nan_to_num(disp[..., 1]) * ok
            diff_u = (fproj.u - prev_proj[..., 0] - du) * s * ok
            diff_v = (fproj.v - prev_proj[..., 1] - dv) * s * ok
            per = c.w_flow / valid.sum(-1, keepdim=True).clamp_min(1).to(diff_u.dtype)
            value = value + (per * (diff_u * diff_u + diff_v * diff_v)).sum()
            f_points, f_rot, f_trans = fproj.pull(2.0 * per * diff_u * s, 2.0 * per * diff_v * s)
            gx, g_rot, g_trans = gx + self.flow_points.weights_gradient(f_points), g_rot + f_rot, g_trans + f_trans
        return float(value), gx, g_rot, g_trans


def _solve_frame(problem, obj, config, j, prev_j, x_all, rot_all, trans_all, direction,
                 written: _FrameGradient | None = None) -> dict[str, float]:
    """Optimise frame j in place (x_all, rot_all, trans_all hold the current solution of every frame); `written`:
    the frame's gradient written out (without L_rgb), else autograd."""
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
        if written is not None:
            with torch.no_grad():
                value, x.grad, rot.grad, trans.grad = written(j, x, rot, trans, prev_x, flow)
            if not math.isfinite(value):
                raise FloatingPointError(f"non-finite tracking loss at frame {j}")
        else:
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
