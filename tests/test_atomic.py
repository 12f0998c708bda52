"""Atomic writes (`visemeflow.atomic`): concurrent writers of one file, killed writers, failing writers."""

import os
import re
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from factories import write_wav

from visemeflow.atomic import (
    atomic_path,
    atomic_write,
    atomic_write_text,
    is_temporary_name,
    temporary_path,
    temporary_writer,
    temporary_writer_pid,
    this_machine,
)
from visemeflow.ops.clean import clean, reclaimable
from visemeflow.storage import Store


def hidden_files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob(".*") if p.is_file())


def test_temporary_names_are_unique_and_recognised(tmp_path):
    target = tmp_path / "reports" / "sweep-a.png"
    names = {temporary_path(target).name for _ in range(200)}
    assert len(names) == 200
    name = temporary_path(target, keep_suffix=True).name
    assert name.startswith(".sweep-a.png.") and name.endswith(".tmp.png")
    assert temporary_writer_pid(name) == os.getpid() and is_temporary_name(name)
    assert temporary_writer(name) == (os.getpid(), this_machine())
    assert temporary_writer_pid(temporary_path(tmp_path / "x.parquet").name) == os.getpid()
    for legacy in (".robustness.md.tmp", ".last.pt.k2j4_x9a.tmp", ".u1.4242.tmp.mp4"):
        assert is_temporary_name(legacy) and temporary_writer_pid(legacy) is None
    for data in ("u1.parquet", "tmp.parquet", ".locks", "model.pt"):
        assert not is_temporary_name(data)


def test_threads_writing_one_file_never_collide_or_corrupt(tmp_path):
    path = tmp_path / "reports" / "robustness.md"
    versions = {k: (f"version {k}\n" * (2000 + 500 * k)) for k in range(6)}
    errors, stop = [], threading.Event()

    def writer(k: int) -> None:
        try:
            for _ in range(30):
                atomic_write_text(path, versions[k])
        except Exception as exc:  # noqa: BLE001 - any failure of a writer fails the test
            errors.append(exc)

    def reader() -> None:
        while not stop.is_set():
            if path.exists():
                text = path.read_text()
                if text not in versions.values():
                    errors.append(AssertionError(f"a reader saw a mixed file of {len(text)} characters"))

    threads = [threading.Thread(target=writer, args=(k,)) for k in versions]
    watch = threading.Thread(target=reader)
    watch.start()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    stop.set()
    watch.join()
    assert errors == []
    assert path.read_text() in versions.values()
    assert hidden_files(tmp_path) == []  # every temporary file became the target or was removed


def test_threads_writing_one_video_never_collide(tmp_path):
    """`write_video` from two threads of one process (same pid): each write is whole, none fails."""
    from visemeflow.tracking.video import probe_video, write_video

    path = tmp_path / "out" / "clip.avi"
    errors = []

    def writer(value: int) -> None:
        frames = [np.full((32, 32, 3), value, np.uint8) for _ in range(12)]
        try:
            for _ in range(4):
                write_video(path, frames, 25.0)
        except Exception as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=writer, args=(v,)) for v in (40, 200)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert probe_video(path).n_frames == 12
    assert hidden_files(tmp_path) == []


def test_store_threads_writing_one_report(tmp_path):
    store = Store(tmp_path)
    errors = []

    def writer(k: int) -> None:
        try:
            for _ in range(20):
                store.write_report_text("robustness.csv", f"{k}\n" * 5000)
        except Exception as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=writer, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert len(set(store.report_path("robustness.csv").read_text().split())) == 1
    assert store.report_files() == [store.report_path("robustness.csv")]


@pytest.mark.parametrize("exc", [OSError(28, "No space left on device"), ValueError("bad data"), KeyboardInterrupt()])
def test_a_failing_writer_leaves_the_previous_file(tmp_path, exc):
    path = tmp_path / "a" / "model.pt"
    atomic_write_text(path, "old")

    def half(tmp: Path) -> None:
        tmp.write_text("new but only ha")
        raise exc

    with pytest.raises(type(exc)):
        atomic_write(path, half)
    with pytest.raises(type(exc)), atomic_path(path, keep_suffix=True) as tmp:
        tmp.write_text("new")
        raise exc
    assert path.read_text() == "old"
    assert hidden_files(tmp_path) == []


