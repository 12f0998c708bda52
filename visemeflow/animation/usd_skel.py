"""OpenUSD export of SSDR bone animation (`bones.BoneRig` + curves) as UsdSkel with joints:

    /<Name>                  SkelRoot (the default prim)
        Skeleton             Skeleton: joints "root", "root/bone_00", ... (the root at the origin, every bone its
                             child), bindTransforms (skel space) = restTransforms (local): identity for the root,
                             a translation to c_b for bone b; UsdSkel.BindingAPI: skel:animationSource -> Animation
            Animation        SkelAnimation: translations (local: c_b + blended offset) and rotations (float quats)
                             time-sampled, one sample per frame; scales constant 1 (rigid bones)
        Mesh                 Mesh (triangles, the neutral as rest points), UsdSkel.BindingAPI: skel:skeleton ->
                             Skeleton, primvars:skel:jointIndices / jointWeights (vertex, elementSize 4, indices
                             into the skeleton's joint order: bone b is joint b + 1), geomBindTransform identity

For a character read from a glTF scene (`write_usd_skel(..., character=)`), one such Mesh per driven mesh, named by it
(`Wolf3D_Head`, `Wolf3D_Teeth`, ...), and the rest of the scene as the blendshape USD has it (`usd_scene`: the
meshes no target moves, placed as the file places them, named by their node; every glTF material as a
UsdPreviewSurface; texture coordinates): the user's whole avatar, its face on the SSDR bones. A driven mesh that a
second node shows (one eye mesh for both eyes) is there at rest: the bones are placed for its first node.

A glTF avatar whose moving meshes are all on skins (a Ready Player Me or Mixamo head) gets its own skeleton instead
(`usd_joints`), the face bones joints under the joint the bone GLB puts them under (`skinned_asset`'s plan:
`Hips/Spine/Neck/Head/Head_bone_00`), with rigid bind transforms and local poses under that joint, and each driven
mesh as stored with the GLB's influences: a body animation on that skeleton carries the face (`_define_joined`).
A driven mesh on a node without a skin (teeth on a node) gets its bones under the joint above its node, bound where
the scene shows it. Where joining would leave the lips part of their motion (`LIP_LOSS_MM`), the flat skeleton stays.

Each time sample is our blended pose of that frame (`bones.blend_poses`), so UsdSkel's skinning (linear blend, as
`UsdSkel.BakeSkinning` computes it) reproduces our vertices. Time, units and suffixes as `usd.py`: frame k is time
code k, timeCodesPerSecond = framesPerSecond = fps, upAxis Y, metersPerUnit the rig's unit by default (0.01 for the
demo rig's centimetres, 1 for a glTF character's metres); `.usda` text, `.usd`/`.usdc` binary crate.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt

from visemeflow.animation.bones import BoneRig, blend_poses, bone_animation
from visemeflow.animation.usd import _format_args, _unique_prim_names, one_at_a_time, prim_name, timed_stage
from visemeflow.atomic import atomic_path
from visemeflow.rig.character import Character

if TYPE_CHECKING:
    from visemeflow.animation.skinned_asset import _Plan
    from visemeflow.animation.usd_joints import AvatarSkeleton

__all__ = ["LIP_LOSS_MM", "build_skel_stage", "joint_paths", "write_usd_skel"]

LIP_LOSS_MM = 0.1
"""The most viseme motion (mm) the inner-lip vertices may lose when the face bones join the avatar's skeleton (the
bone GLB's plan moves a vertex shared with joints above the head by the head's share only); beyond it the bone USD
keeps the flat skeleton of SSDR bones, which plays the lips exactly."""


def joint_paths(rig: BoneRig) -> list[str]:
    """The skeleton's joint tokens: the root, then each bone under it."""
    return [BoneRig.ROOT] + [f"{BoneRig.ROOT}/{prim_name(b)}" for b in rig.bone_names]


def _translate(v) -> Gf.Matrix4d:
    return Gf.Matrix4d(1.0).SetTranslate(Gf.Vec3d(*map(float, v)))


