"""Short stable digests of configs and values, for cache keys and provenance."""

import hashlib
import json

from pydantic import BaseModel


def stable_hash(*values: object, size: int = 16) -> str:
    """Hex digest of JSON-able values (pydantic models by their JSON dump), stable across processes."""
    h = hashlib.blake2b(digest_size=size)
    for v in values:
        text = v.model_dump_json() if isinstance(v, BaseModel) else json.dumps(v, sort_keys=True, default=str)
        h.update(text.encode())
        h.update(b"\0")
    return h.hexdigest()