def test_a_failing_store_write_leaves_the_previous_report(tmp_path):
    store = Store(tmp_path)
    store.write_report_text("robustness.md", "old")

    def half(tmp: Path) -> None:
        tmp.write_bytes(b"\x89PNG half")
        raise OSError(28, "No space left on device")

    from visemeflow.storage import StoreError

    with pytest.raises(StoreError, match="disk full"):
        store.write_report("robustness.md", half)
    assert store.report_path("robustness.md").read_text() == "old"
    assert hidden_files(tmp_path) == []


# ---- killed writers ------------------------------------------------------------------------------

_KILLED_CHECKPOINT = """
import os, torch
from pathlib import Path
from visemeflow.learning import train

def dying_save(obj, f, *a, **k):
    Path(f).write_bytes(b"half a checkpoint")
    os._exit(9)

torch.save = dying_save
train._atomic_torch_save({"w": 1}, Path(STORE) / "models" / "m" / "checkpoints" / "last.pt")
"""

_KILLED_AUGMENTED_AUDIO = """
import os
from pathlib import Path
import soundfile
from visemeflow.learning.augment import AugmentConfig
from visemeflow.tasks.evaluate import augment_condition

def dying_write(file, *a, **k):
    Path(file).write_bytes(b"RIFF half a wav")
    os._exit(9)

soundfile.write = dying_write
augment_condition.fn(STORE, "volume", 0, AugmentConfig(), [{"utterance_id": "spk/u1", "audio_path": AUDIO}])
"""


@pytest.mark.parametrize("script", [_KILLED_CHECKPOINT, _KILLED_AUGMENTED_AUDIO], ids=["checkpoint", "augmented"])
def test_a_killed_writers_leftover_is_found_by_clean_temporary(tmp_path, script):
    store_root = (tmp_path / "store").resolve()
    audio = write_wav(tmp_path / "u1.wav", 0.5)
    code = f"STORE = {str(store_root)!r}\nAUDIO = {str(audio)!r}\n" + textwrap.dedent(script)
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 9, proc.stderr
    left = [p for p in store_root.rglob("*") if p.is_file()]
    assert len(left) == 1 and left[0].name.startswith("."), left  # only the dead writer's temporary file

    store = Store(store_root)
    assert store.stale_temporary_files() == left
    (temporary,) = [item for item in reclaimable(store) if item.kind == "temporary"]
    assert temporary.paths == left and temporary.n_bytes == left[0].stat().st_size
    clean(store, ["temporary"])
    assert not left[0].exists()


def test_clean_temporary_finds_suffixed_and_legacy_leftovers_but_not_live_ones(tmp_path):
    dead = subprocess.Popen(["true"])
    dead.wait()
    store = Store(tmp_path)
    files = {
        "reports/.sweep-a.png.%d.0a1b2c3d.tmp.png" % dead.pid: True,             # dead writer, suffix kept
        "augmented/volume-s0/spk/.u1.wav.%d.0a1b2c3d.tmp" % dead.pid: True,      # dead writer
        "reports/.robustness.md.tmp": True,                                     # an old fixed name, old
        "models/m/.model.pt.k2j4_x9a.tmp": True,                                # tempfile's name, old
        "reports/.robustness.csv.%d.0a1b2c3d.tmp" % os.getpid(): False,          # a live writer (this one)
        "reports/.fresh.md.tmp": False,                                         # no pid and young: maybe live
        "reports/robustness.md": False,                                         # data
        # a store on a folder several machines share: the pids of this machine's writers are judged here, another
        # machine's writer (its pid dead or alive here, it means nothing) only by the file's age
        f"tables/.shard-0001.parquet.{dead.pid}-{this_machine()}.0a1b2c3d.tmp": True,   # dead writer of this one
        f"tables/.shard-0002.parquet.{os.getpid()}-{this_machine()}.0a1b2c3d.tmp": False,   # live writer here
        f"tables/.shard-0003.parquet.{dead.pid}-0badf00d.0a1b2c3d.tmp": False,   # another machine's, young
        f"tables/.shard-0004.parquet.{dead.pid}-0badf00d.0a1b2c3d.tmp.png": True,   # another machine's, old
    }
    old = time.time() - 2 * 3600
    for rel in files:
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(b"x")
        if rel.endswith(("robustness.md.tmp", "k2j4_x9a.tmp", "0badf00d.0a1b2c3d.tmp.png")):
            os.utime(tmp_path / rel, (old, old))
    found = {str(p.relative_to(tmp_path.resolve())) for p in store.stale_temporary_files()}
    assert found == {rel for rel, stale in files.items() if stale}


