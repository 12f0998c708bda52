"""glTF 2.0 characters: read a mesh with named morph targets, write it back as a GLB that plays a weight animation.

Both directions go through pygltflib's typed model (`GLTF2`, `Accessor`, `BufferView`, ...); this module lays out
the one binary buffer and computes what the specification asks of it, pygltflib writes and reads the container.

Writing (`write_glb`): one scene, one node, one mesh with one triangle primitive, in metres as glTF defines its
unit (`Character.in_metres`: the demo rig's centimetres are scaled by 0.01):

- `POSITION` (float32 VEC3, min/max), `NORMAL` (unit, area-weighted vertex normals of the neutral; a vertex on no
  triangle or only on degenerate ones gets +Z) and `indices` (uint16, or uint32 when the mesh has 65,535 vertices
  or more: 65,535 is the primitive-restart value uint16 indices may not hold);
- `COLOR_0` when the character has vertex colours: float32 VEC3, *linear* RGB as glTF defines it (3.7.2.1), i.e.
  `srgb_to_linear` of our sRGB display colours, so a viewer shows the colours the preview shows; the reader turns
  them back (to float32 rounding);
- one material, "skin": PBR metallic-roughness with a white base colour, metallic 0, roughness 0.6 (the glTF
  defaults, metallic 1 and no material, show a dark grey metal); the vertex colours multiply the base colour
  (three.js's GLTFLoader turns on `vertexColors` when COLOR_0 is there);
- one morph target per shape, `POSITION` deltas only (float32 VEC3 with the min/max the specification requires),
  names in `mesh.extras.targetNames` (three.js, Blender) and in the primitive's `extras.targetNames` (Babylon and
  others read that one); `mesh.weights` all zero. A target is written as a sparse accessor (no buffer view: zeros,
  then the rows of the vertices it moves, found by an exact-zero test, and their ids) when that is smaller than
  the dense array; min/max are those of the values after substitution, as the specification asks;
- one animation with one `weights` channel on the node: LINEAR sampler, input = the T frame times k / fps (float32,
  min/max), output = the T x S weights frame by frame.

Every accessor has its own buffer view (a sparse one two), 4-byte aligned; vertex views target ARRAY_BUFFER, the
index view ELEMENT_ARRAY_BUFFER, sparse ids and values and animation views none. Morph targets carry no NORMAL
deltas: a viewer shades the moving mouth with the neutral's normals (adding them would double the file for a
shading detail).

`write_glb` is for characters that are not glTF scenes (and for tests); a character read from a glTF scene is
written back as its own whole asset with the clip added (`gltf_asset.write_character_glb` chooses).

Reading (`read_character_glb`): a glTF scene as one character, through the rig layer's glTF reader
(`rig.gltf.GltfScene`: every mesh described, the chosen ones read with primitives joined, sparse / strided /
quantized accessors, target names from `extras.targetNames`, COLOR_0 as vertex colours, and placed by their node's
world transform or their skin's rest pose), whose `RigError`s become `CharacterError`s naming the file; which
meshes are driven is in the function's doc; `validate_character` checks the rest.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pygltflib as gl

from visemeflow.rig.character import Character, CharacterError, CharacterPart, make_character, \
    validate_character
from visemeflow.shapes.conventions import CONVENTION_NAMES, normalize_shape_name
from visemeflow.atomic import atomic_path
from visemeflow.rig import RigError
from visemeflow.rig.gltf import MAX_MORPH_VALUES, MAX_VERTICES, GltfMeshInfo, GltfScene, read_gltf_mesh, \
    srgb_to_linear

__all__ = ["GLTF_SUFFIXES", "read_character_glb", "vertex_normals", "write_glb"]

GLTF_SUFFIXES = (".glb", ".gltf", ".vrm")
"""Characters read as glTF scenes: a .vrm (VRoid and other VRM avatars) is a GLB with VRM's extensions."""

_ALIGN = 4
_MATERIAL = "skin"
_ROUGHNESS = 0.6
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


