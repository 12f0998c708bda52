"""Synthetic rooms and channels for training audio (visemeflow.learning.rooms)."""

from __future__ import annotations

import numpy as np
import pytest

from visemeflow.learning.rooms import apply_channel, apply_room, estimate_rt60, room_impulse_response

SR = 16000


def _speechlike(seconds: float = 1.5, seed: int = 0) -> np.ndarray:
    """Bursts of a harmonic tone separated by silence (so reverb has gaps to fill)."""
    t = np.arange(int(seconds * SR)) / SR
    tone = sum(np.sin(2 * np.pi * 140 * k * t) / k for k in range(1, 12))
    gate = (np.sin(2 * np.pi * 2.0 * t) > 0.3).astype(np.float64)
    return (0.1 * tone * gate + 1e-4 * np.random.default_rng(seed).standard_normal(len(t))).astype(np.float32)


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x, dtype=np.float64))))


@pytest.mark.parametrize("rt60", [0.2, 0.4, 0.8])
@pytest.mark.parametrize("darkening", [0.0, 0.5])
def test_the_tails_energy_decays_at_the_requested_rt60(rt60, darkening):
    estimates = []
    for seed in range(5):
        h = room_impulse_response(SR, rt60, np.random.default_rng(seed), drr_db=0.0, predelay_s=0.005,
                                  darkening=darkening)
        assert h[0] == 1.0 and np.all(h[1:int(0.005 * SR)] == 0.0)   # direct path at 0, nothing before the tail
        assert len(h) == int(0.005 * SR) + int(rt60 * SR)
        estimates.append(estimate_rt60(h, SR, skip=int(0.005 * SR)))
    # each draw within 10 %, their mean within 5 % (a T20 fit on one noise draw wobbles a few %)
    assert all(abs(e / rt60 - 1) < 0.1 for e in estimates), estimates
    assert abs(np.mean(estimates) / rt60 - 1) < 0.05, estimates


def test_the_direct_to_reverberant_ratio_is_the_requested_one():
    for drr in (-3.0, 0.0, 10.0):
        h = room_impulse_response(SR, 0.5, np.random.default_rng(1), drr_db=drr)
        assert 10 * np.log10(h[0] ** 2 / np.sum(h[1:] ** 2)) == pytest.approx(drr, abs=1e-6)


def test_a_longer_rt60_leaves_more_energy_late():
    late = []
    for rt60 in (0.2, 0.8):
        h = room_impulse_response(SR, rt60, np.random.default_rng(0), drr_db=0.0)
        late.append(np.sum(h[int(0.1 * SR):] ** 2) / np.sum(h[1:] ** 2))
    assert late[1] > 3 * late[0]


@pytest.mark.parametrize("channel", [False, True])
def test_apply_room_keeps_length_and_level_and_is_deterministic_per_seed(channel):
    x = _speechlike()
    a = apply_room(x, SR, np.random.default_rng(7), channel=channel)
    b = apply_room(x, SR, np.random.default_rng(7), channel=channel)
    c = apply_room(x, SR, np.random.default_rng(8), channel=channel)
    assert a.shape == x.shape and a.dtype == np.float32
    assert np.array_equal(a, b)
    assert not np.allclose(a, c)
    assert _rms(a) == pytest.approx(_rms(x), rel=1e-4)
    assert np.all(np.isfinite(a))
    assert not np.allclose(a, x, atol=1e-3)   # it did change the sound


def test_apply_room_does_not_move_speech_in_time():
    x = np.zeros(SR, np.float32)
    x[8000:8400] = np.sin(2 * np.pi * 500 * np.arange(400) / SR)   # a 25-ms burst at 0.5 s
    for seed in range(5):
        y = apply_room(x, SR, np.random.default_rng(seed), channel=True, snr_db=(200.0, 200.0))
        assert np.max(np.abs(y[:7900])) < 0.05 * np.max(np.abs(y))   # nothing arrives before the burst
        env = np.convolve(y.astype(np.float64) ** 2, np.ones(160), "same")
        assert 7900 <= int(np.argmax(env)) <= 8600   # the loudest 10 ms are the burst's own (direct path)


def test_the_draw_is_within_the_ranges():
    y, draw = apply_room(_speechlike(), SR, np.random.default_rng(3), rt60=(0.3, 0.4), channel=True,
                         low_hz=(300.0, 300.0), high_hz=(3400.0, 3400.0), return_draw=True)
    assert 0.3 <= draw.rt60 <= 0.4 and draw.low_hz == 300.0 and draw.high_hz == 3400.0
    assert -3 <= draw.tilt_db <= 3 and 20 <= draw.snr_db <= 40
    assert apply_room(_speechlike(), SR, np.random.default_rng(3), channel=False, return_draw=True)[1].low_hz is None


def test_the_channel_band_limits():
    x = np.random.default_rng(0).standard_normal(SR)
    y = apply_channel(x, SR, low_hz=300.0, high_hz=3400.0)
    spec = np.abs(np.fft.rfft(y)) ** 2
    f = np.fft.rfftfreq(len(y), 1 / SR)
    band = spec[(f > 600) & (f < 2500)].mean()
    assert spec[f < 80].mean() < 0.01 * band
    assert spec[f > 6500].mean() < 0.01 * band


@pytest.mark.parametrize("channel", [False, True])
@pytest.mark.parametrize("n", [0, 1, 20, SR])
def test_silence_and_tiny_inputs_give_finite_output(channel, n):
    y = apply_room(np.zeros(n, np.float32), SR, np.random.default_rng(0), channel=channel)
    assert y.shape == (n,) and np.all(np.isfinite(y)) and not np.any(y)


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError):
        room_impulse_response(SR, 0.0, np.random.default_rng(0))
    with pytest.raises(ValueError):
        room_impulse_response(SR, 0.5, np.random.default_rng(0), darkening=1.0)
    with pytest.raises(ValueError):
        apply_room(np.zeros((2, 100)), SR, np.random.default_rng(0))
