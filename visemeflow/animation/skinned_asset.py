"""The user's own glTF avatar back with its face on SSDR bones: `write_asset_bones_glb`.

Bone mode (`animate --mode bones`) on a character read from a glTF scene writes that whole scene, as the blendshape
export does (`gltf_asset`: every mesh, material, texture, skin, node and clip kept; one new clip first), with the
character's SSDR bones (`bones.BoneRig`, solved on the driven meshes as the scene shows them) added to its skeleton:

- **A driven mesh on a skin** (a Ready Player Me head and teeth on the `Head` joint): the bones become joints of
  that skin, children of the joint the moving vertices follow: the deepest joint whose subtree carries at least
  90% of their skin weight, weighted by how far each vertex moves (`Head`, not `Neck`, nor a `Jaw` that only the
  lower lip follows). Each moving vertex gives the share g of its weight held by that joint and by the joints under
  it posed as it is (a jaw, in the usual bind pose) to the face bones, in SSDR's proportions; the rest of its
  weight stays on its other joints (a neck vertex keeps bending with the neck). At most 4 influences a vertex
  (JOINTS_0 / WEIGHTS_0: what three.js and most engines skin with), the largest kept and scaled to sum 1. A
  vertex the visemes do not move keeps its skinning exactly.
- **A driven mesh without a skin** (a head exported without an armature, teeth on a node): the bones become
  children of each node that shows it; the mesh moves to a new root node of the node's name, skinned by a new skin
  of those bones (glTF ignores a skinned mesh node's own transform, and three.js applies it anyway: only a root
  node without a transform is read alike everywhere); the old node keeps its transform and children, named
  `<name>_FaceBones`, and a clip of the file that set its morph weights now sets the new node's.
- A driven mesh the visemes do not move (an eye sharing the avatar's morph targets) stays as it is.
- The driven meshes' default morph weights (`mesh.weights`, a node's `weights`) are set to 0: the bones play the
  visemes, and a file that stores 1.0 for every target (some exporters do) showed every shape added on top of them
  in Blender (lips 104-122 mm apart where the bones put them 0.8-9 mm). A clip of the file that animates morph
  weights still does.

Poses: bone b's SSDR transform at frame t is W_b(t) = [R_b(t) | c_b + d_b(t)] in the scene's space
(`bones.blend_poses`), and the driven vertices were placed in that space by the parent P's rest pose. Its node's
local transform is world(P)^-1 W_b(t) (P at rest) without P's uniform scale s (a rest scale on a joint is what
Blender's importer cannot hold: it put the face metres away), keyed per frame (LINEAR, rotation and translation
channels for the bones that move), and its inverse bind matrix is (world(P) L_b(bind))^-1 world(P) IBM_P =
S(1 / s) T(-c_b) world(P) IBM_P (IBM_P the skin's own inverse bind matrix of P; the identity for a node): the
skinning matrix world(P) L_b(t) L_b(bind)^-1 IBM_P is W_b(t) T(-c_b) world(P) IBM_P, the rig's. So with the
skeleton at rest the file plays our skinning of the rig exactly (float32), at every frame time; when the user's
own clip moves the head, the face moves with it. A vertex that gives only the share g < 1 to the face bones moves
by g times its viseme motion: `notes` says how many and how far at most, in millimetres.

Refused, with a CharacterError naming the file and node: a parent scaled unevenly or mirrored (its local poses would
need a shear), a mesh on a node with a skin but without JOINTS_0, a driven primitive with a second set of
influences (JOINTS_1). Characters that are not glTF scenes are written by `skinned_gltf.write_skinned_glb`.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visemeflow.animation.bones import BoneRig, blend_poses, check_curves
from visemeflow.animation.gltf import GLTF_SUFFIXES
from visemeflow.animation.gltf_asset import _append, _append_array, _fits, _glb, _one_buffer, _read_document
from visemeflow.animation.skinned_gltf import frame_times
from visemeflow.atomic import atomic_path
from visemeflow.rig.character import Character, CharacterError
from visemeflow.rig.gltf import GltfScene, RigError

__all__ = ["asset_bone_notes", "is_gltf_asset", "write_asset_bones_glb"]

MAX_INFLUENCES = 4
PARENT_SHARE = 0.9
"""The parent joint of a skin's face bones: the deepest joint whose subtree carries this share of the moving
vertices' weight (each vertex counted by how far it moves)."""
_ARRAY_BUFFER = 34962
_LINEAR = "LINEAR"


