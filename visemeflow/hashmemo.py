"""A persistent memo of file digests, keyed on what the OS says about the files without reading them.

`hashing.file_hash` and `hashing.files_hash` go through `memoised`: the identity of what is hashed (the kind of
digest, its size, the files' absolute paths in order, None entries included) is looked up in an SQLite file;
the row holds a stamp of the files' stat results (device, inode, size, mtime_ns, ctime_ns of each) and the digest.
While the stamp matches, the digest is returned without opening any file; any change (a write, a rename over the
file, a `touch`, a chmod: each moves ctime, which no program can set back) reads the files again. The stamp alone
decides a hit (it is of the file the path leads to now, symlinks followed), so the key is the absolute path as
spelt (`os.path.abspath`, no syscall) rather than the real path: a symlink pointed elsewhere gives another
(device, inode), hence a miss; two spellings of one file merely get a row each. `files_hash` is memoised as a whole
(one row per tuple of files), so its digest stays exactly the one-hasher digest it always was.

Where: `$VISEMEFLOW_HASH_MEMO` (a path; `off` disables the memo), else `file-digests.sqlite` in the package's cache
folder: `$VISEMEFLOW_CACHE_DIR`, else `$XDG_CACHE_HOME/visemeflow`, else `~/.cache/visemeflow`. WAL journal, a busy
timeout, one connection per thread (and per process: a forked child opens its own), autocommit single-row writes:
several threads and processes may share it.

Racy files (git's "racy clean" problem): a file written in the same clock tick as its row could be written again
with the same size, mtime and ctime. A digest is therefore stored only when the files' newest mtime/ctime is more
than `RACY_WINDOW_NS` (2 s, above any file system's timestamp granularity) before now, and only when a second stat
after reading equals the first (nothing changed the file while it was read). Such files are simply hashed each time.

Bounds: rows are keyed on the paths, so a changed file replaces its row. Past `MAX_ROWS` (1,000,000 rows, about
120 MB: keys and stamps are stored as 16-byte digests) the least recently used rows are deleted; the check runs on
about one insert in `PRUNE_EVERY` (10,000), and a row's last-use time is refreshed at most once a day, so a warm
rerun writes nothing.

Robust: an unreadable, corrupt or read-only memo, a cache folder that cannot be made, or a memo locked for longer
than the busy timeout never fails a hash: the files are read as without a memo (logged once per memo at debug level).

Free of imports from the rest of the package (hashing.py, which every layer uses, imports it).
"""

from __future__ import annotations

import functools
import hashlib
import logging
import os
import random
import sqlite3
import stat
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

log = logging.getLogger(__name__)

ENV = "VISEMEFLOW_HASH_MEMO"
OFF = "off"
FILE_NAME = "file-digests.sqlite"
RACY_WINDOW_NS = 2_000_000_000
MAX_ROWS = 1_000_000
PRUNE_EVERY = 10_000
REFRESH_USED_S = 86_400
BUSY_TIMEOUT_S = 2.0
MAX_LOCK_FAILURES = 3
INIT_ATTEMPTS = 20
"""Tries to open a memo that other connections are opening at the same moment (see `_Memo`)."""
"""Writes in a row that fail (a lock held past the timeout, a read-only file) before this process stops writing to
that memo (reads go on)."""

_TABLE = "digests_v1"
_SCHEMA = (
    f"CREATE TABLE IF NOT EXISTS {_TABLE} (key BLOB PRIMARY KEY, stamp BLOB NOT NULL, digest TEXT NOT NULL, "
    "used INTEGER NOT NULL) WITHOUT ROWID",
    f"CREATE INDEX IF NOT EXISTS {_TABLE}_used ON {_TABLE}(used)",
)

_local = threading.local()
_state_lock = threading.Lock()
_broken: set[str] = set()
"""Memo paths this process gave up on (logged once each)."""
_lock_failures: dict[str, int] = {}
_prune_dice = random.Random()
"""Our own generator: a caller's `random.seed` and draws are never disturbed by the memo's."""


def memo_path() -> Path | None:
    """The memo file in use now, or None when `VISEMEFLOW_HASH_MEMO=off` or no cache folder can be named."""
    env = os.environ
    return _memo_path(env.get(ENV, ""), env.get("VISEMEFLOW_CACHE_DIR", ""), env.get("XDG_CACHE_HOME", ""),
                      env.get("HOME", ""))


@functools.lru_cache(maxsize=16)
def _memo_path(value: str, cache_dir: str, xdg: str, home: str) -> Path | None:
    value = value.strip()
    if value.lower() == OFF:
        return None
    if value:
        return Path(value).expanduser()
    if cache_dir:  # the package's cache folder (the Whisper weights' too)
        return Path(cache_dir).expanduser() / FILE_NAME
    try:
        base = Path(xdg) if xdg and os.path.isabs(xdg) else Path.home() / ".cache"
    except RuntimeError:  # no home folder to name
        return None
    return base / "visemeflow" / FILE_NAME


def _give_up(path: str, why: object) -> None:
    with _state_lock:
        first = path not in _broken
        _broken.add(path)
    if first:
        log.debug("file digest memo %s unusable (%s): files are hashed without it", path, why)


