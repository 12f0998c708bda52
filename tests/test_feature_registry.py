"""A new audio encoder is one module: an extractor registered with `register_feature` and a preset registered with
`register_preset`, then trained, saved, loaded and used for prediction with nothing else changed. This file is that
module (the extractor below is defined nowhere else). It registers them in a fixture and removes them afterwards, so
the tests that run over every preset (ONNX export, smoke tests) in the same process see only the shipped ones."""

import numpy as np
import pytest
import torch

from visemeflow.learning.features import (
    FEATURE_KINDS,
    FeatureConfig,
    FeatureExtractor,
    FilterbankExtractor,
    build_feature_extractor,
    register_feature,
)
from visemeflow.learning.presets import PRESETS, Preset, register_preset
from visemeflow.learning.train import Example, TrainConfig, load_model, predict_curves, save_model, train_model


class EnergyExtractor(FeatureExtractor):
    """Log energy and zero-crossing rate of frames of `options["frame_ms"]` milliseconds: a 2-dim feature."""

    def __init__(self, config: FeatureConfig) -> None:
        super().__init__(config)
        self.hop = round(config.sample_rate * float(config.options.get("frame_ms", 10)) / 1000)
        self.dim = 2
        self.frame_rate_hz = config.sample_rate / self.hop

    def output_lengths(self, lengths: torch.Tensor) -> torch.Tensor:
        return torch.as_tensor(lengths) // self.hop

    def forward(self, audio, lengths=None):
        audio, lengths = self._prepare(audio, lengths)
        t = audio.shape[1] // self.hop
        frames = audio[:, : t * self.hop].reshape(audio.shape[0], t, self.hop)
        energy = torch.log(frames.pow(2).mean(-1) + 1e-8)
        zcr = (frames[..., 1:] * frames[..., :-1] < 0).float().mean(-1)
        return torch.stack([energy, zcr], -1), self.output_lengths(lengths)


ENERGY_BLSTM = Preset(name="test-energy-blstm", feature="test-energy", lr=3e-3, spec_augment=None,
                      feature_options={"frame_ms": 20}, note="tests/test_feature_registry.py")


@pytest.fixture(autouse=True)
def registered():
    register_feature("test-energy")(EnergyExtractor)
    register_preset(ENERGY_BLSTM)
    yield
    PRESETS.pop(ENERGY_BLSTM.name)
    FEATURE_KINDS.pop("test-energy")


def examples(n: int = 3) -> list[Example]:
    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        audio = (rng.standard_normal(16000) * np.linspace(0, 0.5, 16000)).astype(np.float32)
        curves = np.tile(np.linspace(0, 1, 30, dtype=np.float32)[:, None], (1, 16))
        out.append(Example(f"s/{i}", audio, curves, 30.0))
    return out


def test_a_registered_feature_trains_saves_loads_and_predicts(tmp_path):
    config = TrainConfig(preset="test-energy-blstm", epochs=1, d_model=8, seed=0)
    result = train_model(examples(), [], config)
    assert result.model.features.config.options == {"frame_ms": 20}
    assert result.model.features.frame_rate_hz == 50.0
    path = save_model(result.model, config, tmp_path / "energy.pt", {"test": True})
    model, loaded_config, _ = load_model(path)
    assert isinstance(model.features, EnergyExtractor) and loaded_config.preset == "test-energy-blstm"
    audio = examples(1)[0].audio
    np.testing.assert_allclose(predict_curves(model, audio, 16000, 30.0), predict_curves(result.model, audio, 16000,
                                                                                         30.0), atol=1e-6)


def test_unknown_kinds_and_presets_are_refused_naming_what_is_registered():
    with pytest.raises(ValueError, match=r"unknown feature kind 'nope'; registered: .*fbank.*test-energy"):
        FeatureConfig(kind="nope")
    with pytest.raises(ValueError, match="not registered"):
        register_preset(Preset(name="nope-blstm", feature="nope", lr=1e-3))
    with pytest.raises(ValueError, match="already named"):
        register_preset(ENERGY_BLSTM.model_copy(update={"lr": 1.0}))
    assert register_preset(ENERGY_BLSTM) is ENERGY_BLSTM and PRESETS["test-energy-blstm"] == ENERGY_BLSTM
    with pytest.raises(ValueError, match="already computed by EnergyExtractor"):
        register_feature("test-energy")(FilterbankExtractor)


def test_built_in_kinds_are_registered_and_their_configs_keep_their_json():
    assert {"fbank", "mfcc", "lpc", "wav2vec2", "whisper"} <= set(FEATURE_KINDS)
    assert isinstance(build_feature_extractor(FeatureConfig(kind="mfcc")), FilterbankExtractor)
    assert "options" not in FeatureConfig(kind="fbank").model_dump_json()  # hashes of existing models unchanged
