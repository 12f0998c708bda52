"""Where a store lives: a local (or shared) folder, or a prefix on object storage (`s3://bucket/prefix`).

A store root is given as text everywhere (command line, flow parameters, task arguments): a path, or a URL whose
scheme fsspec knows (`s3://`; `gs://`, `az://`, `memory://` where their fsspec packages are installed). A URL store
is reached through fsspec (`universal_pathlib`'s `UPath`, so the store's path arithmetic is the same for both) and
shares nothing host-local: no rename, no `flock`, no pid. Credentials and the endpoint come from the environment
as every AWS tool reads them (`AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_ENDPOINT_URL` for an S3-compatible
server such as MinIO, Ceph or moto; or an AWS profile), so each worker machine needs only those variables.

What object storage gives instead of what a folder gives:
- A PUT is atomic: an object appears whole or not at all (a multipart upload only when it is completed). A file is
  written into a local temporary file and uploaded once, so a writer that fails or is killed uploads nothing.
- A create that must not overwrite (`If-None-Match: *`) and a replace of exactly the version read (`If-Match:
  <ETag>`) are conditional PUTs, which S3 (since 2024), MinIO and moto honour: the store's lock objects and its
  read-modify-write of shard files (a rerun of one utterance) use them (`Store.locked`, `replace_utterance_rows`).
- Listings are never cached (`use_listings_cache=False`): another machine's writes must be seen.

Input files may live there too (a corpus at `s3://bucket/corpus`): readers that take only a local path (soundfile,
PyAV, the TextGrid parser) get a local copy of each object, downloaded once per version of it (`local_input`: its
ETag names the copy, so a file replaced on the server is fetched again and an unchanged one costs one HEAD), in a
folder of this user's under the machine's temporary folder (`TMPDIR` chooses the disk). `mirror` gives a prefix's
objects as a local folder tree of such copies (hard links), which corpus discovery reads as it reads a folder;
there the media are only named (`object_identity`: their ETag and size), never downloaded, so discovering a corpus
costs a listing and its text files, and each audio or video file is fetched by the task that reads it.
"""

import errno
import fcntl
import hashlib
import os
import re
import secrets
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

from visemeflow.atomic import atomic_path
from visemeflow.hashing import file_hash, stable_hash

URL = re.compile(r"^(?P<scheme>[A-Za-z][A-Za-z0-9+.-]*)://(?P<rest>.*)$")

LOCAL_SCHEMES = frozenset({"file", "local"})

StoreRoot = Path | str
"""A store root as the parameters carry it: a local Path, or a URL as text."""


def is_url(root: object) -> bool:
    """Whether `root` names object storage (a URL with a scheme other than `file://`)."""
    if isinstance(root, os.PathLike):
        return False
    match = URL.match(str(root))
    return bool(match) and match["scheme"].lower() not in LOCAL_SCHEMES


def parse_root(root: object) -> StoreRoot:
    """`root` as the flows keep it: a URL stays text (a `Path` would fold its `//`), anything else becomes a Path
    (`file:///x` becomes `/x`)."""
    if isinstance(root, Path):
        return root
    if hasattr(root, "protocol") and hasattr(root, "fs"):   # a UPath (`Store.root` of a URL store)
        return parse_root(str(root))
    text = os.fspath(root) if isinstance(root, os.PathLike) else str(root)
    match = URL.match(text)
    if match and match["scheme"].lower() in LOCAL_SCHEMES:
        return Path("/" + match["rest"].lstrip("/"))
    if match:
        url = text.rstrip("/")
        if not match["rest"].strip("/"):
            raise ValueError(f"{text}: a store on object storage needs a bucket (s3://bucket/prefix)")
        if ".." in url.split("/") or "." in url.split("/")[3:]:
            raise ValueError(f"{text}: a store URL may not hold '.' or '..' segments")
        return url
    return Path(text)


def as_text(location: object) -> str:
    """A location as flows record it: a URL as it is, a local path made absolute."""
    parsed = parse_root(location)
    return parsed if isinstance(parsed, str) else str(parsed.resolve())


