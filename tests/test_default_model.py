"""The model shipped with the package: present, small, loadable, used by `predict` and `speak` when no model is named,
and its real-speech figures (stored in its lineage and quoted in the README) reproduce on the held-out speech."""

import sys

import numpy as np
import pytest
from factories import REPO
from test_predict import AUDIO
from typer.testing import CliRunner

from visemeflow.learning.default_model import DEFAULT_MODEL, default_model_path
from visemeflow.learning.train import load_model, predict_curves
from visemeflow.storage import Store


def test_the_default_model_ships_small_with_its_recipe_and_figures():
    path = default_model_path()
    assert path.is_file(), f"{path} missing: run examples/train_default_model.py"
    assert path.stat().st_size < 20e6
    model, config, lineage = load_model(path)
    assert config.preset == "fbank-blstm" and lineage["script"] == "examples/train_default_model.py"
    assert lineage["held_out"]["captured"] == "FACEGOOD 1114_2_05"
    assert not any("1114_2_05" in uid or "SSB1624" in uid for uid in lineage["data"]["real_examples"])
    curves = predict_curves(model, np.zeros(16000, np.float32), 16000, 30.0)
    assert curves.shape == (30, 16) and np.isfinite(curves).all()


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_predict_without_a_model_installs_and_uses_the_default(tmp_path):
    from visemeflow.cli import app

    store = tmp_path / "store"
    result = CliRunner().invoke(app, ["predict", str(AUDIO), "--store", str(store)])
    assert result.exit_code == 0, result.output
    assert "-> predict/SSB16240001" in result.output
    s = Store(store)
    assert s.has_model(DEFAULT_MODEL)
    assert s.model_path(DEFAULT_MODEL).read_bytes() == default_model_path().read_bytes()
    assert s.has_curves("predicted", DEFAULT_MODEL, "predict/SSB16240001")


def test_the_recorded_real_speech_figures_reproduce():
    sys.path.insert(0, str(REPO / "bench"))
    from domain_gap import judge, load_sets

    model, _, lineage = load_model(default_model_path())
    figures = judge(load_sets(synthetic=False),
                    lambda audio, n: predict_curves(model, audio, 16000, 30.0, n_frames=n))
    recorded = lineage["figures"]
    assert [figures["mbp"].hits, figures["mbp"].total] == recorded["mbp_closure"]
    assert [figures["fff"].hits, figures["fff"].total] == recorded["fff_closure"]
    assert [figures["agreement"].hits, figures["agreement"].total] == recorded["agreement"]
    assert figures["captured_l1_x100"] == pytest.approx(recorded["captured_l1_x100"], abs=1e-3)
