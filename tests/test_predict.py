"""The `predict` flow and command: curves of new audio from a trained model, cached per model and audio content,
CSV/JSON copies, an artifact with the real-time factors, and a command that exits cleanly every time."""

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from factories import DEMO_AUDIO, REPO, tiny_model

from visemeflow.animation.export import FORMATS
from visemeflow.schemas import curves_array
from visemeflow.storage import Store

AUDIO = DEMO_AUDIO


@pytest.fixture
def store(tmp_path):
    s = Store(tmp_path / "store")
    tiny_model(s)
    return s


def test_prediction_ids_keep_the_file_name_in_any_script_and_stay_safe():
    import unicodedata

    from visemeflow.flows.predict import prediction_id

    assert prediction_id("a/b/take 1 (final).wav") == "predict/take 1 (final)"
    assert prediction_id("/x/张三 第一句.wav") == "predict/张三 第一句"
    assert prediction_id(unicodedata.normalize("NFD", "Sätze.wav")) == "predict/Sätze"
    assert prediction_id("/x/.hidden.wav") == "predict/hidden"
    assert prediction_id("/x/....wav") == "predict/audio"
    assert prediction_id("clip.v2.mp4") == "predict/clip.v2"
    assert prediction_id("/x/a\\b\tc.wav") == "predict/a_b_c"


def test_files_of_one_name_get_ids_of_their_own_that_the_same_batch_gets_again(tmp_path):
    import unicodedata

    from visemeflow.flows.predict import prediction_ids

    nfc, nfd = unicodedata.normalize("NFC", "Sätze.wav"), unicodedata.normalize("NFD", "Sätze.wav")
    batch = [tmp_path / "a" / "x.wav", tmp_path / "b" / "x.wav", tmp_path / "y.wav", tmp_path / nfc, tmp_path / nfd,
             tmp_path / "a" / ".." / "y.wav"]
    ids = prediction_ids(batch)
    assert ids[2] == ids[5] == "predict/y"   # one file under two spellings of its path: one id
    assert len(set(ids[:5])) == 5 and all(i.startswith("predict/x-") for i in ids[:2])
    assert ids[3].startswith("predict/Sätze-") and ids[4].startswith("predict/Sätze-")
    assert prediction_ids(batch) == ids and prediction_ids(list(reversed(batch))) == list(reversed(ids))
    # a file named like a disambiguated one is told apart too; a name at the length limit still gets its suffix
    taken = prediction_ids([tmp_path / ids[0].split("/")[1], *batch[:2]])
    assert len(set(taken)) == 3
    long = "n" * 200
    assert len(set(prediction_ids([tmp_path / "a" / f"{long}.wav", tmp_path / "b" / f"{long}.wav"]))) == 2


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_predict_flow_caches_per_model_and_audio_content_and_exports(store, tmp_path):
    from prefect.client.orchestration import get_client

    from visemeflow.flows.predict import PredictParams, predict_flow

    stereo = tmp_path / "in" / "stereo.wav"
    stereo.parent.mkdir()
    audio, rate = sf.read(AUDIO, dtype="float32")
    sf.write(stereo, np.stack([audio, 0.5 * audio], axis=1), rate)
    out = tmp_path / "out"
    params = PredictParams(store=store.root, model="tiny", audio=[AUDIO, stereo], fps=25.0, out=out)

    first = predict_flow(params)
    rows = first["predictions"]
    assert [r["utterance_id"] for r in rows] == ["predict/SSB16240001", "predict/stereo"]
    assert [r["cached"] for r in rows] == [False, False]
    assert all(r["frames"] == round(len(audio) / rate * 25) and r["real_time_factor"] > 0 for r in rows)
    curves = store.read_curves("predict/stereo", "predicted", "tiny")
    assert curves.num_rows == rows[1]["frames"]
    assert sorted(p.name for p in out.iterdir()) == sorted(f"{s}.{f}" for s in ("SSB16240001", "stereo") for f in FORMATS)
    exported = {p.name: p.read_bytes() for p in out.iterdir()}

    with get_client(sync_client=True) as client:
        artifact = client.read_latest_artifacts()  # newest per key
    markdown = next(a for a in artifact if a.key == "predictions").data
    assert "predict/stereo" in markdown and "real-time factor" in markdown and str(out / "stereo.csv") in markdown

    # the same run again, with the device named: every file is a cache hit (where the model runs is not part of the
    # key), nothing in the store changes, the copies are the same
    stamp = store.curve_path("predicted", "tiny", "predict/stereo").stat().st_mtime_ns
    again = predict_flow(params.model_copy(update={"device": "cpu"}))
    assert [r["cached"] for r in again["predictions"]] == [True, True]
    assert [r["real_time_factor"] for r in again["predictions"]] == [r["real_time_factor"] for r in rows]
    assert store.curve_path("predicted", "tiny", "predict/stereo").stat().st_mtime_ns == stamp
    assert {p.name: p.read_bytes() for p in out.iterdir()} == exported

    # changed audio under the same name is predicted again; the other file stays cached
    sf.write(stereo, np.stack([0.5 * audio, audio], axis=1), rate)
    changed = predict_flow(params)["predictions"]
    assert [r["cached"] for r in changed] == [True, False]
    # a retrained model (other weights, same name) recomputes everything
    tiny_model(store, seed=1)
    assert [r["cached"] for r in predict_flow(params)["predictions"]] == [False, False]
    # curves deleted from the store are made again rather than trusted from the cache
    store.curve_path("predicted", "tiny", "predict/stereo").unlink()
    assert [r["cached"] for r in predict_flow(params)["predictions"]] == [True, False]
    assert store.has_curves("predicted", "tiny", "predict/stereo")


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_predict_flow_refuses_unknown_models_and_missing_files(store, tmp_path):
    from visemeflow.flows.predict import PredictParams, predict_flow

    with pytest.raises(LookupError, match="no trained model named nope.*known models: tiny"):
        predict_flow(PredictParams(store=store.root, model="nope", audio=[AUDIO]))
    from visemeflow.flows.errors import StageFailed

    with pytest.raises(StageFailed, match="every audio file was rejected.*missing.wav: no such audio file"):
        predict_flow(PredictParams(store=store.root, model="tiny", audio=[tmp_path / "missing.wav"]))


