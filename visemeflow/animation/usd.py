"""OpenUSD export: a character's mesh, its blendshapes and their weights over time, as UsdSkel.

The layout follows what NVIDIA Audio2Face and Maya USD exchange for blendshape-driven faces (UsdSkel,
`pxr/usd/usdSkel` "Schemas In-Depth"):

    /<Name>                      SkelRoot (the default prim)
        Skeleton                 Skeleton, one joint "root" at the origin (bind = rest = identity), with
                                 UsdSkel.BindingAPI: skel:animationSource -> Animation
            Animation            SkelAnimation: the joint "root" held at identity (UsdSkel only accepts an animation
                                 source whose translations/rotations/scales match its joints), blendShapes = the
                                 real shape names, blendShapeWeights time-sampled, one sample per frame
        Mesh                     Mesh (triangles, rest points), UsdSkel.BindingAPI: skel:skeleton -> Skeleton,
                                 skel:blendShapes (the real names), skel:blendShapeTargets -> its BlendShape
                                 children, rigidly bound to "root" (constant jointIndices [0], jointWeights [1],
                                 geomBindTransform identity), so importers that expect a skinned mesh find one
            <shape>              BlendShape per shape: offsets = the deltas; pointIndices when fewer than 3/4
                                 of the vertices move (only those vertices' offsets are stored)

Blend shapes need a bound Skeleton in UsdSkel: the weights live on the SkelAnimation, which only reaches the mesh
through the skeleton that `skel:skeleton` names, so a blendshape-only character still has one.

A character of several meshes (a glTF avatar's head, teeth, eyes: `Character.parts`) gets one Mesh prim per part
(named by the part, made a valid prim name) in place of `Mesh`, placed as in the scene, each with only its own
targets as BlendShapes and its own `skel:blendShapes` order, all bound to the one Skeleton: the SkelAnimation's
`blendShapes` (the union of the names) drives every part by name. A character read from a glTF scene (one mesh
or several) also gets the scene's texture coordinates, materials and undriven meshes (`usd_scene`); `write_usdz`
packs the stage with the materials' images into one `.usdz`. A glTF avatar with skins gets its own skeleton in
place of the one-joint one, its skinned meshes skinned as the file skins them (`usd_joints`). A character with
vertex colours (the demo head, a glTF's COLOR_0) gets them as `primvars:displayColor` (linear), and its meshes
without a material of their own a `Materials/VertexColours` UsdPreviewSurface whose diffuse colour reads them
(Blender wires it to Base Color).

Time: frame k is time code k; `timeCodesPerSecond` = `framesPerSecond` = fps; start/end time codes 0 .. T-1.
Stage: upAxis Y, `metersPerUnit` the character's own unit (`Character.mm_per_unit` / 1000: 0.01 for the demo rig's
centimetres, 1 for a glTF character's metres; a USD of an avatar in metres said 0.01 before, a head 2 mm tall).

Names: USD prim names must be identifiers ([A-Za-z_][A-Za-z0-9_]*); a shape whose name is not one gets a prim
name made valid (other characters -> "_", a leading digit prefixed by "_", made unique with a suffix), while the
`blendShapes` tokens on the animation and the mesh keep the real name, which is what the weights map by.

Formats by suffix: `.usda` text, `.usdc` binary crate, `.usd` binary crate (written as crate explicitly, whatever
USD_DEFAULT_FILE_FORMAT says). The file is written to a temporary path with the same suffix and renamed over
the target (`atomic_path`). Values are stored as float32, so the weights and offsets read back exactly.
"""

from __future__ import annotations

import functools
import os
import threading
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, UsdSkel, Vt

from visemeflow.animation.usd_scene import MATERIALS
from visemeflow.rig.character import Character
from visemeflow.rig.gltf import srgb_to_linear
from visemeflow.animation.usd_names import prim_name
from visemeflow.animation.usd_names import unique_prim_names as _unique_prim_names
from visemeflow.atomic import atomic_path

__all__ = ["USD_SUFFIXES", "build_stage", "prim_name", "read_usd_weights", "write_usd", "write_usdz"]