def is_gltf_asset(character: Character) -> bool:
    """Whether `character` was read from a glTF scene whose file the bone export writes back."""
    return bool(character.parts) and Path(character.source).suffix.lower() in GLTF_SUFFIXES


# ---- quaternions (w, x, y, z) -----------------------------------------------------------------------------------
def _product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def _quaternion(rotation: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) as unit quaternions (..., 4): w, x, y, z."""
    import torch
    from kornia.geometry.conversions import rotation_matrix_to_quaternion

    q = rotation_matrix_to_quaternion(torch.from_numpy(np.ascontiguousarray(rotation, np.float64))).numpy()
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _continuous(q: np.ndarray) -> np.ndarray:
    """(T, 4) quaternions with each on the previous one's hemisphere (the same rotations; glTF's slerp between
    keys then takes the short way in every client)."""
    q = q.copy()
    for k in range(1, len(q)):
        if float(q[k] @ q[k - 1]) < 0:
            q[k] = -q[k]
    return q


@dataclass
class _Frame:
    """A parent's rest transform split as world = T(translation) R(rotation) s (s uniform): the bones under it get
    rigid local poses, its scale undone by their inverse bind matrices."""

    node: int
    translation: np.ndarray
    rotation: np.ndarray      # (3, 3)
    quaternion: np.ndarray    # (4,) w, x, y, z
    scale: float

    @classmethod
    def of(cls, scene: GltfScene, node: int) -> _Frame:
        world = scene.world_matrix(node)
        linear = world[:3, :3]
        scale = float(np.cbrt(np.linalg.det(linear)))
        name = scene.gltf.nodes[node].name or "unnamed"
        if not _conformal(linear):
            culprit = next((k for k in _ancestors(node, _parents(scene)) if not _conformal(_local(scene, k))), node)
            whose = "" if culprit == node else \
                f", because its parent node {culprit} ({scene.gltf.nodes[culprit].name or 'unnamed'}) is"
            raise CharacterError(f"{scene.path}: node {node} ({name}) is scaled unevenly or mirrored in the scene"
                                 f"{whose}; face bones under it cannot carry rigid poses (use --mode blendshape for "
                                 "this avatar)")
        rotation = linear / scale
        return cls(node, world[:3, 3].copy(), rotation, _quaternion(rotation), scale)

    def local(self, rotations: np.ndarray, translations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Local (rotation w, x, y, z; translation) under this parent of scene-space poses (..., 4), (..., 3)."""
        inverse = self.quaternion * np.array([1.0, -1.0, -1.0, -1.0])
        q = _product(np.broadcast_to(inverse, rotations.shape), rotations)
        q /= np.linalg.norm(q, axis=-1, keepdims=True)
        t = np.einsum("ji,...j->...i", self.rotation, translations - self.translation) / self.scale
        return q, t


def _conformal(linear: np.ndarray) -> bool:
    """Whether a 3x3 matrix is a rotation times a positive uniform scale."""
    scale = float(np.cbrt(np.linalg.det(linear)))
    return scale > 0 and np.allclose(linear.T @ linear, np.eye(3) * scale ** 2, rtol=1e-5,
                                     atol=1e-9 * max(scale ** 2, 1e-30))


def _local(scene: GltfScene, node: int) -> np.ndarray:
    """A node's own 3x3 linear part (its parent's world removed)."""
    parent = _parents(scene).get(node)
    world = scene.world_matrix(node)
    if parent is None:
        return world[:3, :3]
    return (np.linalg.inv(scene.world_matrix(parent)) @ world)[:3, :3]


