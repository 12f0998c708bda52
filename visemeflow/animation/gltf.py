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

Reading (`read_character_glb`): the first mesh with morph targets, in scene order (the default scene's node tree,
then the other scenes and loose nodes), else in mesh order. Every primitive must be TRIANGLES and carry the same
number of targets; primitives are joined into one vertex array (primitives that share their POSITION and target
accessors share their vertices). Accessors may be strided, sparse, or integer (normalized or not, as
KHR_mesh_quantization allows). Target names come from `mesh.extras.targetNames`, else the first primitive's.
Node transforms are not applied: the character stays in mesh space. Buffers may be the GLB's binary chunk, data
URIs or files beside a .gltf. Every problem is a `CharacterError` that names the file.
"""

from __future__ import annotations

import json
import os
import struct
import warnings
from pathlib import Path

import numpy as np
import pygltflib as gl

from visemeflow.animation.character import Character, CharacterError, make_character, validate_character
from visemeflow.atomic import atomic_path

__all__ = ["read_character_glb", "vertex_normals", "write_glb"]

_ALIGN = 4
_GLB_MAGIC = b"glTF"
_COMPONENT_DTYPES = {
    gl.BYTE: np.dtype("<i1"), gl.UNSIGNED_BYTE: np.dtype("<u1"), gl.SHORT: np.dtype("<i2"),
    gl.UNSIGNED_SHORT: np.dtype("<u2"), gl.UNSIGNED_INT: np.dtype("<u4"), gl.FLOAT: np.dtype("<f4"),
}
_INDEX_TYPES = (gl.UNSIGNED_BYTE, gl.UNSIGNED_SHORT, gl.UNSIGNED_INT)
_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
_MODES = {gl.POINTS: "POINTS", gl.LINES: "LINES", gl.LINE_LOOP: "LINE_LOOP", gl.LINE_STRIP: "LINE_STRIP",
          gl.TRIANGLES: "TRIANGLES", gl.TRIANGLE_STRIP: "TRIANGLE_STRIP", gl.TRIANGLE_FAN: "TRIANGLE_FAN"}


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
class _Reader:
    """Accessors of one loaded glTF as numpy arrays; every error names the file."""

    def __init__(self, path: Path, gltf: gl.GLTF2):
        self.path = path
        self.gltf = gltf
        self.buffers: dict[int, bytes] = {}

    def fail(self, message: str) -> CharacterError:
        return CharacterError(f"{self.path}: {message}")

    def buffer(self, index: int) -> bytes:
        if index not in self.buffers:
            if not 0 <= index < len(self.gltf.buffers):
                raise self.fail(f"buffer {index} does not exist ({len(self.gltf.buffers)} buffers)")
            uri = self.gltf.buffers[index].uri
            if uri is not None and not uri.startswith("data:") and ("://" in uri or Path(uri).is_absolute()):
                raise self.fail(f"buffer {index}: only data: URIs and files beside the glTF are read, not {uri!r}")
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    data = self.gltf.get_data_from_buffer_uri(uri)
            except (OSError, ValueError) as exc:
                raise self.fail(f"buffer {index} ({uri or 'GLB binary chunk'}) cannot be read: {exc}") from None
            if data is None:
                raise self.fail(f"buffer {index} ({uri or 'GLB binary chunk'}) is missing")
            self.buffers[index] = bytes(data)
        return self.buffers[index]

    def _elements(self, view_index: int, byte_offset: int, count: int, width: int, dtype: np.dtype,
                  what: str) -> np.ndarray:
        if view_index is None or not 0 <= view_index < len(self.gltf.bufferViews):
            raise self.fail(f"{what}: buffer view {view_index} does not exist")
        view = self.gltf.bufferViews[view_index]
        data = self.buffer(view.buffer)
        element = width * dtype.itemsize
        stride = view.byteStride or element
        start = (view.byteOffset or 0) + (byte_offset or 0)
        needed = (count - 1) * stride + element if count else 0
        if (byte_offset or 0) + needed > view.byteLength or (view.byteOffset or 0) + view.byteLength > len(data):
            raise self.fail(f"{what}: {count} elements of {element} bytes lie outside buffer view {view_index}")
        if count == 0:
            return np.zeros((0, width), dtype)
        if stride == element:
            return np.frombuffer(data, dtype, count * width, start).reshape(count, width)
        return np.ndarray((count, width), dtype, buffer=data, offset=start, strides=(stride, dtype.itemsize))

    def accessor(self, index: int, what: str, types: tuple[str, ...]) -> np.ndarray:
        """(count, width) in the accessor's own component type, sparse values applied."""
        if index is None or not 0 <= index < len(self.gltf.accessors):
            raise self.fail(f"{what}: accessor {index} does not exist")
        acc = self.gltf.accessors[index]
        what = f"{what} (accessor {index})"
        if acc.type not in types or acc.componentType not in _COMPONENT_DTYPES:
            raise self.fail(f"{what}: expected {' or '.join(types)}, got {acc.type} of component type "
                            f"{acc.componentType}")
        dtype, width, count = _COMPONENT_DTYPES[acc.componentType], _WIDTHS[acc.type], int(acc.count or 0)
        if acc.bufferView is None:
            values = np.zeros((count, width), dtype)
        else:
            values = self._elements(acc.bufferView, acc.byteOffset, count, width, dtype, what)
        sparse = acc.sparse
        if sparse is not None and sparse.count:
            if sparse.indices.componentType not in _INDEX_TYPES:
                raise self.fail(f"{what}: sparse indices of component type {sparse.indices.componentType}")
            ids = self._elements(sparse.indices.bufferView, sparse.indices.byteOffset, sparse.count, 1,
                                 _COMPONENT_DTYPES[sparse.indices.componentType], f"{what} sparse indices")[:, 0]
            if ids.size and int(ids.max()) >= count:
                raise self.fail(f"{what}: sparse index {int(ids.max())} outside its {count} elements")
            values = np.array(values)                 # a writable copy of the dense part
            values[ids.astype(np.intp)] = self._elements(sparse.values.bufferView, sparse.values.byteOffset,
                                                         sparse.count, width, dtype, f"{what} sparse values")
        return values

    def floats(self, index: int, what: str) -> np.ndarray:
        """A VEC3 accessor as (count, 3) float32: float as is; integers dequantized when normalized (glTF 2.0
        3.11), taken as they are otherwise (KHR_mesh_quantization)."""
        values = self.accessor(index, what, ("VEC3",))
        acc = self.gltf.accessors[index]
        if values.dtype.kind == "f":
            return np.ascontiguousarray(values, dtype=np.float32)
        if acc.normalized:
            info = np.iinfo(values.dtype)
            return np.maximum(values.astype(np.float64) / info.max, -1.0).astype(np.float32)
        return values.astype(np.float32)

    def indices(self, index: int | None, n_vertices: int, what: str) -> np.ndarray:
        if index is None:   # non-indexed: every three vertices are a triangle
            if n_vertices % 3:
                raise self.fail(f"{what}: {n_vertices} vertices without indices are not whole triangles")
            return np.arange(n_vertices, dtype=np.int64).reshape(-1, 3)
        values = self.accessor(index, f"{what} indices", ("SCALAR",))
        if self.gltf.accessors[index].componentType not in _INDEX_TYPES:
            raise self.fail(f"{what} indices (accessor {index}): component type "
                            f"{self.gltf.accessors[index].componentType} is not an unsigned integer")
        if len(values) % 3:
            raise self.fail(f"{what}: {len(values)} indices are not whole triangles")
        ids = values[:, 0].astype(np.int64)
        if ids.size and int(ids.max()) >= n_vertices:
            raise self.fail(f"{what}: index {int(ids.max())} outside its {n_vertices} vertices")
        return ids.reshape(-1, 3)