@one_at_a_time
def build_skel_stage(rig: BoneRig, curves, fps: float, *, name: str | None = None,
                     meters_per_unit: float | None = None, character: Character | None = None) -> Usd.Stage:
    """The in-memory stage `write_usd_skel` saves (see the module doc); `meters_per_unit` defaults to the rig's unit
    (its character's). `character`: the glTF character the rig was solved on, whose scene the stage then holds."""
    if meters_per_unit is None:
        meters_per_unit = rig.mm_per_unit / 1000.0
    if not (isinstance(fps, (int, float, np.integer, np.floating)) and np.isfinite(fps) and fps > 0):
        raise ValueError(f"bones of {rig.name!r}: fps must be a positive number, got {fps!r}")
    if not (np.isfinite(meters_per_unit) and meters_per_unit > 0):
        raise ValueError(f"bones of {rig.name!r}: meters_per_unit must be a positive number, got {meters_per_unit!r}")
    rotations, translations = blend_poses(rig, curves)
    fps = float(fps)
    n_frames = len(rotations)

    stage = timed_stage(fps, n_frames, meters_per_unit, f"visemeflow bones: {rig.name} ({rig.n_bones} SSDR bones, "
                                                        f"{n_frames} frames at {fps:g} fps)")

    root_path = Sdf.Path.absoluteRootPath.AppendChild(prim_name(name if name is not None else rig.name))
    root = UsdSkel.Root.Define(stage, root_path)
    stage.SetDefaultPrim(root.GetPrim())

    parts = character.parts if character is not None and character.parts else ()
    if parts and rig.n_vertices != character.n_vertices:
        raise ValueError(f"bones of {rig.name!r}: {rig.n_vertices} vertices, the character {character.n_vertices}")
    joined, note = _joined(character, rig) if parts else (None, None)
    if joined is not None:           # the face bones in the avatar's own skeleton
        skeleton = UsdSkel.Skeleton.Define(stage, root_path.AppendChild("Skeleton"))
        anim = UsdSkel.Animation.Define(stage, skeleton.GetPath().AppendChild("Animation"))
        UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
        _define_joined(stage, root, skeleton, anim, joined, rig, character, rotations, translations)
        return stage

    joints = Vt.TokenArray(joint_paths(rig))
    bind = Vt.Matrix4dArray([Gf.Matrix4d(1.0)] + [_translate(c) for c in rig.bind_translations])
    skeleton = UsdSkel.Skeleton.Define(stage, root_path.AppendChild("Skeleton"))
    skeleton.CreateJointsAttr(joints)
    skeleton.CreateJointNamesAttr(Vt.TokenArray([BoneRig.ROOT, *rig.bone_names]))
    skeleton.CreateBindTransformsAttr(bind)
    skeleton.CreateRestTransformsAttr(bind)     # the root is the identity, so local = skel space

    anim = UsdSkel.Animation.Define(stage, skeleton.GetPath().AppendChild("Animation"))
    anim.CreateJointsAttr(joints)
    anim.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)] * len(joints)))
    t_attr, r_attr = anim.CreateTranslationsAttr(), anim.CreateRotationsAttr()
    zero = np.zeros((n_frames, 1, 3))
    t_all = np.concatenate([zero, translations], axis=1).astype(np.float32)
    q_all = np.concatenate([np.tile([[[1.0, 0, 0, 0]]], (n_frames, 1, 1)), rotations], axis=1)
    with Sdf.ChangeBlock():
        for k in range(n_frames):
            t_attr.Set(Vt.Vec3fArray.FromNumpy(t_all[k]), Usd.TimeCode(k))
            r_attr.Set(Vt.QuatfArray([Gf.Quatf(float(w), float(x), float(y), float(z)) for w, x, y, z in q_all[k]]),
                       Usd.TimeCode(k))
    UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])

    spans = [(root_path.AppendChild(prim), part.start, part.stop)
             for prim, part in zip(_unique_prim_names(p.name for p in parts), parts)] or \
        [(root_path.AppendChild("Mesh"), 0, rig.n_vertices)]
    boxes = [_skinned_mesh(stage, path, skeleton, rig, translations, start, stop) for path, start, stop in spans]
    extent = Vt.Vec3fArray([Gf.Vec3f(*map(float, np.min([b[0] for b in boxes], axis=0))),
                            Gf.Vec3f(*map(float, np.max([b[1] for b in boxes], axis=0)))])
    root.CreateExtentAttr(extent)
    if parts:        # a glTF avatar: its other meshes and its materials too (`usd_scene`)
        from visemeflow.animation.usd import _static_mesh
        from visemeflow.animation.usd_scene import dress_gltf_scene

        static = _static_mesh(stage)

        def other_instance(path: Sdf.Path, points: np.ndarray, faces: np.ndarray, names, deltas,
                           **_) -> UsdGeom.Mesh:
            return static(path, points, faces)      # the bones are placed for the mesh's first node

        notes = dress_gltf_scene(stage, root_path, character, [path for path, _, _ in spans], None, prim_name,
                                 static, other_instance)
        if note:
            notes.append(note)
        if notes:
            stage.GetRootLayer().documentation += "\nNot carried from the glTF file: " + "; ".join(notes)
    return stage


