"""Training loop, exact resume, evaluation, inference and model files (visemeflow.learning.train)."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch
from factories import TRAIN_FPS, TRAIN_SR, assert_same_params, envelope_examples, params_of
from torch import nn

from visemeflow.learning import train as T
from visemeflow.learning.features import make_tiny_wav2vec2, resample_audio
from visemeflow.learning.train import (
    EpochReport,
    Example,
    TrainConfig,
    Trainer,
    apply_audio_augment,
    build_training_model,
    evaluate,
    load_model,
    predict_curves,
    save_model,
    train_model,
)

SR = TRAIN_SR
FPS = TRAIN_FPS


@pytest.fixture(scope="module")
def data() -> tuple[list[Example], list[Example]]:
    return envelope_examples(4, seed=1), envelope_examples(2, seed=2)


def test_training_reduces_l1(data):
    train, val = data
    cfg = TrainConfig(preset="fbank-blstm", epochs=8, d_model=16, lr=3e-3, seed=0)
    before, _, _ = evaluate(build_training_model(cfg, FPS), train)
    seen: list[EpochReport] = []
    res = train_model(train, val, cfg, on_epoch=seen.append)
    assert [r.epoch for r in res.history] == list(range(1, 9)) == [r.epoch for r in seen]
    assert all(r.steps == len(train) and r.val_l1_x100 is not None and r.frames_per_s > 0 for r in res.history)
    after, per_utt, per_vis = evaluate(res.model, train)
    assert after < 0.6 * before
    assert res.history[-1].train_l1_x100 < 0.6 * res.history[0].train_l1_x100
    assert set(per_utt) == {ex.utterance_id for ex in train} and per_vis.shape == (16,)
    assert res.checkpoint is None


def test_a_custom_loss_is_the_objective(data):
    """`train_model(loss=...)` trains on that objective: a loss with zero gradient leaves the initial weights
    (Adam's step is 0 for a zero gradient) where the default L1 moves them; the reported train L1 is that loss."""
    train, _ = data
    cfg = TrainConfig(preset="fbank-blstm", epochs=1, d_model=8, lr=3e-3, seed=0)
    initial = params_of(build_training_model(cfg, FPS))
    calls: list[tuple[int, ...]] = []

    def flat(pred, target, mask):
        calls.append(tuple(pred.shape))
        return (pred * 0.0).sum() + 0.25

    res = train_model(train, [], cfg, loss=flat)
    assert_same_params(initial, params_of(res.model))
    assert len(calls) == len(train) and res.history[0].train_l1_x100 == pytest.approx(25.0)
    moved = params_of(train_model(train, [], cfg).model)
    assert any(not torch.equal(initial[k], moved[k]) for k in initial)


def test_trainer_steps_driven_by_hand_train_the_same_weights_as_train_model(tmp_path):
    """The Trainer's parts are the training: resume, prepare the features, run the epochs, checkpoint each, as
    fit() does; a subclass may replace one part (here: every step's items seen) and the weights stay bit-equal."""
    train = envelope_examples(3, seed=5, learnable=False)
    cfg = TrainConfig(preset="fbank-blstm", epochs=2, d_model=16, lr=1e-3, seed=7)
    ref = params_of(train_model(train, [], cfg).model)

    class Counting(Trainer):
        seen: list[int] = []

        def items_of(self, batch):
            items = super().items_of(batch)
            self.seen.extend(it.index for it in items)
            return items

    t = Counting(train, [], cfg, checkpoint_dir=tmp_path)
    t.resume()
    t.prepare_features()
    for epoch in range(t.start_epoch, cfg.epochs):
        t.history.append(t.run_epoch(epoch))
        t.checkpoint(epoch)
    assert_same_params(ref, params_of(t.model))
    assert sorted(t.seen) == [0, 0, 1, 1, 2, 2] and t.n_steps == 6
    resumed = Trainer(train, [], cfg, checkpoint_dir=tmp_path)
    resumed.resume()
    assert resumed.start_epoch == 2 and [h.epoch for h in resumed.history] == [1, 2]


@pytest.mark.parametrize("preset", ["fbank-blstm", "fbank-tcn"])
def test_exact_resume(preset, tmp_path):
    train = envelope_examples(3, seed=5, learnable=False)
    val = envelope_examples(1, seed=6, learnable=False)
    cfg = TrainConfig(preset=preset, epochs=3, d_model=16, lr=1e-3, seed=7)
    full = train_model(train, val, cfg, checkpoint_dir=tmp_path / "full")
    ref = params_of(full.model)
    assert (tmp_path / "full" / "last.pt").exists()

    class Interrupt(Exception):
        pass

    def boom(report: EpochReport) -> None:
        if report.epoch == 1:
            raise Interrupt

    with pytest.raises(Interrupt):
        train_model(train, val, cfg, checkpoint_dir=tmp_path / "int", on_epoch=boom)
    resumed = train_model(train, val, cfg, checkpoint_dir=tmp_path / "int")
    assert_same_params(ref, params_of(resumed.model))
    assert [h.epoch for h in resumed.history] == [1, 2, 3]
    assert resumed.history[-1].train_l1_x100 == full.history[-1].train_l1_x100

    # epochs=2 first, then epochs=3 on the same directory
    train_model(train, val, cfg.model_copy(update={"epochs": 2}), checkpoint_dir=tmp_path / "two")
    again = train_model(train, val, cfg, checkpoint_dir=tmp_path / "two")
    assert_same_params(ref, params_of(again.model))
    # a finished run does nothing more
    done = train_model(train, val, cfg, checkpoint_dir=tmp_path / "two")
    assert_same_params(ref, params_of(done.model))

    # the checkpoint is loadable with weights_only and a different config is refused
    ck = torch.load(tmp_path / "full" / "last.pt", weights_only=True)
    assert ck["epoch"] == 3 and ck["step"] == 9
    with pytest.raises(ValueError, match="different training config"):
        train_model(train, val, cfg.model_copy(update={"seed": 8}), checkpoint_dir=tmp_path / "full")


def test_wav2vec2_preset_trains_and_round_trips(tmp_path):
    w2v_dir = make_tiny_wav2vec2(tmp_path / "w2v")
    train = envelope_examples(2, seed=3)
    cfg = TrainConfig(preset="wav2vec2-blstm", epochs=1, d_model=16, wav2vec2_model=str(w2v_dir))
    init = params_of(build_training_model(cfg, FPS))
    res = train_model(train, train[:1], cfg)
    after = params_of(res.model)
    assert res.history[0].steps == 2 and np.isfinite(res.history[0].train_l1_x100)
    enc = [k for k in after if k.startswith("features.model.feature_extractor.")]
    tf = [k for k in after if k.startswith("features.model.encoder.") and k.endswith("weight")]
    assert enc and tf
    assert all(torch.equal(init[k], after[k]) for k in enc)  # CNN encoder frozen
    assert any(not torch.equal(init[k], after[k]) for k in tf)  # transformer fine-tuned
    path = save_model(res.model, cfg, tmp_path / "w2v_model.pt", {"run": "x"})
    loaded, cfg2, lineage = load_model(path)
    assert cfg2 == cfg and lineage == {"run": "x"}
    a = predict_curves(res.model, train[0].audio, SR, FPS)
    assert np.array_equal(a, predict_curves(loaded, train[0].audio, SR, FPS))


def test_wav2vec2_needs_model_path():
    with pytest.raises(ValueError, match="wav2vec2_model"):
        train_model(envelope_examples(1, seed=0), [], TrainConfig(preset="wav2vec2-blstm", epochs=1))


def test_mean_curve_is_the_mean(data):
    train, val = data
    res = train_model(train, val, TrainConfig(preset="mean-curve"))
    mean = np.concatenate([ex.curves for ex in train]).astype(np.float64).mean(0)
    np.testing.assert_allclose(res.model.head.mean.numpy(), mean, atol=1e-6)
    assert len(res.history) == 1 and res.history[0].steps == 0
    pred = predict_curves(res.model, val[0].audio, SR, FPS)
    np.testing.assert_allclose(pred, np.broadcast_to(np.clip(mean, 0, 1), pred.shape), atol=1e-6)


class _Oracle(nn.Module):
    """Returns each example's targets (+ offset), looked up by audio length."""

    def __init__(self, examples: list[Example], offset: float) -> None:
        super().__init__()
        self.by_len = {len(ex.audio): torch.from_numpy(ex.curves) for ex in examples}
        self.offset = offset

    def forward(self, audio, lengths, n_frames, targets=None, fps=None):
        t = int(n_frames.max())
        out = torch.zeros(audio.shape[0], t, 16)
        for j, n in enumerate(lengths.tolist()):
            c = self.by_len[n]
            out[j, : c.shape[0]] = c + self.offset
        mask = torch.arange(t)[None] < n_frames[:, None]
        return out, mask


@pytest.mark.parametrize("batch_size", [1, 3])
def test_evaluate_exact_and_offset(data, batch_size):
    examples = data[0] + data[1]
    overall, per_utt, per_vis = evaluate(_Oracle(examples, 0.0), examples, batch_size=batch_size)
    assert overall == 0.0 and all(v == 0.0 for v in per_utt.values()) and np.all(per_vis == 0.0)
    overall, per_utt, per_vis = evaluate(_Oracle(examples, -0.25), examples, batch_size=batch_size)
    assert overall == pytest.approx(25.0, abs=1e-4)
    assert len(per_utt) == len(examples) and all(v == pytest.approx(25.0, abs=1e-4) for v in per_utt.values())
    np.testing.assert_allclose(per_vis, 25.0, atol=1e-4)


def test_save_load_round_trip_and_weights_only(data, tmp_path, monkeypatch):
    train, val = data
    cfg = TrainConfig(preset="fbank-tcn", epochs=1, d_model=16, lr=1e-3)
    res = train_model(train, val, cfg)
    path = save_model(res.model, cfg, tmp_path / "m.pt", {"data": "synthetic", "epochs": 1})
    calls = []
    real_load = torch.load

    def spy(*args, **kwargs):
        calls.append(kwargs.get("weights_only"))
        return real_load(*args, **kwargs)

    monkeypatch.setattr(T.torch, "load", spy)
    model, cfg2, lineage = load_model(path)
    assert calls == [True]
    assert cfg2 == cfg and lineage == {"data": "synthetic", "epochs": 1}
    for ex in val:
        np.testing.assert_array_equal(
            predict_curves(res.model, ex.audio, SR, FPS), predict_curves(model, ex.audio, SR, FPS)
        )
    assert_same_params(params_of(res.model), params_of(model))

    class Evil:
        def __reduce__(self):
            return (print, ("unpickled!",))

    bad = tmp_path / "bad.pt"
    with open(bad, "wb") as f:
        torch.save({"format": "visemeflow-curve-model/1", "x": Evil()}, f)
    with pytest.raises(T.ModelFileError, match="objects other than tensors and plain values") as info:
        load_model(bad)
    assert isinstance(info.value.__cause__, pickle.UnpicklingError)


def test_predict_curves_any_rate_stereo():
    model = build_training_model(TrainConfig(preset="fbank-blstm", d_model=16), FPS)
    with torch.no_grad():
        model.head.f_fc.bias.copy_(torch.linspace(-3, 3, 16))  # outputs well outside [0, 1]
    rate, dur = 44100, 1.3
    rng = np.random.default_rng(0)
    stereo = (0.1 * rng.standard_normal((int(rate * dur), 2))).astype(np.float32)
    out = predict_curves(model, stereo, rate, FPS)
    assert out.shape == (round(stereo.shape[0] / rate * FPS), 16) and out.dtype == np.float32
    assert out.min() >= 0.0 and out.max() <= 1.0 and out.min() == 0.0 and out.max() == 1.0
    assert predict_curves(model, stereo, rate, 30.0, n_frames=7).shape == (7, 16)
    assert model.training  # mode restored


def _speed_up(audio: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    # play 1.25x faster: treat 16 kHz as 20 kHz and resample back to 16 kHz
    return resample_audio(audio, 20000, SR), 1.25


def test_speed_augment_shortens_targets(data):
    train, val = data
    ex = Example("ramp", train[0].audio, np.tile(np.linspace(0, 1, 40, dtype=np.float32)[:, None], (1, 16)), FPS)
    audio, curves = apply_audio_augment(ex, _speed_up, np.random.default_rng(0))
    assert len(audio) == int(np.ceil(len(ex.audio) / 1.25))
    assert curves.shape == (32, 16)  # round(40 / 1.25)
    # new frame k shows what original frame 1.25 k showed (linear ramp: exact)
    np.testing.assert_allclose(curves[:, 0], np.minimum(np.arange(32) * 1.25, 39) / 39, atol=1e-6)

    cfg = TrainConfig(preset="fbank-blstm", epochs=1, d_model=16, train_augment=True)
    res = train_model(train, val, cfg, augment_audio=_speed_up)
    expected = sum(round(len(e.curves) / 1.25) for e in train)
    r = res.history[0]
    assert r.frames_per_s * r.seconds == pytest.approx(expected, rel=1e-6)
    # without a hook: the paper's augmentations (visemeflow.learning.augment), reproducible from the seed
    cfg = cfg.model_copy(update={"train_augment_probability": 1.0})
    a, b = train_model(train, val, cfg), train_model(train, val, cfg)
    plain = train_model(train, val, cfg.model_copy(update={"train_augment": False}))
    assert a.history[0].train_l1_x100 == b.history[0].train_l1_x100
    assert a.history[0].train_l1_x100 != plain.history[0].train_l1_x100


# ---- model files: what is written and what is read ------------------------------------------------------------


def test_files_that_are_not_models_are_refused_naming_the_file(data, tmp_path):
    """A text file gave "pop from empty list", an empty one EOFError: every reader of a model file says which file
    is not a model and why (load_model, and the Whisper-weights check `predict` runs first)."""
    from visemeflow.flows.predict import check_whisper_weights

    cfg = TrainConfig(preset="fbank-tcn", epochs=0, d_model=16)
    good = save_model(build_training_model(cfg, FPS), cfg, tmp_path / "good.pt", {})
    blob = torch.load(good, weights_only=True)
    cases = {"text.pt": ("this is a text file\nnot a model\n", "starts with b'this'"),
             "empty.pt": ("", "the file is empty"),
             "zip.pt": (b"PK\x03\x04 then nothing a zip archive holds", "cannot be read"),
             "list.pt": ([1, 2, 3], "holds no visemeflow model"),
             "newer.pt": ({**blob, "format": "visemeflow-curve-model/2"}, "another visemeflow version"),
             "field.pt": ({**blob, "config": '{"preset": "fbank-tcn", "device": "cuda"}'}, "config does not validate"),
             "preset.pt": ({**blob, "config": '{"preset": "no-such-preset"}'}, "unknown preset 'no-such-preset'"),
             "lineage.pt": ({**blob, "lineage": "{not json"}, "lineage is not JSON"),
             "weights.pt": ({**blob, "state_dict": {k: v for k, v in blob["state_dict"].items() if "convs" not in k}},
                            "missing weights head.decoder.convs.0.weight")}
    for name, (content, reason) in cases.items():
        path = tmp_path / name
        if isinstance(content, str):
            path.write_text(content)
        elif isinstance(content, bytes):
            path.write_bytes(content)
        else:
            torch.save(content, path)
        for read in (load_model,) if name == "weights.pt" else (load_model, check_whisper_weights):
            with pytest.raises(T.ModelFileError) as info:
                read(path)
            message = str(info.value)
            assert message.startswith(f"{path} is not a visemeflow model file (expected a file written by visemeflow "
                                      "train / save_model): "), message
            assert reason in message, message
            assert isinstance(info.value, ValueError) and pickle.loads(pickle.dumps(info.value)).path == str(path)


def test_non_finite_weights_are_never_written_nor_loaded(tmp_path):
    cfg = TrainConfig(preset="fbank-tcn", epochs=0, d_model=16)
    model = build_training_model(cfg, FPS)
    path = save_model(model, cfg, tmp_path / "model.pt", {"run": 1})
    before = path.read_bytes()
    with torch.no_grad():
        model.head.f_fc.weight[0, :5] = float("nan")
        model.head.f_fc.bias[3] = float("inf")
    total = sum(v.numel() for v in model.state_dict().values())
    with pytest.raises(T.NonFiniteWeightsError) as info:
        save_model(model, cfg, path, {"run": 2})
    assert str(path) in str(info.value) and f"6 of {total:,} weights are NaN or infinite" in str(info.value)
    assert "head.f_fc.weight" in str(info.value)
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["model.pt"]

    poisoned = tmp_path / "poisoned.pt"  # such a file written by other means is refused on loading
    blob = torch.load(path, weights_only=True)
    blob["state_dict"]["head.f_fc.weight"][0, 0] = float("nan")
    torch.save(blob, poisoned)
    with pytest.raises(T.ModelFileError, match=f"1 of {total:,} weights are NaN or infinite"):
        load_model(poisoned)


def test_a_diverging_run_keeps_its_last_good_checkpoint(data, tmp_path):
    train, _ = data
    cfg = TrainConfig(preset="fbank-tcn", epochs=2, d_model=16, lr=1e-3)
    steps = []

    def loss(pred, target, mask):  # diverges in the second epoch
        steps.append(1)
        return T.l1_loss(pred, target, mask) * (float("nan") if len(steps) > len(train) else 1.0)

    ckpt = tmp_path / "ckpt" / "last.pt"
    with pytest.raises(T.NonFiniteWeightsError) as info:
        train_model(train, [], cfg, checkpoint_dir=ckpt.parent, loss=loss)
    assert str(ckpt) in str(info.value) and "epoch 2" in str(info.value)
    state = torch.load(ckpt, weights_only=True)
    assert state["epoch"] == 1 and all(torch.isfinite(v).all() for v in state["model"].values())
    assert sorted(p.name for p in ckpt.parent.iterdir()) == ["last.pt"]


def test_huge_finite_audio_trains_no_model(data, tmp_path):
    """Samples of 3e38 (finite) overflow the features: the weights turn NaN and neither the checkpoint nor the
    model is written (ingest refuses such audio; this is the last line for audio that did not pass through it)."""
    train, _ = data
    loud = [Example(ex.utterance_id, np.full_like(ex.audio, 3e38), ex.curves, ex.fps) for ex in train[:2]]
    cfg = TrainConfig(preset="fbank-tcn", epochs=1, d_model=16, lr=1e-3)
    with pytest.raises(T.NonFiniteWeightsError, match="last.pt"):
        train_model(loud, [], cfg, checkpoint_dir=tmp_path / "ckpt")
    assert not (tmp_path / "ckpt" / "last.pt").exists()
    result = train_model(loud, [], cfg)
    with pytest.raises(T.NonFiniteWeightsError, match="model.pt"):
        save_model(result.model, cfg, tmp_path / "model.pt", {})
    assert not (tmp_path / "model.pt").exists()
