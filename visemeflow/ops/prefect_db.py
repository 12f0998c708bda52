"""A new Prefect home's database copied from a migrated template, so that its first server start skips the migrations.

A Prefect server started on a Prefect home without a database (`visemeflow serve` on a new store, a command's
temporary server in a new PREFECT_HOME) first creates the SQLite database and runs Prefect's whole chain of
migrations on it: about 10 s of a core on the 2-core machine, half of the server's start (measured: 19.8 s and
17.8 s fresh against 9.5 s and 10.3 s on a migrated copy). Every such database is the same file for one Prefect
version, so the first one built is kept as a template, `<cache>/prefect-<version>.db` (`<cache>`:
VISEMEFLOW_PREFECT_DB_CACHE, else `$XDG_CACHE_HOME/visemeflow/prefect-db`, else `~/.cache/visemeflow/prefect-db`),
and a later new home gets a copy of it before its server starts; the server then finds the database at its head
revision and goes on.

Never slower: when the template is missing the server starts as before (it migrates its own database) and the
template is built beside it by a detached process (`python -m visemeflow.ops.prefect_db TEMPLATE`, at low priority,
one at a time). Never in the way: a home that already has a database, or a server told to use another database
(PREFECT_SERVER_DATABASE_CONNECTION_URL or PREFECT_API_DATABASE_CONNECTION_URL set), is left alone; the copy is
linked into place only where no file is (a server that created its database meanwhile keeps it); VISEMEFLOW_PREFECT_DB_CACHE=off
turns the whole thing off.

Standard library only at import (imported by the CLI before Prefect; the Prefect version is read from the package
metadata); `test_harness` imports Prefect when it is called.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import os
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CACHE_ENV = "VISEMEFLOW_PREFECT_DB_CACHE"
DB_NAME = "prefect.db"   # Prefect's default database: sqlite in PREFECT_HOME
OTHER_DATABASE_ENVS = ("PREFECT_SERVER_DATABASE_CONNECTION_URL", "PREFECT_API_DATABASE_CONNECTION_URL")
BUILD_STALE_S = 600.0    # a build lock older than this was left by a builder that died


def cache_dir() -> Path | None:
    """Where templates are kept; None when VISEMEFLOW_PREFECT_DB_CACHE is `off`."""
    value = os.environ.get(CACHE_ENV, "").strip()
    if value.lower() in ("off", "0", "false", "no"):
        return None
    if value:
        return Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "visemeflow" / "prefect-db"


def template_path() -> Path | None:
    """The template of this Prefect version (None when turned off)."""
    folder = cache_dir()
    if folder is None:
        return None
    return folder / f"prefect-{importlib.metadata.version('prefect')}.db"


def seed_home(home: Path, *, build_missing: bool = True) -> str:
    """Give the Prefect home `home` a copy of the template as its database, before a server starts there.

    Returns what was done: "seeded"; "exists" (the home has a database: left alone); "other-database" (the server
    is told to use another database); "off"; "no-template" (the server migrates as before; with `build_missing`
    the template is being built for the next time)."""
    if any(os.environ.get(name) for name in OTHER_DATABASE_ENVS):
        return "other-database"
    target = Path(home) / DB_NAME
    if target.exists():
        return "exists"
    template = template_path()
    if template is None:
        return "off"
    if not template.is_file():
        if build_missing:
            start_build(template)
        return "no-template"
    target.parent.mkdir(parents=True, exist_ok=True)
    part = target.with_name(f".{DB_NAME}.{os.getpid()}.part")
    try:
        shutil.copyfile(template, part)
        os.chmod(part, 0o600)
        os.link(part, target)          # never over a file: a database that appeared meanwhile is kept
    except FileExistsError:
        return "exists"
    except OSError:
        return "no-template"           # an unreadable template or a full disk: the server migrates as before
    finally:
        with contextlib.suppress(OSError):
            part.unlink()
    return "seeded"


def start_build(template: Path) -> subprocess.Popen | None:
    """Build `template` in a detached low-priority process (None when another build is under way)."""
    lock = _build_lock(template)
    if lock is None:
        return None
    return subprocess.Popen(
        [sys.executable, "-m", "visemeflow.ops.prefect_db", str(template), str(lock)],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
        env={k: v for k, v in os.environ.items() if k not in OTHER_DATABASE_ENVS},
        preexec_fn=(lambda: os.nice(10)) if hasattr(os, "nice") else None,
    )


def _build_lock(template: Path) -> Path | None:
    """The build's lock file, made here (None when a live build holds it)."""
    lock = template.with_name(template.name + ".building")
    try:
        template.parent.mkdir(parents=True, exist_ok=True)
        if lock.exists() and time.time() - lock.stat().st_mtime > BUILD_STALE_S:
            lock.unlink(missing_ok=True)
        os.close(os.open(lock, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    except OSError:
        return None
    return lock


def build(template: Path, timeout_s: float = 300.0) -> Path:
    """Migrate a new SQLite database to Prefect's head revision (`prefect server database upgrade`) and put it at
    `template` in one rename. Raises RuntimeError when the upgrade fails."""
    template.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=template.parent, prefix=".build-") as work:
        db = Path(work) / DB_NAME
        env = {**os.environ, "PREFECT_SERVER_DATABASE_CONNECTION_URL": f"sqlite+aiosqlite:///{db}",
               "PREFECT_HOME": work, "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}
        env.pop("PREFECT_API_DATABASE_CONNECTION_URL", None)
        done = subprocess.run([sys.executable, "-m", "prefect", "server", "database", "upgrade", "-y"], env=env,
                              stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=timeout_s)
        if done.returncode != 0 or not db.is_file():
            raise RuntimeError(f"prefect server database upgrade exited {done.returncode}: {done.stderr[-2000:]}")
        with contextlib.closing(sqlite3.connect(db)) as con:   # one self-contained file: no WAL beside it
            con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
            con.execute("PRAGMA journal_mode=DELETE")
            (version,) = con.execute("SELECT version_num FROM alembic_version").fetchone()
        if not version:
            raise RuntimeError("the upgraded database has no alembic revision")
        os.replace(db, template)
    return template


HARNESS_DB_NAME = "prefect-test.db"   # the database file `prefect_test_harness` makes in its own temporary folder


@contextlib.contextmanager
def test_harness(startup_timeout_s: float = 180):
    """Prefect's `prefect_test_harness` (a throw-away server on a temporary SQLite database) on a copy of the template,
    for the tests' session server and the benches' (about 10 s less of a core per start, measured 18.9-19.9 s ->
    9.8-10.8 s). Yields "seeded"; else the harness migrates its database as before, and yields why: "no-template"
    (it is being built beside it for the next time), "off", or "harness-changed" (Prefect no longer makes its
    folder as below).

    The harness makes its folder with `tempfile.mkdtemp` and its database as `prefect-test.db` in it; the copy is put
    there as the folder is made. tests/test_prefect_db.py checks that it still is, so a Prefect that changes either
    fails there instead of quietly starting slower."""
    from unittest import mock

    from prefect.testing import utilities

    template = template_path()
    status = "off" if template is None else "seeded" if template.is_file() else "no-template"
    if status == "no-template":
        start_build(template)
    made = []

    def seeded_mkdtemp(*args, **kwargs):
        folder = tempfile.mkdtemp(*args, **kwargs)
        if status == "seeded" and not made:
            shutil.copyfile(template, Path(folder) / HARNESS_DB_NAME)
            made.append(Path(folder) / HARNESS_DB_NAME)
        return folder

    with contextlib.ExitStack() as stack:
        with mock.patch.object(utilities, "mkdtemp", seeded_mkdtemp):
            stack.enter_context(utilities.prefect_test_harness(server_startup_timeout=startup_timeout_s))
        yield status if made or status != "seeded" else "harness-changed"


def main(argv: list[str]) -> int:
    template, lock = Path(argv[0]), Path(argv[1]) if len(argv) > 1 else None
    try:
        build(template)
    except (RuntimeError, OSError, subprocess.SubprocessError, sqlite3.Error):
        return 1
    finally:
        if lock is not None:
            lock.unlink(missing_ok=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
