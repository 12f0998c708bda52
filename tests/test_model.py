"""Mapping models (paper Sec. 5.1, Tables 2/3): PPE, interpolation, decoders, SpecAugment, presets."""

import math

import numpy as np
import pytest
import torch

from visemeflow.learning.model import (
    AudioCurveModel,
    CurveModel,
    DecoderConfig,
    FaceFormerDecoder,
    KarrasConvNet,
    MeanCurveBaseline,
    ModelConfig,
    count_parameters,
    frames_for_duration,
    interpolate_to_frames,
    l1_loss,
    periodic_positional_encoding,
    spec_augment,
)
from visemeflow.learning.presets import PRESETS, augment, build_model, build_optimizer
from visemeflow.visemes import N_VISEMES

D_FEAT = 8
RATE = 100.0
FPS = 25.0
KINDS = ["blstm", "lstm", "tcn", "transformer"]


def _model(kind: str, d: int = 16, layers: int = 2, **kw) -> CurveModel:
    torch.manual_seed(0)
    cfg = ModelConfig(
        feature_dim=D_FEAT, feature_rate_hz=RATE, curve_fps=FPS, d_model=d,
        decoder=DecoderConfig(kind=kind, layers=layers, width=d), **kw,
    )
    return CurveModel(cfg).eval()


def _batch(lengths=(120, 80, 47), seed=0):
    g = torch.Generator().manual_seed(seed)
    lengths = torch.tensor(lengths)
    feats = torch.randn(len(lengths), int(lengths.max()), D_FEAT, generator=g)
    for i, n in enumerate(lengths):
        feats[i, n:] = 123.0  # garbage padding must never be read
    n_frames = frames_for_duration(lengths, RATE, FPS)
    return feats, lengths, n_frames


# --- PPE and interpolation -----------------------------------------------------------------------


def test_ppe_is_periodic_and_distinct_within_period():
    p = 25
    pe = periodic_positional_encoding(80, 32, p)
    assert pe.shape == (80, 32)
    for t in range(80 - p):
        assert torch.allclose(pe[t], pe[t + p])
    within = pe[:p]
    dists = torch.cdist(within, within) + torch.eye(p) * 1e9
    assert dists.min() > 1e-3
    assert torch.allclose(pe[0, 0::2], torch.zeros(16)) and torch.allclose(pe[0, 1::2], torch.ones(16))


def test_default_ppe_period_is_fps():
    assert ModelConfig(feature_dim=1, feature_rate_hz=100, curve_fps=25).ppe_period() == 25
    assert ModelConfig(feature_dim=1, feature_rate_hz=100, curve_fps=30).ppe_period() == 30
    assert ModelConfig(feature_dim=1, feature_rate_hz=100, ppe_period_frames=7).ppe_period() == 7


def test_interpolation_lengths_and_linear_ramp_exact():
    assert int(frames_for_duration(200, 100.0, 25.0)) == 50  # 2 s @ 100 Hz -> 50 frames @ 25 fps
    assert int(frames_for_duration(16000 * 2, 16000, 30.0)) == 60
    # ramp x[i] = 0.5 i + 2 sampled at 100 Hz; frame k at 30 fps sits at i = k * 100/30
    n_src = 200
    x = (0.5 * torch.arange(n_src, dtype=torch.float32) + 2)[None, :, None].repeat(1, 1, 3)
    nf = frames_for_duration(torch.tensor([n_src]), 100.0, 30.0)
    assert int(nf[0]) == 60
    y = interpolate_to_frames(x, torch.tensor([n_src]), nf, 100.0, 30.0)
    assert y.shape == (1, 60, 3)
    expected = 0.5 * (torch.arange(60, dtype=torch.float64) * 100 / 30) + 2
    assert torch.allclose(y[0, :, 0].double(), expected, atol=1e-4)
    # 100 Hz -> 25 fps picks every 4th frame exactly
    y2 = interpolate_to_frames(x, torch.tensor([n_src]), torch.tensor([50]), 100.0, 25.0)
    assert torch.allclose(y2[0, :, 0], x[0, ::4, 0])