USD_SUFFIXES = (".usda", ".usdc", ".usd")
ROOT_JOINT = "root"
SKELETON = "Skeleton"
ANIMATION = "Animation"
MESH = "Mesh"
VERTEX_COLOURS = "VertexColours"
# USD (usd-core) from several Python threads at once can deadlock for good: its first use builds singletons (the
# asset resolver, the file-format registry) under C++ static-init guards while one thread holds the GIL and the
# other, inside the guard, waits for the GIL (`animate`'s threads writing two packages' .usd files hung CI; a
# barrier of 8 threads writing their first stage hung 1 run in 10). Every USD call of ours takes this lock:
# waiting on a Python lock releases the GIL. The stages are small; the lock costs little.
_USD_LOCK = threading.RLock()


def one_at_a_time(function):
    """`function` (which calls USD) runs in one thread at a time in this process (see `_USD_LOCK`)."""
    @functools.wraps(function)
    def locked(*args, **kwargs):
        with _USD_LOCK:
            return function(*args, **kwargs)
    return locked


# Store sparse offsets (pointIndices) when they are smaller than dense ones: an index costs 4 bytes, an offset 12.
_SPARSE_BELOW = 0.75

def _check_weights(weights, n_shapes: int, fps: float, where: str) -> np.ndarray:
    w = np.asarray(weights)
    if w.ndim != 2 or w.shape[1] != n_shapes or w.shape[0] == 0:
        raise ValueError(f"{where}: weights must be (frames > 0, {n_shapes}), got {w.shape}")
    w = np.ascontiguousarray(w, dtype=np.float32)
    if not np.isfinite(w).all():
        raise ValueError(f"{where}: weights hold NaN or infinite values")
    if w.min() < 0 or w.max() > 1:
        raise ValueError(f"{where}: weights must lie in [0, 1], got {float(w.min())} .. {float(w.max())}")
    if not (isinstance(fps, (int, float, np.integer, np.floating)) and np.isfinite(fps) and fps > 0):
        raise ValueError(f"{where}: fps must be a positive number, got {fps!r}")
    return w


def _format_args(path: Path) -> dict[str, str]:
    suffix = path.suffix.lower()
    if suffix not in USD_SUFFIXES:
        raise ValueError(f"{path}: unknown USD suffix {path.suffix!r}; use {', '.join(USD_SUFFIXES)}")
    return {"format": "usdc"} if suffix == ".usd" else {}


def _extent(character: Character) -> Vt.Vec3fArray:
    """A bound of the mesh under every weight combination in [0, 1]: rest points plus all negative (positive) parts."""
    neg = np.minimum(character.deltas, 0).sum(axis=0)
    pos = np.maximum(character.deltas, 0).sum(axis=0)
    lo = (character.neutral + neg).min(axis=0)
    hi = (character.neutral + pos).max(axis=0)
    return Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))])