def _bounds(columns: np.ndarray) -> tuple[list[float], list[float]]:
    """Per-component min and max of (width, count) float32 columns, as JSON-exact floats."""
    # float(float32) is the exact value; JSON's shortest repr of that double reads back to it exactly
    return [float(x) for x in columns.min(axis=1)], [float(x) for x in columns.max(axis=1)]


class _Layout:
    """The binary buffer being laid out: one buffer view per array, each starting on a 4-byte boundary."""

    def __init__(self, gltf: gl.GLTF2):
        self.gltf = gltf
        self.parts: list[memoryview | bytes] = []
        self.offset = 0

    def view(self, data: np.ndarray, target: int | None = None) -> int:
        """Append contiguous little-endian `data` as a buffer view; its index."""
        self.parts.append(memoryview(data).cast("B"))
        padding = -data.nbytes % _ALIGN
        if padding:
            self.parts.append(bytes(padding))
        self.gltf.bufferViews.append(gl.BufferView(buffer=0, byteOffset=self.offset, byteLength=data.nbytes,
                                                   target=target))
        self.offset += data.nbytes + padding
        return len(self.gltf.bufferViews) - 1

    def accessor(self, array: np.ndarray, kind: str, *, target: int | None = None, bounds: bool = False) -> int:
        """Append `array` ((count,) or (count, width), little-endian) as a view and an accessor; its index."""
        data = np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("<"))
        component = next(c for c, d in _COMPONENT_DTYPES.items() if d == data.dtype)
        count = data.shape[0]
        accessor = gl.Accessor(bufferView=self.view(data, target), byteOffset=0, componentType=component,
                               count=count, type=kind)
        if bounds:
            # one contiguous row per component: numpy reduces those ~15x faster than the columns of a (count, 3)
            accessor.min, accessor.max = _bounds(np.ascontiguousarray(data.reshape(count, -1).T))
        self.gltf.accessors.append(accessor)
        return len(self.gltf.accessors) - 1

    def sparse_vec3(self, values: np.ndarray) -> int | None:
        """(V, 3) float32 `values` as a sparse accessor over zeros (glTF 2.0 3.6.2.3): the ids of the rows with a
        non-zero component (strictly increasing, the smallest unsigned type that holds V - 1) and those rows, each
        in its own untargeted view; min/max of the values after substitution, as the specification asks. None when
        that is not smaller than the dense array (then the caller writes it dense)."""
        count = len(values)
        columns = np.ascontiguousarray(values.T, dtype=np.float32)     # (3, V): numpy scans rows much faster
        moved = np.flatnonzero((columns[0] != 0) | (columns[1] != 0) | (columns[2] != 0))
        id_dtype = np.dtype("<u1") if count <= 0x100 else np.dtype("<u2") if count <= 0x10000 else np.dtype("<u4")
        n = max(len(moved), 1)      # sparse.count must be >= 1: a shape that moves nothing lists vertex 0's zero
        if n * (id_dtype.itemsize + 12) >= count * 12:
            return None
        if not len(moved):
            moved = np.zeros(1, np.intp)
        rows = np.ascontiguousarray(values[moved], dtype="<f4")
        ids = moved.astype(id_dtype)
        # the rows left out are exact zeros, so the dense columns' bounds are those after substitution (a -0.0 left
        # out reads back as +0.0, the same number)
        low, high = _bounds(columns)
        component = next(c for c, d in _COMPONENT_DTYPES.items() if d == id_dtype)
        sparse = gl.Sparse(count=len(ids),
                           indices=gl.AccessorSparseIndices(bufferView=self.view(ids), byteOffset=0,
                                                            componentType=component),
                           values=gl.AccessorSparseValues(bufferView=self.view(rows), byteOffset=0))
        # no bufferView, so no byteOffset either (the schema makes byteOffset depend on bufferView)
        self.gltf.accessors.append(gl.Accessor(byteOffset=None, componentType=gl.FLOAT, count=count, type=gl.VEC3,
                                               sparse=sparse, min=low, max=high))
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