def test_interpolation_upsampling_and_padding():
    # 50 Hz features -> 100 fps: midpoints are averages; past the utterance's end it holds the last value
    x = torch.tensor([[0.0, 2.0, 4.0, 99.0]])[..., None]
    y = interpolate_to_frames(x, torch.tensor([3]), torch.tensor([7]), 50.0, 100.0)
    assert y[0, :, 0].tolist() == [0.0, 1.0, 2.0, 3.0, 4.0, 4.0, 4.0]
    ys = interpolate_to_frames(x.repeat(2, 1, 1), torch.tensor([3, 4]), torch.tensor([3, 5]), 50.0, 100.0)
    assert ys[0, 3:].abs().sum() == 0  # zero past n_frames
    assert ys[1, :, 0].tolist() == [0.0, 1.0, 2.0, 3.0, 4.0]


# --- decoders ------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_decoder_shapes_and_mask(kind):
    model = _model(kind)
    feats, lengths, n_frames = _batch()
    curves, mask = model(feats, lengths, n_frames)
    assert curves.shape == (3, int(n_frames.max()), N_VISEMES)
    assert mask.dtype == torch.bool and mask.sum(1).tolist() == n_frames.tolist()
    assert curves[~mask].abs().sum() == 0
    assert torch.isfinite(curves).all()


@pytest.mark.parametrize("kind", KINDS)
def test_decoder_padding_invariance(kind):
    model = _model(kind)
    feats, lengths, n_frames = _batch()
    with torch.no_grad():
        batched, _ = model(feats, lengths, n_frames)
        for i in range(3):
            n, t = int(lengths[i]), int(n_frames[i])
            alone, _ = model(feats[i : i + 1, :n], lengths[i : i + 1], n_frames[i : i + 1])
            assert alone.shape[1] == t
            torch.testing.assert_close(batched[i, :t], alone[0], atol=1e-5, rtol=1e-5)


def _future_change(kind: str):
    model = _model(kind)
    feats, lengths, n_frames = _batch(lengths=(120,))
    t = int(n_frames[0])
    k = 15  # curve frame; change feature frames from well after it (frame 15 reads feature 60..61)
    feats2 = feats.clone()
    feats2[:, 64:] += torch.randn_like(feats2[:, 64:])
    with torch.no_grad():
        a, _ = model(feats, lengths, n_frames)
        b, _ = model(feats2, lengths, n_frames)
    assert t > k + 5
    return a, b, k


def test_lstm_is_causal():
    a, b, k = _future_change("lstm")
    torch.testing.assert_close(a[:, : k + 1], b[:, : k + 1], atol=0, rtol=0)
    assert not torch.allclose(a[:, k + 2 :], b[:, k + 2 :])


def test_blstm_is_not_causal():
    a, b, k = _future_change("blstm")
    assert not torch.allclose(a[:, :k], b[:, :k], atol=1e-7)


def test_sigmoid_output_in_unit_interval():
    model = _model("blstm", output="sigmoid")
    feats, lengths, n_frames = _batch()
    curves, mask = model(feats, lengths, n_frames)
    assert (curves[mask] > 0).all() and (curves[mask] < 1).all()


# --- SpecAugment and loss ------------------------------------------------------------------------


def test_spec_augment_fractions_padding_and_determinism():
    feats, lengths, _ = _batch(lengths=(100, 60))
    out, masked = spec_augment(feats, lengths, time_masks=1, time_width=0.1, freq_masks=0,
                               generator=torch.Generator().manual_seed(1), return_mask=True)
    changed = out != feats
    assert torch.equal(changed, masked)
    # exactly one run of round(0.1 * n) whole frames per utterance
    frames = changed.all(dim=2)
    assert frames[0].sum() == 10 and frames[1].sum() == 6
    assert torch.equal(changed.any(dim=2), frames)
    idx = frames[0].nonzero().flatten()
    assert (idx[-1] - idx[0]).item() == 9
    # frequency masks: round(0.25 * 8) = 2 channels over the valid frames only
    out, masked = spec_augment(feats, lengths, time_masks=0, freq_masks=1, freq_width=0.25,
                               generator=torch.Generator().manual_seed(2), return_mask=True)
    chans = (out != feats)[1, :60].all(dim=0)
    assert chans.sum() == 2
    # padding untouched, several masks cover at most the requested total, seeded -> deterministic
    kw = {"time_masks": 2, "time_width": 0.05, "freq_masks": 2, "freq_width": 0.25}
    a = spec_augment(feats, lengths, generator=torch.Generator().manual_seed(3), **kw)
    b = spec_augment(feats, lengths, generator=torch.Generator().manual_seed(3), **kw)
    assert torch.equal(a, b)
    assert torch.equal(a[1, 60:], feats[1, 60:])
    time_frac = (a != feats)[0].all(dim=1).float().mean()
    assert 0.05 - 1e-6 <= time_frac <= 0.10 + 1e-6
    c = spec_augment(feats, lengths, generator=torch.Generator().manual_seed(4), sample_widths=True, **kw)
    assert torch.equal(c[1, 60:], feats[1, 60:])
    assert (c != feats)[0].all(dim=1).sum() <= 10


