"""Audio-features -> viseme-curve mapping models (paper Section 5.1, Tables 2 and 3).

Everything here works on *precomputed* audio features ``(B, T_feat, D)`` at a known feature frame
rate; a feature module (anything with ``forward(audio, lengths) -> (features, feat_lengths)`` and a
``frame_rate_hz`` attribute) can be put in front with :class:`AudioCurveModel`.

Common calling convention of every model in this module::

    curves, mask = model(features, feat_lengths, n_frames, targets=None)

* ``features`` (B, T_feat, D) float, padded past ``feat_lengths`` (B,) with anything;
* ``n_frames`` (B,) long: how many curve frames to produce for each utterance (known from the
  tracked curves in training, from the audio duration at inference: :func:`frames_for_duration`);
* ``targets`` (B, T_max, 16): only used by the autoregressive :class:`FaceFormerDecoder` (teacher
  forcing); the other models ignore it;
* returns ``curves`` (B, T_max, 16) with ``T_max = n_frames.max()``, zero at padded frames, and
  ``mask`` (B, T_max) bool, True on valid frames.

Output activation: the paper's model is ``Y = f_FC(f_BLSTM(U_3))`` trained with L1, i.e. a plain
linear output, so the default is ``output="linear"`` (raw values; clip to [0, 1] before driving a
rig). ``output="sigmoid"`` squashes the outputs into (0, 1) for users who want that guarantee.

Padding: every model gives an utterance in a padded batch the same output as the utterance alone
(LSTMs use packed sequences, the TCN zeroes padded frames before every convolution, the
transformers use key padding / causal masks, interpolation and windows never read past a length).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor, nn
from torch.nn.utils.rnn import pack_padded_sequence, pad_packed_sequence

from visemeflow.timebase import DEFAULT_FPS
from visemeflow.visemes import N_VISEMES

DecoderKind = Literal["blstm", "lstm", "tcn", "transformer"]


# --------------------------------------------------------------------------------------------------
# configuration


class DecoderConfig(BaseModel):
    """Sequence decoder of :class:`CurveModel`; Table 2 compares the four kinds at l = 1, D = 512."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: DecoderKind = "blstm"
    layers: int = Field(1, ge=1)
    width: int = Field(512, ge=2)  # D: hidden/output width of the decoder (= d_model in the paper)
    dropout: float = Field(0.0, ge=0.0, lt=1.0)
    tcn_kernel: int = Field(5, ge=1)
    heads: int = Field(8, ge=1)


class ModelConfig(BaseModel):
    """:class:`CurveModel` configuration (paper: wav2vec2 D_W = 1024 -> D = 512, one BLSTM layer)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    feature_dim: int = Field(ge=1)
    feature_rate_hz: float = Field(gt=0)
    curve_fps: float = Field(DEFAULT_FPS, gt=0)
    d_model: int = Field(512, ge=2)
    decoder: DecoderConfig = DecoderConfig()
    ppe_period_frames: int | None = Field(None, ge=1)  # None: round(curve_fps), FaceFormer's p
    output: Literal["linear", "sigmoid"] = "linear"

    def ppe_period(self, fps: float | None = None) -> int:
        if self.ppe_period_frames is not None:
            return self.ppe_period_frames
        return max(1, round(fps if fps is not None else self.curve_fps))


# --------------------------------------------------------------------------------------------------
# building blocks


def frames_for_duration(n_samples_or_frames: Tensor | int, rate_hz: float, fps: float) -> Tensor:
    """Number of curve frames covering ``n`` items sampled at ``rate_hz`` (rounded): 200 @ 100 Hz -> 50 @ 25 fps."""
    n = torch.as_tensor(n_samples_or_frames, dtype=torch.float64)
    return torch.round(n * (fps / rate_hz)).to(torch.long)


def length_mask(lengths: Tensor, max_len: int | None = None) -> Tensor:
    """(B, max_len) bool, True where the time index is < the utterance's length."""
    lengths = lengths.to(torch.long)
    t_max = int(lengths.max().item()) if max_len is None else max_len
    return torch.arange(t_max, device=lengths.device)[None, :] < lengths[:, None]