@one_at_a_time
def build_stage(character: Character, weights, fps: float, *, name: str | None = None,
                meters_per_unit: float | None = None, textures: Path | None = None) -> Usd.Stage:
    """The in-memory stage `write_usd` saves (see the module doc for its layout); `meters_per_unit` defaults to the
    character's unit. For a glTF character, `textures` is the folder its materials' images are written to (and
    referenced from as `./textures/...`, relative to a layer saved beside it); None: materials without images."""
    where = character.where()
    if meters_per_unit is None:
        meters_per_unit = character.mm_per_unit / 1000.0
    w = _check_weights(weights, character.n_shapes, fps, where)
    if not (np.isfinite(meters_per_unit) and meters_per_unit > 0):
        raise ValueError(f"{where}: meters_per_unit must be a positive number, got {meters_per_unit!r}")
    fps = float(fps)
    n_frames = int(w.shape[0])

    stage = timed_stage(fps, n_frames, meters_per_unit,
                        f"visemeflow: {character.name} ({n_frames} frames at {fps:g} fps)")

    root_path = Sdf.Path.absoluteRootPath.AppendChild(prim_name(name if name is not None else character.name))
    root = UsdSkel.Root.Define(stage, root_path)
    stage.SetDefaultPrim(root.GetPrim())
    extent = _extent(character)
    root.CreateExtentAttr(extent)

    identity = Gf.Matrix4d(1.0)
    shape_tokens = Vt.TokenArray(list(character.shape_names))

    avatar, avatar_note, scene, scale = None, None, None, 1000.0 / float(character.mm_per_unit)
    if character.parts:          # a glTF scene: its own skeleton, where it has one (`usd_joints`)
        from visemeflow.animation.usd_joints import avatar_skeleton
        from visemeflow.rig.gltf import GltfScene

        scene = GltfScene(character.source)
        avatar, avatar_note = avatar_skeleton(scene, {i.skin for i in scene.meshes if i.skin is not None}, scale,
                                              prim_name)

    skeleton = UsdSkel.Skeleton.Define(stage, root_path.AppendChild(SKELETON))
    anim = UsdSkel.Animation.Define(stage, skeleton.GetPath().AppendChild(ANIMATION))
    if avatar is not None:
        avatar.define(skeleton, anim)
    else:
        skeleton.CreateJointsAttr(Vt.TokenArray([ROOT_JOINT]))
        skeleton.CreateJointNamesAttr(Vt.TokenArray([ROOT_JOINT]))
        skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray([identity]))
        skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray([identity]))
        anim.CreateJointsAttr(Vt.TokenArray([ROOT_JOINT]))
        anim.CreateTranslationsAttr(Vt.Vec3fArray([Gf.Vec3f(0, 0, 0)]))
        anim.CreateRotationsAttr(Vt.QuatfArray([Gf.Quatf(1, 0, 0, 0)]))
        anim.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)]))
    anim.CreateBlendShapesAttr(shape_tokens)
    weights_attr = anim.CreateBlendShapeWeightsAttr()
    with Sdf.ChangeBlock():
        for k in range(n_frames):
            weights_attr.Set(Vt.FloatArray.FromNumpy(w[k]), Usd.TimeCode(k))

    skel_binding = UsdSkel.BindingAPI.Apply(skeleton.GetPrim())
    skel_binding.CreateAnimationSourceRel().SetTargets([anim.GetPath()])

    # vertex colours (sRGB display values) as USD's displayColor, which is linear
    colors = None if character.vertex_colors is None else srgb_to_linear(character.vertex_colors)
    def part_mesh(path: Sdf.Path, part, points: np.ndarray, faces: np.ndarray, names, deltas: np.ndarray,
                  part_colors: np.ndarray | None) -> None:
        """A driven mesh: on the avatar's skeleton, as stored and skinned by its skin, or rigidly on the joint above
        it; without one, rigidly on the root joint."""
        skinned = avatar.skinned_source(part.mesh, points) if avatar is not None else None
        if skinned is not None:
            points, deltas = avatar.stored(skinned[1])
            names = part.target_names
        mesh = _define_mesh(stage, path, skeleton, points, faces, names, deltas, part_colors,
                            rigid_root=avatar is None)
        if skinned is not None:
            avatar.bind_skinned(mesh, skeleton, *skinned)
        elif avatar is not None:
            avatar.bind_rigid(mesh, skeleton, part.nodes[0] if part.nodes else None)

    part_prims = []
    if len(character.parts) > 1:
        for prim, part in zip(_unique_prim_names(p.name for p in character.parts), character.parts):
            columns = part.columns(character.shape_names)
            inside = (character.faces >= part.start).all(axis=1) & (character.faces < part.stop).all(axis=1)
            part_prims.append(root_path.AppendChild(prim))
            part_mesh(part_prims[-1], part, character.neutral[part.start:part.stop],
                      character.faces[inside] - part.start, part.target_names,
                      character.deltas[columns, part.start:part.stop],
                      None if colors is None else colors[part.start:part.stop])
    elif character.parts:
        part_prims.append(root_path.AppendChild(MESH))
        part_mesh(part_prims[-1], character.parts[0], character.neutral, character.faces, character.shape_names,
                  character.deltas, colors)
    else:
        part_prims.append(root_path.AppendChild(MESH))
        _define_mesh(stage, part_prims[-1], skeleton, character.neutral, character.faces,
                     character.shape_names, character.deltas, colors)
    if character.parts:          # read from a glTF scene: its materials and other meshes too (`usd_scene`)
        from visemeflow.animation.usd_scene import dress_gltf_scene

        static = _static_mesh(stage)

        def driven(path: Sdf.Path, points: np.ndarray, faces: np.ndarray, names, deltas: np.ndarray,
                   node: int | None = None) -> UsdGeom.Mesh:
            mesh = _define_mesh(stage, path, skeleton, points, faces, names, deltas, rigid_root=avatar is None)
            if avatar is not None:
                avatar.bind_rigid(mesh, skeleton, node)
            return mesh

        undriven = static if avatar is None else avatar.undriven(static, skeleton)
        notes = dress_gltf_scene(stage, root_path, character, part_prims, textures, prim_name, undriven, driven,
                                 scene)
        if avatar is not None:   # its own clips, each a SkelAnimation beside ours (`usd_clips`)
            from visemeflow.animation.usd_clips import define_clips

            notes += define_clips(stage, root_path, avatar, fps)
        if avatar_note:
            notes.append(avatar_note)
        if notes:
            stage.GetRootLayer().documentation += "\nNot carried from the glTF file: " + "; ".join(notes)
    if colors is not None:
        _bind_vertex_colours(stage, root_path, part_prims)
    return stage


