"""Bones from blendshapes (paper 6.2): SSDR bone poses, one per viseme, blended per frame by the 16 curves.

SSDR (smooth skinning decomposition with rigid bones, Le and Deng 2012) through `py_dem_bones` (bindings of
Electronic Arts' Dem Bones): the frames are the neutral followed by the 16 viseme meshes (the character's own
shapes as its binding drives them from a one-hot curve), the rest pose is the neutral, so the neutral is a solved
frame (Dem Bones returns identity transforms for it) and the bind pose is the neutral mesh itself. Dem Bones returns
per-vertex weights (convex, at most `max_influences` = 4 non-zero: one glTF JOINTS_0/WEIGHTS_0 set) and one rigid
transform M[f, b] (rotation R, translation t, skin space) per frame and bone, with v_f = sum_b w_vb M[f, b] u_v.

Bones: SSDR gives no bone positions, only transforms. Bone b's bind matrix is a translation to the weighted
centroid c_b of the vertices it moves (bind rotation identity), so a rotation pivots about the part of the face it
moves; all bones are children of one root joint at the origin (a flat skeleton: SSDR transforms are independent).
Pose of bone b for viseme s, relative to the bind pose: rotation q_sb = quat(R), translation d_sb = R c_b + t - c_b
(the joint's local translation is c_b + d_sb); the skinning matrix of that pose is then exactly M[s, b].

Blend (per frame, curves c in [0, 1], one weight per viseme pose), what every export carries:
- translation: c_b + sum_s c_s d_sb (linear, additive about the bind pose);
- rotation: normalise(q_I + sum_s c_s (q_sb - q_I)), q_I the identity, every q_sb on the hemisphere of q_I
  (w >= 0): normalised weighted quaternion blending about the bind pose, i.e. the identity takes the weight
  1 - sum c; a one-hot curve gives the viseme's pose exactly, all-zero curves the bind pose;
- scale: SSDR bones are rigid, every pose has unit scale, so the blended scale is 1 (no scale channel is written);
- then linear blend skinning: v = sum_k w_vk (R_jk (u_v - c_jk) + c_jk + d_jk), at most 4 influences per vertex.
docs/bones.md says how this relates to Unreal's Pose Assets and Unity's Direct Blend Trees.

Quaternions here are (w, x, y, z) (kornia's order); the writers convert (glTF: x, y, z, w; USD: real, imaginary).
Pure numpy / torch / kornia: arrays in, arrays out (torch and kornia imported where they run, so a module that
only names the bone formats loads neither).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from visemeflow.rig.character import Character, validate_character
from visemeflow.visemes import VISEMES

__all__ = ["BoneError", "BoneRig", "blend_poses", "bone_animation", "check_curves", "lip_emphasis", "locked_parts", "mbp_gap_mm",
           "refine_for_lips",
           "skin_vertices", "solve_bones", "viseme_meshes", "MAX_INFLUENCES", "MIN_VERTICES_PER_BONE"]

MAX_INFLUENCES = 4
"""Influences per vertex: one glTF JOINTS_0 / WEIGHTS_0 set (and what most engines skin with by default)."""
MIN_VERTICES_PER_BONE = 3
"""A rigid transform needs three non-collinear points: SSDR cannot determine a bone that moves fewer."""
DEFAULT_BONES = 32
DEFAULT_ITERATIONS = 5
DEFAULT_INIT_ITERATIONS = 20
"""Dem Bones' bone-initialisation iterations (its own default is 10). On the demo rig at 64 bones without locked parts,
10 / 20 / 30 / 40 gave lips errors of 0.512 / 0.492 / 0.485 / 0.529 mm RMS at about the same CPU time
(bench/bones.py --no-lock --init-iterations N): the clustering lands differently each time, so the figure moves by
a few hundredths of a millimetre either way."""


LIP_SHARE = 0.25
"""After SSDR, the bone poses and skin weights are fitted again with this share of the fit's weight on the mouth
(`lip_emphasis`, `refine_for_lips`): SSDR weighs every vertex alike, so the few vertices a viewer watches most are
fitted no better than the scalp. Demo head, 32 bones, over 8 LJ sequences: lips 0.405 -> 0.246 mm RMS (bench/bones.py);
a Ready Player Me head: lips 0.27 -> 0.05 mm RMS. 0: SSDR's fit as it is."""
SMALL_PART = 0.02
"""A connected part of the vertices SSDR would fit with fewer vertices than this share of the moving ones rides the
bones of its nearest vertex (`_riders`) instead of taking bones of its own."""
LIP_SWEEPS = 4
"""Rounds of the refit: each fits every bone's poses (weighted Procrustes), then every vertex's weights."""


class BoneError(ValueError):
    """Bones that cannot be solved or blended: the message names the character and what is wrong."""


