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
from visemeflow.animation.usd import _format_args, one_at_a_time, prim_name, timed_stage
from visemeflow.atomic import atomic_path

__all__ = ["build_skel_stage", "joint_paths", "write_usd_skel"]


def joint_paths(rig: BoneRig) -> list[str]:
    """The skeleton's joint tokens: the root, then each bone under it."""
    return [BoneRig.ROOT] + [f"{BoneRig.ROOT}/{prim_name(b)}" for b in rig.bone_names]


def _translate(v) -> Gf.Matrix4d:
    return Gf.Matrix4d(1.0).SetTranslate(Gf.Vec3d(*map(float, v)))


@one_at_a_time
def build_skel_stage(rig: BoneRig, curves, fps: float, *, name: str | None = None,
                     meters_per_unit: float | None = None) -> Usd.Stage:
    """The in-memory stage `write_usd_skel` saves (see the module doc); `meters_per_unit` defaults to the rig's unit
    (its character's)."""
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

    mesh = UsdGeom.Mesh.Define(stage, root_path.AppendChild("Mesh"))
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(rig.neutral, np.float32)))
    faces = np.ascontiguousarray(rig.faces, np.int32)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    weights = np.ascontiguousarray(rig.weights, np.float32)
    indices = np.where(weights > 0, rig.joints + 1, 0).astype(np.int32)
    binding.CreateJointIndicesPrimvar(False, 4).Set(Vt.IntArray.FromNumpy(indices.reshape(-1)))
    binding.CreateJointWeightsPrimvar(False, 4).Set(Vt.FloatArray.FromNumpy(weights.reshape(-1)))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    # extent over the animation: a skinned vertex is a convex combination of its bones' images of it, each within
    # r_b (the farthest vertex bone b moves from its head) of that bone's posed head, so the box around those balls
    # bounds every frame
    lo, hi = rig.neutral.min(axis=0).astype(np.float64), rig.neutral.max(axis=0).astype(np.float64)
    if rig.n_bones:
        reach = np.zeros(rig.n_bones)
        distance = np.linalg.norm(rig.neutral[:, None, :] - rig.bind_translations[rig.joints], axis=2)
        np.maximum.at(reach, rig.joints[weights > 0], distance[weights > 0])
        lo = np.minimum(lo, (translations - reach[None, :, None]).min(axis=(0, 1)))
        hi = np.maximum(hi, (translations + reach[None, :, None]).max(axis=(0, 1)))
    extent = Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))])
    mesh.CreateExtentAttr(extent)
    root.CreateExtentAttr(extent)
    return stage


@one_at_a_time
def write_usd_skel(path: str | os.PathLike, rig: BoneRig, curves, fps: float, *, name: str | None = None,
                   meters_per_unit: float | None = None) -> Path:
    """Write the bone animation of (T, 16) `curves` (frame k at time code k) as a UsdSkel stage; atomic."""
    path = Path(path)
    args = _format_args(path)
    stage = build_skel_stage(rig, curves, fps, name=name, meters_per_unit=meters_per_unit)
    with atomic_path(path, keep_suffix=True) as tmp:
        if not stage.GetRootLayer().Export(str(tmp), "", args):
            raise OSError(f"{path}: USD could not write the stage")
    return path