def remote_root(url: str):
    """The fsspec path (`upath.UPath`) of a URL store root; its filesystem caches no listings."""
    try:
        from upath import UPath
    except ImportError as exc:  # pragma: no cover - a dependency of the package
        raise RuntimeError("a store on object storage needs universal_pathlib and fsspec") from exc
    scheme = URL.match(url)["scheme"].lower()
    options = {"use_listings_cache": False} if scheme in {"s3", "s3a", "gs", "gcs", "az", "abfs"} else {}
    try:
        return UPath(url, **options)
    except (ImportError, ValueError) as exc:
        hint = " (pip install s3fs)" if scheme.startswith("s3") else ""
        raise ValueError(f"{url}: no filesystem for {scheme}:// URLs{hint}: {exc}") from exc


def remote_problem(url: str) -> str | None:
    """Why the store at `url` cannot be used, in one line (no filesystem package, no such bucket, no access, no
    endpoint answering); None when its bucket answers. One request."""
    try:
        root = remote_root(url)
    except (ValueError, RuntimeError) as exc:
        return str(exc)
    bucket = root.path.split("/", 1)[0]
    endpoint = os.environ.get("AWS_ENDPOINT_URL") or os.environ.get("AWS_ENDPOINT_URL_S3") or "AWS"
    try:
        if root.fs.exists(bucket):
            return None
        reason = "does not exist or this machine's credentials may not see it"
    except Exception as exc:   # botocore, aiohttp and fsspec each raise their own kinds
        reason = f"cannot be reached ({type(exc).__name__}: {exc})"
    where = f" at {endpoint}" if root.protocol in ("s3", "s3a") else ""
    return f"cannot use the store {url}: bucket {bucket!r}{where} {reason}"


def private_folder(kind: str, what: str) -> Path:
    """`visemeflow-<kind>-<uid>` in the machine's temporary folder, made when missing; PermissionError unless it is
    a folder of this user's that no one else may write (`what` it holds names it in the message): a copy planted
    there by another user would be read as the original."""
    folder = Path(tempfile.gettempdir()) / f"visemeflow-{kind}-{os.getuid()}"
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    info = os.lstat(folder)
    if not os.path.isdir(folder) or os.path.islink(folder) or info.st_uid != os.getuid() or info.st_mode & 0o022:
        raise PermissionError(errno.EPERM, f"{folder}: {what} must be in a folder of this user's that no one else "
                              "may write")
    return folder


def _version(info: dict) -> str:
    """What names one version of an object: its ETag (the server's digest of the content), else its time and size."""
    return str(info.get("ETag") or info.get("etag") or (info.get("mtime") or info.get("LastModified"), info.get("size")))


def _copy_path(url: str, version: str) -> Path:
    """Where the local copy of one version of the object `url` lives: `<digest of the URL>/<digest of the version>/`,
    holding the object under its own name (its suffix tells readers the format; messages show it), cut to keep
    within the file system's 255 bytes."""
    folder = private_folder("objects", "the local copies of objects (a copy planted there would be read as the "
                            "original)")
    name = url.rsplit("/", 1)[-1]
    while len(name.encode()) > 200:
        name = name[1:]
    return folder / _digest(url) / _digest(version) / name


def _digest(text: str) -> str:
    return hashlib.blake2b(text.encode(), digest_size=12).hexdigest()


def object_copy(fs, key: str, url: str, info: dict | None = None) -> str:
    """A local file holding the object `key` of the fsspec filesystem `fs` (`url` names it), downloaded once per
    version into this user's private folder; `info` (a listing's entry) spares the HEAD. The copy is written whole
    or not at all. Copies of the object's older versions are removed then, so the copies take the disk of the
    objects as they are now, not of every version ever read (a reader that opened an old copy keeps reading it)."""
    info = fs.info(key) if info is None else info
    if info.get("type") == "directory":
        raise IsADirectoryError(errno.EISDIR, f"{url} is a folder, not a file")
    local = _copy_path(url, _version(info))
    if not local.is_file():
        local.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        with atomic_path(local, keep_suffix=True, fsync=False) as tmp:
            fs.get_file(key, str(tmp))
        _drop_older_versions(local)
    return str(local)


