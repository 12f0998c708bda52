"""Atomic file writes: the one way this package replaces a file.

A file is written to a temporary file in the target's folder, flushed to disk (fsync), renamed over the
target (`os.replace`) and the folder's entry flushed too. A reader sees the old file or the new one, whole;
a writer that fails removes its temporary file and leaves the old file in place; a killed writer leaves at
most its temporary file, which `Store.stale_temporary_files` (`visemeflow clean temporary`) finds.

Temporary names follow one pattern, so they can be recognised and never collide:

    .<target name>.<pid>-<machine>.<token>.tmp            .shard-0003.parquet.4242-9c1e04aa.1f3a9c0b.tmp
    .<target name>.<pid>-<machine>.<token>.tmp<suffix>    .sweep-x.png.4242-9c1e04aa.1f3a9c0b.tmp.png
                                                          (`keep_suffix=True`, for writers that pick the format
                                                          by the file's suffix)

The pid tells a dead writer's leftover from a live one's, on the machine that took it: `<machine>` names the
process space the pid belongs to (the kernel's boot id and the pid namespace, `this_machine`), so where several
machines or containers share a store's folder, none takes another's live writer for a dead one of its own. The
random token keeps two writers of one target apart (two threads share a pid). Names start with a dot, so readers that skip hidden files never
see a half-written file.

Durability costs time: the fsync of file and folder took 6-8 ms per file on this machine's disk (a 150-frame
curve file: about 3 ms to write without, 10 ms with), which dominates writing many small files. It protects against
a power loss or kernel crash (a rename reaching the disk before the data: an empty file), not against a killed
process, which the rename alone covers. `VISEMEFLOW_FSYNC=0` in the environment turns it off (e.g. for a bulk
rebuild that can simply be run again); the default is on.

Many small files (a shard's curve files) can share one flush: inside `group_sync()`, atomic writes skip their own
fsyncs and the block's end flushes every file system they touched at once (`syncfs`; where that is missing, each
file and folder in turn). Each file still appears whole or not at all; what the grouping gives up is only that,
after a power loss or kernel crash inside the block, a file renamed in it may come back empty or short. Whoever
writes a record that points at such files (a task's result, a shard table) writes it after the block ends, so a
crash leaves the block's work undone, not recorded as done; and a curve file that comes back empty counts as missing
(`Store.has_curves`, `Store.curves_provenance`: also one whose footer does not parse), so a rerun writes it again,
even where an older record of the same task is still there. (Linux before 5.8 reports no writeback error from
syncfs; per-file fsync did.)

This module uses the standard library only. It lives at the top of the package, beside `hashing.py`, so
that the pure domain packages (`tracking/`, `learning/`), which may not import `storage/` (DESIGN), write
their own files (videos, landmark files, checkpoints) through the same helper as the store.
"""

import contextvars
import ctypes
import ctypes.util
import functools
import hashlib
import os
import re
import secrets
import socket
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = [
    "atomic_path",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_text",
    "fsync_enabled",
    "group_sync",
    "is_temporary_name",
    "temporary_path",
    "temporary_writer",
    "temporary_writer_pid",
    "this_machine",
]

_TEMPORARY = re.compile(r"^\.(?P<target>.+)\.(?P<pid>[0-9]+)(?:-(?P<machine>[0-9a-f]{8}))?\.(?P<token>[0-9A-Za-z_]+)"
                        r"\.tmp(?P<suffix>\.[0-9A-Za-z]+)?$")
# Names older versions of this package used (a fixed `.name.tmp`, tempfile's `.name.XXXXXXXX.tmp`, videos'
# `.stem.pid.tmp.mp4`): recognised so that their leftovers can be cleaned, but they carry no usable pid.
_LEGACY_TEMPORARY = re.compile(r"^\..+\.tmp(\.[0-9A-Za-z]+)?$")


@functools.cache
def this_machine() -> str:
    """8 hex digits naming the space this process's pid lives in: the kernel's boot id (else the host name) and the
    pid namespace, so two machines, or two containers on one, sharing a folder never read each other's pids as
    their own."""
    try:
        boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        boot = socket.gethostname()
    try:
        namespace = os.stat("/proc/self/ns/pid").st_ino
    except OSError:
        namespace = 0
    return hashlib.blake2b(f"{boot}/{namespace}".encode(), digest_size=4).hexdigest()


def temporary_path(path: str | os.PathLike, keep_suffix: bool = False) -> Path:
    """A fresh temporary path in `path`'s folder, named by the pattern above (nothing is created)."""
    path = Path(path)
    suffix = path.suffix if keep_suffix else ""
    return path.with_name(f".{path.name}.{os.getpid()}-{this_machine()}.{secrets.token_hex(4)}.tmp{suffix}")


def temporary_writer(name: str) -> tuple[int, str | None] | None:
    """(pid, machine) of the process that wrote the temporary file `name`, the machine None in names of versions
    before it was written (taken as this machine's); None when `name` carries no pid."""
    match = _TEMPORARY.match(name)
    return (int(match["pid"]), match["machine"]) if match else None


