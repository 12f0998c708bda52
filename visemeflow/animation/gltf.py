"""glTF 2.0 characters: read a mesh with named morph targets, write it back as a GLB that plays a weight animation.

Both directions go through pygltflib's typed model (`GLTF2`, `Accessor`, `BufferView`, ...); this module lays out
the one binary buffer and computes what the specification asks of it, pygltflib writes and reads the container.

Writing (`write_glb`): one scene, one node, one mesh with one triangle primitive:

- `POSITION` (float32 VEC3, min/max), `NORMAL` (unit, area-weighted vertex normals of the neutral; a vertex on no
  triangle or only on degenerate ones gets +Z) and `indices` (uint16, or uint32 when the mesh has 65,535 vertices
  or more: 65,535 is the primitive-restart value uint16 indices may not hold);
- one morph target per shape, `POSITION` deltas only (float32 VEC3 with the min/max the specification requires),
  names in `mesh.extras.targetNames` (three.js, Blender) and in the primitive's `extras.targetNames` (Babylon and
  others read that one); `mesh.weights` all zero;
- one animation with one `weights` channel on the node: LINEAR sampler, input = the T frame times k / fps (float32,
  min/max), output = the T x S weights frame by frame.

Every accessor has its own buffer view, 4-byte aligned; vertex views target ARRAY_BUFFER, the index view
ELEMENT_ARRAY_BUFFER, animation views none. Morph targets carry no NORMAL deltas: a viewer shades the moving mouth
with the neutral's normals (adding them would double the file for a shading detail).

Reading (`read_character_glb`): a thin wrapper over the rig layer's glTF reader, `rig.gltf.read_gltf_mesh` (the
first mesh with morph targets in scene order, primitives joined, sparse / strided / quantized accessors, target
names from `extras.targetNames`, COLOR_0 as vertex colours; node transforms not applied), whose `RigError`s become
`CharacterError`s naming the file; `validate_character` checks the rest.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pygltflib as gl

from visemeflow.animation.character import Character, CharacterError, make_character, validate_character
from visemeflow.atomic import atomic_path
from visemeflow.rig import RigError
from visemeflow.rig.gltf import read_gltf_mesh

__all__ = ["read_character_glb", "vertex_normals", "write_glb"]

_ALIGN = 4
_COMPONENT_DTYPES = {
    gl.BYTE: np.dtype("<i1"), gl.UNSIGNED_BYTE: np.dtype("<u1"), gl.SHORT: np.dtype("<i2"),
    gl.UNSIGNED_SHORT: np.dtype("<u2"), gl.UNSIGNED_INT: np.dtype("<u4"), gl.FLOAT: np.dtype("<f4"),
}


# ---- writing -----------------------------------------------------------------------------------------------
def vertex_normals(neutral: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) float32 unit normals: the area-weighted sum of the normals of each vertex's triangles; +Z for a
    vertex on no triangle (or only on degenerate ones), so that every normal is a unit vector."""
    v = np.asarray(neutral, dtype=np.float64)
    f = np.asarray(faces, dtype=np.intp)
    n_vertices = len(v)
    normals = np.zeros((n_vertices, 3))
    if len(f):
        face_normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])   # length = 2 x area
        corners = f.ravel()
        for axis in range(3):
            normals[:, axis] = np.bincount(corners, weights=np.repeat(face_normals[:, axis], 3),
                                           minlength=n_vertices)
    length = np.linalg.norm(normals, axis=1)
    ok = length > 1e-30
    normals[ok] /= length[ok, None]
    normals[~ok] = (0.0, 0.0, 1.0)
    return normals.astype(np.float32)


class _Layout:
    """The binary buffer being laid out: one buffer view per accessor, each starting on a 4-byte boundary."""

    def __init__(self, gltf: gl.GLTF2):
        self.gltf = gltf
        self.parts: list[memoryview | bytes] = []
        self.offset = 0

    def accessor(self, array: np.ndarray, kind: str, *, target: int | None = None, bounds: bool = False) -> int:
        """Append `array` ((count,) or (count, width), little-endian) as a view and an accessor; its index."""
        data = np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("<"))
        component = next(c for c, d in _COMPONENT_DTYPES.items() if d == data.dtype)
        count = data.shape[0]
        self.parts.append(memoryview(data).cast("B"))
        padding = -data.nbytes % _ALIGN
        if padding:
            self.parts.append(bytes(padding))
        self.gltf.bufferViews.append(gl.BufferView(buffer=0, byteOffset=self.offset, byteLength=data.nbytes,
                                                   target=target))
        self.offset += data.nbytes + padding
        accessor = gl.Accessor(bufferView=len(self.gltf.bufferViews) - 1, byteOffset=0, componentType=component,
                               count=count, type=kind)
        if bounds:
            # one contiguous row per component: numpy reduces those ~15x faster than the columns of a (count, 3)
            columns = np.ascontiguousarray(data.reshape(count, -1).T)
            # float(float32) is the exact value; JSON's shortest repr of that double reads back to it exactly
            accessor.min = [float(x) for x in columns.min(axis=1)]
            accessor.max = [float(x) for x in columns.max(axis=1)]
        self.gltf.accessors.append(accessor)
        return len(self.gltf.accessors) - 1

    def finish(self) -> None:
        blob = b"".join(self.parts)
        self.gltf.buffers = [gl.Buffer(byteLength=len(blob))]
        self.gltf.set_binary_blob(blob)


