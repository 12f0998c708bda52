"""The one glTF 2.0 reader: a mesh, its named morph targets and vertex colours as plain arrays, through pygltflib.

`read_gltf_mesh(path)` is used by the rig loaders (`rig.io.load_rig_glb`, `rig.io.read_mesh`); `GltfScene(path)`
(every mesh described, any mesh read and placed in the scene: node world transforms, skin rest poses) by the
character loader, `animation.gltf.read_character_glb`, which drives several meshes of one avatar. pygltflib parses
the container (GLB or glTF JSON); this module turns accessors into numpy arrays and checks what a mesh reader needs.

Which mesh: with `morph_targets=True`, the first mesh with morph targets in scene order (the default scene's node
tree depth first, then the other scenes, then nodes in no scene, then meshes no node uses), else the first mesh in
that order with no targets (S = 0: the caller says why that is not enough); with `morph_targets=False`, the first
mesh in that order, its targets not read.

What is read: every primitive must draw triangles (TRIANGLES, or TRIANGLE_STRIP and TRIANGLE_FAN, made into
triangles) and carry the same number of targets; primitives are joined into one
vertex array in primitive order (primitives that share their POSITION, COLOR_0 and target accessors share their
vertices). Accessors may be strided, sparse, or integer (normalized or not, as KHR_mesh_quantization allows).
Target names come from `mesh.extras.targetNames`, else the first primitive's. `read_gltf_mesh` applies no node
transform (`GltfScene.placed_mesh` does). Files that require Draco or meshopt compression are refused with how to
decompress them.
Buffers may be the GLB's binary chunk, data URIs or files inside the glTF's folder: every buffer and image URI
is checked at load (`resolve_gltf_uri`: percent-decoded, then refused when absolute, with a scheme, or leading out of
the folder through `..` or a link), so a character cannot make an export copy a file from elsewhere.

Declared sizes are checked before anything is allocated from them: a buffer's byteLength against its data, every
accessor against its buffer view and `MAX_ACCESSOR_VALUES`, a mesh's vertices against `MAX_VERTICES`, its morph
targets times vertices against `MAX_MORPH_VALUES`, its triangles against `MAX_TRIANGLES`, and a buffer file's size
against `MAX_FILE_BYTES`; a file of a few hundred bytes cannot ask for gigabytes.

Vertex colours: `COLOR_0` (VEC3 or VEC4, float or normalized unsigned byte / short; alpha dropped) holds *linear*
RGB (glTF 2.0, 3.7.2.1), while the package's colours (`VisemeRig.vertex_colors`, `Character.vertex_colors`, the
preview renderer) are sRGB display values; the reader converts with `linear_to_srgb` and a writer should store
`srgb_to_linear` of its colours. Values outside [0, 1] are clipped. When only some primitives have COLOR_0 the
others are white (glTF's implied multiplier). Vertex data is returned as it is stored: no finiteness check here,
the callers validate.

Every problem is a `RigError` whose message starts with the file's path.
"""

from __future__ import annotations

import base64
import binascii
import json
import os
import struct
import urllib.parse
import warnings
from collections.abc import Collection
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pygltflib as gl

from visemeflow.rig.model import RigError

__all__ = ["COMPRESSION_EXTENSIONS", "MAX_ACCESSOR_VALUES", "MAX_FILE_BYTES", "MAX_MORPH_VALUES", "MAX_SCENE_VERTICES",
           "MAX_TRIANGLES",
           "MAX_VERTICES", "GltfMesh", "GltfMeshInfo", "GltfScene", "linear_to_srgb", "read_gltf_mesh",
           "read_gltf_uri", "resolve_gltf_uri", "srgb_to_linear"]

COMPRESSION_EXTENSIONS = ("KHR_draco_mesh_compression", "EXT_meshopt_compression", "KHR_meshopt_compression")
"""Geometry compression extensions: a file that requires one is refused with how to decompress it."""

MAX_FILE_BYTES = 1 << 30
"""The largest glTF, GLB, buffer or image file read (1 GiB; a GLB can hold 4 GiB, a talking character is far
smaller)."""
MAX_ACCESSOR_VALUES = 1 << 26
"""The most values (elements x components) one accessor may declare: 67M, 256 MiB as float32."""
MAX_VERTICES = 1 << 21
"""The most vertices of one mesh, and of all the meshes one character drives: 2,097,152 (the skin rest pose
blends a 4 x 4 matrix per vertex and influence, 512 bytes a vertex)."""
MAX_TRIANGLES = 1 << 22
"""The most triangles of one mesh (primitives joined)."""
MAX_SCENE_VERTICES = 1 << 23
"""The most vertices a preview or a USD places besides the driven meshes: the meshes no target moves and a driven
mesh's other instances, counted once per node that shows them (8,388,608; a file of a few hundred kB can make a
million nodes show one large mesh). Meshes past it are left out, with a note."""
MAX_MORPH_VALUES = 1 << 27
"""The most morph target values (targets x vertices x 3) of one mesh or character: 134M, 512 MiB as float32
(800 targets on a 50,000-vertex face is 120M)."""

