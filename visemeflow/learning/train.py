"""Training of the audio-to-viseme-curve models (paper Section 5.1 "Training").

Pure domain code (torch/numpy, no Prefect). Files are touched only by the checkpoint functions
inside :func:`train_model` (``checkpoint_dir/last.pt``) and by :func:`save_model` / :func:`load_model`.

Model files are untrusted input and never hold NaN: a checkpoint or model whose weights turned NaN or infinite (a
diverged run) is not written (:class:`NonFiniteWeightsError`; the previous file stays). Reading one
(:func:`read_model_file`, :func:`load_model`) checks the format, the configs, that each weight is a tensor the file
really stores and is finite, and then the weights' names and shapes against a skeleton of the configs' model on
the meta device, before anything is built, so a crafted config cannot make loading allocate beyond what the file
holds; anything else is a :class:`ModelFileError` naming the file and why.

Recipe (as in the paper): one utterance per optimisation step, L1 loss on the valid curve frames,
Adam at the preset's fixed learning rate (``TrainConfig.lr`` overrides it), SpecAugment on the
features of hand-crafted-feature presets (:func:`visemeflow.learning.presets.augment`), utterance
order reshuffled every epoch from a seeded generator. The ``mean-curve`` preset is *fit* (the
frame-weighted mean of the training curves), with no optimisation step.

Model: every preset becomes an :class:`~visemeflow.learning.model.AudioCurveModel` (feature
extractor + head), so a trained model maps 16 kHz audio to curves on its own. For ``wav2vec2-*``
presets the Wav2Vec2 model is part of the trained model (CNN encoder frozen, transformer
fine-tuned, and its own dropout / time masking active in training). Hand-crafted features
(fbank / mfcc / lpc, with per-utterance CMVN: ``FeatureConfig(normalize=True)``) have no
parameters; their features are computed once per training utterance and cached for the whole run
(recomputed each step only when an audio augmentation hook changes the audio).

Determinism and exact resume: ``torch.manual_seed(seed)`` before the model is built (same
initial weights), a ``numpy.random.Generator`` (PCG64, seed) for the epoch shuffles, a separate
``torch.Generator`` (seed + 1) for SpecAugment, another numpy Generator for the audio augmentation
hook. At the end of every epoch ``checkpoint_dir/last.pt`` is written atomically (``visemeflow.atomic``:
temporary file + ``os.replace``) with the model and optimizer states, epoch, step, history, and every RNG state
(torch CPU global state, SpecAugment generator state, the numpy generators' states as JSON strings,
numpy's legacy global state, which transformers uses for wav2vec2 time masking). The file holds
only tensors and plain Python values, and is read with ``torch.load(weights_only=True)``. A run
interrupted after epoch k and restarted with the same config (``epochs`` may differ) continues from
that checkpoint and ends with bit-identical weights to an uninterrupted run.

Devices (``device=``: ``cpu``, ``cuda``, ``cuda:N`` or ``auto``, :mod:`visemeflow.learning.device`): the model is
built and seeded on the CPU (same initial weights everywhere), then moved; every batch goes to the device,
forward passes run under :func:`~visemeflow.learning.device.autocast_context` (``precision=``: ``auto`` is bf16
on a CUDA GPU that has it; the CPU always runs float32, so CPU results are bit-identical whatever is asked) and
fp16 training uses loss scaling (the scaler's state is checkpointed). Hand-crafted features are always computed
in float32. Neither the device nor the precision is part of the config: a model or checkpoint does not record
where it was computed; checkpoints and model files are read with ``map_location="cpu"`` (a run started on a GPU
resumes on the CPU and the other way round) and model files hold CPU tensors. Exact resume is guaranteed on the
CPU only (CUDA kernels are not bit-reproducible); on CUDA the CUDA RNG state is checkpointed too.

Feature caches (results equal to recomputing, never a different number): parameter-free features of an
utterance's original audio are computed at its first step and kept for the run; for ``wav2vec2-*`` presets,
whose CNN feature encoder is frozen (and ``whisper-*`` presets, whose whole encoder is), the encoder's outputs for
original (not augmented) audio are kept in a :class:`~visemeflow.learning.features.EncoderOutputCache` keyed by
(encoder architecture + weights digest, audio content hash, device type and precision) (``encoder_cache=``: True
in memory, a folder to also keep them in files, False to run the encoder every step), so epochs after the first
skip the encoder. A step whose audio the augmentation hook changed always runs the extractor/encoder on that audio.

Batches (``TrainConfig.batch_size``; 1, the default, is the paper's recipe and gives bit-identical results to
versions before batches existed): each epoch's shuffled order is cut into buckets of ``batch_size *
bucket_batches`` utterances, each bucket is sorted by audio length (stable, so ties keep the shuffled order) and
cut into batches of ``batch_size`` (never mixing curve frame rates), and the batches' order is shuffled (from the
same seeded generator). ``max_steps_per_epoch`` counts batches. Padding: features are computed per utterance
(hand-crafted ones, and wav2vec2's CNN encoder outputs) and padded with zeros; wav2vec2's transformer gets the
attention mask of the real samples (padded frames are zeroed before its positional convolution and never
attended to); the decoder gets each utterance's frame count (packed LSTMs, masked TCN/transformer,
interpolation that never reads past the last valid feature frame); the L1 loss averages over the valid frames of
the batch (longer utterances weigh more, as frames do in ``evaluate``). What the padding holds changes nothing.
With the wav2vec2 encoder cache switched off, a batch runs the CNN encoder on the zero-padded batch (equal to the
per-utterance outputs to float rounding, ~1e-6); with ``batch_size=1`` cached and uncached runs are bit-identical.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import pickle
import re
import time
import zipfile
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import ValidationError
from torch import Tensor, nn

from visemeflow.atomic import atomic_write
from visemeflow.hashing import new_hasher
from visemeflow.learning.device import (
    autocast_context,
    grad_scaler,
    model_device,
    resolve_device,
    resolve_precision,
)
from visemeflow.learning.features import (
    EncoderOutputCache,
    FeatureConfig,
    Wav2Vec2Extractor,
    WhisperExtractor,
    build_feature_extractor,
    resample_audio,
)
from visemeflow.learning.config import AugmentConfig, TrainConfig
from visemeflow.learning.model import AudioCurveModel, ClosurePeaks, CurveModel, MeanCurveBaseline, ReleaseCut, l1_loss
from visemeflow.learning.presets import (
    Preset,
    augment,
    build_model,
    build_optimizer,
)
from visemeflow.visemes import N_VISEMES

__all__ = [
    "SAMPLE_RATE",
    "EpochReport",
    "Example",
    "ModelFile",
    "ModelFileError",
    "NonFiniteWeightsError",
    "TrainConfig",
    "TrainResult",
    "apply_audio_augment",
    "build_training_model",
    "evaluate",
    "length_batches",
    "load_model",
    "predict_curves",
    "read_model_file",
    "resample_curves",
    "save_model",
    "train_model",
]

SAMPLE_RATE = 16000
CHECKPOINT_NAME = "last.pt"
_MODEL_FORMAT = "visemeflow-curve-model/1"
_CKPT_FORMAT = "visemeflow-train-checkpoint/1"

AudioAugment = Callable[[np.ndarray, np.random.Generator], tuple[np.ndarray, float]]


class ModelFileError(ValueError):
    """A file given as a model that is not one this version can use; names the file and why."""

    def __init__(self, path: str | Path, reason: str):
        super().__init__(f"{path} is not a visemeflow model file (expected a file written by visemeflow train / "
                         f"save_model): {reason}")
        self.path, self.reason = str(path), reason

    def __reduce__(self):  # keeps the two-argument constructor picklable (Prefect ships exceptions)
        return (type(self), (self.path, self.reason))


class NonFiniteWeightsError(ValueError):
    """Weights holding NaN or infinite values, refused before a model or checkpoint file is written."""

    def __init__(self, path: str | Path, reason: str):
        super().__init__(f"{path}: not written: {reason}")
        self.path, self.reason = str(path), reason

    def __reduce__(self):
        return (type(self), (self.path, self.reason))


# --------------------------------------------------------------------------------------------------
# data types


@dataclass(frozen=True)
class Example:
    """One training utterance: mono 16 kHz float32 audio and its (T, 16) target curves at ``fps``."""

    utterance_id: str
    audio: np.ndarray
    curves: np.ndarray
    fps: float
    # (T,) int: the viseme index (visemeflow.visemes.VISEME_INDEX) of the phone at each curve frame, -1 where there
    # is none (silence, no alignment); only read by the auxiliary viseme loss (TrainConfig.viseme_loss_weight)
    visemes: np.ndarray | None = None


@dataclass
class EpochReport:
    epoch: int  # 1-based
    steps: int  # optimisation steps (batches) in this epoch
    train_l1_x100: float  # mean per-step training L1 x 100 (with augmentation, train mode)
    val_l1_x100: float | None  # evaluate() on the validation set; None without one
    seconds: float  # wall time of the training steps of this epoch
    frames_per_s: float  # trained curve frames per second of training


@dataclass
class TrainResult:
    model: nn.Module
    history: list[EpochReport] = field(default_factory=list)
    checkpoint: Path | None = None


# --------------------------------------------------------------------------------------------------
# model construction


def _feature_config(config: TrainConfig, preset: Preset) -> FeatureConfig:
    if config.whisper_tune_layers and preset.feature != "whisper":
        raise ValueError(f"whisper_tune_layers: preset {preset.name!r} has no Whisper encoder (its feature is "
                         f"{preset.feature})")
    if preset.feature == "wav2vec2":
        if not config.wav2vec2_model:
            raise ValueError(f"preset {preset.name!r} needs TrainConfig.wav2vec2_model (path or hub id)")
        return FeatureConfig(kind="wav2vec2", wav2vec2_model=config.wav2vec2_model)
    if preset.feature == "whisper":
        return FeatureConfig(kind="whisper", whisper_source=config.whisper_source or preset.whisper_source or "package",
                             whisper_layers=config.whisper_layers or "last",
                             whisper_tune_layers=config.whisper_tune_layers)
    return FeatureConfig(kind=preset.feature, normalize=True, options=dict(preset.feature_options))


def _assemble(config: TrainConfig, feature_module: nn.Module, curve_fps: float) -> AudioCurveModel:
    preset = config.resolved_preset()
    head = build_model(
        preset, feature_module.dim, feature_module.frame_rate_hz, curve_fps, d_model=config.d_model
    )
    peaks = (ClosurePeaks(config.mbp_peaks_half_window_s, config.mbp_peaks_power, config.mbp_lead_s,
                          config.mbp_others_power)
             if config.mbp_peaks_half_window_s > 0 else None)
    cut = ReleaseCut(config.mbp_release_rise_db) if config.mbp_release_rise_db > 0 else None
    return AudioCurveModel(feature_module, head, peaks, cut)


def build_training_model(config: TrainConfig, curve_fps: float) -> AudioCurveModel:
    """The (untrained) feature extractor + head for ``config``; seeds torch's global RNG first."""
    preset = config.resolved_preset()
    fcfg = _feature_config(config, preset)
    torch.manual_seed(config.seed)
    features = build_feature_extractor(fcfg)
    torch.manual_seed(config.seed)  # head init independent of how the extractor was built
    return _assemble(config, features, curve_fps)


