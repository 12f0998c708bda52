"""`load_character`: a character from a .glb/.gltf, a .npz (ours or a viseme rig) or a folder of meshes, validated.

Above `character` (the model and the npz/folder readers) and `gltf` (the glTF reader), so neither imports the other.
"""

from __future__ import annotations

import os
from pathlib import Path

from visemeflow.rig.character import Character, CharacterError, load_character_folder, load_character_npz
from visemeflow.animation.gltf import GLTF_SUFFIXES, read_character_glb
from visemeflow.shapes.conventions import Binding, bind, load_mapping_csv


def load_character(path: str | os.PathLike, name: str | None = None, meshes=None, extra_names=None) -> Character:
    """Read a character from a .glb/.gltf/.vrm, a .npz (ours or a viseme rig) or a folder of meshes; validated.

    For a glTF scene, `meshes` names the meshes to drive (default: chosen by their target names) and `extra_names`
    are shape names that count as usable besides the known conventions' (a mapping CSV's); see
    `gltf.read_character_glb`. `meshes` on another kind of character is an error."""
    path = Path(path)
    glb = path.suffix.lower() in GLTF_SUFFIXES and not path.is_dir()
    if meshes and not glb:
        raise CharacterError(f"{path}: --mesh chooses meshes of a .glb/.gltf scene; this character is one mesh")
    if path.is_dir():
        return load_character_folder(path, name)
    if not path.is_file():
        raise CharacterError(f"{path}: no such character file or folder")
    suffix = path.suffix.lower()
    if glb:
        return read_character_glb(path, name=name, meshes=meshes, extra_names=extra_names)
    if suffix == ".npz":
        return load_character_npz(path, name)
    raise CharacterError(f"{path}: unknown character format {suffix!r}; use .glb, .gltf, .vrm, .npz or a folder of "
                         "meshes")


def load_bound_character(path: str | os.PathLike, convention: str | None = None, mapping: str | os.PathLike | None = None,
                         meshes=None) -> tuple[Character, Binding]:
    """The character of `path` bound to the 16 visemes: by the mapping CSV (whose shape names count as usable in a
    glTF scene), else by `convention` (detected when None). CharacterError naming the file for either step."""
    extra = sorted({s for row in load_mapping_csv(mapping).values() for s in row}) if mapping else None
    character = load_character(path, meshes=meshes or None, extra_names=extra)
    return character, bind(character, convention, mapping)
