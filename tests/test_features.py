"""Audio features for the mapping model (visemeflow.learning.features)."""

import math

import numpy as np
import pydantic
import pytest
import torch

from visemeflow.learning.features import (
    FeatureConfig,
    build_feature_extractor,
    dct_matrix,
    levinson_durbin,
    make_tiny_wav2vec2,
    mel_filterbank,
    resample_audio,
)

SR = 16000


def tone(freq, seconds, rate=SR, amp=0.5, phase=0.0):
    t = np.arange(round(seconds * rate)) / rate
    return (amp * np.sin(2 * np.pi * freq * t + phase)).astype(np.float32)


@pytest.fixture(scope="module")
def tiny_w2v_path(tmp_path_factory):
    return make_tiny_wav2vec2(tmp_path_factory.mktemp("w2v") / "tiny")


def config_for(kind, tiny_path=None, **kw):
    if kind == "wav2vec2":
        kw.setdefault("wav2vec2_model", str(tiny_path))
    return FeatureConfig(kind=kind, **kw)


KINDS = ["fbank", "mfcc", "lpc", "wav2vec2"]


@pytest.mark.parametrize("kind", KINDS)
def test_shapes_and_frame_rates(kind, tiny_w2v_path):
    ext = build_feature_extractor(config_for(kind, tiny_w2v_path)).eval()
    audio = torch.randn(2, 2 * SR) * 0.1
    lengths = torch.tensor([2 * SR, SR])
    with torch.no_grad():
        feats, feat_lengths = ext(audio, lengths)
    expected_dim = {"fbank": 80, "mfcc": 13, "lpc": 12, "wav2vec2": 32}[kind]
    expected_rate = 50.0 if kind == "wav2vec2" else 100.0
    assert ext.dim == expected_dim and feats.shape[-1] == expected_dim
    assert ext.frame_rate_hz == expected_rate
    assert feats.shape[0] == 2 and feats.shape[1] == int(feat_lengths.max())
    # about frame_rate frames per second of valid audio (within one window)
    for b, seconds in enumerate((2.0, 1.0)):
        assert abs(int(feat_lengths[b]) - seconds * expected_rate) <= 2
    assert torch.isfinite(feats).all()
    assert (feats[1, int(feat_lengths[1]) :] == 0).all()


# CMVN is the same code path for every kind, so wav2vec2 is checked without it only
@pytest.mark.parametrize(
    ("kind", "extra"),
    [(k, {}) for k in KINDS]
    + [(k, {"normalize": True}) for k in KINDS[:3]]
    + [("mfcc", {"mfcc_deltas": True})],
)
def test_batching_is_invariant_to_padding(kind, extra, tiny_w2v_path):
    ext = build_feature_extractor(config_for(kind, tiny_w2v_path, **extra)).eval()
    gen = torch.Generator().manual_seed(1)
    long = torch.randn(SR, generator=gen) * 0.3
    short = torch.randn(11_000, generator=gen) * 0.3
    batch = torch.zeros(2, SR)
    batch[0] = long
    batch[1, : short.shape[0]] = short
    batch[1, short.shape[0] :] = 5.0  # loud garbage in the padding must not leak
    with torch.no_grad():
        feats, lens = ext(batch, torch.tensor([SR, short.shape[0]]))
        alone, alone_len = ext(short[None], torch.tensor([short.shape[0]]))
        long_alone, _ = ext(long[None], torch.tensor([SR]))
    n = int(alone_len[0])
    assert int(lens[1]) == n and n > 0
    torch.testing.assert_close(feats[1, :n], alone[0, :n], atol=2e-4, rtol=1e-4)
    torch.testing.assert_close(feats[0], long_alone[0], atol=2e-4, rtol=1e-4)


def test_fbank_of_pure_tone_peaks_in_its_mel_band():
    ext = build_feature_extractor(FeatureConfig(kind="fbank"))
    fb = mel_filterbank(80, ext.n_fft, SR)
    for freq in (300.0, 1000.0, 3000.0, 6000.0):
        feats, _ = ext(torch.from_numpy(tone(freq, 0.5))[None])
        band = int(feats[0].mean(0).argmax())
        # the band whose triangle responds most at that frequency
        bin_idx = round(freq * ext.n_fft / SR)
        assert abs(band - int(fb[bin_idx].argmax())) <= 1, (freq, band)
    # silence hits the log floor, not -inf
    feats, _ = ext(torch.zeros(1, SR))
    assert torch.allclose(feats, torch.full_like(feats, math.log(1e-10)))