_GLB_MAGIC = b"glTF"
_COMPONENT_DTYPES = {
    gl.BYTE: np.dtype("<i1"), gl.UNSIGNED_BYTE: np.dtype("<u1"), gl.SHORT: np.dtype("<i2"),
    gl.UNSIGNED_SHORT: np.dtype("<u2"), gl.UNSIGNED_INT: np.dtype("<u4"), gl.FLOAT: np.dtype("<f4"),
}
_INDEX_TYPES = (gl.UNSIGNED_BYTE, gl.UNSIGNED_SHORT, gl.UNSIGNED_INT)
_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
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


# ---- URIs ------------------------------------------------------------------------------------------------------
def resolve_gltf_uri(source: Path, uri: str) -> Path:
    """The file that `uri`, a relative reference of the glTF at `source` (not a data: URI), names inside
    `source`'s folder, links resolved. ValueError saying why for anything else: a scheme (http:, file:), an
    absolute path, or a path that leads out of the folder (`..`, a link to elsewhere). Percent-encoding is decoded
    first (glTF 2.0 URIs are RFC 3986 references), so `%2E%2E/` is `../`."""
    if not isinstance(uri, str) or not uri:
        raise ValueError(f"{uri!r} is not a URI")
    folder = source.parent.resolve()
    parts = urllib.parse.urlsplit(uri)
    if parts.scheme or parts.netloc:
        raise ValueError(f"{uri!r} is not a file inside the character's folder {folder}; only data: URIs and "
                         "relative paths are read")
    relative = urllib.parse.unquote(parts.path)
    if "\0" in relative or os.path.isabs(relative):
        raise ValueError(f"{uri!r} leads outside the character's folder {folder} (an absolute path); only data: "
                         "URIs and files inside it are read")
    target = (folder / relative).resolve()
    if not target.is_relative_to(folder):
        raise ValueError(f"{uri!r} leads outside the character's folder {folder} (to {target}); only data: URIs "
                         "and files inside it are read")
    return target


def read_gltf_uri(source: Path, uri: str) -> bytes:
    """The bytes of a data: URI, or of the file a relative URI names inside `source`'s folder (see
    `resolve_gltf_uri`). FileNotFoundError when that file is missing; ValueError saying why for a URI that leads
    elsewhere, a file larger than `MAX_FILE_BYTES` or a data: URI that does not decode."""
    if isinstance(uri, str) and uri.startswith("data:"):
        header, comma, payload = uri.partition(",")
        if not comma:
            raise ValueError("a data: URI without a comma before its data")
        try:
            if header.endswith(";base64"):
                return base64.b64decode(payload)   # lenient, as pygltflib: line breaks in the data are skipped
            return urllib.parse.unquote_to_bytes(payload)
        except binascii.Error as exc:
            raise ValueError(f"its data: URI is not valid base64 ({exc})") from None
    target = resolve_gltf_uri(source, uri)
    if target.exists() and not target.is_file():   # a FIFO or device would block or never end
        raise ValueError(f"{uri!r} is not a regular file")
    with open(target, "rb") as handle:   # sized through the handle: the file checked is the file read
        size = os.fstat(handle.fileno()).st_size
        if size > MAX_FILE_BYTES:
            raise ValueError(f"{uri!r} is {size} bytes, more than the {MAX_FILE_BYTES} bytes a character file may "
                             "have")
        return handle.read(size)   # read(n) reserves n bytes first: never more than the file's size


