"""The `train` flow on a small synthetic store: model, metrics, cache, and `predict` through the CLI."""

import os
import shutil

import numpy as np
import pytest
from factories import DEMO_CORPUS, REPO, kill_cli_when, make_curve_store
from typer.testing import CliRunner

pytestmark = [pytest.mark.flow, pytest.mark.usefixtures("prefect_harness")]


def test_train_flow_writes_model_metrics_and_is_cached_then_predicts(tmp_path):
    from visemeflow.cli import app
    from visemeflow.flows.params import SynthParams, TrainParams
    from visemeflow.flows.synth import synth_flow
    from visemeflow.flows.train import train_flow
    from visemeflow.ingest import IngestConfig
    from visemeflow.learning.train import TrainConfig, load_model
    from visemeflow.schemas import C
    from visemeflow.storage import Store

    source = tmp_path / "source"
    (source / "LJ").mkdir(parents=True)
    for name in ("LJ001-0002", "LJ001-0005", "LJ001-0012", "LJ001-0019"):
        for ext in (".wav", ".TextGrid"):
            shutil.copyfile(DEMO_CORPUS / "LJ" / f"{name}{ext}", source / "LJ" / f"{name}{ext}")
    store = tmp_path / "store"
    synth_flow(SynthParams(corpus=source, out=tmp_path / "synth", store=store))
    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.params import IngestParams

    ingest_flow(IngestParams(corpus=tmp_path / "synth", store=store, n_shards=2,
                             config=IngestConfig(val_fraction=0.25)))
    s = Store(store)
    splits = {r[C.UTTERANCE_ID]: r[C.SPLIT] for r in s.read_table("utterances").to_pylist()}
    assert "train" in splits.values()

    config = TrainConfig(preset="fbank-tcn", epochs=2, d_model=16)
    params = TrainParams(store=store, config=config, source="ground_truth", model_name="tiny")
    report = train_flow(params)
    assert report["epochs"] == 2 and report["train"] + report["val"] == 4
    assert (s.model_dir("tiny") / "model.pt").exists() and (s.model_dir("tiny") / "checkpoints" / "last.pt").exists()
    metrics = s.read_metrics("tiny").to_pylist()
    per_epoch = [m for m in metrics if m[C.RUN] == "train"]
    assert len(per_epoch) == 2 and all(m[C.CONDITION] == "validation" for m in per_epoch)
    _, loaded_config, lineage = load_model(s.model_dir("tiny") / "model.pt")
    assert loaded_config == config and set(lineage["train"]) | set(lineage["val"]) == set(splits)

    mtime = (s.model_dir("tiny") / "model.pt").stat().st_mtime_ns
    # the device and precision name where the model is computed, not what it is: the same cached model
    again = train_flow(params.model_copy(update={"device": "cpu", "precision": "fp32"}))
    assert again == report and (s.model_dir("tiny") / "model.pt").stat().st_mtime_ns == mtime

    result = CliRunner().invoke(app, ["predict", str(DEMO_CORPUS / "SSB1624" / "SSB16240001.wav"), "--model", "tiny",
                                      "--store", str(store), "--fps", "25", "--out", str(tmp_path / "pred")])
    assert result.exit_code == 0, result.output
    assert "real-time factor" in result.output
    predicted = s.read_curves("predict/SSB16240001", "predicted", "tiny")
    assert predicted.num_rows == round(1.73 * 25)
    values = np.stack([predicted.column(v).to_numpy() for v in ("AAA", "MBP")])
    assert np.isfinite(values).all() and values.min() >= 0 and values.max() <= 1
    assert (tmp_path / "pred" / "SSB16240001.csv").exists() and "the curves are in the store" not in result.output
    # without --out: where the curves are, and the command that writes them out, which works as printed
    result = CliRunner().invoke(app, ["predict", str(DEMO_CORPUS / "SSB1624" / "SSB16240001.wav"), "--model", "tiny",
                                      "--store", str(store), "--fps", "25"])
    assert result.exit_code == 0 and "(cached;" in result.output, result.output
    said = result.output.splitlines()[-1]
    assert said.startswith(f"the curves are in the store {store} (source predicted, variant tiny): `visemeflow "), said
    command = said.split("`")[1].replace("FILE.csv", str(tmp_path / "out.csv")).split()
    exported = CliRunner().invoke(app, command[1:])
    assert exported.exit_code == 0, exported.output
    assert (tmp_path / "out.csv").read_text() == (tmp_path / "pred" / "SSB16240001.csv").read_text()