def periodic_positional_encoding(n_frames: int, d_model: int, period: int) -> Tensor:
    """FaceFormer's periodic positional encoding: the sinusoidal encoding of ``t mod period``.

    ``PPE(t, 2i) = sin((t mod p) / 10000^(2i/d))``, ``PPE(t, 2i+1) = cos(...)``; returns (n_frames, d_model).
    Rows repeat with period ``p`` and are distinct within one period.
    """
    if period < 1:
        raise ValueError(f"period must be >= 1, got {period}")
    pos = (torch.arange(n_frames, dtype=torch.float64) % period)[:, None]
    i = torch.arange(0, d_model, 2, dtype=torch.float64)
    div = torch.exp(-math.log(10000.0) * i / d_model)
    pe = torch.zeros(n_frames, d_model, dtype=torch.float64)
    pe[:, 0::2] = torch.sin(pos * div)
    pe[:, 1::2] = torch.cos(pos * div[: d_model // 2])
    return pe.to(torch.float32)


def interpolate_to_frames(
    x: Tensor, lengths: Tensor, n_frames: Tensor, src_rate_hz: float, dst_fps: float
) -> Tensor:
    """f_interp: linear interpolation along time from ``src_rate_hz`` to ``dst_fps``.

    Output frame ``k`` (time ``k / dst_fps``) reads source position ``k * src_rate / dst_fps`` (source
    frame ``i`` sits at time ``i / src_rate``), clamped to the utterance's last valid source frame, so
    padding is never read. Returns (B, max(n_frames), D), zero past each ``n_frames``.
    """
    b, t_src, _ = x.shape
    n_frames = n_frames.to(device=x.device, dtype=torch.long)
    lengths = lengths.to(device=x.device, dtype=torch.long)
    t_out = int(n_frames.max().item()) if b else 0
    k = torch.arange(t_out, device=x.device, dtype=torch.float64)
    pos = (k * (src_rate_hz / dst_fps))[None, :].expand(b, t_out)
    last = (lengths.clamp(min=1, max=t_src) - 1).to(torch.float64)[:, None]
    pos = torch.minimum(pos, last)
    i0 = torch.floor(pos).to(torch.long)
    i1 = torch.minimum(i0 + 1, last.to(torch.long))
    w = (pos - i0.to(torch.float64)).to(x.dtype)[..., None]
    g0 = torch.gather(x, 1, i0[..., None].expand(b, t_out, x.shape[2]))
    g1 = torch.gather(x, 1, i1[..., None].expand(b, t_out, x.shape[2]))
    out = g0 * (1 - w) + g1 * w
    return out * length_mask(n_frames, t_out)[..., None].to(x.dtype)


def l1_loss(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """Mean absolute error over valid frames and the 16 visemes (padding ignored)."""
    m = mask.to(pred.dtype)[..., None]
    n = m.sum() * pred.shape[-1]
    return ((pred - target).abs() * m).sum() / n.clamp(min=1)


def spec_augment(
    features: Tensor,
    lengths: Tensor,
    time_masks: int = 2,
    time_width: float = 0.05,
    freq_masks: int = 2,
    freq_width: float = 0.1,
    generator: torch.Generator | None = None,
    *,
    sample_widths: bool = False,
    fill: float | None = None,
    return_mask: bool = False,
) -> Tensor | tuple[Tensor, Tensor]:
    """SpecAugment (Park et al. 2019) on feature sequences, for training only.

    Each of ``time_masks`` masks covers ``round(time_width * length)`` consecutive valid frames (at
    least 1 when ``time_width > 0``) at a random start; each of ``freq_masks`` masks covers
    ``round(freq_width * D)`` consecutive feature channels over the valid frames. With
    ``sample_widths`` the widths are drawn uniformly from [0, that maximum] as in the original
    recipe. Masks may overlap. Masked entries get ``fill`` (default: the utterance's mean over its
    valid entries). Padded frames are never touched. Returns a new tensor (and the bool mask of the
    masked entries with ``return_mask``).
    """
    b, t, d = features.shape
    out = features.clone()
    masked = torch.zeros(b, t, d, dtype=torch.bool, device=features.device)

    def randint(low: int, high: int) -> int:  # inclusive low, exclusive high
        return int(torch.randint(low, high, (1,), generator=generator).item())

    for j in range(b):
        n = int(min(int(lengths[j]), t))
        if n <= 0:
            continue
        tw = round(time_width * n)
        tw = max(1, tw) if time_width > 0 else 0
        tw = min(tw, n)
        fw = min(round(freq_width * d), d)
        for _ in range(time_masks):
            w = randint(0, tw + 1) if sample_widths else tw
            if w <= 0:
                continue
            s = randint(0, n - w + 1)
            masked[j, s : s + w, :] = True
        for _ in range(freq_masks):
            w = randint(0, fw + 1) if sample_widths else fw
            if w <= 0:
                continue
            s = randint(0, d - w + 1)
            masked[j, :n, s : s + w] = True
        value = features[j, :n].mean() if fill is None else torch.tensor(fill, dtype=features.dtype)
        out[j] = torch.where(masked[j], value.to(features.dtype), out[j])
    return (out, masked) if return_mask else out


# --------------------------------------------------------------------------------------------------
# decoders (Table 2)


class _LSTMDecoder(nn.Module):
    def __init__(self, cfg: DecoderConfig, d_in: int, bidirectional: bool) -> None:
        super().__init__()
        if bidirectional and cfg.width % 2:
            raise ValueError("BLSTM width must be even (hidden = width / 2 per direction)")
        hidden = cfg.width // 2 if bidirectional else cfg.width
        self.lstm = nn.LSTM(
            d_in, hidden, num_layers=cfg.layers, batch_first=True, bidirectional=bidirectional,
            dropout=cfg.dropout if cfg.layers > 1 else 0.0,
        )

    def forward(self, x: Tensor, lengths: Tensor) -> Tensor:
        packed = pack_padded_sequence(x, lengths.clamp(min=1).cpu(), batch_first=True, enforce_sorted=False)
        out, _ = self.lstm(packed)
        out, _ = pad_packed_sequence(out, batch_first=True, total_length=x.shape[1])
        return out


class _TCNDecoder(nn.Module):
    """Non-causal dilated 1-D convolutions ('same' padding), dilation 2^i, ReLU, residual."""

    def __init__(self, cfg: DecoderConfig, d_in: int) -> None:
        super().__init__()
        self.inp = nn.Identity() if d_in == cfg.width else nn.Linear(d_in, cfg.width)
        self.convs = nn.ModuleList(
            nn.Conv1d(cfg.width, cfg.width, cfg.tcn_kernel, dilation=2**i, padding="same")
            for i in range(cfg.layers)
        )
        self.drop = nn.Dropout(cfg.dropout)

    def forward(self, x: Tensor, lengths: Tensor) -> Tensor:
        m = length_mask(lengths.to(x.device), x.shape[1]).to(x.dtype)[:, None, :]
        h = self.inp(x).transpose(1, 2)
        for conv in self.convs:
            h = h + self.drop(torch.relu(conv(h * m)))
        return (h * m).transpose(1, 2)


class _TransformerDecoder(nn.Module):
    """Transformer *encoder* stack (self-attention over the whole utterance, key padding mask)."""

    def __init__(self, cfg: DecoderConfig, d_in: int) -> None:
        super().__init__()
        self.inp = nn.Identity() if d_in == cfg.width else nn.Linear(d_in, cfg.width)
        layer = nn.TransformerEncoderLayer(
            cfg.width, cfg.heads, dim_feedforward=2 * cfg.width, dropout=cfg.dropout, batch_first=True
        )
        self.enc = nn.TransformerEncoder(layer, cfg.layers, enable_nested_tensor=False)

    def forward(self, x: Tensor, lengths: Tensor) -> Tensor:
        pad = ~length_mask(lengths.to(x.device), x.shape[1])
        return self.enc(self.inp(x), src_key_padding_mask=pad)


def build_decoder(cfg: DecoderConfig, d_in: int) -> nn.Module:
    """A decoder mapping (B, T, d_in) + lengths to (B, T, cfg.width)."""
    if cfg.kind == "blstm":
        return _LSTMDecoder(cfg, d_in, bidirectional=True)
    if cfg.kind == "lstm":
        return _LSTMDecoder(cfg, d_in, bidirectional=False)
    if cfg.kind == "tcn":
        return _TCNDecoder(cfg, d_in)
    if cfg.kind == "transformer":
        return _TransformerDecoder(cfg, d_in)
    raise ValueError(f"unknown decoder kind {cfg.kind!r}")


# --------------------------------------------------------------------------------------------------
# models


class _CurveHead(nn.Module):
    """Shared plumbing: frame rates, output activation, masking."""

    feature_rate_hz: float
    curve_fps: float
    output: str = "linear"

    def _fps(self, fps: float | None) -> float:
        return self.curve_fps if fps is None else fps

    def _finish(self, y: Tensor, n_frames: Tensor) -> tuple[Tensor, Tensor]:
        if self.output == "sigmoid":
            y = torch.sigmoid(y)
        mask = length_mask(n_frames.to(y.device), y.shape[1])
        return y * mask[..., None].to(y.dtype), mask


class CurveModel(_CurveHead):
    """The paper's mapping model: f_proj -> f_interp -> + PPE -> decoder -> f_FC (16 visemes)."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        self.feature_rate_hz = config.feature_rate_hz
        self.curve_fps = config.curve_fps
        self.output = config.output
        self.f_proj = nn.Linear(config.feature_dim, config.d_model)
        self.decoder = build_decoder(config.decoder, config.d_model)
        self.drop = nn.Dropout(config.decoder.dropout)
        self.f_fc = nn.Linear(config.decoder.width, N_VISEMES)

    def forward(
        self, features: Tensor, feat_lengths: Tensor, n_frames: Tensor,
        targets: Tensor | None = None, fps: float | None = None,
    ) -> tuple[Tensor, Tensor]:
        fps = self._fps(fps)
        n_frames = n_frames.to(torch.long)
        u2 = interpolate_to_frames(self.f_proj(features), feat_lengths, n_frames, self.feature_rate_hz, fps)
        t = u2.shape[1]
        ppe = periodic_positional_encoding(t, self.config.d_model, self.config.ppe_period(fps)).to(u2)
        u3 = u2 + ppe[None]
        h = self.drop(self.decoder(u3, n_frames))
        return self._finish(self.f_fc(h), n_frames)


class MeanCurveBaseline(_CurveHead):
    """Predicts the training set's mean curve vector (frame-weighted) for every frame."""

    def __init__(self, feature_rate_hz: float = 100.0, curve_fps: float = DEFAULT_FPS) -> None:
        super().__init__()
        self.feature_rate_hz = feature_rate_hz
        self.curve_fps = curve_fps
        self.register_buffer("mean", torch.zeros(N_VISEMES))

    def fit(self, curves_list: Sequence[Tensor | np.ndarray]) -> MeanCurveBaseline:
        total = torch.zeros(N_VISEMES, dtype=torch.float64)
        count = 0
        for c in curves_list:
            c = torch.as_tensor(np.asarray(c), dtype=torch.float64).reshape(-1, N_VISEMES)
            total += c.sum(0)
            count += c.shape[0]
        if count == 0:
            raise ValueError("no curve frames to fit")
        self.mean.copy_((total / count).to(self.mean.dtype))
        return self

    def forward(
        self, features: Tensor, feat_lengths: Tensor, n_frames: Tensor,
        targets: Tensor | None = None, fps: float | None = None,
    ) -> tuple[Tensor, Tensor]:
        n_frames = n_frames.to(torch.long)
        t = int(n_frames.max().item())
        y = self.mean.to(features.dtype)[None, None, :].expand(n_frames.shape[0], t, N_VISEMES)
        mask = length_mask(n_frames.to(y.device), t)
        return y * mask[..., None].to(y.dtype), mask


class KarrasConvNet(_CurveHead):
    """Karras et al. 2017-style window CNN, adapted to 16 viseme outputs.

    For every curve frame a window of ``window_frames`` feature frames centred on it (520 ms in the
    original: 64 frames of 8 ms; zeros outside the utterance) goes through a per-frame linear layer
    (standing in for the original "formant analysis" convolutions over the autocorrelation axis,
    since our feature dimension varies), then stride-2 kernel-3 convolutions along time until one
    time step is left ("articulation network"), then FC(channels -> hidden) -> ReLU -> FC(-> 16).
    The emotion input of the original is omitted (one speaker, neutral).
    """

    def __init__(
        self, feature_dim: int, feature_rate_hz: float, curve_fps: float = DEFAULT_FPS, channels: int = 256,
        hidden: int = 150, window_ms: float = 520.0, window_frames: int | None = None,
        dropout: float = 0.0, output: Literal["linear", "sigmoid"] = "linear",
    ) -> None:
        super().__init__()
        self.feature_rate_hz = feature_rate_hz
        self.curve_fps = curve_fps
        self.output = output
        self.window = window_frames or max(2, round(window_ms / 1000.0 * feature_rate_hz))
        self.formant = nn.Sequential(nn.Linear(feature_dim, channels), nn.ReLU())
        convs: list[nn.Module] = []
        n = self.window
        while n > 1:
            convs += [nn.Conv1d(channels, channels, 3, stride=2, padding=1), nn.ReLU()]
            n = (n - 1) // 2 + 1
        self.articulation = nn.Sequential(*convs)
        self.fc = nn.Sequential(nn.Dropout(dropout), nn.Linear(channels, hidden), nn.ReLU(), nn.Linear(hidden, N_VISEMES))

    def forward(
        self, features: Tensor, feat_lengths: Tensor, n_frames: Tensor,
        targets: Tensor | None = None, fps: float | None = None,
    ) -> tuple[Tensor, Tensor]:
        fps = self._fps(fps)
        n_frames = n_frames.to(torch.long)
        b, t_feat, d = features.shape
        t = int(n_frames.max().item())
        centre = torch.round(torch.arange(t, dtype=torch.float64) * (self.feature_rate_hz / fps)).to(torch.long)
        offs = torch.arange(self.window) - self.window // 2
        idx = (centre[:, None] + offs[None, :]).to(features.device)  # (t, W)
        valid = (idx[None] >= 0) & (idx[None] < feat_lengths.to(features.device)[:, None, None])  # (B, t, W)
        flat = idx.clamp(0, max(t_feat - 1, 0)).reshape(-1)
        win = features[:, flat, :].reshape(b, t, self.window, d) * valid[..., None].to(features.dtype)
        h = self.formant(win) * valid[..., None].to(features.dtype)  # (B, t, W, C)
        h = h.reshape(b * t, self.window, -1).transpose(1, 2)
        h = self.articulation(h)[:, :, 0].reshape(b, t, -1)
        return self._finish(self.fc(h), n_frames)


class FaceFormerDecoder(_CurveHead):
    """FaceFormer-style (Fan et al. 2022) autoregressive transformer decoder, adapted to 16 visemes.

    Audio: f_proj + f_interp to the curve rate (the "memory"). Motion side: previous curve frames ->
    Linear(16 -> d) + PPE, a learned start vector in place of FaceFormer's style embedding. Decoder:
    ``nn.TransformerDecoder`` with a causal self-attention mask (plain causal mask; FaceFormer's
    ALiBi-like bias is replaced by the PPE alone) and the cross-modal alignment mask: frame t
    attends to the audio frame aligned with it only (diagonal). Training: teacher forcing with
    ``targets``; inference (no targets): greedy frame-by-frame autoregression.
    """

    def __init__(
        self, feature_dim: int, feature_rate_hz: float, curve_fps: float = DEFAULT_FPS, d_model: int = 64,
        layers: int = 1, heads: int = 4, dropout: float = 0.0, ppe_period_frames: int | None = None,
        output: Literal["linear", "sigmoid"] = "linear",
    ) -> None:
        super().__init__()
        self.feature_rate_hz = feature_rate_hz
        self.curve_fps = curve_fps
        self.output = output
        self.d_model = d_model
        self.ppe_period_frames = ppe_period_frames
        self.f_proj = nn.Linear(feature_dim, d_model)
        self.motion_in = nn.Linear(N_VISEMES, d_model)
        self.start = nn.Parameter(torch.zeros(d_model))
        layer = nn.TransformerDecoderLayer(d_model, heads, dim_feedforward=2 * d_model, dropout=dropout, batch_first=True)
        self.dec = nn.TransformerDecoder(layer, layers)
        self.fc = nn.Linear(d_model, N_VISEMES)

    def _period(self, fps: float) -> int:
        return self.ppe_period_frames or max(1, round(fps))

    def _step(self, prev: Tensor, memory: Tensor, fps: float) -> Tensor:
        """Decoder outputs for inputs [start, prev_0 .. prev_{n-2}] -> (B, n, d) given (B, n-1, 16)."""
        b, n = prev.shape[0], prev.shape[1] + 1
        tgt = torch.cat([self.start.expand(b, 1, -1), self.motion_in(prev)], dim=1)
        tgt = tgt + periodic_positional_encoding(n, self.d_model, self._period(fps)).to(tgt)[None]
        causal = torch.triu(torch.ones(n, n, dtype=torch.bool, device=tgt.device), diagonal=1)
        align = ~torch.eye(n, dtype=torch.bool, device=tgt.device)
        return self.dec(tgt, memory[:, :n], tgt_mask=causal, memory_mask=align)

    def forward(
        self, features: Tensor, feat_lengths: Tensor, n_frames: Tensor,
        targets: Tensor | None = None, fps: float | None = None,
    ) -> tuple[Tensor, Tensor]:
        fps = self._fps(fps)
        n_frames = n_frames.to(torch.long)
        memory = interpolate_to_frames(self.f_proj(features), feat_lengths, n_frames, self.feature_rate_hz, fps)
        t = memory.shape[1]
        if targets is not None:
            h = self._step(targets[:, : t - 1].to(memory), memory, fps)
            return self._finish(self.fc(h), n_frames)
        ys: list[Tensor] = []
        for k in range(t):
            prev = torch.stack(ys, 1) if ys else memory.new_zeros(memory.shape[0], 0, N_VISEMES)
            y = self.fc(self._step(prev, memory, fps)[:, -1])
            if self.output == "sigmoid":
                y = torch.sigmoid(y)  # feed back what is predicted
            ys.append(y)
        y = torch.stack(ys, 1)
        mask = length_mask(n_frames.to(y.device), t)
        return y * mask[..., None].to(y.dtype), mask


class ClosurePeaks(nn.Module):
    """Inference-only narrowing of the MBP (b/p/m closure) channel to its peaks: each frame's MBP weight ``x`` becomes
    ``x * (x / m) ** power``, where ``m`` is the largest MBP weight within ``half_window_s`` on either side.

    Why: a regression on curves whose closures rise and fall over ~0.1 s learns broad MBP bumps, and a bump's
    shoulders make MBP the strongest shape in the phones *next to* a b/p/m -- lips that close on the vowel before a
    "b" (measured on unseen speakers: 24% of the other phones, issue 25). At a local peak ``x == m`` and the weight is
    kept, so the closure itself is untouched; a shoulder at half the peak is multiplied by ``0.5 ** power``. No
    parameters (model files keep the same weights); the window is in seconds, so it means the same at any rate. The
    ONNX graph applies the same arithmetic (``learning.onnx_export``).

    ``lead_s`` first moves the MBP channel that much earlier (each frame takes the weight at ``t + lead_s``, linearly
    interpolated between frames; the last frame's weight holds past the end). Why: the model's closures linger into
    the phone after a b/p/m (the /l/ of "blue", the vowel after "p": four times as many false closures after a b/p/m
    as before one, measured on unseen speech, issue 25), and lips that close a little before the sound is what
    animators draw anyway.

    ``others_power`` k > 0 then caps every other viseme at ``(1 - MBP) ** k`` on the frames where MBP is the strongest
    viseme (the closure rule of ``articulation.close_lips`` caps them at ``1 - MBP`` on every frame). Why: where the
    model calls a closure but is not sure of it (MBP 0.5-0.8), the opening shapes beside it held the rendered lips 2-5
    mm apart; on unseen speech the mesh closed at 82% of b/p/m phones whose MBP was the top viseme at 94% (issue 25).
    Frames where another viseme leads are untouched, so the top viseme of every frame stays what it was."""

    def __init__(self, half_window_s: float, power: float, lead_s: float = 0.0, others_power: float = 0.0) -> None:
        super().__init__()
        if not (half_window_s > 0 and power > 0):
            raise ValueError(f"ClosurePeaks needs a positive window and power, got {half_window_s}, {power}")
        if not (0.0 <= lead_s <= 0.1):
            raise ValueError(f"ClosurePeaks' lead must be within 0..0.1 s, got {lead_s}")
        if not (0.0 <= others_power <= 16.0):
            raise ValueError(f"ClosurePeaks' others_power must be within 0..16, got {others_power}")
        self.half_window_s, self.power, self.lead_s = float(half_window_s), float(power), float(lead_s)
        self.others_power = float(others_power)

    def half_window(self, fps: float) -> int:
        """The half window in frames at ``fps`` (at least one frame)."""
        return max(1, int(round(self.half_window_s * float(fps))))

    def forward(self, curves: Tensor, fps: float) -> Tensor:
        return self.cap_others(self.narrow(curves, fps))

    def narrow(self, curves: Tensor, fps: float) -> Tensor:
        """The lead and the narrowing of the MBP channel (the first part of `forward`)."""
        from visemeflow.visemes import VISEME_INDEX

        k = VISEME_INDEX["MBP"]
        w = self.half_window(fps)
        x = curves[..., k].clamp(min=0.0)                                        # (B, T)
        if self.lead_s > 0:
            x = self._lead(x, self.lead_s * float(fps))
        peak = nn.functional.max_pool1d(x[:, None], 2 * w + 1, stride=1, padding=w)[:, 0]
        narrowed = x * (x / peak.clamp(min=1e-6)) ** self.power
        return torch.cat([curves[..., :k], narrowed[..., None].to(curves.dtype), curves[..., k + 1:]], dim=-1)

    def cap_others(self, out: Tensor) -> Tensor:
        """The cap of the other visemes where MBP leads (the second part of `forward`; nothing when
        ``others_power`` is 0)."""
        from visemeflow.visemes import VISEME_INDEX

        if self.others_power <= 0:
            return out
        k = VISEME_INDEX["MBP"]
        mbp = out[..., k:k + 1]
        leads = (mbp >= out.amax(dim=-1, keepdim=True)) & (mbp > 0)              # (B, T, 1)
        cap = (1.0 - mbp.clamp(0.0, 1.0)) ** self.others_power
        capped = torch.where(leads, torch.minimum(out, cap), out)
        return torch.cat([capped[..., :k], mbp, capped[..., k + 1:]], dim=-1)

    @staticmethod
    def _lead(x: Tensor, frames: float) -> Tensor:
        """``x`` (B, T) sampled ``frames`` later: ``(1 - a) x[t + i] + a x[t + i + 1]`` with ``i + a = frames``, the
        last frame repeated past the end. Constant slices only, so the ONNX export traces it at a fixed rate."""
        i = int(math.floor(frames))
        a = frames - i
        padded = torch.cat([x, x[:, -1:].expand(-1, i + 1)], dim=1)             # (B, T + i + 1)
        return (1.0 - a) * padded[:, i:-1] + a * padded[:, i + 1:]


class ReleaseCut(nn.Module):
    """Inference-only: a closure ends where the lips open, at the release the audio shows. Where MBP leads a frame at
    a peak of at least ``min_peak`` and the energy of the 400-3400 Hz band rises by ``rise_db`` or more within 20 ms
    (a burst, or a nasal opening into a vowel) between ``before_s`` before that frame and ``after_s`` after it, the
    closure's whole pose moves to the last frame before the earliest such rise (where the peak came late), and MBP
    no longer leads the frames after it up to three frames past the peak (it is lowered to 0.95 of the strongest
    other viseme there).

    Why: most of the learned model's false closures on unseen speech fall right after a b/p/m, the closure held
    into the /l/ of "blue" or the vowel after "p" (issue 25); timing shifts and sharper peaks traded them against
    closures everywhere, because the error is not a constant lag. The release is in the audio of every language.
    Rises are found on 20-ms frames every 10 ms, above a floor 50 dB under the file's loudest frame. No parameters
    to learn; numpy on the CPU, in eval mode only (the ONNX graph does not apply it, see ``learning.onnx_export``)."""

    def __init__(self, rise_db: float, before_s: float = 0.02, after_s: float = 0.07, min_peak: float = 0.3,
                 band_hz: tuple[float, float] = (400.0, 3400.0), floor_db: float = 50.0) -> None:
        super().__init__()
        if not rise_db > 0:
            raise ValueError(f"ReleaseCut needs a positive rise in dB, got {rise_db}")
        self.rise_db, self.before_s, self.after_s = float(rise_db), float(before_s), float(after_s)
        self.min_peak, self.band_hz, self.floor_db = float(min_peak), tuple(band_hz), float(floor_db)

    HOP, WINDOW, RATE = 160, 320, 16000

    def releases(self, audio: np.ndarray) -> np.ndarray:
        """Times (s) where the band's energy rises by ``rise_db`` within 20 ms (a local maximum of the rise), in 16-kHz
        mono ``audio``."""
        audio = np.asarray(audio, np.float64)
        if len(audio) < self.WINDOW:
            return np.zeros(0)
        padded = np.pad(audio, (self.WINDOW // 2, self.WINDOW // 2))
        n = 1 + (len(padded) - self.WINDOW) // self.HOP
        freqs = np.fft.rfftfreq(self.WINDOW, 1.0 / self.RATE)
        band = (freqs >= self.band_hz[0]) & (freqs <= self.band_hz[1])
        window = np.hanning(self.WINDOW)
        energy = np.empty(n)
        for start in range(0, n, 4096):                       # bounded memory for an hour of audio
            idx = np.arange(start, min(n, start + 4096))[:, None] * self.HOP + np.arange(self.WINDOW)[None]
            spectrum = np.abs(np.fft.rfft(padded[idx] * window, axis=1)[:, band]) ** 2
            energy[start:start + len(idx)] = 10.0 * np.log10(spectrum.sum(axis=1) + 1e-10)
        back = 2                                               # 20 ms
        before = np.full(n, np.inf)
        for k in range(1, back + 1):
            before[k:] = np.minimum(before[k:], energy[:-k])
        rise = np.where(np.arange(n) >= back, energy - before, 0.0)
        strong = (rise >= self.rise_db) & (energy > energy.max() - self.floor_db)
        local = rise >= np.max(np.stack([np.roll(rise, s) for s in (-2, -1, 1, 2)]), axis=0)
        return np.flatnonzero(strong & local) * (self.HOP / self.RATE)

    def cut(self, curves: np.ndarray, audio: np.ndarray, fps: float) -> np.ndarray:
        """(T, 16) curves at ``fps`` with each closure ended at its release (see the class); a new array."""
        from visemeflow.articulation import contact_keys
        from visemeflow.visemes import VISEME_INDEX

        mbp = VISEME_INDEX["MBP"]
        out = np.array(curves, np.float32, copy=True)
        if len(out) == 0:
            return out
        releases = self.releases(audio)
        if not len(releases):
            return out
        for k in contact_keys(curves):
            if int(np.argmax(curves[k])) != mbp or curves[k, mbp] < self.min_peak:
                continue
            t = k / fps
            near = releases[(releases >= t - self.before_s) & (releases <= t + self.after_s)]
            if not len(near):
                continue
            last = int(np.floor(near.min() * fps + 1e-9))      # the last frame at or before the release
            if 0 <= last < k:
                out[last] = curves[k]
            for j in range(max(last, 0) + 1, min(len(out), k + 4)):
                others = float(np.delete(out[j], mbp).max())
                if out[j, mbp] >= others:
                    out[j, mbp] = 0.95 * others
        return out

    def forward(self, curves: Tensor, audio: Tensor, lengths: Tensor, fps: float) -> Tensor:
        out = curves.detach().float().cpu().numpy()
        a = audio.detach().float().cpu().numpy()
        for b in range(len(out)):
            out[b] = self.cut(out[b], a[b, :int(lengths[b])], fps)
        return torch.from_numpy(out).to(device=curves.device, dtype=curves.dtype)


class AudioCurveModel(nn.Module):
    """A feature module (audio -> features) followed by one of the curve models above, and optionally, at inference
    (eval mode) only, :class:`ClosurePeaks` and :class:`ReleaseCut` on its output (`finish`)."""

    def __init__(self, features: nn.Module, head: nn.Module, closure_peaks: ClosurePeaks | None = None,
                 release_cut: ReleaseCut | None = None) -> None:
        super().__init__()
        self.features = features
        self.head = head
        self.closure_peaks = closure_peaks
        self.release_cut = release_cut

    def forward(
        self, audio: Tensor, lengths: Tensor, n_frames: Tensor,
        targets: Tensor | None = None, fps: float | None = None,
    ) -> tuple[Tensor, Tensor]:
        feats, feat_lengths = self.features(audio, lengths)
        y, mask = self.head(feats, feat_lengths, n_frames, targets=targets, fps=fps)
        if not self.training:
            y = self.finish(y, mask, audio, lengths, float(fps if fps is not None else self.head.curve_fps))
        return y, mask

    def finish(self, y: Tensor, mask: Tensor, audio: Tensor, lengths: Tensor, fps: float) -> Tensor:
        """The inference-only steps on the decoder's curves: the MBP peaks narrowed, each closure ended at its release
        (16-kHz ``audio``), then the other visemes capped where MBP leads."""
        if self.closure_peaks is not None:
            y = self.closure_peaks.narrow(y, fps)
        if self.release_cut is not None:
            y = self.release_cut(y, audio, lengths, fps)
        if self.closure_peaks is not None:
            y = self.closure_peaks.cap_others(y) * mask[..., None].to(y.dtype)
        return y


def count_parameters(model: nn.Module, trainable_only: bool = True) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad or not trainable_only)