# `visemeflow predict` used to end with SIGABRT ("terminate called without an active exception", exit 134) after
# writing its outputs, now and then. The cause (core dump): `Store` reads a Parquet file through a Python file object
# (`storage/store.py: _read_whole`), so Arrow's reads return buffers owned by Python; Arrow's I/O threads can drop the
# last reference to one after `read_table` returned. When that happens while the interpreter is finalizing (the
# command's last act was a read), the I/O thread must take the GIL, CPython ends the thread with pthread_exit, and the
# forced unwind through pyarrow's noexcept ~PyBuffer calls std::terminate. The window is short (the I/O thread must be
# preempted between completing the read and releasing the buffer), so the reads run four at a time on the 2 cores:
# that made about 1 process in 8 abort before the fix. A regression shows with probability above 99% in 40 runs
# (1 - (7/8)^40 = 99.5%).
READ_RUNS = 40
READ_PARALLEL = 4
PREDICT_RUNS = 4   # the real command end to end (slower: it imports torch and Prefect)

_READ_LAST = """
import sys
from visemeflow.storage import Store
print(Store(sys.argv[1]).read_curves(sys.argv[2], "predicted", "tiny").num_rows)
"""


def _run_many(command, runs, env, cwd, parallel=1):
    """The failures (exit status and end of stderr) of `runs` runs of `command`, `parallel` at a time."""
    from concurrent.futures import ThreadPoolExecutor

    def run(k):
        done = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=180)
        if done.returncode != 0 or "terminate called" in done.stderr:
            return f"run {k}: exit {done.returncode}\n{done.stderr[-1500:]}"
        return None

    with ThreadPoolExecutor(parallel) as pool:
        return [f for f in pool.map(run, range(runs)) if f]