# --------------------------------------------------------------------------------------------------
# augmentation helpers


def resample_curves(curves: np.ndarray, time_factor: float) -> np.ndarray:
    """Curves of audio sped up by ``time_factor``: ``round(T / time_factor)`` frames, linear interp.

    New frame ``k`` (time ``k / fps`` in the sped-up audio) is original time ``k * time_factor /
    fps``, i.e. original frame position ``k * time_factor`` (clamped to the last frame).
    """
    curves = np.asarray(curves, dtype=np.float32)
    if time_factor <= 0:
        raise ValueError(f"time_factor must be positive, got {time_factor}")
    if time_factor == 1.0 or curves.shape[0] == 0:
        return curves
    t = curves.shape[0]
    n = max(1, round(t / time_factor))
    pos = np.minimum(np.arange(n, dtype=np.float64) * time_factor, t - 1)
    i0 = np.floor(pos).astype(np.int64)
    i1 = np.minimum(i0 + 1, t - 1)
    w = (pos - i0)[:, None]
    return (curves[i0] * (1 - w) + curves[i1] * w).astype(np.float32)


def apply_audio_augment(
    example: Example, augment_audio: AudioAugment, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Run the hook on the example's audio; returns (audio, curves resampled by its time factor)."""
    audio, factor = augment_audio(example.audio, rng)
    audio = np.asarray(audio, dtype=np.float32)
    return audio, resample_curves(example.curves, float(factor))


# --------------------------------------------------------------------------------------------------
# RNG state (de)serialisation: only tensors / plain values, for torch.load(weights_only=True)


def _np_gen_state(g: np.random.Generator) -> str:
    return json.dumps(g.bit_generator.state)


def _set_np_gen_state(g: np.random.Generator, s: str) -> None:
    g.bit_generator.state = json.loads(s)


def _np_global_state() -> dict[str, Any]:
    name, keys, pos, has_gauss, cached = np.random.get_state()
    return {"name": name, "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)), "pos": int(pos),
            "has_gauss": int(has_gauss), "cached": float(cached)}


def _set_np_global_state(s: dict[str, Any]) -> None:
    np.random.set_state(
        (s["name"], s["keys"].numpy().astype(np.uint32), s["pos"], s["has_gauss"], s["cached"])
    )


def _data_fingerprint(examples: Sequence[Example]) -> str:
    h = hashlib.sha256()
    for ex in examples:
        h.update(ex.utterance_id.encode())
        h.update(np.ascontiguousarray(ex.audio, dtype=np.float32).tobytes())
        h.update(np.ascontiguousarray(ex.curves, dtype=np.float32).tobytes())
        h.update(repr(float(ex.fps)).encode())
    return h.hexdigest()


def _resume_key(config: TrainConfig) -> str:
    return config.model_copy(update={"epochs": 0}).model_dump_json()


def _atomic_torch_save(obj: Any, path: Path) -> None:
    # visemeflow.atomic: stdlib-only, so this pure package need not import storage (DESIGN)
    atomic_write(path, lambda tmp: torch.save(obj, tmp))


def _non_finite_weights(state: dict[str, Tensor]) -> str | None:
    """`3,216 of 3,232 weights are NaN or infinite (in head.f_proj.weight, ...)`, or None when all are finite."""
    bad, total, where = 0, 0, []
    for name, value in state.items():
        if not torch.is_floating_point(value):
            continue
        n = int((~torch.isfinite(value.detach())).sum())
        total += value.numel()
        if n:
            bad += n
            where.append(name)
    if not bad:
        return None
    more = f", ... ({len(where)} tensors)" if len(where) > 3 else ""
    return f"{bad:,} of {total:,} weights are NaN or infinite (in {', '.join(where[:3])}{more})"


def _refuse_non_finite(state: dict[str, Tensor], path: Path, when: str) -> None:
    """NonFiniteWeightsError before `path` is written, when `state` holds a NaN or infinite weight."""
    found = _non_finite_weights(state)
    if found is not None:
        kept = "the previous file is kept" if path.exists() else "nothing was written"
        raise NonFiniteWeightsError(path, f"{found} {when}: the training diverged (check the audio's amplitude and "
                                          f"the learning rate); {kept}")


# --------------------------------------------------------------------------------------------------
# training


def _check_examples(examples: Sequence[Example], what: str) -> None:
    for ex in examples:
        a, c = np.asarray(ex.audio), np.asarray(ex.curves)
        if a.ndim != 1:
            raise ValueError(f"{what} {ex.utterance_id!r}: audio must be mono (samples,), got {a.shape}")
        if c.ndim != 2 or c.shape[1] != N_VISEMES:
            raise ValueError(f"{what} {ex.utterance_id!r}: curves must be (T, {N_VISEMES}), got {c.shape}")
        if ex.fps <= 0:
            raise ValueError(f"{what} {ex.utterance_id!r}: fps must be positive")


def _audio_tensors(audio: np.ndarray, device: torch.device | None = None) -> tuple[Tensor, Tensor]:
    a = torch.from_numpy(np.ascontiguousarray(audio, dtype=np.float32))[None]
    lengths = torch.tensor([a.shape[1]], dtype=torch.long)
    if device is not None:
        a, lengths = a.to(device), lengths.to(device)
    return a, lengths


def _audio_hash(audio: np.ndarray) -> str:
    """Content hash of the float32 samples (what the wav2vec2 encoder cache is keyed on)."""
    h = new_hasher()
    a = np.ascontiguousarray(audio, dtype=np.float32)
    h.update(str(a.shape[0]).encode() + b"\0")
    h.update(a.tobytes())
    return h.hexdigest()


def _pad_audio(audios: Sequence[np.ndarray], device: torch.device) -> tuple[Tensor, Tensor]:
    """(B, max samples) zero-padded audio and (B,) lengths; one utterance: exactly :func:`_audio_tensors`."""
    if len(audios) == 1:
        return _audio_tensors(audios[0], device)
    lengths = torch.tensor([len(a) for a in audios], dtype=torch.long)
    batch = torch.zeros(len(audios), int(lengths.max()), dtype=torch.float32)
    for j, a in enumerate(audios):
        batch[j, : len(a)] = torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))
    return batch.to(device), lengths.to(device)