def test_sweep_subsets_are_nested_and_disjoint_from_validation():
    from visemeflow.flows.sweep import nested_subsets

    rows = [{"utterance_id": f"s/u{i:03d}"} for i in range(50)]
    val = {f"s/v{i}" for i in range(5)}
    subsets = nested_subsets(rows, [40, 10, 25, 100, 0])
    assert sorted(subsets) == [10, 25, 40]  # sizes beyond the training set or empty are left out
    ids = {k: [r["utterance_id"] for r in v] for k, v in subsets.items()}
    assert ids[10] == ids[25][:10] and ids[25] == ids[40][:25]
    assert all(len(set(v)) == len(v) and not set(v) & val for v in ids.values())
    assert nested_subsets(list(reversed(rows)), [10]) == {10: subsets[10]}  # order-independent


def test_train_flow_killed_with_kill_minus_nine_resumes_to_the_uninterrupted_weights(
    tmp_path, prefect_api_url, monkeypatch
):
    import torch

    import visemeflow.tasks.train as train_tasks
    from visemeflow.flows.params import TrainParams
    from visemeflow.flows.train import train_flow
    from visemeflow.learning.train import TrainConfig, load_model

    killed, clean = make_curve_store(tmp_path / "killed"), make_curve_store(tmp_path / "clean")
    epochs = 6
    checkpoint = killed.model_dir("m") / "checkpoints" / "last.pt"
    kill_cli_when(["train", "--store", str(killed.root), "--source", "ground_truth", "--preset", "fbank-blstm",
                   "--d-model", "16", "--epochs", str(epochs), "--name", "m", "--train-augment", "0.5"],
                  prefect_api_url, checkpoint.exists)
    assert checkpoint.exists() and not (killed.model_dir("m") / "model.pt").exists()
    done = torch.load(checkpoint, weights_only=True)["epoch"]
    assert 1 <= done < epochs, "killed after the last epoch: the test proves nothing"

    config = TrainConfig(preset="fbank-blstm", d_model=16, epochs=epochs, train_augment=True,
                         train_augment_probability=0.5)
    trained_epochs: list[int] = []  # epochs actually trained by the in-process runs below
    original = train_tasks.train_model

    def counting(*args, on_epoch, **kwargs):
        def report(epoch):
            trained_epochs.append(epoch.epoch)
            on_epoch(epoch)
        return original(*args, on_epoch=report, **kwargs)

    monkeypatch.setattr(train_tasks, "train_model", counting)
    train_flow(TrainParams(store=killed.root, config=config, source="ground_truth", model_name="m"))
    assert trained_epochs == list(range(done + 1, epochs + 1)), "the rerun did not resume from the checkpoint"
    train_flow(TrainParams(store=clean.root, config=config, source="ground_truth", model_name="m"))
    a, b = load_model(killed.model_dir("m") / "model.pt")[0], load_model(clean.model_dir("m") / "model.pt")[0]
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
    columns = ["run", "model", "condition", "utterance_id", "epoch", "l1_x100"]
    assert killed.read_metrics("m").select(columns).to_pylist() == clean.read_metrics("m").select(columns).to_pylist()
    assert not list(killed.root.rglob(".*.tmp"))


def test_sweep_flow_trains_each_size_and_plots(tmp_path):
    from visemeflow.flows.params import SweepParams
    from visemeflow.flows.sweep import sweep_flow
    from visemeflow.learning.train import TrainConfig
    from visemeflow.schemas import C

    s = make_curve_store(tmp_path / "store")
    result = sweep_flow(SweepParams(store=s.root, config=TrainConfig(preset="fbank-tcn", d_model=8), sizes=[2, 4],
                                    steps=4, source="ground_truth"))
    assert [p[0] for p in result["points"]] == [2, 4] and all(np.isfinite(p[1]) for p in result["points"])
    assert result["validation_utterances"] == 2
    assert (s.root / "reports" / "sweep-fbank-tcn.png").stat().st_size > 1000
    names = {m[C.MODEL] for m in s.read_metrics().to_pylist()}
    # named by size and a digest of the config and data
    assert len(names) == 2 and {n.rsplit("-", 1)[0] for n in names} == {"sweep-fbank-tcn-n2", "sweep-fbank-tcn-n4"}