@pytest.mark.flow
def test_predict_command_exits_cleanly_every_time(store, tmp_path, prefect_api_url):
    env = {**os.environ, "PREFECT_API_URL": prefect_api_url, "PYTHONFAULTHANDLER": "1"}
    visemeflow = str(Path(sys.executable).parent / "visemeflow")
    out = tmp_path / "out"
    started = time.perf_counter()
    failures = _run_many([visemeflow, "predict", str(AUDIO), "--model", "tiny", "--store", str(store.root),
                          "--out", str(out)], PREDICT_RUNS, env, REPO)
    assert not failures, f"{len(failures)} of {PREDICT_RUNS} predict runs failed:\n" + "\n".join(failures)
    assert sorted(p.name for p in out.iterdir()) == ["SSB16240001.csv", "SSB16240001.json"]
    # the part that aborted: a store read as the process's last act (what `predict --out` and `curves export` do)
    script = tmp_path / "read_last.py"
    script.write_text(_READ_LAST)
    failures = _run_many([sys.executable, str(script), str(store.root), "predict/SSB16240001"], READ_RUNS, env, REPO,
                         parallel=READ_PARALLEL)
    assert not failures, (f"{len(failures)} of {READ_RUNS} processes ending with a store read aborted:\n"
                          + "\n".join(failures[:3]))
    print(f"{PREDICT_RUNS} predict runs and {READ_RUNS} reads in {time.perf_counter() - started:.1f} s")


def _two_files_named_x(tmp_path) -> tuple[Path, Path]:
    """a/x.wav (the demo utterance) and b/x.wav (the same sound reversed): one name, different curves."""
    audio, rate = sf.read(AUDIO, dtype="float32")
    a, b = tmp_path / "a" / "x.wav", tmp_path / "b" / "x.wav"
    for path, samples in ((a, audio), (b, audio[::-1].copy())):
        path.parent.mkdir()
        sf.write(path, samples, rate)
    return a, b


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_files_of_one_name_in_different_folders_each_keep_their_own_curves_and_copies(store, tmp_path):
    from visemeflow.flows.predict import PredictParams, predict_flow

    a, b = _two_files_named_x(tmp_path)
    out = tmp_path / "out"
    rows = predict_flow(PredictParams(store=store.root, model="tiny", audio=[a, b, AUDIO], fps=25.0,
                                      out=out))["predictions"]
    ids = [r["utterance_id"] for r in rows]
    assert len(set(ids)) == 3 and ids[2] == "predict/SSB16240001"  # a file whose name is its own keeps it
    assert all(i.startswith("predict/x-") for i in ids[:2])
    assert len({p for r in rows for p in r["exports"]}) == 6 and len(list(out.iterdir())) == 6
    alone = predict_flow(PredictParams(store=store.root, model="tiny", audio=[b], fps=25.0))["predictions"][0]
    assert alone["utterance_id"] == "predict/x"
    # another batch of the other file of that name replaces those curves, and says so
    other = predict_flow(PredictParams(store=store.root, model="tiny", audio=[a], fps=25.0))
    assert other["replaced"] == [{"utterance_id": "predict/x", "before": str(b.resolve()), "now": str(a.resolve())}]
    assert predict_flow(PredictParams(store=store.root, model="tiny", audio=[b], fps=25.0))["replaced"][0]["now"] \
        == str(b.resolve())
    # the same names in the same batch again: the same ids, each file's own curves
    again = predict_flow(PredictParams(store=store.root, model="tiny", audio=[a, b], fps=25.0))["predictions"]
    assert [r["utterance_id"] for r in again] == ids[:2]
    curves = [curves_array(store.read_curves(i, "predicted", "tiny")) for i in ids[:2]]
    assert not np.allclose(curves[0], curves[1])
    np.testing.assert_array_equal(curves[1], curves_array(store.read_curves("predict/x", "predicted", "tiny")))
    # where each predicted utterance's audio was, for the dashboard (the curves record only its hash)
    from visemeflow.dashboards.records import recorded_predicted_audio

    recorded = recorded_predicted_audio(store)
    assert {i: recorded[i] for i in ids} == {ids[0]: str(a.resolve()), ids[1]: str(b.resolve()),
                                              ids[2]: str(AUDIO.resolve())}


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_a_cache_hit_never_serves_curves_another_file_or_frame_rate_wrote(store, tmp_path):
    from visemeflow.flows.predict import PredictParams, predict_flow

    a, b = _two_files_named_x(tmp_path)
    out = tmp_path / "out"

    def run(path, fps=25.0):
        (row,) = predict_flow(PredictParams(store=store.root, model="tiny", audio=[path], fps=fps,
                                            out=out))["predictions"]
        return row, curves_array(store.read_curves("predict/x", "predicted", "tiny"))

    first, curves_a = run(a)
    run(b)   # same id, other sound: replaces a's curves in the store
    rerun, curves = run(a)
    assert not rerun["cached"]
    np.testing.assert_array_equal(curves, curves_a)
    exported = np.loadtxt(out / "x.csv", delimiter=",", skiprows=1)[:, 2:]
    np.testing.assert_allclose(exported, curves_a, atol=1e-6)
    run(a, fps=30.0)
    at_25, curves = run(a)
    assert not at_25["cached"] and len(curves) == len(curves_a)
    assert run(a)[0]["cached"]   # and a true hit is still one


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_bad_audio_files_are_rejects_and_the_others_are_predicted(store, tmp_path):
    from visemeflow.flows.errors import StageFailed
    from visemeflow.flows.predict import PredictParams, predict_flow
    from visemeflow.schemas import C

    text = tmp_path / "notes.wav"
    text.write_text("not audio")
    missing = tmp_path / "missing.wav"
    result = predict_flow(PredictParams(store=store.root, model="tiny", audio=[text, AUDIO, missing]))
    assert [r["utterance_id"] for r in result["predictions"]] == ["predict/SSB16240001"]
    assert store.has_curves("predicted", "tiny", "predict/SSB16240001")
    assert result["rejected"] == 2 and result["files"] == 3
    rejects = {r[C.PATH]: r for r in store.read_table("rejects", "predict").to_pylist()}
    assert set(rejects) == {str(text), str(missing)}
    assert str(text) in rejects[str(text)][C.MESSAGE] and rejects[str(text)][C.ERROR_TYPE] == "UnreadableAudio"
    assert "no such audio file" in rejects[str(missing)][C.MESSAGE]
    assert {r["audio"] for r in result["rejects"]} == {str(text), str(missing)}
    with pytest.raises(StageFailed, match="every audio file was rejected.*notes.wav"):
        predict_flow(PredictParams(store=store.root, model="tiny", audio=[text]))
    # batches are independent: a batch of other files keeps those rejects listed; a file fixed and predicted again
    # clears its own
    predict_flow(PredictParams(store=store.root, model="tiny", audio=[AUDIO]))
    assert {r[C.PATH] for r in store.read_table("rejects", "predict").to_pylist()} == {str(text), str(missing)}
    sf.write(text, np.zeros(8000, np.float32), 16000)
    predict_flow(PredictParams(store=store.root, model="tiny", audio=[text]))
    assert [r[C.PATH] for r in store.read_table("rejects", "predict").to_pylist()] == [str(missing)]


