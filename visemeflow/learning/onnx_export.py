"""ONNX export of a saved curve model, for game engines (Unity Sentis / Inference Engine, Unreal NNE).

:func:`export_onnx` turns a file written by :func:`visemeflow.learning.train.save_model` into one
self-contained ONNX graph::

    audio  float32 (1, n_samples)      mono samples at the export's ``sample_rate`` (dynamic n_samples)
    curves float32 (1, n_frames, 16)   viseme curves in [0, 1] at the export's ``fps`` (dynamic n_frames)

with ``n_frames = round(n_samples * fps / sample_rate)`` computed exactly in integers, ties to even
(:func:`n_frames_for`), and the 16 columns in :data:`visemeflow.visemes.VISEMES` order (also in
the file's metadata, ``viseme_names``). That is the frame count
:func:`~visemeflow.learning.train.predict_curves` gives, except at exact half-frame ties, where
its float64 ``round(n / rate * fps)`` can land either side (240 of 11.2 million lengths checked,
e.g. 34880 samples at 16 kHz, 25 fps: 54.5 -> graph 54, predict_curves 55); pass ``n_frames`` to
``predict_curves`` to compare there.

What the graph contains (batch 1, no padding, so every length mask of the torch model is all-true
and dropped):

* resampling, when ``sample_rate`` is not 16 kHz: the same band-limited polyphase windowed-sinc
  filter as :func:`~visemeflow.learning.features.resample_audio` (6 zero crossings, cut-off 0.99 x
  the lower Nyquist), as one strided ``Conv``, in float32 (torch runs it in float64). Only rates
  whose reduced up-factor against 16 kHz is at most 1024 (8, 11.025, 22.05, 24, 32, 44.1, 48,
  96 kHz ...) can be built in; others raise :class:`OnnxExportError`. With the default
  ``sample_rate=16000`` the caller must hand over 16 kHz mono audio: downmix to mono (channel mean)
  and resample to 16 kHz first, as ``predict_curves`` does.
* the features, inside the graph: fbank / MFCC as a ``Conv`` whose kernels are the Hann-windowed
  real and imaginary DFT basis (the 512-point zero-padded real FFT of the torch extractor, framed
  by the convolution's stride), power, mel ``MatMul``, log, DCT ``MatMul`` for MFCC, per-utterance
  CMVN; LPC as a framing ``Conv`` (windowed identity kernel), autocorrelation lags 0..p as sums of
  products and Levinson-Durbin unrolled over the p orders (float64); wav2vec2 as the model's own graph
  (per-utterance waveform normalisation, CNN encoder, transformer); Whisper's log-mel and encoder (see
  "Whisper models" below). No ``DFT``/``STFT`` operator.
  Tensors are float32 and int64 (engines with 32-bit ints: the index arithmetic stays below 2**31
  for clips under about two hours at 30 fps), except in LPC graphs, which keep torch's float64 for
  the autocorrelation and Levinson-Durbin (``ExportReport.uses_float64``): in float32 the recursion
  is unstable on frames with little high-frequency energy. ONNX Runtime based engines (Unreal NNE's
  ORT runtimes) run float64; Unity Sentis's operator table lists float / int / short types only, so
  use fbank / MFCC / wav2vec2 models there.
* the head: projection, linear interpolation to the curve rate (integer index arithmetic, exact),
  the periodic positional encoding as a table lookup, the decoder (``LSTM`` operator for the
  (B)LSTM, ``Conv`` for the TCN, attention for the transformer), the Karras window CNN, or the
  constant mean curve; then the clip to [0, 1] that ``predict_curves`` applies.

``fps`` is fixed at export (default: the fps the model was trained at); the positional encoding
period and the interpolation ratio depend on it. Not exportable: ``faceformer-*`` presets (their
autoregressive inference runs one decoder pass per output frame in a Python loop whose trip count
is the clip length; torch.export unrolls such a loop for the example's length, so the time axis
could not stay dynamic; it would have to be rewritten as a ``torch.while_loop`` / ONNX ``Loop``)
-> :class:`OnnxExportError` naming the preset.

Exporter: ``torch.export.export`` (non-strict, ``Dim.DYNAMIC`` sample axis) then
``torch.onnx.export(..., dynamo=True)`` on the exported program (dynamo=True is torch 2.13's
default; it needs the ``onnxscript`` and ``onnx`` packages). The legacy TorchScript exporter is
deprecated, and it would trace Python integer arithmetic on sizes as constants; the dynamo exporter
keeps the sample/frame counts symbolic (``Shape`` -> integer ops -> ``Range``). Two things needed
care: ``nn.LSTM`` is unrolled over the example's time steps by torch.export (fixed length), so the
LSTMs go through a custom op translated to the ONNX ``LSTM`` operator; and the exporter writes
opset 18, its own down-conversion fails before constant folding, so the optimised graph is
converted here with ``onnx.version_converter`` (plus removal of an attribute that converter leaves
behind) and validated with the full ONNX checker. ``opset`` 17 (default) or 18 for the transformer
and wav2vec2 models (``LayerNormalization`` is opset 17); the others also convert to 15, the
highest opset Unity Sentis before 2.6 officially reads (2.6 reads up to 25). Unreal NNE's ORT
runtimes are ONNX Runtime builds.

Whisper models (``whisper-*`` presets; issue 25 item 5). The graph holds what
:class:`~visemeflow.learning.features.WhisperExtractor` computes for audio of one window or less, exactly as
:mod:`visemeflow.learning.whisper` does: the signal ``audio[1:201]`` reversed (the STFT's reflect centering), the
audio, then zeros up to the 30-s window (Whisper's short-audio padding, ``whisper_pad_short``; 3000 mel frames);
a ``Conv`` with the periodic-Hann 400-point real DFT basis, stride 160; power, the Slaney mel ``MatMul``,
``log10(max(x, 1e-10))``, the floor ``max - 8`` over the whole window, ``(x + 4) / 4``; the encoder (conv1/conv2 +
GELU, sinusoidal positions, 6 pre-LN blocks with ``LayerNormalization``, attention as ``MatMul``/``Softmax``,
exact GELU through ``Erf``; the learned layer mix for ``whisper_layers="weighted"``); then the ``ceil((n // 160)
/ 2)`` encoder frames that carry audio go to the head. Weights are stored in float32 (the package's float16
values widened, as torch runs them): a whisper-base-blstm graph is about 91 MB (the encoder's 20.6 M weights
~82 MB). Opset 17 (``LayerNormalization``). The encoder weights come from wherever the saved model's
``whisper_source`` points (the ``visemeflow[whisper]`` package, a folder, a hub id), checked by its digest as
``load_model`` does.

Longer audio. One graph call takes at most ``ExportReport.max_samples`` samples (metadata
``visemeflow.max_samples``: 480,159 at 16 kHz, i.e. ``n // 160 <= 3000`` mel frames, whisper.py's single
window); a longer input makes the runtime fail in the padding's ``ConstantOfShape`` (negative size) instead of
silently cutting the audio. Building whisper.py's windows into the graph was not attempted: as one dynamic
batch of windows it would hold every window's activations at once (memory growing with the clip, unbounded for
hour-long files); as an ONNX ``Loop`` it needs the exporter's ``while_loop`` path, untried here. The caller splits
longer audio
(:func:`onnx_curves` does it, with :func:`windowed_curves`): windows of 30 s every 25 s, the last one moved back
to end where the audio ends (whisper.py's rule), each window's curves placed at ``n_frames_for(start)`` and
crossfaded linearly over each 5-s overlap. That is **not** what ``predict_curves`` computes past 30 s: torch
crossfades the encoder *features* (one log-mel floor over the whole file) and runs the decoder once over the
whole clip, so the windowed curves differ from torch's away from the first window (measured: 40 s of LJSpeech,
small trained head: max |diff| 0.12, mean 0.004; 70 s, untrained default-size head: max 0.098, mean 0.0024;
exactly equal to the windows' own curves outside the overlaps). Up to one window the graph equals
``predict_curves`` (tolerance :data:`WHISPER_TOLERANCE`, 1e-3; measured 1.3e-6 on a 30-s LJSpeech clip).

Speed (one CPU thread, 30 s of LJSpeech, whisper-base-blstm at the preset's d_model, the 2-core development
machine, shared with a training run at the time: load average 2.9): onnxruntime (``intra_op_num_threads=1``)
0.72-0.81 s, real-time factor 0.024-0.027; torch ``predict_curves`` (``torch.set_num_threads(1)``) 0.71-0.83 s,
0.024-0.028 (two runs, best of 3 and median of 5): the same within the noise. Any clip up to 30 s costs the same
(padded to the window). Export takes about 10 s.

Inputs shorter than ``ExportReport.min_samples`` (one 25 ms feature window and one curve frame:
400 samples at 16 kHz) are not supported, as in torch.

Checks: :func:`export_onnx` writes the graph to a temporary file beside the target, runs that file with
onnxruntime (CPU) on a deterministic test signal and compares it with ``predict_curves``
(``ExportReport.max_abs_diff``); over :data:`DEFAULT_TOLERANCE` it raises and the temporary file is removed, so a
previous export at the target stays as it was; only a graph that passed replaces it (``os.replace``). A file that
is not a saved model, or one from another format version, raises :class:`OnnxExportError` naming the file and why
(:class:`~visemeflow.learning.train.ModelFileError`'s reason; nothing is loaded silently).
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from visemeflow.learning.features import (
    FeatureExtractor,
    FilterbankExtractor,
    LpcExtractor,
    Wav2Vec2Extractor,
    WhisperExtractor,
    _sinc_kernels,
)
from visemeflow.learning.model import (
    AudioCurveModel,
    CurveModel,
    FaceFormerDecoder,
    KarrasConvNet,
    MeanCurveBaseline,
    _LSTMDecoder,
    _TCNDecoder,
    _TransformerDecoder,
    periodic_positional_encoding,
)
from visemeflow.learning.presets import PRESETS
from visemeflow.learning.whisper import HOP as WHISPER_HOP
from visemeflow.learning.whisper import N_FFT as WHISPER_N_FFT
from visemeflow.learning.whisper import mel_filters as whisper_mel_filters
from visemeflow.visemes import N_VISEMES, VISEMES

__all__ = [
    "DEFAULT_OPSET",
    "DEFAULT_TOLERANCE",
    "WHISPER_TOLERANCE",
    "EXPORTABLE_PRESETS",
    "NOT_EXPORTABLE",
    "ExportReport",
    "OnnxExportError",
    "build_export_module",
    "export_onnx",
    "n_frames_for",
    "onnx_curves",
    "check_signal",
    "windowed_curves",
]

DEFAULT_OPSET = 17
MIN_OPSET = 15  # Sentis before 2.6 reads opsets 7-15; LayerNormalization (transformer, wav2vec2) needs 17
MAX_OPSET = 21
_NATIVE_OPSET = 18  # what torch.onnx's dynamo exporter writes
MODEL_SAMPLE_RATE = 16000  # every trained model's feature rate (FeatureConfig.sample_rate)
DEFAULT_TOLERANCE = 1e-4  # max |onnx - torch| over the check signal's curves
WHISPER_TOLERANCE = 1e-3  # the same for whisper models (a 6-layer float32 encoder over 30 s of log-mel)

NOT_EXPORTABLE: dict[str, str] = {
    name: (
        "its FaceFormer-style autoregressive inference runs one decoder pass per output frame in a Python "
        "loop as long as the clip; torch.export unrolls it for one length, so the time axis cannot stay "
        "dynamic; use predict_curves in Python"
    )
    for name, p in PRESETS.items()
    if p.architecture == "faceformer"
}
EXPORTABLE_PRESETS: tuple[str, ...] = tuple(n for n in PRESETS if n not in NOT_EXPORTABLE)


class OnnxExportError(ValueError):
    """The model cannot be exported (wrong file, other version, unsupported preset or setting)."""


RELEASE_CUT_NOTE = ("the model ends each closure at its release in the audio (learning.model.ReleaseCut, numpy after "
                    "the network); the graph does not: its curves are predict_curves' without that step (on unseen "
                    "English speech, false closures 2.4% with it, 3.5% without)")


@dataclass(frozen=True)
class ExportReport:
    path: Path
    preset: str
    opset: int
    sample_rate: int  # of the graph's audio input
    fps: float  # of its curve output
    feature: str  # fbank / mfcc / lpc / wav2vec2 / whisper (computed inside the graph)
    min_samples: int  # shortest input supported (one feature frame and one curve frame; 400 at 16 kHz, 30 fps)
    size_bytes: int
    stored_values: int  # numbers stored in the file: weights and constant tables (DFT basis, filterbank, PPE)
    ops: tuple[str, ...]  # ONNX operator types used (default domain only)
    uses_float64: bool  # float64 tensors inside (LPC features); engines without float64 (Sentis) cannot run it
    export_seconds: float
    max_abs_diff: float | None = None  # onnxruntime vs predict_curves on the check signal; None: not checked
    check_seconds: float | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)
    # longest input the graph takes (whisper: one 30-s window at the input rate); None: any length
    max_samples: int | None = None


# --------------------------------------------------------------------------------------------------
# integer time arithmetic (symbolic at export: the sample count is a torch.export dimension)


def _ratio(num: float | int, den: float | int) -> Fraction:
    """``num / den`` as a small exact fraction (the decimal values a user typed: 29.97 -> 2997/100)."""
    r = Fraction(str(float(num))) / Fraction(str(float(den)))
    return r.limit_denominator(1_000_000)


def _round_half_even(num: Any, den: int) -> Any:
    """round(num / den) with ties to even, for non-negative ints or torch SymInts / int64 tensors."""
    twice = 2 * num + den
    up = twice // (2 * den)  # round half up
    rem = twice % (2 * den)
    tie = 1 - (rem + 2 * den - 1) // (2 * den)  # 1 where rem == 0, else 0
    return up - tie * (up % 2)


def n_frames_for(n_samples: int, sample_rate: int, fps: float) -> int:
    """Curve frames of ``n_samples`` audio at ``sample_rate``: round(n * fps / rate), ties to even (the graph's
    rule, exact in integers)."""
    r = _ratio(fps, sample_rate)
    return int(_round_half_even(n_samples * r.numerator, r.denominator))


# --------------------------------------------------------------------------------------------------
# graph modules (batch 1, no padding)


class _Resample(nn.Module):
    """features.resample_audio as a strided Conv (float32): any rate -> 16 kHz, reduced up-factor <= 1024."""

    def __init__(self, rate: int, target: int) -> None:
        super().__init__()
        r = Fraction(target, rate)
        self.up, self.down = r.numerator, r.denominator
        if self.up > 1024:
            raise OnnxExportError(
                f"sample_rate {rate} cannot be resampled inside the graph (up-factor {self.up} > 1024 "
                f"against {target} Hz); resample to {target} Hz in the engine and export with sample_rate={target}"
            )
        kernels, self.half = _sinc_kernels(self.up, self.down, zero_crossings=6, rolloff=0.99)
        self.register_buffer("kernels", kernels.to(torch.float32)[:, None, :])

    def out_len(self, n: Any) -> Any:
        return (n * self.up + self.down - 1) // self.down  # ceil(n * up / down)

    def forward(self, audio: Tensor) -> Tensor:
        x = nn.functional.pad(audio[:, None, :], (self.half, self.half + self.down))
        y = nn.functional.conv1d(x, self.kernels, stride=self.down)  # (1, up, blocks)
        y = y.transpose(1, 2).reshape(1, -1)
        return y[:, : self.out_len(audio.shape[1])]


class _Cmvn(nn.Module):
    def forward(self, x: Tensor) -> Tensor:  # (1, T, D), every frame valid
        mean = x.mean(1, keepdim=True)
        var = ((x - mean) ** 2).mean(1, keepdim=True)
        return (x - mean) / torch.sqrt(var + 1e-5)


class _FilterbankGraph(nn.Module):
    """Log-mel / MFCC: framing + windowed real DFT in one Conv (no DFT op)."""

    def __init__(self, ext: FilterbankExtractor) -> None:
        super().__init__()
        cfg = ext.config
        win, n_fft = cfg.win_length, ext.n_fft
        self.hop = cfg.hop_length
        j = torch.arange(win, dtype=torch.float64)[:, None]
        k = torch.arange(n_fft // 2 + 1, dtype=torch.float64)[None, :]
        ang = 2.0 * math.pi * j * k / n_fft
        w = ext.window.to(torch.float64)[:, None]
        basis = torch.cat([w * torch.cos(ang), -w * torch.sin(ang)], dim=1)  # (win, 2K)
        self.register_buffer("basis", basis.T.to(torch.float32)[:, None, :].contiguous())  # (2K, 1, win)
        self.n_bins = n_fft // 2 + 1
        self.register_buffer("mel_fb", ext.mel_fb.clone())
        self.mfcc = cfg.kind == "mfcc"
        if self.mfcc:
            self.register_buffer("dct", ext.dct.clone())
        self.cmvn = _Cmvn() if cfg.normalize else None

    def forward(self, audio: Tensor) -> Tensor:
        spec = nn.functional.conv1d(audio[:, None, :], self.basis, stride=self.hop)  # (1, 2K, T)
        re, im = spec[:, : self.n_bins], spec[:, self.n_bins :]
        power = (re * re + im * im).transpose(1, 2)  # (1, T, K)
        feats = torch.log(torch.clamp(power @ self.mel_fb, min=1e-10))
        if self.mfcc:
            feats = feats @ self.dct
        return self.cmvn(feats) if self.cmvn is not None else feats


class _LpcGraph(nn.Module):
    """LPC predictor coefficients: framing Conv, autocorrelation sums and unrolled Levinson-Durbin in float64.

    float64 as in the torch extractor: in float32 the recursion is unstable on frames with little
    high-frequency energy (coefficient errors of 2 on speech, 5e4 on a band-limited signal, measured).
    """

    def __init__(self, ext: LpcExtractor) -> None:
        super().__init__()
        cfg = ext.config
        self.hop, self.order = cfg.hop_length, cfg.lpc_order
        framer = torch.diag(ext.window.to(torch.float32))[:, None, :]  # (win, 1, win): frame t, windowed
        self.register_buffer("framer", framer.contiguous())
        # r0 * (1 + 1e-9) + 1e-12 written as r0 + r0 * 1e-9 + 1e-12 with shape-(1,) float64 tensors: two
        # optimisers drop the white-noise correction otherwise (onnxscript's no-op rules take any scalar within
        # rel 1e-5 of 1 / abs 1e-8 of 0 for 1 / 0; onnxruntime's graph optimisation removes a float64 Mul by
        # 1 + 1e-9), which moves the coefficients of ill-conditioned frames by up to 7e-3 (measured)
        self.register_buffer("r0_rel", torch.tensor([1e-9], dtype=torch.float64))
        self.register_buffer("r0_abs", torch.tensor([1e-12], dtype=torch.float64))
        self.cmvn = _Cmvn() if cfg.normalize else None

    def forward(self, audio: Tensor) -> Tensor:
        frames = nn.functional.conv1d(audio[:, None, :], self.framer, stride=self.hop).to(torch.float64)  # (1, win, T)
        win = frames.shape[1]
        r = [(frames[:, : win - lag] * frames[:, lag:]).sum(1) for lag in range(self.order + 1)]  # (1, T) each
        r[0] = r[0] + r[0] * self.r0_rel + self.r0_abs
        a: list[Tensor] = []
        err = r[0]
        for i in range(self.order):
            acc = r[i + 1]
            for j in range(i):
                acc = acc - a[j] * r[i - j]
            k = acc / err
            a = [a[j] - k * a[i - 1 - j] for j in range(i)] + [k]
            err = err * (1.0 - k * k)
        feats = torch.stack(a, dim=-1).to(torch.float32)  # (1, T, p)
        return self.cmvn(feats) if self.cmvn is not None else feats


class _Wav2Vec2Graph(nn.Module):
    def __init__(self, ext: Wav2Vec2Extractor) -> None:
        super().__init__()
        self.model = ext.model
        self.cmvn = _Cmvn() if ext.config.normalize else None

    def forward(self, audio: Tensor) -> Tensor:
        mean = audio.mean(1, keepdim=True)
        var = ((audio - mean) ** 2).mean(1, keepdim=True)
        x = (audio - mean) / torch.sqrt(var + 1e-7)
        feats = self.model(x).last_hidden_state
        return self.cmvn(feats) if self.cmvn is not None else feats


class _WhisperMel(nn.Module):
    """whisper.log_mel of one window: ``(1, n) -> (1, n_mels, window)``, the audio padded with zeros to the window
    (Whisper's short-audio padding); framing + periodic-Hann 400-point real DFT in one strided Conv.

    Padded signal as in whisper.py: ``audio[1:201]`` reversed (the STFT's reflect centering), the audio, then
    zeros; frame t covers samples ``[160 t, 160 t + 400)`` of it. The zeros are ``max_samples - n`` long (then the
    signal is cut to what the window's frames read): a negative length, audio over one window, makes the runtime
    fail (ConstantOfShape) instead of silently cutting the audio.
    """

    def __init__(self, n_mels: int, window: int) -> None:
        super().__init__()
        self.window = window
        self.max_samples = (window + 1) * WHISPER_HOP - 1  # n // 160 <= window: one window in whisper.py
        self.span = (window - 1) * WHISPER_HOP + WHISPER_N_FFT  # padded samples the frames read
        j = torch.arange(WHISPER_N_FFT, dtype=torch.float64)[:, None]
        k = torch.arange(WHISPER_N_FFT // 2 + 1, dtype=torch.float64)[None, :]
        ang = 2.0 * math.pi * j * k / WHISPER_N_FFT
        w = torch.hann_window(WHISPER_N_FFT, periodic=True, dtype=torch.float64)[:, None]
        basis = torch.cat([w * torch.cos(ang), -w * torch.sin(ang)], dim=1)  # (400, 2 * 201)
        self.register_buffer("basis", basis.T.to(torch.float32)[:, None, :].contiguous())  # (402, 1, 400)
        self.n_bins = WHISPER_N_FFT // 2 + 1
        self.register_buffer("filters", whisper_mel_filters(n_mels).clone())  # (n_mels, 201)

    def forward(self, audio: Tensor) -> Tensor:
        half = WHISPER_N_FFT // 2
        zeros = audio.new_zeros(1, self.max_samples - audio.shape[1])  # < 0 over one window: a runtime error
        x = torch.cat([audio[:, 1 : half + 1].flip(1), audio, zeros], dim=1)[:, : self.span]
        spec = nn.functional.conv1d(x[:, None, :], self.basis, stride=WHISPER_HOP)  # (1, 402, window)
        re, im = spec[:, : self.n_bins], spec[:, self.n_bins :]
        mel = self.filters @ (re * re + im * im)  # (1, n_mels, window)
        logs = torch.log10(torch.clamp(mel, min=1e-10))
        logs = torch.maximum(logs, logs.max() - 8.0)
        return (logs + 4.0) / 4.0


class _WhisperGraph(nn.Module):
    """WhisperExtractor for audio up to one window: log-mel (padded to the window), the encoder, the encoder frames
    that carry audio (``ceil((n // 160) / 2)``), the learned layer weights, CMVN when configured."""

    def __init__(self, ext: WhisperExtractor) -> None:
        super().__init__()
        cfg = ext.config
        if not cfg.whisper_pad_short:
            raise OnnxExportError("whisper_pad_short=False is not exported (every whisper preset pads short audio "
                                  "to one window, as Whisper was trained)")
        self.mel = _WhisperMel(ext.encoder.dims.n_mels, ext.windows.window)
        self.encoder = ext.encoder
        self.weighted = ext.weighted
        if self.weighted:
            self.register_buffer("layer_weights", torch.softmax(ext.layer_weights.detach().float(), dim=0))
        self.cmvn = _Cmvn() if cfg.normalize else None

    @property
    def max_samples(self) -> int:
        return self.mel.max_samples

    def forward(self, audio: Tensor) -> Tensor:
        t = (audio.shape[1] // WHISPER_HOP + 1) // 2  # encoder_frames(n) for n >= 160
        y = self.encoder(self.mel(audio), all_layers=self.weighted)
        if self.weighted:
            y = (y * self.layer_weights[None, :, None, None]).sum(1)
        feats = y[:, :t]
        return self.cmvn(feats) if self.cmvn is not None else feats


def _feature_graph(ext: nn.Module) -> nn.Module:
    if isinstance(ext, WhisperExtractor):
        return _WhisperGraph(ext)
    if isinstance(ext, FilterbankExtractor):
        if ext.config.mfcc_deltas:
            raise OnnxExportError("MFCC deltas are not exported (no preset trains with them)")
        return _FilterbankGraph(ext)
    if isinstance(ext, LpcExtractor):
        return _LpcGraph(ext)
    if isinstance(ext, Wav2Vec2Extractor):
        return _Wav2Vec2Graph(ext)
    raise OnnxExportError(f"no ONNX graph for feature extractor {type(ext).__name__}")


def _min_feature_samples(ext: nn.Module) -> int:
    """Fewest 16 kHz samples that give one feature frame."""
    if isinstance(ext, Wav2Vec2Extractor):
        n = 1
        while int(ext.output_lengths(torch.tensor([n]))[0]) < 1:
            n += 1
        return n
    if isinstance(ext, WhisperExtractor):
        return WHISPER_N_FFT  # one full STFT frame (the reflect centering reads audio[1:201])
    assert isinstance(ext, FeatureExtractor)
    return int(ext.config.win_length)


class _Interp(nn.Module):
    """interpolate_to_frames for one utterance, positions k * rate / fps in exact integer arithmetic."""

    def __init__(self, src_rate_hz: float, fps: float) -> None:
        super().__init__()
        r = _ratio(src_rate_hz, fps)
        self.num, self.den = r.numerator, r.denominator

    def forward(self, x: Tensor, t: Any) -> Tensor:  # x (1, T_src, D), t: frames (SymInt)
        last = x.shape[1] - 1
        scaled = torch.arange(t, dtype=torch.int64) * self.num
        i0 = scaled // self.den
        rem = scaled - i0 * self.den
        over = i0 >= last
        i0 = torch.clamp(i0, max=last)
        i1 = torch.clamp(i0 + 1, max=last)
        w = torch.where(over, torch.zeros_like(rem), rem).to(x.dtype) / float(self.den)
        w = w[None, :, None]
        return x.index_select(1, i0) * (1 - w) + x.index_select(1, i1) * w  # Gather, not GatherND


# nn.LSTM: torch.export unrolls it over time (one step per frame of the example input, so the time axis
# would be fixed). Wrapped in an opaque custom op instead, translated to the ONNX LSTM operator.


def _to_onnx_gates(t: Tensor, hidden: int) -> Tensor:
    i, f, g, o = t.split(hidden, dim=0)  # torch gate order
    return torch.cat([i, o, f, g])  # ONNX order (i, o, f, c)


def _to_torch_gates(t: Tensor, hidden: int) -> Tensor:
    i, o, f, c = t.split(hidden, dim=0)
    return torch.cat([i, f, c, o])


@torch.library.custom_op("visemeflow::onnx_lstm", mutates_args=())
def _onnx_lstm(x: Tensor, w: Tensor, r: Tensor, b: Tensor) -> Tensor:
    """One LSTM layer with ONNX-layout weights (gates i, o, f, c).

    x (1, T, D), W (dirs, 4H, D), R (dirs, 4H, H), B (dirs, 8H) -> (1, T, dirs * H).
    """
    dirs, h4 = w.shape[0], w.shape[1]
    h = h4 // 4
    params: list[Tensor] = []
    for d in range(dirs):
        params += [_to_torch_gates(w[d], h), _to_torch_gates(r[d], h),
                   _to_torch_gates(b[d, :h4], h), _to_torch_gates(b[d, h4:], h)]
    h0 = x.new_zeros(dirs, x.shape[0], h)
    return torch.lstm(x, (h0, h0), params, True, 1, 0.0, False, dirs == 2, True)[0]


@_onnx_lstm.register_fake
def _(x: Tensor, w: Tensor, r: Tensor, b: Tensor) -> Tensor:
    return x.new_empty(x.shape[0], x.shape[1], w.shape[0] * (w.shape[1] // 4))


def _lstm_translation() -> Any:
    from onnxscript import opset18 as op

    def onnx_lstm(x: Any, w: Any, r: Any, b: Any) -> Any:
        dirs, hidden = w.shape[0], w.shape[1] // 4
        y, _, _ = op.LSTM(op.Transpose(x, perm=[1, 0, 2]), w, r, b, hidden_size=hidden,
                          direction="bidirectional" if dirs == 2 else "forward")  # (T, dirs, 1, H)
        y = op.Transpose(y, perm=[2, 0, 1, 3])  # (1, T, dirs, H)
        return op.Reshape(y, op.Constant(value_ints=[0, 0, dirs * hidden]))

    return onnx_lstm


class _LstmStack(nn.Module):
    def __init__(self, lstm: nn.LSTM) -> None:
        super().__init__()
        if not lstm.batch_first or lstm.proj_size or not lstm.bias:
            raise OnnxExportError("only batch-first LSTMs with biases and no projection are exported")
        h, dirs = lstm.hidden_size, ["", "_reverse"] if lstm.bidirectional else [""]
        self.layers = lstm.num_layers
        for k in range(lstm.num_layers):
            def get(name: str, sfx: str, k: int = k) -> Tensor:
                return _to_onnx_gates(getattr(lstm, f"{name}_l{k}{sfx}").detach(), h)

            self.register_buffer(f"w{k}", torch.stack([get("weight_ih", d) for d in dirs]))
            self.register_buffer(f"r{k}", torch.stack([get("weight_hh", d) for d in dirs]))
            biases = [torch.cat([get("bias_ih", d), get("bias_hh", d)]) for d in dirs]
            self.register_buffer(f"b{k}", torch.stack(biases))

    def forward(self, x: Tensor) -> Tensor:
        for k in range(self.layers):  # eval: no dropout between layers
            w, r, b = (getattr(self, f"{name}{k}") for name in "wrb")
            x = torch.ops.visemeflow.onnx_lstm(x, w, r, b)
        return x


class _PpeTable(nn.Module):
    def __init__(self, d_model: int, period: int) -> None:
        super().__init__()
        self.period = period
        self.register_buffer("table", periodic_positional_encoding(period, d_model, period))

    def forward(self, t: Any) -> Tensor:
        return self.table.index_select(0, torch.arange(t, dtype=torch.int64) % self.period)[None]  # (1, t, d)


class _CurveGraph(nn.Module):
    def __init__(self, head: CurveModel, fps: float) -> None:
        super().__init__()
        self.f_proj, self.f_fc = head.f_proj, head.f_fc
        self.interp = _Interp(head.feature_rate_hz, fps)
        self.ppe = _PpeTable(head.config.d_model, head.config.ppe_period(fps))
        self.sigmoid = head.output == "sigmoid"
        dec = head.decoder
        self.decoder = dec
        self.lstm = _LstmStack(dec.lstm) if isinstance(dec, _LSTMDecoder) else None

    def forward(self, feats: Tensor, t: Any) -> Tensor:
        u3 = self.interp(self.f_proj(feats), t) + self.ppe(t)
        dec = self.decoder
        if self.lstm is not None:
            h = self.lstm(u3)
        elif isinstance(dec, _TCNDecoder):
            x = dec.inp(u3).transpose(1, 2)
            for conv in dec.convs:
                x = x + torch.relu(conv(x))
            h = x.transpose(1, 2)
        elif isinstance(dec, _TransformerDecoder):
            h = dec.enc(dec.inp(u3))
        else:  # pragma: no cover - build_decoder knows only these
            raise OnnxExportError(f"no ONNX graph for decoder {type(dec).__name__}")
        y = self.f_fc(h)
        return torch.sigmoid(y) if self.sigmoid else y


class _KarrasGraph(nn.Module):
    def __init__(self, head: KarrasConvNet, fps: float) -> None:
        super().__init__()
        self.head = head
        r = _ratio(head.feature_rate_hz, fps)
        self.num, self.den = r.numerator, r.denominator
        self.register_buffer("offs", (torch.arange(head.window) - head.window // 2).to(torch.int64))

    def forward(self, feats: Tensor, t: Any) -> Tensor:
        h = self.head
        t_feat = feats.shape[1]
        centre = _round_half_even(torch.arange(t, dtype=torch.int64) * self.num, self.den)
        idx = centre[:, None] + self.offs[None, :]  # (t, W)
        valid = ((idx >= 0) & (idx < t_feat)).to(feats.dtype)[None, ..., None]  # (1, t, W, 1)
        win = feats.index_select(1, idx.clamp(0, t_feat - 1).reshape(-1)).reshape(1, t, self.offs.shape[0], -1) * valid
        x = h.formant(win) * valid
        x = x[0].transpose(1, 2)  # (t, C, W)
        x = h.articulation(x)[:, :, 0][None]  # (1, t, C)
        y = h.fc(x)
        return torch.sigmoid(y) if h.output == "sigmoid" else y


class _MeanGraph(nn.Module):
    def __init__(self, head: MeanCurveBaseline) -> None:
        super().__init__()
        self.register_buffer("mean", head.mean.detach().clone().to(torch.float32))

    def forward(self, feats: Tensor | None, t: Any) -> Tensor:
        return self.mean[None, None, :].expand(1, t, N_VISEMES)


class CurveGraph(nn.Module):
    """``audio (1, n) float32 at sample_rate -> curves (1, round(n * fps / sample_rate), 16)`` in [0, 1]."""

    def __init__(self, model: AudioCurveModel, sample_rate: int, fps: float) -> None:
        super().__init__()
        head = model.head
        if isinstance(head, FaceFormerDecoder):
            raise OnnxExportError(NOT_EXPORTABLE["faceformer-fbank"])
        self.sample_rate, self.fps = int(sample_rate), float(fps)
        r = _ratio(fps, sample_rate)
        self.t_num, self.t_den = r.numerator, r.denominator
        self.resample = _Resample(sample_rate, MODEL_SAMPLE_RATE) if sample_rate != MODEL_SAMPLE_RATE else None
        self.features: nn.Module | None
        if isinstance(head, MeanCurveBaseline):
            self.features, self.head = None, _MeanGraph(head)
        else:
            self.features = _feature_graph(model.features)
            if isinstance(head, CurveModel):
                self.head = _CurveGraph(head, fps)
            elif isinstance(head, KarrasConvNet):
                self.head = _KarrasGraph(head, fps)
            else:
                raise OnnxExportError(f"no ONNX graph for head {type(head).__name__}")
        self.closure_peaks = model.closure_peaks   # the same arithmetic as torch's eval-mode forward
        # shortest input: one curve frame and one feature frame after resampling (also for the mean curve, whose
        # graph needs no features: torch's predict_curves computes them and fails below one window)
        n = 1
        while n_frames_for(n, sample_rate, fps) < 1:
            n += 1
        need = _min_feature_samples(model.features)
        m = math.ceil(need * sample_rate / MODEL_SAMPLE_RATE)
        while self.resample is not None and self.resample.out_len(m) < need:
            m += 1
        self.min_samples = max(n, m)
        # longest input: whisper graphs take one window (after resampling, when the graph resamples)
        self.max_samples: int | None = None
        top = getattr(self.features, "max_samples", None)
        if top is not None:
            if self.resample is None:
                self.max_samples = int(top)
            else:  # the largest n whose resampled length fits
                m = top * self.resample.down // self.resample.up
                while self.resample.out_len(m + 1) <= top:
                    m += 1
                while self.resample.out_len(m) > top:
                    m -= 1
                self.max_samples = int(m)

    def forward(self, audio: Tensor) -> Tensor:
        t = _round_half_even(audio.shape[1] * self.t_num, self.t_den)
        if self.features is None:
            y = self.head(None, t)
        else:
            x = self.resample(audio) if self.resample is not None else audio
            y = self.head(self.features(x), t)
        if self.closure_peaks is not None:
            y = self.closure_peaks(y, self.fps)
        return torch.clamp(y, 0.0, 1.0)


def build_export_module(
    model: AudioCurveModel, sample_rate: int = MODEL_SAMPLE_RATE, fps: float | None = None
) -> CurveGraph:
    """The torch module that :func:`export_onnx` traces (eval mode; ``fps`` defaults to the model's)."""
    if not isinstance(model, AudioCurveModel):
        raise OnnxExportError(f"expected an AudioCurveModel, got {type(model).__name__}")
    if sample_rate <= 0:
        raise OnnxExportError(f"sample_rate must be positive, got {sample_rate}")
    fps = float(model.head.curve_fps if fps is None else fps)
    if fps <= 0:
        raise OnnxExportError(f"fps must be positive, got {fps}")
    return CurveGraph(model, int(sample_rate), fps).eval()


# --------------------------------------------------------------------------------------------------
# loading


def _load(model_path: Path) -> tuple[AudioCurveModel, Any]:
    from visemeflow.learning.train import ModelFileError, load_model

    if not model_path.is_file():
        raise OnnxExportError(f"{model_path}: no such model file")
    try:
        model, config, _ = load_model(model_path)
    except ModelFileError as exc:
        raise OnnxExportError(str(exc)) from exc
    return model, config


# --------------------------------------------------------------------------------------------------
# export and check


def _drop_stale_reduce_attributes(proto: Any) -> None:
    """onnx's version converter moves Reduce* axes back to an attribute but keeps ``noop_with_empty_axes``,
    which only ReduceSum has before opset 18; at its default (0, with axes given) it means nothing: drop it."""
    for node in proto.graph.node:
        if node.op_type.startswith("Reduce") and node.op_type != "ReduceSum":
            for attr in list(node.attribute):
                if attr.name == "noop_with_empty_axes":
                    if attr.i != 0:
                        raise OnnxExportError(f"{node.op_type} with noop_with_empty_axes=1 has no opset<18 form")
                    node.attribute.remove(attr)


def _convert_opset(proto: Any, opset: int) -> Any:
    """The exporter writes opset 18; convert the optimised graph down (the exporter's own conversion runs before
    constant folding and fails on Reduce* axes inputs) and check that the result really is at ``opset``."""
    import onnx
    from onnx import version_converter

    if opset != _NATIVE_OPSET:
        try:
            proto = version_converter.convert_version(proto, opset)
        except Exception as exc:
            hint = (" (LayerNormalization, in transformer and wav2vec2 models, exists from opset 17: "
                    "use opset 17 or 18)" if "LayerNormalization" in str(exc) else "")
            raise OnnxExportError(f"the graph cannot be converted to opset {opset}: {str(exc)[:300]}{hint}") from exc
        _drop_stale_reduce_attributes(proto)
    versions = {o.domain or "ai.onnx": o.version for o in proto.opset_import}
    if versions.get("ai.onnx") != opset or set(versions) - {"ai.onnx"}:
        raise OnnxExportError(f"the exported graph uses opsets {versions}, not ai.onnx {opset} only")
    try:
        onnx.checker.check_model(proto, full_check=True)
    except Exception as exc:
        raise OnnxExportError(f"the opset-{opset} graph does not validate: {str(exc)[:300]}") from exc
    return proto


def _uses_float64(proto: Any) -> bool:
    from onnx import TensorProto

    double = TensorProto.DOUBLE
    if any(i.data_type == double for i in proto.graph.initializer):
        return True
    for node in proto.graph.node:
        for attr in node.attribute:
            if (node.op_type == "Cast" and attr.name == "to" and attr.i == double) or (
                attr.name == "value" and attr.t.data_type == double
            ):
                return True
    return False


def _name_dynamic_axes(proto: Any, out_dim: int = N_VISEMES) -> None:
    """Check that the time axes stayed symbolic (a traced constant would fail on other lengths) and name them."""
    (inp,), (out,) = proto.graph.input, proto.graph.output
    if inp.name != "audio" or out.name != "curves":
        raise OnnxExportError(f"unexpected graph signature {inp.name!r} -> {out.name!r}")
    in_dims, out_dims = inp.type.tensor_type.shape.dim, out.type.tensor_type.shape.dim
    if len(in_dims) != 2 or len(out_dims) != 3 or in_dims[0].dim_value != 1 or out_dims[2].dim_value != out_dim:
        raise OnnxExportError("unexpected input/output ranks in the exported graph")
    for what, d in (("audio samples", in_dims[1]), ("curve frames", out_dims[1])):
        if d.HasField("dim_value"):
            raise OnnxExportError(
                f"the exporter fixed the {what} axis to {d.dim_value}; the graph would not take other lengths"
            )
    in_dims[1].dim_param, out_dims[1].dim_param = "n_samples", "n_frames"


def check_signal(seconds: float, sample_rate: int = MODEL_SAMPLE_RATE, seed: int = 0) -> np.ndarray:
    """A deterministic speech-like mono signal (harmonic 'vowels' with a moving pitch, noise bursts, a pause)."""
    rng = np.random.default_rng(seed)
    n = max(1, round(seconds * sample_rate))
    t = np.arange(n) / sample_rate
    f0 = 120 + 30 * np.sin(2 * np.pi * 0.7 * t)
    phase = 2 * np.pi * np.cumsum(f0) / sample_rate
    voiced = sum(np.sin(h * phase) / h for h in range(1, 12))
    env = 0.5 * (1 + np.sin(2 * np.pi * 3.1 * t)) * (np.sin(2 * np.pi * 0.37 * t + 1) > -0.8)
    noise = rng.standard_normal(n) * (np.sin(2 * np.pi * 1.3 * t) > 0.6)
    floor = 1e-3 * rng.standard_normal(n)  # a recording's noise floor (no band at float32's log floor)
    return (0.2 * voiced * env + 0.05 * noise + floor).astype(np.float32)


WINDOW_S = 30.0  # the caller's windows for whisper graphs (whisper.py's window and overlap)
OVERLAP_S = 5.0


def onnx_curves(path: str | Path | Any, audio: np.ndarray, *, threads: int | None = None) -> np.ndarray:
    """(T, 16) curves of mono float32 ``audio`` (at the export's sample rate) from an exported file (onnxruntime;
    ``path`` may also be an open ``InferenceSession`` of one).

    A graph with a ``visemeflow.max_samples`` limit (whisper: one 30-s window) is run on longer audio in windows
    (:func:`windowed_curves`)."""
    sess = path if hasattr(path, "run") else _session(Path(path), threads)
    x = np.ascontiguousarray(np.asarray(audio, dtype=np.float32).reshape(-1))
    meta = sess.get_modelmeta().custom_metadata_map
    limit = meta.get("visemeflow.max_samples")
    if limit is not None and x.shape[0] > int(limit):
        return windowed_curves(lambda a: sess.run(["curves"], {"audio": a[None]})[0][0], x,
                               int(meta["visemeflow.sample_rate"]), float(meta["visemeflow.fps"]))
    return sess.run(["curves"], {"audio": x[None]})[0][0]


def windowed_curves(run: Any, audio: np.ndarray, sample_rate: int, fps: float,
                    window_s: float = WINDOW_S, overlap_s: float = OVERLAP_S) -> np.ndarray:
    """Curves of audio longer than one whisper graph's window: ``run(samples) -> (frames, 16)`` on windows of
    ``window_s`` every ``window_s - overlap_s`` (the last one moved back to end where the audio ends, as
    whisper.py's windows), each window's curves placed at ``n_frames_for(start)`` and crossfaded linearly over
    the overlaps (whisper.py's ramp, on curves instead of encoder features)."""
    n = audio.shape[0]
    win, ov = round(window_s * sample_rate), round(overlap_s * sample_rate)
    total = n_frames_for(n, sample_rate, fps)
    if n <= win:
        return run(audio)
    starts = list(range(0, n - win, win - ov))
    if n - win > starts[-1]:
        starts.append(n - win)
    out = np.zeros((total, N_VISEMES), np.float64)
    weight = np.zeros(total, np.float64)
    spans = [(n_frames_for(s, sample_rate, fps), n_frames_for(s + win, sample_rate, fps)) for s in starts]
    for i, s in enumerate(starts):
        y = run(np.ascontiguousarray(audio[s : s + win]))
        f0 = spans[i][0]
        m = min(y.shape[0], total - f0)
        w = np.ones(m)
        if i > 0:
            k = min(m, spans[i - 1][1] - f0)
            w[:k] = np.arange(1, k + 1) / (k + 1)
        if i + 1 < len(starts):
            k = min(m, f0 + m - spans[i + 1][0])
            w[m - k :] = np.minimum(w[m - k :], np.arange(k, 0, -1) / (k + 1))
        out[f0 : f0 + m] += w[:, None] * y[:m]
        weight[f0 : f0 + m] += w
    return (out / weight[:, None]).astype(np.float32)


def _session(model: Path | bytes, threads: int | None = None) -> Any:
    """An onnxruntime CPU session (all graph optimisations on, as engines run it) on a file or serialized model."""
    try:
        import onnxruntime as ort
    except ImportError as exc:  # pragma: no cover - dependency missing
        raise ImportError("checking an ONNX export needs `onnxruntime` (pip install onnxruntime)") from exc
    opts = ort.SessionOptions()
    if threads is not None:
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    source = model if isinstance(model, bytes) else str(model)
    return ort.InferenceSession(source, opts, providers=["CPUExecutionProvider"])


def _to_onnx(module: nn.Module, example: Tensor, opset: int, what: str = "the model", out_dim: int = N_VISEMES) -> Any:
    """ModelProto of ``module(audio (1, n)) -> (1, T, out_dim)``, dynamic n, at ``opset``; axes checked and named."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)  # torch-internal deprecation (pytree LeafSpec)
            # Dim.DYNAMIC, not a named Dim: the frame count round(n * fps / rate) (ties to even) is a symbolic
            # expression whose lower bounds the shape solver cannot prove; a named Dim turns that into an error
            exported = torch.export.export(
                module, (example,), dynamic_shapes=({1: torch.export.Dim.DYNAMIC},), strict=False
            )
            program = torch.onnx.export(
                exported, input_names=["audio"], output_names=["curves"], opset_version=_NATIVE_OPSET, dynamo=True,
                external_data=False, verbose=False,
                custom_translation_table={torch.ops.visemeflow.onnx_lstm.default: _lstm_translation()},
            )
    except Exception as exc:
        raise OnnxExportError(f"torch.onnx.export failed for {what}: {type(exc).__name__}: {exc}") from exc
    if program is None:  # pragma: no cover - dynamo=True always returns the program
        raise OnnxExportError("torch.onnx.export returned no program")
    proto = _convert_opset(program.model_proto, opset)
    _name_dynamic_axes(proto, out_dim)
    return proto


def _require(check: bool) -> None:
    import importlib.util

    need = ["onnx", "onnxscript"] + (["onnxruntime"] if check else [])
    missing = [m for m in need if importlib.util.find_spec(m) is None]
    if missing:
        raise ImportError(
            f"ONNX export needs {', '.join(missing)} (pip install {' '.join(missing)}); onnxruntime only for the "
            "check (check=False skips it)"
        )


def export_onnx(
    model_path: str | Path,
    out_path: str | Path,
    *,
    opset: int = DEFAULT_OPSET,
    sample_rate: int = MODEL_SAMPLE_RATE,
    fps: float | None = None,
    check: bool = True,
    check_seconds: float = 3.0,
    tolerance: float | None = None,
) -> ExportReport:
    """Export the model saved at ``model_path`` to ``out_path`` (one .onnx file; see the module docstring).

    ``fps`` defaults to the model's training fps. With ``check`` (default) the file is run with
    onnxruntime on :func:`check_signal` (``check_seconds``) and compared with ``predict_curves``;
    a difference over ``tolerance`` (default :data:`DEFAULT_TOLERANCE`, :data:`WHISPER_TOLERANCE` for whisper
    models) raises :class:`OnnxExportError`. The graph is checked in a temporary file beside ``out_path`` and
    replaces ``out_path`` only when it passed: a failed export leaves a previous file there as it was (``check=False``
    writes the unchecked graph, for inspection).
    """
    _require(check)
    import onnx

    from visemeflow.atomic import atomic_path

    model_path, out_path = Path(model_path), Path(out_path)
    if not MIN_OPSET <= opset <= MAX_OPSET:
        raise OnnxExportError(f"opset must be in [{MIN_OPSET}, {MAX_OPSET}], got {opset}")
    model, config = _load(model_path)
    if config.preset in NOT_EXPORTABLE:
        raise OnnxExportError(f"preset {config.preset!r} cannot be exported to ONNX: {NOT_EXPORTABLE[config.preset]}")
    graph = build_export_module(model, sample_rate, fps)
    whisper = isinstance(graph.features, _WhisperGraph)
    if tolerance is None:
        tolerance = WHISPER_TOLERANCE if whisper else DEFAULT_TOLERANCE
    t0 = time.perf_counter()
    proto = _to_onnx(graph, torch.from_numpy(check_signal(1.0, sample_rate))[None], opset, f"preset {config.preset!r}")
    meta = {
        "visemeflow.preset": config.preset,
        "visemeflow.sample_rate": str(graph.sample_rate),
        "visemeflow.fps": repr(graph.fps),
        "visemeflow.min_samples": str(graph.min_samples),
        "visemeflow.n_frames": "round(n_samples * fps / sample_rate), ties to even",
        "viseme_names": ",".join(VISEMES),
        "visemeflow.input": "audio: float32 (1, n_samples) mono",
        "visemeflow.output": "curves: float32 (1, n_frames, 16) in [0, 1]",
    }
    if getattr(model, "release_cut", None) is not None:
        meta["visemeflow.release_cut"] = RELEASE_CUT_NOTE
    if graph.max_samples is not None:
        meta["visemeflow.max_samples"] = str(graph.max_samples)
        meta["visemeflow.long_audio"] = (
            f"inputs over max_samples fail (ConstantOfShape, negative size); split longer audio into windows of "
            f"{WINDOW_S:g} s every {WINDOW_S - OVERLAP_S:g} s, the last ending where the audio ends, and crossfade "
            f"the curves linearly over each overlap (visemeflow.learning.onnx_export.onnx_curves does)"
        )
    del proto.metadata_props[:]
    for k, v in meta.items():
        proto.metadata_props.add(key=k, value=v)
    onnx.checker.check_model(proto)
    with atomic_path(out_path, keep_suffix=True) as tmp:
        onnx.save_model(proto, str(tmp))
        report = _report(out_path, tmp, proto, graph, config, model, opset, sample_rate, whisper,
                         time.perf_counter() - t0)
        if check:
            report = _check_export(tmp, out_path, report, model, graph, sample_rate, check_seconds, tolerance)
    return report


def _report(out_path: Path, written: Path, proto: Any, graph: CurveGraph, config: Any, model: AudioCurveModel,
            opset: int, sample_rate: int, whisper: bool, secs: float) -> ExportReport:
    """What :func:`export_onnx` wrote (the graph now at ``written``, to be at ``out_path``)."""
    ops = tuple(sorted({n.op_type for n in proto.graph.node}))
    notes: list[str] = []
    if sample_rate != MODEL_SAMPLE_RATE:
        notes.append(f"resamples {sample_rate} Hz -> {MODEL_SAMPLE_RATE} Hz inside the graph (float32 polyphase sinc)")
    else:
        notes.append("input must be 16 kHz mono: downmix (channel mean) and resample before calling")
    if whisper:
        notes.append(
            f"whisper: log-mel padded to one 30-s window and the encoder inside (weights float32); inputs up to "
            f"{graph.max_samples} samples; longer audio in windows crossfaded on the curves by the caller "
            "(onnx_curves), which is not what predict_curves computes (it crossfades encoder features)"
        )
    if getattr(model, "release_cut", None) is not None:
        notes.append(RELEASE_CUT_NOTE)
    uses_float64 = _uses_float64(proto)
    if uses_float64:
        notes.append(
            "float64 inside (LPC autocorrelation / Levinson-Durbin, as in torch): ONNX Runtime based engines "
            "(Unreal NNE ORT) run it; Unity Sentis / Inference Engine has no float64 tensors"
        )
    report = ExportReport(
        path=out_path, preset=config.preset, opset=opset, sample_rate=graph.sample_rate, fps=graph.fps,
        feature=model.features.config.kind if graph.features is not None else "none",
        min_samples=graph.min_samples, size_bytes=written.stat().st_size,
        stored_values=sum(int(np.prod(i.dims)) for i in proto.graph.initializer),
        ops=ops, uses_float64=uses_float64, export_seconds=secs, notes=tuple(notes),
        max_samples=graph.max_samples,
    )
    return report


def _check_export(written: Path, out_path: Path, report: ExportReport, model: AudioCurveModel, graph: CurveGraph,
                  sample_rate: int, check_seconds: float, tolerance: float) -> ExportReport:
    """``report`` with the check's figures: the graph at ``written`` run with onnxruntime against torch, or
    OnnxExportError naming ``out_path`` (where it was to go)."""
    from visemeflow.learning.train import predict_curves

    t1 = time.perf_counter()
    audio = check_signal(check_seconds, sample_rate)
    cut, model.release_cut = getattr(model, "release_cut", None), None      # the graph has no release cut
    try:
        want = predict_curves(model, audio, sample_rate, graph.fps)
    finally:
        model.release_cut = cut
    got = onnx_curves(written, audio)
    if got.shape != want.shape:
        raise OnnxExportError(f"{out_path}: ONNX gives {got.shape} curves, torch {want.shape} (check signal)")
    diff = float(np.abs(got - want).max()) if want.size else 0.0
    if not diff <= tolerance:
        raise OnnxExportError(f"{out_path}: ONNX curves differ from torch by {diff:.3g} > {tolerance:g} (check signal)")
    return ExportReport(**{**report.__dict__, "max_abs_diff": diff, "check_seconds": time.perf_counter() - t1})