def _check_uris(path: Path, gltf: gl.GLTF2) -> None:
    """Every buffer and image URI of the document resolves inside `path`'s folder (RigError naming the first that
    does not): the export copies them all, used by a mesh or not."""
    entries = [("buffer", k, b.uri) for k, b in enumerate(gltf.buffers or [])]
    entries += [("image", k, i.uri) for k, i in enumerate(gltf.images or [])]
    for kind, k, uri in entries:
        if uri is None or (isinstance(uri, str) and uri.startswith("data:")):
            continue
        try:
            resolve_gltf_uri(path, uri)
        except ValueError as exc:
            raise RigError(f"{path}: {kind} {k}: {exc}") from None


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
    joints: np.ndarray | None = None
    """(V, 4) int64 JOINTS_0 (indices into the skin's joints) when read with skin attributes and every primitive
    has them, else None."""
    weights: np.ndarray | None = None
    """(V, 4) float32 WEIGHTS_0 (dequantized, each row scaled to sum 1), alongside `joints`."""
    uvs: np.ndarray | None = None
    """(V, 2) float32 TEXCOORD_0 as stored (glTF's origin top left), or None when no primitive has it (zeros for
    a primitive without it). Primitives sharing their positions share the first one's."""
    surfaces: tuple[tuple[int | None, int], ...] = ()
    """Per primitive, in order: (its material index or None, its triangle count); the triangles of `faces` follow
    the same order."""
    primitive_starts: tuple[int, ...] = ()
    """Per primitive, in order: its first vertex in the joined arrays (primitives sharing their POSITION, COLOR_0,
    target and skin accessors share one block of vertices, hence one start)."""
    uv_problems: tuple[str, ...] = ()
    """Why a primitive's TEXCOORD_0 was not read (NaN, a wrong count, a broken accessor): texture coordinates
    only colour the mesh, so the mesh is read without them (zeros) and the exports say so."""


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
        """Buffer `index`'s bytes, cut to its declared byteLength (which its data must hold)."""
        if index not in self.buffers:
            if not isinstance(index, int) or not 0 <= index < len(self.gltf.buffers):
                raise self.fail(f"buffer {index} does not exist ({len(self.gltf.buffers)} buffers)")
            buffer = self.gltf.buffers[index]
            uri = buffer.uri
            if uri is None:
                data = self.gltf.binary_blob() if index == 0 else None
            else:
                try:
                    data = read_gltf_uri(self.path, uri)
                except FileNotFoundError:
                    data = None
                except ValueError as exc:
                    raise self.fail(f"buffer {index}: {exc}") from None
                except OSError as exc:
                    raise self.fail(f"buffer {index} ({uri}) cannot be read: {exc.strerror or exc}") from None
            if data is None:
                raise self.fail(f"buffer {index} ({uri or 'GLB binary chunk'}) is missing")
            declared = buffer.byteLength
            if not isinstance(declared, int) or not 0 <= declared <= len(data):
                source = "GLB binary chunk" if uri is None else "data: URI" if uri.startswith("data:") else uri
                raise self.fail(f"buffer {index} declares {declared!r} bytes (byteLength) but its data ({source}) "
                                f"holds {len(data)}")
            self.buffers[index] = bytes(data[:declared])
        return self.buffers[index]

    def declared_count(self, index: int | None, what: str) -> int:
        """The element count accessor `index` declares, checked against `MAX_ACCESSOR_VALUES` (nothing read)."""
        if not isinstance(index, int) or not 0 <= index < len(self.gltf.accessors):
            raise self.fail(f"{what}: accessor {index} does not exist")
        acc = self.gltf.accessors[index]
        count, width = acc.count, _WIDTHS.get(acc.type, 1)
        if not isinstance(count, int) or count < 0:
            raise self.fail(f"{what} (accessor {index}): count must be a whole number >= 0, got {count!r}")
        if count * width > MAX_ACCESSOR_VALUES:
            raise self.fail(f"{what} (accessor {index}): declares {count} {acc.type} elements ({count * width} "
                            f"values), more than the {MAX_ACCESSOR_VALUES} values visemeflow reads from one accessor")
        return count

    def _elements(self, view_index: int | None, byte_offset: int | None, count: int, width: int, dtype: np.dtype,
                  what: str) -> np.ndarray:
        if not isinstance(view_index, int) or not 0 <= view_index < len(self.gltf.bufferViews):
            raise self.fail(f"{what}: buffer view {view_index} does not exist")
        view = self.gltf.bufferViews[view_index]
        data = self.buffer(view.buffer)
        element = width * dtype.itemsize
        stride = view.byteStride or element
        for name, value in (("byteOffset", view.byteOffset), ("byteLength", view.byteLength),
                            ("byteStride", view.byteStride), ("accessor byteOffset", byte_offset)):
            if value is not None and (not isinstance(value, int) or value < 0):
                raise self.fail(f"{what}: buffer view {view_index} {name} must be a whole number >= 0, got {value!r}")
        if not isinstance(count, int) or count < 0:
            raise self.fail(f"{what}: count must be a whole number >= 0, got {count!r}")
        if stride < element:
            raise self.fail(f"{what}: buffer view {view_index} byteStride {stride} is shorter than its {element}-byte "
                            "elements")
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
        count = self.declared_count(index, what)
        what = f"{what} (accessor {index})"
        if acc.type not in types or acc.componentType not in _COMPONENT_DTYPES:
            raise self.fail(f"{what}: expected {' or '.join(types)}, got {acc.type} of component type "
                            f"{acc.componentType}")
        dtype, width = _COMPONENT_DTYPES[acc.componentType], _WIDTHS[acc.type]
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

    def texcoords(self, index: int, what: str) -> np.ndarray:
        """TEXCOORD_n as (count, 2) float32: float, normalized integers dequantized (glTF 2.0 3.7.2.1), other
        integers as they are (KHR_mesh_quantization)."""
        values = self.accessor(index, what, ("VEC2",))
        if values.dtype.kind == "f":
            uv = np.asarray(values, dtype=np.float32)
            if not np.isfinite(uv).all():
                raise self.fail(f"{what} (accessor {index}): NaN or infinite texture coordinates")
            return uv
        if self.gltf.accessors[index].normalized:
            return _dequantize(values)
        return values.astype(np.float32)

    def skin_influences(self, joints_index: int, weights_index: int, what: str) -> tuple[np.ndarray, np.ndarray]:
        """JOINTS_0 as (count, 4) int64 and WEIGHTS_0 as (count, 4) float32, each row scaled to sum 1 (a row of
        zeros stays zero)."""
        joints = self.accessor(joints_index, f"{what} JOINTS_0", ("VEC4",))
        if joints.dtype.kind != "u":
            raise self.fail(f"{what} JOINTS_0 (accessor {joints_index}): expected unsigned byte or short, got "
                            f"{joints.dtype}")
        weights = self.accessor(weights_index, f"{what} WEIGHTS_0", ("VEC4",))
        if weights.dtype.kind == "f":
            weights = np.asarray(weights, np.float32)
        elif weights.dtype.kind == "u" and self.gltf.accessors[weights_index].normalized:
            weights = _dequantize(weights)
        else:
            raise self.fail(f"{what} WEIGHTS_0 (accessor {weights_index}): expected float or normalized unsigned "
                            f"byte/short, got {weights.dtype}")
        if len(joints) != len(weights):
            raise self.fail(f"{what}: {len(joints)} JOINTS_0 but {len(weights)} WEIGHTS_0")
        total = weights.sum(axis=1, keepdims=True)
        weights = np.where(total > 0, weights / np.where(total > 0, total, 1), 0).astype(np.float32)
        return joints.astype(np.int64), weights

    def matrices(self, index: int, what: str) -> np.ndarray:
        """A MAT4 float accessor as (count, 4, 4) float64 row-major matrices (glTF stores them column-major)."""
        values = self.accessor(index, what, ("MAT4",))
        if values.dtype.kind != "f":
            raise self.fail(f"{what} (accessor {index}): matrices must be float, got {values.dtype}")
        return np.asarray(values, np.float64).reshape(-1, 4, 4).transpose(0, 2, 1)

    def indices(self, index: int | None, n_vertices: int, what: str, mode: int = gl.TRIANGLES) -> np.ndarray:
        """(F, 3) int64 triangles of a primitive drawn as TRIANGLES, TRIANGLE_STRIP or TRIANGLE_FAN (glTF 2.0
        3.7.2.1: strip triangle i is v_i, v_{i+1+i%2}, v_{i+2-i%2}; fan triangle i is v_{i+1}, v_{i+2}, v_0), from
        its indices or, without them, its vertices in order. A strip's or fan's degenerate triangles (two equal
        corners, how strips are joined) are dropped."""
        if index is None:   # non-indexed: the vertices in order
            ids = np.arange(n_vertices, dtype=np.int64)
        else:
            values = self.accessor(index, f"{what} indices", ("SCALAR",))
            if self.gltf.accessors[index].componentType not in _INDEX_TYPES:
                raise self.fail(f"{what} indices (accessor {index}): component type "
                                f"{self.gltf.accessors[index].componentType} is not an unsigned integer")
            ids = values[:, 0].astype(np.int64)
            if ids.size and int(ids.max()) >= n_vertices:
                raise self.fail(f"{what}: index {int(ids.max())} outside its {n_vertices} vertices")
        if mode == gl.TRIANGLES:
            if len(ids) % 3:
                raise self.fail(f"{what}: {len(ids)} {'indices' if index is not None else 'vertices without indices'}"
                                " are not whole triangles")
            return ids.reshape(-1, 3)
        n = max(len(ids) - 2, 0)
        i = np.arange(n)
        if mode == gl.TRIANGLE_STRIP:
            faces = np.stack([ids[i], ids[i + 1 + i % 2], ids[i + 2 - i % 2]], axis=1)
        else:                                                   # TRIANGLE_FAN
            faces = np.stack([ids[i + 1], ids[i + 2], np.full(n, ids[0] if len(ids) else 0)], axis=1)
        keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
        return faces[keep].reshape(-1, 3)


