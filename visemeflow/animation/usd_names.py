"""Valid, distinct USD prim names for the names a user's file gives (meshes, shapes, joints, clips)."""

from __future__ import annotations

import re

__all__ = ["prim_name", "unique_prim_names"]

_INVALID = re.compile(r"[^A-Za-z0-9_]")


def prim_name(name: str) -> str:
    """`name` as a valid USD prim name: other characters become "_", a leading digit gets a "_" before it."""
    text = _INVALID.sub("_", str(name)) or "_"
    if text[0].isdigit():
        text = "_" + text
    return text


def unique_prim_names(names) -> list[str]:
    """One distinct prim name per shape: names that are valid keep theirs, the others get `prim_name` plus "_1",
    "_2" ... when that is taken."""
    names = [str(n) for n in names]
    used = {n for n in names if prim_name(n) == n}
    out = []
    for name in names:
        if prim_name(name) == name:
            out.append(name)
            continue
        base = candidate = prim_name(name)
        k = 1
        while candidate in used:
            candidate = f"{base}_{k}"
            k += 1
        used.add(candidate)
        out.append(candidate)
    return out