@dataclass(frozen=True, eq=False)
class BoneRig:
    """A character's SSDR bones: bind pose, skin weights and one pose per viseme (see the module doc)."""

    name: str
    neutral: np.ndarray
    """(V, 3) float32 bind-pose vertices (the character's neutral)."""
    faces: np.ndarray
    """(F, 3) int32 triangles."""
    pose_names: tuple[str, ...]
    """The P poses' names (the 16 visemes, in `VISEMES` order)."""
    bone_names: tuple[str, ...]
    """The B bones' names: SSDR's "bone_00", ..., then the locked parts' "rigid_00", ... and "static" (`locked_parts`);
    their parent is the root joint `ROOT`."""
    bind_translations: np.ndarray
    """(B, 3) float64 bone heads c_b in skin space (bind rotation identity; the root joint sits at the origin)."""
    joints: np.ndarray
    """(V, 4) int: the bones each vertex follows (unused slots: bone 0 with weight 0)."""
    weights: np.ndarray
    """(V, 4) float32 skin weights, each row summing to 1 (non-increasing along the row)."""
    rotations: np.ndarray
    """(P, B, 4) float64 unit quaternions (w, x, y, z), w >= 0: each pose's bone rotations relative to the bind."""
    translations: np.ndarray
    """(P, B, 3) float64 each pose's bone translations relative to the bind (joint local = bind + this)."""
    fit_rms: np.ndarray
    """(P,) RMS vertex error of SSDR's own fit of each pose (mesh units)."""
    bind_error: float
    """Largest deviation of SSDR's neutral frame transforms from the identity."""
    solve_seconds: float
    """Wall-clock seconds of the SSDR solve."""
    solve_cpu_seconds: float
    """CPU seconds of this process during the solve (Dem Bones' threads included: set OMP_NUM_THREADS=1 for one
    core)."""
    vertex_colors: np.ndarray | None = None
    mm_per_unit: float = 1000.0
    """Millimetres per unit of the positions and translations: the character's (10 for the demo rig's centimetres)."""

    ROOT = "root"

    def in_metres(self) -> BoneRig:
        """The same rig in metres (glTF's unit; itself when already so): skinning is linear, so scaling the bind
        pose, the bone heads and the pose translations scales every skinned vertex, rotations unchanged."""
        if self.mm_per_unit == 1000.0:
            return self
        s = self.mm_per_unit / 1000.0
        return replace(self, neutral=(self.neutral * np.float32(s)).astype(np.float32),
                       bind_translations=self.bind_translations * s, translations=self.translations * s,
                       fit_rms=self.fit_rms * s, mm_per_unit=1000.0)

    @property
    def n_bones(self) -> int:
        return len(self.bone_names)

    @property
    def n_poses(self) -> int:
        return len(self.pose_names)

    @property
    def n_vertices(self) -> int:
        return int(self.neutral.shape[0])

    def inverse_bind_matrices(self) -> np.ndarray:
        """(B, 4, 4) float64 column-vector inverse bind matrices: translations by -c_b."""
        m = np.tile(np.eye(4), (self.n_bones, 1, 1))
        m[:, :3, 3] = -self.bind_translations
        return m


# ---- inputs -----------------------------------------------------------------------------------------------
def viseme_meshes(character: Character, binding=None) -> np.ndarray:
    """(16, V, 3) float64: each viseme at full weight on the character. With a `conventions.Binding`, the shapes
    its one-hot curve drives; without one, the character's shapes must be the 16 visemes (any order)."""
    neutral = np.asarray(character.neutral, np.float64)
    deltas = np.asarray(character.deltas, np.float64)
    if binding is not None:
        w = np.asarray(binding.weights(np.eye(len(VISEMES), dtype=np.float32)), np.float64)   # (16, S)
        return neutral[None] + np.einsum("ps,svc->pvc", w, deltas)
    missing = [v for v in VISEMES if v not in character.shape_names]
    if missing:
        raise BoneError(f"{character.where()}: no shape for viseme(s) {', '.join(missing)}; give a binding "
                        "(conventions.bind) to drive other shape names")
    return neutral[None] + deltas[[character.shape_index(v) for v in VISEMES]]


def max_bones(n_vertices: int) -> int:
    """The most bones `n_vertices` vertices can support: every bone must move at least MIN_VERTICES_PER_BONE."""
    return int(n_vertices) // MIN_VERTICES_PER_BONE