def _dequantize(values: np.ndarray) -> np.ndarray:
    """Normalized integers to float32 (glTF 2.0 3.11: c / max, and max(c / max, -1) for signed types)."""
    info = np.iinfo(values.dtype)
    return np.maximum(values.astype(np.float64) / info.max, -1.0).astype(np.float32)


# ---- the document ----------------------------------------------------------------------------------------------
def _load(path: Path) -> gl.GLTF2:
    """The glTF document (a GLB, or glTF JSON), checked to be glTF 2.x; RigError otherwise."""
    try:
        with open(path, "rb") as handle:
            size = os.fstat(handle.fileno()).st_size
            if size > MAX_FILE_BYTES:
                raise RigError(f"{path}: {size} bytes, more than the {MAX_FILE_BYTES} bytes a character file may have")
            data = handle.read(size)   # read(n) reserves n bytes first: never more than the file's size
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
                if data.lstrip()[:15].lower().startswith((b"<!doctype html", b"<html")):
                    raise ValueError("it is an HTML page: a web page saved instead of the file? (on GitHub, "
                                     "download the raw file)")
                document = json.loads(data.decode("utf-8-sig"))
                if not isinstance(document, dict) or not isinstance(document.get("asset"), dict):
                    raise ValueError("no glTF asset object")
                gltf = gl.GLTF2.gltf_from_json(json.dumps(document))
    except (ValueError, TypeError, KeyError, AttributeError, OSError, struct.error) as exc:
        raise RigError(f"{path}: not a glTF 2.0 / GLB file ({exc})") from None
    _check_uris(path, gltf)
    version = str(getattr(gltf.asset, "version", "") or "")
    if not version.startswith("2"):
        raise RigError(f"{path}: glTF version {version or '(none)'}; only glTF 2.0 is read")
    compressed = [e for e in gltf.extensionsRequired or [] if e in COMPRESSION_EXTENSIONS]
    if compressed:
        raise RigError(f"{path}: its geometry is compressed with {', '.join(compressed)}, which visemeflow does not "
                       "decode; write an uncompressed copy first, e.g. `npx @gltf-transform/cli copy "
                       f"{path.name} {path.stem}-plain{path.suffix}` (gltf-transform decodes both), or import it "
                       "in Blender and export glTF without compression")
    return gltf


