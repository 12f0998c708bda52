"""Length-bucketed batches beside the paper's one utterance per step (TrainConfig.batch_size in
visemeflow.learning.train)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from factories import TRAIN_FPS as FPS
from factories import TRAIN_SR
from factories import envelope_examples as make_examples

from visemeflow.learning import train as T
from visemeflow.learning.train import EpochReport, Example, TrainConfig, length_batches, train_model

# TrainConfig() as JSON before batch_size existed: checkpoints' resume keys, model names hashed from the config and
# saved models' configs must not change for the paper's recipe.
OLD_DEFAULT_JSON = (
    '{"preset":"fbank-blstm","epochs":10,"seed":0,"d_model":null,"lr":null,"max_steps_per_epoch":null,'
    '"wav2vec2_model":null,"train_augment":false,"train_augment_probability":0.5}'
)


def _state(model) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def _same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_the_papers_recipe_serialises_as_before_and_new_fields_round_trip():
    assert TrainConfig().model_dump_json() == OLD_DEFAULT_JSON
    assert TrainConfig(batch_size=1, bucket_batches=8).model_dump_json() == OLD_DEFAULT_JSON
    assert "batch_size" not in TrainConfig().model_dump(mode="json")
    batched = TrainConfig(batch_size=4, bucket_batches=2)
    assert '"batch_size":4' in batched.model_dump_json() and '"bucket_batches":2' in batched.model_dump_json()
    assert TrainConfig.model_validate_json(batched.model_dump_json()) == batched
    assert TrainConfig.model_validate_json(OLD_DEFAULT_JSON) == TrainConfig()
    with pytest.raises(ValueError):
        TrainConfig(batch_size=0)


def test_batch_size_one_is_the_shuffled_order_and_draws_nothing():
    rng = np.random.default_rng(3)
    before = rng.bit_generator.state
    order = np.array([4, 0, 3, 1, 2])
    batches = length_batches(order, [5, 4, 3, 2, 1], [25.0] * 5, 1, 8, rng)
    assert [b.tolist() for b in batches] == [[4], [0], [3], [1], [2]]
    assert rng.bit_generator.state == before  # the epoch's later draws are those of the old loop


def test_buckets_sort_by_length_keep_every_index_once_and_never_mix_frame_rates():
    rng = np.random.default_rng(0)
    n = 23
    lengths = rng.integers(1000, 50000, n).tolist()
    fps = [25.0 if i % 5 else 30.0 for i in range(n)]
    order = rng.permutation(n)
    batches = length_batches(order, lengths, fps, 3, 4, np.random.default_rng(1))
    flat = np.concatenate(batches)
    assert sorted(flat.tolist()) == list(range(n))
    assert all(1 <= len(b) <= 3 and len({fps[i] for i in b}) == 1 for b in batches)
    # within each bucket of 12 shuffled indices, batches hold neighbours in length: sorting there cuts padding
    padded = sum(len(b) * max(lengths[i] for i in b) for b in batches)
    unsorted = sum(len(c) * max(lengths[i] for i in c) for c in np.array_split(order, len(batches)))
    assert padded < unsorted
    for start in range(0, n, 12):
        bucket = set(order[start:start + 12].tolist())
        mine = [b for b in batches if set(b.tolist()) <= bucket]
        assert sum(len(b) for b in mine) == len(bucket)  # no batch crosses buckets
    # the batches' order comes from the generator: another seed, another order, same batches
    again = length_batches(order, lengths, fps, 3, 4, np.random.default_rng(2))
    assert sorted(map(tuple, again)) == sorted(map(tuple, batches))
    assert list(map(tuple, again)) != list(map(tuple, batches))


def test_batched_training_learns(tmp_path):
    train = make_examples(6, seed=1)
    cfg = TrainConfig(preset="fbank-blstm", epochs=8, d_model=16, lr=3e-3, seed=0, batch_size=3, bucket_batches=2)
    res = train_model(train, train[:2], cfg)
    assert [h.steps for h in res.history] == [2] * 8  # 6 utterances, 3 per step
    assert res.history[-1].train_l1_x100 < 0.7 * res.history[0].train_l1_x100
    assert res.history[-1].val_l1_x100 < 0.7 * res.history[0].val_l1_x100
    frames = sum(len(ex.curves) for ex in train)
    assert res.history[0].frames_per_s * res.history[0].seconds == pytest.approx(frames, rel=1e-6)


def _garbage_padding(monkeypatch):
    """Fill every padded sample, feature frame, encoder frame and target frame with large random values."""
    rng = torch.Generator().manual_seed(99)
    orig_audio, orig_time, orig_curves = T._pad_audio, T._pad_time, T._pad_curves
    filled = {"audio": 0, "time": 0, "curves": 0}

    def noise_like(t):
        return 1e3 * torch.randn(t.shape, generator=rng, dtype=t.dtype)

    def pad_audio(audios, device):
        batch, lengths = orig_audio(audios, device)
        for j, n in enumerate(lengths.tolist()):
            if n < batch.shape[1]:
                batch[j, n:] = noise_like(batch[j, n:])
                filled["audio"] += 1
        return batch, lengths

    def pad_time(tensors, dim):
        out = orig_time(tensors, dim)
        for j, t in enumerate(tensors):
            rest = out[j].narrow(dim - 1, t.shape[dim], out.shape[dim] - t.shape[dim])
            if rest.numel():
                rest.copy_(noise_like(rest))
                filled["time"] += 1
        return out

    def pad_curves(curves, device):
        target, n_frames = orig_curves(curves, device)
        for j, n in enumerate(n_frames.tolist()):
            if n < target.shape[1]:
                target[j, n:] = noise_like(target[j, n:])
                filled["curves"] += 1
        return target, n_frames

    monkeypatch.setattr(T, "_pad_audio", pad_audio)
    monkeypatch.setattr(T, "_pad_time", pad_time)
    monkeypatch.setattr(T, "_pad_curves", pad_curves)
    return filled


@pytest.mark.parametrize("preset", ["fbank-blstm", "fbank-tcn", "fbank-transformer"])
def test_what_padding_holds_changes_nothing(preset, monkeypatch):
    train = make_examples(5, seed=4, learnable=False)  # 1-2 s each: every batch pads
    cfg = TrainConfig(preset=preset, epochs=2, d_model=16, lr=1e-3, seed=2, batch_size=5)
    zeros = train_model(train, [], cfg)
    filled = _garbage_padding(monkeypatch)
    garbage = train_model(train, [], cfg)
    assert filled["time"] > 0 and filled["curves"] > 0  # padding was really there, and really garbage
    assert [h.train_l1_x100 for h in garbage.history] == [h.train_l1_x100 for h in zeros.history]
    assert _same(_state(zeros.model), _state(garbage.model))


def test_a_batched_step_is_the_frame_weighted_loss_of_its_utterances(monkeypatch):
    """One step on a batch of two = the L1 over the two utterances' frames, each predicted as if alone."""
    train = make_examples(2, seed=8, learnable=False)
    cfg = TrainConfig(preset="fbank-blstm", epochs=1, d_model=16, lr=1e-3, seed=5, batch_size=2)
    model = T.build_training_model(cfg, FPS)  # the same initial weights as train_model's (seeded)
    errors, frames = 0.0, 0
    with torch.no_grad():
        for ex in train:
            feats, lengths = model.features(*T._audio_tensors(ex.audio))
            target = torch.from_numpy(ex.curves)[None]
            pred, _ = model.head(feats, lengths, torch.tensor([target.shape[1]]), fps=FPS)
            errors += float((pred - target).abs().sum())
            frames += target.shape[1]
    monkeypatch.setattr(T, "augment", lambda preset, feats, lengths, generator=None: feats)  # no SpecAugment
    res = train_model(train, [], cfg)
    assert res.history[0].steps == 1
    assert res.history[0].train_l1_x100 == pytest.approx(100.0 * errors / (frames * 16), rel=1e-5)


