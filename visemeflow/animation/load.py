"""`load_character`: a character from a .glb/.gltf, a .npz (ours or a viseme rig) or a folder of meshes, validated.

Above `character` (the model and the npz/folder readers) and `gltf` (the glTF reader), so neither imports the other.
"""

from __future__ import annotations

import os
from pathlib import Path

from visemeflow.animation.character import Character, CharacterError, load_character_folder, load_character_npz
from visemeflow.animation.gltf import read_character_glb


def load_character(path: str | os.PathLike, name: str | None = None) -> Character:
    """Read a character from a .glb/.gltf, a .npz (ours or a viseme rig) or a folder of meshes; validated."""
    path = Path(path)
    if path.is_dir():
        return load_character_folder(path, name)
    if not path.is_file():
        raise CharacterError(f"{path}: no such character file or folder")
    suffix = path.suffix.lower()
    if suffix in (".glb", ".gltf"):
        return read_character_glb(path, name=name)
    if suffix == ".npz":
        return load_character_npz(path, name)
    raise CharacterError(f"{path}: unknown character format {suffix!r}; use .glb, .gltf, .npz or a folder of meshes")