def test_l1_loss_ignores_padding():
    pred = torch.zeros(2, 5, N_VISEMES)
    target = torch.ones(2, 5, N_VISEMES) * 0.5
    mask = torch.tensor([[1, 1, 1, 1, 1], [1, 1, 0, 0, 0]], dtype=torch.bool)
    target[1, 2:] = 1000.0
    assert l1_loss(pred, target, mask).item() == pytest.approx(0.5)
    pred2 = pred.clone()
    pred2[0, 0, 0] = 1.5
    assert l1_loss(pred2, target, mask).item() == pytest.approx(0.5 + 0.5 / (7 * N_VISEMES))


# --- baselines -----------------------------------------------------------------------------------


def test_mean_curve_baseline_equals_mean():
    rng = np.random.default_rng(0)
    curves = [rng.random((n, N_VISEMES)) for n in (10, 30, 5)]
    model = MeanCurveBaseline(RATE, FPS).fit(curves)
    expected = np.concatenate(curves).mean(0)
    feats, lengths, n_frames = _batch()
    out, mask = model(feats, lengths, n_frames)
    assert np.allclose(out[0, 0].numpy(), expected, atol=1e-6)
    assert np.allclose(out[mask].numpy(), expected[None], atol=1e-6)
    assert out[~mask].abs().sum() == 0


def test_karras_shapes_window_and_padding():
    torch.manual_seed(0)
    model = KarrasConvNet(D_FEAT, RATE, FPS, channels=12, hidden=20).eval()
    assert model.window == 52  # 520 ms at 100 Hz
    feats, lengths, n_frames = _batch()
    with torch.no_grad():
        out, _ = model(feats, lengths, n_frames)
        assert out.shape == (3, int(n_frames.max()), N_VISEMES)
        alone, _ = model(feats[2:, :47], lengths[2:], n_frames[2:])
    torch.testing.assert_close(out[2, : int(n_frames[2])], alone[0], atol=1e-5, rtol=1e-5)
    # the receptive field is the window: features > 26 frames past a frame's centre don't matter
    feats2 = feats.clone()
    feats2[0, 80:] += 5.0  # curve frame 13 is centred on feature 52: window 26..77
    with torch.no_grad():
        out2, _ = model(feats2, lengths, n_frames)
    torch.testing.assert_close(out[0, :14], out2[0, :14], atol=0, rtol=0)
    assert not torch.allclose(out[0, 20:30], out2[0, 20:30])


def test_faceformer_shapes_teacher_forcing_and_causal_inference():
    torch.manual_seed(0)
    model = FaceFormerDecoder(D_FEAT, RATE, FPS, d_model=16, heads=4).eval()
    feats, lengths, n_frames = _batch()
    targets = torch.rand(3, int(n_frames.max()), N_VISEMES)
    with torch.no_grad():
        tf, mask = model(feats, lengths, n_frames, targets=targets)
        ar, mask2 = model(feats, lengths, n_frames)
    assert tf.shape == ar.shape == (3, int(n_frames.max()), N_VISEMES)
    assert torch.equal(mask, mask2)
    # teacher forcing: output at frame t depends only on targets < t
    t2 = targets.clone()
    t2[:, 10:] = torch.rand_like(t2[:, 10:])
    with torch.no_grad():
        tf2, _ = model(feats, lengths, n_frames, targets=t2)
    torch.testing.assert_close(tf[:, :11], tf2[:, :11], atol=1e-6, rtol=1e-6)
    # inference: changing future audio does not change past frames
    feats2 = feats.clone()
    feats2[:, 64:] += torch.randn_like(feats2[:, 64:])
    with torch.no_grad():
        ar2, _ = model(feats2, lengths, n_frames)
    torch.testing.assert_close(ar[:, :16], ar2[:, :16], atol=1e-6, rtol=1e-6)
    assert not torch.allclose(ar[0, 17:30], ar2[0, 17:30])
    # greedy autoregression == teacher forcing on its own predictions
    with torch.no_grad():
        tf_self, _ = model(feats, lengths, n_frames, targets=ar)
    torch.testing.assert_close(tf_self, ar, atol=1e-5, rtol=1e-5)
    # batching invariance at inference
    with torch.no_grad():
        alone, _ = model(feats[2:, :47], lengths[2:], n_frames[2:])
    torch.testing.assert_close(ar[2, : int(n_frames[2])], alone[0], atol=1e-5, rtol=1e-5)


