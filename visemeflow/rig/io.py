"""Rig readers and writers: a folder of meshes (OBJ/PLY/GLB), one GLB with morph targets, the compact npz.

Vertex order is the rig's identity (landmark ids and deltas index it), so every reader keeps the file's order:
OBJ is parsed here, glTF/GLB by `rig.gltf.read_gltf_mesh` (pygltflib; the package's one glTF reader), PLY goes
through trimesh with `process=False, maintain_order=True` (the default processing merges and reorders vertices).
"""

from __future__ import annotations

import gzip
import json
import re
import warnings
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visemeflow.atomic import atomic_write
from visemeflow.rig.gltf import read_gltf_mesh
from visemeflow.rig.model import N_LANDMARKS, RigError, VisemeRig, validate_rig
from visemeflow.visemes import N_VISEMES, VISEMES

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf")
NPZ_FORMAT = "visemeflow-rig/1"


@dataclass(frozen=True)
class MeshData:
    """One mesh as read from a file: (V, 3) float64 vertices, (F, 3) int32 triangles, optional (V, 3) RGB in [0, 1]."""

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray | None = None


# ---------------------------------------------------------------------------------------------- meshes

def _mesh_suffix(path: Path) -> str:
    """Lower-case mesh suffix, looking through a trailing .gz (`a.obj.gz` -> `.obj`)."""
    suffixes = [s.lower() for s in path.suffixes]
    if suffixes and suffixes[-1] == ".gz":
        suffixes = suffixes[:-1]
    return suffixes[-1] if suffixes else ""


def _mesh_stem(path: Path) -> str:
    name = path.name
    if name.lower().endswith(".gz"):
        name = name[:-3]
    return name.rsplit(".", 1)[0]


_OBJ_VERTEX = re.compile(r"^v (.*)$", re.M)
_OBJ_FACE = re.compile(r"^f (.*)$", re.M)
_OBJ_REFS = re.compile(r"/\S*")   # a face token's /texture/normal references


def _numbers(rows: list[str], dtype, path: Path, what: str) -> tuple[np.ndarray, np.ndarray]:
    """The numbers of `rows` (one OBJ line's fields each, whitespace-separated) as one flat array, and each row's count.
    Parsed in one C call; a bad field is then looked for row by row, so that the error names its line."""
    counts = np.fromiter(map(len, map(str.split, rows)), np.int64, len(rows))
    with warnings.catch_warnings():
        warnings.simplefilter("error")   # numpy only warns when it stops at a field it cannot read
        try:
            flat = np.fromstring(" ".join(rows), dtype=dtype, sep=" ")
        except (ValueError, DeprecationWarning):
            flat = None
    if flat is None or len(flat) != counts.sum():
        for row in rows:
            for field in row.split():
                try:
                    dtype(field)
                except ValueError:
                    raise RigError(f"{path}: malformed OBJ {what} line: {row.strip()!r}") from None
        raise RigError(f"{path}: malformed OBJ {what} lines")
    return flat, counts


MAX_OBJ_BYTES = 256 << 20
"""The most bytes of OBJ text read (a mesh of a few million vertices; the ICT face's is 3 MB)."""
MAX_OBJ_GZ_RATIO = 100
"""The most an .obj.gz may unpack to beyond 16 MiB, as a multiple of its packed size (OBJ text packs 3-5 times; a
400 KB file that unpacks to 400 MB is a bomb)."""


def _read_obj_text(path: Path) -> str:
    """The OBJ's text (universal newlines, undecodable bytes replaced); RigError past ``MAX_OBJ_BYTES`` or, packed,
    past ``MAX_OBJ_GZ_RATIO`` times the packed size, found before more than that is unpacked."""
    packed = path.name.lower().endswith(".gz")
    try:
        size = path.stat().st_size
        limit = min(MAX_OBJ_BYTES, max(MAX_OBJ_GZ_RATIO * size, 16 << 20)) if packed else MAX_OBJ_BYTES
        if not packed and size > limit:
            raise RigError(f"{path}: {size} bytes of OBJ, more than the {MAX_OBJ_BYTES} an OBJ may have")
        with (gzip.open if packed else open)(path, "rb") as handle:
            data = handle.read(limit + 1)
    except (OSError, EOFError, zlib.error) as error:
        raise RigError(f"{path}: cannot read OBJ: {error}") from None
    if len(data) > limit:
        raise RigError(f"{path}: unpacks to more than {limit} bytes of OBJ (from {size} packed): more than "
                       + (f"{MAX_OBJ_GZ_RATIO} times its size, which no mesh packs to" if limit < MAX_OBJ_BYTES
                          else f"the {MAX_OBJ_BYTES} an OBJ may have"))
    return data.decode("utf-8", errors="replace").replace("\r\n", "\n").replace("\r", "\n")