def _pad_time(tensors: Sequence[Tensor], dim: int) -> Tensor:
    """Concatenate (1, ...) tensors along the batch, zero-padding dimension ``dim`` to the longest."""
    if len(tensors) == 1:
        return tensors[0]
    size = max(t.shape[dim] for t in tensors)
    out = tensors[0].new_zeros((len(tensors), *[size if d == dim else n for d, n in enumerate(tensors[0].shape)][1:]))
    for j, t in enumerate(tensors):
        out[j].narrow(dim - 1, 0, t.shape[dim]).copy_(t[0])
    return out


def _pad_curves(curves: Sequence[np.ndarray], device: torch.device) -> tuple[Tensor, Tensor]:
    """(B, max T, 16) zero-padded targets on ``device`` and (B,) frame counts (CPU)."""
    if len(curves) == 1:
        target = torch.from_numpy(np.ascontiguousarray(curves[0]))[None]
        return target.to(device), torch.tensor([target.shape[1]], dtype=torch.long)
    n_frames = torch.tensor([c.shape[0] for c in curves], dtype=torch.long)
    target = torch.zeros(len(curves), int(n_frames.max()), N_VISEMES, dtype=torch.float32)
    for j, c in enumerate(curves):
        target[j, : c.shape[0]] = torch.from_numpy(np.ascontiguousarray(c, dtype=np.float32))
    return target.to(device), n_frames


def length_batches(
    order: Sequence[int], lengths: Sequence[int], fps: Sequence[float], batch_size: int, bucket_batches: int,
    rng: np.random.Generator,
) -> list[np.ndarray]:
    """One epoch's batches of example indices from its shuffled ``order`` (see the module docstring).

    ``batch_size == 1``: one index per batch in ``order`` and ``rng`` untouched (the paper's recipe, as before
    batches existed). Otherwise buckets of ``batch_size * bucket_batches`` consecutive indices of ``order``, each
    sorted by (fps, length) (stable) and cut into batches of at most ``batch_size`` that share one fps; the
    batches are then put in an order drawn from ``rng``.
    """
    order = np.asarray(order, dtype=np.int64)
    if batch_size == 1:
        return [order[k : k + 1] for k in range(len(order))]
    span = batch_size * bucket_batches
    batches: list[np.ndarray] = []
    for s in range(0, len(order), span):
        bucket = sorted(order[s : s + span].tolist(), key=lambda i: (float(fps[i]), int(lengths[i])))
        run: list[int] = []
        for i in bucket:
            if run and (len(run) == batch_size or float(fps[run[0]]) != float(fps[i])):
                batches.append(np.asarray(run, dtype=np.int64))
                run = []
            run.append(i)
        if run:
            batches.append(np.asarray(run, dtype=np.int64))
    return [batches[k] for k in rng.permutation(len(batches))]


@dataclass
class _Item:
    """One utterance of a step: its index, the audio and targets it trains on, and whether that audio is the
    example's own (not changed by augmentation), so its cached features may stand in."""

    index: int
    audio: np.ndarray
    curves: np.ndarray
    original: bool
    visemes: np.ndarray | None = None


def _encoder_cache(option: bool | str | Path | EncoderOutputCache | None) -> EncoderOutputCache | None:
    if option is None or option is False:
        return None
    if isinstance(option, EncoderOutputCache):
        return option
    return EncoderOutputCache(None if option is True else Path(option))


def _resample_labels(labels: np.ndarray | None, n: int) -> np.ndarray | None:
    """Per-frame labels stretched to ``n`` frames (nearest frame), as :func:`resample_curves` stretches curves."""
    if labels is None:
        return None
    labels = np.asarray(labels)
    if len(labels) == 0 or n == len(labels):
        return labels
    idx = np.minimum((np.arange(n) * len(labels) / n).astype(np.int64), len(labels) - 1)
    return labels[idx]


