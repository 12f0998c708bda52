"""Task caches see the code a task runs: an edit to a domain module recomputes the stages that run it, only those."""

import importlib
import os
import pkgutil
import shutil
from pathlib import Path

import pytest
from factories import make_lj_corpus, run_pipeline

import visemeflow
import visemeflow.tasks
from visemeflow.storage import Store

PACKAGE = Path(visemeflow.__file__).resolve().parent
STAGES = ["ingest", "procedural", "track", "landmarks", "synth", "import_curves", "predict", "train", "evaluate",
          "animate"]


def package_copy(tmp_path: Path) -> Path:
    """A copy of the package's source, to edit."""
    root = tmp_path / "visemeflow"
    shutil.copytree(PACKAGE, root, ignore=shutil.ignore_patterns("__pycache__", "data"))
    return root


def edit(root: Path, relative: str) -> None:
    """Append a function to one module of the copy (a change of its code, not of its imports)."""
    path = root / relative
    path.write_text(path.read_text(encoding="utf-8") + "\n\ndef _edited_by_a_test():\n    return 1\n", encoding="utf-8")


def digests(root: Path) -> dict[str, str]:
    from visemeflow.tasks.code_version import source_digest

    return {stage: source_digest(f"visemeflow.tasks.{stage}", root) for stage in STAGES}


def changed_by(tmp_path: Path, relative: str) -> set[str]:
    """The stages whose code digest an edit of `relative` changes."""
    root = package_copy(tmp_path)
    before = digests(root)
    edit(root, relative)
    after = digests(root)
    return {stage for stage in STAGES if before[stage] != after[stage]}


def test_editing_jali_changes_the_procedural_digest_not_ingest(tmp_path):
    changed = changed_by(tmp_path, "procedural/jali.py")
    assert "procedural" in changed
    assert not changed & {"ingest", "landmarks", "track", "import_curves"}, changed


def test_editing_the_solver_changes_the_track_digest_not_procedural(tmp_path):
    changed = changed_by(tmp_path, "tracking/solver.py")
    assert "track" in changed and not changed & {"ingest", "procedural", "landmarks"}, changed


def test_editing_a_feature_extractor_changes_train_predict_and_evaluate(tmp_path):
    changed = changed_by(tmp_path, "learning/features.py")
    assert {"train", "predict", "evaluate"} <= changed and not changed & {"ingest", "procedural"}, changed


def test_editing_ingest_changes_every_stage_that_reads_its_rows(tmp_path):
    assert changed_by(tmp_path, "ingest/utterance.py") == set(STAGES)


def test_editing_the_dashboards_changes_no_stage(tmp_path):
    assert changed_by(tmp_path, "dashboards/plots.py") == set()


def test_relative_imports_and_parent_packages_are_followed(tmp_path):
    from visemeflow.tasks.code_version import imported_modules

    root = tmp_path / "visemeflow"
    (root / "a").mkdir(parents=True)
    (root / "__init__.py").write_text("")
    (root / "a" / "__init__.py").write_text("from . import b\n")
    (root / "a" / "b.py").write_text("def f():\n    from ..c import g\n")
    (root / "c.py").write_text("g = 1\n")
    (root / "d.py").write_text("from visemeflow.a.b import f\n")
    assert imported_modules("visemeflow.d", root) == {"visemeflow", "visemeflow.a", "visemeflow.a.b",
                                                      "visemeflow.c", "visemeflow.d"}


def _persisted_tasks():
    from prefect.tasks import Task

    for info in pkgutil.iter_modules(visemeflow.tasks.__path__):
        module = importlib.import_module(f"visemeflow.tasks.{info.name}")
        for value in vars(module).values():
            if isinstance(value, Task) and value.persist_result:
                yield value


def test_every_persisted_task_is_keyed_on_its_code():
    from prefect.cache_policies import CompoundCachePolicy

    from visemeflow.tasks.common import CodeDigest, DataOnlyCache

    tasks = list(_persisted_tasks())
    assert len(tasks) >= 12
    for t in tasks:
        assert isinstance(t.cache_policy, DataOnlyCache), t.name
        inner = t.cache_policy.policy
        assert isinstance(inner, CompoundCachePolicy) and any(isinstance(p, CodeDigest) for p in inner.policies), \
            f"{t.name}: its cache key does not hold the code digest of its module"


def test_a_task_outside_the_package_has_no_code_digest():
    from visemeflow.tasks.code_version import code_digest

    with pytest.raises(ValueError, match="test_module.*outside"):
        code_digest("test_module")


