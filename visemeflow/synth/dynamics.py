"""Ground-truth viseme dynamics: a model of another family than the procedural rules.

The procedural rules (JALI-like, `visemeflow.procedural`) are piecewise: onset, apex, sustain, decay per
phone, combined by a maximum. The "true" curves of the synthetic corpus come instead from
Cohen-Massaro coarticulation (Cohen & Massaro 1993): every phone has a dominance function that rises
and falls exponentially around the phone's centre, and at each instant each viseme's weight is its
share of the total dominance, a neutral "rest" dominance included. The articulators then follow that
target through a critically damped second-order system (they have mass), and a little band-limited
jitter is added. Each speaker has its own articulation strength, timing offset, anticipation and
carry-over rates and articulator stiffness, drawn from the speaker name and a seed. Procedural curves
are therefore a plausible but imperfect guess of these curves, as in the paper.
"""

import zlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from visemeflow.phonetics.types import VisemeSegment
from visemeflow.visemes import N_VISEMES, VISEME_INDEX
from visemeflow.synth.config import GroundTruthConfig  # noqa: F401 (re-exported)

CLOSURES = frozenset({"MBP", "FFF"})
TONGUE_ONLY = frozenset({"LNTD", "GK", "TTH"})



@dataclass(frozen=True)
class SpeakerStyle:
    """How one speaker articulates (drawn once per speaker and seed)."""

    strength: float
    timing_shift_s: float
    anticipation_s: float
    carryover_s: float
    stiffness_hz: float


def _rng(*keys: object) -> np.random.Generator:
    return np.random.default_rng([zlib.crc32(str(k).encode()) for k in keys])


def speaker_style(speaker: str, config: GroundTruthConfig) -> SpeakerStyle:
    """The articulation style of `speaker`, the same in every process for the same seed."""
    rng = _rng("speaker", speaker, config.seed)
    return SpeakerStyle(
        strength=float(rng.uniform(*config.strength)),
        timing_shift_s=float(rng.normal(0.0, config.timing_shift_s)),
        anticipation_s=float(rng.uniform(*config.anticipation_s)),
        carryover_s=float(rng.uniform(*config.carryover_s)),
        stiffness_hz=float(rng.uniform(*config.stiffness_hz)),
    )


def dominance_targets(
    segments: Sequence[VisemeSegment], times_s: np.ndarray, style: SpeakerStyle, config: GroundTruthConfig
) -> np.ndarray:
    """Target curves (len(times), 16): each viseme's share of the total dominance at each time."""
    dominance = np.full((len(times_s), N_VISEMES), 0.0)
    targets = np.zeros(N_VISEMES)
    for seg in segments:
        centre = 0.5 * (seg.start_s + seg.end_s) - style.timing_shift_s
        half = 0.5 * seg.duration_s
        dt = times_s - centre
        # flat inside the phone, flanks before (anticipation) and after (carry-over) it
        # closures are sharp and strong: the lips close fully but only around the closure itself
        sharp = config.closure_sharpness if seg.viseme in CLOSURES else 1.0
        p = config.flank_power
        before = np.exp(-((np.maximum(-dt - half, 0.0) / (style.anticipation_s * sharp)) ** p))
        after = np.exp(-((np.maximum(dt - half, 0.0) / (style.carryover_s * sharp)) ** p))
        d = np.where(dt < 0, before, after)
        if seg.viseme in CLOSURES:
            d *= config.closure_dominance
        dominance[:, VISEME_INDEX[seg.viseme]] += d
    for name, i in VISEME_INDEX.items():
        if name in CLOSURES:
            targets[i] = 1.0
        elif name in TONGUE_ONLY:
            targets[i] = config.tongue_weight * style.strength
        else:
            targets[i] = style.strength
    total = dominance.sum(axis=1, keepdims=True) + config.rest_dominance
    return dominance / total * targets


def second_order_response(target: np.ndarray, rate_hz: float, stiffness_hz: float, damping: float) -> np.ndarray:
    """Curves (T, 16) following `target` sampled at `rate_hz` through a damped spring (semi-implicit Euler)."""
    omega = 2.0 * np.pi * stiffness_hz
    dt = 1.0 / rate_hz
    x = target[0].copy()
    v = np.zeros_like(x)
    out = np.empty_like(target)
    for k in range(len(target)):
        v += dt * (omega * omega * (target[k] - x) - 2.0 * damping * omega * v)
        x += dt * v
        out[k] = x
    return out


def _smooth(values: np.ndarray, a: float) -> np.ndarray:
    """One-pole low-pass y_k = a y_{k-1} + (1 - a) x_k run forward then backward (zero phase), along axis 0."""
    out = values.copy()
    for direction in (1, -1):
        seq = out[::direction]
        for k in range(1, len(seq)):
            seq[k] = a * seq[k - 1] + (1 - a) * seq[k]
    return out


def band_limited_noise(
    rng: np.random.Generator, n: int, rate_hz: float, cutoff_hz: float, dims: int = N_VISEMES
) -> np.ndarray:
    """(n, dims) zero-mean noise low-passed to `cutoff_hz`, scaled to unit standard deviation in expectation.

    The scale comes from the filter's impulse response, not from the sample: a short clip gets a short stretch of
    the same process (slowly varying, small), not noise blown up to unit variance.
    """
    a = float(np.exp(-2.0 * np.pi * cutoff_hz / rate_hz))
    span = int(np.ceil(20.0 / max(1.0 - a, 1e-6)))
    impulse = np.zeros((2 * span + 1, 1))
    impulse[span] = 1.0
    gain = float(np.sqrt((_smooth(impulse, a) ** 2).sum()))
    # warm-up stretches on both sides, cut off again, so the kept samples are stationary (the filter's start-up
    # transient would otherwise leave raw white noise in the first samples)
    padded = _smooth(rng.standard_normal((n + 2 * span, dims)), a)
    return padded[span:span + n] / gain


def generate_ground_truth(
    segments: Sequence[VisemeSegment], n_frames: int, fps: float, speaker: str, utterance_id: str,
    config: GroundTruthConfig = GroundTruthConfig(),
) -> np.ndarray:
    """True viseme curves (n_frames, 16) float32 in [0, 1], frame k at k / fps; reproducible from the seed."""
    style = speaker_style(speaker, config)
    rate = config.internal_rate_hz
    duration = n_frames / fps
    times = np.arange(int(np.ceil(duration * rate)) + 2) / rate
    target = dominance_targets(segments, times, style, config)
    response = second_order_response(target, rate, style.stiffness_hz, config.damping)
    if config.jitter > 0:
        noise = band_limited_noise(_rng("jitter", utterance_id, config.seed), len(times), rate, config.jitter_hz)
        response = response + config.jitter * noise * (response > 0.02)
    frame_times = np.arange(n_frames) / fps
    curves = np.stack([np.interp(frame_times, times, response[:, i]) for i in range(N_VISEMES)], axis=1)
    return np.clip(curves, 0.0, 1.0).astype(np.float32)