def test_fsync_of_file_and_folder_by_default_and_off_by_environment(tmp_path, monkeypatch):
    import visemeflow.atomic as atomic

    synced = []
    real = os.fsync
    monkeypatch.setattr(atomic.os, "fsync", lambda fd: synced.append(os.readlink(f"/proc/self/fd/{fd}")) or real(fd))
    path = tmp_path / "d" / "x.txt"
    atomic_write_text(path, "x")
    assert len(synced) == 2 and synced[0].startswith(str(tmp_path / "d" / ".x.txt.")) and synced[1] == str(path.parent)
    synced.clear()
    monkeypatch.setenv("VISEMEFLOW_FSYNC", "0")
    atomic_write_text(path, "y")
    assert synced == [] and path.read_text() == "y"


def test_the_machine_token_is_stable_and_differs_by_boot_and_by_pid_namespace(monkeypatch):
    """Two machines differ by boot id, two containers on one host by pid namespace: either gives another token,
    the same pair the same token (read through fakes of /proc, so it holds wherever the suite runs)."""
    import types

    import visemeflow.atomic as atomic

    assert re.fullmatch(r"[0-9a-f]{8}", this_machine()) and this_machine() == this_machine()
    boot, namespace = ["boot-a"], [4026531836]
    real_stat, real_read = atomic.os.stat, atomic.Path.read_text
    monkeypatch.setattr(atomic.os, "stat", lambda path, *a, **k: types.SimpleNamespace(st_ino=namespace[0])
                        if str(path) == "/proc/self/ns/pid" else real_stat(path, *a, **k))
    monkeypatch.setattr(atomic.Path, "read_text", lambda self, *a, **k: boot[0] + "\n"
                        if str(self) == "/proc/sys/kernel/random/boot_id" else real_read(self, *a, **k))
    first = atomic.this_machine.__wrapped__()
    assert atomic.this_machine.__wrapped__() == first
    namespace[0] = 4026532001
    other_container = atomic.this_machine.__wrapped__()
    boot[0], namespace[0] = "boot-b", 4026531836
    other_machine = atomic.this_machine.__wrapped__()
    assert len({first, other_container, other_machine}) == 3


def test_a_child_in_a_new_pid_namespace_has_another_machine_token():
    """The same on a real pid namespace, where this machine lets root make one (`unshare`); the fakes above hold the
    rule everywhere, this the kernel's side of it."""
    import shutil

    unshare = shutil.which("unshare")
    if unshare is None or os.geteuid() != 0:
        pytest.skip("needs unshare as root to make a pid namespace")
    code = "from visemeflow.atomic import this_machine; print(this_machine())"
    done = subprocess.run([unshare, "--pid", "--fork", "--mount-proc", sys.executable, "-c", code],
                          capture_output=True, text=True, timeout=60)
    if done.returncode != 0:
        pytest.skip(f"unshare refused here (a restricted container): {done.stderr.strip()[:200]}")
    assert re.fullmatch(r"[0-9a-f]{8}", done.stdout.strip()) and done.stdout.strip() != this_machine()