def test_two_sweeps_of_other_configs_and_sources_on_one_store_keep_their_own_models(tmp_path):
    """A second sweep with another --d-model (or another --source) trains models of its own: it neither resumes
    nor overwrites the checkpoints and model files of the first."""
    from visemeflow.flows.params import SweepParams
    from visemeflow.flows.sweep import sweep_flow
    from visemeflow.learning.train import TrainConfig, load_model
    from visemeflow.schemas import C, curves_table

    s = make_curve_store(tmp_path / "store")
    small = SweepParams(store=s.root, config=TrainConfig(preset="fbank-tcn", d_model=8), sizes=[2, 4], steps=4,
                        source="ground_truth")
    first = sweep_flow(small)
    first_models = set(s.model_names())
    assert len(first_models) == 2
    files = {name: s.model_path(name).read_bytes() for name in first_models}

    wider = sweep_flow(small.model_copy(update={"config": TrainConfig(preset="fbank-tcn", d_model=12)}))
    assert [p[0] for p in wider["points"]] == [2, 4] and all(np.isfinite(p[1]) for p in wider["points"])
    wider_models = set(s.model_names()) - first_models
    assert len(wider_models) == 2, s.model_names()
    assert {load_model(s.model_path(name))[1].d_model for name in wider_models} == {12}
    assert {name: s.model_path(name).read_bytes() for name in first_models} == files

    # the same sweep on another source's curves (same utterances, other targets): models of its own too
    rng = np.random.default_rng(1)
    for uid in s.curve_ids("ground_truth", "cm"):
        s.write_curves(curves_table(uid, "tracked", "cm", rng.random((25, 16)).astype(np.float32), 25.0))
    sweep_flow(small.model_copy(update={"source": "tracked"}))
    assert len(set(s.model_names()) - first_models - wider_models) == 2, s.model_names()
    assert {name: s.model_path(name).read_bytes() for name in first_models} == files

    again = sweep_flow(small)  # the first sweep again: its models, cached
    assert again["points"] == first["points"] and len(s.model_names()) == 6

    # new target curves that record no provenance: told apart by their files' content
    for uid in s.curve_ids("ground_truth", "cm"):
        s.write_curves(curves_table(uid, "ground_truth", "cm", rng.random((25, 16)).astype(np.float32), 25.0))
    sweep_flow(small)
    assert len(s.model_names()) == 8 and {name: s.model_path(name).read_bytes() for name in first_models} == files
    assert {m[C.MODEL] for m in s.read_metrics().to_pylist()} == set(s.model_names())


def test_training_without_validation_utterances_finishes_and_reports_no_validation(tmp_path):
    from visemeflow.storage import Store
    from visemeflow.tasks.train import train_model_task
    from visemeflow.learning.train import TrainConfig
    from visemeflow.schemas import C

    from prefect import flow

    s = make_curve_store(tmp_path / "store", n=3)
    rows = s.read_table("utterances").to_pylist()

    @flow
    def train_without_validation():
        return train_model_task(str(s.root), "noval", rows, [], "ground_truth", "cm", {},
                                TrainConfig(preset="fbank-tcn", d_model=8, epochs=2))

    result = train_without_validation()
    assert result["epochs"] == 2 and result["val"] == 0 and Store(s.root).has_model("noval")
    assert not [m for m in s.read_metrics().to_pylist() if m[C.MODEL] == "noval" and m[C.RUN] == "train"]


@pytest.mark.flow
def test_sigterm_ends_a_training_command_at_once_and_marks_its_run(tmp_path, prefect_api_url):
    """`kill`, `timeout` or a scheduler's stop ends the command within seconds, though its training task still runs
    in a worker thread (Prefect's pool would wait for it: hours), and the run is marked Crashed, not left running."""
    import signal
    import subprocess
    import sys
    import time

    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterName

    store = make_curve_store(tmp_path / "store")
    checkpoint = store.model_dir("long") / "checkpoints" / "last.pt"
    env = {**os.environ, "PREFECT_API_URL": prefect_api_url, "PREFECT_LOGGING_LEVEL": "WARNING"}
    proc = subprocess.Popen([sys.executable, "-m", "visemeflow.cli", "train", "--store", str(store.root), "--source",
                             "ground_truth", "--preset", "fbank-blstm", "--d-model", "16", "--epochs", "100000",
                             "--name", "long"], cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and proc.poll() is None and not checkpoint.exists():
            time.sleep(0.05)
        assert proc.poll() is None and checkpoint.exists(), "training never started"
        proc.send_signal(signal.SIGTERM)
        stopped = time.monotonic()
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 143 and err.splitlines()[-1] == "terminated", err[-2000:]
    assert time.monotonic() - stopped < 60   # a bound, not a timing: without the fix it runs 100000 epochs
    with get_client(sync_client=True) as client:
        runs = client.read_flow_runs(flow_run_filter=FlowRunFilter(name=FlowRunFilterName(any_=["train(fbank-blstm)"])))
    ours = [r for r in runs if r.parameters.get("params", {}).get("store") == str(store.root)]
    assert len(ours) == 1 and ours[0].state.name == "Crashed", [(r.parameters, r.state) for r in runs]