def temporary_writer_pid(name: str) -> int | None:
    """The pid of the process that wrote the temporary file `name`, or None when `name` carries none."""
    writer = temporary_writer(name)
    return writer[0] if writer else None


def is_temporary_name(name: str) -> bool:
    """Whether `name` is a temporary file of an atomic write (of this version or an older one)."""
    return bool(_TEMPORARY.match(name) or _LEGACY_TEMPORARY.match(name))


def fsync_enabled() -> bool:
    """Whether writes are flushed to disk (`VISEMEFLOW_FSYNC`, default on; `0`, `false`, `no`, `off` turn it off)."""
    return os.environ.get("VISEMEFLOW_FSYNC", "1").strip().lower() not in {"0", "false", "no", "off"}


def _fsync_path(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_folder(folder: Path) -> None:
    """Make a rename in `folder` durable. Best effort: the rename has happened whatever this says, and some
    file systems cannot fsync a folder (EINVAL)."""
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _remove_quietly(path: Path) -> None:
    try:
        path.unlink(missing_ok=True)
    except OSError:
        pass  # the folder itself is unusable, so there is no temporary file to remove


# the files written inside the innermost `group_sync` block of this context (thread, task), or None outside one
_GROUP: contextvars.ContextVar[list[Path] | None] = contextvars.ContextVar("visemeflow_group_sync", default=None)


@functools.cache
def _libc_syncfs() -> Callable[[int], int] | None:
    """glibc's syncfs(2) (Linux), or None where it cannot be had."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        return libc.syncfs
    except (OSError, AttributeError):
        return None


def _sync_files(paths: list[Path]) -> None:
    """Make the writes of `paths` (renamed into place) durable: one syncfs per file system, else fsync each file
    and each folder."""
    syncfs = _libc_syncfs()
    folders = {p.parent for p in paths}
    if syncfs is not None:
        devices: dict[int, Path] = {}
        for folder in folders:
            try:
                devices.setdefault(os.stat(folder).st_dev, folder)
            except OSError:
                pass
        failed = False
        for folder in devices.values():
            try:
                fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
            except OSError:
                failed = True
                continue
            try:
                failed |= syncfs(fd) != 0
            finally:
                os.close(fd)
        if not failed:
            return
    for path in paths:
        try:
            _fsync_path(path)
        except FileNotFoundError:
            pass  # replaced or removed since: nothing of this block's left to flush
    for folder in folders:
        _fsync_folder(folder)


@contextmanager
def group_sync() -> Iterator[None]:
    """Inside the block, atomic writes that would fsync (`fsync_enabled()`) skip it; leaving the block (also by an
    exception) flushes every file they wrote at once. Nested blocks flush with the outermost. See the module
    docstring for what a crash inside the block can cost."""
    if _GROUP.get() is not None:
        yield
        return
    written: list[Path] = []
    token = _GROUP.set(written)
    try:
        yield
    finally:
        _GROUP.reset(token)
        if written:
            _sync_files(written)


@contextmanager
def atomic_path(path: str | os.PathLike, *, keep_suffix: bool = False, fsync: bool | None = None) -> Iterator[Path]:
    """Yield a temporary path to write; on leaving the block, it replaces `path` atomically.

    The caller writes the whole file to the yielded path (by any library that takes a path). On normal exit the
    file is flushed and renamed over `path`; on any exception (also KeyboardInterrupt) the temporary file is
    removed, `path` keeps its previous content, and the exception propagates. The folder is created if needed.
    `fsync` (default: `fsync_enabled()`) flushes the file before the rename and the folder after it.

        with atomic_path(out / "model.pt") as tmp:
            torch.save(state, tmp)
    """
    path = Path(path)
    fsync = fsync_enabled() if fsync is None else fsync
    group = _GROUP.get() if fsync else None
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_path(path, keep_suffix)
    try:
        yield tmp
        if fsync and group is None:
            _fsync_path(tmp)
        os.replace(tmp, path)
    except BaseException:
        _remove_quietly(tmp)
        raise
    if group is not None:
        group.append(path)
    elif fsync:
        _fsync_folder(path.parent)


def atomic_write(
    path: str | os.PathLike, writer: Callable[[Path], object], *, keep_suffix: bool = False, fsync: bool | None = None
) -> Path:
    """Call `writer(temporary_path)` and put the file it wrote at `path` atomically; returns `path`."""
    with atomic_path(path, keep_suffix=keep_suffix, fsync=fsync) as tmp:
        writer(tmp)
    return Path(path)


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, fsync: bool | None = None) -> Path:
    """Replace the file at `path` with `data`, atomically."""
    def write(tmp: Path) -> None:
        with open(tmp, "xb") as fh:
            fh.write(data)

    return atomic_write(path, write, fsync=fsync)


def atomic_write_text(
    path: str | os.PathLike, text: str, *, encoding: str = "utf-8", fsync: bool | None = None
) -> Path:
    """Replace the file at `path` with `text`, atomically."""
    return atomic_write_bytes(path, text.encode(encoding), fsync=fsync)