def _drop_older_versions(copy: Path) -> None:
    for old in copy.parent.parent.iterdir():
        if old != copy.parent:
            shutil.rmtree(old, ignore_errors=True)


FETCH_CONCURRENCY = 32
"""Objects a mirror downloads at once (fsspec's batched `get` on an asynchronous filesystem such as S3): a first
discovery of 24,000 alignments is then latency / 32, not one round trip after another."""


def _fetch_copies(fs, wanted: list[tuple[str, Path]], concurrency: int = FETCH_CONCURRENCY) -> None:
    """Download the objects `key` into their local copies `copy` (paths of `_copy_path`), up to `concurrency` at
    once; each copy is written whole or not at all, and its object's older copies are removed."""
    if not wanted:
        return
    parts = []
    for _, copy in wanted:
        copy.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        parts.append(copy.with_name(f".{copy.name[:200]}.{os.getpid()}-{secrets.token_hex(4)}.part"))
    try:
        if getattr(fs, "async_impl", False):
            fs.get([key for key, _ in wanted], [str(p) for p in parts], batch_size=concurrency)
        else:
            for (key, _), part in zip(wanted, parts):
                fs.get_file(key, str(part))
        for (_, copy), part in zip(wanted, parts):
            os.replace(part, copy)
            _drop_older_versions(copy)
    finally:
        for part in parts:
            part.unlink(missing_ok=True)


def _write_if_changed(target: Path, text: str) -> None:
    """`target` holding `text`, replaced atomically (a hard link there is replaced, never written through)."""
    data = text.encode()
    try:
        if target.is_file() and not target.is_symlink() and target.stat().st_size == len(data) \
                and target.read_bytes() == data:
            return
    except OSError:
        pass
    with atomic_path(target, fsync=False) as tmp:
        Path(tmp).write_bytes(data)


def _link(source: str, target: Path) -> None:
    """`target` made a hard link to `source` (a copy where links are refused), replaced atomically; nothing done
    when it already is one."""
    if target.is_file() and os.path.samefile(target, source):
        return
    with atomic_path(target, fsync=False) as tmp:
        try:
            os.link(source, tmp)
        except OSError:
            shutil.copyfile(source, tmp)


def local_input(location: str | os.PathLike | None, beside: tuple[str, ...] = ()) -> str | None:
    """A local path to read the file `location` from: a path stays itself; a URL (`s3://bucket/corpus/a.wav`)
    becomes its local copy (`object_copy`). None and "" pass through. FileNotFoundError names the URL when the
    object is gone.

    `beside`: suffixes of files that readers look for next to this one under its stem (a synthetic video's
    `.camera.json`): where the object `<stem><suffix>` exists beside the URL, its copy is put next to the local copy
    under the same name, and a stale one is removed where it is gone."""
    if location is None or location == "" or not is_url(location):
        return None if location is None else os.fspath(location)
    location = str(location)
    path = remote_root(location)
    try:
        copy = object_copy(path.fs, path.path, location)
    except FileNotFoundError as exc:
        raise FileNotFoundError(errno.ENOENT, f"{location}: no such object", location) from exc
    folder, name = location.rsplit("/", 1)
    for suffix in beside:
        sibling = f"{folder}/{name.rsplit('.', 1)[0]}{suffix}"
        target = Path(copy).with_name(Path(sibling).name)
        there = remote_root(sibling)
        try:
            _link(object_copy(there.fs, there.path, sibling), target)
        except FileNotFoundError:
            target.unlink(missing_ok=True)
    return copy