def test_batched_training_resumes_exactly(tmp_path):
    train = make_examples(5, seed=5, learnable=False)
    cfg = TrainConfig(preset="fbank-blstm", epochs=3, d_model=16, lr=1e-3, seed=7, batch_size=2, bucket_batches=2,
                      train_augment=True)
    full = train_model(train, [], cfg, checkpoint_dir=tmp_path / "full")

    class Interrupt(Exception):
        pass

    def stop_after_first(report: EpochReport) -> None:
        if report.epoch == 1:
            raise Interrupt

    with pytest.raises(Interrupt):
        train_model(train, [], cfg, checkpoint_dir=tmp_path / "cut", on_epoch=stop_after_first)
    resumed = train_model(train, [], cfg, checkpoint_dir=tmp_path / "cut")
    assert _same(_state(full.model), _state(resumed.model))
    assert [h.train_l1_x100 for h in resumed.history] == [h.train_l1_x100 for h in full.history]
    # another batch size is another training: its checkpoint is refused
    with pytest.raises(ValueError, match="different training config"):
        train_model(train, [], cfg.model_copy(update={"batch_size": 3}), checkpoint_dir=tmp_path / "full")


def test_batches_never_mix_frame_rates_in_training(monkeypatch):
    a = make_examples(2, seed=1)
    b = [Example(f"b{i}", ex.audio, ex.curves[: round(len(ex.audio) / 16000 * 30)], 30.0)
         for i, ex in enumerate(make_examples(2, seed=2))]
    seen: list[tuple[float, int]] = []
    cfg = TrainConfig(preset="fbank-tcn", epochs=1, d_model=8, seed=0, batch_size=4)
    head_class = type(T.build_training_model(cfg, 25.0).head)
    original = head_class.forward

    def spy(self, features, feat_lengths, n_frames, targets=None, fps=None):
        seen.append((fps, int(features.shape[0])))
        return original(self, features, feat_lengths, n_frames, targets=targets, fps=fps)

    monkeypatch.setattr(head_class, "forward", spy)
    res = train_model(a + b, [], cfg)
    assert res.history[0].steps == 2 and sorted(seen) == [(25.0, 2), (30.0, 2)]