def _bind_vertex_colours(stage: Usd.Stage, root: Sdf.Path, meshes: list[Sdf.Path]) -> None:
    """Bind `VERTEX_COLOURS` (a UsdPreviewSurface whose diffuse colour reads `displayColor`) to the meshes that carry
    vertex colours and have no material of their own: Blender, Omniverse and Quick Look then show the character's
    colours (a mesh without a material is shown in its displayColor by some viewers, grey by others)."""
    unbound = [path for path in meshes
               if not UsdShade.MaterialBindingAPI(stage.GetPrimAtPath(path)).GetDirectBindingRel().GetTargets()]
    if not unbound:
        return
    folder = root.AppendChild(MATERIALS)
    if not stage.GetPrimAtPath(folder):
        UsdGeom.Scope.Define(stage, folder)
    material = UsdShade.Material.Define(stage, folder.AppendChild(VERTEX_COLOURS))
    surface = UsdShade.Shader.Define(stage, material.GetPath().AppendChild("Surface"))
    surface.CreateIdAttr("UsdPreviewSurface")
    reader = UsdShade.Shader.Define(stage, material.GetPath().AppendChild("displayColor"))
    reader.CreateIdAttr("UsdPrimvarReader_float3")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("displayColor")
    reader.CreateOutput("result", Sdf.ValueTypeNames.Float3)
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(reader.ConnectableAPI(), "result")
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.6)
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    for path in unbound:
        UsdShade.MaterialBindingAPI.Apply(stage.GetPrimAtPath(path)).Bind(material)


def _static_mesh(stage: Usd.Stage):
    """`define(path, points, faces)`: a Mesh prim of a glTF scene's undriven meshes, bound to no skeleton (an
    avatar's skeleton may bind it after: `usd_joints.AvatarSkeleton.undriven`)."""
    def define(path: Sdf.Path, points: np.ndarray, faces: np.ndarray, **_) -> UsdGeom.Mesh:
        mesh = UsdGeom.Mesh.Define(stage, path)
        points = np.ascontiguousarray(points, dtype=np.float32)
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points))
        faces = np.ascontiguousarray(faces, dtype=np.int32)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1)))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, points.min(axis=0))),
                                             Gf.Vec3f(*map(float, points.max(axis=0)))]))
        return mesh
    return define


def _define_mesh(stage: Usd.Stage, path: Sdf.Path, skeleton: UsdSkel.Skeleton, neutral: np.ndarray,
                 faces: np.ndarray, shape_names, deltas: np.ndarray, colors: np.ndarray | None = None, *,
                 rigid_root: bool = True) -> UsdGeom.Mesh:
    """A Mesh prim bound to the skeleton, rigidly to its root joint unless `rigid_root` is false (the caller binds
    its joints then), with one BlendShape child per shape (see the module), and `colors` (linear RGB per vertex) as
    its displayColor."""
    identity = Gf.Matrix4d(1.0)
    mesh = UsdGeom.Mesh.Define(stage, path)
    if colors is not None:
        UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray,
                                                UsdGeom.Tokens.vertex).Set(
            Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(colors, dtype=np.float32)))
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(neutral, dtype=np.float32)))
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    neg, pos = np.minimum(deltas, 0).sum(axis=0), np.maximum(deltas, 0).sum(axis=0)
    lo, hi = (neutral + neg).min(axis=0), (neutral + pos).max(axis=0)
    mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))

    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    if rigid_root:
        binding.CreateJointIndicesPrimvar(True, 1).Set(Vt.IntArray([0]))
        binding.CreateJointWeightsPrimvar(True, 1).Set(Vt.FloatArray([1.0]))
        binding.CreateGeomBindTransformAttr(identity)
    binding.CreateBlendShapesAttr(Vt.TokenArray(list(shape_names)))

    targets = []
    n_vertices = len(neutral)
    for shape_prim, delta in zip(_unique_prim_names(shape_names), deltas):
        shape = UsdSkel.BlendShape.Define(stage, mesh.GetPath().AppendChild(shape_prim))
        moving = np.flatnonzero((delta != 0).any(axis=1)).astype(np.int32)
        if len(moving) < _SPARSE_BELOW * n_vertices:
            shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(delta[moving], dtype=np.float32)))
            shape.CreatePointIndicesAttr(Vt.IntArray.FromNumpy(moving))
        else:
            shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(delta, dtype=np.float32)))
        targets.append(shape.GetPath())
    binding.CreateBlendShapeTargetsRel().SetTargets(targets)
    return mesh


