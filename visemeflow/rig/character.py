"""Characters: a mesh with named blendshapes (morph targets), whatever the naming convention of its rig.

A `Character` holds the neutral mesh, its triangles and one delta per named shape (shape - neutral), in the
character's own names and order. `conventions.py` says how our 16 viseme curves drive those names; the exporters
(glTF, USD, Live Link, web JSON) and the preview write or show the character's own shapes.

Loaders (`load.load_character(path)` picks one by the path):
- a `.glb` / `.gltf` scene with morph targets (`gltf.read_character_glb`, through pygltflib): every mesh whose
  targets match (head, teeth, eyes ...) joined as the scene places them, each kept as a `CharacterPart` (its vertex
  range and own target order) so the GLB export animates the user's own asset (`gltf_asset`),
- a compact `.npz` written by `save_character_npz` (or one of our 16-viseme rig files, `rig.save_rig_npz`),
- a folder of meshes (OBJ/PLY, gzipped or not): `neutral.<ext>` and one file per shape, named by the shape.
Every loader ends in `validate_character`, which names the file and what is wrong: no shapes, an empty or
duplicate shape name, non-finite vertices, deltas of the wrong size, faces outside the mesh.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from visemeflow.atomic import atomic_path
from visemeflow.rig import RigError, VisemeRig, load_rig_npz, read_mesh
from visemeflow.rig.io import check_npz_sizes
from visemeflow.visemes import VISEMES


class CharacterError(ValueError):
    """A character that cannot be used: the message names the file and what is wrong with it."""


@dataclass(frozen=True)
class CharacterPart:
    """One mesh of a glTF scene that the character drives (a head, the teeth, an eye ...)."""

    mesh: int
    """The mesh's index in the file's `meshes`."""
    nodes: tuple[int, ...]
    """The nodes that instance it (each gets a `weights` channel in the exported GLB)."""
    name: str
    start: int
    """Its first vertex in the character's joined arrays."""
    stop: int
    """One past its last vertex."""
    target_names: tuple[str, ...]
    """Its own morph target names, in its own order."""
    placement: str = ""
    """How its vertices were put in the scene's space (node transform, skin rest pose)."""
    node_name: str = ""
    """The name people know it by when that is not `name`: its first node's, the object Blender and the engines
    show (`Head` for the mesh `HeadMesh`); "" when the two are the same."""

    def summary(self) -> str:
        """`Head (mesh HeadMesh, 4,418 v)`, or `Head (4,418 v)` when node and mesh share the name."""
        return (f"{self.node_name} (mesh {self.name}, {self.n_vertices:,} v)" if self.node_name
                else f"{self.name} ({self.n_vertices:,} v)")

    @property
    def n_vertices(self) -> int:
        return self.stop - self.start

    def columns(self, shape_names: tuple[str, ...] | list[str]) -> list[int]:
        """The character's shape index of each of its targets, in its target order."""
        index = {n: i for i, n in enumerate(shape_names)}
        return [index[n] for n in self.target_names]


