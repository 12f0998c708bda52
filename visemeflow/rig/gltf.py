"""The one glTF 2.0 reader: a mesh, its named morph targets and vertex colours as plain arrays, through pygltflib.

`read_gltf_mesh(path)` is used by the rig loaders (`rig.io.load_rig_glb`, `rig.io.read_mesh`) and, through
`animation.gltf.read_character_glb`, by the character loaders. pygltflib parses the container (GLB or glTF JSON);
this module turns accessors into numpy arrays and checks what a mesh reader needs.

Which mesh: with `morph_targets=True`, the first mesh with morph targets in scene order (the default scene's node
tree depth first, then the other scenes, then nodes in no scene, then meshes no node uses), else the first mesh in
that order with no targets (S = 0: the caller says why that is not enough); with `morph_targets=False`, the first
mesh in that order, its targets not read.

What is read: every primitive must be TRIANGLES and carry the same number of targets; primitives are joined into one
vertex array in primitive order (primitives that share their POSITION, COLOR_0 and target accessors share their
vertices). Accessors may be strided, sparse, or integer (normalized or not, as KHR_mesh_quantization allows).
Target names come from `mesh.extras.targetNames`, else the first primitive's. Node transforms are not applied.
Buffers may be the GLB's binary chunk, data URIs or files beside a .gltf (no other URI is followed).

Vertex colours: `COLOR_0` (VEC3 or VEC4, float or normalized unsigned byte / short; alpha dropped) holds *linear*
RGB (glTF 2.0, 3.7.2.1), while the package's colours (`VisemeRig.vertex_colors`, `Character.vertex_colors`, the
preview renderer) are sRGB display values; the reader converts with `linear_to_srgb` and a writer should store
`srgb_to_linear` of its colours. Values outside [0, 1] are clipped. When only some primitives have COLOR_0 the
others are white (glTF's implied multiplier). Vertex data is returned as it is stored: no finiteness check here,
the callers validate.

Every problem is a `RigError` whose message starts with the file's path.
"""

from __future__ import annotations

import json
import os
import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pygltflib as gl

from visemeflow.rig.model import RigError

__all__ = ["GltfMesh", "linear_to_srgb", "read_gltf_mesh", "srgb_to_linear"]

_GLB_MAGIC = b"glTF"
_COMPONENT_DTYPES = {
    gl.BYTE: np.dtype("<i1"), gl.UNSIGNED_BYTE: np.dtype("<u1"), gl.SHORT: np.dtype("<i2"),
    gl.UNSIGNED_SHORT: np.dtype("<u2"), gl.UNSIGNED_INT: np.dtype("<u4"), gl.FLOAT: np.dtype("<f4"),
}
_INDEX_TYPES = (gl.UNSIGNED_BYTE, gl.UNSIGNED_SHORT, gl.UNSIGNED_INT)
_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
_MODES = {gl.POINTS: "POINTS", gl.LINES: "LINES", gl.LINE_LOOP: "LINE_LOOP", gl.LINE_STRIP: "LINE_STRIP",
          gl.TRIANGLES: "TRIANGLES", gl.TRIANGLE_STRIP: "TRIANGLE_STRIP", gl.TRIANGLE_FAN: "TRIANGLE_FAN"}


