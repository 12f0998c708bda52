"""`visemeflow clean`: removes only what the flows can make again, and a rerun after it gives the same store."""

import os
import subprocess

import pytest
from factories import make_lj_corpus, run_pipeline, snapshot
from typer.testing import CliRunner

from visemeflow.cli import app
from visemeflow.ops.clean import KINDS, clean, reclaimable
from visemeflow.storage import Store
from visemeflow.tasks.common import result_storage


def dead_pid() -> int:
    child = subprocess.Popen(["true"])
    child.wait()
    return child.pid


def layout(root) -> dict[str, list]:
    """A store with one file of every kind, reclaimable or not."""
    files = {
        "keep": [
            "curves/procedural/jali/LJ/LJ001-0001.parquet", "tables/utterances/shard-0000.parquet",
            "models/done/model.pt", "models/killed/checkpoints/last.pt", "metrics/done/train.parquet",
            f"curves/procedural/jali/LJ/.LJ001-0002.parquet.{os.getpid()}.abc.tmp",  # a writer still running
        ],
        "temporary": [f"tables/phones/.shard-0001.parquet.{dead_pid()}.abc.tmp",
                      f"reports/.sweep-x.png.{dead_pid()}.0a1b2c3d.tmp.png",            # a writer that needs the suffix
                      f"models/killed/checkpoints/.last.pt.{dead_pid()}.0a1b2c3d.tmp"],
        "augmented": ["augmented/pitch-s0/LJ/LJ001-0001.wav", "augmented/noise-s0/LJ/LJ001-0001.wav"],
        "checkpoints": ["models/done/checkpoints/last.pt"],
        "results": [".prefect-results/0123abcd"],
    }
    for paths in files.values():
        for rel in paths:
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            (root / rel).write_bytes(b"x" * 100)
    return files


@pytest.mark.parametrize("kind", KINDS)
def test_each_kind_removes_its_own_files_and_nothing_else(tmp_path, kind):
    files = layout(tmp_path)
    store = Store(tmp_path)
    listed = {item.kind: item for item in reclaimable(store)}
    assert listed[kind].n_bytes == 100 * len(files[kind])
    assert all((tmp_path / rel).exists() for paths in files.values() for rel in paths)  # listing removes nothing
    removed = clean(store, [kind])
    assert [item.kind for item in removed] == [kind]
    for group, paths in files.items():
        for rel in paths:
            assert (tmp_path / rel).exists() == (group != kind), (group, rel)


def test_cli_lists_without_removing_and_removes_what_is_named(tmp_path):
    files = layout(tmp_path)
    runner = CliRunner()
    listed = runner.invoke(app, ["clean", "--store", str(tmp_path)])
    assert listed.exit_code == 0, listed.output
    assert "augmented" in listed.output and "200 B reclaimable in 2 paths" in listed.output
    assert "nothing removed" in listed.output
    dry = runner.invoke(app, ["clean", "augmented", "--dry-run", "--store", str(tmp_path)])
    assert dry.exit_code == 0 and "reclaimable" in dry.output
    assert all((tmp_path / rel).exists() for rel in files["augmented"])
    done = runner.invoke(app, ["clean", "augmented", "checkpoints", "--store", str(tmp_path)])
    assert done.exit_code == 0, done.output
    assert "augmented" in done.output and "200 B removed in 2 paths" in done.output
    assert not any((tmp_path / rel).exists() for rel in files["augmented"] + files["checkpoints"])
    assert all((tmp_path / rel).exists() for rel in files["keep"] + files["results"])
    bad = runner.invoke(app, ["clean", "curves", "--store", str(tmp_path)])
    assert bad.exit_code == 2 and bad.output == "error: unknown kind curves; choose from temporary, augmented, checkpoints, results\n"
    typo = runner.invoke(app, ["clean", "--store", str(tmp_path / "no-such-store")])
    assert typo.exit_code == 2 and f"no store at {tmp_path / 'no-such-store'}" in typo.output


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_a_rerun_after_removing_the_cached_results_gives_the_same_store(tmp_path):
    corpus = make_lj_corpus(tmp_path / "corpus")
    store = tmp_path / "store"
    run_pipeline(corpus, store)
    before = snapshot(store)
    assert any(result_storage(store).iterdir())
    clean(Store(store), ["results"])
    assert not result_storage(store).exists()
    summary = run_pipeline(corpus, store)
    assert summary["ingest"]["cached_shards"] == summary["procedural"]["cached_shards"] == 0  # all ran again
    assert snapshot(store) == before
    assert any(result_storage(store).iterdir())  # and the cache is back
