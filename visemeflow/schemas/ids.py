"""Utterance ids (`<speaker>/<name>`) and other names that become parts of store paths.

Utterance ids come from corpus folder and file names (or a manifest), so they hold what people name things
with: letters of any script, digits, spaces and punctuation (`Speaker One/take 1`, `Sprecher_ü/a`, `张三/一`).
An id is safe by construction:

- exactly one `/`, between a non-empty speaker and a non-empty name;
- each part is NFC-normalised Unicode (the same id on every OS: macOS file names arrive decomposed, use
  `make_utterance_id`), made of letters, marks, digits, punctuation, symbols and the ASCII space only: no
  backslash, no control or format characters (no NUL, newline, bidi override), no other whitespace;
- no part starts with `.` (so no `.` or `..` part and no hidden file), none starts or ends with a space.

An id is never used raw as a path. Store paths are made by `id_path_parts`: every character outside
`[A-Za-z0-9_.~-]` is percent-encoded as UTF-8 bytes (`张三` -> `%E5%BC%A0%E4%B8%89`, a space -> `%20`, `%` ->
`%25`). The encoding is reversible (`utterance_id_from_path_parts`), ASCII-only and the same on every OS, and
ids of the old rule (ASCII letters, digits, `_ - .`) map to the same paths as before, so older stores read
unchanged.

Other names (curve sources, variants, model and run names, stages) stay one plain ASCII component.
"""

import re
import unicodedata
import zlib
from urllib.parse import quote, unquote

_PART = re.compile(r"^[A-Za-z0-9_.\-]+$")
_SAFE_PATH_CHARS = "_.-"  # with ASCII letters, digits and `~` (always safe to `quote`): kept as they are
# A path component is at most 255 bytes on common file systems; the store adds `.parquet` and the atomic
# write's temporary name adds up to ~35 more, so an encoded part is kept to 200 characters.
MAX_ENCODED_PART = 200


class InvalidIdError(ValueError):
    """An id that is not a safe `<speaker>/<name>` (see the module's rules), or a name that could escape a folder."""


def validate_name(name: str, what: str = "name") -> str:
    """`name` if it is one safe path component (letters, digits, `_ - .`, not `.` or `..`)."""
    if not isinstance(name, str) or not _PART.match(name) or name in {".", ".."} or name.startswith("."):
        raise InvalidIdError(
            f"invalid {what} {name!r}: use letters, digits, '_', '-' and '.', not starting with '.'"
        )
    return name


def encode_path_part(part: str) -> str:
    """`part` as one ASCII path component: characters outside `[A-Za-z0-9_.~-]` percent-encoded (UTF-8)."""
    return quote(part, safe=_SAFE_PATH_CHARS, encoding="utf-8", errors="strict")


def _why_bad_part(part: str) -> str | None:
    """Why `part` cannot be a speaker or name of an utterance id, or None when it can."""
    if not part:
        return "is empty"
    if unicodedata.normalize("NFC", part) != part:
        return "is not NFC-normalised Unicode (build ids with make_utterance_id)"
    if part.startswith("."):
        return "starts with '.'"
    if part[0] == " " or part[-1] == " ":
        return "starts or ends with a space"
    for ch in part:
        if ch == "\\":
            return "holds a backslash '\\' (a path separator on Windows)"
        category = unicodedata.category(ch)
        if ch != " " and category[0] not in "LMNPS":
            return f"holds the character U+{ord(ch):04X} (Unicode category {category}); " \
                   "allowed are letters, digits, punctuation, symbols and spaces"
    if len(encode_path_part(part)) > MAX_ENCODED_PART:
        return f"is too long for a file name ({len(encode_path_part(part))} characters once encoded, at most {MAX_ENCODED_PART})"
    return None


def validate_utterance_id(utterance_id: str) -> str:
    """`utterance_id` if it is `<speaker>/<name>` with two safe parts (see the module's rules)."""
    if not isinstance(utterance_id, str):
        raise InvalidIdError(f"invalid utterance id {utterance_id!r}: not a string")
    parts = utterance_id.split("/")
    if len(parts) != 2:
        raise InvalidIdError(
            f"invalid utterance id {utterance_id!r}: expected '<speaker>/<name>' with exactly one '/'"
        )
    for what, part in zip(("speaker", "name"), parts):
        why = _why_bad_part(part)
        if why is not None:
            raise InvalidIdError(f"invalid utterance id {utterance_id!r}: the {what} {part!r} {why}")
    return utterance_id


def make_utterance_id(speaker: str, name: str) -> str:
    """The id of `name` spoken by `speaker` (e.g. a corpus folder and file stem), NFC-normalised and validated."""
    return validate_utterance_id(
        unicodedata.normalize("NFC", speaker) + "/" + unicodedata.normalize("NFC", name)
    )


def normalize_utterance_id(utterance_id: str) -> str:
    """An id typed or listed somewhere (a manifest, the command line) NFC-normalised, then validated."""
    if not isinstance(utterance_id, str):
        raise InvalidIdError(f"invalid utterance id {utterance_id!r}: not a string")
    return validate_utterance_id(unicodedata.normalize("NFC", utterance_id))


def split_utterance_id(utterance_id: str) -> tuple[str, str]:
    """(speaker, name) of a valid utterance id, as they are (not encoded for a path)."""
    speaker, name = validate_utterance_id(utterance_id).split("/")
    return speaker, name


def id_path_parts(utterance_id: str) -> tuple[str, str]:
    """(speaker folder, name stem) of a valid utterance id in store paths: percent-encoded, reversible."""
    speaker, name = split_utterance_id(utterance_id)
    return encode_path_part(speaker), encode_path_part(name)


_NOT_IN_FILE_NAMES = re.compile(r'[%/\\:*?"<>|]')   # `%` too, so that the names stay reversible


def readable_path_parts(utterance_id: str) -> tuple[str, str]:
    """(speaker folder, name stem) of a valid utterance id for files a person opens (`--out` of animate and speak):
    the id as it reads (`my voice/take 1`, `张三/一`), only the characters no common file system takes in a name, and
    `%`, percent-encoded. Reversible like `id_path_parts`, and never longer in UTF-8 bytes than its parts (which
    validation keeps to 200 characters)."""
    speaker, name = split_utterance_id(utterance_id)
    encode = lambda part: _NOT_IN_FILE_NAMES.sub(lambda m: quote(m.group(0), safe=""), part)  # noqa: E731
    return encode(speaker), encode(name)


def utterance_id_from_path_parts(speaker_part: str, name_part: str) -> str:
    """The utterance id whose store path parts are these (the inverse of `id_path_parts`)."""
    speaker = unquote(speaker_part, encoding="utf-8", errors="strict")
    name = unquote(name_part, encoding="utf-8", errors="strict")
    utterance_id = validate_utterance_id(f"{speaker}/{name}")
    if id_path_parts(utterance_id) != (speaker_part, name_part):
        raise InvalidIdError(f"{speaker_part}/{name_part} is not a path made by the store")
    return utterance_id


def shard_of(utterance_id: str, n_shards: int) -> int:
    """Stable shard number of an utterance: the same in every run and process, whatever the corpus size."""
    return zlib.crc32(utterance_id.encode("utf-8")) % n_shards