def timed_stage(fps: float, n_frames: int, meters_per_unit: float, documentation: str):
    """An in-memory stage, Y up, `meters_per_unit`, time codes = frames at `fps` from 0 to `n_frames - 1`."""
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, float(meters_per_unit))
    stage.SetTimeCodesPerSecond(fps)
    stage.SetFramesPerSecond(fps)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(n_frames - 1)
    stage.GetRootLayer().documentation = documentation
    return stage


@one_at_a_time
def write_usd(path: str | os.PathLike, character: Character, weights, fps: float, *, name: str | None = None,
              meters_per_unit: float | None = None) -> Path:
    """Write `character` animated by `weights` ((T, S) in [0, 1], columns in `character.shape_names` order, frame
    k at time k / fps) as a UsdSkel stage: `.usda` (text), `.usd` or `.usdc` (binary crate). `name` names the
    SkelRoot (default: the character's name, made a valid prim name). Atomic; returns `path`."""
    path = Path(path)
    args = _format_args(path)
    stage = build_stage(character, weights, fps, name=name, meters_per_unit=meters_per_unit)
    with atomic_path(path, keep_suffix=True) as tmp:
        if not stage.GetRootLayer().Export(str(tmp), "", args):
            raise OSError(f"{path}: USD could not write the stage")
    return path


@one_at_a_time
def write_usdz(path: str | os.PathLike, character: Character, weights, fps: float, *, name: str | None = None,
               meters_per_unit: float | None = None) -> Path:
    """`write_usd`'s stage and its textures in one USDZ package (a zip archive that USD, Omniverse, Blender and
    Apple's Quick Look read as one file): the stage as a binary crate, a glTF character's material images beside it
    under `textures/`. Atomic; returns `path`."""
    import tempfile

    from pxr import UsdUtils

    path = Path(path)
    if path.suffix.lower() != ".usdz":
        raise ValueError(f"{path}: a USDZ package's name ends in .usdz")
    with tempfile.TemporaryDirectory(prefix="visemeflow-usdz-") as folder:
        layer = Path(folder) / f"{path.stem}.usdc"
        stage = build_stage(character, weights, fps, name=name, meters_per_unit=meters_per_unit,
                            textures=Path(folder) / "textures")
        if not stage.GetRootLayer().Export(str(layer)):
            raise OSError(f"{path}: USD could not write the stage")
        with atomic_path(path, keep_suffix=True) as tmp:
            if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(layer)), str(tmp)):
                raise OSError(f"{path}: USD could not write the USDZ package")
    return path


@one_at_a_time
def read_usd_weights(path: str | os.PathLike) -> tuple[tuple[str, ...], np.ndarray, float]:
    """Read back (shape names, (T, S) float32 weights at time codes 0 .. T-1, fps) from the first SkelAnimation
    of a stage written by `write_usd` (a check and a convenience; any UsdSkel reader sees the same values)."""
    path = Path(path)
    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise ValueError(f"{path}: not a readable USD stage")
    anim = next((UsdSkel.Animation(p) for p in stage.Traverse() if p.IsA(UsdSkel.Animation)), None)
    if anim is None:
        raise ValueError(f"{path}: no SkelAnimation prim")
    names = tuple(str(t) for t in anim.GetBlendShapesAttr().Get() or ())
    attr = anim.GetBlendShapeWeightsAttr()
    times = attr.GetTimeSamples()
    rows = [np.asarray(attr.Get(Usd.TimeCode(t)), dtype=np.float32) for t in times]
    weights = np.stack(rows) if rows else np.zeros((0, len(names)), np.float32)
    return names, weights, float(stage.GetTimeCodesPerSecond())