class _VisemeAux:
    """The auxiliary viseme classifier of ``TrainConfig.viseme_loss_weight``: a linear layer (built after the model,
    from the seeded torch RNG) on the decoder's output features, which a forward hook keeps from each step."""

    def __init__(self, model: AudioCurveModel, config: TrainConfig, device: torch.device) -> None:
        head = model.head
        if not isinstance(head, CurveModel):
            raise ValueError(f"viseme_loss_weight needs a curve-model preset (f_proj -> decoder -> f_fc); "
                             f"{config.preset!r} has {type(head).__name__}")
        self.weight = float(config.viseme_loss_weight)
        self.linear = nn.Linear(head.f_fc.in_features, N_VISEMES).to(device)
        self.hidden: Tensor | None = None
        self._handle = head.drop.register_forward_hook(self._keep)

    def _keep(self, module: nn.Module, args: Any, output: Tensor) -> None:
        self.hidden = output

    def close(self) -> None:
        self._handle.remove()

    def loss(self, items: Sequence[_Item], mask: Tensor) -> Tensor:
        assert self.hidden is not None
        h = self.hidden.float()
        labels = torch.full(mask.shape, -1, dtype=torch.long)
        for b, it in enumerate(items):
            if it.visemes is not None:
                v = torch.as_tensor(np.asarray(it.visemes, dtype=np.int64)[: mask.shape[1]])
                labels[b, : len(v)] = v
        labels = labels.to(h.device)
        labels[~mask.to(h.device)] = -1
        if not bool((labels >= 0).any()):
            return h.sum() * 0.0
        logits = self.linear(h)
        return self.weight * nn.functional.cross_entropy(logits.reshape(-1, N_VISEMES), labels.reshape(-1),
                                                         ignore_index=-1)


