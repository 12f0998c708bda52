"""A new Prefect home's database is a copy of a migrated template (visemeflow.ops.prefect_db): built once, copied only
where no database is, never for a server told to use another database."""

import sqlite3
import pytest

from visemeflow.ops import prefect_db


@pytest.fixture
def cache(tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    monkeypatch.setenv(prefect_db.CACHE_ENV, str(folder))
    for name in prefect_db.OTHER_DATABASE_ENVS:
        monkeypatch.delenv(name, raising=False)
    return folder


def _revision(db) -> str:
    with sqlite3.connect(db) as con:
        return con.execute("SELECT version_num FROM alembic_version").fetchone()[0]


def _sqlite_heads() -> set[str]:
    """The head revisions of Prefect's SQLite migrations: revisions no other migration names as its down revision."""
    import re
    from pathlib import Path

    import prefect.server.database as database

    revisions, downs = set(), set()
    for path in (Path(database.__file__).parent / "_migrations" / "versions" / "sqlite").glob("*.py"):
        text = path.read_text(encoding="utf-8")
        revisions |= set(re.findall(r'^revision = "(\w+)"', text, re.M))
        for down in re.findall(r'^down_revision = (.+)$', text, re.M):
            downs |= set(re.findall(r'"(\w+)"', down))
    return revisions - downs


def test_a_missing_template_is_built_beside_the_start_then_new_homes_get_a_copy_at_prefects_head(cache, tmp_path):
    template = prefect_db.template_path()
    assert template.parent == cache and template.name.startswith("prefect-") and template.suffix == ".db"
    # no template yet: the server would migrate as before, and one detached build starts (one at a time)
    assert prefect_db.seed_home(tmp_path / "first", build_missing=False) == "no-template"
    builder = prefect_db.start_build(template)
    assert builder is not None and prefect_db.start_build(template) is None   # the first one holds the lock
    assert builder.wait(timeout=300) == 0
    assert template.is_file() and not template.with_name(template.name + ".building").exists()
    heads = _sqlite_heads()
    assert len(heads) == 1 and _revision(template) in heads
    assert not template.with_name(template.name + "-wal").exists()
    # a new home gets a private copy
    home = tmp_path / "home"
    assert prefect_db.seed_home(home) == "seeded"
    db = home / prefect_db.DB_NAME
    assert db.read_bytes() == template.read_bytes() and db.stat().st_mode & 0o777 == 0o600
    assert [p.name for p in home.iterdir()] == [prefect_db.DB_NAME]   # no part file left


def test_a_home_with_a_database_or_a_server_on_another_database_is_left_alone(cache, tmp_path, monkeypatch):
    template = prefect_db.template_path()
    template.parent.mkdir(parents=True)
    template.write_bytes(b"template")
    home = tmp_path / "home"
    home.mkdir()
    (home / "prefect.db").write_bytes(b"the user's runs")
    assert prefect_db.seed_home(home) == "exists"
    assert (home / "prefect.db").read_bytes() == b"the user's runs"
    monkeypatch.setenv("PREFECT_SERVER_DATABASE_CONNECTION_URL", "postgresql+asyncpg://db/prefect")
    assert prefect_db.seed_home(tmp_path / "other") == "other-database"
    assert not (tmp_path / "other").exists()
    monkeypatch.delenv("PREFECT_SERVER_DATABASE_CONNECTION_URL")
    monkeypatch.setenv(prefect_db.CACHE_ENV, "off")
    assert prefect_db.template_path() is None and prefect_db.seed_home(tmp_path / "off") == "off"


def test_a_failed_build_leaves_no_template_and_frees_its_lock(cache, tmp_path, monkeypatch):
    template = cache / "prefect-0.db"
    lock = prefect_db._build_lock(template)
    assert lock is not None and prefect_db._build_lock(template) is None
    monkeypatch.setattr(prefect_db, "build", lambda path: (_ for _ in ()).throw(RuntimeError("upgrade exited 1")))
    assert prefect_db.main([str(template), str(lock)]) == 1
    assert not template.exists() and not lock.exists()
    assert prefect_db._build_lock(template) is not None   # the next start may try again


@pytest.mark.flow
def test_the_session_server_starts_on_a_copy_of_the_template_and_runs_flows(prefect_harness):
    """`test_harness` (the tests' and benches' throw-away server) puts the template where Prefect's harness makes its
    database; a Prefect that makes it elsewhere fails here rather than quietly migrating a new one at every start."""
    from prefect import flow
    from prefect.settings import get_current_settings
    from sqlalchemy.engine import make_url

    assert prefect_harness == "seeded"
    db = make_url(get_current_settings().server.database.connection_url.get_secret_value()).database
    assert db.endswith(prefect_db.HARNESS_DB_NAME) and _revision(db) in _sqlite_heads()

    @flow
    def answer() -> int:
        return 42

    assert answer() == 42