def test_dropout_trains_differently_saves_as_before_and_predicts_as_it_trained(tmp_path):
    """TrainConfig.dropout (issue 25): dropout on the decoder's output in training only. A config without it
    serialises as before; with it the training takes other steps, and the saved file loads to the same network,
    whose predictions are deterministic (eval mode: no dropout at inference)."""
    from visemeflow.learning.train import load_model, predict_curves, save_model

    assert "dropout" not in TrainConfig().model_dump(mode="json")
    assert TrainConfig(dropout=None).model_dump_json() == OLD_DEFAULT_JSON
    assert TrainConfig(dropout=0.4).resolved_preset().decoder.dropout == 0.4
    assert TrainConfig(dropout=0.0) == TrainConfig() and TrainConfig(dropout=0).model_dump_json() == OLD_DEFAULT_JSON
    with pytest.raises(ValueError, match="no decoder"):
        TrainConfig(preset="mean-curve", dropout=0.2)
    assert TrainConfig().resolved_preset().decoder.dropout == 0.0
    with pytest.raises(ValueError):
        TrainConfig(dropout=1.0)
    train = make_examples(4, seed=2)
    plain = TrainConfig(preset="fbank-blstm", epochs=3, d_model=16, lr=3e-3, seed=0)
    dropped = plain.model_copy(update={"dropout": 0.4})
    a, b = train_model(train, [], plain).model, train_model(train, [], dropped).model
    assert a.head.drop.p == 0.0 and b.head.drop.p == 0.4
    assert not _same(_state(a), _state(b))   # the dropout masks changed the steps
    path = save_model(b, dropped, tmp_path / "m.pt", {})
    loaded, config, _ = load_model(path)
    assert config.dropout == 0.4 and _same(_state(loaded), _state(b))
    audio = train[0].audio
    once = predict_curves(loaded, audio, TRAIN_SR, FPS)
    assert np.array_equal(once, predict_curves(loaded, audio, TRAIN_SR, FPS))
    b.eval()
    assert np.allclose(once, predict_curves(b, audio, TRAIN_SR, FPS), atol=1e-6)