class Trainer:
    """One training run of :func:`train_model`, in the steps a maintainer changes one at a time: ``__init__`` sets
    up the model, optimizer, auxiliary loss and random generators (in that order: the seeded torch generator builds
    the model, then the auxiliary classifier), :meth:`resume` loads a checkpoint, :meth:`prepare_features` sets up
    the feature caches, :meth:`features_of` computes (or takes cached) features, :meth:`items_of` applies the
    augmentation hook, :meth:`step` is one optimisation step, :meth:`run_epoch` one epoch, :meth:`checkpoint` writes
    ``last.pt``, :meth:`fit` runs them all.
    Same arguments as :func:`train_model`."""

    def __init__(
        self,
        train: Sequence[Example],
        val: Sequence[Example],
        config: TrainConfig,
        checkpoint_dir: Path | None = None,
        on_epoch: Callable[[EpochReport], None] | None = None,
        augment_audio: AudioAugment | None = None,
        *,
        device: str | torch.device = "cpu",
        precision: str | None = "auto",
        encoder_cache: bool | str | Path | EncoderOutputCache | None = True,
        loss: Callable[[Tensor, Tensor, Tensor], Tensor] | None = None,
    ) -> None:
        if not train:
            raise ValueError("no training examples")
        _check_examples(train, "training example")
        _check_examples(val, "validation example")
        self.train, self.val, self.config, self.on_epoch, self.loss = train, val, config, on_epoch, loss
        self.dev = resolve_device(device)
        self.amp = resolve_precision(self.dev, precision)
        self.hook: AudioAugment | None = None
        default_hook = config.train_augment and augment_audio is None   # its speed range is AugmentConfig's
        if config.train_augment:
            if augment_audio is None:
                from visemeflow.learning.augment import train_augment_hook

                augment_audio = train_augment_hook(probability=config.train_augment_probability,
                                                   sample_rate=SAMPLE_RATE)
            self.hook = augment_audio
        self.preset = config.resolved_preset()
        self.model = build_training_model(config, float(train[0].fps)).to(self.dev)
        self.history: list[EpochReport] = []
        self.ckpt_path = Path(checkpoint_dir) / CHECKPOINT_NAME if checkpoint_dir is not None else None
        self._encoder_cache_arg = encoder_cache
        if not self.preset.trainable:
            return
        tuned = self.model.features.tuned_parameters() if isinstance(self.model.features, WhisperExtractor) else []
        if tuned:
            windows = self.model.features.windows
            # train_augment's speed changes lengthen audio by up to 1 / the slowest factor (a custom hook: as given)
            slowest = min(AugmentConfig().speed[0], 1.0) if default_hook else 1.0
            long = [ex.utterance_id for ex in train if not windows.fits_one_window(math.ceil(len(ex.audio) / slowest))]
            if long:
                limit = windows.window * 0.01 * slowest   # mel frames are 10 ms
                raise ValueError(f"whisper_tune_layers={config.whisper_tune_layers}: tuned Whisper blocks train on "
                                 f"utterances of at most {limit:g} s"
                                 + (" (30 s at the slowest train_augment speed)" if slowest < 1 else "")
                                 + f"; {len(long)} are longer ({', '.join(long[:3])}{', ...' if len(long) > 3 else ''})"
                                 ": cut them or tune none")
        optimizer = build_optimizer(self.preset, self.model, slow=tuned, slow_lr=config.whisper_tune_lr)
        if optimizer is None:
            raise ValueError(f"preset {self.preset.name!r} has no trainable parameters")
        self.optimizer = optimizer
        self.aux = _VisemeAux(self.model, config, self.dev) if config.viseme_loss_weight > 0 else None
        if self.aux is not None:
            optimizer.add_param_group({"params": list(self.aux.linear.parameters())})
        self.scaler = grad_scaler(self.dev, self.amp)
        self.shuffle_rng = np.random.default_rng(config.seed)
        self.augment_rng = np.random.default_rng([config.seed, 2])
        self.spec_gen = torch.Generator().manual_seed(config.seed + 1)
        np.random.seed(config.seed % (2**32))  # legacy global RNG (wav2vec2 time masking in transformers)
        self.start_epoch, self.n_steps = 0, 0
        self.fingerprint = _data_fingerprint(train)
        self.lengths_of = [len(ex.audio) for ex in train]
        self.fps_of = [float(ex.fps) for ex in train]

    def resume(self) -> None:
        """Continue from ``last.pt`` when there is one; it must come from the same config and data."""
        ckpt_path = self.ckpt_path
        if ckpt_path is None or not ckpt_path.exists():
            return
        ck = torch.load(ckpt_path, map_location="cpu", weights_only=True)
        if ck.get("format") != _CKPT_FORMAT or ck.get("resume_key") != _resume_key(self.config):
            raise ValueError(f"{ckpt_path} was written for a different training config; remove it or use another dir")
        if ck.get("data") != self.fingerprint:
            raise ValueError(f"{ckpt_path} was written for different training data")
        self.model.load_state_dict(ck["model"])
        if self.aux is not None:
            self.aux.linear.load_state_dict(ck["viseme_aux"])
        self.optimizer.load_state_dict(ck["optimizer"])
        if ck.get("scaler") and self.scaler.is_enabled():
            self.scaler.load_state_dict(ck["scaler"])
        self.start_epoch, self.n_steps = int(ck["epoch"]), int(ck["step"])
        self.history = [EpochReport(**h) for h in ck["history"]]
        torch.set_rng_state(ck["rng"]["torch"])
        if "cuda" in ck["rng"] and self.dev.type == "cuda":
            torch.cuda.set_rng_state(ck["rng"]["cuda"], self.dev)
        self.spec_gen.set_state(ck["rng"]["spec_augment"])
        _set_np_gen_state(self.shuffle_rng, ck["rng"]["shuffle"])
        _set_np_gen_state(self.augment_rng, ck["rng"]["augment"])
        _set_np_global_state(ck["rng"]["numpy_global"])

    def prepare_features(self) -> None:
        """Feature caches: parameter-free extractors keep each utterance's features; wav2vec2 keeps its frozen CNN
        outputs, whisper its frozen encoder's (in the encoder cache)."""
        feats = self.model.features
        self.w2v = (feats if isinstance(feats, (Wav2Vec2Extractor, WhisperExtractor)) and feats.encoder_frozen
                    else None)
        self.enc_cache = (_encoder_cache(self._encoder_cache_arg)
                          if self.w2v is not None and self.start_epoch < self.config.epochs else None)
        self.enc_fingerprint = (self.w2v.encoder_fingerprint() if self.enc_cache is not None and self.w2v is not None
                                else "")
        self.enc_tag = f"{self.dev.type}-{self.amp or 'fp32'}"
        self.audio_hashes: dict[int, str] = {}
        self.has_feature_params = any(True for _ in feats.parameters())
        self.feat_cache: dict[int, tuple[Tensor, Tensor]] = {}

    def features_of(self, items: list[_Item]) -> tuple[Tensor, Tensor]:
        """(features (B, T, D), lengths (B,)) of a step's items."""
        model, dev, w2v = self.model, self.dev, self.w2v
        if w2v is not None:  # per-utterance CNN outputs (cached for original audio), the transformer batched
            audio, lengths = _pad_audio([it.audio for it in items], dev)
            if self.enc_cache is None:
                return model.features(audio, lengths)
            encoded = []
            for it in items:
                one = _audio_tensors(it.audio, dev)[0]
                if it.original:
                    if it.index not in self.audio_hashes:
                        self.audio_hashes[it.index] = _audio_hash(it.audio)
                    encoded.append(self.enc_cache.get_or_encode(w2v, self.enc_fingerprint, one,
                                                                self.audio_hashes[it.index], self.enc_tag))
                else:
                    encoded.append(w2v.encode(one))
            return model.features(audio, lengths, encoded=_pad_time(encoded, 2))
        if not self.has_feature_params:  # per utterance, float32 (outside autocast), padded with zeros
            per = []
            with torch.autocast(dev.type, enabled=False) if self.amp is not None else contextlib.nullcontext():
                for it in items:
                    if not it.original:
                        per.append(model.features(*_audio_tensors(it.audio, dev)))
                        continue
                    if it.index not in self.feat_cache:
                        with torch.no_grad():
                            self.feat_cache[it.index] = model.features(*_audio_tensors(it.audio, dev))
                    per.append(self.feat_cache[it.index])
            if len(per) == 1:
                return per[0]
            return _pad_time([f for f, _ in per], 1), torch.cat([n for _, n in per])
        return model.features(*_pad_audio([it.audio for it in items], dev))

    def items_of(self, batch: Sequence[int]) -> list[_Item]:
        """The batch's examples, through the augmentation hook (its targets resampled by the hook's time factor)."""
        items = []
        for i in batch:
            ex = self.train[int(i)]
            if self.hook is not None:
                raw, factor = self.hook(ex.audio, self.augment_rng)
                if raw is not ex.audio or float(factor) != 1.0:
                    curves = resample_curves(ex.curves, float(factor))
                    items.append(_Item(int(i), np.asarray(raw, dtype=np.float32), curves, False,
                                       _resample_labels(ex.visemes, len(curves))))
                    continue
            items.append(_Item(int(i), ex.audio, np.asarray(ex.curves, dtype=np.float32), True, ex.visemes))
        return items

    def step(self, items: list[_Item], fps: float) -> tuple[float, int]:
        """One optimisation step on ``items``: (its loss, the curve frames it trained on)."""
        with autocast_context(self.dev, self.amp):
            feats, feat_lengths = self.features_of(items)
            feats = augment(self.preset, feats, feat_lengths, generator=self.spec_gen)
            target, n_frames = _pad_curves([it.curves for it in items], self.dev)
            pred, mask = self.model.head(feats, feat_lengths, n_frames, targets=target, fps=fps)
        step_loss = (self.loss or l1_loss)(pred.float(), target, mask)
        if self.aux is not None:
            step_loss = step_loss + self.aux.loss(items, mask)
        self.optimizer.zero_grad(set_to_none=True)
        self.scaler.scale(step_loss).backward()
        self.scaler.step(self.optimizer)
        self.scaler.update()
        self.n_steps += 1
        return float(step_loss.detach()), int(n_frames.sum())

    def run_epoch(self, epoch: int) -> EpochReport:
        """Epoch ``epoch`` (0-based): shuffled length batches, a step each, then validation."""
        self.model.train()
        config = self.config
        order = self.shuffle_rng.permutation(len(self.train))
        batches = length_batches(order, self.lengths_of, self.fps_of, config.batch_size, config.bucket_batches,
                                 self.shuffle_rng)
        if config.max_steps_per_epoch is not None:
            batches = batches[: config.max_steps_per_epoch]
        losses: list[float] = []
        frames = 0
        t0 = time.perf_counter()
        for batch in batches:
            step_loss, n = self.step(self.items_of(batch), self.fps_of[int(batch[0])])
            losses.append(step_loss)
            frames += n
        secs = time.perf_counter() - t0
        val_l1 = evaluate(self.model, self.val)[0] if self.val else None
        return EpochReport(
            epoch=epoch + 1, steps=len(batches), train_l1_x100=100.0 * float(np.mean(losses)) if losses else math.nan,
            val_l1_x100=val_l1, seconds=secs, frames_per_s=frames / max(secs, 1e-9),
        )

    def checkpoint(self, epoch: int) -> None:
        """Write ``last.pt`` after epoch ``epoch`` (0-based): weights, optimizer, history and every generator's
        state, so a resumed run goes on exactly as an uninterrupted one; never a model with non-finite weights."""
        assert self.ckpt_path is not None
        dev = self.dev
        rng_state: dict[str, Any] = {
            "torch": torch.get_rng_state(),
            "spec_augment": self.spec_gen.get_state(),
            "shuffle": _np_gen_state(self.shuffle_rng),
            "augment": _np_gen_state(self.augment_rng),
            "numpy_global": _np_global_state(),
        }
        if dev.type == "cuda":
            rng_state["cuda"] = torch.cuda.get_rng_state(dev)
        state = {
            "format": _CKPT_FORMAT,
            "resume_key": _resume_key(self.config),
            "data": self.fingerprint,
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "epoch": epoch + 1,
            "step": self.n_steps,
            "history": [asdict(h) for h in self.history],
            "rng": rng_state,
        }
        if self.scaler.is_enabled():
            state["scaler"] = self.scaler.state_dict()
        if self.aux is not None:
            state["viseme_aux"] = self.aux.linear.state_dict()
        # a diverged run must not replace the last good epoch it could resume from
        aux_state = {f"viseme_aux.{k}": v for k, v in state.get("viseme_aux", {}).items()}
        _refuse_non_finite({**state["model"], **aux_state}, self.ckpt_path, f"after epoch {epoch + 1}")
        _atomic_torch_save(state, self.ckpt_path)

    def _fit_mean(self) -> TrainResult:
        """mean-curve: fitted, no steps."""
        model = self.model
        t0 = time.perf_counter()
        if not isinstance(model.head, MeanCurveBaseline):
            raise TypeError(f"preset {self.preset.name!r} is not trainable and has no fit()")
        model.head.fit([ex.curves for ex in self.train])
        secs = time.perf_counter() - t0
        frames = sum(int(np.asarray(ex.curves).shape[0]) for ex in self.train)
        train_l1, _, _ = evaluate(model, self.train)
        val_l1 = evaluate(model, self.val)[0] if self.val else None
        report = EpochReport(1, 0, train_l1, val_l1, secs, frames / max(secs, 1e-9))
        if self.on_epoch is not None:
            self.on_epoch(report)
        return TrainResult(model, [report], None)

    def fit(self) -> TrainResult:
        """Resume if there is a checkpoint, train the remaining epochs (a checkpoint and ``on_epoch`` after each)."""
        if not self.preset.trainable:
            return self._fit_mean()
        self.resume()
        self.prepare_features()
        for epoch in range(self.start_epoch, self.config.epochs):
            report = self.run_epoch(epoch)
            self.history.append(report)
            if self.ckpt_path is not None:
                self.checkpoint(epoch)
            if self.on_epoch is not None:
                self.on_epoch(report)
        if self.aux is not None:
            self.aux.close()
        self.model.eval()
        return TrainResult(self.model, self.history, self.ckpt_path)


