"""The file digest memo (visemeflow/hashmemo.py): same digests as reading the bytes, no read while a file's stat
results are unchanged, a re-read on any change, and never a failed hash because of the memo itself.

Every test points VISEMEFLOW_HASH_MEMO at a temporary file (the user's cache folder is never touched). Files made
here are fresh, so inside git's "racy" window; tests other than the racy one move the memo's clock 10 s ahead.
"""

import hashlib
import multiprocessing
import os
import sqlite3
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from visemeflow import hashing, hashmemo
from visemeflow.hashing import file_hash, files_hash


def reference_file(path, size=16) -> str:
    return hashlib.blake2b(open(path, "rb").read(), digest_size=size).hexdigest()


def reference_files(paths, size=16) -> str:
    """The one-hasher digest files_hash always gave (part of stored cache keys)."""
    h = hashlib.blake2b(digest_size=size)
    for p in paths:
        h.update(b"\0" if p is None else b"\1")
        if p is not None:
            h.update(open(p, "rb").read())
            h.update(b"\0")
    return h.hexdigest()


def rows(path) -> int:
    with sqlite3.connect(path) as conn:
        return conn.execute("SELECT count(*) FROM digests_v1").fetchone()[0]


def later() -> int:
    return time.time_ns() + 10_000_000_000


@pytest.fixture
def memo(tmp_path, monkeypatch):
    path = tmp_path / "cache" / "file-digests.sqlite"
    monkeypatch.setenv(hashmemo.ENV, str(path))
    monkeypatch.setattr(hashmemo, "_broken", set())
    monkeypatch.setattr(hashmemo, "_lock_failures", {})
    monkeypatch.setattr(hashmemo, "_now_ns", later)
    return path


@pytest.fixture
def opens(monkeypatch):
    """Paths hashing.py opens, in order."""
    seen: list[str] = []

    def counting_open(path, *args, **kwargs):
        seen.append(os.fspath(path))
        return open(path, *args, **kwargs)

    monkeypatch.setattr(hashing, "open", counting_open, raising=False)
    return seen


def make(folder, name, data: bytes):
    path = folder / name
    path.write_bytes(data)
    return path


def test_digests_equal_the_unmemoised_ones(memo, tmp_path, monkeypatch):
    a = make(tmp_path, "a.wav", os.urandom(300_000))
    b = make(tmp_path, "b.TextGrid", b"phones")
    empty = make(tmp_path, "empty.csv", b"")
    tuples = [[a, b, None, empty], [a, None, b], [None, a], [a], [], [None]]
    for _ in range(2):  # the second pass is served by the memo
        for size in (16, 32, 8):
            for path in (a, b, empty):
                assert file_hash(path, size) == reference_file(path, size)
            for paths in tuples:
                assert files_hash(paths, size) == reference_files(paths, size)
                assert files_hash(iter(paths), size) == reference_files(paths, size)
    assert files_hash([a, None]) != files_hash([None, a])
    assert file_hash(a) != files_hash([a])  # one file's digest and a tuple's are told apart
    assert rows(memo) == 3 * 3 + 3 * 4 + 1  # [] and [None] read no file: not memoised; + [a, None]
    monkeypatch.setenv(hashmemo.ENV, "off")
    assert file_hash(a) == reference_file(a) and files_hash([a, None, b]) == reference_files([a, None, b])


def test_a_second_call_opens_no_file(memo, tmp_path, opens):
    a = make(tmp_path, "a.wav", b"x" * 1000)
    b = make(tmp_path, "b.TextGrid", b"y" * 10)
    first = file_hash(a), files_hash([a, None, b])
    assert opens == [str(a), str(a), str(b)]
    opens.clear()
    assert (file_hash(a), files_hash([a, None, b])) == first
    assert file_hash(str(a)) == first[0]  # str or Path, the same row
    assert opens == []


