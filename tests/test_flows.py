"""Real flow runs under the session's Prefect harness: caching, changed files, reruns, kill and resume."""

import os
from pathlib import Path

import pyarrow as pa
import pytest
from factories import (
    LJ_NAMES,
    kill_cli_when,
    make_lj_corpus,
    run_pipeline,
    snapshot,
)

from visemeflow.schemas import C, validate_utterance_id
from visemeflow.storage import Store

pytestmark = [pytest.mark.flow, pytest.mark.usefixtures("prefect_harness")]

def curve_mtimes(store: Path) -> dict[str, int]:
    return {p: os.stat(p).st_mtime_ns for p in Store(store).curve_files()}


def test_second_run_on_unchanged_corpus_is_all_cache_hits(tmp_path):
    corpus = make_lj_corpus(tmp_path / "corpus")
    store = tmp_path / "store"
    first = run_pipeline(corpus, store)
    n = 2 * len(LJ_NAMES) + 1
    assert first["ingest"]["utterances"] == n and first["ingest"]["ingested"] == n
    assert first["procedural"]["generated"] == n and first["ingest"]["cached_shards"] == 0
    before = curve_mtimes(store)
    assert len(before) == n

    second = run_pipeline(corpus, store)
    for stage in ("ingest", "procedural"):
        assert second[stage]["cached_shards"] == second[stage]["shards"] == first[stage]["shards"]
        assert second[stage].get("ingested", 0) == 0 and second[stage].get("generated", 0) == 0
    assert curve_mtimes(store) == before


def test_changed_textgrid_recomputes_only_that_utterance(tmp_path):
    corpus = make_lj_corpus(tmp_path / "corpus")
    store = tmp_path / "store"
    run_pipeline(corpus, store)
    before = curve_mtimes(store)
    old_curves = Store(store).read_curves("spk1/LJ001-0003", "procedural").to_pylist()

    grid = corpus / "spk1" / "LJ001-0003.TextGrid"
    text = grid.read_text()
    # Relabel the first vowel: same timing, different viseme.
    grid.write_text(text.replace('"AH0"', '"IY1"', 1) if '"AH0"' in text else text.replace('"IH0"', '"AA1"', 1))
    assert grid.read_text() != text

    again = run_pipeline(corpus, store)
    assert again["ingest"]["ingested"] == 1
    assert again["procedural"]["generated"] == 1
    # The rest of the changed shard is reused, every other shard is a cache hit.
    assert again["ingest"]["cached_shards"] == again["ingest"]["shards"] - 1
    after = curve_mtimes(store)
    changed = {p for p in after if after[p] != before[p]}
    assert changed == {str(Store(store).curve_path("procedural", "jali", "spk1/LJ001-0003"))}
    assert Store(store).read_curves("spk1/LJ001-0003", "procedural").to_pylist() != old_curves


def test_rerun_one_utterance_even_when_cache_is_valid(tmp_path):
    from visemeflow.flows.params import RerunParams
    from visemeflow.flows.rerun import rerun_flow

    corpus = make_lj_corpus(tmp_path / "corpus", speakers=1)
    store = tmp_path / "store"
    run_pipeline(corpus, store)
    before = curve_mtimes(store)
    content = snapshot(store)

    report = rerun_flow(RerunParams(utterance_id="zh/SSB16240001", stage="procedural", store=store))
    assert report["generated"] == 1
    after = curve_mtimes(store)
    target = str(Store(store).curve_path("procedural", "jali", "zh/SSB16240001"))
    assert {p for p in after if after[p] != before[p]} == {target}
    assert snapshot(store) == content  # regenerated, and deterministic

    report = rerun_flow(RerunParams(utterance_id="spk0/LJ001-0002", stage="ingest", store=store))
    assert report["ingested"] == 1
    assert snapshot(store) == content