def train_model(
    train: Sequence[Example],
    val: Sequence[Example],
    config: TrainConfig,
    checkpoint_dir: Path | None = None,
    on_epoch: Callable[[EpochReport], None] | None = None,
    augment_audio: AudioAugment | None = None,
    *,
    device: str | torch.device = "cpu",
    precision: str | None = "auto",
    encoder_cache: bool | str | Path | EncoderOutputCache | None = True,
    loss: Callable[[Tensor, Tensor, Tensor], Tensor] | None = None,
) -> TrainResult:
    """Train ``config.preset`` on ``train`` (see the module docstring); validate on ``val`` each epoch.

    When ``config.train_augment`` is true, every training utterance of a step passes through
    ``augment_audio(audio, rng) -> (audio, time_factor)`` (default:
    :func:`visemeflow.learning.augment.train_augment_hook` with
    ``config.train_augment_probability``) and its targets are resampled by the time factor
    (:func:`resample_curves`); a hook that returns the audio object it was given with factor 1 left it
    unchanged (cached features are used). Without ``config.train_augment`` no hook is used.
    With ``checkpoint_dir``, ``last.pt`` is written after every epoch (before ``on_epoch`` is
    called) and an existing one is resumed from; it must come from the same config (``epochs``
    aside) and the same training data, else ``ValueError``. ``device``, ``precision`` and
    ``encoder_cache``: see the module docstring (:class:`~visemeflow.learning.device.DeviceError`
    for a device or precision this machine does not have). The returned model is on ``device``.
    ``loss(pred, target, mask) -> scalar`` replaces the paper's masked L1 (:func:`l1_loss`) as the training
    objective, for experiments such as ``bench/domain_gap.py``'s weighted losses; it is not part of the config, so
    neither model files nor checkpoints record it (validation L1 stays the plain L1).
    """
    return Trainer(train, val, config, checkpoint_dir, on_epoch, augment_audio, device=device, precision=precision,
                   encoder_cache=encoder_cache, loss=loss).fit()


# --------------------------------------------------------------------------------------------------
# evaluation / inference


def evaluate(
    model: nn.Module, examples: Sequence[Example], batch_size: int = 1, precision: str | None = None
) -> tuple[float, dict[str, float], np.ndarray]:
    """L1 x 100 of the raw (unclipped) predictions, in eval mode, without teacher forcing.

    Returns (mean over all valid frames and visemes of all utterances, {utterance_id: its mean},
    per-viseme mean over all frames (16,)). ``model(audio, lengths, n_frames, fps=fps)`` must
    follow the :class:`AudioCurveModel` convention; batches (padded) only group equal-fps examples.
    Runs where the model is (:func:`~visemeflow.learning.device.model_device`), in float32 unless
    ``precision`` asks for autocast there (``auto``/``bf16``/``fp16``; the CPU is always float32).
    """
    if not examples:
        raise ValueError("no examples to evaluate")
    device = model_device(model)
    amp = resolve_precision(device, precision)
    was_training = model.training
    model.eval()
    total = np.zeros(N_VISEMES, dtype=np.float64)
    n_total = 0
    per_utt: dict[str, float] = {}
    try:
        by_fps: dict[float, list[Example]] = {}
        for ex in examples:
            by_fps.setdefault(float(ex.fps), []).append(ex)
        with torch.no_grad():
            for fps, group in by_fps.items():
                for s in range(0, len(group), max(1, batch_size)):
                    batch = group[s : s + max(1, batch_size)]
                    lengths = torch.tensor([len(ex.audio) for ex in batch], dtype=torch.long)
                    audio = torch.zeros(len(batch), int(lengths.max()), dtype=torch.float32)
                    for j, ex in enumerate(batch):
                        audio[j, : len(ex.audio)] = torch.from_numpy(np.asarray(ex.audio, dtype=np.float32))
                    n_frames = torch.tensor([np.asarray(ex.curves).shape[0] for ex in batch], dtype=torch.long)
                    with autocast_context(device, amp):
                        pred, _ = model(audio.to(device), lengths.to(device), n_frames, fps=fps)
                    pred = pred.float().cpu()
                    for j, ex in enumerate(batch):
                        t = int(n_frames[j])
                        err = (pred[j, :t].to(torch.float64) - torch.as_tensor(
                            np.asarray(ex.curves), dtype=torch.float64)).abs().numpy()
                        total += err.sum(0)
                        n_total += t
                        per_utt[ex.utterance_id] = 100.0 * float(err.mean()) if t else math.nan
    finally:
        model.train(was_training)
    per_viseme = 100.0 * total / max(n_total, 1)
    overall = 100.0 * float(total.sum() / max(n_total * N_VISEMES, 1))
    return overall, per_utt, per_viseme.astype(np.float64)