def test_group_sync_flushes_a_block_of_writes_once(tmp_path, monkeypatch):
    """Inside `group_sync` no write fsyncs; leaving it syncs the file system once (syncfs), or, where syncfs fails,
    every file and folder written; outside it each write fsyncs as before; nested blocks flush with the outer one."""
    import visemeflow.atomic as atomic

    synced, syncfs_calls = [], []
    real = os.fsync
    monkeypatch.setattr(atomic.os, "fsync", lambda fd: synced.append(os.readlink(f"/proc/self/fd/{fd}")) or real(fd))
    libc = atomic._libc_syncfs()
    assert libc is not None, "glibc's syncfs is there on Linux"
    monkeypatch.setattr(atomic, "_libc_syncfs", lambda: lambda fd: syncfs_calls.append(os.readlink(f"/proc/self/fd/{fd}")) or libc(fd))
    paths = [tmp_path / "a" / f"{i}.txt" for i in range(3)] + [tmp_path / "b" / "3.txt"]
    with atomic.group_sync():
        for i, p in enumerate(paths[:2]):
            atomic_write_text(p, str(i))
        with atomic.group_sync():            # nested: flushed with the outer block
            for i, p in enumerate(paths[2:], 2):
                atomic_write_text(p, str(i))
        assert synced == [] and syncfs_calls == []
        assert [p.read_text() for p in paths] == ["0", "1", "2", "3"]   # renamed at once, whole
    assert synced == [] and len(syncfs_calls) == 1    # one file system: one syncfs
    # syncfs failing: each file, then each folder
    syncfs_calls.clear()
    monkeypatch.setattr(atomic, "_libc_syncfs", lambda: lambda fd: -1)
    with atomic.group_sync():
        for p in paths:
            atomic_write_text(p, "again")
    assert sorted(synced) == sorted([*map(str, paths), str(tmp_path / "a"), str(tmp_path / "b")])
    # an exception inside the block: what was written is still flushed, the exception goes on
    synced.clear()
    with pytest.raises(RuntimeError, match="boom"), atomic.group_sync():
        atomic_write_text(paths[0], "last")
        raise RuntimeError("boom")
    assert str(paths[0]) in synced and paths[0].read_text() == "last"
    # outside a block: file and folder each write, as before
    synced.clear()
    atomic_write_text(paths[1], "alone")
    assert len(synced) == 2 and synced[1] == str(tmp_path / "a")
    # fsync off by the environment: nothing is flushed, in a block or not
    synced.clear()
    monkeypatch.setenv("VISEMEFLOW_FSYNC", "0")
    with atomic.group_sync():
        atomic_write_text(paths[2], "off")
    assert synced == []


def test_a_curve_file_cut_short_by_a_crash_reads_as_missing_and_is_written_again(tmp_path):
    """After a power loss inside `group_sync`, a renamed curve file may come back empty: its provenance reads as
    None (not an error), so the procedural stage writes it again."""
    from visemeflow.schemas import curves_table

    store = Store(tmp_path / "s")
    table = curves_table("spk/u1", "procedural", "jali", np.zeros((5, 16), np.float32), 30.0)
    store.write_curves(table, provenance="made", fps=30.0)
    assert store.curves_provenance("procedural", "jali", "spk/u1") == "made"
    path = store.curve_path("procedural", "jali", "spk/u1")
    path.write_bytes(b"")
    assert store.curves_provenance("procedural", "jali", "spk/u1") is None
    assert not store.has_curves("procedural", "jali", "spk/u1")   # an empty file counts as missing
    path.write_bytes(b"PAR1\0\0")
    assert store.curves_provenance("procedural", "jali", "spk/u1") is None
    # a whole-length file whose footer was zeroed (its end marker intact): pyarrow raises OSError, not ArrowInvalid
    store.write_curves(table, provenance="made", fps=30.0)
    raw = bytearray(path.read_bytes())
    footer = int.from_bytes(raw[-8:-4], "little")
    raw[-8 - footer:-8] = bytes(footer)
    path.write_bytes(bytes(raw))
    assert store.has_curves("procedural", "jali", "spk/u1")
    assert store.curves_provenance("procedural", "jali", "spk/u1") is None
