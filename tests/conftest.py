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


# Test files that take about half a minute or more of one xdist worker on the 2-core CI machine (rough seconds, from
# CI runs of 2026-12-05/06 and single-file runs), longest first. `make test` gives pytest-xdist whole files
# (--dist loadfile) in collection order (--no-loadscope-reorder), and `pytest_collection_modifyitems` below puts these
# files first. xdist's own order (most tests first) left the heavy files of few tests to the end (syllables, install,
# onnx_whisper, faults, speaker_identity: one to two minutes each of one worker), and one worker finished about a
# minute before the other. A file missing here only runs later; the order changes nothing a test does.
HEAVY_FILES = {
    "test_benches.py": 310, "test_s3_store.py": 250, "test_serve.py": 90, "test_bones.py": 80, "test_faults.py": 70,
    "test_predict.py": 70, "test_cli_output.py": 65, "test_syllables.py": 65, "test_animate_flow.py": 60,
    "test_install.py": 50, "test_flows.py": 50, "test_onnx_export.py": 50, "test_cli_fast.py": 50,
    "test_recognise.py": 45, "test_security.py": 45, "test_corpus_mistakes.py": 45, "test_dask.py": 40,
    "test_landmarks_flow.py": 38, "test_livelink.py": 37, "test_synth.py": 36, "test_default_model.py": 35,
    "test_onnx_whisper.py": 35, "test_speaker_identity.py": 35, "test_arkit_character.py": 30,
    "test_prefect_db.py": 25,
}


def pytest_collection_modifyitems(config, items):
    """Whole files, the HEAVY_FILES first (longest first), then the others most tests first (xdist's own order),
    each file's tests in their own order: the longest work starts first and both workers end together."""
    files: dict[str, int] = {}
    counts: dict[str, int] = {}
    for item in items:
        f = item.nodeid.split("::", 1)[0]
        files.setdefault(f, len(files))
        counts[f] = counts.get(f, 0) + 1

    def key(item):
        f = item.nodeid.split("::", 1)[0]
        return -HEAVY_FILES.get(f.rsplit("/", 1)[-1], 0), -counts[f], files[f]

    items.sort(key=key)   # stable: each file's tests keep their order


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