def predict_curves(
    model: nn.Module, audio: np.ndarray, sample_rate: int, fps: float, n_frames: int | None = None,
    precision: str | None = None,
) -> np.ndarray:
    """(T, 16) curves in [0, 1] for audio of any rate, (samples,) or (samples, channels).

    The audio is downmixed and resampled to 16 kHz (on the CPU); ``n_frames`` defaults to
    ``round(duration * fps)`` with the duration of the input audio. The model runs where it is, in float32
    unless ``precision`` asks for autocast on CUDA (as :func:`evaluate`).
    """
    audio = np.asarray(audio)
    duration = audio.shape[0] / float(sample_rate)
    x = resample_audio(audio, int(sample_rate), SAMPLE_RATE)
    t = round(duration * fps) if n_frames is None else int(n_frames)
    if t <= 0:
        return np.zeros((0, N_VISEMES), dtype=np.float32)
    device = model_device(model)
    amp = resolve_precision(device, precision)
    was_training = model.training
    model.eval()
    try:
        with torch.no_grad(), autocast_context(device, amp):
            a, lengths = _audio_tensors(x, device)
            pred, _ = model(a, lengths, torch.tensor([t], dtype=torch.long), fps=float(fps))
    finally:
        model.train(was_training)
    return np.clip(pred[0, :t].float().cpu().numpy(), 0.0, 1.0).astype(np.float32)


# --------------------------------------------------------------------------------------------------
# save / load


def _cpu_state_dict(model: nn.Module) -> dict[str, Tensor]:
    """``model.state_dict()`` with every tensor on the CPU (the same object when it already is)."""
    state = model.state_dict()
    if all(v.device.type == "cpu" for v in state.values()):
        return state
    cpu: OrderedDict[str, Tensor] = OrderedDict((k, v.cpu()) for k, v in state.items())
    cpu._metadata = getattr(state, "_metadata", None)  # type: ignore[attr-defined]
    return cpu


def save_model(model: nn.Module, config: TrainConfig, path: str | Path, lineage: dict[str, Any]) -> Path:
    """One file: weights (CPU tensors, wherever the model is), TrainConfig JSON, feature config, head frame rate,
    lineage JSON.

    For wav2vec2 presets the Wav2Vec2 architecture config is stored too, so loading needs neither
    the original pretrained model nor the network. Written atomically; weights holding NaN or infinity are refused
    (:class:`NonFiniteWeightsError`) and leave any earlier file at ``path`` as it was.
    """
    if not isinstance(model, AudioCurveModel):
        raise TypeError("save_model expects an AudioCurveModel (as returned by train_model)")
    path = Path(path)
    state = _cpu_state_dict(model)
    _refuse_non_finite(state, path, "in the model to save")
    feats = model.features
    w2v_config = feats.model.config.to_json_string() if isinstance(feats, Wav2Vec2Extractor) else None
    blob = {
        "format": _MODEL_FORMAT,
        "config": config.model_dump_json(),
        "feature_config": feats.config.model_dump_json(),
        "curve_fps": float(model.head.curve_fps),
        "wav2vec2_config": w2v_config,
        "lineage": json.dumps(lineage, sort_keys=True, default=str),
        "state_dict": state,
    }
    _atomic_torch_save(blob, path)
    return path


@dataclass(frozen=True)
class ModelFile:
    """What a model file holds, read and checked by :func:`read_model_file` (nothing built yet)."""

    path: Path
    config: TrainConfig
    feature_config: FeatureConfig
    curve_fps: float
    wav2vec2_config: dict[str, Any] | None  # the Wav2Vec2 architecture (wav2vec2 presets), else None
    lineage: dict[str, Any]
    state_dict: dict[str, Tensor]


_ZIP_MAGIC = b"PK\x03\x04"  # torch.save's format (a zip archive), the only one save_model writes
# Values of the tables a parameter-free extractor computes from its config alone (window, mel filters, DCT), which
# no weight in the file bounds: the presets' hold about 21 thousand.
MAX_FEATURE_TABLE_VALUES = 1 << 22
# What torch.load raises on a damaged archive or pickle stream (a text file gives IndexError, an empty one EOFError)
_UNREADABLE = (RuntimeError, EOFError, IndexError, KeyError, ValueError, TypeError, AttributeError, zipfile.BadZipFile)


def _one_line(exc: BaseException, limit: int = 300) -> str:
    return " ".join(str(exc).split())[:limit]


def read_model_file(path: str | Path) -> ModelFile:
    """The parts of a :func:`save_model` file, each checked, or :class:`ModelFileError` naming the file and why.

    Read with ``torch.load(weights_only=True, map_location="cpu")``: tensors and plain values only, whatever the
    file holds. Checks the format tag, the configs, the lineage, and that every weight is a tensor whose values the
    file really stores (no broadcast view claiming more) and is finite. The weights' names and shapes are checked
    against the configs by :func:`load_model`, before the model is built.
    """
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(len(_ZIP_MAGIC))
    if not head:
        raise ModelFileError(path, "the file is empty")
    if head != _ZIP_MAGIC:
        raise ModelFileError(path, f"it is not a torch.save zip archive (it starts with {head!r})")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        refused = re.search(r"Unsupported global: GLOBAL (\S+)", str(exc))
        what = f" ({refused.group(1)})" if refused else ""
        raise ModelFileError(path, f"it holds objects other than tensors and plain values{what}, which are never "
                                   "unpickled") from exc
    except _UNREADABLE as exc:
        raise ModelFileError(path, f"it cannot be read as a torch.save file ({type(exc).__name__}: "
                                   f"{_one_line(exc)})") from exc
    fmt = blob.get("format") if isinstance(blob, dict) else None
    if fmt != _MODEL_FORMAT:
        if fmt == _CKPT_FORMAT:
            raise ModelFileError(path, "it is a training checkpoint, not a finished model")
        if isinstance(fmt, str) and fmt.startswith("visemeflow-curve-model/"):
            raise ModelFileError(path, f"it was written by another visemeflow version (format {fmt!r}; this one "
                                       f"reads {_MODEL_FORMAT!r}); use the version that trained it, or retrain")
        raise ModelFileError(path, f"it holds no visemeflow model (format field: {_one_line(repr(fmt), 80)})")
    kinds = {"config": str, "feature_config": str, "curve_fps": (int, float), "wav2vec2_config": (str, type(None)),
             "lineage": str, "state_dict": dict}
    for name, kind in kinds.items():
        if not isinstance(blob.get(name), kind):
            raise ModelFileError(path, f"its {name!r} field is {type(blob.get(name)).__name__}")
    try:
        config = TrainConfig.model_validate_json(blob["config"])
        fcfg = FeatureConfig.model_validate_json(blob["feature_config"])
    except ValidationError as exc:
        raise ModelFileError(path, f"its config does not validate here (written by another visemeflow version?): "
                                   f"{_one_line(exc)}") from exc
    try:
        config.resolved_preset()
    except ValueError as exc:  # an unknown preset
        raise ModelFileError(path, _one_line(exc)) from exc
    curve_fps = float(blob["curve_fps"])
    if not (math.isfinite(curve_fps) and curve_fps > 0):
        raise ModelFileError(path, f"its curve frame rate is {curve_fps}")
    parsed = {}
    for name in ("lineage", "wav2vec2_config"):
        if blob[name] is None:
            parsed[name] = None
            continue
        try:
            parsed[name] = json.loads(blob[name])
        except json.JSONDecodeError as exc:
            raise ModelFileError(path, f"its {name.replace('_', ' ')} is not JSON ({exc})") from exc
        if not isinstance(parsed[name], dict):
            raise ModelFileError(path, f"its {name.replace('_', ' ')} is not a JSON object")
    if (fcfg.kind == "wav2vec2") != (parsed["wav2vec2_config"] is not None):
        # without its architecture a wav2vec2 model would be fetched from config.wav2vec2_model (a hub id)
        raise ModelFileError(path, f"its feature kind is {fcfg.kind} but it "
                                   f"{'holds no' if fcfg.kind == 'wav2vec2' else 'holds a'} wav2vec2 architecture")
    state = blob["state_dict"]
    for key, value in state.items():
        if not isinstance(key, str) or not isinstance(value, Tensor):
            raise ModelFileError(path, f"its weights must map names to tensors; {key!r} holds a {type(value).__name__}")
        stored = value.untyped_storage().nbytes() // max(value.element_size(), 1)
        if value.numel() > stored:
            raise ModelFileError(path, f"weight {key} is a broadcast view: it claims {value.numel():,} values "
                                       f"{tuple(value.shape)} but the file stores {stored:,}")
    found = _non_finite_weights(state)
    if found is not None:
        raise ModelFileError(path, found)
    return ModelFile(path, config, fcfg, curve_fps, parsed["wav2vec2_config"], parsed["lineage"], state)


