"""Prefect's cached task results inside a store: written as JSON data, and checked before Prefect reads them.

A store is copied between people and drives, so nothing in it may run code when read. Prefect reads a result
record with whatever serializer the record's own metadata names (a pickle runs its `__reduce__`; Prefect's "json"
serializer imports any module a `__class__` field names), so choosing our serializer for writing is not enough:
`check_result_record` looks at a record as plain JSON before Prefect touches it and accepts only records whose
serializer is `StoreJSONSerializer`, which decodes plain JSON plus tagged datetimes and nothing else.
"""

import json
import os
import stat
from datetime import datetime
from pathlib import Path, PurePath
from typing import Any, Literal

import numpy as np
from prefect.serializers import Serializer
from pydantic import Field

SERIALIZER_TYPE = "visemeflow-json"
# A record of one task's report is kilobytes; a file far past this is not one, and is not read into memory.
MAX_RECORD_BYTES = 64 * 1024 * 1024
RECORD_FIELDS = {"metadata", "result"}
METADATA_FIELDS = {"storage_key", "expiration", "serializer", "prefect_version", "storage_block_id"}
_DATETIME_TAG = "__datetime__"


class UntrustedResultError(ValueError):
    """A file in a store's results folder that is not a JSON result record of `StoreJSONSerializer`."""


def _to_json_data(value: Any, where: str = "result") -> Any:
    """`value` as JSON data: dicts with str keys, lists, str, numbers, bools, None; datetimes tagged."""
    if value is None or isinstance(value, (str, bool, int, float)):
        return value
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise TypeError(f"{where} has a {type(k).__name__} key {k!r}; a JSON result's keys are strings")
            out[k] = _to_json_data(v, f"{where}[{k!r}]")
        return out
    if isinstance(value, (list, tuple)):
        return [_to_json_data(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, datetime):
        return {_DATETIME_TAG: value.isoformat()}
    if isinstance(value, PurePath):
        return str(value)
    if isinstance(value, np.generic):
        return _to_json_data(value.item(), where)
    if isinstance(value, BaseException):
        # Prefect writes a failed task's exception as its result; kept as a description, never rebuilt on reading
        return {"error_type": f"{type(value).__module__}.{type(value).__qualname__}", "message": str(value)}
    raise TypeError(f"{where} is a {type(value).__module__}.{type(value).__qualname__}; a task's cached result "
                    "must be JSON data (dict, list, str, number, bool, None, datetime)")


def _from_json_object(obj: dict[str, Any]) -> Any:
    if len(obj) == 1 and isinstance(obj.get(_DATETIME_TAG), str):
        return datetime.fromisoformat(obj[_DATETIME_TAG])
    return obj


class StoreJSONSerializer(Serializer):
    """Task results as JSON data: tuples come back as lists, paths and numpy scalars as their plain values, an
    exception as `{"error_type", "message"}`."""

    type: Literal["visemeflow-json"] = Field(default=SERIALIZER_TYPE, frozen=True)

    def dumps(self, obj: Any) -> bytes:
        return json.dumps(_to_json_data(obj), ensure_ascii=False).encode()

    def loads(self, blob: bytes) -> Any:
        return json.loads(blob, object_hook=_from_json_object)


def check_result_record(path: Path) -> None:
    """Raise `UntrustedResultError` (naming `path`) unless it is a regular file holding a JSON result record whose
    serializer is `StoreJSONSerializer`. Reads it as plain JSON only: nothing in it is decoded or imported."""
    info = os.lstat(path)
    if not stat.S_ISREG(info.st_mode):
        raise UntrustedResultError(f"{path}: a cached result must be a regular file, not a link or special file")
    if info.st_size > MAX_RECORD_BYTES:
        raise UntrustedResultError(f"{path}: {info.st_size} bytes, more than a cached result record holds "
                                   f"({MAX_RECORD_BYTES} at most)")
    check_result_bytes(path, path.read_bytes())


def check_result_bytes(path: object, data: bytes) -> None:
    """`check_result_record` of the bytes of the record at `path` (named in the error)."""
    try:
        record = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise UntrustedResultError(f"{path}: not a JSON result record ({type(exc).__name__}: {exc}); a raw pickle "
                                   "or other binary is never loaded") from None
    if not isinstance(record, dict) or set(record) != RECORD_FIELDS or not isinstance(record["metadata"], dict):
        raise UntrustedResultError(f"{path}: not a result record (expected a JSON object with exactly "
                                   f"{sorted(RECORD_FIELDS)}, 'metadata' an object)")
    metadata = record["metadata"]
    if not set(metadata) <= METADATA_FIELDS:
        raise UntrustedResultError(f"{path}: unknown result metadata {sorted(set(metadata) - METADATA_FIELDS)}")
    serializer = metadata.get("serializer")
    if serializer != {"type": SERIALIZER_TYPE}:
        named = serializer.get("type") if isinstance(serializer, dict) else serializer
        raise UntrustedResultError(
            f"{path}: result serialized with {named!r}, expected {SERIALIZER_TYPE!r}; a store's cached results "
            "are JSON data only, and pickles or other serializers are never loaded")
    if not isinstance(record["result"], str):
        raise UntrustedResultError(f"{path}: the record's result is a {type(record['result']).__name__}, "
                                   "expected the JSON text of the result")