def _skinned_mesh(stage: Usd.Stage, path: Sdf.Path, skeleton: UsdSkel.Skeleton, rig: BoneRig,
                  translations: np.ndarray, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
    """The Mesh of the rig's vertices start..stop (its triangles among them), bound to the skeleton with their 4
    influences; returns its extent's (low, high) corners."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    neutral = np.ascontiguousarray(rig.neutral[start:stop], np.float32)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(neutral))
    inside = (rig.faces >= start).all(axis=1) & (rig.faces < stop).all(axis=1)
    faces = np.ascontiguousarray(rig.faces[inside] - start, np.int32)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    weights = np.ascontiguousarray(rig.weights[start:stop], np.float32)
    joints = rig.joints[start:stop]
    indices = np.where(weights > 0, joints + 1, 0).astype(np.int32)
    binding.CreateJointIndicesPrimvar(False, 4).Set(Vt.IntArray.FromNumpy(indices.reshape(-1)))
    binding.CreateJointWeightsPrimvar(False, 4).Set(Vt.FloatArray.FromNumpy(weights.reshape(-1)))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    # extent over the animation: a skinned vertex is a convex combination of its bones' images of it, each within
    # r_b (the farthest vertex bone b moves from its head) of that bone's posed head, so the box around those balls
    # bounds every frame
    lo, hi = neutral.min(axis=0).astype(np.float64), neutral.max(axis=0).astype(np.float64)
    if rig.n_bones:
        reach = np.zeros(rig.n_bones)
        distance = np.linalg.norm(neutral[:, None, :] - rig.bind_translations[joints], axis=2)
        np.maximum.at(reach, joints[weights > 0], distance[weights > 0])
        used = np.zeros(rig.n_bones, bool)
        used[joints[weights > 0]] = True
        if used.any():
            lo = np.minimum(lo, (translations[:, used] - reach[None, used, None]).min(axis=(0, 1)))
            hi = np.maximum(hi, (translations[:, used] + reach[None, used, None]).max(axis=(0, 1)))
    mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
    return lo, hi


@one_at_a_time
def write_usd_skel(path: str | os.PathLike, rig: BoneRig, curves, fps: float, *, name: str | None = None,
                   meters_per_unit: float | None = None, character: Character | None = None) -> Path:
    """Write the bone animation of (T, 16) `curves` (frame k at time code k) as a UsdSkel stage; atomic. With the
    glTF `character` the rig was solved on: one Mesh per driven mesh and the rest of its scene (see the module)."""
    path = Path(path)
    args = _format_args(path)
    stage = build_skel_stage(rig, curves, fps, name=name, meters_per_unit=meters_per_unit, character=character)
    with atomic_path(path, keep_suffix=True) as tmp:
        if not stage.GetRootLayer().Export(str(tmp), "", args):
            raise OSError(f"{path}: USD could not write the stage")
    return path


# ---- a glTF avatar's own skeleton with the face bones in it -------------------------------------------------------
@dataclass
class _Joined:
    """The avatar's skeleton (`usd_joints`) and the face bones the bone GLB adds to it (`skinned_asset`'s plan)."""

    avatar: AvatarSkeleton
    plan: _Plan
    tokens: list[str]         # the face bones' joint tokens, set by set
    bind: np.ndarray          # (N, 4, 4) their bind transforms in the skeleton's space
    rest: list                # per set: rest quaternions w, x, y, z (K, 4), translations (K, 3), scale: local


def _joined(character: Character, rig: BoneRig) -> tuple[_Joined | None, str | None]:
    """The face bones on the avatar's own skeleton, as the bone GLB puts them: under the joint the moving vertices
    follow (for a driven mesh on a node without a skin, the joint above that node), rigid bind transforms, local
    poses under that joint; (None, why) where the USD keeps the flat skeleton of SSDR bones: lips that joining would
    leave part of their motion (`LIP_LOSS_MM`), such a node under no joint that can carry it, a skin plan the GLB
    refuses, skins that cannot be one Skeleton, a moving mesh whose stored arrays UsdSkel would not skin to where
    the scene shows it (a vertex of no weight); (None, None) for a character not in metres (not a glTF's)."""
    from dataclasses import replace

    from visemeflow.animation.skinned_asset import _Frame, _plan
    from visemeflow.animation.usd_joints import avatar_skeleton
    from visemeflow.rig.character import CharacterError

    if rig.mm_per_unit != 1000.0 or character.mm_per_unit != 1000.0:
        return None, None
    try:
        scene, plan = _plan(character, rig)
    except CharacterError as exc:
        return None, f"{exc}: the face bones are on a skeleton of their own"
    if not plan.sets:
        return None, None
    own = "the face bones are on a skeleton of their own"
    avatar, why = avatar_skeleton(scene, {i.skin for i in scene.meshes if i.skin is not None}, 1.0, prim_name)
    if avatar is None:
        return None, why and f"{why}; {own}"
    sets = []
    for bone_set in plan.sets:
        if bone_set.skin is not None:
            sets.append(bone_set)
            continue
        # a driven mesh on a node without a skin (teeth on a node): its bones go under the joint the mesh would be
        # bound to rigidly (the nearest above its node, else the topmost), bound where the mesh lies at rest; a
        # second node showing the mesh keeps its instance at rest, as the blendshape USD places it
        part = next(p for p in character.parts if bone_set.mesh_node in p.nodes)
        if bone_set.mesh_node != part.nodes[0]:
            continue
        joint = avatar.rigid_joint(bone_set.mesh_node)
        if joint is None:
            return None, f"{part.name} is on a node without a skin and no joint can carry it: {own}"
        try:
            frame = _Frame.of(scene, avatar.nodes[joint])
        except CharacterError as exc:
            return None, f"{exc}: {own}"
        sets.append(replace(bone_set, frame=frame, parent=avatar.nodes[joint], base=np.eye(4)))
    plan = replace(plan, sets=sets)
    if plan.lost is not None:
        # the lips must meet where ours meet: a plan that leaves them part of their motion (lip vertices shared with
        # joints above the face bones' parent) keeps the flat skeleton, which plays our bones exactly
        from visemeflow.animation.lips import inner_lip_pairs

        pairs = inner_lip_pairs(character)
        at_lips = plan.lost[pairs.ravel()] if pairs is not None else plan.lost
        worst = float(at_lips.max(initial=0.0)) * rig.mm_per_unit
        if worst > LIP_LOSS_MM:
            where = "lips" if pairs is not None else "face"
            return None, (f"on the avatar's skeleton the face bones would move the {where} up to {worst:.1f} mm less "
                          f"than ours (vertices weighted to joints above the head too): {own}")
    moved = {p.mesh for p in plan.primitives}
    for part in character.parts:
        on_skin = any(i.index == part.mesh and i.skin is not None for i in scene.meshes)
        if part.mesh in moved and on_skin and \
                avatar.skinned_source(part.mesh, character.neutral[part.start:part.stop]) is None:
            return None, f"{part.name}: its skin does not place every vertex (one without weight): {own}"
    index = {node: k for k, node in enumerate(avatar.nodes)}
    tokens, binds, rests, taken = [], [], [], set(avatar.tokens)
    for bone_set in plan.sets:
        frame, parent = bone_set.frame, avatar.tokens[index[bone_set.parent]]
        named = bone_set.parent if bone_set.skin is not None else bone_set.mesh_node
        stem = prim_name(scene.gltf.nodes[named].name or f"node{named}")
        for b in bone_set.bones:
            token = base = f"{parent}/{stem}_{prim_name(rig.bone_names[b])}"
            k = 1
            while token in taken:
                token, k = f"{base}_{k}", k + 1
            taken.add(token)
            tokens.append(token)
        # bone b binds at T(c_b) in the avatar's skin space (`base`: skin space -> scene at rest), a rigid matrix
        # where that is rigid, as Blender's importer needs (it makes bones of the bind transforms and drops a
        # scale; the GLB's inverse bind matrices carry P's scale instead); its local pose under P then carries
        # 1 / P's scale, which half floats hold exactly for the usual 0.01 and 1
        shift = np.tile(np.eye(4), (len(bone_set.bones), 1, 1))
        shift[:, :3, 3] = rig.bind_translations[bone_set.bones]
        binds.append(np.einsum("ij,bjk->bik", np.linalg.inv(bone_set.base), shift))
        rests.append(frame.local(np.tile([1.0, 0.0, 0.0, 0.0], (len(bone_set.bones), 1)),
                                 rig.bind_translations[bone_set.bones]) + (1.0 / frame.scale,))
    return _Joined(avatar, plan, tokens, np.concatenate(binds), rests), None


def _posed(q: np.ndarray, t: np.ndarray, scale: float) -> np.ndarray:
    """(K, 4, 4) column-vector transforms T(t) R(q) S(scale) of rotations (K, 4) w, x, y, z and translations (K, 3)."""
    from visemeflow.rig.gltf import _quaternion_matrix

    out = np.tile(np.eye(4), (len(q), 1, 1))
    for k, (w, x, y, z) in enumerate(q):
        out[k, :3, :3] = _quaternion_matrix((x, y, z, w)) * scale
    out[:, :3, 3] = t
    return out


def _define_joined(stage: Usd.Stage, root: UsdSkel.Root, skeleton: UsdSkel.Skeleton, anim: UsdSkel.Animation,
                   joined: _Joined, rig: BoneRig, character: Character, rotations: np.ndarray,
                   translations: np.ndarray) -> None:
    """The skeleton, animation and meshes of a glTF avatar whose face bones join its own skeleton (see `_joined`):
    the avatar's joints at rest (`usd_joints`), the face bones under them animated per frame (local rigid poses, as
    the bone GLB keys them), every driven mesh as stored with the bone GLB's influences, the rest of the scene as the
    blendshape USD has it."""
    from visemeflow.animation.skinned_asset import _continuous, _moving_bones
    from visemeflow.animation.usd import _static_mesh
    from visemeflow.animation.usd_clips import define_clips
    from visemeflow.animation.usd_joints import usd_matrix
    from visemeflow.animation.usd_scene import dress_gltf_scene

    avatar, plan = joined.avatar, joined.plan
    root_path = root.GetPath()
    moving = _moving_bones(rig)
    tokens = avatar.tokens + joined.tokens
    skeleton.CreateJointsAttr(Vt.TokenArray(tokens))
    skeleton.CreateJointNamesAttr(Vt.TokenArray(avatar.names + [t.rpartition("/")[2] for t in joined.tokens]))
    skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray([usd_matrix(m) for m in
                                                        np.concatenate([avatar.bind, joined.bind])]))
    rest_local = [*avatar.rest_local] + [m for q, t, scale in joined.rest for m in _posed(q, t, scale)]
    skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray([usd_matrix(m) for m in rest_local]))
    # the animation poses the face bones that move (each in its parent joint's frame); the avatar's joints stay at
    # their rest transforms (`usd_joints`: no half-float scales)
    animated, keys, scales = [], [], []
    k = 0
    for bone_set in plan.sets:
        for b in bone_set.bones:
            if moving[b]:
                q, t = bone_set.frame.local(rotations[:, b], translations[:, b])
                animated.append(joined.tokens[k])
                keys.append((_continuous(q), t))
                scales.append(Gf.Vec3h(*[1.0 / bone_set.frame.scale] * 3))
            k += 1
    n_frames = len(rotations)
    anim.CreateJointsAttr(Vt.TokenArray(animated))
    anim.CreateScalesAttr(Vt.Vec3hArray(scales))
    t_attr, r_attr = anim.CreateTranslationsAttr(), anim.CreateRotationsAttr()
    with Sdf.ChangeBlock():
        for f in range(n_frames):
            t_attr.Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, t[f])) for _, t in keys]), Usd.TimeCode(f))
            r_attr.Set(Vt.QuatfArray([Gf.Quatf(*map(float, q[f])) for q, _ in keys]), Usd.TimeCode(f))

    set_tokens, k = [], 0
    for bone_set in plan.sets:
        set_tokens.append(joined.tokens[k:k + len(bone_set.bones)])
        k += len(bone_set.bones)
    by_skin = {bone_set.skin: tokens_ for bone_set, tokens_ in zip(plan.sets, set_tokens) if bone_set.skin is not None}
    by_node = {bone_set.mesh_node: tokens_ for bone_set, tokens_ in zip(plan.sets, set_tokens) if bone_set.skin is None}
    prims = {p.mesh: p for p in plan.primitives}
    extent = bone_animation(rig, np.eye(rig.n_poses))
    lo, hi = np.minimum(extent.min(axis=(0, 1)), rig.neutral.min(axis=0)), \
        np.maximum(extent.max(axis=(0, 1)), rig.neutral.max(axis=0))
    root.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
    static = _static_mesh(stage)
    part_paths = []
    for prim, part in zip(_unique_prim_names(p.name for p in character.parts), character.parts):
        path = root_path.AppendChild(prim)
        part_paths.append(path)
        span = slice(part.start, part.stop)
        inside = (character.faces >= part.start).all(axis=1) & (character.faces < part.stop).all(axis=1)
        faces = character.faces[inside] - part.start
        skinned = avatar.skinned_source(part.mesh, character.neutral[span])
        if part.mesh in prims and skinned is not None:       # moved by the face bones: the bone GLB's influences
            skin, source = skinned
            mesh = static(path, source.neutral, faces)
            _bind(mesh, skeleton, [avatar.tokens[j] for j in avatar.skin_joints[skin]] + list(by_skin[skin]),
                  prims[part.mesh].blocks)
        elif part.mesh in prims and part.nodes and part.nodes[0] in by_node:   # on a node without a skin
            mesh = static(path, character.neutral[span], faces)          # where the scene shows it at rest
            _bind(mesh, skeleton, by_node[part.nodes[0]], prims[part.mesh].blocks)
        elif skinned is not None:                             # a driven mesh no bone moves (an eye): its own skin
            mesh = static(path, skinned[1].neutral, faces)
            avatar.bind_skinned(mesh, skeleton, *skinned)
        else:
            mesh = static(path, character.neutral[span], faces)
            avatar.bind_rigid(mesh, skeleton, part.nodes[0] if part.nodes else None)

    def other_instance(path: Sdf.Path, points: np.ndarray, faces: np.ndarray, names, deltas, node=None,
                       **_) -> UsdGeom.Mesh:
        mesh = static(path, points, faces)        # a driven mesh's second node: its own skin's bones are not there
        avatar.bind_rigid(mesh, skeleton, node)
        return mesh

    notes = dress_gltf_scene(stage, root_path, character, part_paths, None, prim_name,
                             avatar.undriven(static, skeleton), other_instance, avatar.scene)
    notes += define_clips(stage, root_path, avatar, stage.GetTimeCodesPerSecond())
    if notes:
        stage.GetRootLayer().documentation += "\nNot carried from the glTF file: " + "; ".join(notes)
    if plan.notes:
        stage.GetRootLayer().documentation += "\n" + "; ".join(plan.notes)


def _bind(mesh: UsdGeom.Mesh, skeleton: UsdSkel.Skeleton, tokens: list[str], blocks: dict) -> None:
    """`mesh` skinned by the bone GLB's influences of it (`blocks`, per primitive block: joints (n, 4) indexing
    `tokens`, weights (n, 4)), its points in the skeleton's space (geomBindTransform identity)."""
    joints = np.concatenate([blocks[s][0] for s in sorted(blocks)]).astype(np.int32)
    weights = np.concatenate([blocks[s][1] for s in sorted(blocks)]).astype(np.float32)
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    binding.CreateJointsAttr(Vt.TokenArray(tokens))
    binding.CreateJointIndicesPrimvar(False, 4).Set(Vt.IntArray.FromNumpy(np.ascontiguousarray(joints).reshape(-1)))
    binding.CreateJointWeightsPrimvar(False, 4).Set(Vt.FloatArray.FromNumpy(weights.reshape(-1)))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