@dataclass
class _BoneSet:
    """Face bones added under one parent node: the rig's bones `bones` (their order is the set's joint order)."""

    frame: _Frame             # where the rig's poses were placed (the first node for a mesh shown twice)
    parent: int               # the node the bones are children of
    bones: np.ndarray         # (K,) rig bone indices
    base: np.ndarray          # (4, 4) world(P) @ IBM_P at rest: skin space -> scene
    skin: int | None = None   # the existing skin extended, or None: a new skin for `mesh_node`
    mesh_node: int | None = None


@dataclass
class _Primitives:
    """New JOINTS_0 / WEIGHTS_0 of one driven mesh: per vertex block start, (joints (n, 4), weights (n, 4))."""

    mesh: int
    starts: tuple[int, ...]
    """Each primitive's block start, in the mesh's primitive order."""
    blocks: dict[int, tuple[np.ndarray, np.ndarray]]


@dataclass
class _Plan:
    sets: list[_BoneSet]
    primitives: list[_Primitives]
    notes: list[str]
    lost: np.ndarray | None = None
    """(V,) the viseme motion (rig units) each vertex loses to the plan: a moving vertex shared by joints above the
    face bones' parent moves by that parent's share of it; one that follows no joint under it, by none."""


def _moving_bones(rig: BoneRig) -> np.ndarray:
    """(B,) whether any pose moves the bone."""
    size = float(np.ptp(rig.neutral, axis=0).max()) or 1.0
    return (np.abs(rig.rotations[..., 1:]).max(axis=(0, 2)) > 1e-9) | \
        (np.abs(rig.translations).max(axis=(0, 2)) > 1e-9 * size)


def _viseme_motion(rig: BoneRig) -> np.ndarray:
    """(V,) how far each vertex moves at most over the one-hot poses (rig units)."""
    from visemeflow.animation.bones import bone_animation

    posed = bone_animation(rig, np.eye(rig.n_poses))
    return np.linalg.norm(posed - rig.neutral[None].astype(np.float64), axis=2).max(axis=0)


def _parents(scene: GltfScene) -> dict[int, int]:
    parents = {}
    for i, node in enumerate(scene.gltf.nodes or []):
        for child in node.children or []:
            parents.setdefault(child, i)
    return parents


def _ancestors(node: int, parents: dict[int, int]) -> list[int]:
    chain, seen = [node], {node}
    while node in parents and parents[node] not in seen:
        node = parents[node]
        seen.add(node)
        chain.append(node)
    return chain