def read_obj(path: Path | str) -> MeshData:
    """Wavefront OBJ (optionally gzip-compressed): `v` lines (with optional r g b), polygons split into fans, both in
    the file's order. Parsed with regular expressions and numpy's text reader (the ICT face's 26,719 vertices and
    26,384 quads in 0.05 s rather than 0.5 s line by line)."""
    path = Path(path)
    text = _read_obj_text(path)
    vertex_rows = _OBJ_VERTEX.findall(text)
    if not vertex_rows:
        raise RigError(f"{path}: OBJ has no vertices ('v' lines)")
    flat, widths = _numbers(vertex_rows, np.float64, path, "vertex")
    if widths.min() < 3:
        raise RigError(f"{path}: malformed OBJ vertex line: {vertex_rows[int(np.argmin(widths))].strip()!r}")
    colors = None
    if widths[0] in (6, 7) and (widths == widths[0]).all():
        table = flat.reshape(len(widths), widths[0])
        vertices, colors = table[:, :3], table[:, 3:6]
        if colors.max(initial=0.0) > 1.0:
            colors = colors / 255.0
    else:
        starts = np.cumsum(widths) - widths
        vertices = flat[starts[:, None] + np.arange(3)]
    n_vertices = len(vertices)
    face_rows = _OBJ_REFS.sub("", "\n".join(_OBJ_FACE.findall(text))).split("\n")
    if face_rows == [""]:
        return MeshData(vertices, np.zeros((0, 3), np.int32), colors)
    ids, sizes = _numbers(face_rows, int, path, "face")
    if sizes.min() < 3:
        raise RigError(f"{path}: OBJ face with {int(sizes.min())} vertices (need at least 3)")
    ids = np.where(ids < 0, ids + n_vertices, ids - 1)  # 1-based, negatives count back from the end
    # fans in the file's polygon order: polygon p of n corners from ids[o:o + n] gives (o, o+k, o+k+1), k = 1..n-2
    fans = sizes - 2
    first = np.repeat(np.cumsum(sizes) - sizes, fans)
    k = np.arange(len(first)) - np.repeat(np.cumsum(fans) - fans, fans) + 1
    faces = ids[np.stack([first, first + k, first + k + 1], axis=1)]
    if faces.min() < 0 or faces.max() >= n_vertices:
        raise RigError(f"{path}: OBJ face refers to a vertex outside 1..{n_vertices}")
    return MeshData(vertices, faces.astype(np.int32), colors)


def read_ply(path: Path | str) -> MeshData:
    """PLY through trimesh, vertex order kept; vertex colours when the file has them."""
    import trimesh

    path = Path(path)
    try:
        mesh = trimesh.load(path, file_type="ply", process=False, maintain_order=True, force="mesh")
    except Exception as error:  # trimesh raises many types for a bad file; name the file either way
        raise RigError(f"{path}: cannot read PLY: {error}") from None
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int32).reshape(-1, 3)
    colors = None
    visual = getattr(mesh, "visual", None)
    if visual is not None and getattr(visual, "kind", None) == "vertex":
        rgba = np.asarray(visual.vertex_colors)
        if rgba.shape[0] == len(vertices):
            colors = rgba[:, :3].astype(np.float64) / 255.0
    return MeshData(vertices, faces, colors)


def read_mesh(path: Path | str) -> MeshData:
    """Any supported mesh file (.obj[.gz], .ply, .glb, .gltf); a glTF gives its first mesh in scene order (with its
    COLOR_0 as sRGB colours), morph targets ignored (`rig.gltf.read_gltf_mesh`)."""
    path = Path(path)
    suffix = _mesh_suffix(path)
    if suffix == ".obj":
        return read_obj(path)
    if suffix == ".ply":
        return read_ply(path)
    if suffix in (".glb", ".gltf"):
        mesh = read_gltf_mesh(path, morph_targets=False)
        return MeshData(mesh.neutral.astype(np.float64), mesh.faces, mesh.colors)
    raise RigError(f"{path}: unsupported mesh format {suffix or '(none)'}; expected one of {', '.join(MESH_SUFFIXES)}")


# ---------------------------------------------------------------------------------------------- landmarks