def test_mel_filterbank_and_dct_are_well_formed():
    fb = mel_filterbank(80, 512, SR)
    assert (
        fb.shape == (257, 80)
        and float(fb.max()) <= 1.0 + 1e-6
        and (fb.sum(0) > 0).all()
    )
    d = dct_matrix(80, 80)
    torch.testing.assert_close(d.T @ d, torch.eye(80), atol=1e-5, rtol=0)


def test_mfcc_is_dct_of_log_mel():
    audio = torch.randn(1, SR) * 0.2
    fbank, _ = build_feature_extractor(FeatureConfig(kind="fbank"))(audio)
    mfcc, _ = build_feature_extractor(FeatureConfig(kind="mfcc"))(audio)
    x = fbank[0].double().numpy()  # (T, 80)
    n = np.arange(80)
    ref = np.stack(
        [np.sum(x * np.cos(np.pi / 80 * (n + 0.5) * k), axis=1) for k in range(13)],
        axis=1,
    )
    ref *= np.sqrt(2.0 / 80)
    ref[:, 0] /= np.sqrt(2.0)
    np.testing.assert_allclose(mfcc[0].double().numpy(), ref, atol=1e-3, rtol=1e-4)


def test_mfcc_deltas_shape_and_values():
    ext = build_feature_extractor(FeatureConfig(kind="mfcc", mfcc_deltas=True))
    assert ext.dim == 39
    audio = torch.randn(2, SR) * 0.2
    feats, _lens = ext(audio, torch.tensor([SR, 8000]))
    assert feats.shape[-1] == 39
    # the delta of a frame in the middle is the regression slope over +-2 frames
    c = feats[0, :, :13]
    t = 50
    slope = (1 * (c[t + 1] - c[t - 1]) + 2 * (c[t + 2] - c[t - 2])) / 10
    torch.testing.assert_close(feats[0, t, 13:26], slope, atol=1e-4, rtol=1e-4)


def test_lpc_recovers_ar2_coefficients():
    rng = np.random.default_rng(0)
    a1, a2 = 1.3, -0.6  # stable: poles inside the unit circle
    e = rng.standard_normal(3 * SR)
    x = np.zeros_like(e)
    for n in range(2, len(e)):
        x[n] = a1 * x[n - 1] + a2 * x[n - 2] + e[n]
    x = (x / np.abs(x).max()).astype(np.float32)
    ext = build_feature_extractor(FeatureConfig(kind="lpc", lpc_order=2))
    feats, _ = ext(torch.from_numpy(x)[None])
    est = feats[0].mean(0).numpy()
    np.testing.assert_allclose(est, [a1, a2], atol=0.04)
    # higher order: extra coefficients of an AR(2) process are ~0
    feats12, _ = build_feature_extractor(FeatureConfig(kind="lpc"))(
        torch.from_numpy(x)[None]
    )
    est12 = feats12[0].mean(0).numpy()
    np.testing.assert_allclose(est12[:2], [a1, a2], atol=0.06)
    assert np.abs(est12[2:]).max() < 0.06


def test_levinson_matches_direct_solve_and_silence_gives_zeros():
    rng = np.random.default_rng(3)
    sig = rng.standard_normal(400)
    r = np.array([np.dot(sig[: 400 - k], sig[k:]) for k in range(7)])
    toeplitz = np.array([[r[abs(i - j)] for j in range(6)] for i in range(6)])
    direct = np.linalg.solve(toeplitz, r[1:7])
    a, err = levinson_durbin(torch.from_numpy(r), 6)
    np.testing.assert_allclose(a.numpy(), direct, rtol=1e-8, atol=1e-10)
    assert 0 < float(err) < r[0]
    feats, _ = build_feature_extractor(FeatureConfig(kind="lpc"))(torch.zeros(1, SR))
    assert torch.isfinite(feats).all() and (feats == 0).all()


def test_resampler_keeps_frequency_and_level_44k_stereo_to_16k_mono():
    rate = 44100
    left = tone(1000.0, 1.0, rate=rate, amp=0.5)
    stereo = np.stack(
        [left, left], axis=1
    )  # identical channels: the mono mix keeps the level
    y = resample_audio(stereo, rate, SR)
    assert y.dtype == np.float32 and y.ndim == 1 and len(y) == SR
    core = y[800:-800]  # skip filter edges
    spec = np.abs(np.fft.rfft(core * np.hanning(len(core))))
    peak_hz = np.argmax(spec) * SR / len(core)
    assert abs(peak_hz - 1000.0) < 2.0
    rms = np.sqrt(np.mean(core.astype(np.float64) ** 2))
    assert abs(rms - 0.5 / np.sqrt(2)) < 0.005
    # phase-exact against the analytic tone
    t = np.arange(len(y)) / SR
    np.testing.assert_allclose(
        y[800:-800], (0.5 * np.sin(2 * np.pi * 1000 * t))[800:-800], atol=5e-3
    )