def _node_order(gltf: gl.GLTF2) -> list[int]:
    """Node indices: the default scene's tree first (depth first), then the other scenes', then nodes in no scene."""
    nodes, scenes = gltf.nodes or [], gltf.scenes or []
    roots: list = []
    if isinstance(gltf.scene, int) and 0 <= gltf.scene < len(scenes):
        roots += scenes[gltf.scene].nodes or []
    for scene in scenes:
        roots += scene.nodes or []
    roots += range(len(nodes))
    order, seen = [], set()
    for root in roots:
        stack = [root]
        while stack:
            i = stack.pop()
            if not isinstance(i, int) or not 0 <= i < len(nodes) or i in seen:
                continue
            seen.add(i)
            order.append(i)
            stack.extend(reversed(nodes[i].children or []))
    return order


def _mesh_order(gltf: gl.GLTF2) -> list[int]:
    """Mesh indices: those of the nodes in `_node_order`, then meshes no node uses."""
    nodes, meshes = gltf.nodes or [], gltf.meshes or []
    order: list[int] = []
    for i in _node_order(gltf):
        mesh = nodes[i].mesh
        if isinstance(mesh, int) and 0 <= mesh < len(meshes) and mesh not in order:
            order.append(mesh)
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
    order = _mesh_order(gltf)
    index = order[0]
    if morph_targets:
        index = next((m for m in order if any(p.targets for p in gltf.meshes[m].primitives or [])), index)
    return _read_mesh(_Reader(path, gltf), index, morph_targets=morph_targets)