def write_glb(path: str | os.PathLike, character: Character, weights, fps: float, *, name: str | None = None,
              sparse: bool = True) -> Path:
    """Write `character` with its weight animation as a GLB at `path` (atomically); returns `path`.

    `weights` is (T, S) in [0, 1], T >= 1 frames, columns in `character.shape_names` order; frame k plays at
    k / fps seconds. The animation is named `name`, else the character's name. `sparse=False` writes every morph
    target dense (for a client without sparse accessors); by default a target is sparse when that is smaller.
    """
    path = Path(path)
    validate_character(character)
    if not len(character.faces):
        raise ValueError(f"{character.where()}: no triangles; a glTF mesh needs at least one")
    times, w = _check_animation(character, weights, fps)
    label = name or character.name
    character = character.in_metres()   # glTF's unit (the demo rig is in centimetres)
    gltf = gl.GLTF2(asset=gl.Asset(generator=f"visemeflow (pygltflib {gl.__version__})", version="2.0"))
    layout = _Layout(gltf)

    neutral = np.ascontiguousarray(character.neutral, dtype=np.float32)
    faces = np.asarray(character.faces)
    index_dtype = np.uint16 if character.n_vertices <= 0xFFFF else np.uint32
    position = layout.accessor(neutral, gl.VEC3, target=gl.ARRAY_BUFFER, bounds=True)
    normal = layout.accessor(vertex_normals(neutral, faces), gl.VEC3, target=gl.ARRAY_BUFFER)
    indices = layout.accessor(faces.astype(index_dtype).ravel(), gl.SCALAR, target=gl.ELEMENT_ARRAY_BUFFER)
    attributes = gl.Attributes(POSITION=position, NORMAL=normal)
    if character.vertex_colors is not None:
        attributes.COLOR_0 = layout.accessor(srgb_to_linear(character.vertex_colors), gl.VEC3, target=gl.ARRAY_BUFFER)
    deltas = np.ascontiguousarray(character.deltas, dtype=np.float32)
    targets = []
    for d in deltas:
        target = layout.sparse_vec3(d) if sparse else None
        if target is None:
            target = layout.accessor(d, gl.VEC3, target=gl.ARRAY_BUFFER, bounds=True)
        targets.append(gl.Attributes(POSITION=target))
    names = list(character.shape_names)
    gltf.materials.append(gl.Material(name=_MATERIAL, pbrMetallicRoughness=gl.PbrMetallicRoughness(
        baseColorFactor=[1.0, 1.0, 1.0, 1.0], metallicFactor=0.0, roughnessFactor=_ROUGHNESS)))
    primitive = gl.Primitive(attributes=attributes, indices=indices, material=0, mode=gl.TRIANGLES, targets=targets,
                             extras={"targetNames": names})
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
_CONVENTION_KEYS = frozenset(normalize_shape_name(n) for names in CONVENTION_NAMES.values() for n in names)


def _mesh_summary(info: GltfMeshInfo, names: int = 0) -> str:
    """`Head (2,162 v, 67 targets)`, with the first `names` target names when asked."""
    if not info.n_targets:
        targets = "no targets"
    elif info.target_names is None:
        targets = f"{info.n_targets} targets without names"
    else:
        shown = ", ".join(info.target_names[:names]) + (" ..." if info.n_targets > names else "")
        targets = f"{info.n_targets} targets" + (f": {shown}" if names else "")
    return f"{info.label} ({info.n_vertices:,} v, {targets})"