@dataclass(frozen=True, eq=False)
class Character:
    """A mesh with named blendshapes: vertices(w) = neutral + sum_s w_s deltas[s]."""

    name: str
    source: str
    """The file or folder it was read from ("" for one built in memory)."""
    neutral: np.ndarray
    """(V, 3) float32 rest positions, in the mesh's own units and axes."""
    faces: np.ndarray
    """(F, 3) int32 triangles."""
    shape_names: tuple[str, ...]
    """The S shape (morph target) names, in the character's order."""
    deltas: np.ndarray
    """(S, V, 3) float32, shape - neutral, in `shape_names` order."""
    vertex_colors: np.ndarray | None = None
    """(V, 3) float32 RGB in [0, 1] for previews (lips, teeth, mouth socket), or None (grey)."""
    parts: tuple[CharacterPart, ...] = ()
    """For a glTF character: the driven meshes, their vertex ranges in the joined arrays above and their own target
    orders (the exported GLB animates each in its order); () for characters of one mesh from elsewhere."""
    left_out: tuple[str, ...] = ()
    """For a glTF character: the scene's meshes that are not driven, each with why ("Body (no targets)")."""
    landmark_ids: np.ndarray | None = None
    """(68,) int64 Multi-PIE landmark vertex ids (-1 = none) when known (the demo rig, transferred characters):
    then the lips can be measured on the mesh (`animation.lips`); None otherwise."""
    mm_per_unit: float = 1000.0
    """Millimetres per mesh unit: 1000 for metres (glTF's unit), 10 for the ICT demo rig's centimetres."""

    @property
    def n_vertices(self) -> int:
        return int(self.neutral.shape[0])

    @property
    def n_shapes(self) -> int:
        return len(self.shape_names)

    def in_metres(self) -> Character:
        """This character with its positions and shapes in metres (glTF's unit; itself when already so): what a
        new GLB of it holds, so that a tool opening it sees a head a head's size (the demo rig's centimetres
        written as they are made it 100 times too large in Blender, Unity and three.js)."""
        if self.mm_per_unit == 1000.0:
            return self
        s = np.float32(self.mm_per_unit / 1000.0)
        return replace(self, neutral=self.neutral * s, deltas=self.deltas * s, mm_per_unit=1000.0)

    def shape_index(self, name: str) -> int:
        return self.shape_names.index(name)

    def where(self) -> str:
        return f"character {self.name!r}" + (f" ({self.source})" if self.source else "")

    @property
    def label(self) -> str:
        """What people call it: its file's name without the suffix (`avatar` for avatar.glb, whose head mesh may be
        named `Wolf3D_Head`), else its own name."""
        return Path(self.source).stem if self.source else self.name

    def describe(self) -> str:
        """Which meshes it drives, for people: `character a.glb: driving Head (2,162 v), Teeth (480 v): 67 shared
        targets; not driven: Body (no targets)`."""
        label = Path(self.source).name if self.source else self.name
        if not self.parts:
            return f"character {label}: {self.n_vertices:,} vertices, {self.n_shapes} shapes"
        driving = ", ".join(p.summary() for p in self.parts)
        shared = set(self.parts[0].target_names).intersection(*(p.target_names for p in self.parts[1:]))
        text = f"character {label}: driving {driving}: "
        if len(self.parts) == 1 or len(shared) == self.n_shapes:
            text += f"{self.n_shapes} targets" + (" on every mesh" if len(self.parts) > 1 else "")
        else:   # "3 shared targets (34 in all)" read as 3 driven: a user's probe
            text += f"{self.n_shapes} targets, {len(shared)} of them on every mesh"
        return text + (f"; not driven: {', '.join(self.left_out)}" if self.left_out else "")