@pytest.mark.flow
def test_predict_command_exits_1_and_says_so_when_a_file_was_rejected(store, tmp_path, prefect_api_url):
    env = {**os.environ, "PREFECT_API_URL": prefect_api_url}
    text = tmp_path / "notes.wav"
    text.write_text("not audio")
    done = subprocess.run([str(Path(sys.executable).parent / "visemeflow"), "predict", str(text), str(AUDIO),
                           "--model", "tiny", "--store", str(store.root)], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 1, done.stderr
    assert "predict: 2 files, 1 predicted, 0 cached, 1 rejected" in done.stdout
    assert f"rejected {text}: " in done.stderr
    assert store.has_curves("predicted", "tiny", "predict/SSB16240001")


@pytest.mark.flow
def test_a_cached_predict_command_is_still_tracked_and_prints_and_stores_the_same(store, tmp_path, prefect_api_url):
    """The command ends its flow run without waiting for the heartbeat thread (`ops.connect.unjoined_heartbeats`),
    records its parameters without importing FastAPI (`flows.predict.serialize_parameters`) and ends its process
    without Python's teardown (`cli.main`), which took about 1.5 s of a cached 3.5 s `predict` (bench/cli.py). The
    cached run is still in the API as before: Completed, with its parameters as Prefect records them, its cached task
    run, its artifact and its heartbeat; it prints what the first run printed, cached, and changes nothing stored."""
    from prefect import Flow
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterFlowRunId, FlowRunFilter
    from prefect.client.schemas.filters import FlowRunFilterId, FlowRunFilterName
    from prefect.client.schemas.sorting import FlowRunSort
    from prefect.events.filters import EventAnyResourceFilter, EventFilter, EventNameFilter

    from visemeflow.flows.predict import PredictParams, predict_flow

    env = {**os.environ, "PREFECT_API_URL": prefect_api_url}
    command = [str(Path(sys.executable).parent / "visemeflow"), "predict", str(AUDIO), "--model", "tiny", "--store",
               str(store.root), "--device", "cpu"]
    first = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert first.returncode == 0, first.stderr
    curves = store.curve_path("predicted", "tiny", "predict/SSB16240001")
    stored = (curves.read_bytes(), curves.stat().st_mtime_ns, sorted(p.name for p in store.root.rglob("*")))
    second = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert second.returncode == 0, second.stderr
    line, summary, where = first.stdout.splitlines()
    assert line.endswith(")") and summary == "predict: 1 file, 1 predicted, 0 cached, 0 rejected"
    assert where.startswith(f"the curves are in the store {store.root} (source predicted, variant tiny): ")
    head, speed = line[:-1].split(" (real-time factor ")   # the cached line names the speed it was computed at
    assert second.stdout.splitlines() == [f"{head} (cached; computed at real-time factor {speed})",
                                          "predict: 1 file, 0 predicted, 1 cached, 0 rejected", where]
    assert (curves.read_bytes(), curves.stat().st_mtime_ns, sorted(p.name for p in store.root.rglob("*"))) == stored

    params = PredictParams(store=store.root, model="tiny", audio=[AUDIO], device="cpu")
    with get_client(sync_client=True) as client:
        runs = client.read_flow_runs(flow_run_filter=FlowRunFilter(name=FlowRunFilterName(any_=["predict(tiny)"])),
                                     sort=FlowRunSort.START_TIME_DESC)
        runs = [r for r in runs if r.parameters["params"]["store"] == str(store.root)]
        assert len(runs) == 2
        run = runs[0]   # the cached one
        assert run.state.is_completed() and run.state.message == "1 of 1 audio files predicted"
        # the parameters as Prefect's own serializer (FastAPI's jsonable_encoder) records them
        assert run.parameters == Flow.serialize_parameters(predict_flow, {"params": params})
        artifacts = client.read_artifacts(artifact_filter=ArtifactFilter(
            flow_run_id=ArtifactFilterFlowRunId(any_=[run.id])))
        assert [a.key for a in artifacts] == ["predictions"] and "| yes |" in artifacts[0].data
        # task runs and heartbeats reach the API as events, recorded by the server shortly after
        deadline = time.monotonic() + 60
        while True:
            tasks = client.read_task_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=[run.id])))
            beats = client.read_events(EventFilter(
                any_resource=EventAnyResourceFilter(id=[f"prefect.flow-run.{run.id}"]),
                event=EventNameFilter(name=["prefect.flow-run.heartbeat"])), limit=10)
            if (tasks and tasks[0].state and tasks[0].state.is_final() and beats.events) or time.monotonic() > deadline:
                break
            time.sleep(0.5)
    assert [(t.name, t.state.name if t.state else None) for t in tasks] == [("predict[predict/SSB16240001]", "Cached")]
    assert beats.events, "no heartbeat of the cached run reached the API"


def test_the_flow_parameters_are_recorded_as_prefect_records_them(tmp_path):
    """`serialize_parameters` (no FastAPI import) gives what Prefect's `Flow.serialize_parameters` gives."""
    from prefect import Flow

    from visemeflow.flows.predict import PredictParams, predict_flow, serialize_parameters

    for params in (PredictParams(audio=[AUDIO]),
                   PredictParams(store=tmp_path / "s", model="m", audio=[AUDIO, tmp_path / "ä b.wav"], fps=25.5,
                                 out=tmp_path / "out", device="cuda:1")):
        assert serialize_parameters({"params": params}) == Flow.serialize_parameters(predict_flow, {"params": params})
    assert predict_flow.serialize_parameters is serialize_parameters
    other = {"x": 1, "when": tmp_path}   # not a model: Prefect's own
    expected = {"x": 1, "when": str(tmp_path)}
    assert serialize_parameters(other) == Flow.serialize_parameters(predict_flow, other) == expected
