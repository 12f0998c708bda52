"""Audio augmentations of the robustness evaluation (paper Section 5.2) and for training.

Pure numpy/librosa: no Prefect, no files. The paper augments the validation set "by randomly
adjusting the pitch in the range of -3 semitone to 3 semitones, volume in the range of -10 dB to
+10 dB, speed in the range of 0.7 to 1.3, and add[ing] additional Gaussian noise with amplitude
smaller than 0.005"; those ranges are the :class:`AugmentConfig` defaults. One condition is
applied at a time:

* ``volume``: multiply by ``10 ** (dB / 20)``, so the RMS level changes by exactly ``dB``. The
  result is **not clipped**: at +10 dB it may leave [-1, 1]. The models take float audio, so this
  keeps the gain exact; whoever writes the audio to a PCM file must clip (or normalise) there.
* ``pitch``: ``librosa.effects.pitch_shift`` by ``value`` semitones; the length is unchanged.
* ``speed``: ``librosa.effects.time_stretch`` with ``rate=value`` (> 1 is faster, i.e. shorter);
  pitch is kept. The output has exactly ``round(len(audio) / value)`` samples (padded / trimmed),
  the frame count :func:`visemeflow.learning.train.resample_curves` gives the curves for the same
  ``time_factor``, so audio and targets stay aligned. ``time_factor`` is ``value``.
* ``noise``: add ``value * N(0, 1)`` per sample, i.e. white Gaussian noise whose **standard
  deviation** (on audio in -1..1) is ``value``; we read the paper's "amplitude smaller than
  0.005" as that standard deviation, drawn uniformly in ``[0, 0.005]``.

Both librosa effects use an STFT of about 32 ms (``n_fft`` = the power of two nearest to
``0.032 * sample_rate``: 512 at 16 kHz, hop ``n_fft // 4``) rather than librosa's music default of
2048 samples: a speech-sized window smears transients less, which keeps a sped-up utterance aligned
to its curves within a fraction of a frame. Inputs shorter than ``n_fft`` are zero-padded first and
trimmed after. Every operation is deterministic (same inputs -> bit-identical float32 output).

Evaluation (:func:`augment_utterance`): the value of condition ``c`` for utterance ``u`` and seed
``s`` comes from a numpy Generator seeded with ``sha256("value", u, c, s)`` (:func:`draw_value`),
the noise samples from one seeded with ``sha256("noise", u, c, s)``; so the augmented validation
set is the same in every run and process. Training (:func:`train_augment_hook`): a picklable
callable ``(audio, rng) -> (audio, time_factor)`` for ``train_model(..., augment_audio=...)``.

Augmented ids (:func:`augmented_id`) are ``<speaker>/<name>__<condition>_<value>``:

* ``spk/utt__volume_m3.52`` (-3.52 dB), ``spk/utt__pitch_p2.10`` (+2.10 semitones): signed
  conditions write the sign as ``p`` / ``m`` and 2 decimals;
* ``spk/utt__speed_1.124`` (3 decimals), ``spk/utt__noise_0.00312`` (std, 5 decimals).

Only letters, digits, ``_``, ``-`` and ``.`` are allowed in id parts
(:func:`visemeflow.schemas.validate_utterance_id`), hence no ``~`` or ``+``. The id shows the
value rounded; :attr:`Augmented.value` holds the exact value applied. :func:`source_id` strips the
last such suffix (it is anchored at the end of the id, so a name that itself contains ``__`` still
round-trips) and returns an id without one unchanged.
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from visemeflow.learning.config import CONDITIONS, AugmentConfig, _check_condition  # noqa: F401 (re-exported)
from visemeflow.schemas.ids import validate_utterance_id

__all__ = [
    "CONDITIONS",
    "DEFAULT_CONFIG",
    "AugmentConfig",
    "Augmented",
    "TrainAugment",
    "apply_condition",
    "augment_utterance",
    "augmented_id",
    "draw_value",
    "parse_augmented_id",
    "source_id",
    "train_augment_hook",
]


# id suffix: decimals per condition and whether the sign is written (p / m)
_DECIMALS = {"volume": 2, "pitch": 2, "speed": 3, "noise": 5}
_SIGNED = {"volume": True, "pitch": True, "speed": False, "noise": False}
_SUFFIX = re.compile(
    r"^(?P<source>.+)__(?P<condition>volume|pitch|speed|noise)_(?P<sign>[pm]?)(?P<number>\d+\.\d+)$"
)


# --------------------------------------------------------------------------------------------------
# configuration


DEFAULT_CONFIG = AugmentConfig()  # the paper's ranges (frozen, so safe as a shared default)


# --------------------------------------------------------------------------------------------------
# deterministic draws


def _seeded_rng(purpose: str, utterance_id: str, condition: str, seed: int) -> np.random.Generator:
    """Generator seeded by sha256 of (purpose, utterance, condition, seed): stable across processes."""
    key = "\x1f".join((purpose, utterance_id, condition, str(int(seed)))).encode("utf-8")
    digest = hashlib.sha256(key).digest()
    return np.random.default_rng(int.from_bytes(digest[:16], "little"))


def draw_value(condition: str, utterance_id: str, seed: int, config: AugmentConfig = DEFAULT_CONFIG) -> float:
    """The value of ``condition`` for ``utterance_id`` under ``seed``: uniform in its range, deterministic."""
    low, high = config.range_of(condition)
    return float(_seeded_rng("value", utterance_id, condition, seed).uniform(low, high))


# --------------------------------------------------------------------------------------------------
# ids


def augmented_id(utterance_id: str, condition: str, value: float) -> str:
    """``<utterance_id>__<condition>_<value>`` (see the module docstring); a valid utterance id."""
    validate_utterance_id(utterance_id)
    _check_condition(condition)
    if not math.isfinite(value):
        raise ValueError(f"augmentation value must be finite, got {value}")
    decimals = _DECIMALS[condition]
    rounded = round(float(value), decimals)
    if _SIGNED[condition]:
        text = ("m" if rounded < 0 else "p") + f"{abs(rounded):.{decimals}f}"
    else:
        if rounded < 0:
            raise ValueError(f"{condition} value must be >= 0, got {value}")
        text = f"{rounded:.{decimals}f}"
    return validate_utterance_id(f"{utterance_id}__{condition}_{text}")


def parse_augmented_id(augmented: str) -> tuple[str, str, float] | None:
    """``(source_id, condition, rounded value)`` of an augmented id; None for an id without a suffix."""
    m = _SUFFIX.match(augmented)
    if m is None or "/" not in m["source"]:
        return None
    if bool(m["sign"]) != _SIGNED[m["condition"]]:
        return None
    value = float(m["number"]) * (-1.0 if m["sign"] == "m" else 1.0)
    return m["source"], m["condition"], value


def source_id(augmented: str) -> str:
    """The utterance id an augmented id was made from (``augmented`` itself if it has no suffix)."""
    parsed = parse_augmented_id(augmented)
    return augmented if parsed is None else parsed[0]


# --------------------------------------------------------------------------------------------------
# signal processing


def _n_fft(sample_rate: int) -> int:
    """Power of two nearest to 32 ms (512 at 16 kHz)."""
    return int(2 ** round(math.log2(0.032 * sample_rate)))


def _padded(audio: np.ndarray, n_fft: int) -> np.ndarray:
    return np.pad(audio, (0, n_fft - audio.shape[0])) if audio.shape[0] < n_fft else audio


def _fit_length(audio: np.ndarray, n: int) -> np.ndarray:
    if audio.shape[0] >= n:
        return audio[:n]
    return np.pad(audio, (0, n - audio.shape[0]))


def _pitch(audio: np.ndarray, sample_rate: int, semitones: float) -> np.ndarray:
    import librosa

    n = audio.shape[0]
    if n == 0:
        return audio
    n_fft = _n_fft(sample_rate)
    out = librosa.effects.pitch_shift(
        _padded(audio, n_fft), sr=sample_rate, n_steps=float(semitones), n_fft=n_fft
    )
    return _fit_length(out, n)


def _speed(audio: np.ndarray, sample_rate: int, factor: float) -> np.ndarray:
    import librosa

    n_out = round(audio.shape[0] / factor)
    if audio.shape[0] == 0:
        return audio
    n_fft = _n_fft(sample_rate)
    out = librosa.effects.time_stretch(_padded(audio, n_fft), rate=float(factor), n_fft=n_fft)
    return _fit_length(out, n_out)


def apply_condition(
    audio: np.ndarray,
    sample_rate: int,
    condition: str,
    value: float,
    rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, float]:
    """``(augmented float32 audio, time_factor)``: ``condition`` applied with ``value``.

    ``time_factor`` is ``value`` for ``speed`` (resample the curves with it) and 1.0 otherwise.
    ``noise`` needs ``rng`` (its samples come from it). No clipping (see the module docstring).
    """
    _check_condition(condition)
    audio = np.asarray(audio, dtype=np.float32)
    if audio.ndim != 1:
        raise ValueError(f"audio must be mono (samples,), got shape {audio.shape}")
    if sample_rate <= 0:
        raise ValueError(f"sample_rate must be positive, got {sample_rate}")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{condition} value must be finite, got {value}")

    if condition == "volume":
        out = audio * np.float32(10.0 ** (value / 20.0))
        return out.astype(np.float32, copy=False), 1.0
    if condition == "pitch":
        return _pitch(audio, sample_rate, value).astype(np.float32, copy=False), 1.0
    if condition == "speed":
        if value <= 0:
            raise ValueError(f"speed factor must be > 0, got {value}")
        return _speed(audio, sample_rate, value).astype(np.float32, copy=False), value
    # noise
    if value < 0:
        raise ValueError(f"noise std must be >= 0, got {value}")
    if rng is None:
        raise ValueError("condition 'noise' needs an rng (numpy Generator) for the noise samples")
    noise = rng.standard_normal(audio.shape[0]) * value
    return (audio.astype(np.float64) + noise).astype(np.float32), 1.0


# --------------------------------------------------------------------------------------------------
# evaluation: one deterministic augmented copy per (utterance, condition, seed)


@dataclass(frozen=True)
class Augmented:
    """An augmented utterance: float32 audio, its curve time factor, and where it came from."""

    audio: np.ndarray
    time_factor: float  # resample the target curves with this (resample_curves); 1.0 but for speed
    value: float  # exact value applied (dB, semitones, speed factor or noise std)
    condition: str
    utterance_id: str  # the augmented id (augmented_id)
    source_id: str  # the original utterance id


def augment_utterance(
    audio: np.ndarray,
    sample_rate: int,
    utterance_id: str,
    condition: str,
    seed: int,
    config: AugmentConfig = DEFAULT_CONFIG,
) -> Augmented:
    """``condition`` applied to one utterance with its :func:`draw_value` value; deterministic."""
    value = draw_value(condition, utterance_id, seed, config)
    rng = _seeded_rng("noise", utterance_id, condition, seed) if condition == "noise" else None
    out, factor = apply_condition(audio, sample_rate, condition, value, rng)
    return Augmented(
        audio=out,
        time_factor=factor,
        value=value,
        condition=condition,
        utterance_id=augmented_id(utterance_id, condition, value),
        source_id=utterance_id,
    )


# --------------------------------------------------------------------------------------------------
# training hook


@dataclass(frozen=True)
class TrainAugment:
    """``(audio, rng) -> (audio, time_factor)`` for ``train_model(..., augment_audio=...)``.

    Per call: ``rng.random() < probability`` decides whether to augment; if so, one of
    ``conditions`` is chosen uniformly (``rng.integers``), its value uniformly in its range
    (``rng.uniform``) and, for noise, the noise samples also come from ``rng``. Otherwise the
    audio is returned unchanged (the same object) with factor 1.0. Deterministic given the rng state.
    A plain frozen dataclass, so it pickles (e.g. as a Prefect task argument).
    """

    config: AugmentConfig = DEFAULT_CONFIG
    conditions: tuple[str, ...] = CONDITIONS
    probability: float = 0.5
    sample_rate: int = 16000

    def __post_init__(self) -> None:
        object.__setattr__(self, "conditions", tuple(self.conditions))
        if not self.conditions:
            raise ValueError("conditions must not be empty")
        for c in self.conditions:
            _check_condition(c)
        if not 0.0 <= self.probability <= 1.0:
            raise ValueError(f"probability must be in [0, 1], got {self.probability}")
        if self.sample_rate <= 0:
            raise ValueError(f"sample_rate must be positive, got {self.sample_rate}")

    def __call__(self, audio: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, float]:
        if not rng.random() < self.probability:
            return audio, 1.0
        condition = self.conditions[int(rng.integers(len(self.conditions)))]
        low, high = self.config.range_of(condition)
        value = float(rng.uniform(low, high))
        return apply_condition(audio, self.sample_rate, condition, value, rng)


def train_augment_hook(
    config: AugmentConfig = DEFAULT_CONFIG,
    conditions: Sequence[str] = CONDITIONS,
    probability: float = 0.5,
    sample_rate: int = 16000,
) -> TrainAugment:
    """The training augmentation hook (see :class:`TrainAugment`)."""
    return TrainAugment(config=config, conditions=tuple(conditions), probability=probability, sample_rate=sample_rate)