def _choose_meshes(path: Path, infos: list[GltfMeshInfo], meshes, extra_names) -> tuple[list, list[str]]:
    """(the driven meshes' infos, primary first; "label (why)" of each other mesh). See `read_character_glb`."""
    listing = "; ".join(_mesh_summary(i) for i in infos)
    if meshes:
        chosen = []
        for wanted in dict.fromkeys(meshes):
            hits = [i for i in infos if wanted in (i.label, str(i.index))] or \
                [i for i in infos if wanted in i.node_names]
            if not hits:
                raise CharacterError(f"{path}: no mesh {wanted!r}; its meshes: {listing}")
            for info in hits:
                if not info.n_targets:
                    raise CharacterError(f"{path}: mesh {info.label!r} has no morph targets; its meshes: {listing}")
                if info.target_names is None:
                    raise CharacterError(f"{path}: mesh {info.label!r} has {info.n_targets} morph targets but no "
                                         "names (mesh.extras.targetNames or the primitive's extras.targetNames)")
                if info not in chosen:
                    chosen.append(info)
        return chosen, [_left_out(i, "not asked for") for i in infos if i not in chosen]
    keys = _CONVENTION_KEYS | {normalize_shape_name(n) for n in extra_names or ()}
    named = [i for i in infos if i.n_targets and i.target_names is not None]
    if any(i.nodes for i in named):
        named = [i for i in named if i.nodes]
    if not named:
        unnamed = [i for i in infos if i.n_targets]
        if unnamed:   # the reader names the first such mesh and what it expected
            read_gltf_mesh(path)
        raise CharacterError(f"{path}: no mesh has morph targets ({len(infos)} meshes: {listing}); a character "
                             "needs its blendshapes as glTF morph targets")
    usable = {i.index: {n for n in i.target_names if normalize_shape_name(n) in keys} for i in named}
    if any(usable.values()):
        primary = max(named, key=lambda i: (len(usable[i.index]), i.n_vertices, -named.index(i)))
        keys_of = {i.index: {normalize_shape_name(n) for n in usable[i.index]} for i in named}
        chosen = [primary] + [i for i in named if i is not primary and keys_of[i.index] & keys_of[primary.index]]
    elif len(named) == 1:     # one mesh of other names: a mapping CSV may drive them, `bind` says if none does
        chosen = named
    else:
        raise CharacterError(
            f"{path}: no mesh has morph targets visemeflow can drive (ARKit, Oculus viseme or visemeflow names, or "
            f"a mapping CSV's); its meshes: {'; '.join(_mesh_summary(i, 6) for i in infos)}; choose meshes with "
            "--mesh and give a mapping CSV (viseme,shape,weight)")
    left_out = []
    for i in infos:
        if i in chosen:
            continue
        if not i.n_targets:
            why = "no targets"
        elif i.target_names is None:
            why = "targets without names"
        elif not i.nodes and i not in named:
            why = "no node uses it"
        elif usable.get(i.index):
            why = f"targets share nothing with {chosen[0].label}'s"
        else:
            shown = ", ".join(i.target_names[:4]) + (" ..." if i.n_targets > 4 else "")
            why = f"targets {shown}: none usable"
        left_out.append(_left_out(i, why))
    return chosen, left_out


def _left_out(info: GltfMeshInfo, why: str) -> str:
    """`Body (mesh Wolf3D_Body; no targets)`: the object's name first when the mesh's is another, then why."""
    node = _node_name(info)
    return f"{node} (mesh {info.label}; {why})" if node else f"{info.label} ({why})"


def _node_name(info: GltfMeshInfo) -> str:
    """The name of the mesh's first node (the object Blender and the engines show) when it differs from the mesh's,
    else ""."""
    node = info.node_names[0] if info.node_names else ""
    return node if node != info.label else ""


def _check_sizes(path: Path, chosen: list[GltfMeshInfo]) -> None:
    """The driven meshes together, as their accessors declare them, fit `MAX_VERTICES` and `MAX_MORPH_VALUES`
    (the joined deltas are shapes x vertices x 3); CharacterError naming the meshes otherwise."""
    n_vertices = sum(i.n_vertices for i in chosen)
    n_shapes = len({n for i in chosen for n in i.target_names or ()})
    meshes = ", ".join(_mesh_summary(i) for i in chosen)
    if n_vertices > MAX_VERTICES:
        raise CharacterError(f"{path}: the driven meshes have {n_vertices} vertices together, more than the "
                             f"{MAX_VERTICES} visemeflow animates ({meshes})")
    if n_shapes * n_vertices * 3 > MAX_MORPH_VALUES:
        raise CharacterError(f"{path}: the driven meshes' {n_shapes} morph targets on {n_vertices} vertices are "
                             f"{n_shapes * n_vertices * 3} values, more than the {MAX_MORPH_VALUES} visemeflow "
                             f"reads (shapes x vertices x 3; {meshes})")