def test_bad_inputs_are_rejected_and_the_rest_goes_on(tmp_path):
    from visemeflow.flows.params import RerunParams
    from visemeflow.flows.rerun import rerun_flow

    corpus = make_lj_corpus(tmp_path / "corpus", speakers=1)
    broken = corpus / "spk0" / "LJ001-0005.TextGrid"
    good_text = broken.read_text()
    broken.write_text(good_text[: len(good_text) // 3])
    unknown = corpus / "spk0" / "LJ001-0008.TextGrid"
    unknown.write_text(unknown.read_text().replace('"N"', '"QQ9"', 1))
    store = tmp_path / "store"

    result = run_pipeline(corpus, store)
    assert result["ingest"]["rejected"] == 2
    rejects = {r[C.UTTERANCE_ID]: r for r in Store(store).read_table("rejects").to_pylist()}
    assert set(rejects) == {"spk0/LJ001-0005", "spk0/LJ001-0008"}
    assert rejects["spk0/LJ001-0008"][C.ERROR_TYPE] == "UnknownPhoneme"
    assert "'QQ9'" in rejects["spk0/LJ001-0008"][C.MESSAGE]
    assert str(unknown) in rejects["spk0/LJ001-0008"][C.MESSAGE]
    assert "spk0/LJ001-0005" in rejects["spk0/LJ001-0005"][C.MESSAGE] and str(broken) in rejects["spk0/LJ001-0005"][C.PATH]
    assert result["procedural"]["generated"] == len(LJ_NAMES) + 1 - 2
    # the flow's final state says how many failed (the Prefect UI shows this message on the run)
    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.params import IngestParams

    state = ingest_flow(IngestParams(corpus=corpus, store=store, n_shards=4), return_state=True)
    assert state.is_completed() and state.message.startswith(f"ingest: 2 of {len(LJ_NAMES) + 1} utterances failed")
    assert state.result()["utterances"] == len(LJ_NAMES) + 1
    # every shard a cache hit: the summary still counts the 2 rejects the store holds (it said 0, beside "2 of N")
    assert state.result()["cached_shards"] == state.result()["shards"] and state.result()["rejected"] == 2

    # Fixing the file and rerunning that one utterance by hand clears its reject.
    broken.write_text(good_text)
    rerun_flow(RerunParams(utterance_id="spk0/LJ001-0005", stage="ingest", store=store))
    rerun_flow(RerunParams(utterance_id="spk0/LJ001-0005", stage="procedural", store=store))
    s = Store(store)
    assert "spk0/LJ001-0005" in s.read_table("utterances").column(C.UTTERANCE_ID).to_pylist()
    assert {r[C.UTTERANCE_ID] for r in s.read_table("rejects").to_pylist()} == {"spk0/LJ001-0008"}
    assert s.has_curves("procedural", "jali", "spk0/LJ001-0005")


def test_kill_minus_nine_then_rerun_gives_the_uninterrupted_store(tmp_path, prefect_api_url):
    corpus = make_lj_corpus(tmp_path / "corpus", speakers=8)
    killed_store, clean_store = tmp_path / "killed", tmp_path / "clean"
    curves_dir = killed_store / "curves"
    kill_cli_when(["pipeline", str(corpus), "--store", str(killed_store), "--shards", "8"], prefect_api_url,
                  lambda: curves_dir.exists() and any(curves_dir.rglob("*.parquet")))
    n_total = 8 * len(LJ_NAMES) + 1
    assert len(Store(killed_store).curve_files()) < n_total, "killed after all work was done: the test proves nothing"

    run_pipeline(corpus, killed_store, n_shards=8)
    run_pipeline(corpus, clean_store, n_shards=8)
    assert not [p for p in killed_store.rglob(".*.tmp") if ".prefect-results" not in p.parts]
    killed, clean = snapshot(killed_store), snapshot(clean_store)
    # Paths differ only by the store folder; the data must be the same.
    assert killed == clean
    assert len(killed["curve_files"]) == n_total


def test_utterance_ids_in_the_store_are_valid(tmp_path):
    corpus = make_lj_corpus(tmp_path / "corpus", speakers=1)
    store = tmp_path / "store"
    run_pipeline(corpus, store)
    ids = Store(store).read_table("utterances").column(C.UTTERANCE_ID).to_pylist()
    assert all(validate_utterance_id(i) == i for i in ids)
    assert isinstance(Store(store).scan_curves(), pa.Table)


def test_an_input_changed_and_changed_back_is_processed_again(tmp_path):
    """A TextGrid edited, then restored (A, B, A): the cache records of the first run matched the third, and the
    store kept the edit's phones and curves (a new user's report). A shard's output now records the inputs it was
    made from, and a cached shard whose files say otherwise runs again: the store ends as after the first run."""
    corpus = make_lj_corpus(tmp_path / "corpus")
    store = tmp_path / "store"
    run_pipeline(corpus, store)
    uid = "spk1/LJ001-0003"
    first_phones = Store(store).read_table("phones", utterance_ids=[uid]).to_pylist()
    first_curves = Store(store).read_curves(uid, "procedural").to_pylist()

    grid = corpus / "spk1" / "LJ001-0003.TextGrid"
    text = grid.read_text()
    grid.write_text(text.replace('"AH0"', '"IY1"', 1) if '"AH0"' in text else text.replace('"IH0"', '"AA1"', 1))
    edited = run_pipeline(corpus, store)
    assert edited["ingest"]["ingested"] == 1 and edited["procedural"]["generated"] == 1
    assert Store(store).read_table("phones", utterance_ids=[uid]).to_pylist() != first_phones

    grid.write_text(text)
    restored = run_pipeline(corpus, store)
    assert restored["ingest"]["ingested"] == 1 and restored["procedural"]["generated"] == 1
    assert restored["ingest"]["cached_shards"] == restored["ingest"]["shards"] - 1
    assert Store(store).read_table("phones", utterance_ids=[uid]).to_pylist() == first_phones
    assert Store(store).read_curves(uid, "procedural").to_pylist() == first_curves