def _load(path: Path) -> gl.GLTF2:
    """The glTF document (a GLB, or glTF JSON), checked to be glTF 2.x; CharacterError otherwise."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise CharacterError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if data[:4] == _GLB_MAGIC:
                if len(data) < 20:
                    raise ValueError(f"{len(data)} bytes, shorter than a GLB header and its JSON chunk")
                version, length = np.frombuffer(data, "<u4", 2, 4)
                if version != 2:
                    raise ValueError(f"GLB container version {version}, not 2")
                if length > len(data):
                    raise ValueError(f"the header says {length} bytes, the file has {len(data)}: truncated")
                gltf = gl.GLTF2.load_from_bytes(data[:length])
                if gltf is None:
                    raise ValueError("no JSON chunk")
            else:
                document = json.loads(data.decode("utf-8-sig"))
                if not isinstance(document, dict) or not isinstance(document.get("asset"), dict):
                    raise ValueError("no glTF asset object")
                gltf = gl.GLTF2.gltf_from_json(json.dumps(document))
                gltf._path = path.parent
    except (ValueError, TypeError, KeyError, AttributeError, OSError, struct.error) as exc:
        raise CharacterError(f"{path}: not a glTF 2.0 / GLB file ({exc})") from None
    version = str(getattr(gltf.asset, "version", "") or "")
    if not version.startswith("2"):
        raise CharacterError(f"{path}: glTF version {version or '(none)'}; only glTF 2.0 is read")
    return gltf


def _mesh_order(gltf: gl.GLTF2) -> list[int]:
    """Mesh indices: those of nodes in the default scene's tree first (depth first), then the other scenes',
    then nodes in no scene, then meshes no node uses."""
    nodes, meshes = gltf.nodes or [], gltf.meshes or []
    scenes = gltf.scenes or []
    scene_order = ([gltf.scene] if isinstance(gltf.scene, int) and 0 <= gltf.scene < len(scenes) else []) + \
        list(range(len(scenes)))
    seen_nodes: set[int] = set()
    order: list[int] = []

    def visit(node_index: int) -> None:
        stack = [node_index]
        while stack:
            i = stack.pop()
            if not isinstance(i, int) or not 0 <= i < len(nodes) or i in seen_nodes:
                continue
            seen_nodes.add(i)
            node = nodes[i]
            if isinstance(node.mesh, int) and 0 <= node.mesh < len(meshes) and node.mesh not in order:
                order.append(node.mesh)
            stack.extend(reversed(node.children or []))

    for s in scene_order:
        for root in scenes[s].nodes or []:
            visit(root)
    for i in range(len(nodes)):
        visit(i)
    return order + [m for m in range(len(meshes)) if m not in order]


def _target_names(mesh: gl.Mesh) -> list | None:
    for extras in [mesh.extras] + [p.extras for p in mesh.primitives[:1]]:
        if isinstance(extras, dict) and isinstance(extras.get("targetNames"), list):
            return extras["targetNames"]
    return None


def read_character_glb(path: str | os.PathLike, name: str | None = None) -> Character:
    """The character of a .glb / .gltf: its first mesh with morph targets (see the module's notes); validated.

    Its name: `name`, else the mesh's name, else the file's stem. Raises CharacterError naming the file when it is
    not glTF 2.0, has no mesh, no mesh with morph targets, no target names (`extras.targetNames`), primitives other
    than triangles, targets that differ between primitives, or data that `validate_character` rejects.
    """
    path = Path(path)
    gltf = _load(path)
    reader = _Reader(path, gltf)
    if not gltf.meshes:
        raise CharacterError(f"{path}: no mesh in this glTF file")
    try:
        index = next((m for m in _mesh_order(gltf) if any(p.targets for p in gltf.meshes[m].primitives or [])), None)
        if index is None:
            raise CharacterError(f"{path}: no mesh has morph targets ({len(gltf.meshes)} meshes); a character needs "
                                 "its blendshapes as glTF morph targets")
        mesh = gltf.meshes[index]
        where = f"mesh {index}" + (f" ({mesh.name!r})" if mesh.name else "")
        n_targets = len(next(p.targets for p in mesh.primitives if p.targets))
        names = _target_names(mesh)
        if names is None:
            raise CharacterError(f"{path}: {where} has {n_targets} morph targets but no names; expected "
                                 "mesh.extras.targetNames (or the primitive's extras.targetNames)")
        if len(names) != n_targets or not all(isinstance(n, str) for n in names):
            raise CharacterError(f"{path}: {where}: extras.targetNames must be {n_targets} strings (one per morph "
                                 f"target), got {names!r:.200}")
        positions: list[np.ndarray] = []
        deltas: list[np.ndarray] = []
        faces: list[np.ndarray] = []
        shared: dict[tuple, tuple[int, int]] = {}   # (POSITION, target POSITIONs) accessors -> (first vertex, count)
        n_vertices = 0
        for k, primitive in enumerate(mesh.primitives):
            what = f"{where} primitive {k}"
            mode = gl.TRIANGLES if primitive.mode is None else primitive.mode
            if mode != gl.TRIANGLES:
                raise CharacterError(f"{path}: {what} draws {_MODES.get(mode, mode)}; only TRIANGLES are read")
            targets = primitive.targets or []
            if len(targets) != n_targets:
                raise CharacterError(f"{path}: {what} has {len(targets)} morph targets, the mesh's first has "
                                     f"{n_targets}; every primitive needs the same targets")
            attributes = primitive.attributes
            position_index = getattr(attributes, "POSITION", None) if attributes is not None else None
            if position_index is None:
                raise CharacterError(f"{path}: {what} has no POSITION attribute")
            target_ids = tuple(t.get("POSITION") if isinstance(t, dict) else getattr(t, "POSITION", None)
                               for t in targets)
            key = (position_index, target_ids)
            if key in shared:
                first, count = shared[key]
            else:
                vertices = reader.floats(position_index, f"{what} POSITION")
                count = len(vertices)
                block = np.zeros((n_targets, count, 3), np.float32)
                for t, target_index in enumerate(target_ids):
                    if target_index is not None:     # a target that moves no position (e.g. NORMAL only)
                        d = reader.floats(target_index, f"{what} target {t} ({names[t]!r}) POSITION")
                        if len(d) != count:
                            raise CharacterError(f"{path}: {what} target {t} ({names[t]!r}) has {len(d)} "
                                                 f"positions, the primitive {count}")
                        block[t] = d
                first = n_vertices
                shared[key] = (first, count)
                positions.append(vertices)
                deltas.append(block)
                n_vertices += count
            faces.append(reader.indices(primitive.indices, count, what) + first)
    except CharacterError:
        raise
    except (AttributeError, IndexError, KeyError, TypeError, ValueError) as exc:
        raise CharacterError(f"{path}: malformed glTF ({type(exc).__name__}: {exc})") from None
    return make_character(name or mesh.name or path.stem, np.concatenate(positions), np.concatenate(faces),
                          names, np.concatenate(deltas, axis=1), source=path)