def _pack(influences: list[list[tuple[int, float]]], n_joints: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(n, 4) joints, (n, 4) weights (largest 4 kept, rows scaled to 1) and the largest weight left out."""
    joints = np.zeros((len(influences), MAX_INFLUENCES), np.uint8 if n_joints <= 256 else np.uint16)
    weights = np.zeros((len(influences), MAX_INFLUENCES), np.float32)
    dropped = 0.0
    for v, pairs in enumerate(influences):
        merged: dict[int, float] = {}
        for joint, weight in pairs:
            if weight > 0:
                merged[joint] = merged.get(joint, 0.0) + weight
        ranked = sorted(merged.items(), key=lambda p: -p[1])
        if len(ranked) > MAX_INFLUENCES:
            dropped = max(dropped, ranked[MAX_INFLUENCES][1])
        kept = ranked[:MAX_INFLUENCES]
        total = sum(w for _, w in kept)
        for k, (joint, weight) in enumerate(kept):
            joints[v, k], weights[v, k] = joint, weight / total
    return joints, weights, dropped


@functools.lru_cache(maxsize=4)
def _plan(character: Character, rig: BoneRig) -> tuple[GltfScene, _Plan]:
    """What bones go where and each driven primitive's new skin (see the module), for the export and for
    `asset_bone_notes` alike: memoised on the two objects (compared by identity, as `animate` reuses one character and
    one solved rig for every utterance), never changed by its users."""
    source = Path(character.source)
    try:
        scene = GltfScene(source)
    except RigError as exc:
        raise CharacterError(str(exc)) from None
    if rig.n_vertices != character.n_vertices:
        raise CharacterError(f"{source}: the bone rig has {rig.n_vertices} vertices, the character "
                             f"{character.n_vertices}; solve the bones on this character")
    moving = _moving_bones(rig)
    on_moving = (rig.weights > 0) & moving[rig.joints]
    moved = on_moving.any(axis=1)
    motion = _viseme_motion(rig)
    mm = rig.mm_per_unit
    parents = _parents(scene)
    infos = {i.index: i for i in scene.meshes}
    sets: list[_BoneSet] = []
    primitives: list[_Primitives] = []
    notes: list[str] = []
    by_skin: dict[int, list] = {}
    lost = np.zeros(rig.n_vertices)
    for part in character.parts:
        span = slice(part.start, part.stop)
        if not moved[span].any():
            continue
        info = infos[part.mesh]
        try:
            mesh = scene.placed_mesh(part.mesh, morph_targets=False)[0]
        except RigError as exc:
            raise CharacterError(str(exc)) from None
        if any(getattr(p.attributes, "JOINTS_1", None) is not None for p in scene.gltf.meshes[part.mesh].primitives):
            raise CharacterError(f"{source}: mesh {part.name} has a second set of skin influences (JOINTS_1); bone "
                                 "mode writes 4 influences a vertex (use --mode blendshape for this avatar)")
        if info.skin is not None:
            if mesh.joints is None:
                raise CharacterError(f"{source}: mesh {part.name} is on a node with skin {info.skin} but has no "
                                     "JOINTS_0 / WEIGHTS_0")
            by_skin.setdefault(info.skin, []).append((part, mesh))
            continue
        # a mesh without a skin: bones under each node that shows it, a new skin each, the mesh on a new root node
        local = np.arange(part.n_vertices)
        bones = np.unique(rig.joints[span][rig.weights[span] > 0])
        column = {int(b): k for k, b in enumerate(bones)}
        influences = [[(column[int(rig.joints[g, k])], float(rig.weights[g, k]))
                       for k in range(rig.joints.shape[1]) if rig.weights[g, k] > 0] for g in part.start + local]
        joints, weights, _ = _pack(influences, len(bones))
        frame = _Frame.of(scene, part.nodes[0])
        for node in part.nodes:
            sets.append(_BoneSet(frame, node, bones, scene.world_matrix(part.nodes[0]), mesh_node=node))
        primitives.append(_Primitives(part.mesh, mesh.primitive_starts, _blocks(mesh, joints, weights)))
    for skin_index, members in by_skin.items():
        sets_and_prims, skin_notes = _skin_plan(scene, rig, skin_index, members, moved, motion, parents, mm, lost)
        sets.append(sets_and_prims[0])
        primitives += sets_and_prims[1]
        notes += skin_notes
    return scene, _Plan(sets, primitives, notes, lost)


def _blocks(mesh, joints: np.ndarray, weights: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per distinct primitive block start: that block's rows of the mesh's (V, 4) joints and weights."""
    starts = sorted(set(mesh.primitive_starts))
    ends = starts[1:] + [len(mesh.neutral)]
    return {s: (joints[s:e], weights[s:e]) for s, e in zip(starts, ends)}


def _skin_plan(scene: GltfScene, rig: BoneRig, skin_index: int, members: list, moved: np.ndarray, motion: np.ndarray,
               parents: dict[int, int], mm: float, lost: np.ndarray):
    source = scene.path
    skin = scene.gltf.skins[skin_index]
    joint_nodes = list(skin.joints or [])
    if skin.inverseBindMatrices is None:
        inverse = np.tile(np.eye(4), (len(joint_nodes), 1, 1))
    else:
        try:
            inverse = scene.reader.matrices(skin.inverseBindMatrices, f"skin {skin_index} inverseBindMatrices")
        except RigError as exc:
            raise CharacterError(str(exc)) from None
    rest = np.stack([scene.world_matrix(j) @ inverse[k] for k, j in enumerate(joint_nodes)])
    # each skin joint's weight over the moving vertices, counted by how far they move
    score = np.zeros(len(joint_nodes))
    for part, mesh in members:
        ids = np.flatnonzero(moved[part.start:part.stop])
        np.add.at(score, mesh.joints[ids].ravel(),
                  (mesh.weights[ids] * motion[part.start + ids][:, None]).ravel())
    total = float(score.sum())
    position = {node: k for k, node in enumerate(joint_nodes)}
    subtree = np.zeros(len(joint_nodes))
    for k, node in enumerate(joint_nodes):
        for above in _ancestors(node, parents):
            if above in position:
                subtree[position[above]] += score[k]
    candidates = [k for k in range(len(joint_nodes)) if subtree[k] >= PARENT_SHARE * total]
    if not candidates or total <= 0:
        names = ", ".join(p.name for p, _ in members)
        raise CharacterError(f"{source}: the moving vertices of {names} follow no joint of skin {skin_index}")
    parent = max(candidates, key=lambda k: (len(_ancestors(joint_nodes[k], parents)), -k))   # the deepest
    size = float(np.abs(rest[parent]).max()) or 1.0
    group = {parent} | {k for k, node in enumerate(joint_nodes)
                        if k != parent and joint_nodes[parent] in _ancestors(node, parents)[1:]
                        and np.allclose(rest[k], rest[parent], atol=1e-6 * size)}
    in_group = np.zeros(len(joint_nodes), bool)
    in_group[list(group)] = True
    parts_moved = [(part, mesh, np.flatnonzero(moved[part.start:part.stop])) for part, mesh in members]
    bones = np.unique(np.concatenate([rig.joints[part.start + ids][rig.weights[part.start + ids] > 0]
                                      for part, _, ids in parts_moved]))
    first = len(joint_nodes)
    column = {int(b): first + k for k, b in enumerate(bones)}
    n_joints = first + len(bones)
    prims, notes = [], []
    shared_count, shared_miss, orphans, dropped_most = 0, 0.0, 0, 0.0
    for part, mesh, ids in parts_moved:
        rows = [[(int(mesh.joints[v, k]), float(mesh.weights[v, k])) for k in range(mesh.joints.shape[1])]
                for v in range(part.n_vertices)]
        for v in ids:
            share = float(mesh.weights[v][in_group[mesh.joints[v]]].sum())
            g = part.start + v
            if share <= 0:
                orphans += 1
                lost[g] = motion[g]
                continue
            if share < 1 - 1e-6:
                shared_count += 1
                shared_miss = max(shared_miss, (1 - share) * float(motion[g]))
                lost[g] = (1 - share) * motion[g]
            rows[v] = [(column[int(rig.joints[g, k])], share * float(rig.weights[g, k]))
                       for k in range(rig.joints.shape[1]) if rig.weights[g, k] > 0] + \
                [(j, w) for j, w in rows[v] if not in_group[j]]
        joints, weights, dropped = _pack(rows, n_joints)
        dropped_most = max(dropped_most, dropped)
        prims.append(_Primitives(part.mesh, mesh.primitive_starts, _blocks(mesh, joints, weights)))
    parent_name = scene.gltf.nodes[joint_nodes[parent]].name or f"node {joint_nodes[parent]}"
    names = ", ".join(p.name for p, _ in members)
    if shared_count:
        notes.append(f"bones: {shared_count} moving vertices of {names} are shared by {parent_name} with other "
                     f"joints; they move by {parent_name}'s share of their viseme motion (up to "
                     f"{shared_miss * mm:.2f} mm less)")
    if orphans:
        notes.append(f"bones: {orphans} moving vertices of {names} follow no joint under {parent_name}; the face "
                     "bones leave them where their skin puts them")
    if dropped_most > 0:
        notes.append(f"bones: vertices of {names} with more than {MAX_INFLUENCES} influences kept their "
                     f"{MAX_INFLUENCES} largest (the largest left out weighed {dropped_most:.3f})")
    face = _BoneSet(_Frame.of(scene, joint_nodes[parent]), joint_nodes[parent], bones, rest[parent], skin=skin_index)
    return (face, prims), notes


def asset_bone_notes(character: Character, rig: BoneRig) -> tuple[str, ...]:
    """What the bone GLB of a glTF character leaves out or approximates (see the module), one line each; () for a
    character that is not a glTF scene."""
    if not is_gltf_asset(character):
        return ()
    return tuple(_plan(character, rig)[1].notes)


def write_asset_bones_glb(path: str | os.PathLike, character: Character, rig: BoneRig, curves, fps: float, *,
                          name: str | None = None) -> Path:
    """Write the glTF scene `character` was read from, whole, with `rig`'s bones (solved on this character) added
    to its skeleton and one new clip first (named `name`, else the character's name) posing them by (T, P)
    `curves` (frame k at k / fps), as a GLB at `path` (atomically); returns `path`. See the module.

    CharacterError naming the file for a scene the bones cannot be added to; BoneError for bad curves."""
    path = Path(path)
    source = Path(character.source)
    curves = check_curves(rig, curves, f"bones of {character.name!r}")
    times = frame_times(len(curves), fps)
    scene, plan = _plan(character, rig)
    rotations, translations = blend_poses(rig, curves)          # (T, B, 4) w, x, y, z; (T, B, 3)
    document, binary = _read_document(source)
    blob = _one_buffer(source, document, binary)
    nodes = document.setdefault("nodes", [])
    skins = document.setdefault("skins", [])
    moving = _moving_bones(rig)
    time_accessor = _append(document, blob, times, bounds=True)
    samplers: list[dict] = []
    channels: list[dict] = []
    keyed: dict[tuple[int, int], tuple[int, int]] = {}     # (frame node, bone) -> (rotation, translation) sampler
    scene_roots = [s.setdefault("nodes", []) for s in document.get("scenes") or []]
    moved_meshes: dict[int, int] = {}                      # old node -> the new root node showing its mesh
    for bone_set in plan.sets:
        frame = bone_set.frame
        parent = nodes[bone_set.parent]
        rest_q, rest_t = frame.local(np.tile([1.0, 0.0, 0.0, 0.0], (len(bone_set.bones), 1)),
                                     rig.bind_translations[bone_set.bones])
        stem = parent.get("name") or f"node{bone_set.parent}"
        added: list[int] = []
        for k, b in enumerate(bone_set.bones):
            nodes.append({"name": f"{stem}_{rig.bone_names[b]}", "rotation": rest_q[k][[1, 2, 3, 0]].tolist(),
                          "translation": rest_t[k].tolist()})
            added.append(len(nodes) - 1)
            if not moving[b]:
                continue
            if (frame.node, int(b)) not in keyed:
                q, t = frame.local(rotations[:, b], translations[:, b])
                q = _continuous(q)[:, [1, 2, 3, 0]].astype(np.float32)
                _fits(source, blob, q.nbytes + t.size * 4 + 8, "the face bones' poses")
                samplers.append({"input": time_accessor, "output": _append_array(document, blob, q),
                                 "interpolation": _LINEAR})
                samplers.append({"input": time_accessor, "interpolation": _LINEAR,
                                 "output": _append_array(document, blob, t.astype(np.float32))})
                keyed[(frame.node, int(b))] = (len(samplers) - 2, len(samplers) - 1)
            rotation_sampler, translation_sampler = keyed[(frame.node, int(b))]
            channels.append({"sampler": rotation_sampler, "target": {"node": len(nodes) - 1, "path": "rotation"}})
            channels.append({"sampler": translation_sampler,
                             "target": {"node": len(nodes) - 1, "path": "translation"}})
        parent.setdefault("children", []).extend(added)
        shift = np.tile(np.eye(4) / frame.scale, (len(bone_set.bones), 1, 1))     # (world(P) @ local bind)^-1
        shift[:, :3, 3] = -rig.bind_translations[bone_set.bones] / frame.scale
        shift[:, 3, 3] = 1.0
        ibm = np.einsum("bij,jk->bik", shift, bone_set.base).transpose(0, 2, 1).reshape(-1, 16).astype(np.float32)
        if bone_set.skin is not None:
            skin = skins[bone_set.skin]
            old = skin.get("inverseBindMatrices")
            count = len(skin.get("joints") or [])
            before = np.tile(np.eye(4, dtype=np.float32).reshape(1, 16), (count, 1)) if old is None else \
                scene.reader.matrices(old, "skin").transpose(0, 2, 1).reshape(-1, 16).astype(np.float32)
            skin["inverseBindMatrices"] = _append_array(document, blob, np.concatenate([before, ibm]))
            skin["joints"] = list(skin.get("joints") or []) + added
        else:
            skins.append({"name": f"{stem} face bones", "joints": added,
                          "inverseBindMatrices": _append_array(document, blob, ibm)})
            old_node = nodes[bone_set.mesh_node]
            shown = {"name": old_node.get("name") or f"node{bone_set.mesh_node}", "mesh": old_node.pop("mesh"),
                     "skin": len(skins) - 1}
            if "weights" in old_node:
                shown["weights"] = old_node.pop("weights")
            old_node["name"] = f"{shown['name']}_FaceBones"
            nodes.append(shown)
            moved_meshes[bone_set.mesh_node] = len(nodes) - 1
            for roots in scene_roots:
                if _in_tree(nodes, roots, bone_set.mesh_node):
                    roots.append(len(nodes) - 1)
    for primitives in plan.primitives:
        made: dict[int, tuple[int, int]] = {}      # primitives sharing their vertices share the new accessors
        for primitive, start in zip(document["meshes"][primitives.mesh]["primitives"], primitives.starts):
            if start not in made:
                joints, weights = primitives.blocks[start]
                _fits(source, blob, joints.nbytes + weights.nbytes + 8, "the face bones' skin weights")
                made[start] = (_append_array(document, blob, joints, target=_ARRAY_BUFFER),
                               _append_array(document, blob, weights, target=_ARRAY_BUFFER))
            attributes = primitive.setdefault("attributes", {})
            attributes["JOINTS_0"], attributes["WEIGHTS_0"] = made[start]
    for part in character.parts:     # the bones stand for the morph targets: a default weight would add a shape twice
        mesh = document["meshes"][part.mesh]
        if isinstance(mesh.get("weights"), list):
            mesh["weights"] = [0.0] * len(mesh["weights"])
        for node in [*part.nodes, *(moved_meshes[n] for n in part.nodes if n in moved_meshes)]:
            if isinstance(nodes[node].get("weights"), list):
                nodes[node]["weights"] = [0.0] * len(nodes[node]["weights"])
    for animation in document.get("animations") or []:      # a clip that set a moved mesh's morph weights
        for channel in animation.get("channels") or []:
            target = channel.get("target") or {}
            if target.get("path") == "weights" and target.get("node") in moved_meshes:
                target["node"] = moved_meshes[target["node"]]
    document.setdefault("animations", []).insert(0, {"name": name or character.name, "samplers": samplers,
                                                     "channels": channels})
    document["buffers"] = [dict((document.get("buffers") or [{}])[0], byteLength=len(blob))]
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(_glb(document, blob))
    return path


def _in_tree(nodes: list, roots: list, node: int) -> bool:
    stack, seen = list(roots), set()
    while stack:
        i = stack.pop()
        if i == node:
            return True
        if not isinstance(i, int) or i in seen or not 0 <= i < len(nodes):
            continue
        seen.add(i)
        stack.extend(nodes[i].get("children") or [])
    return False