def test_same_size_edit_with_the_mtime_put_back_is_read_again(memo, tmp_path, opens):
    a = make(tmp_path, "a.wav", b"aaaa")
    assert file_hash(a) == reference_file(a)
    assert files_hash([a]) == reference_files([a])
    before = os.stat(a)
    time.sleep(0.05)  # past the kernel's timestamp tick
    a.write_bytes(b"bbbb")
    os.utime(a, ns=(before.st_atime_ns, before.st_mtime_ns))
    after = os.stat(a)
    assert (after.st_size, after.st_mtime_ns, after.st_ino) == (before.st_size, before.st_mtime_ns, before.st_ino)
    assert after.st_ctime_ns != before.st_ctime_ns
    opens.clear()
    assert file_hash(a) == reference_file(a) == hashlib.blake2b(b"bbbb", digest_size=16).hexdigest()
    assert files_hash([a]) == reference_files([a])
    assert len(opens) == 2


def test_a_file_renamed_over_is_read_again(memo, tmp_path, opens):
    a = make(tmp_path, "a.wav", b"aaaa")
    file_hash(a)
    stamp = os.stat(a)
    b = make(tmp_path, "b.wav", b"bbbb")
    os.utime(b, ns=(stamp.st_atime_ns, stamp.st_mtime_ns))
    os.replace(b, a)
    opens.clear()
    assert file_hash(a) == hashlib.blake2b(b"bbbb", digest_size=16).hexdigest()
    assert opens == [str(a)]


def test_a_file_changed_while_read_is_not_memoised(memo, tmp_path, monkeypatch, opens):
    a = make(tmp_path, "a.wav", b"aaaa")
    read = hashing._update_with_file

    def read_then_append(h, path):
        read(h, path)
        with open(path, "ab") as fh:
            fh.write(b"more")

    monkeypatch.setattr(hashing, "_update_with_file", read_then_append)
    file_hash(a)
    monkeypatch.setattr(hashing, "_update_with_file", read)
    assert rows(memo) == 0
    opens.clear()
    assert file_hash(a) == hashlib.blake2b(b"aaaamore", digest_size=16).hexdigest()
    assert opens == [str(a)]


def test_a_racy_file_is_not_memoised(memo, tmp_path, monkeypatch, opens):
    monkeypatch.setattr(hashmemo, "_now_ns", time.time_ns)  # the real clock: the file is seconds old at most
    a = make(tmp_path, "a.wav", b"aaaa")
    for _ in range(2):
        assert file_hash(a) == reference_file(a)
        assert files_hash([a, None]) == reference_files([a, None])
    assert opens == [str(a)] * 4
    assert rows(memo) == 0
    old = time.time_ns() - 60_000_000_000
    os.utime(a, ns=(old, old))  # an old mtime alone is not enough: the utime moved ctime to now
    file_hash(a)
    assert rows(memo) == 0
    monkeypatch.setattr(hashmemo, "_now_ns", later)  # 10 s later the file is out of the window
    opens.clear()
    file_hash(a)
    file_hash(a)
    assert opens == [str(a)] and rows(memo) == 1


def test_a_corrupt_memo_never_fails_a_hash(memo, tmp_path, opens):
    memo.parent.mkdir(parents=True)
    memo.write_bytes(b"this is not an SQLite database" * 100)
    a = make(tmp_path, "a.wav", b"aaaa")
    for _ in range(2):
        assert file_hash(a) == reference_file(a)
        assert files_hash([a, None]) == reference_files([a, None])
    assert len(opens) == 4  # no memo: every call reads
    assert memo.read_bytes().startswith(b"this is not")


def test_a_locked_memo_never_fails_a_hash(memo, tmp_path, monkeypatch):
    monkeypatch.setattr(hashmemo, "BUSY_TIMEOUT_S", 0.05)
    first = make(tmp_path, "first.wav", b"first")
    file_hash(first)  # the memo exists, in WAL mode
    holder = sqlite3.connect(memo, isolation_level=None)
    holder.execute("BEGIN EXCLUSIVE")  # another process writing, for longer than the busy timeout
    try:
        for i in range(5):
            path = make(tmp_path, f"{i}.wav", bytes([i]) * 10)
            assert file_hash(path) == reference_file(path)
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    assert rows(memo) == 1