# ---- colour spaces (IEC 61966-2-1, the sRGB transfer function) ---------------------------------------------
def srgb_to_linear(values) -> np.ndarray:
    """sRGB-encoded values in [0, 1] (clipped) to linear RGB, float32."""
    c = np.clip(np.asarray(values, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(values) -> np.ndarray:
    """Linear RGB in [0, 1] (clipped) to sRGB-encoded values, float32; the inverse of `srgb_to_linear`."""
    c = np.clip(np.asarray(values, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * c ** (1.0 / 2.4) - 0.055).clip(0.0, 1.0).astype(np.float32)


# ---- the result ------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class GltfMesh:
    """One mesh of a glTF file, primitives joined, as arrays."""

    path: Path
    index: int
    """The mesh's index in the file's `meshes`."""
    name: str | None
    n_meshes: int
    """How many meshes the file has (for messages)."""
    neutral: np.ndarray
    """(V, 3) float32 positions as stored (node transforms not applied)."""
    faces: np.ndarray
    """(F, 3) int32 triangles."""
    target_names: tuple[str, ...]
    """The S morph target names; () when the mesh has no targets (or they were not asked for)."""
    deltas: np.ndarray
    """(S, V, 3) float32 POSITION displacements, one per target (zeros for a target without POSITION)."""
    colors: np.ndarray | None = None
    """(V, 3) float32 sRGB in [0, 1] from COLOR_0, or None when no primitive has COLOR_0."""
    extras: dict = field(default_factory=dict)
    """The mesh's `extras` when it is a JSON object, else {}."""


# ---- accessors -------------------------------------------------------------------------------------------------
class _Reader:
    """Accessors of one loaded glTF as numpy arrays; every error names the file."""

    def __init__(self, path: Path, gltf: gl.GLTF2):
        self.path = path
        self.gltf = gltf
        self.buffers: dict[int, bytes] = {}

    def fail(self, message: str) -> RigError:
        return RigError(f"{self.path}: {message}")

    def buffer(self, index: int) -> bytes:
        if index not in self.buffers:
            if not isinstance(index, int) or not 0 <= index < len(self.gltf.buffers):
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

    def _elements(self, view_index: int | None, byte_offset: int | None, count: int, width: int, dtype: np.dtype,
                  what: str) -> np.ndarray:
        if not isinstance(view_index, int) or not 0 <= view_index < len(self.gltf.bufferViews):
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

    def accessor(self, index: int | None, what: str, types: tuple[str, ...]) -> np.ndarray:
        """(count, width) in the accessor's own component type, sparse values applied."""
        if not isinstance(index, int) or not 0 <= index < len(self.gltf.accessors):
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
        if values.dtype.kind == "f":
            return np.ascontiguousarray(values, dtype=np.float32)
        if self.gltf.accessors[index].normalized:
            return _dequantize(values)
        return values.astype(np.float32)

    def colors(self, index: int, what: str) -> np.ndarray:
        """COLOR_0 as (count, 3) float32 linear RGB clipped to [0, 1]: float, or normalized unsigned byte/short."""
        values = self.accessor(index, what, ("VEC3", "VEC4"))[:, :3]
        if values.dtype.kind == "f":
            rgb = np.asarray(values, dtype=np.float32)
            if not np.isfinite(rgb).all():
                raise self.fail(f"{what} (accessor {index}): NaN or infinite colour values")
        elif values.dtype.kind == "u" and self.gltf.accessors[index].normalized:
            rgb = _dequantize(values)
        else:
            raise self.fail(f"{what} (accessor {index}): colours must be float or normalized unsigned byte/short, "
                            f"got {'normalized ' if self.gltf.accessors[index].normalized else ''}{values.dtype}")
        return np.clip(rgb, 0.0, 1.0)

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


def _dequantize(values: np.ndarray) -> np.ndarray:
    """Normalized integers to float32 (glTF 2.0 3.11: c / max, and max(c / max, -1) for signed types)."""
    info = np.iinfo(values.dtype)
    return np.maximum(values.astype(np.float64) / info.max, -1.0).astype(np.float32)


# ---- the document ----------------------------------------------------------------------------------------------
def _load(path: Path) -> gl.GLTF2:
    """The glTF document (a GLB, or glTF JSON), checked to be glTF 2.x; RigError otherwise."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise RigError(f"{path}: cannot be read ({exc.strerror or exc})") from None
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
        raise RigError(f"{path}: not a glTF 2.0 / GLB file ({exc})") from None
    version = str(getattr(gltf.asset, "version", "") or "")
    if not version.startswith("2"):
        raise RigError(f"{path}: glTF version {version or '(none)'}; only glTF 2.0 is read")
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


def _attribute(attributes, name: str) -> int | None:
    """An attribute's accessor index from pygltflib's Attributes object or a plain dict (morph targets)."""
    if attributes is None:
        return None
    return attributes.get(name) if isinstance(attributes, dict) else getattr(attributes, name, None)


# ---- the mesh --------------------------------------------------------------------------------------------------
def read_gltf_mesh(path: str | os.PathLike, *, morph_targets: bool = True) -> GltfMesh:
    """The mesh of a .glb / .gltf that a rig or character uses (see the module's notes for which, and how).

    Raises RigError naming the file when it cannot be read, is not glTF 2.0, has no mesh, has targets without
    names (`extras.targetNames`, one string per target), primitives other than triangles, primitives with
    different target counts, or accessors that are missing, of the wrong type or outside their buffers.
    """
    path = Path(path)
    gltf = _load(path)
    if not gltf.meshes:
        raise RigError(f"{path}: no mesh in this glTF file")
    reader = _Reader(path, gltf)
    try:
        order = _mesh_order(gltf)
        index = order[0]
        if morph_targets:
            index = next((m for m in order if any(p.targets for p in gltf.meshes[m].primitives or [])), index)
        mesh = gltf.meshes[index]
        where = f"mesh {index}" + (f" ({mesh.name!r})" if mesh.name else "")
        if not mesh.primitives:
            raise RigError(f"{path}: {where} has no primitives")
        with_targets = [p.targets for p in mesh.primitives if p.targets] if morph_targets else []
        n_targets = len(with_targets[0]) if with_targets else 0
        names: list = []
        if n_targets:
            found = _target_names(mesh)
            if found is None:
                raise RigError(f"{path}: {where} has {n_targets} morph targets but no names; expected "
                               "mesh.extras.targetNames (or the primitive's extras.targetNames)")
            if len(found) != n_targets or not all(isinstance(n, str) for n in found):
                raise RigError(f"{path}: {where}: extras.targetNames must be {n_targets} strings (one per morph "
                               f"target), got {found!r:.200}")
            names = found
        positions: list[np.ndarray] = []
        deltas: list[np.ndarray] = []
        colors: list[np.ndarray | None] = []
        faces: list[np.ndarray] = []
        shared: dict[tuple, tuple[int, int]] = {}   # (POSITION, COLOR_0, target POSITIONs) -> (first vertex, count)
        n_vertices = 0
        for k, primitive in enumerate(mesh.primitives):
            what = f"{where} primitive {k}"
            mode = gl.TRIANGLES if primitive.mode is None else primitive.mode
            if mode != gl.TRIANGLES:
                raise RigError(f"{path}: {what} draws {_MODES.get(mode, mode)}; only TRIANGLES are read")
            targets = (primitive.targets or []) if morph_targets else []
            if len(targets) != n_targets:
                raise RigError(f"{path}: {what} has {len(targets)} morph targets, the mesh's first has "
                               f"{n_targets}; every primitive needs the same targets")
            position_index = _attribute(primitive.attributes, "POSITION")
            if position_index is None:
                raise RigError(f"{path}: {what} has no POSITION attribute")
            color_index = _attribute(primitive.attributes, "COLOR_0")
            target_ids = tuple(_attribute(t, "POSITION") for t in targets)
            key = (position_index, color_index, target_ids)
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
                            raise RigError(f"{path}: {what} target {t} ({names[t]!r}) has {len(d)} "
                                           f"positions, the primitive {count}")
                        block[t] = d
                rgb = None
                if color_index is not None:
                    rgb = reader.colors(color_index, f"{what} COLOR_0")
                    if len(rgb) != count:
                        raise RigError(f"{path}: {what} COLOR_0 has {len(rgb)} colours, the primitive {count} "
                                       "positions")
                first = n_vertices
                shared[key] = (first, count)
                positions.append(vertices)
                deltas.append(block)
                colors.append(rgb)
                n_vertices += count
            faces.append(reader.indices(primitive.indices, count, what) + first)
    except RigError:
        raise
    except (AttributeError, IndexError, KeyError, TypeError, ValueError) as exc:
        raise RigError(f"{path}: malformed glTF ({type(exc).__name__}: {exc})") from None
    rgb = None
    if any(c is not None for c in colors):
        linear = np.concatenate([np.ones((len(p), 3), np.float32) if c is None else c
                                 for p, c in zip(positions, colors)])
        rgb = linear_to_srgb(linear)
    return GltfMesh(path=path, index=index, name=mesh.name or None, n_meshes=len(gltf.meshes),
                    neutral=np.concatenate(positions).astype(np.float32, copy=False),
                    faces=np.concatenate(faces).astype(np.int32),
                    target_names=tuple(names), deltas=np.concatenate(deltas, axis=1), colors=rgb,
                    extras=mesh.extras if isinstance(mesh.extras, dict) else {})