def test_audio_curve_model_wraps_a_generic_feature_module():
    class FrameMeans(torch.nn.Module):  # 10 ms frames of 160 samples -> 100 Hz, D = 8 by tiling the mean
        dim = D_FEAT
        frame_rate_hz = 100.0

        def forward(self, audio, lengths):
            frames = audio[:, : audio.shape[1] // 160 * 160].reshape(audio.shape[0], -1, 160)
            return frames.mean(-1, keepdim=True).repeat(1, 1, D_FEAT), lengths // 160

    fm = FrameMeans()
    head = build_model("fbank-blstm", fm.dim, fm.frame_rate_hz, FPS, d_model=16).eval()
    model = AudioCurveModel(fm, head)
    audio = torch.randn(2, 16000)
    lengths = torch.tensor([16000, 8000])
    n_frames = frames_for_duration(lengths, 16000, FPS)
    with torch.no_grad():
        curves, mask = model(audio, lengths, n_frames)
        alone, _ = model(audio[1:, :8000], lengths[1:], n_frames[1:])
    assert curves.shape == (2, 25, N_VISEMES) and mask.sum(1).tolist() == [25, 12]
    torch.testing.assert_close(curves[1, :12], alone[0], atol=1e-5, rtol=1e-5)


# --- presets -------------------------------------------------------------------------------------


def test_preset_registry_contents():
    for name in ["fbank-blstm", "fbank-lstm", "fbank-tcn", "fbank-transformer", "mfcc-blstm", "lpc-blstm",
                 "wav2vec2-blstm", "karras-lpc", "faceformer-fbank", "mean-curve"]:
        assert name in PRESETS
    assert PRESETS["wav2vec2-blstm"].lr == 1e-5
    assert PRESETS["wav2vec2-blstm"].spec_augment is None
    assert PRESETS["fbank-blstm"].spec_augment is not None
    for p in PRESETS.values():
        if p.architecture == "curve":
            assert p.decoder.layers == 1 and p.d_model == 512


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_two_step_training_every_preset(name):
    preset = PRESETS[name]
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    lengths = torch.tensor([60, 45, 30])  # 0.6, 0.45, 0.3 s at 100 Hz
    feats = torch.randn(3, 60, D_FEAT, generator=g)
    n_frames = frames_for_duration(lengths, RATE, FPS)
    targets = torch.rand(3, int(n_frames.max()), N_VISEMES, generator=g)
    model = build_model(preset, D_FEAT, RATE, FPS, d_model=16)
    if isinstance(model, MeanCurveBaseline):
        model.fit([targets[i, : int(n_frames[i])] for i in range(3)])
    opt = build_optimizer(preset, model)
    assert (opt is None) == (name == "mean-curve")
    model.train()
    losses = []
    for _ in range(2):
        x = augment(preset, feats, lengths, generator=g)
        curves, mask = model(x, lengths, n_frames, targets=targets)
        loss = l1_loss(curves, targets[:, : curves.shape[1]], mask)
        assert torch.isfinite(loss)
        if opt is not None:
            opt.zero_grad()
            loss.backward()
            assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
            opt.param_groups[0]["lr"] = preset.lr
            opt.step()
        losses.append(loss.item())
    assert all(math.isfinite(v) for v in losses)
    model.eval()
    with torch.no_grad():
        curves, mask = model(feats, lengths, n_frames)
    assert curves.shape == (3, int(n_frames.max()), N_VISEMES) and torch.isfinite(curves).all()


def test_fbank_blstm_parameter_count_at_paper_width():
    model = build_model("fbank-blstm", feature_dim=80, feature_rate_hz=100.0, curve_fps=30.0)
    n = count_parameters(model)
    # proj 80*512+512, BLSTM 2 * (4*256*(512+256) + 2*4*256), FC 512*16+16
    expected = 80 * 512 + 512 + 2 * (4 * 256 * (512 + 256) + 2 * 4 * 256) + 512 * 16 + 16
    assert n == expected
    assert 1_000_000 < n < 3_000_000


def test_closure_peaks_keep_the_peak_and_cut_its_shoulders_at_any_rate():
    from visemeflow.learning.model import ClosurePeaks
    from visemeflow.visemes import VISEME_INDEX

    k = VISEME_INDEX["MBP"]
    y = torch.zeros(1, 12, N_VISEMES)
    y[0, :, 0] = 0.3                                             # another viseme: untouched
    y[0, 3:8, k] = torch.tensor([0.25, 0.5, 1.0, 0.5, 0.25])     # a broad closure
    y[0, 10, k] = 0.6                                            # a second, separate closure 5 frames later
    out = ClosurePeaks(0.1, 16.0)(y, 30.0)                       # 3 frames either side at 30 fps
    assert torch.equal(out[..., 0], y[..., 0])
    assert out[0, 5, k] == 1.0 and out[0, 10, k] == pytest.approx(0.6)   # local maxima kept
    assert out[0, 4, k] == pytest.approx(0.5 * 0.5 ** 16) and out[0, 3, k] < 1e-9
    assert ClosurePeaks(0.1, 16.0).half_window(30.0) == 3 and ClosurePeaks(0.1, 16.0).half_window(60.0) == 6
    with pytest.raises(ValueError):
        ClosurePeaks(0.0, 16.0)


def test_closure_peaks_lead_moves_mbp_earlier_and_a_leading_closure_caps_the_other_visemes():
    from visemeflow.learning.model import ClosurePeaks
    from visemeflow.visemes import VISEME_INDEX

    k, aa = VISEME_INDEX["MBP"], VISEME_INDEX["AHH"]
    y = torch.zeros(1, 8, N_VISEMES)
    y[0, :, k] = torch.tensor([0.0, 0.0, 0.2, 0.6, 0.2, 0.0, 0.0, 0.4])
    y[0, :, aa] = torch.tensor([0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5])
    led = ClosurePeaks(0.1, 1.0, lead_s=0.25 / 30.0)
    x = led._lead(y[..., k], 0.25)
    assert torch.allclose(x[0], torch.tensor([0.0, 0.05, 0.3, 0.5, 0.15, 0.0, 0.1, 0.4]))  # the last frame holds
    out = led(y, 30.0)
    assert out[0, 3, k] == pytest.approx(0.5) and torch.equal(out[..., aa], y[..., aa])   # no others_power: as is
    closed = ClosurePeaks(0.1, 16.0, others_power=3.0)(y, 30.0)
    assert closed[0, 3, k] == pytest.approx(0.6)                     # MBP leads frame 3: AHH capped at 0.4 ** 3
    assert closed[0, 3, aa] == pytest.approx(0.4 ** 3) and closed[0, 2, aa] == 0.5   # elsewhere AHH leads: as is
    assert torch.equal(closed.argmax(-1)[0, [0, 1, 2, 3, 4, 5]], torch.tensor([aa, aa, aa, k, aa, aa]))
    for bad in ({"lead_s": -0.01}, {"lead_s": 0.2}, {"others_power": -1.0}):
        with pytest.raises(ValueError):
            ClosurePeaks(0.1, 16.0, **bad)


def test_closure_peaks_apply_at_inference_only_and_configs_without_them_serialise_as_before():
    from visemeflow.learning.train import TrainConfig, build_training_model

    plain = TrainConfig(preset="fbank-blstm", d_model=32)
    assert not {"mbp_peaks_half_window_s", "mbp_peaks_power", "mbp_lead_s", "mbp_others_power"} & set(plain.model_dump())
    assert build_training_model(plain, 30.0).closure_peaks is None
    config = plain.model_copy(update={"mbp_peaks_half_window_s": 0.1})
    model = build_training_model(config, 30.0)
    assert model.closure_peaks is not None
    torch.manual_seed(0)
    audio, lengths, n = torch.randn(1, 16000), torch.tensor([16000]), torch.tensor([30])
    model.train()
    torch.manual_seed(1)
    trained, _ = model(audio, lengths, n, fps=30.0)
    torch.manual_seed(1)
    plain_train, _ = model.head(*model.features(audio, lengths), n, fps=30.0)
    assert torch.equal(trained, plain_train)           # training sees the head's own output (same dropout draws)
    model.eval()
    with torch.no_grad():
        inferred, _ = model(audio, lengths, n, fps=30.0)
        raw, _ = model.head(*model.features(audio, lengths), n, fps=30.0)
    assert torch.allclose(inferred, model.closure_peaks(raw, 30.0))
    assert not torch.allclose(inferred, raw)          # the MBP channel changed, at inference


def _speech_like(seconds: float, onset_s: float, rate: int = 16000) -> np.ndarray:
    """Quiet noise, then from `onset_s` a loud vowel-like buzz (harmonics of 120 Hz): one release, at `onset_s`."""
    rng = np.random.default_rng(0)
    t = np.arange(int(seconds * rate)) / rate
    audio = rng.normal(0, 1e-4, len(t))
    buzz = sum(np.sin(2 * np.pi * 120 * h * t) / h for h in range(1, 30))
    audio[t >= onset_s] += 0.3 * buzz[t >= onset_s]
    return audio.astype(np.float32)


def test_release_cut_finds_the_release_in_the_audio_and_ends_the_closure_there():
    from visemeflow.learning.model import ReleaseCut
    from visemeflow.visemes import VISEME_INDEX

    cut = ReleaseCut(12.0)
    audio = _speech_like(1.0, 0.5)
    found = cut.releases(audio)
    assert len(found) == 1 and abs(found[0] - 0.5) <= 0.02, found
    assert cut.releases(_speech_like(1.0, 2.0)).size == 0             # no rise: no release
    assert cut.releases(audio[:100]).size == 0                        # shorter than a frame
    k, aa = VISEME_INDEX["MBP"], VISEME_INDEX["AHH"]
    y = np.zeros((60, N_VISEMES), np.float32)                     # 60 fps: frame 31 is 0.517 s
    y[:, aa] = 0.6
    y[29:33, k] = (0.5, 0.7, 0.95, 0.6)      # a closure whose peak (frame 31) comes just after the release (0.51 s)
    y[31, aa] = 0.01
    out = cut.cut(y, audio, 60.0)
    assert np.array_equal(out[30], y[31])                # its pose moved to frame 30 (0.5 s), the last before it
    assert (out[31:35].argmax(axis=1) != k).all()         # after the release MBP no longer leads
    assert np.array_equal(out[:30], y[:30]) and np.array_equal(out[35:], y[35:])
    late = y.copy()
    late[29:33, k], late[31, aa] = 0.0, 0.6
    late[33:37, k] = (0.5, 0.7, 0.95, 0.6)   # a peak 0.08 s after the release: another closure, left alone
    late[35, aa] = 0.01
    assert np.array_equal(cut.cut(late, audio, 60.0), late)
    early = y.copy()
    early[29:33, k], early[31, aa] = 0.0, 0.6
    early[25:30, k] = (0.5, 0.7, 0.95, 0.9, 0.8)   # a peak before the release, MBP leading up to it: the closure
    early[27:30, aa] = 0.01                        # stays, and MBP no longer leads after the release
    cut_early = cut.cut(early, audio, 60.0)
    assert np.array_equal(cut_early[:31], early[:31]) and (cut_early[31:].argmax(axis=1) != k).all()
    # a closure with no release near it, or too weak a peak, stays as it was
    assert np.array_equal(cut.cut(y, _speech_like(1.0, 2.0), 60.0), y)
    weak = y.copy()
    weak[29:33, k] = (0.1, 0.2, 0.25, 0.1)
    assert np.array_equal(cut.cut(weak, audio, 60.0), weak)
    with pytest.raises(ValueError):
        ReleaseCut(0.0)


def test_release_cut_applies_at_inference_only_between_the_narrowing_and_the_cap():
    from visemeflow.learning.train import TrainConfig, build_training_model

    plain = TrainConfig(preset="fbank-blstm", d_model=32)
    assert "mbp_release_rise_db" not in plain.model_dump()                    # older configs serialise as before
    config = plain.model_copy(update={"mbp_peaks_half_window_s": 0.067, "mbp_others_power": 6.0,
                                      "mbp_release_rise_db": 12.0})
    model = build_training_model(config, 30.0)
    assert model.release_cut is not None and model.release_cut.rise_db == 12.0
    audio = torch.from_numpy(_speech_like(1.0, 0.5))[None]
    lengths, n = torch.tensor([16000]), torch.tensor([30])
    model.eval()
    with torch.no_grad():
        inferred, mask = model(audio, lengths, n, fps=30.0)
        raw, _ = model.head(*model.features(audio, lengths), n, fps=30.0)
    peaks = model.closure_peaks
    cut = torch.from_numpy(model.release_cut.cut(peaks.narrow(raw, 30.0)[0].numpy(), audio[0].numpy(), 30.0))[None]
    assert torch.allclose(inferred, peaks.cap_others(cut) * mask[..., None])
    model.train()
    trained, _ = model(audio, lengths, n, fps=30.0)
    assert trained.requires_grad                                              # training: the head's own output
