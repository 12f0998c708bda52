"""Short stable digests of configs, values and files, for cache keys and provenance.

The one place a digest is computed: blake2b with a 16-byte digest unless told otherwise. Top-level and free of
imports from the rest of the package (but `hashmemo.py`, itself stdlib only), so every layer (the pure domain
packages included) can use it.

File digests are memoised across processes on the files' stat results (`hashmemo.py`: path, device, inode, size,
mtime and ctime; `VISEMEFLOW_HASH_MEMO` names the SQLite file or is `off`), so a cached rerun of a large corpus
does not read every input again; the digests are exactly those of the bytes, memo or not.
"""

import hashlib
import json
import os
from collections.abc import Iterable
from typing import Any

from pydantic import BaseModel

from visemeflow import hashmemo

DIGEST_SIZE = 16
_CHUNK = 1 << 20


def new_hasher(size: int = DIGEST_SIZE) -> "hashlib._Hash":
    """An empty hasher of the package's digest (blake2b), for content fed piece by piece."""
    return hashlib.blake2b(digest_size=size)


def stable_hash(*values: object, size: int = DIGEST_SIZE) -> str:
    """Hex digest of JSON-able values (pydantic models by their JSON dump), stable across processes."""
    h = new_hasher(size)
    for v in values:
        text = v.model_dump_json() if isinstance(v, BaseModel) else json.dumps(v, sort_keys=True, default=str)
        h.update(text.encode())
        h.update(b"\0")
    return h.hexdigest()


def _update_with_file(h: "hashlib._Hash", path: str | os.PathLike) -> None:
    with open(path, "rb") as fh:
        while chunk := fh.read(_CHUNK):
            h.update(chunk)


def _read_file_hash(path: str | os.PathLike, size: int) -> str:
    h = new_hasher(size)
    _update_with_file(h, path)
    return h.hexdigest()


def _read_files_hash(paths: list[str | os.PathLike | None], size: int) -> str:
    h = new_hasher(size)
    for p in paths:
        h.update(b"\0" if p is None else b"\1")
        if p is not None:
            _update_with_file(h, p)
            h.update(b"\0")
    return h.hexdigest()


def file_hash(path: str | os.PathLike, size: int = DIGEST_SIZE) -> str:
    """Hex digest of one file's bytes (read in chunks; memoised while the file's stat results are unchanged)."""
    return hashmemo.memoised("file", size, [path], lambda: _read_file_hash(path, size))


def files_hash(paths: Iterable[str | os.PathLike | None], size: int = DIGEST_SIZE) -> str:
    """Hex digest of several files' bytes, in order; a None entry counts as an absent file (distinct from an
    empty one), so (audio, None) and (None, audio) differ. All bytes feed one hasher (the digest is part of stored
    cache keys); the memo keeps the whole tuple's digest."""
    paths = list(paths)
    return hashmemo.memoised("files", size, paths, lambda: _read_files_hash(paths, size))


def without_added_defaults(data: dict[str, Any], added: dict[str, Any]) -> dict[str, Any]:
    """A config's JSON without the fields added after configs were first stored (`added`: name -> default) where
    they hold their default, so an older config means the same JSON (checkpoint resume keys, model names hashed
    from it, Prefect cache keys) as before they existed."""
    return {name: value for name, value in data.items() if name not in added or value != added[name]}