class _Memo:
    """One connection to one memo file, used by one thread of one process."""

    def __init__(self, path: str) -> None:
        self.path = path
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        self.conn = sqlite3.connect(path, timeout=BUSY_TIMEOUT_S, isolation_level=None, check_same_thread=True)
        try:
            self.conn.execute(f"PRAGMA busy_timeout = {int(BUSY_TIMEOUT_S * 1000)}")
            self.conn.execute("PRAGMA synchronous = NORMAL")
            for attempt in range(INIT_ATTEMPTS):
                try:
                    # WAL is kept in the file: only the first connection to a new memo switches it. Connections
                    # that switch at once (threads of a pool starting together) get "database is locked" at once,
                    # without the busy timeout's wait: they try again shortly instead of giving the memo up.
                    if self.conn.execute("PRAGMA journal_mode").fetchone()[0].lower() != "wal":
                        self.conn.execute("PRAGMA journal_mode = WAL")
                    for sql in _SCHEMA:
                        self.conn.execute(sql)
                    break
                except sqlite3.OperationalError as exc:
                    if "locked" not in str(exc) or attempt == INIT_ATTEMPTS - 1:
                        raise
                    time.sleep(0.02 * (attempt + 1))
        except BaseException:
            self.conn.close()
            raise

    def get(self, key: bytes, stamp: bytes) -> str | None:
        row = self.conn.execute(f"SELECT stamp, digest, used FROM {_TABLE} WHERE key = ?", (key,)).fetchone()
        if row is None or row[0] != stamp:
            return None
        now = int(time.time())
        if now - row[2] > REFRESH_USED_S:
            self._write(f"UPDATE {_TABLE} SET used = ? WHERE key = ?", (now, key))
        return row[1]

    def put(self, key: bytes, stamp: bytes, digest: str) -> None:
        if self._write(f"INSERT OR REPLACE INTO {_TABLE} (key, stamp, digest, used) VALUES (?, ?, ?, ?)",
                       (key, stamp, digest, int(time.time()))) and _prune_dice.random() * PRUNE_EVERY < 1:
            self.prune()

    def prune(self) -> None:
        """Delete all but the `MAX_ROWS` most recently used rows."""
        self._write(f"DELETE FROM {_TABLE} WHERE key IN "
                    f"(SELECT key FROM {_TABLE} ORDER BY used DESC LIMIT -1 OFFSET ?)", (MAX_ROWS,))

    def _write(self, sql: str, args: tuple) -> bool:
        with _state_lock:
            if _lock_failures.get(self.path, 0) >= MAX_LOCK_FAILURES:
                return False
        try:
            self.conn.execute(sql, args)
        except sqlite3.OperationalError as exc:  # locked past the timeout, read-only file or folder, disk full
            with _state_lock:
                _lock_failures[self.path] = _lock_failures.get(self.path, 0) + 1
                stop = _lock_failures[self.path] >= MAX_LOCK_FAILURES
            if stop:
                log.debug("file digest memo %s: writes failed (%s): no more writes from this process", self.path, exc)
            return False
        if _lock_failures.get(self.path):
            with _state_lock:
                _lock_failures[self.path] = 0
        return True


def _memo() -> _Memo | None:
    path = memo_path()
    if path is None:
        return None
    key = os.fspath(path)
    if key in _broken:
        return None
    pid = os.getpid()
    memos: dict[str, _Memo] | None = getattr(_local, "memos", None)
    if memos is None or getattr(_local, "pid", None) != pid:  # a forked child never uses its parent's connections
        memos = _local.memos = {}
        _local.pid = pid
    memo = memos.get(key)
    if memo is None:
        try:
            memo = memos[key] = _Memo(key)
        except (OSError, sqlite3.Error) as exc:
            _give_up(key, exc)
            return None
    return memo


def _stats(paths: Sequence[str | os.PathLike | None]) -> tuple[tuple[int, int, int, int, int] | None, ...] | None:
    """Each file's (device, inode, size, mtime_ns, ctime_ns), None for a None entry; None if one is not a regular
    file (a pipe, a device, a folder: never memoised). An OSError (a missing file) propagates."""
    out = []
    for p in paths:
        if p is None:
            out.append(None)
            continue
        st = os.stat(p)
        if not stat.S_ISREG(st.st_mode):
            return None
        out.append((st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns))
    return tuple(out)


def _now_ns() -> int:
    return time.time_ns()


def _racy(stats: tuple) -> bool:
    newest = max((max(s[3], s[4]) for s in stats if s is not None), default=0)
    return newest > _now_ns() - RACY_WINDOW_NS


def _key(kind: str, size: int, paths: Sequence[str | os.PathLike | None]) -> bytes:
    h = hashlib.blake2b(digest_size=16)
    h.update(f"{kind}\0{size}\0".encode())
    for p in paths:
        h.update(b"\2" if p is None else b"\1" + os.fsencode(os.path.abspath(p)) + b"\0")
    return h.digest()


def _stamp(stats: tuple) -> bytes:
    return hashlib.blake2b(repr(stats).encode(), digest_size=16).digest()


def memoised(kind: str, size: int, paths: Sequence[str | os.PathLike | None], compute: Callable[[], str]) -> str:
    """`compute()` (the digest of `paths`' bytes), or the stored digest while none of the files changed.

    `kind` and `size` tell digests of the same files apart (a single file's digest vs a tuple's, digest sizes)."""
    memo = _memo()
    if memo is None:
        return compute()
    try:
        before = _stats(paths)
    except (OSError, ValueError, TypeError):
        return compute()  # the read raises what it always raised
    if before is None or all(s is None for s in before):  # a pipe or a folder; or no file at all
        return compute()
    try:
        key, stamp = _key(kind, size, paths), _stamp(before)
        hit = memo.get(key, stamp)
    except (OSError, sqlite3.Error, ValueError) as exc:
        _give_up(memo.path, exc)
        return compute()
    if hit is not None:
        return hit
    digest = compute()
    try:
        if not _racy(before) and _stats(paths) == before:
            memo.put(key, stamp, digest)
    except (OSError, sqlite3.Error) as exc:
        _give_up(memo.path, exc)
    return digest
