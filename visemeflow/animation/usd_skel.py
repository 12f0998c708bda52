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

Each time sample is our blended pose of that frame (`bones.blend_poses`), so UsdSkel's skinning (linear blend, as
`UsdSkel.BakeSkinning` computes it) reproduces our vertices. Time, units and suffixes as `usd.py`: frame k is time
code k, timeCodesPerSecond = framesPerSecond = fps, upAxis Y, metersPerUnit the rig's unit by default (0.01 for the
demo rig's centimetres, 1 for a glTF character's metres); `.usda` text, `.usd`/`.usdc` binary crate.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt

from visemeflow.animation.bones import BoneRig, blend_poses
from visemeflow.animation.usd import _format_args, _unique_prim_names, one_at_a_time, prim_name, timed_stage
from visemeflow.atomic import atomic_path
from visemeflow.rig.character import Character

__all__ = ["build_skel_stage", "joint_paths", "write_usd_skel"]


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

    parts = character.parts if character is not None and character.parts else ()
    if parts and rig.n_vertices != character.n_vertices:
        raise ValueError(f"bones of {rig.name!r}: {rig.n_vertices} vertices, the character {character.n_vertices}")
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
