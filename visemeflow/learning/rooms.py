"""Synthetic rooms and channels for training audio: the same utterance as heard in a reverberant room and through a
band-limited, equalised, slightly noisy channel (a telephone, a cheap microphone, a game's voice track).

Numpy/scipy only; every draw comes from the ``numpy.random.Generator`` passed in, so a seeded generator gives the
same audio in every run and process. Nothing here moves speech in time: the room's direct path sits at sample 0
(the reverberant tail only follows it), the channel's filters are zero-phase (``sosfiltfilt``), and the output is
trimmed to the input's length, so an utterance's target curves stay valid unchanged.

* :func:`room_impulse_response`: a direct path (1 at sample 0) plus a tail of Gaussian noise from ``predelay_s``
  whose amplitude decays as ``exp(-3 ln(10) t / rt60)`` (energy falls 60 dB in ``rt60`` seconds), scaled to the
  direct-to-reverberant energy ratio ``drr_db``; optionally darkened as it decays (high frequencies die sooner, as in
  a real room with absorbing surfaces).
* :func:`apply_channel`: a zero-phase band-pass (e.g. 300-3400 Hz for a telephone), a random smooth EQ tilt and
  white noise at a signal-to-noise ratio.
* :func:`apply_room`: both, with every parameter drawn from its range; the output has the input's RMS level.
* :func:`estimate_rt60`: RT60 of an impulse response from its Schroeder energy decay curve (a T20 fit).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import signal

__all__ = ["RoomDraw", "apply_channel", "apply_room", "estimate_rt60", "room_impulse_response"]

_DECAY = 3.0 * math.log(10.0)   # amplitude exp(-_DECAY t / rt60): energy -60 dB at t = rt60


def room_impulse_response(sample_rate: int, rt60: float, rng: np.random.Generator, *, drr_db: float = 3.0,
                          predelay_s: float = 0.005, darkening: float = 0.0) -> np.ndarray:
    """A synthetic room impulse response (float64, ``predelay_s + rt60`` s long): 1 at sample 0 (the direct path),
    then exponentially decaying Gaussian noise whose energy is ``drr_db`` below the direct path's.

    ``darkening`` in [0, 1): each sample of the tail passes a one-pole low-pass whose coefficient grows from 0 to
    ``darkening`` along the tail (a later reflection is duller); 0 leaves the tail white."""
    if rt60 <= 0 or sample_rate <= 0:
        raise ValueError(f"rt60 and sample_rate must be positive, got {rt60}, {sample_rate}")
    if not 0.0 <= darkening < 1.0:
        raise ValueError(f"darkening must be in [0, 1), got {darkening}")
    start = max(1, int(round(predelay_s * sample_rate)))
    n_tail = max(1, int(round(rt60 * sample_rate)))
    t = np.arange(n_tail) / sample_rate
    tail = rng.standard_normal(n_tail) * np.exp(-_DECAY * t / rt60)
    if darkening > 0:
        coef = darkening * np.linspace(0.0, 1.0, n_tail)
        out, y = np.empty(n_tail), 0.0
        for i in range(n_tail):   # time-varying one-pole low-pass, gain-normalised at DC
            y = coef[i] * y + (1.0 - coef[i]) * tail[i]
            out[i] = y
        # restore each stretch's energy, so the low-pass changes the colour and not the decay
        tail = out * np.sqrt((1.0 + coef) / np.maximum(1.0 - coef, 1e-6))
    tail *= math.sqrt(10.0 ** (-drr_db / 10.0) / max(float(np.sum(tail ** 2)), 1e-20))
    h = np.zeros(start + n_tail)
    h[0] = 1.0
    h[start:] = tail
    return h


def estimate_rt60(h: np.ndarray, sample_rate: int, *, skip: int = 0, fit_db: tuple[float, float] = (-5.0, -25.0)
                  ) -> float:
    """RT60 (s) of an impulse response from ``h[skip:]``: Schroeder backward integration, a line fitted to the
    energy decay curve between ``fit_db`` and extrapolated to -60 dB (T20 by default)."""
    e = np.asarray(h, np.float64)[skip:] ** 2
    edc = np.cumsum(e[::-1])[::-1]
    edc_db = 10.0 * np.log10(np.maximum(edc / max(edc[0], 1e-300), 1e-30))
    hi, lo = fit_db
    idx = np.nonzero((edc_db <= hi) & (edc_db >= lo))[0]
    if len(idx) < 2:
        raise ValueError("the decay curve does not span the fit range")
    slope = np.polyfit(idx / sample_rate, edc_db[idx], 1)[0]   # dB per second
    return float(-60.0 / slope)


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x, dtype=np.float64)))) if len(x) else 0.0


def apply_channel(audio: np.ndarray, sample_rate: int, *, low_hz: float | None = 300.0,
                  high_hz: float | None = 3400.0, tilt_db: float = 0.0, snr_db: float | None = None,
                  rng: np.random.Generator | None = None) -> np.ndarray:
    """``audio`` through a channel: a 2nd-order Butterworth high-pass at ``low_hz`` and low-pass at ``high_hz``
    (None: no such edge), each run forward and backward (zero-phase, 4th order in magnitude), a spectral tilt of ``tilt_db`` per octave around 1 kHz (zero-phase, a gain
    curve on the FFT), and white noise ``snr_db`` below the filtered signal's RMS (None: none; needs ``rng``)."""
    x = np.asarray(audio, np.float64)
    nyq = sample_rate / 2.0
    if len(x) > 27:   # sosfiltfilt's default padding needs a few samples more than 3 x (2 x sections)
        if low_hz is not None and 0 < low_hz < nyq:
            x = signal.sosfiltfilt(signal.butter(2, low_hz, "highpass", fs=sample_rate, output="sos"), x)
        if high_hz is not None and 0 < high_hz < nyq:
            x = signal.sosfiltfilt(signal.butter(2, high_hz, "lowpass", fs=sample_rate, output="sos"), x)
    if tilt_db and len(x):
        f = np.fft.rfftfreq(len(x), 1.0 / sample_rate)
        octaves = np.log2(np.maximum(f, 50.0) / 1000.0)
        x = np.fft.irfft(np.fft.rfft(x) * 10.0 ** (tilt_db * octaves / 20.0), n=len(x))
    if snr_db is not None:
        if rng is None:
            raise ValueError("noise needs an rng")
        x = x + rng.standard_normal(len(x)) * _rms(x) * 10.0 ** (-snr_db / 20.0)
    return x


