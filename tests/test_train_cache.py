"""The frozen wav2vec2 CNN encoder's outputs cached across epochs (visemeflow.learning.features.EncoderOutputCache in
visemeflow.learning.train.train_model), on a tiny randomly initialised Wav2Vec2: equal results, fewer encoder runs."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from factories import envelope_examples as make_examples
from transformers.models.wav2vec2 import modeling_wav2vec2 as hf

from visemeflow.learning.features import EncoderOutputCache, make_tiny_wav2vec2
from visemeflow.learning.train import TrainConfig, train_model


@pytest.fixture(scope="module")
def w2v(tmp_path_factory):
    # wav2vec2's own time masking on: the cache must not disturb its draws from numpy's global RNG
    return make_tiny_wav2vec2(tmp_path_factory.mktemp("w2v") / "tiny", mask_time_prob=0.2, mask_time_length=2)


@pytest.fixture
def encoder_runs(monkeypatch):
    """How many utterances went through the real CNN feature encoder (its class forward; batch rows counted)."""
    runs = {"n": 0}
    original = hf.Wav2Vec2FeatureEncoder.forward

    def counting(self, input_values):
        runs["n"] += int(input_values.shape[0])
        return original(self, input_values)

    monkeypatch.setattr(hf.Wav2Vec2FeatureEncoder, "forward", counting)
    return runs


def _state(model) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def _same(a, b) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def _config(w2v, **kw) -> TrainConfig:
    settings = {"preset": "wav2vec2-blstm", "epochs": 3, "d_model": 16, "lr": 1e-3, "seed": 1, **kw}
    return TrainConfig(wav2vec2_model=str(w2v), **settings)


def test_cached_encoder_outputs_give_bit_identical_training_and_skip_the_encoder(w2v, encoder_runs):
    train = make_examples(3, seed=3)
    cfg = _config(w2v)
    plain = train_model(train, [], cfg, encoder_cache=False)
    assert encoder_runs["n"] == 3 * 3  # every step ran the encoder
    encoder_runs["n"] = 0
    cache = EncoderOutputCache()
    cached = train_model(train, [], cfg, encoder_cache=cache)
    assert encoder_runs["n"] == 3  # the first epoch only
    assert (cache.misses, cache.hits, len(cache)) == (3, 6, 3)
    assert _same(_state(plain.model), _state(cached.model))
    assert [h.train_l1_x100 for h in plain.history] == [h.train_l1_x100 for h in cached.history]
    # the encoder really is frozen (what makes the cache valid) and the transformer did learn
    init = _state(train_model(train, [], cfg.model_copy(update={"epochs": 0})).model)
    after = _state(cached.model)
    assert all(torch.equal(init[k], after[k]) for k in after if ".feature_extractor." in k)
    assert any(not torch.equal(init[k], after[k]) for k in after if ".encoder.layers." in k)


def test_augmented_audio_always_goes_through_the_encoder(w2v, encoder_runs):
    train = make_examples(2, seed=4)
    calls = {"augmented": 0}

    def half_the_steps_louder(audio, rng):
        if rng.random() < 0.5:
            calls["augmented"] += 1
            return audio * 0.5, 1.0
        return audio, 1.0  # unchanged: the same object

    cfg = _config(w2v, train_augment=True)
    plain = train_model(train, [], cfg, augment_audio=half_the_steps_louder, encoder_cache=False)
    augmented_steps, calls["augmented"], encoder_runs["n"] = calls["augmented"], 0, 0
    assert 0 < augmented_steps < 6
    cache = EncoderOutputCache()
    cached = train_model(train, [], cfg, augment_audio=half_the_steps_louder, encoder_cache=cache)
    assert calls["augmented"] == augmented_steps  # the same draws
    assert cache.misses + cache.hits == 6 - augmented_steps  # only clean audio asked the cache
    assert encoder_runs["n"] == augmented_steps + cache.misses
    assert _same(_state(plain.model), _state(cached.model))


def test_an_on_disk_cache_serves_a_later_run_and_its_files_are_whole(w2v, encoder_runs, tmp_path):
    train = make_examples(2, seed=5)
    cfg = _config(w2v, epochs=2)
    first = train_model(train, [], cfg, encoder_cache=tmp_path / "enc")
    files = sorted((tmp_path / "enc").iterdir())
    assert len(files) == 2 and all(f.suffix == ".pt" and not f.name.startswith(".") for f in files)
    assert encoder_runs["n"] == 2
    encoder_runs["n"] = 0
    again = EncoderOutputCache(tmp_path / "enc")
    second = train_model(train, [], cfg, encoder_cache=again)
    assert encoder_runs["n"] == 0 and again.misses == 0 and again.hits == 4
    assert _same(_state(first.model), _state(second.model))
    stored = torch.load(files[0], weights_only=True)
    assert stored.ndim == 3 and stored.shape[:2] == (1, 32)  # (1, conv_dim[-1], encoder frames)
    # another encoder (other weights) never reads these entries
    other = make_tiny_wav2vec2(tmp_path / "other", seed=1)
    third = EncoderOutputCache(tmp_path / "enc")
    train_model(train, [], _config(other, epochs=1), encoder_cache=third)
    assert third.hits == 0 and third.misses == 2 and len(list((tmp_path / "enc").iterdir())) == 4


def test_batched_wav2vec2_training_with_the_cache_matches_the_padded_encoder(w2v, encoder_runs):
    train = make_examples(4, seed=6)
    cfg = _config(w2v, epochs=2, batch_size=2, bucket_batches=2)
    plain = train_model(train, [], cfg, encoder_cache=False)
    cached = train_model(train, [], cfg, encoder_cache=True)
    # the uncached batch runs the CNN on the zero-padded batch: equal to per-utterance outputs up to rounding
    a, b = _state(plain.model), _state(cached.model)
    assert a.keys() == b.keys()
    assert max(float((a[k].float() - b[k].float()).abs().max()) for k in a) < 1e-5
    assert np.allclose([h.train_l1_x100 for h in plain.history], [h.train_l1_x100 for h in cached.history],
                       rtol=1e-5)
    assert cached.history[0].steps == 2
