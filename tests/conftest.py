"""Session-wide settings: one Prefect test harness for every flow test."""

import os

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
# the file-digest memo (visemeflow.hashmemo) stays out of the tests: never the real ~/.cache, never shared between
# runs (tests/test_hash_memo.py points it at its own temporary files)
os.environ["VISEMEFLOW_HASH_MEMO"] = "off"
# the migrated Prefect database that new Prefect homes start from (visemeflow.ops.prefect_db): the tests' own, one per
# Prefect version on this machine, never the real ~/.cache; built once before the workers start (pytest_configure)
os.environ.setdefault("VISEMEFLOW_PREFECT_DB_CACHE",
                      os.path.join(__import__("tempfile").gettempdir(), f"visemeflow-tests-prefect-db-{os.getuid()}"))

import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

# CI explores a fixed set of examples (a red CI is always reproducible); local runs keep exploring new ones.
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


def pytest_configure(config):
    """The controller (not an xdist worker) builds the template Prefect database when this machine has none yet
    (about 15 s once), so that the servers the tests start on new Prefect homes skip Prefect's migrations."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        return
    from visemeflow.ops.prefect_db import build, template_path

    template = template_path()
    if template is not None and not template.is_file():
        build(template)


@pytest.fixture(scope="session")
def prefect_harness():
    """A temporary Prefect server for the whole test session (start-up is paid once, on a copy of the template)."""
    from visemeflow.ops.prefect_db import test_harness

    with test_harness(startup_timeout_s=180) as seeded:
        yield seeded


@pytest.fixture(scope="session")
def prefect_api_url(prefect_harness) -> str:
    """The harness server's API address, for flows run in a child process."""
    from prefect.settings import get_current_settings

    return str(get_current_settings().api.url)


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    """Headless chromium (tests/browser.py) for one test module: the GLB tests play our files in three.js."""
    from browser import Browser, chromium_or_fail

    b = Browser(chromium_or_fail(), tmp_path_factory.mktemp("chromium") / "profile", timeout=120.0)
    yield b
    b.close()