@dataclass(frozen=True)
class RoomDraw:
    """The parameters :func:`apply_room` drew (channel fields None when no channel was applied)."""

    rt60: float
    drr_db: float
    predelay_s: float
    darkening: float
    low_hz: float | None = None
    high_hz: float | None = None
    tilt_db: float | None = None
    snr_db: float | None = None


def apply_room(audio: np.ndarray, sample_rate: int, rng: np.random.Generator, *,
               rt60: tuple[float, float] = (0.2, 0.8), drr_db: tuple[float, float] = (-3.0, 10.0),
               predelay_s: tuple[float, float] = (0.002, 0.012), darkening: tuple[float, float] = (0.0, 0.6),
               channel: bool = False, low_hz: tuple[float, float] = (80.0, 400.0),
               high_hz: tuple[float, float] = (3000.0, 7500.0), tilt_db: tuple[float, float] = (-3.0, 3.0),
               snr_db: tuple[float, float] = (20.0, 40.0), return_draw: bool = False):
    """``audio`` (mono, float) as heard in a synthetic room, each parameter drawn uniformly from its range with
    ``rng``: RT60 (s), direct-to-reverberant ratio (dB), pre-delay (s) and darkening of the tail
    (:func:`room_impulse_response`); with ``channel``, then a band-pass (``low_hz``, ``high_hz``), EQ tilt (dB per
    octave) and white noise at ``snr_db`` (:func:`apply_channel`). FFT convolution, trimmed to the input's length;
    the output (float32) has the input's RMS level (silence stays silence). ``return_draw``: also the
    :class:`RoomDraw`."""
    x = np.asarray(audio, np.float64)
    if x.ndim != 1:
        raise ValueError(f"audio must be mono (1-D), got shape {x.shape}")
    draw = RoomDraw(float(rng.uniform(*rt60)), float(rng.uniform(*drr_db)), float(rng.uniform(*predelay_s)),
                    float(rng.uniform(*darkening)))
    h = room_impulse_response(sample_rate, draw.rt60, rng, drr_db=draw.drr_db, predelay_s=draw.predelay_s,
                              darkening=draw.darkening)
    y = signal.fftconvolve(x, h)[: len(x)] if len(x) else x.copy()
    if channel:
        draw = RoomDraw(draw.rt60, draw.drr_db, draw.predelay_s, draw.darkening, float(rng.uniform(*low_hz)),
                        float(rng.uniform(*high_hz)), float(rng.uniform(*tilt_db)), float(rng.uniform(*snr_db)))
        y = apply_channel(y, sample_rate, low_hz=draw.low_hz, high_hz=draw.high_hz, tilt_db=draw.tilt_db,
                          snr_db=draw.snr_db, rng=rng)
    level_in, level_out = _rms(x), _rms(y)
    y = y * (level_in / level_out) if level_out > 0 else np.zeros_like(y)
    y = np.nan_to_num(y, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
    return (y, draw) if return_draw else y