def validate_character(character: Character) -> Character:
    """Raise CharacterError naming the first problem (and the file); return the character when it is usable."""
    where = character.where()
    neutral = np.asarray(character.neutral)
    if neutral.ndim != 2 or neutral.shape[1] != 3 or neutral.shape[0] == 0:
        raise CharacterError(f"{where}: the neutral mesh must be (V, 3) with V > 0, got {neutral.shape}")
    if not np.isfinite(neutral).all():
        bad = int(np.flatnonzero(~np.isfinite(neutral).all(axis=1))[0])
        raise CharacterError(f"{where}: the neutral mesh has NaN or infinite coordinates (first at vertex {bad})")
    names = list(character.shape_names)
    if not names:
        raise CharacterError(f"{where}: the mesh has no blendshapes (morph targets); a character needs named shapes")
    empty = [i for i, n in enumerate(names) if not isinstance(n, str) or not n.strip()]
    if empty:
        raise CharacterError(f"{where}: shape {empty[0]} has no name; every blendshape needs a unique name")
    seen: dict[str, int] = {}
    for i, n in enumerate(names):
        if n in seen:
            raise CharacterError(f"{where}: the shape name {n!r} is used twice (shapes {seen[n]} and {i})")
        seen[n] = i
    deltas = np.asarray(character.deltas)
    if deltas.shape != (len(names), neutral.shape[0], 3):
        raise CharacterError(f"{where}: expected {len(names)} shape deltas of ({neutral.shape[0]}, 3), "
                             f"got {deltas.shape}")
    finite = np.isfinite(deltas).reshape(len(names), -1).all(axis=1)
    if not finite.all():
        raise CharacterError(f"{where}: shape {names[int(np.flatnonzero(~finite)[0])]!r} has NaN or infinite "
                             "coordinates")
    faces = np.asarray(character.faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise CharacterError(f"{where}: faces must be (F, 3) integer triangles, got {faces.dtype} {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= neutral.shape[0]):
        raise CharacterError(f"{where}: face vertex ids must lie in [0, {neutral.shape[0]}), "
                             f"got {faces.min()}..{faces.max()}")
    colors = character.vertex_colors
    if colors is not None and (np.shape(colors) != neutral.shape or not np.isfinite(colors).all()
                               or np.min(colors) < 0 or np.max(colors) > 1):
        raise CharacterError(f"{where}: vertex colours must be ({neutral.shape[0]}, 3) RGB in [0, 1]")
    end = 0
    for part in character.parts:
        if part.start != end or part.stop <= part.start or part.stop > neutral.shape[0]:
            raise CharacterError(f"{where}: part {part.name!r} covers vertices {part.start}..{part.stop}; parts must "
                                 f"tile the {neutral.shape[0]} vertices in order")
        unknown = [n for n in part.target_names if n not in seen]
        if unknown or len(set(part.target_names)) != len(part.target_names):
            raise CharacterError(f"{where}: part {part.name!r} has targets {unknown or list(part.target_names)} "
                                 "that are not the character's shapes once each")
        end = part.stop
    if character.parts and end != neutral.shape[0]:
        raise CharacterError(f"{where}: its parts cover {end} of its {neutral.shape[0]} vertices")
    return character


def make_character(name: str, neutral, faces, shape_names, deltas, source: str | os.PathLike = "",
                   vertex_colors=None, parts=(), left_out=()) -> Character:
    """A validated Character from arrays (converted to float32 / int32)."""
    return validate_character(Character(
        name=name, source=str(source), neutral=np.ascontiguousarray(neutral, np.float32),
        faces=np.ascontiguousarray(faces, np.int32), shape_names=tuple(shape_names),
        deltas=np.ascontiguousarray(deltas, np.float32),
        vertex_colors=None if vertex_colors is None else np.ascontiguousarray(vertex_colors, np.float32),
        parts=tuple(parts), left_out=tuple(left_out)))


def character_from_rig(rig: VisemeRig, source: str | os.PathLike = "") -> Character:
    """A 16-viseme rig (our convention: one shape per viseme, named as `visemes.VISEMES`) as a character, with its
    landmarks (so its lips can be measured) and the rigs' centimetres."""
    character = make_character(rig.name, rig.neutral, rig.faces, VISEMES, rig.deltas, source, rig.vertex_colors)
    return replace(character, landmark_ids=np.asarray(rig.landmark_ids, np.int64), mm_per_unit=10.0)


_NPZ_KEYS = ("neutral", "faces", "shape_names", "deltas")


def save_character_npz(character: Character, path: str | os.PathLike) -> Path:
    """Write a compact character file (`load_character` reads it back exactly)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            colors = {} if character.vertex_colors is None else {"vertex_colors": character.vertex_colors}
            np.savez_compressed(f, name=np.array(character.name), neutral=character.neutral, faces=character.faces,
                                shape_names=np.array(character.shape_names), deltas=character.deltas, **colors)
    return path


def load_character_npz(path: Path, name: str | None) -> Character:
    try:
        check_npz_sizes(path)
        with np.load(path, allow_pickle=False) as data:
            keys = set(data.files)
            if set(_NPZ_KEYS) <= keys:
                return make_character(name or str(data["name"]) if "name" in keys else name or path.stem,
                                      data["neutral"], data["faces"], [str(n) for n in data["shape_names"]],
                                      data["deltas"], path,
                                      data["vertex_colors"] if "vertex_colors" in keys else None)
    except (OSError, ValueError) as exc:
        raise CharacterError(f"{path}: not a readable .npz character file ({exc})") from None
    try:
        rig = load_rig_npz(path)
    except RigError as exc:
        raise CharacterError(f"{path}: neither a character file (keys {', '.join(_NPZ_KEYS)}) nor a viseme rig: "
                             f"{exc}") from None
    return character_from_rig(rig, path) if name is None else make_character(
        name, rig.neutral, rig.faces, VISEMES, rig.deltas, path, rig.vertex_colors)


_MESH_SUFFIXES = (".obj", ".ply", ".obj.gz", ".ply.gz")


def _mesh_name(path: Path) -> str | None:
    lower = path.name.lower()
    for suffix in _MESH_SUFFIXES:
        if lower.endswith(suffix):
            return path.name[: -len(suffix)]
    return None


def load_character_folder(path: Path, name: str | None) -> Character:
    meshes = {stem: p for p in sorted(path.iterdir()) if p.is_file() and (stem := _mesh_name(p)) is not None}
    neutral_key = next((k for k in meshes if k.lower() in ("neutral", "base", "basis")), None)
    if neutral_key is None:
        raise CharacterError(f"{path}: a character folder needs neutral.obj (or .ply) and one mesh per shape; "
                             f"found {', '.join(sorted(meshes)) or 'no meshes'}")
    try:
        base = read_mesh(meshes.pop(neutral_key))
        shapes = {k: read_mesh(p) for k, p in meshes.items()}
    except RigError as exc:
        raise CharacterError(str(exc)) from None
    for key, mesh in shapes.items():
        if mesh.vertices.shape != base.vertices.shape:
            raise CharacterError(f"{meshes[key]}: {len(mesh.vertices)} vertices, the neutral has "
                                 f"{len(base.vertices)}; every shape must share the neutral's topology")
    names = list(shapes)
    deltas = (np.stack([shapes[k].vertices for k in names]) - base.vertices[None]) if names else \
        np.zeros((0,) + base.vertices.shape, np.float32)
    return make_character(name or path.name, base.vertices, base.faces, names, deltas, path)