def _layer_count(state: dict[str, Tensor], prefix: str) -> int:
    """How many numbered layers `<prefix><i>.` the weights hold."""
    return len({k[len(prefix):].split(".", 1)[0] for k in state if k.startswith(prefix)})


def _wav2vec2_features(mf: ModelFile) -> Callable[[], nn.Module]:
    """A builder of the file's Wav2Vec2 extractor, once its config's layer counts match the weights (building a
    million layers would exhaust memory even on the meta device)."""
    from transformers import Wav2Vec2Config, Wav2Vec2Model

    assert mf.wav2vec2_config is not None
    try:
        w2v = Wav2Vec2Config.from_dict(mf.wav2vec2_config)
    except (ValueError, TypeError) as exc:
        raise ModelFileError(mf.path, f"its wav2vec2 config does not validate: {_one_line(exc)}") from exc
    counts = {"num_hidden_layers": (w2v.num_hidden_layers, "features.model.encoder.layers."),
              "conv_dim": (w2v.num_feat_extract_layers, "features.model.feature_extractor.conv_layers.")}
    if w2v.add_adapter:
        counts["num_adapter_layers"] = (w2v.num_adapter_layers, "features.model.adapter.layers.")
    for name, (asked, prefix) in counts.items():
        held = _layer_count(mf.state_dict, prefix)
        if asked != held:
            raise ModelFileError(mf.path, f"its wav2vec2 config asks for {asked} layers ({name}), its weights hold "
                                          f"{held}")
    return lambda: Wav2Vec2Extractor(mf.feature_config, model=Wav2Vec2Model(w2v))


def _feature_table_values(fcfg: FeatureConfig) -> int:
    """Values of the tables :class:`FilterbankExtractor` / :class:`LpcExtractor` compute from ``fcfg``."""
    win = fcfg.win_length
    if fcfg.kind == "lpc":
        return win
    n_fft = 1 << (win - 1).bit_length()  # the extractor's zero-padded FFT length
    return win + fcfg.n_mels * (n_fft // 2 + 1) + fcfg.n_mels * fcfg.n_mfcc


def _check_weights_fit(mf: ModelFile, skeleton: nn.Module) -> None:
    """ModelFileError unless the file's weights have exactly the names and shapes the configs' model has."""
    want = skeleton.state_dict()
    missing = [k for k in want if k not in mf.state_dict]
    unexpected = [k for k in mf.state_dict if k not in want]
    if missing or unexpected:
        parts = [f"{what} weights {', '.join(keys[:3])}{f', ... ({len(keys)} in all)' if len(keys) > 3 else ''}"
                 for what, keys in (("missing", missing), ("unexpected", unexpected)) if keys]
        raise ModelFileError(mf.path, f"its weights do not fit its config: {'; '.join(parts)}")
    for key, value in want.items():
        held = tuple(mf.state_dict[key].shape)
        if tuple(value.shape) != held:
            raise ModelFileError(mf.path, f"weight {key}: its config asks for {tuple(value.shape)}, the file holds "
                                          f"{held}")


def _build_checked(mf: ModelFile) -> AudioCurveModel:
    """The model the file's configs describe, built only once its weights' names and shapes are those the configs
    ask for (compared on a skeleton on the meta device, which allocates nothing): a config cannot make loading
    allocate more than the file holds, besides the feature tables (MAX_FEATURE_TABLE_VALUES) and a Whisper
    encoder, which comes from its own source."""
    fcfg = mf.feature_config
    if fcfg.kind == "wav2vec2":
        build_features = _wav2vec2_features(mf)
    else:
        if fcfg.kind != "whisper" and _feature_table_values(fcfg) > MAX_FEATURE_TABLE_VALUES:
            raise ModelFileError(mf.path, f"its feature config (n_mels={fcfg.n_mels}, a {fcfg.win_length}-sample "
                                          f"window) asks for feature tables of {_feature_table_values(fcfg):,} "
                                          f"values; a model may ask for at most {MAX_FEATURE_TABLE_VALUES:,}")
        # parameter-free, or a Whisper encoder from its own source (tuned blocks then loaded from the file)
        features = build_feature_extractor(fcfg)

        def build_features() -> nn.Module:
            return features
    try:
        with torch.device("meta"):
            skeleton = _assemble(mf.config, build_features(), mf.curve_fps)
    except (ValueError, AssertionError) as exc:  # e.g. an odd BLSTM width, heads that do not divide d_model
        raise ModelFileError(mf.path, f"its config does not build a model: {_one_line(exc)}") from exc
    _check_weights_fit(mf, skeleton)
    return _assemble(mf.config, build_features(), mf.curve_fps)


def load_model(
    path: str | Path, device: str | torch.device | None = None
) -> tuple[AudioCurveModel, TrainConfig, dict[str, Any]]:
    """Inverse of :func:`save_model` (``torch.load(weights_only=True, map_location="cpu")``, so a file written
    from a GPU loads anywhere); the model is in eval mode, on ``device`` (default: the CPU).

    :class:`ModelFileError` (naming the file and why) for anything that is not a model file of this version, before
    the model is built (:func:`read_model_file`, then the weights' names and shapes against the configs)."""
    mf = read_model_file(path)
    model = _build_checked(mf)
    model.load_state_dict(mf.state_dict)
    if device is not None:
        model.to(resolve_device(device))
    model.eval()
    return model, mf.config, mf.lineage