def test_resampler_removes_content_above_new_nyquist_and_handles_other_rates():
    rate = 48000
    x = tone(12000.0, 0.5, rate=rate)  # above 8 kHz Nyquist of the target
    y = resample_audio(x, rate, SR)
    assert np.sqrt(np.mean(y[400:-400] ** 2)) < 0.01
    up = resample_audio(tone(440.0, 0.25, rate=8000), 8000, SR)  # upsampling
    t = np.arange(len(up)) / SR
    np.testing.assert_allclose(
        up[200:-200], (0.5 * np.sin(2 * np.pi * 440 * t))[200:-200], atol=5e-3
    )
    odd = resample_audio(
        tone(440.0, 0.25, rate=22051), 22051, SR
    )  # awkward ratio -> direct sinc path
    t = np.arange(len(odd)) / SR
    assert len(odd) == math.ceil(len(tone(440.0, 0.25, rate=22051)) * SR / 22051)
    np.testing.assert_allclose(
        odd[400:-400], (0.5 * np.sin(2 * np.pi * 440 * t))[400:-400], atol=1e-2
    )
    same = resample_audio(np.ones((10, 2), dtype=np.float64), SR, SR)
    assert same.dtype == np.float32 and same.shape == (10,)


def test_resampler_polyphase_and_direct_paths_agree():
    from visemeflow.learning.features import _sinc_direct

    x = np.random.default_rng(5).standard_normal(4410).astype(np.float32)
    poly = resample_audio(x, 44100, SR)
    direct = _sinc_direct(torch.from_numpy(x).double(), 44100, SR, len(poly)).numpy()
    np.testing.assert_allclose(poly, direct, atol=1e-5)


def test_wav2vec2_tiny_model_loads_freezes_encoder_and_trains_transformer(
    tiny_w2v_path,
):
    cfg = FeatureConfig(kind="wav2vec2", wav2vec2_model=str(tiny_w2v_path))
    ext = build_feature_extractor(cfg)
    model = ext.model
    assert type(model).__name__ == "Wav2Vec2Model"
    assert ext.dim == model.config.hidden_size == 32
    assert ext.frame_rate_hz == 50.0
    enc = list(model.feature_extractor.parameters())
    assert enc and all(not p.requires_grad for p in enc)
    trans = list(model.encoder.parameters())
    assert trans and all(p.requires_grad for p in trans)
    # weights really came from disk: a second load gives identical parameters
    again = build_feature_extractor(cfg).model
    for (n1, p1), (n2, p2) in zip(
        model.state_dict().items(), again.state_dict().items()
    ):
        assert n1 == n2 and torch.equal(p1, p2)
    ext.train()
    audio = torch.randn(2, SR) * 0.1
    feats, _lens = ext(audio, torch.tensor([SR, 12000]))
    (feats**2).sum().backward()
    grads = [p.grad for p in model.encoder.parameters()]
    assert (
        all(g is not None for g in grads)
        and sum(float(g.abs().sum()) for g in grads) > 0
    )
    assert all(p.grad is None for p in enc)
    unfrozen = build_feature_extractor(
        cfg.model_copy(update={"freeze_feature_encoder": False})
    )
    assert all(p.requires_grad for p in unfrozen.model.feature_extractor.parameters())


def test_wav2vec2_unavailable_model_raises_clear_error(tmp_path):
    cfg = FeatureConfig(kind="wav2vec2", wav2vec2_model=str(tmp_path / "no-such-model"))
    with pytest.raises(RuntimeError, match="local directory"):
        build_feature_extractor(cfg)


def test_config_validation():
    with pytest.raises(ValueError):
        FeatureConfig(kind="wav2vec2", sample_rate=8000)
    with pytest.raises(ValueError):
        FeatureConfig(kind="mfcc", n_mfcc=100)
    with pytest.raises(ValueError):
        FeatureConfig(kind="spectrogram")
    cfg = FeatureConfig(kind="fbank")
    assert cfg.win_length == 400 and cfg.hop_length == 160
    with pytest.raises(pydantic.ValidationError):
        cfg.n_mels = 40  # frozen