def read_character_glb(path: str | os.PathLike, name: str | None = None, meshes=None,
                       extra_names=None) -> Character:
    """The character of a .glb / .gltf scene: every mesh whose morph targets it drives, as one character; validated.

    Which meshes (avatars split the face into head, teeth, tongue, eyes, beard, all with the same target names):
    `meshes` (mesh names, else names of the nodes that instance them, or mesh indices as text) when given; else the mesh
    with the most usable target names (a known convention's: ARKit 52, Oculus visemes, ours; or `extra_names`, a
    mapping CSV's shapes) and every mesh that shares a usable name with it. Meshes used by a node are preferred
    over meshes no node uses. A scene with a single mesh with targets drives it whatever its names. The others are
    not driven and listed in `Character.left_out` with why: no targets, nothing usable, nothing shared.

    The joined arrays (neutral, faces, deltas, colours) put the parts together as the scene shows them: each part
    read by `rig.gltf` (primitives joined, sparse / strided / quantized accessors, target names from
    `extras.targetNames`, COLOR_0) and placed by `GltfScene.placed_mesh` (node world transform, or the skin's rest
    pose for a skinned mesh; a mesh instanced by several nodes is placed by the first). Shapes are the union of the
    parts' target names (the first part's order, then new names in part order); `Character.parts` keeps each
    part's vertex range and its own target order, which the exported GLB animates (`gltf_asset`).

    Its name: `name`, else the single driven mesh's name, else the file's stem. Raises CharacterError naming the
    file: not glTF 2.0, compressed geometry (Draco, meshopt), no mesh, no mesh with targets, several meshes with
    targets none of which is usable, a `meshes` entry that is not there (the error lists the meshes), targets
    without names, primitives other than triangles, targets that differ between primitives, or data that
    `validate_character` rejects.
    """
    path = Path(path)
    try:
        scene = GltfScene(path)
        if not scene.meshes:
            raise RigError(f"{path}: no mesh in this glTF file")
        chosen, left_out = _choose_meshes(path, scene.meshes, meshes, extra_names)
        _check_sizes(path, chosen)
        placed = [(info, *scene.placed_mesh(info.index)) for info in chosen]
    except RigError as exc:   # its message starts with the path
        message = str(exc)
        raise CharacterError(message if str(path) in message else f"{path}: {message}") from None
    for info, mesh, *_ in placed:
        seen: dict[str, int] = {}
        for k, n in enumerate(mesh.target_names):
            if n in seen:
                raise CharacterError(f"{path}: mesh {info.label!r}: the shape name {n!r} is used twice (targets "
                                     f"{seen[n]} and {k})")
            seen[n] = k
    names = list(dict.fromkeys(n for _, mesh, *_ in placed for n in mesh.target_names))
    column = {n: k for k, n in enumerate(names)}
    n_vertices = sum(len(neutral) for _, _, neutral, _, _ in placed)
    deltas = np.zeros((len(names), n_vertices, 3), np.float32)
    parts, positions, faces, colors, start = [], [], [], [], 0
    for info, mesh, neutral, part_deltas, how in placed:
        stop = start + len(neutral)
        deltas[[column[n] for n in mesh.target_names], start:stop] = part_deltas
        positions.append(neutral)
        faces.append(mesh.faces + start)
        colors.append(mesh.colors)
        parts.append(CharacterPart(mesh=info.index, nodes=info.nodes, name=info.label, start=start, stop=stop,
                                   target_names=tuple(mesh.target_names), placement=how, node_name=_node_name(info)))
        start = stop
    rgb = None
    if any(c is not None for c in colors):
        rgb = np.concatenate([np.ones((len(p), 3), np.float32) if c is None else c for p, c in zip(positions, colors)])
    label = name or (placed[0][1].name if len(placed) == 1 else None) or path.stem
    return make_character(label, np.concatenate(positions), np.concatenate(faces), names, deltas, source=path,
                          vertex_colors=rgb, parts=parts, left_out=left_out)