def _check_animation(character: Character, weights, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """(frame times float32 (T,), weights float32 (T, S)); ValueError naming what is wrong."""
    w = np.asarray(weights)
    if w.ndim != 2 or w.shape[1] != character.n_shapes or w.shape[0] < 1:
        raise ValueError(f"{character.where()}: weights must be (T >= 1, {character.n_shapes}) in the order of "
                         f"its shapes, got {w.shape}")
    w = np.ascontiguousarray(w, dtype=np.float32)
    if not np.isfinite(w).all():
        raise ValueError(f"{character.where()}: weights hold NaN or infinite values")
    if w.min() < 0.0 or w.max() > 1.0:
        raise ValueError(f"{character.where()}: weights must lie in [0, 1], got {w.min()}..{w.max()}")
    fps = float(fps)
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"frames per second must be a positive number, got {fps}")
    times = (np.arange(len(w), dtype=np.float64) / fps).astype(np.float32)
    if len(times) > 1 and not (np.diff(times) > 0).all():
        raise ValueError(f"{len(w)} frames at {fps} fps: frame times are not distinct in float32")
    return times, w


def write_glb(path: str | os.PathLike, character: Character, weights, fps: float, *, name: str | None = None) -> Path:
    """Write `character` with its weight animation as a GLB at `path` (atomically); returns `path`.

    `weights` is (T, S) in [0, 1], T >= 1 frames, columns in `character.shape_names` order; frame k plays at
    k / fps seconds. The animation is named `name`, else the character's name.
    """
    path = Path(path)
    validate_character(character)
    if not len(character.faces):
        raise ValueError(f"{character.where()}: no triangles; a glTF mesh needs at least one")
    times, w = _check_animation(character, weights, fps)
    label = name or character.name
    gltf = gl.GLTF2(asset=gl.Asset(generator=f"visemeflow (pygltflib {gl.__version__})", version="2.0"))
    layout = _Layout(gltf)

    neutral = np.ascontiguousarray(character.neutral, dtype=np.float32)
    faces = np.asarray(character.faces)
    index_dtype = np.uint16 if character.n_vertices <= 0xFFFF else np.uint32
    position = layout.accessor(neutral, gl.VEC3, target=gl.ARRAY_BUFFER, bounds=True)
    normal = layout.accessor(vertex_normals(neutral, faces), gl.VEC3, target=gl.ARRAY_BUFFER)
    indices = layout.accessor(faces.astype(index_dtype).ravel(), gl.SCALAR, target=gl.ELEMENT_ARRAY_BUFFER)
    deltas = np.ascontiguousarray(character.deltas, dtype=np.float32)
    targets = [gl.Attributes(POSITION=layout.accessor(d, gl.VEC3, target=gl.ARRAY_BUFFER, bounds=True))
               for d in deltas]
    names = list(character.shape_names)
    primitive = gl.Primitive(attributes=gl.Attributes(POSITION=position, NORMAL=normal), indices=indices,
                             mode=gl.TRIANGLES, targets=targets, extras={"targetNames": names})
    gltf.meshes.append(gl.Mesh(name=character.name, primitives=[primitive], weights=[0.0] * len(names),
                               extras={"targetNames": names}))
    gltf.nodes.append(gl.Node(name=character.name, mesh=0))
    gltf.scenes.append(gl.Scene(name=character.name, nodes=[0]))
    gltf.scene = 0

    frame_times = layout.accessor(times, gl.SCALAR, bounds=True)
    values = layout.accessor(w.ravel(), gl.SCALAR)
    gltf.animations.append(gl.Animation(
        name=label,
        samplers=[gl.AnimationSampler(input=frame_times, output=values, interpolation=gl.ANIM_LINEAR)],
        channels=[gl.AnimationChannel(sampler=0, target=gl.AnimationChannelTarget(node=0, path=gl.WEIGHTS))]))
    layout.finish()
    with atomic_path(path) as tmp:
        gltf.save_binary(tmp)
    return path


# ---- reading -----------------------------------------------------------------------------------------------
def read_character_glb(path: str | os.PathLike, name: str | None = None) -> Character:
    """The character of a .glb / .gltf: its first mesh with morph targets, read by `rig.gltf.read_gltf_mesh`
    (see that module for which mesh and how), COLOR_0 as its vertex colours; validated.

    Its name: `name`, else the mesh's name, else the file's stem. Raises CharacterError naming the file when it is
    not glTF 2.0, has no mesh, no mesh with morph targets, no target names (`extras.targetNames`), primitives other
    than triangles, targets that differ between primitives, or data that `validate_character` rejects.
    """
    path = Path(path)
    try:
        mesh = read_gltf_mesh(path)
    except RigError as exc:   # its message starts with the path
        message = str(exc)
        raise CharacterError(message if str(path) in message else f"{path}: {message}") from None
    if not mesh.target_names:
        raise CharacterError(f"{path}: no mesh has morph targets ({mesh.n_meshes} meshes); a character needs its "
                             "blendshapes as glTF morph targets")
    return make_character(name or mesh.name or path.stem, mesh.neutral, mesh.faces, mesh.target_names,
                          mesh.deltas, source=path, vertex_colors=mesh.colors)