def _read_mesh(reader: _Reader, index: int, *, morph_targets: bool = True, skin: bool = False) -> GltfMesh:
    """Mesh `index` of the reader's document as arrays (primitives joined); with `skin`, JOINTS_0 / WEIGHTS_0 too."""
    path, gltf = reader.path, reader.gltf
    try:
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
        uvs: list[np.ndarray | None] = []
        uv_problems: list[str] = []
        surfaces: list[tuple[int | None, int]] = []
        starts: list[int] = []
        faces: list[np.ndarray] = []
        skins: list[tuple[np.ndarray, np.ndarray] | None] = []
        # (POSITION, COLOR_0, target POSITIONs, JOINTS_0, WEIGHTS_0) -> (first vertex, count)
        shared: dict[tuple, tuple[int, int]] = {}
        n_vertices = n_triangles = 0
        for k, primitive in enumerate(mesh.primitives):
            what = f"{where} primitive {k}"
            mode = gl.TRIANGLES if primitive.mode is None else primitive.mode
            if mode not in (gl.TRIANGLES, gl.TRIANGLE_STRIP, gl.TRIANGLE_FAN):
                raise RigError(f"{path}: {what} draws {_MODES.get(mode, mode)}; only triangles (TRIANGLES, "
                               "TRIANGLE_STRIP, TRIANGLE_FAN) are read")
            targets = (primitive.targets or []) if morph_targets else []
            if len(targets) != n_targets:
                raise RigError(f"{path}: {what} has {len(targets)} morph targets, the mesh's first has "
                               f"{n_targets}; every primitive needs the same targets")
            position_index = _attribute(primitive.attributes, "POSITION")
            if position_index is None:
                raise RigError(f"{path}: {what} has no POSITION attribute")
            color_index = _attribute(primitive.attributes, "COLOR_0")
            uv_index = _attribute(primitive.attributes, "TEXCOORD_0")
            target_ids = tuple(_attribute(t, "POSITION") for t in targets)
            skin_ids = (_attribute(primitive.attributes, "JOINTS_0"), _attribute(primitive.attributes, "WEIGHTS_0")) \
                if skin else (None, None)
            key = (position_index, color_index, target_ids, skin_ids)
            if key in shared:
                first, count = shared[key]
            else:
                vertices = reader.floats(position_index, f"{what} POSITION")
                count = len(vertices)
                if n_vertices + count > MAX_VERTICES:
                    raise RigError(f"{path}: {where} has more than {MAX_VERTICES} vertices ({n_vertices + count} "
                                   f"up to {what}), the most visemeflow reads in one mesh")
                if n_targets * (n_vertices + count) * 3 > MAX_MORPH_VALUES:
                    raise RigError(f"{path}: {where}: {n_targets} morph targets on {n_vertices + count} vertices "
                                   f"are {n_targets * (n_vertices + count) * 3} values, more than the "
                                   f"{MAX_MORPH_VALUES} visemeflow reads (targets x vertices x 3)")
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
                influences = None
                if None not in skin_ids:
                    influences = reader.skin_influences(*skin_ids, what)
                    if len(influences[0]) != count:
                        raise RigError(f"{path}: {what} JOINTS_0/WEIGHTS_0 have {len(influences[0])} elements, "
                                       f"the primitive {count} positions")
                uv = None
                if uv_index is not None:     # how it looks, not how it moves: a broken one is noted, not refused
                    try:
                        uv = reader.texcoords(uv_index, f"{what} TEXCOORD_0")
                        if len(uv) != count:
                            raise RigError(f"{path}: {what} TEXCOORD_0 has {len(uv)} coordinates, the primitive "
                                           f"{count} positions")
                    except RigError as exc:
                        uv = None
                        uv_problems.append(str(exc))
                first = n_vertices
                shared[key] = (first, count)
                skins.append(influences)
                uvs.append(uv)
                positions.append(vertices)
                deltas.append(block)
                colors.append(rgb)
                n_vertices += count
            drawn = reader.declared_count(primitive.indices, f"{what} indices") if primitive.indices is not None \
                else count
            n_triangles += drawn // 3 if mode == gl.TRIANGLES else max(drawn - 2, 0)
            if n_triangles > MAX_TRIANGLES:
                raise RigError(f"{path}: {where} has more than {MAX_TRIANGLES} triangles ({n_triangles} up to {what}), "
                               "the most visemeflow reads in one mesh")
            faces.append(reader.indices(primitive.indices, count, what, mode) + first)
            material = primitive.material if isinstance(primitive.material, int) else None
            surfaces.append((material, len(faces[-1])))
            starts.append(first)
    except RigError:
        raise
    except (AttributeError, IndexError, KeyError, TypeError, ValueError) as exc:
        raise RigError(f"{path}: malformed glTF ({type(exc).__name__}: {exc})") from None
    rgb = None
    if any(c is not None for c in colors):
        linear = np.concatenate([np.ones((len(p), 3), np.float32) if c is None else c
                                 for p, c in zip(positions, colors)])
        rgb = linear_to_srgb(linear)
    uv_all = None
    if any(u is not None for u in uvs):
        uv_all = np.concatenate([np.zeros((len(p), 2), np.float32) if u is None else u for p, u in zip(positions, uvs)])
    joints = weights = None
    if skins and all(k is not None for k in skins):
        joints = np.concatenate([k[0] for k in skins])
        weights = np.concatenate([k[1] for k in skins])
    return GltfMesh(path=path, index=index, name=mesh.name or None, n_meshes=len(gltf.meshes),
                    neutral=np.concatenate(positions).astype(np.float32, copy=False),
                    faces=np.concatenate(faces).astype(np.int32),
                    target_names=tuple(names), deltas=np.concatenate(deltas, axis=1), colors=rgb,
                    extras=mesh.extras if isinstance(mesh.extras, dict) else {}, joints=joints, weights=weights,
                    uvs=uv_all, surfaces=tuple(surfaces), primitive_starts=tuple(starts),
                    uv_problems=tuple(uv_problems))


# ---- the scene -------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class GltfMeshInfo:
    """What a scene's mesh is, read without its vertex arrays."""

    index: int
    """The mesh's index in the file's `meshes`."""
    label: str
    """Its name, else the name of the first node that instances it, else "mesh <index>"."""
    nodes: tuple[int, ...]
    """The nodes that instance it, in scene order (default scene depth first, then other nodes)."""
    n_vertices: int
    """Vertices of its primitives (primitives sharing a POSITION accessor counted once)."""
    n_targets: int
    target_names: tuple[str, ...] | None
    """Its morph target names, () without targets, None when its targets have no (valid) names."""
    skin: int | None
    """The skin of its first node, if that node has one."""
    node_names: tuple[str, ...] = ()
    """The names of `nodes` (those that have one)."""


def _quaternion_matrix(q) -> np.ndarray:
    """The (3, 3) rotation of a glTF quaternion (x, y, z, w); (..., 3, 3) for (..., 4) of them."""
    x, y, z, w = np.moveaxis(np.asarray(q, np.float64), -1, 0)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                     np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                     np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)


