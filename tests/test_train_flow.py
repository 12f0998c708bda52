"""The `train` flow on a small synthetic store: model, metrics, cache, and `predict` through the CLI."""

import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from factories import DEMO_CORPUS

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
    model, loaded_config, lineage = load_model(s.model_dir("tiny") / "model.pt")
    assert loaded_config == config and set(lineage["train"]) | set(lineage["val"]) == set(splits)

    mtime = (s.model_dir("tiny") / "model.pt").stat().st_mtime_ns
    again = train_flow(params)
    assert again == report and (s.model_dir("tiny") / "model.pt").stat().st_mtime_ns == mtime

    result = CliRunner().invoke(app, ["predict", str(DEMO_CORPUS / "SSB1624" / "SSB16240001.wav"), "--model", "tiny",
                                      "--store", str(store), "--fps", "25", "--out", str(tmp_path / "pred")])
    assert result.exit_code == 0, result.output
    assert "real-time factor" in result.output
    predicted = s.read_curves("predict/SSB16240001", "predicted", "tiny")
    assert predicted.num_rows == round(1.73 * 25)
    values = np.stack([predicted.column(v).to_numpy() for v in ("AAA", "MBP")])
    assert np.isfinite(values).all() and values.min() >= 0 and values.max() <= 1
    assert (tmp_path / "pred" / "SSB16240001.csv").exists()