def test_a_memo_that_cannot_be_made_never_fails_a_hash(tmp_path, monkeypatch, opens):
    blocker = make(tmp_path, "a-file", b"")
    monkeypatch.setenv(hashmemo.ENV, str(blocker / "cache" / "memo.sqlite"))  # a folder under a file: no mkdir
    monkeypatch.setattr(hashmemo, "_broken", set())
    a = make(tmp_path, "a.wav", b"aaaa")
    assert file_hash(a) == reference_file(a) == file_hash(a)
    assert len(opens) == 2


def test_missing_files_raise_as_before(memo, tmp_path):
    with pytest.raises(FileNotFoundError):
        file_hash(tmp_path / "missing.wav")
    with pytest.raises(FileNotFoundError):
        files_hash([make(tmp_path, "a.wav", b"a"), tmp_path / "missing.wav"])
    with pytest.raises(IsADirectoryError):
        file_hash(tmp_path)


def test_off_makes_no_memo_file(tmp_path, monkeypatch, opens):
    monkeypatch.delenv(hashmemo.ENV, raising=False)
    monkeypatch.delenv("VISEMEFLOW_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert hashmemo.memo_path() == tmp_path / "xdg" / "visemeflow" / "file-digests.sqlite"
    monkeypatch.setenv(hashmemo.ENV, "off")
    monkeypatch.setattr(hashmemo, "_now_ns", later)
    assert hashmemo.memo_path() is None
    a = make(tmp_path, "a.wav", b"aaaa")
    assert file_hash(a) == reference_file(a) == file_hash(a)
    assert len(opens) == 2
    assert not (tmp_path / "xdg").exists() and not (tmp_path / "home").exists()


def test_rows_past_the_limit_are_pruned(memo, tmp_path, monkeypatch):
    monkeypatch.setattr(hashmemo, "MAX_ROWS", 5)
    monkeypatch.setattr(hashmemo, "PRUNE_EVERY", 1)
    for i in range(12):
        file_hash(make(tmp_path, f"{i}.wav", bytes([i])))
    assert rows(memo) == 5


def _hash_in_child(args):
    paths, expected = args
    hashmemo._now_ns = later  # a spawned child: files made just now are out of the racy window
    for _ in range(3):
        got = [file_hash(p) for p in paths] + [files_hash([p, None, paths[0]]) for p in paths]
        if got != expected:
            return False
    return True


def test_two_processes_hashing_at_once(memo, tmp_path):
    paths = [str(make(tmp_path, f"{i}.wav", os.urandom(2000 + i))) for i in range(40)]
    expected = [reference_file(p) for p in paths] + [reference_files([p, None, paths[0]]) for p in paths]
    with multiprocessing.get_context("spawn").Pool(2) as pool:
        assert pool.map(_hash_in_child, [(paths, expected)] * 2) == [True, True]
    assert rows(memo) == 2 * len(paths)
    assert [file_hash(p) for p in paths] == expected[:len(paths)]


def test_threads_hashing_at_once(memo, tmp_path):
    paths = [make(tmp_path, f"{i}.wav", os.urandom(1000 + i)) for i in range(30)]
    expected = [reference_file(p) for p in paths]
    with ThreadPoolExecutor(8) as pool:
        for _ in range(3):
            assert list(pool.map(file_hash, paths)) == expected
    assert rows(memo) == len(paths)


def test_threads_opening_a_new_memo_at_once_all_keep_it(tmp_path, monkeypatch):
    """Eight threads open a new memo file at the same moment, 40 times: none gives the memo up (switching a new file
    to WAL fails at once with "database is locked" for all but one; before they retried, 1 try in about 40 lost the
    memo for the whole process, and `test_threads_hashing_at_once` then found 1 row of 30)."""
    import threading

    given_up = 0
    for trial in range(40):
        monkeypatch.setenv(hashmemo.ENV, str(tmp_path / f"m{trial}" / "file-digests.sqlite"))
        monkeypatch.setattr(hashmemo, "_broken", set())
        monkeypatch.setattr(hashmemo, "_local", threading.local())
        barrier = threading.Barrier(8)

        def open_memo(_):
            barrier.wait()
            return hashmemo._memo() is not None

        with ThreadPoolExecutor(8) as pool:
            given_up += not all(pool.map(open_memo, range(8)))
    assert given_up == 0
