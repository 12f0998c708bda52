"""Faults and load on real flows: kill -9 during tracking, two pipelines writing one store at once, an unwritable store.

(kill -9 during ingestion: tests/test_flows.py; during training: tests/test_train_flow.py.)
"""

import os
import shutil
import subprocess
import sys

import pytest
from factories import (
    DEMO_CORPUS,
    REPO,
    kill_cli_when,
    make_lj_corpus,
    run_pipeline,
    snapshot,
)

from visemeflow.storage import Store

pytestmark = [pytest.mark.flow, pytest.mark.usefixtures("prefect_harness")]


def _child_env(prefect_api_url: str) -> dict[str, str]:
    return {**os.environ, "PREFECT_API_URL": prefect_api_url, "PREFECT_LOGGING_LEVEL": "WARNING"}


def _video_corpus(tmp_path, names=("LJ001-0002", "LJ001-0008", "LJ001-0013", "LJ001-0011")):
    from visemeflow.flows.params import SynthParams
    from visemeflow.flows.synth import synth_flow

    source = tmp_path / "source" / "LJ"
    source.mkdir(parents=True)
    for name in names:
        for ext in (".wav", ".TextGrid"):
            shutil.copyfile(DEMO_CORPUS / "LJ" / f"{name}{ext}", source / f"{name}{ext}")
    out = tmp_path / "videos"
    synth_flow(SynthParams(corpus=source.parent, out=out, store=tmp_path / "truth-store"))
    return out, len(names)


def test_kill_minus_nine_during_tracking_then_rerun_gives_the_uninterrupted_store(tmp_path, prefect_api_url):
    corpus, n = _video_corpus(tmp_path)
    killed, clean = tmp_path / "killed", tmp_path / "clean"
    tracked = killed / "curves" / "tracked"
    kill_cli_when(["pipeline", str(corpus), "--store", str(killed), "--shards", "2"], prefect_api_url,
                  lambda: tracked.exists() and any(tracked.rglob("*.parquet")))
    assert len(Store(killed).curve_files("tracked")) < n, "killed after tracking was done: the test proves nothing"

    run_pipeline(corpus, killed, n_shards=2)
    run_pipeline(corpus, clean, n_shards=2)
    assert not [p for p in killed.rglob(".*.tmp") if ".prefect-results" not in p.parts]
    a, b = snapshot(killed), snapshot(clean)
    assert len(a["curve_files"]) == 2 * n and len(a["tracking_frames"]) > 0
    assert a == b


def test_two_pipelines_writing_one_store_at_once_leave_it_whole(tmp_path, prefect_api_url):
    corpus = make_lj_corpus(tmp_path / "corpus", speakers=6)
    shared, alone = tmp_path / "shared", tmp_path / "alone"
    command = [sys.executable, "-m", "visemeflow.cli", "pipeline", str(corpus), "--store", str(shared), "--shards", "4"]
    procs = [subprocess.Popen(command, cwd=REPO, env=_child_env(prefect_api_url), stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True) for _ in range(2)]
    outputs = [p.communicate(timeout=300)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outputs
    run_pipeline(corpus, alone, n_shards=4)
    a, b = snapshot(shared), snapshot(alone)
    ids = [r["utterance_id"] for r in a["utterances"]]
    assert len(ids) == len(set(ids)) == 6 * 6 + 1  # no duplicate rows
    assert a == b
    assert not [p for p in shared.rglob(".*.tmp") if ".prefect-results" not in p.parts]


def test_an_unwritable_store_is_a_clear_error_and_keeps_what_was_stored(tmp_path, prefect_api_url):
    corpus = make_lj_corpus(tmp_path / "corpus", speakers=1)
    store = tmp_path / "store"
    run_pipeline(corpus, store, n_shards=2)
    before = snapshot(store)
    # a new speaker whose curves cannot be written: a file stands where its folder would go (root ignores
    # permission bits, so a read-only folder would prove nothing here)
    shutil.copytree(corpus / "spk0", corpus / "spk9")
    (store / "curves" / "procedural" / "jali" / "spk9").write_text("not a folder")
    result = subprocess.run(
        [sys.executable, "-m", "visemeflow.cli", "pipeline", str(corpus), "--store", str(store), "--shards", "2"],
        cwd=REPO, env=_child_env(prefect_api_url), capture_output=True, text=True, timeout=300, check=False,
    )
    output = result.stdout + result.stderr
    assert "cannot write" in output and str(store / "curves" / "procedural" / "jali" / "spk9") in output, output
    after = snapshot(store)
    old_ids = {r["utterance_id"] for r in before["utterances"]}
    assert [r for r in after["curves"] if r["utterance_id"] in old_ids] == before["curves"]
    assert not [p for p in store.rglob(".*.tmp") if ".prefect-results" not in p.parts]

    # a store under a regular file cannot exist at all: refused before any flow starts, exit 2, no traceback
    (tmp_path / "afile").write_text("x")
    result = subprocess.run(
        [sys.executable, "-m", "visemeflow.cli", "ingest", str(corpus), "--store", str(tmp_path / "afile" / "store")],
        cwd=REPO, env={**_child_env(prefect_api_url), "COLUMNS": "400"}, capture_output=True, text=True, timeout=300,
        check=False,
    )
    assert result.returncode == 2, result.stdout + result.stderr
    assert "is a file, not a folder" in result.stderr and "Traceback" not in result.stderr