def read_landmarks_json(path: Path | str) -> np.ndarray:
    """(68,) int64 vertex ids from a JSON list (null or -1 = none) or an object with a "landmark_ids" list."""
    path = Path(path)
    try:
        data = json.loads(path.read_text("utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise RigError(f"{path}: cannot read landmark ids: {error}") from None
    if isinstance(data, dict):
        data = data.get("landmark_ids")
    if not isinstance(data, list):
        raise RigError(f"{path}: expected a JSON list of {N_LANDMARKS} vertex ids (or {{\"landmark_ids\": [...]}})")
    if len(data) != N_LANDMARKS:
        raise RigError(f"{path}: expected {N_LANDMARKS} landmark vertex ids (Multi-PIE order), got {len(data)}")
    try:
        return np.array([-1 if v is None else int(v) for v in data], dtype=np.int64)
    except (TypeError, ValueError):
        raise RigError(f"{path}: landmark ids must be integers or null") from None


def _check_landmarks(landmarks: np.ndarray, n_vertices: int, source: Path) -> None:
    if landmarks.min() < -1 or landmarks.max() >= n_vertices:
        raise RigError(
            f"{source}: landmark ids must lie in [0, {n_vertices}) or be -1, got {landmarks.min()}..{landmarks.max()}"
        )


def _no_landmarks() -> np.ndarray:
    return np.full(N_LANDMARKS, -1, dtype=np.int64)


def _check_finite(vertices: np.ndarray, source: Path) -> None:
    finite = np.isfinite(vertices).all(axis=1)
    if not finite.all():
        raise RigError(f"{source}: non-finite vertex coordinates (first at vertex {int(np.flatnonzero(~finite)[0])})")


# ---------------------------------------------------------------------------------------------- rigs

def load_rig_folder(path: Path | str, name: str | None = None) -> VisemeRig:
    """A folder of `neutral.<ext>` and one mesh per viseme (`AAA.obj`, `mbp.ply`, ...; obj/ply/glb, any case).

    All meshes must share the neutral's vertex count and triangles. Optional `landmarks.json`: 68 vertex ids.
    Other mesh files are an error (a misspelt viseme would otherwise be silently missing); non-mesh files are ignored.
    """
    folder = Path(path)
    if not folder.is_dir():
        raise RigError(f"{folder}: not a folder")
    expected = {v.lower(): v for v in VISEMES}
    found: dict[str, Path] = {}
    for file in sorted(folder.iterdir()):
        if not file.is_file() or _mesh_suffix(file) not in MESH_SUFFIXES:
            continue
        key = _mesh_stem(file).lower()
        if key != "neutral" and key not in expected:
            raise RigError(
                f"{file}: unknown mesh name {_mesh_stem(file)!r}; expected 'neutral' or one of {', '.join(VISEMES)}"
            )
        if key in found:
            raise RigError(f"{file}: a second mesh for {key!r} (first: {found[key].name})")
        found[key] = file
    if "neutral" not in found:
        raise RigError(f"{folder}: no neutral mesh (neutral.obj, neutral.ply or neutral.glb)")
    missing = [v for v in VISEMES if v.lower() not in found]
    if missing:
        raise RigError(f"{folder}: missing viseme mesh(es) {', '.join(missing)} (e.g. {missing[0]}.obj)")

    neutral_file = found["neutral"]
    neutral = read_mesh(neutral_file)
    _check_finite(neutral.vertices, neutral_file)
    n_vertices = len(neutral.vertices)
    deltas = np.empty((N_VISEMES, n_vertices, 3), np.float32)
    for i, viseme in enumerate(VISEMES):
        file = found[viseme.lower()]
        mesh = read_mesh(file)
        if len(mesh.vertices) != n_vertices:
            raise RigError(
                f"{file}: {len(mesh.vertices)} vertices, but {neutral_file.name} has {n_vertices}; "
                "every viseme must share the neutral's topology"
            )
        if mesh.faces.shape != neutral.faces.shape or not np.array_equal(mesh.faces, neutral.faces):
            raise RigError(
                f"{file}: topology differs from {neutral_file.name} ({len(mesh.faces)} vs {len(neutral.faces)} "
                "triangles, or different vertex ids)"
            )
        _check_finite(mesh.vertices, file)
        deltas[i] = mesh.vertices - neutral.vertices

    landmark_file = next((f for f in folder.iterdir() if f.name.lower() == "landmarks.json"), None)
    landmarks = _no_landmarks()
    if landmark_file is not None:
        landmarks = read_landmarks_json(landmark_file)
        _check_landmarks(landmarks, n_vertices, landmark_file)
    colors = None if neutral.colors is None else np.clip(neutral.colors, 0.0, 1.0).astype(np.float32)
    rig = VisemeRig(
        name=name or folder.name,
        neutral=neutral.vertices.astype(np.float32),
        deltas=deltas,
        faces=neutral.faces.astype(np.int32),
        landmark_ids=landmarks,
        vertex_colors=colors,
    )
    _validate(rig, folder)
    return rig


def load_rig_glb(path: Path | str, name: str | None = None, landmarks: Path | str | None = None) -> VisemeRig:
    """One glTF/GLB whose morph targets are named by viseme (mesh `extras.targetNames`, any case).

    The mesh used is the first one with morph targets in scene order (`rig.gltf.read_gltf_mesh`); its primitives are
    joined, node transforms are not applied, COLOR_0 becomes the rig's (sRGB) vertex colours. Every morph target
    must be a viseme and all 16 must be there. Landmark ids come from `landmarks` (a JSON file), else
    `<stem>.landmarks.json` beside the file, else mesh `extras.landmark_ids`, else none (-1).
    """
    path = Path(path)
    mesh = read_gltf_mesh(path)
    if not mesh.target_names:
        raise RigError(f"{path}: no mesh with morph targets; the 16 visemes must be morph targets of one mesh")
    vertices, extras = mesh.neutral, mesh.extras
    _check_finite(vertices, path)
    expected = {v.lower(): v for v in VISEMES}
    by_viseme: dict[str, np.ndarray] = {}
    for target_name, delta in zip(mesh.target_names, mesh.deltas):
        key = target_name.lower()
        if key not in expected:
            raise RigError(f"{path}: unknown morph target name {target_name!r}; expected one of {', '.join(VISEMES)}")
        if expected[key] in by_viseme:
            raise RigError(f"{path}: morph target {target_name!r} appears twice")
        if not np.isfinite(delta).all():
            raise RigError(f"{path}: morph target {target_name!r} has non-finite coordinates")
        by_viseme[expected[key]] = delta
    missing = [v for v in VISEMES if v not in by_viseme]
    if missing:
        raise RigError(f"{path}: missing viseme morph target(s) {', '.join(missing)}")
    deltas = np.stack([by_viseme[v] for v in VISEMES]).astype(np.float32)

    landmark_ids = _no_landmarks()
    sidecar = Path(landmarks) if landmarks is not None else path.with_name(f"{path.name.split('.')[0]}.landmarks.json")
    if landmarks is not None or sidecar.is_file():
        landmark_ids = read_landmarks_json(sidecar)
        _check_landmarks(landmark_ids, len(vertices), sidecar)
    elif "landmark_ids" in extras:
        ids = extras["landmark_ids"]
        if not isinstance(ids, list) or len(ids) != N_LANDMARKS:
            raise RigError(f"{path}: extras.landmark_ids must list {N_LANDMARKS} vertex ids")
        try:
            landmark_ids = np.array([-1 if v is None else int(v) for v in ids], dtype=np.int64)
        except (TypeError, ValueError):
            raise RigError(f"{path}: extras.landmark_ids must be integers or null") from None
        _check_landmarks(landmark_ids, len(vertices), path)
    rig = VisemeRig(
        name=name or path.name.split(".")[0],
        neutral=vertices.astype(np.float32),
        deltas=deltas,
        faces=mesh.faces,
        landmark_ids=landmark_ids,
        vertex_colors=mesh.colors,
    )
    _validate(rig, path)
    return rig


def save_rig_npz(rig: VisemeRig, path: Path | str) -> Path:
    """The compact rig file: float16 deltas, float32 neutral, int32 faces, zip-compressed. Returns the path."""
    validate_rig(rig)
    path = Path(path)
    peak = float(np.abs(rig.deltas).max(initial=0.0))
    if peak > 6.0e4:
        raise RigError(f"rig {rig.name!r}: deltas up to {peak:g} overflow float16; rescale the mesh units")
    arrays = {
        "format": np.array(NPZ_FORMAT),
        "name": np.array(rig.name),
        "visemes": np.array(VISEMES),
        "neutral": rig.neutral.astype(np.float32),
        "deltas": rig.deltas.astype(np.float16),
        "faces": rig.faces.astype(np.int32),
        "landmark_ids": rig.landmark_ids.astype(np.int32),
    }
    if rig.vertex_colors is not None:
        arrays["vertex_colors"] = np.round(np.asarray(rig.vertex_colors) * 255.0).astype(np.uint8)
    for region, ids in rig.regions.items():
        arrays[f"region/{region}"] = np.asarray(ids).astype(np.int32)
    return atomic_write(path, lambda tmp: _write_npz(tmp, arrays))  # a rig file is whole or absent


def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """np.savez_compressed's format with fixed entry timestamps, so one rig always gives the same bytes."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for key, array in arrays.items():
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            with archive.open(info, "w", force_zip64=True) as handle:
                np.lib.format.write_array(handle, np.asanyarray(array), allow_pickle=False)


MAX_NPZ_BYTES = 1 << 30
"""The most bytes the arrays of one rig or character .npz may declare in all (1 GiB, as a glTF file)."""


def check_npz_sizes(path: Path | str, limit: int = MAX_NPZ_BYTES) -> None:
    """ValueError unless every array of the .npz at `path` declares no more bytes than its member holds
    uncompressed, and all together at most `limit`: `np.load` allocates an array's declared shape before it reads
    a byte, so a 1 kB file may otherwise ask for terabytes. Reads only the members' headers."""
    total = 0
    try:
        with zipfile.ZipFile(path) as archive:
            for info in archive.infolist():
                if not info.filename.endswith(".npy"):
                    continue
                with archive.open(info) as member:
                    version = np.lib.format.read_magic(member)
                    if version == (1, 0):
                        shape, _, dtype = np.lib.format.read_array_header_1_0(member)
                    elif version == (2, 0):
                        shape, _, dtype = np.lib.format.read_array_header_2_0(member)
                    else:   # 3.0 (utf-8 field names) is never written for these arrays
                        raise ValueError(f"array {info.filename}: .npy format {version} is not read here")
                declared = int(np.prod(shape, dtype=object)) * dtype.itemsize
                if declared > info.file_size:
                    raise ValueError(f"array {info.filename} declares {declared} bytes ({shape}, {dtype}) but holds "
                                     f"{info.file_size}")
                total += declared
                if total > limit:
                    raise ValueError(f"its arrays declare more than {limit >> 20} MiB")
    except zipfile.BadZipFile as exc:
        raise ValueError(f"not a zip archive ({exc})") from None


def load_rig_npz(path: Path | str) -> VisemeRig:
    """A rig written by `save_rig_npz`; arrays come back as float32 / int32 / int64 as VisemeRig documents."""
    path = Path(path)
    try:
        check_npz_sizes(path)
        archive = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as error:
        raise RigError(f"{path}: cannot read rig npz: {error}") from None
    with archive:
        keys = set(archive.files)
        missing = [k for k in ("neutral", "deltas", "faces", "landmark_ids") if k not in keys]
        if missing:
            raise RigError(f"{path}: not a visemeflow rig npz (missing {', '.join(missing)})")
        deltas = archive["deltas"].astype(np.float32)
        if "visemes" in keys:
            names = [str(v) for v in archive["visemes"]]
            if sorted(names) != sorted(VISEMES) or len(names) != N_VISEMES:
                raise RigError(f"{path}: viseme list {names} is not the 16 visemes {', '.join(VISEMES)}")
            if deltas.shape[0] == N_VISEMES:
                deltas = deltas[[names.index(v) for v in VISEMES]]
        colors = archive["vertex_colors"] if "vertex_colors" in keys else None
        if colors is not None:
            colors = colors.astype(np.float32) / (255.0 if colors.dtype == np.uint8 else 1.0)
        rig = VisemeRig(
            name=str(archive["name"]) if "name" in keys else path.stem,
            neutral=archive["neutral"].astype(np.float32),
            deltas=deltas,
            faces=archive["faces"].astype(np.int32),
            landmark_ids=archive["landmark_ids"].astype(np.int64),
            vertex_colors=colors,
            regions={k.split("/", 1)[1]: archive[k].astype(np.int64) for k in sorted(keys) if k.startswith("region/")},
        )
    _validate(rig, path)
    return rig


def load_rig(path: Path | str) -> VisemeRig:
    """Any rig: a folder of meshes, a .glb/.gltf with morph targets, or a .npz from `save_rig_npz`."""
    path = Path(path)
    if path.is_dir():
        return load_rig_folder(path)
    if not path.exists():
        raise RigError(f"{path}: no such rig file or folder")
    suffix = path.suffix.lower()
    if suffix in (".glb", ".gltf"):
        return load_rig_glb(path)
    if suffix == ".npz":
        return load_rig_npz(path)
    raise RigError(f"{path}: unknown rig format {suffix or '(none)'}; expected a folder, .glb, .gltf or .npz")


def _validate(rig: VisemeRig, source: Path) -> None:
    try:
        validate_rig(rig)
    except RigError as error:
        raise RigError(f"{source}: {error}") from None