def input_digest(location: str | os.PathLike) -> str:
    """What identifies the content of the input file `location` in cache keys: a file's digest of its bytes; an
    object's digest of its `object_identity` (ETag and size: one request, no download), as corpus discovery has
    it. FileNotFoundError names the URL when the object is gone."""
    if not is_url(location):
        return file_hash(location)
    path = remote_root(str(location))
    try:
        info = path.fs.info(path.path)
    except FileNotFoundError as exc:
        raise FileNotFoundError(errno.ENOENT, f"{location}: no such object", str(location)) from exc
    return stable_hash(object_identity(info))


def put_file(local: str | os.PathLike, url: str) -> str:
    """The local file uploaded to the object `url` in one PUT (a large file as a multipart upload, completed only
    when whole): the object appears whole or not at all. Returns `url`."""
    path = remote_root(url)
    path.fs.put_file(os.fspath(local), path.path)
    return url


def input_exists(location: str | os.PathLike | None) -> bool:
    """Whether the file `location` (a path or a URL) is there to be read."""
    if not location:
        return False
    if not is_url(location):
        return Path(location).is_file()
    path = remote_root(str(location))
    return path.fs.isfile(path.path)


def object_identity(info: dict) -> str:
    """One line naming the content of an object from a listing's entry, without reading it: its version (the ETag,
    the server's digest of the content; else its time) and its size."""
    return f"visemeflow object version {_version(info)} size {info.get('size')}\n"


def mirror(url: str, named_only: Callable[[str], bool] | None = None, concurrency: int = FETCH_CONCURRENCY) -> Path:
    """A local folder tree holding what lies under the prefix `url`: `<folder>/<key below the prefix>`, each file a
    hard link to the object's versioned local copy (`object_copy`; a copy where links are refused). Only objects
    whose version changed are downloaded; files of objects gone from the prefix are removed, so the tree is the
    prefix as it is now. Keys with empty, `.` or `..` segments are skipped (they could leave the folder).

    `named_only(name)` True: that object is not downloaded; its file in the tree holds `object_identity` instead (a
    few bytes that change whenever the object does), for what reads the tree only to find and tell files apart
    (corpus discovery: the media are read by each utterance's task, on whatever machine it runs, through
    `local_input`). Objects not yet copied are downloaded `concurrency` at a time. FileNotFoundError when nothing
    lies under `url`."""
    url = url.rstrip("/")
    root = remote_root(url)
    base = root.path.rstrip("/")
    listing = root.fs.find(base, detail=True, withdirs=False)
    digest = _digest(url)
    folder = private_folder("mirrors", "the local trees of objects under a prefix") / digest
    folder.mkdir(mode=0o700, exist_ok=True)
    wanted: set[Path] = set()
    copies: list[tuple[str, Path, Path]] = []   # key, its local copy, its file in the tree
    with open(folder.parent / f".{digest}.lock", "a") as lock:   # two flows on this machine mirror in turn
        fcntl.flock(lock, fcntl.LOCK_EX)
        for key, info in sorted(listing.items()):
            rel = key[len(base):].lstrip("/") if key.startswith(base) else ""
            parts = rel.split("/")
            if not rel or info.get("type") == "directory" or any(p in ("", ".", "..") for p in parts):
                continue
            target = folder.joinpath(*parts)
            wanted.add(target)
            if named_only is not None and named_only(parts[-1]):
                _write_if_changed(target, object_identity(info))
            else:
                copy = _copy_path(f"{url}/{rel}", _version(info))
                copies.append((key, copy, target))
        _fetch_copies(root.fs, [(key, copy) for key, copy, _ in copies if not copy.is_file()], concurrency)
        for _, copy, target in copies:
            _link(str(copy), target)
        for path in sorted(folder.rglob("*"), reverse=True):   # what is gone from the prefix; deepest first
            if path.is_file() and path not in wanted:
                path.unlink()
            elif path.is_dir() and not any(path.iterdir()):
                path.rmdir()
    if not wanted:
        raise FileNotFoundError(errno.ENOENT, f"{url}: no objects under this prefix", url)
    return folder