# ---- SSDR -------------------------------------------------------------------------------------------------
def solve_bones(character: Character, bone_count: int = DEFAULT_BONES, *, binding=None,
                iterations: int = DEFAULT_ITERATIONS, init_iterations: int = DEFAULT_INIT_ITERATIONS,
                lock_parts: bool = True, lip_share: float = LIP_SHARE) -> BoneRig:
    """SSDR of the character's 16 visemes into `bone_count` rigid bones (see the module doc).

    With `lock_parts` (default), the vertices no viseme moves go to one bone `static` (identity in every pose) and
    the connected parts that every viseme moves rigidly (the lower teeth with the jaw) to one bone `rigid_NN` per
    common motion (`locked_parts`), at most a quarter of the bones (static first, then the largest parts); SSDR
    shares the other bones among the rest. Without it, SSDR fits every vertex alike and lets the eyes drift and the
    teeth lag (bench/bones.py --no-lock).

    With `lip_share` > 0 and inner lips found on the character (`lips.inner_lip_pairs`: its landmarks, else
    `lipfinder`), the SSDR bones' poses and their vertices' weights are then fitted again with that share of the
    fit's weight on the mouth (`refine_for_lips`): what the viewer watches, a closure closed, comes first.

    BoneError for a bone count that is not an integer >= 1 or larger than the vertices can support (`max_bones`),
    a character without triangles, or non-finite vertices (CharacterError, also a ValueError, from validation).
    Dem Bones may leave a bone without any vertex; such bones are dropped, so the rig can have fewer bones."""
    import torch
    from kornia.geometry.conversions import quaternion_to_rotation_matrix, rotation_matrix_to_quaternion

    from py_dem_bones import DemBones, solve_skinning

    from visemeflow.animation.lips import inner_lip_pairs

    validate_character(character)
    where = character.where()
    if isinstance(bone_count, bool) or not isinstance(bone_count, (int, np.integer)) or bone_count < 1:
        raise BoneError(f"{where}: the bone count must be an integer >= 1, got {bone_count!r}")
    if not (isinstance(lip_share, (int, float)) and 0 <= lip_share < 1):
        raise BoneError(f"{where}: the lips' share of the bone fit must be in [0, 1), got {lip_share!r}")
    limit = max_bones(character.n_vertices)
    if bone_count > limit:
        raise BoneError(f"{where}: {bone_count} bones are more than its {character.n_vertices} vertices can "
                        f"support (at most {limit}: each bone must move at least {MIN_VERTICES_PER_BONE} vertices)")
    if not len(character.faces):
        raise BoneError(f"{where}: no triangles; SSDR seeds its bones on the mesh's faces")
    poses = viseme_meshes(character, binding)
    if not np.isfinite(poses).all():
        raise BoneError(f"{where}: the viseme meshes hold NaN or infinite coordinates")
    rest_all = np.asarray(character.neutral, np.float64)
    start, cpu = time.perf_counter(), time.process_time()
    cpu_start = cpu
    # the neutral is frame 0: the bind pose is solved; SSDR sees the mesh welded (`_welded`)
    rest, frames, faces, first, inverse = _welded(rest_all, np.concatenate([rest_all[None], poses]),
                                                  np.asarray(character.faces, np.int64))
    locked = locked_parts(rest, frames, faces) if lock_parts else []
    if len(locked) > int(bone_count) // 4:   # keep three quarters of the bones for SSDR: static first, then the
        order = sorted(range(len(locked)), key=lambda k: (locked[k][0] != "static", -len(locked[k][1])))
        locked = [locked[k] for k in sorted(order[: int(bone_count) // 4])]     # largest rigid parts
    free = np.ones(len(rest), bool)
    for _, ids, _ in locked:
        free[ids] = False
    riders = _riders(rest, frames, faces, free)
    free &= ~riders
    n_free = int(bone_count) - len(locked)
    if free.any() and n_free < 1:
        raise BoneError(f"{where}: {bone_count} bone(s) are too few: its parts that move rigidly or not at all take "
                        f"{len(locked)} ({', '.join(name for name, _, _ in locked)}) and the rest needs at least one")
    blocks_w, blocks_m, names = [], [], []
    if free.any():
        ids = np.flatnonzero(free)
        local = np.full(len(rest), -1)
        local[ids] = np.arange(len(ids))
        sub_faces = local[faces[free[faces].all(axis=1)]]
        if not len(sub_faces):
            raise BoneError(f"{where}: no triangle joins the vertices that deform; SSDR seeds its bones on faces")
        solver = DemBones()
        solver.nInitIters = int(init_iterations)
        result = solve_skinning(rest[ids], frames[:, ids], min(n_free, max_bones(len(ids))), faces=sub_faces,
                                max_influences=MAX_INFLUENCES, iterations=int(iterations), solver=solver)
        w_free = np.asarray(result.weights, np.float64)              # (B_free, V_free)
        m_free = np.asarray(result.transforms, np.float64)           # (F, B_free, 4, 4) column-vector
        used = np.flatnonzero(w_free.sum(axis=1) > 0)
        full = np.zeros((len(used), len(rest)))
        full[:, ids] = w_free[used]
        blocks_w.append(full)
        blocks_m.append(m_free[:, used])
        names += [f"bone_{b:02d}" for b in range(len(used))]
    for name, ids, m in locked:
        row = np.zeros((1, len(rest)))
        row[0, ids] = 1.0
        blocks_w.append(row)
        blocks_m.append(m[:, None])
        names.append(name)
    seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
    weights = np.concatenate(blocks_w)                       # (B, V)
    if riders.any():       # each rides the bones of the nearest vertex that has some (rest positions)
        from scipy.spatial import cKDTree

        anchors = np.flatnonzero(weights.sum(axis=0) > 0)
        if not len(anchors):
            raise BoneError(f"{where}: every vertex that moves lies in a part too small for a bone of its own")
        _, nearest = cKDTree(rest[anchors]).query(rest[riders])
        weights[:, riders] = weights[:, anchors[nearest]]
    transforms = np.concatenate(blocks_m, axis=1)            # (F, B, 4, 4)
    n_bones = len(names)

    # bone heads: the weighted centroid of what each bone moves
    mass = weights.sum(axis=1)
    centres = (weights @ rest) / mass[:, None]

    # at most 4 influences per vertex, largest first, renormalised in float32 (glTF asks for sums of 1)
    order = np.argsort(-weights, axis=0, kind="stable")[:MAX_INFLUENCES].T       # (V, 4)
    w4 = np.take_along_axis(weights.T, order, axis=1)
    if n_bones < MAX_INFLUENCES:
        pad = MAX_INFLUENCES - n_bones
        order = np.concatenate([order, np.zeros((len(order), pad), order.dtype)], axis=1)
        w4 = np.concatenate([w4, np.zeros((len(w4), pad))], axis=1)
    w4[w4 < 1e-6] = 0.0
    w4 /= w4.sum(axis=1, keepdims=True)
    joints = np.where(w4 > 0, order, 0)
    w4 = w4.astype(np.float32)
    w4[:, 0] += np.float32(1.0) - w4.sum(axis=1, dtype=np.float32)              # float32 sum exactly 1 (or 1 ulp)

    rot = transforms[1:, :, :3, :3]
    trans = transforms[1:, :, :3, 3]
    rot = _nearest_rotation(rot)
    q = rotation_matrix_to_quaternion(torch.from_numpy(rot.reshape(-1, 3, 3))).numpy().reshape(len(poses),
                                                                                               n_bones, 4)
    q = _unit_hemisphere(q)
    rot = quaternion_to_rotation_matrix(torch.from_numpy(q.reshape(-1, 4))).numpy().reshape(rot.shape)
    d = np.einsum("pbij,bj->pbi", rot, centres) + trans - centres[None]
    rig = BoneRig(name=character.name, neutral=rest.astype(np.float32), faces=faces.astype(np.int32),
                  pose_names=VISEMES,
                  bone_names=tuple(names), bind_translations=centres,
                  joints=joints.astype(np.int64), weights=w4, rotations=q, translations=d,
                  fit_rms=np.zeros(len(poses)), bind_error=float(np.abs(transforms[0] - np.eye(4)).max()),
                  solve_seconds=seconds, solve_cpu_seconds=cpu, mm_per_unit=character.mm_per_unit)
    pairs = inner_lip_pairs(character) if lip_share > 0 else None
    emphasis = _emphasis(rest, rest_all[pairs.ravel()], lip_share) if pairs is not None else None
    if emphasis is not None:     # on the welded mesh too: a vertex split in three counts once
        rig = refine_for_lips(rig, frames[1:], emphasis, np.array([n.startswith("bone_") for n in names]))
        object.__setattr__(rig, "solve_seconds", time.perf_counter() - start)
        object.__setattr__(rig, "solve_cpu_seconds", time.process_time() - cpu_start)
    # every vertex as the welded one it was made of
    rig = replace(rig, neutral=np.asarray(character.neutral, np.float32), faces=np.asarray(character.faces, np.int32),
                  joints=rig.joints[inverse], weights=rig.weights[inverse], vertex_colors=character.vertex_colors)
    fitted = skin_vertices(rig, *blend_poses(rig, np.eye(len(poses), dtype=np.float32)))
    object.__setattr__(rig, "fit_rms", np.sqrt(((fitted - poses) ** 2).sum(axis=2).mean(axis=1)))
    return rig


def _welded(rest: np.ndarray, frames: np.ndarray, faces: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The mesh with the vertices that coincide in every frame made one: (rest (U, 3), frames (F, U, 3), faces
    (without those two of whose corners became one), first (U,) a vertex of each, inverse (V,) each vertex's welded
    index). glTF exports split a
    vertex at every UV seam and sharp edge (a flat-shaded head is a soup of separate triangles), and SSDR seeds and
    smooths its bones along the triangles: on a Ready Player Me head split so (6,412 parts for 24,320 vertices), 13
    of 32 bones went to four-vertex pieces and one to the whole face, whose lips then did not close."""
    size = float(np.linalg.norm(np.ptp(rest, axis=0))) or 1.0
    key = np.round(np.transpose(frames, (1, 0, 2)).reshape(len(rest), -1) / (1e-7 * size)).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    welded = inverse[faces]
    keep = (welded[:, 0] != welded[:, 1]) & (welded[:, 1] != welded[:, 2]) & (welded[:, 0] != welded[:, 2])
    return rest[first], frames[:, first], welded[keep], first, inverse


def _riders(rest: np.ndarray, frames: np.ndarray, faces: np.ndarray, free: np.ndarray) -> np.ndarray:
    """(V,) the free vertices in connected parts (of the free vertices' triangles) smaller than `SMALL_PART` of the
    free vertices that move: eyelash and brow cards, a tooth, a stray quad. Given to SSDR, each such part took a
    bone of its own (a Ready Player Me head's 32 bones became 13 four-vertex pieces and one bone for the whole face,
    whose lips then stayed 1.55 mm apart at MBP; at 64 bones one bone held the face and its lips never moved). They
    ride the bones of their nearest vertex instead. None ride when that would leave SSDR nothing."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    size = float(np.linalg.norm(np.ptp(rest, axis=0))) or 1.0
    moving = free & (np.linalg.norm(frames - rest[None], axis=2).max(axis=0) > STATIC_TOL * size)
    inside = faces[free[faces].all(axis=1)]
    n = len(rest)
    edges = np.concatenate([inside[:, [0, 1]], inside[:, [1, 2]], inside[:, [2, 0]]])
    graph = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    smallest = max(MIN_VERTICES_PER_BONE, int(SMALL_PART * moving.sum()))
    counts = np.bincount(label[free], minlength=label.max() + 1)
    riders = free & (counts[label] < smallest)
    return riders if (free & ~riders).any() else np.zeros(n, bool)


def lip_emphasis(character: Character, share: float = LIP_SHARE) -> np.ndarray | None:
    """(V,) float64 weights of the bone fit: 1 + K exp(-(d / r)^2), d a vertex's distance to the nearest of the six
    inner-lip vertices, r half the span of those six (about half the mouth's width), K such that the mouth term
    carries `share` of the total; None when no inner lips are found (then nothing is refitted)."""
    from visemeflow.animation.lips import inner_lip_pairs

    if not 0 <= share < 1:
        raise BoneError(f"{character.where()}: the lips' share of the bone fit must be in [0, 1), got {share!r}")
    pairs = inner_lip_pairs(character)
    if pairs is None:
        return None
    rest = np.asarray(character.neutral, np.float64)
    return _emphasis(rest, rest[pairs.ravel()], share)


def _emphasis(rest: np.ndarray, lips: np.ndarray, share: float) -> np.ndarray | None:
    """`lip_emphasis` of the vertices `rest` (V, 3), the inner lips at `lips` (6, 3)."""
    radius = float(np.linalg.norm(lips.max(axis=0) - lips.min(axis=0))) / 2
    if not radius > 0:
        return None
    near = np.full(len(rest), np.inf)
    for point in lips:
        near = np.minimum(near, np.linalg.norm(rest - point, axis=1))
    mouth = np.exp(-(near / radius) ** 2)
    return 1.0 + share / (1 - share) * len(rest) / mouth.sum() * mouth


def mbp_gap_mm(character: Character, rig: BoneRig) -> float | None:
    """The inner lips' gap (mm) of the bone mesh at MBP's full weight (what a viewer sees of a closure in bone mode),
    or None when no inner lips are found on the character (`lips.inner_lip_pairs`)."""
    from visemeflow.animation.lips import inner_lip_pairs, pair_gap_mm

    pairs = inner_lip_pairs(character)
    if pairs is None or rig.n_vertices != character.n_vertices:
        return None
    one = np.zeros((1, rig.n_poses))
    one[0, list(rig.pose_names).index("MBP")] = 1.0
    lips = bone_animation(rig, one)[0][pairs.ravel()]
    return float(pair_gap_mm(lips.reshape(3, 2, 3), rig.mm_per_unit))


def _kabsch(u: np.ndarray, q: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pose p: the rotation R (P, 3, 3) and translation t (P, 3) minimising sum_v a_v |R u_v + t - q_pv|^2
    (u (n, 3), q (P, n, 3), a (n,) >= 0)."""
    total = a.sum()
    u_mean = a @ u / total
    q_mean = np.einsum("v,pvi->pi", a, q) / total
    h = np.einsum("v,vi,pvj->pij", a, u - u_mean, q - q_mean[:, None])
    left, _, right_t = np.linalg.svd(h)
    sign = np.sign(np.linalg.det(np.einsum("pji,pkj->pik", right_t, left)))
    fix = np.tile(np.eye(3), (len(h), 1, 1))
    fix[:, 2, 2] = np.where(sign == 0, 1.0, sign)
    r = np.einsum("pji,pjk,plk->pil", right_t, fix, left)
    return r, q_mean - np.einsum("pij,j->pi", r, u_mean)


def refine_for_lips(rig: BoneRig, poses: np.ndarray, emphasis: np.ndarray, free: np.ndarray,
                    sweeps: int = LIP_SWEEPS, chunk: int = 16384) -> BoneRig:
    """`rig` fitted again to the (P, V, 3) viseme meshes with vertex weights `emphasis` (`lip_emphasis`): `sweeps`
    rounds of SSDR's own two updates (Le and Deng 2012) with the weights in the transform update, (1) each bone in
    `free` (B,) posed anew by weighted Procrustes against what its vertices lack once the other bones have moved
    them, (2) each vertex's weights on its 4 bones solved anew (least squares, summing to 1, clipped at 0; the
    vertices wholly on a locked bone keep theirs). The joints of each vertex and the bind pose stay; so does every
    pose of a locked bone. The weight update also mends SSDR's cut to 4 influences, so on the demo head the whole
    face gains too (bench/bones.py prints both fits side by side)."""
    import torch
    from kornia.geometry.conversions import quaternion_to_rotation_matrix, rotation_matrix_to_quaternion

    n_poses, n_bones = rig.rotations.shape[:2]
    centres = rig.bind_translations
    r = quaternion_to_rotation_matrix(torch.from_numpy(rig.rotations.reshape(-1, 4))).numpy()
    r = r.reshape(n_poses, n_bones, 3, 3)
    t = centres + rig.translations - np.einsum("pbij,bj->pbi", r, centres)        # x -> R x + t
    u = rig.neutral.astype(np.float64)
    target = np.asarray(poses, np.float64)
    n = len(u)
    joints = rig.joints
    used = rig.weights > 0
    weights = rig.weights.astype(np.float64)
    movable = ~((~free[joints]) & used).any(axis=1)        # not on a locked bone at all

    def posed_slots(lo: int, hi: int) -> np.ndarray:
        """(P, n, 4, 3): each vertex of lo..hi moved by each of its 4 bones."""
        j = joints[lo:hi]
        return np.einsum("pvkij,vj->pvki", r[:, j], u[lo:hi]) + t[:, j]

    for _ in range(sweeps):
        skinned = np.concatenate([np.einsum("pvki,vk->pvi", posed_slots(lo, min(lo + chunk, n)), weights[lo:lo + chunk])
                                  for lo in range(0, n, chunk)], axis=1)
        for b in np.flatnonzero(free):
            slot = (joints == b) & (weights > 0)      # a weight the last round set to 0 no longer binds
            ids = np.flatnonzero(slot.any(axis=1))
            if len(ids) < MIN_VERTICES_PER_BONE:
                continue
            w = (weights[ids] * slot[ids]).sum(axis=1)
            mine = np.einsum("pij,vj->pvi", r[:, b], u[ids]) + t[:, b, None]
            others = skinned[:, ids] - w[None, :, None] * mine
            r[:, b], t[:, b] = _kabsch(u[ids], (target[:, ids] - others) / w[None, :, None], emphasis[ids] * w ** 2)
            skinned[:, ids] = others + w[None, :, None] * (np.einsum("pij,vj->pvi", r[:, b], u[ids]) + t[:, b, None])
        for lo in range(0, n, chunk):             # each vertex's weights on its own 4 bones
            hi = min(lo + chunk, n)
            x = np.transpose(posed_slots(lo, hi), (1, 2, 0, 3)).reshape(hi - lo, MAX_INFLUENCES, -1)
            y = np.transpose(target[:, lo:hi], (1, 0, 2)).reshape(hi - lo, -1)
            system = np.zeros((hi - lo, MAX_INFLUENCES + 1, MAX_INFLUENCES + 1))
            system[:, :MAX_INFLUENCES, :MAX_INFLUENCES] = np.einsum("vkm,vlm->vkl", x, x)
            system[:, :MAX_INFLUENCES, -1] = system[:, -1, :MAX_INFLUENCES] = 1.0
            rhs = np.concatenate([np.einsum("vkm,vm->vk", x, y), np.ones((hi - lo, 1))], axis=1)
            off = ~used[lo:hi]
            rows, slots = np.nonzero(off)
            system[rows, slots, :] = 0.0
            system[rows, slots, slots] = 1.0
            rhs[rows, slots] = 0.0
            system[:, :MAX_INFLUENCES, :MAX_INFLUENCES] += 1e-12 * np.eye(MAX_INFLUENCES)
            solved = np.clip(np.linalg.solve(system, rhs[..., None])[..., 0][:, :MAX_INFLUENCES], 0.0, None)
            solved[off] = 0.0
            total = solved.sum(axis=1, keepdims=True)
            ok = movable[lo:hi] & (total[:, 0] > 0)
            weights[lo:hi][ok] = solved[ok] / total[ok]

    q = rotation_matrix_to_quaternion(torch.from_numpy(r.reshape(-1, 3, 3))).numpy().reshape(n_poses, n_bones, 4)
    q = _unit_hemisphere(q)
    r = quaternion_to_rotation_matrix(torch.from_numpy(q.reshape(-1, 4))).numpy().reshape(n_poses, n_bones, 3, 3)
    order = np.argsort(-weights, axis=1, kind="stable")                  # largest first, as SSDR's
    w4 = np.take_along_axis(weights, order, axis=1)
    w4[w4 < 1e-6] = 0.0
    w4 /= w4.sum(axis=1, keepdims=True)
    j4 = np.where(w4 > 0, np.take_along_axis(joints, order, axis=1), 0)
    w4 = w4.astype(np.float32)
    w4[:, 0] += np.float32(1.0) - w4.sum(axis=1, dtype=np.float32)
    return replace(rig, rotations=q, translations=np.einsum("pbij,bj->pbi", r, centres) + t - centres,
                   joints=j4.astype(np.int64), weights=w4)


STATIC_TOL = 1e-6
"""A vertex no viseme moves farther than this share of the mesh's size (bounding-box diagonal) is static."""
RIGID_TOL = 2e-3
"""A part whose vertices a rigid transform per viseme puts within this share of the mesh's size is rigid (the demo
rig's lower teeth: 0.44 mm on a 30 cm head, 1.5e-3)."""


def locked_parts(rest: np.ndarray, frames: np.ndarray, faces: np.ndarray, *, static_tol: float = STATIC_TOL,
                 rigid_tol: float = RIGID_TOL) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """The parts that need no SSDR: [(bone name, vertex ids, (F, 4, 4) transforms)]. Vertices that no frame moves
    (`static`, identity); connected parts with no static vertex that one rigid transform per frame fits (the
    frames' rotation and translation by Kabsch, largest vertex error at most `rigid_tol` x size), parts that move
    together sharing one bone (`rigid_00`, ...)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    from visemeflow.animation.fit import similarity

    size = float(np.linalg.norm(np.ptp(rest, axis=0))) or 1.0
    moved = np.linalg.norm(frames - rest[None], axis=2).max(axis=0)
    static = moved <= static_tol * size
    out: list[tuple[str, np.ndarray, np.ndarray]] = []
    identity = np.tile(np.eye(4), (len(frames), 1, 1))

    def rigid(ids: np.ndarray) -> np.ndarray | None:
        """(F, 4, 4) rigid transforms putting rest[ids] on every frame within the tolerance, else None."""
        m = identity.copy()
        for f, frame in enumerate(frames):
            _, r, t = similarity(rest[ids], frame[ids], scale=False)
            if np.linalg.norm(rest[ids] @ r.T + t - frame[ids], axis=1).max() > rigid_tol * size:
                return None
            m[f, :3, :3], m[f, :3, 3] = r, t
        return m

    n = len(rest)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    graph = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    groups: list[np.ndarray] = []
    for part in np.unique(label[~static]):
        ids = np.flatnonzero(label == part)
        if static[ids].any() or len(ids) < MIN_VERTICES_PER_BONE or rigid(ids) is None:
            continue
        for g, members in enumerate(groups):             # one bone per common motion
            if rigid(np.concatenate([members, ids])) is not None:
                groups[g] = np.concatenate([members, ids])
                break
        else:
            groups.append(ids)
    for g, ids in enumerate(sorted(groups, key=len, reverse=True)):
        out.append((f"rigid_{g:02d}", np.sort(ids), rigid(ids)))
    if static.any():
        out.append(("static", np.flatnonzero(static), identity))
    return out


def _nearest_rotation(m: np.ndarray) -> np.ndarray:
    """The rotation nearest each 3x3 matrix (polar decomposition): Dem Bones' rigid transforms, to rounding."""
    u, _, vt = np.linalg.svd(m)
    r = u @ vt
    flip = np.linalg.det(r) < 0
    if flip.any():
        u[flip, :, -1] *= -1
        r = u @ vt
    return r


def _unit_hemisphere(q: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


# ---- blending and skinning ----------------------------------------------------------------------------------
def check_curves(rig: BoneRig, curves, where: str = "") -> np.ndarray:
    """(T, P) float64 pose weights; BoneError for a wrong shape or non-finite values."""
    c = np.asarray(curves, np.float64)
    label = where or f"bones of {rig.name!r}"
    if c.ndim != 2 or c.shape[1] != rig.n_poses or c.shape[0] < 1:
        raise BoneError(f"{label}: curves must be (frames >= 1, {rig.n_poses}), got {c.shape}")
    if not np.isfinite(c).all():
        raise BoneError(f"{label}: curves hold NaN or infinite values")
    return c


def blend_poses(rig: BoneRig, curves) -> tuple[np.ndarray, np.ndarray]:
    """Per frame blended joint pose: ((T, B, 4) unit quaternions (w, x, y, z) and (T, B, 3) local translations =
    bind + blended offset), from (T, P) curves (see the module doc for the blend)."""
    import torch

    c = torch.from_numpy(check_curves(rig, curves))
    q = torch.from_numpy(rig.rotations)                            # (P, B, 4), w >= 0
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    blended = identity + torch.einsum("tp,pbk->tbk", c, q - identity)
    norm = blended.norm(dim=-1, keepdim=True)
    if bool((norm < 1e-12).any()):
        raise BoneError(f"bones of {rig.name!r}: the weighted rotations cancel out (curves far beyond [0, 1])")
    rotations = (blended / norm).numpy()
    translations = rig.bind_translations[None] + np.einsum("tp,pbk->tbk", c.numpy(), rig.translations)
    return rotations, translations


def skinning_matrices(rig: BoneRig, rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """(T, B, 3, 4) skin-space matrices x -> R (x - c_b) + t_b of joint poses (quaternions w, x, y, z)."""
    import torch
    from kornia.geometry.conversions import quaternion_to_rotation_matrix

    q = torch.from_numpy(np.ascontiguousarray(rotations, np.float64))
    r = quaternion_to_rotation_matrix(q.reshape(-1, 4)).numpy().reshape(q.shape[:-1] + (3, 3))
    offset = np.asarray(translations, np.float64) - np.einsum("tbij,bj->tbi", r, rig.bind_translations)
    return np.concatenate([r, offset[..., None]], axis=-1)


def skin_vertices(rig: BoneRig, rotations: np.ndarray, translations: np.ndarray, *, chunk: int = 16) -> np.ndarray:
    """(T, V, 3) float64 linear blend skinning of the bind-pose vertices by the joint poses."""
    import torch

    m = torch.from_numpy(skinning_matrices(rig, rotations, translations))       # (T, B, 3, 4)
    u = torch.from_numpy(np.concatenate([rig.neutral.astype(np.float64), np.ones((rig.n_vertices, 1))], axis=1))
    j = torch.from_numpy(rig.joints)
    w = torch.from_numpy(rig.weights.astype(np.float64))
    out = []
    for start in range(0, m.shape[0], chunk):
        mg = m[start:start + chunk][:, j]                                          # (t, V, 4, 3, 4)
        per = torch.einsum("tvkij,vj->tvki", mg, u)
        out.append(torch.einsum("tvki,vk->tvi", per, w))
    return torch.cat(out).numpy()


def bone_animation(rig: BoneRig, curves) -> np.ndarray:
    """(T, V, 3) vertices of the bone animation of (T, P) curves: blend, then skin."""
    return skin_vertices(rig, *blend_poses(rig, curves))


# ---- pose table ---------------------------------------------------------------------------------------------
POSE_TABLE_COLUMNS = ("pose", "bone", "parent", "qx", "qy", "qz", "qw", "tx", "ty", "tz", "bind_tx", "bind_ty",
                      "bind_tz")


def pose_table_rows(rig: BoneRig) -> list[dict]:
    """One row per (pose, bone): the pose's rotation (unit quaternion x, y, z, w) and translation relative to the
    bind pose, with the bone's parent and bind translation (its local translation at rest; bind rotation identity).
    An engine building its own Pose Asset sets each joint's local transform to (bind + t, q)."""
    rows = []
    for p, pose in enumerate(rig.pose_names):
        for b, bone in enumerate(rig.bone_names):
            w, x, y, z = (float(v) for v in rig.rotations[p, b])
            tx, ty, tz = (float(v) for v in rig.translations[p, b])
            bx, by, bz = (float(v) for v in rig.bind_translations[b])
            rows.append(dict(zip(POSE_TABLE_COLUMNS, (pose, bone, BoneRig.ROOT, x, y, z, w, tx, ty, tz, bx, by, bz))))
    return rows


def write_pose_table(path, rig: BoneRig, fmt: str | None = None):
    """Write the pose table as CSV (one row per pose and bone, `POSE_TABLE_COLUMNS`) or JSON (by the suffix, or
    `fmt` "csv" / "json"); floats written exactly (shortest repr). Atomic; returns the path."""
    import csv
    import io
    import json
    from pathlib import Path

    from visemeflow.atomic import atomic_path

    path = Path(path)
    fmt = fmt or path.suffix.lower().lstrip(".")
    rows = pose_table_rows(rig)
    if fmt == "csv":
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=POSE_TABLE_COLUMNS, lineterminator="\n")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: repr(v) if isinstance(v, float) else v for k, v in row.items()})
        text = buffer.getvalue()
    elif fmt == "json":
        doc = {
            "character": rig.name, "rotation": "unit quaternion [x, y, z, w] relative to the bind pose",
            "translation": "offset from the bind translation, joint local space (= skin space: the root is the "
                           "identity), mesh units",
            "blend": "per frame: translation = bind + sum_s w_s t_s; rotation = normalise(identity + "
                     "sum_s w_s (q_s - identity)), every q_s with qw >= 0; then linear blend skinning",
            "root": BoneRig.ROOT,
            "bones": [{"name": b, "parent": BoneRig.ROOT, "bind_translation": [float(v) for v in c]}
                      for b, c in zip(rig.bone_names, rig.bind_translations)],
            "poses": {pose: {r["bone"]: {"rotation": [r["qx"], r["qy"], r["qz"], r["qw"]],
                                         "translation": [r["tx"], r["ty"], r["tz"]]}
                             for r in rows if r["pose"] == pose} for pose in rig.pose_names},
        }
        text = json.dumps(doc, indent=1) + "\n"
    else:
        raise ValueError(f"{path}: pose table format must be csv or json, got {fmt!r}")
    with atomic_path(path, keep_suffix=True) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    return path


def read_pose_table(path) -> dict:
    """Read a pose table (CSV or JSON by suffix) back: {"poses": names, "bones": names, "rotations": (P, B, 4)
    w, x, y, z, "translations": (P, B, 3), "bind_translations": (B, 3)}; ValueError for a table with missing or
    duplicate (pose, bone) rows or non-finite numbers."""
    import csv
    import json
    from pathlib import Path

    path = Path(path)
    if path.suffix.lower() == ".json":
        doc = json.loads(path.read_text(encoding="utf-8"))
        bones = [b["name"] for b in doc["bones"]]
        bind = {b["name"]: b["bind_translation"] for b in doc["bones"]}
        rows = [{"pose": p, "bone": b, "q": v["rotation"], "t": v["translation"], "bind": bind[b]}
                for p, per in doc["poses"].items() for b, v in per.items()]
    else:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            if tuple(reader.fieldnames or ()) != POSE_TABLE_COLUMNS:
                raise ValueError(f"{path}: columns must be {', '.join(POSE_TABLE_COLUMNS)}")
            rows = [{"pose": r["pose"], "bone": r["bone"], "q": [float(r[k]) for k in ("qx", "qy", "qz", "qw")],
                     "t": [float(r[k]) for k in ("tx", "ty", "tz")],
                     "bind": [float(r[k]) for k in ("bind_tx", "bind_ty", "bind_tz")]} for r in reader]
    poses = list(dict.fromkeys(r["pose"] for r in rows))
    bones = list(dict.fromkeys(r["bone"] for r in rows))
    index = {(r["pose"], r["bone"]): r for r in rows}
    if len(index) != len(rows) or len(index) != len(poses) * len(bones):
        raise ValueError(f"{path}: every pose needs exactly one row per bone")
    q = np.array([[index[p, b]["q"] for b in bones] for p in poses], np.float64)[..., [3, 0, 1, 2]]
    t = np.array([[index[p, b]["t"] for b in bones] for p in poses], np.float64)
    bind = np.array([index[poses[0], b]["bind"] for b in bones], np.float64)
    if not (np.isfinite(q).all() and np.isfinite(t).all() and np.isfinite(bind).all()):
        raise ValueError(f"{path}: non-finite numbers in the pose table")
    return {"poses": tuple(poses), "bones": tuple(bones), "rotations": q, "translations": t,
            "bind_translations": bind}


# ---- one utterance's bone exports ----------------------------------------------------------------------------
BONE_FORMATS: tuple[str, ...] = ("glb", "usd", "pose-csv", "pose-json")
BONE_SUFFIXES = {"glb": ".bones.glb", "usd": ".bones.usd", "pose-csv": ".poses.csv", "pose-json": ".poses.json"}