@pytest.fixture
def digest_root(monkeypatch):
    """Point the code digest at another copy of the package (the code that runs stays the installed one)."""
    from visemeflow.tasks import code_version

    def point(root: Path) -> None:
        monkeypatch.setattr(code_version, "ROOT", root)
        code_version.code_digest.cache_clear()

    yield point
    code_version.code_digest.cache_clear()


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_a_changed_domain_module_recomputes_the_stage_and_an_unrelated_one_does_not(tmp_path, digest_root):
    corpus = make_lj_corpus(tmp_path / "corpus", speakers=1, names=["LJ001-0002", "LJ001-0005"])
    store = tmp_path / "store"
    root = package_copy(tmp_path / "code")
    digest_root(root)
    first = run_pipeline(corpus, store, n_shards=2)
    n = first["procedural"]["generated"]
    assert n == 3 and first["procedural"]["cached_shards"] == 0
    uid = "spk0/LJ001-0002"
    provenance = Store(store).curves_provenance("procedural", "jali", uid)
    path = Store(store).curve_path("procedural", "jali", uid)
    mtime = os.stat(path).st_mtime_ns

    edit(root, "dashboards/html.py")
    digest_root(root)
    unrelated = run_pipeline(corpus, store, n_shards=2)
    for stage in ("ingest", "procedural"):
        assert unrelated[stage]["cached_shards"] == unrelated[stage]["shards"], (stage, unrelated[stage])
    assert os.stat(path).st_mtime_ns == mtime

    edit(root, "procedural/jali.py")
    digest_root(root)
    again = run_pipeline(corpus, store, n_shards=2)
    assert again["ingest"]["cached_shards"] == again["ingest"]["shards"] and again["ingest"].get("ingested", 0) == 0
    # a cache miss that reused the stored curves would be no fix: every utterance's curves are made again
    assert again["procedural"]["cached_shards"] == 0 and again["procedural"]["generated"] == n, again["procedural"]
    assert again["procedural"]["reused"] == 0
    assert os.stat(path).st_mtime_ns != mtime
    # the curves' provenance records the new code, so the stages keyed on it (track, train, animate) recompute too
    assert Store(store).curves_provenance("procedural", "jali", uid) != provenance


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_changed_training_code_trains_again_rather_than_resuming_the_old_checkpoint(tmp_path, digest_root):
    from factories import make_curve_store
    from prefect import flow

    from visemeflow.learning.train import TrainConfig
    from visemeflow.tasks.train import training_task_for

    s = make_curve_store(tmp_path / "store", n=4)
    rows = s.read_table("utterances").to_pylist()
    root = package_copy(tmp_path / "code")
    digest_root(root)

    @flow
    def train_tiny():
        return training_task_for(s, "m")(str(s.root), "m", rows[2:], rows[:2], "ground_truth", "cm", {},
                                         TrainConfig(preset="fbank-tcn", d_model=8, epochs=2))

    first = train_tiny()
    checkpoint = s.checkpoint_dir("m") / "last.pt"
    mtime = os.stat(checkpoint).st_mtime_ns
    assert train_tiny() == first and os.stat(checkpoint).st_mtime_ns == mtime  # same code: cached

    edit(root, "learning/train.py")
    digest_root(root)
    again = train_tiny()
    # resuming the finished checkpoint would hand back the old code's weights without one epoch of the new code
    assert os.stat(checkpoint).st_mtime_ns != mtime and again["epochs"] == 2


def test_the_line_scan_of_imports_finds_what_the_parser_finds_in_every_module():
    """code_version reads import statements from the lines (CPython 3.11's `ast.parse` fails when task threads parse
    at once: "AST constructor recursion depth mismatch", a failed cache key in CI); on every module of the package
    it finds exactly the package modules the parser finds."""
    import ast
    import importlib
    import importlib.util

    from visemeflow.tasks import code_version as cv

    def parsed(module: str, path) -> set[str]:
        found: set[str] = set()
        for node in ast.walk(ast.parse(path.read_bytes())):
            if isinstance(node, ast.Import):
                found.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = module.split(".")
                    anchor = anchor[:len(anchor) - node.level + (1 if path.name == "__init__.py" else 0)]
                    base = ".".join(anchor + ([node.module] if node.module else []))
                found.add(base)
                found.update(f"{base}.{a.name}" for a in node.names if a.name != "*")
        return {n for n in found if n.split(".")[0] == cv.PACKAGE and cv.module_path(n, cv.ROOT)}

    for path in sorted(cv.ROOT.rglob("*.py")):
        module = ".".join(path.relative_to(cv.ROOT.parent).with_suffix("").parts).removesuffix(".__init__")
        scanned = {n for n in cv._imported(module, path) if cv.module_path(n, cv.ROOT)}
        # a package exporting names on first use (visemeflow.lazy) imports the modules of its `_EXPORTS` table then
        exports = getattr(importlib.import_module(module), "_EXPORTS", {}) if path.name == "__init__.py" else {}
        lazy = {importlib.util.resolve_name(name, module) for name in exports.values()}
        assert scanned == parsed(module, path) | lazy, module
