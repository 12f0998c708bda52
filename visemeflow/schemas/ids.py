"""Utterance ids (`<speaker>/<name>`) and other names that become parts of store paths."""

import re
import zlib

_PART = re.compile(r"^[A-Za-z0-9_.\-]+$")


class InvalidIdError(ValueError):
    """An id that is not `<speaker>/<name>` of letters, digits and `_ - .`, or that could escape a folder."""


def validate_name(name: str, what: str = "name") -> str:
    """`name` if it is one safe path component (letters, digits, `_ - .`, not `.` or `..`)."""
    if not isinstance(name, str) or not _PART.match(name) or name in {".", ".."} or name.startswith("."):
        raise InvalidIdError(
            f"invalid {what} {name!r}: use letters, digits, '_', '-' and '.', not starting with '.'"
        )
    return name


def validate_utterance_id(utterance_id: str) -> str:
    """`utterance_id` if it is `<speaker>/<name>` with two safe components."""
    parts = utterance_id.split("/") if isinstance(utterance_id, str) else []
    if len(parts) != 2:
        raise InvalidIdError(f"invalid utterance id {utterance_id!r}: expected '<speaker>/<name>'")
    validate_name(parts[0], f"speaker in utterance id {utterance_id!r}")
    validate_name(parts[1], f"name in utterance id {utterance_id!r}")
    return utterance_id


def split_utterance_id(utterance_id: str) -> tuple[str, str]:
    """(speaker, name) of a valid utterance id."""
    speaker, name = validate_utterance_id(utterance_id).split("/")
    return speaker, name


def shard_of(utterance_id: str, n_shards: int) -> int:
    """Stable shard number of an utterance: the same in every run and process, whatever the corpus size."""
    return zlib.crc32(utterance_id.encode("utf-8")) % n_shards