def _local_matrix(node: gl.Node) -> np.ndarray:
    """A node's local transform (glTF 2.0 5.25: `matrix`, column-major, else T * R * S) as a 4x4 row-major."""
    if node.matrix is not None and len(node.matrix) == 16:
        return np.asarray(node.matrix, np.float64).reshape(4, 4).T
    m = np.eye(4)
    rotation = _quaternion_matrix(node.rotation) if node.rotation is not None else np.eye(3)
    scale = np.asarray(node.scale if node.scale is not None else (1, 1, 1), np.float64)
    m[:3, :3] = rotation * scale[None, :]
    if node.translation is not None:
        m[:3, 3] = node.translation
    return m


class GltfScene:
    """A glTF file as a scene: every mesh described (`meshes`, scene order), any mesh's arrays placed in the
    scene's space (`placed_mesh`). Errors are RigErrors whose message starts with the path."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.gltf = _load(self.path)
        self.reader = _Reader(self.path, self.gltf)
        try:
            self.meshes = self._describe()
        except RigError:
            raise
        except (AttributeError, IndexError, KeyError, TypeError, ValueError) as exc:
            raise RigError(f"{self.path}: malformed glTF ({type(exc).__name__}: {exc})") from None
        self._world: dict[int, np.ndarray] = {}

    def _describe(self) -> list[GltfMeshInfo]:
        gltf = self.gltf
        nodes = gltf.nodes or []
        users: dict[int, list[int]] = {}
        for i in _node_order(gltf):
            if isinstance(nodes[i].mesh, int):
                users.setdefault(nodes[i].mesh, []).append(i)
        infos = []
        for m in _mesh_order(gltf):
            mesh = gltf.meshes[m]
            primitives = mesh.primitives or []
            n_targets = max((len(p.targets or []) for p in primitives), default=0)
            names: tuple[str, ...] | None = ()
            if n_targets:
                found = _target_names(mesh)
                names = tuple(found) if isinstance(found, list) and len(found) == n_targets and \
                    all(isinstance(n, str) for n in found) else None
            counts = {}
            for k, p in enumerate(primitives):
                position = _attribute(p.attributes, "POSITION")
                if isinstance(position, int) and 0 <= position < len(gltf.accessors):
                    counts[position] = self.reader.declared_count(position, f"mesh {m} primitive {k} POSITION")
            used_by = tuple(users.get(m, ()))
            label = mesh.name or next((nodes[n].name for n in used_by if nodes[n].name), None) or f"mesh {m}"
            skin = nodes[used_by[0]].skin if used_by and isinstance(nodes[used_by[0]].skin, int) else None
            infos.append(GltfMeshInfo(m, label, used_by, sum(counts.values()), n_targets, names, skin,
                                      tuple(nodes[n].name for n in used_by if nodes[n].name)))
        return infos

    def world_matrix(self, node: int) -> np.ndarray:
        """(4, 4) float64: the node's transform in the scene (its parents' times its own), in the rest pose."""
        if not self._world:
            parents = {}
            for i, n in enumerate(self.gltf.nodes or []):
                for child in n.children or []:
                    parents.setdefault(child, i)
            nodes = self.gltf.nodes or []
            for i in range(len(nodes)):
                chain, j = [], i
                while j is not None and j not in self._world and j not in chain:
                    chain.append(j)
                    j = parents.get(j)
                base = self._world.get(j, np.eye(4)) if j is not None else np.eye(4)
                for k in reversed(chain):
                    base = base @ _local_matrix(nodes[k])
                    self._world[k] = base
        return self._world[node]

    def other_placements(self, driven: Collection[int]) -> tuple[list[tuple[GltfMeshInfo, int]], str | None]:
        """Where the scene shows meshes besides each driven mesh (index in `driven`) at its first node: (mesh, node)
        for each other node of a driven mesh without a skin (a skinned mesh is posed by its skin, not by the nodes
        that show it), then for each mesh not driven every node that shows it (its first only when skinned), in
        scene order, up to `MAX_SCENE_VERTICES` vertices in all; and a note naming what was left out past that (None
        when nothing was)."""
        found, total, left_out = [], 0, []
        infos = [i for i in self.meshes if i.index in driven] + [i for i in self.meshes if i.index not in driven]
        for info in infos:
            if info.index in driven:
                nodes = () if info.skin is not None else info.nodes[1:]
            else:
                nodes = info.nodes[:1] if info.skin is not None else info.nodes
            for node in nodes:
                if total + info.n_vertices > MAX_SCENE_VERTICES:
                    left_out.append(info.label)
                    continue
                total += info.n_vertices
                found.append((info, node))
        if not left_out:
            return found, None
        named = ", ".join(dict.fromkeys(left_out[:5])) + (", ..." if len(left_out) > 5 else "")
        return found, (f"{len(left_out)} mesh placement{'s' if len(left_out) > 1 else ''} left out ({named}): the "
                       f"scene shows more than {MAX_SCENE_VERTICES:,} vertices besides the driven meshes")

    def placed_mesh(self, index: int, node: int | None = None, *, morph_targets: bool = True
                    ) -> tuple[GltfMesh, np.ndarray, np.ndarray, str]:
        """Mesh `index` read (targets unless `morph_targets` is false, colours, skin attributes) and placed in the
        scene as its first node (or `node`, one of the nodes that instance it) shows it: (mesh, neutral (V, 3)
        float32, deltas (S, V, 3) float32, how it was placed).

        A skinned node (glTF ignores its own transform) is put in its rest pose: each vertex moved by the blend,
        by WEIGHTS_0, of world(joint) @ inverseBindMatrix over its JOINTS_0 (linear blend skinning, what a viewer
        shows with the joints at rest), its target deltas by the linear part of that blend (targets apply before
        skinning). Another node's world transform moves the neutral, its linear part the deltas. A mesh no node
        uses stays as stored."""
        info = next(i for i in self.meshes if i.index == index)
        mesh = _read_mesh(self.reader, index, skin=info.skin is not None, morph_targets=morph_targets)
        if not info.nodes:
            return mesh, mesh.neutral, mesh.deltas, "as stored (no node)"
        if node is None:
            node = info.nodes[0]
        elif node not in info.nodes:
            raise RigError(f"{self.path}: node {node} does not instance mesh {index}")
        if info.skin is not None and mesh.joints is not None:
            blend = self._skin_blend(info.skin, mesh)
            unweighted = mesh.weights.sum(axis=1) == 0      # no influence: left where its node puts it
            blend[unweighted] = self.world_matrix(node)
            how = f"rest pose of skin {info.skin}"
        else:
            blend = np.broadcast_to(self.world_matrix(node), (len(mesh.neutral), 4, 4))
            how = f"node {node} world transform"
        linear = blend[:, :3, :3]
        neutral = np.einsum("vij,vj->vi", linear, mesh.neutral.astype(np.float64)) + blend[:, :3, 3]
        deltas = np.einsum("vij,svj->svi", linear, mesh.deltas.astype(np.float64))
        return mesh, neutral.astype(np.float32), deltas.astype(np.float32), how

    def image(self, index: int) -> tuple[bytes, str]:
        """Image `index`'s bytes and its file suffix (`.png`, `.jpg`, or what its MIME type or URI says), from its
        buffer view or its URI (checked at load as the buffers are). RigError when it cannot be read."""
        images = self.gltf.images or []
        if not isinstance(index, int) or not 0 <= index < len(images):
            raise RigError(f"{self.path}: image {index} does not exist")
        image = images[index]
        try:
            if isinstance(image.bufferView, int):
                if not 0 <= image.bufferView < len(self.gltf.bufferViews):
                    raise RigError(f"{self.path}: image {index}: buffer view {image.bufferView} does not exist")
                view = self.gltf.bufferViews[image.bufferView]
                data = self.reader.buffer(view.buffer)
                start, length = view.byteOffset or 0, view.byteLength
                if not isinstance(length, int) or start + length > len(data):
                    raise RigError(f"{self.path}: image {index} lies outside its buffer")
                blob = bytes(data[start:start + length])
            elif isinstance(image.uri, str):
                blob = read_gltf_uri(self.path, image.uri)
            else:
                raise RigError(f"{self.path}: image {index} has neither a buffer view nor a URI")
        except (OSError, ValueError) as exc:
            raise RigError(f"{self.path}: image {index} cannot be read ({exc})") from None
        if blob.startswith(b"\x89PNG\r\n\x1a\n"):
            return blob, ".png"
        if blob.startswith(b"\xff\xd8\xff"):
            return blob, ".jpg"
        kind = (image.mimeType or "").rpartition("/")[2] or Path(str(image.uri or "")).suffix.lstrip(".")
        return blob, f".{kind.lower()}" if kind else ".bin"

    def _skin_blend(self, skin_index: int, mesh: GltfMesh) -> np.ndarray:
        """(V, 4, 4): per vertex, sum_k weight_k * world(joint_k) @ inverseBindMatrix_k."""
        path = self.path
        if not 0 <= skin_index < len(self.gltf.skins or []):
            raise RigError(f"{path}: skin {skin_index} does not exist")
        skin = self.gltf.skins[skin_index]
        joints = list(skin.joints or [])
        if skin.inverseBindMatrices is None:
            inverse = np.broadcast_to(np.eye(4), (len(joints), 4, 4))
        else:
            inverse = self.reader.matrices(skin.inverseBindMatrices, f"skin {skin_index} inverseBindMatrices")
            if len(inverse) != len(joints):
                raise RigError(f"{path}: skin {skin_index} has {len(joints)} joints but {len(inverse)} inverse "
                               "bind matrices")
        if mesh.joints.size and int(mesh.joints.max()) >= len(joints):
            raise RigError(f"{path}: mesh {mesh.index} JOINTS_0 names joint {int(mesh.joints.max())} of skin "
                           f"{skin_index}, which has {len(joints)}")
        per_joint = np.stack([self.world_matrix(j) @ inverse[k] for k, j in enumerate(joints)]) if joints else \
            np.zeros((1, 4, 4))
        return np.einsum("vk,vkij->vij", mesh.weights.astype(np.float64), per_joint[mesh.joints])
