"""Skinned glTF 2.0: a character's SSDR bones (`bones.BoneRig`) and their per-frame blended poses as a GLB.

Positions and translations are in metres, glTF's unit (`BoneRig.in_metres`). Layout (glTF 2.0, sections 3.7.3 skins
and 3.11 animations), through pygltflib and the morph-target writer's buffer
layout (`gltf._Layout`: one buffer view per array, 4-byte aligned):

- node 0 "<name>": the mesh and the skin, at the scene root with no transform (a skinned mesh's own transform is
  ignored by the specification, and the validator warns about one);
- node 1 "root": the skeleton root joint at the origin, children nodes 2 .. B + 1, one per bone, each with its bind
  translation c_b and no rotation (bind pose = rest pose);
- skin 0: joints = [root, bones...] (the root is joint 0, every vertex weight is on a bone), skeleton = root,
  inverseBindMatrices (float32 MAT4, column-major): identity for the root, translation -c_b for bone b;
- the mesh: POSITION (the neutral, min/max), NORMAL, COLOR_0 when the character has colours (linear RGB), indices,
  JOINTS_0 (unsigned byte joint ids, unsigned short beyond 256 joints) and WEIGHTS_0 (float32, rows summing to 1,
  unused slots joint 0 with weight 0), the same PBR material as the morph-target GLB;
- one animation: per bone a `rotation` channel (float32 VEC4 x, y, z, w unit quaternions) and a `translation`
  channel (float32 VEC3, the joint's local translation), LINEAR samplers sharing one input accessor (frame k at
  k / fps, min/max). Each key is our blended pose of that frame (`bones.blend_poses`), so a client that plays the
  file shows exactly our blend at frame times and glTF's interpolation (slerp, lerp) between them.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pygltflib as gl

from visemeflow.animation.bones import BoneRig, blend_poses
from visemeflow.animation.gltf import _Layout, vertex_normals
from visemeflow.atomic import atomic_path
from visemeflow.rig.gltf import srgb_to_linear

__all__ = ["write_skinned_glb"]

_ROUGHNESS = 0.6


def frame_times(n_frames: int, fps: float) -> np.ndarray:
    fps = float(fps)
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"frames per second must be a positive number, got {fps}")
    times = (np.arange(n_frames, dtype=np.float64) / fps).astype(np.float32)
    if n_frames > 1 and not (np.diff(times) > 0).all():
        raise ValueError(f"{n_frames} frames at {fps} fps: frame times are not distinct in float32")
    return times


def write_skinned_glb(path: str | os.PathLike, rig: BoneRig, curves, fps: float, *, name: str | None = None
                      ) -> Path:
    """Write `rig` animated by (T, 16) `curves` (frame k at k / fps) as a skinned GLB at `path` (atomically)."""
    path = Path(path)
    rig = rig.in_metres()   # glTF's unit (the demo rig is in centimetres)
    rotations, translations = blend_poses(rig, curves)        # (T, B, 4) w, x, y, z; (T, B, 3)
    times = frame_times(len(rotations), fps)
    label = name or rig.name
    gltf = gl.GLTF2(asset=gl.Asset(generator=f"visemeflow bones (pygltflib {gl.__version__})", version="2.0"))
    layout = _Layout(gltf)

    neutral = np.ascontiguousarray(rig.neutral, np.float32)
    n_joints = rig.n_bones + 1
    attributes = gl.Attributes(
        POSITION=layout.accessor(neutral, gl.VEC3, target=gl.ARRAY_BUFFER, bounds=True),
        NORMAL=layout.accessor(vertex_normals(neutral, rig.faces), gl.VEC3, target=gl.ARRAY_BUFFER))
    if rig.vertex_colors is not None:
        attributes.COLOR_0 = layout.accessor(srgb_to_linear(rig.vertex_colors), gl.VEC3, target=gl.ARRAY_BUFFER)
    joint_dtype = np.uint8 if n_joints <= 256 else np.uint16
    weights = np.ascontiguousarray(rig.weights, np.float32)
    skin_joints = np.where(weights > 0, rig.joints + 1, 0).astype(joint_dtype)     # skin joint 0 is the root
    attributes.JOINTS_0 = layout.accessor(skin_joints, gl.VEC4, target=gl.ARRAY_BUFFER)
    attributes.WEIGHTS_0 = layout.accessor(weights, gl.VEC4, target=gl.ARRAY_BUFFER)
    index_dtype = np.uint16 if rig.n_vertices <= 0xFFFF else np.uint32
    indices = layout.accessor(np.asarray(rig.faces).astype(index_dtype).ravel(), gl.SCALAR,
                              target=gl.ELEMENT_ARRAY_BUFFER)
    gltf.materials.append(gl.Material(name="skin", pbrMetallicRoughness=gl.PbrMetallicRoughness(
        baseColorFactor=[1.0, 1.0, 1.0, 1.0], metallicFactor=0.0, roughnessFactor=_ROUGHNESS)))
    gltf.meshes.append(gl.Mesh(name=rig.name, primitives=[gl.Primitive(
        attributes=attributes, indices=indices, material=0, mode=gl.TRIANGLES)]))

    bone_nodes = list(range(2, 2 + rig.n_bones))
    gltf.nodes.append(gl.Node(name=rig.name, mesh=0, skin=0))
    gltf.nodes.append(gl.Node(name=BoneRig.ROOT, children=bone_nodes))
    for bone, head in zip(rig.bone_names, rig.bind_translations):
        gltf.nodes.append(gl.Node(name=bone, translation=[float(x) for x in np.float32(head)]))
    gltf.scenes.append(gl.Scene(name=rig.name, nodes=[0, 1]))
    gltf.scene = 0

    # column-major MAT4: the transpose of each row-major matrix, flattened; the bind heads as float32, as stored
    inverse_bind = np.tile(np.eye(4), (n_joints, 1, 1))
    inverse_bind[1:, :3, 3] = -np.asarray(rig.bind_translations, np.float32)
    ibm = layout.accessor(np.ascontiguousarray(inverse_bind.transpose(0, 2, 1).reshape(n_joints, 16), np.float32),
                          gl.MAT4)
    gltf.skins.append(gl.Skin(name=f"{rig.name} bones", inverseBindMatrices=ibm, skeleton=1,
                              joints=[1, *bone_nodes]))

    time_accessor = layout.accessor(times, gl.SCALAR, bounds=True)
    xyzw = np.ascontiguousarray(rotations[..., [1, 2, 3, 0]], np.float64)
    xyzw /= np.linalg.norm(xyzw, axis=-1, keepdims=True)
    samplers, channels = [], []
    for b, node in enumerate(bone_nodes):
        for kind, values in ((gl.VEC4, xyzw[:, b]), (gl.VEC3, translations[:, b])):
            output = layout.accessor(np.ascontiguousarray(values, np.float32), kind)
            samplers.append(gl.AnimationSampler(input=time_accessor, output=output, interpolation=gl.ANIM_LINEAR))
            channels.append(gl.AnimationChannel(sampler=len(samplers) - 1, target=gl.AnimationChannelTarget(
                node=node, path="rotation" if kind == gl.VEC4 else "translation")))
    gltf.animations.append(gl.Animation(name=label, samplers=samplers, channels=channels))
    layout.finish()
    with atomic_path(path) as tmp:
        gltf.save_binary(tmp)
    return path
