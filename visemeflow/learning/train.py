"""Training of the audio-to-viseme-curve models (paper Section 5.1 "Training").

Pure domain code (torch/numpy, no Prefect). Files are touched only by the checkpoint functions
inside :func:`train_model` (``checkpoint_dir/last.pt``) and by :func:`save_model` / :func:`load_model`.

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
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor, nn

from visemeflow.atomic import atomic_write
from visemeflow.learning.features import (
    FeatureConfig,
    Wav2Vec2Extractor,
    build_feature_extractor,
    resample_audio,
)
from visemeflow.learning.model import AudioCurveModel, MeanCurveBaseline, l1_loss
from visemeflow.learning.presets import (
    Preset,
    augment,
    build_model,
    build_optimizer,
    get_preset,
)
from visemeflow.visemes import N_VISEMES

__all__ = [
    "SAMPLE_RATE",
    "EpochReport",
    "Example",
    "TrainConfig",
    "TrainResult",
    "apply_audio_augment",
    "build_training_model",
    "evaluate",
    "load_model",
    "predict_curves",
    "resample_curves",
    "save_model",
    "train_model",
]

SAMPLE_RATE = 16000
CHECKPOINT_NAME = "last.pt"
_MODEL_FORMAT = "visemeflow-curve-model/1"
_CKPT_FORMAT = "visemeflow-train-checkpoint/1"

AudioAugment = Callable[[np.ndarray, np.random.Generator], tuple[np.ndarray, float]]


# --------------------------------------------------------------------------------------------------
# data types


@dataclass(frozen=True)
class Example:
    """One training utterance: mono 16 kHz float32 audio and its (T, 16) target curves at ``fps``."""

    utterance_id: str
    audio: np.ndarray
    curves: np.ndarray
    fps: float


class TrainConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    preset: str = "fbank-blstm"
    epochs: int = Field(10, ge=0)
    seed: int = 0
    d_model: int | None = Field(None, ge=2)  # override the preset's width (small models)
    lr: float | None = Field(None, gt=0)  # override the preset's learning rate
    max_steps_per_epoch: int | None = Field(None, ge=1)
    wav2vec2_model: str | None = None  # local path or hub id, wav2vec2 presets only
    # train-time audio augmentation (volume, pitch, speed, noise at the paper's ranges): with this
    # probability each training step sees one randomly drawn condition (visemeflow.learning.augment)
    train_augment: bool = False
    train_augment_probability: float = Field(0.5, ge=0, le=1)

    def resolved_preset(self) -> Preset:
        p = get_preset(self.preset)
        return p.model_copy(update={"lr": self.lr}) if self.lr is not None else p


@dataclass
class EpochReport:
    epoch: int  # 1-based
    steps: int  # optimisation steps in this epoch
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
    if preset.feature == "wav2vec2":
        if not config.wav2vec2_model:
            raise ValueError(f"preset {preset.name!r} needs TrainConfig.wav2vec2_model (path or hub id)")
        return FeatureConfig(kind="wav2vec2", wav2vec2_model=config.wav2vec2_model)
    return FeatureConfig(kind=preset.feature, normalize=True)


def _assemble(config: TrainConfig, feature_module: nn.Module, curve_fps: float) -> AudioCurveModel:
    preset = config.resolved_preset()
    head = build_model(
        preset, feature_module.dim, feature_module.frame_rate_hz, curve_fps, d_model=config.d_model
    )
    return AudioCurveModel(feature_module, head)


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


def _audio_tensors(audio: np.ndarray) -> tuple[Tensor, Tensor]:
    a = torch.from_numpy(np.ascontiguousarray(audio, dtype=np.float32))[None]
    return a, torch.tensor([a.shape[1]], dtype=torch.long)


def train_model(
    train: Sequence[Example],
    val: Sequence[Example],
    config: TrainConfig,
    checkpoint_dir: Path | None = None,
    on_epoch: Callable[[EpochReport], None] | None = None,
    augment_audio: AudioAugment | None = None,
) -> TrainResult:
    """Train ``config.preset`` on ``train`` (see the module docstring); validate on ``val`` each epoch.

    When ``config.train_augment`` is true, every training step passes its utterance through
    ``augment_audio(audio, rng) -> (audio, time_factor)`` (default:
    :func:`visemeflow.learning.augment.train_augment_hook` with
    ``config.train_augment_probability``) and resamples the targets by the time factor
    (:func:`resample_curves`). Without ``config.train_augment`` no hook is used.
    With ``checkpoint_dir``, ``last.pt`` is written after every epoch (before ``on_epoch`` is
    called) and an existing one is resumed from; it must come from the same config (``epochs``
    aside) and the same training data, else ``ValueError``.
    """
    if not train:
        raise ValueError("no training examples")
    _check_examples(train, "training example")
    _check_examples(val, "validation example")
    hook: AudioAugment | None = None
    if config.train_augment:
        if augment_audio is None:
            from visemeflow.learning.augment import train_augment_hook

            augment_audio = train_augment_hook(probability=config.train_augment_probability, sample_rate=SAMPLE_RATE)
        hook = augment_audio
    preset = config.resolved_preset()
    curve_fps = float(train[0].fps)
    model = build_training_model(config, curve_fps)

    if not preset.trainable:  # mean-curve: fit, no steps
        t0 = time.perf_counter()
        if not isinstance(model.head, MeanCurveBaseline):
            raise TypeError(f"preset {preset.name!r} is not trainable and has no fit()")
        model.head.fit([ex.curves for ex in train])
        secs = time.perf_counter() - t0
        frames = sum(int(np.asarray(ex.curves).shape[0]) for ex in train)
        train_l1, _, _ = evaluate(model, train)
        val_l1 = evaluate(model, val)[0] if val else None
        report = EpochReport(1, 0, train_l1, val_l1, secs, frames / max(secs, 1e-9))
        if on_epoch is not None:
            on_epoch(report)
        return TrainResult(model, [report], None)

    optimizer = build_optimizer(preset, model)
    if optimizer is None:
        raise ValueError(f"preset {preset.name!r} has no trainable parameters")
    shuffle_rng = np.random.default_rng(config.seed)
    augment_rng = np.random.default_rng([config.seed, 2])
    spec_gen = torch.Generator().manual_seed(config.seed + 1)
    np.random.seed(config.seed % (2**32))  # legacy global RNG (wav2vec2 time masking in transformers)
    history: list[EpochReport] = []
    start_epoch, step = 0, 0
    fingerprint = _data_fingerprint(train)

    ckpt_path = Path(checkpoint_dir) / CHECKPOINT_NAME if checkpoint_dir is not None else None
    if ckpt_path is not None and ckpt_path.exists():
        ck = torch.load(ckpt_path, map_location="cpu", weights_only=True)
        if ck.get("format") != _CKPT_FORMAT or ck.get("resume_key") != _resume_key(config):
            raise ValueError(f"{ckpt_path} was written for a different training config; remove it or use another dir")
        if ck.get("data") != fingerprint:
            raise ValueError(f"{ckpt_path} was written for different training data")
        model.load_state_dict(ck["model"])
        optimizer.load_state_dict(ck["optimizer"])
        start_epoch, step = int(ck["epoch"]), int(ck["step"])
        history = [EpochReport(**h) for h in ck["history"]]
        torch.set_rng_state(ck["rng"]["torch"])
        spec_gen.set_state(ck["rng"]["spec_augment"])
        _set_np_gen_state(shuffle_rng, ck["rng"]["shuffle"])
        _set_np_gen_state(augment_rng, ck["rng"]["augment"])
        _set_np_global_state(ck["rng"]["numpy_global"])

    cached: list[tuple[Tensor, Tensor]] | None = None
    has_feature_params = any(True for _ in model.features.parameters())
    if hook is None and not has_feature_params and start_epoch < config.epochs:
        with torch.no_grad():  # parameter-free extractor: features once per utterance
            cached = [model.features(*_audio_tensors(ex.audio)) for ex in train]

    for epoch in range(start_epoch, config.epochs):
        model.train()
        order = shuffle_rng.permutation(len(train))
        if config.max_steps_per_epoch is not None:
            order = order[: config.max_steps_per_epoch]
        losses: list[float] = []
        frames = 0
        t0 = time.perf_counter()
        for i in order:
            ex = train[int(i)]
            if hook is not None:
                audio, curves = apply_audio_augment(ex, hook, augment_rng)
                feats, feat_lengths = model.features(*_audio_tensors(audio))
            else:
                curves = np.asarray(ex.curves, dtype=np.float32)
                if cached is not None:
                    feats, feat_lengths = cached[int(i)]
                else:
                    feats, feat_lengths = model.features(*_audio_tensors(ex.audio))
            feats = augment(preset, feats, feat_lengths, generator=spec_gen)
            target = torch.from_numpy(np.ascontiguousarray(curves))[None]
            n_frames = torch.tensor([target.shape[1]], dtype=torch.long)
            pred, mask = model.head(feats, feat_lengths, n_frames, targets=target, fps=float(ex.fps))
            loss = l1_loss(pred, target, mask)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            step += 1
            losses.append(float(loss.detach()))
            frames += int(target.shape[1])
        secs = time.perf_counter() - t0
        val_l1 = evaluate(model, val)[0] if val else None
        report = EpochReport(
            epoch=epoch + 1, steps=len(order), train_l1_x100=100.0 * float(np.mean(losses)) if losses else math.nan,
            val_l1_x100=val_l1, seconds=secs, frames_per_s=frames / max(secs, 1e-9),
        )
        history.append(report)
        if ckpt_path is not None:
            _atomic_torch_save(
                {
                    "format": _CKPT_FORMAT,
                    "resume_key": _resume_key(config),
                    "data": fingerprint,
                    "model": model.state_dict(),
                    "optimizer": optimizer.state_dict(),
                    "epoch": epoch + 1,
                    "step": step,
                    "history": [asdict(h) for h in history],
                    "rng": {
                        "torch": torch.get_rng_state(),
                        "spec_augment": spec_gen.get_state(),
                        "shuffle": _np_gen_state(shuffle_rng),
                        "augment": _np_gen_state(augment_rng),
                        "numpy_global": _np_global_state(),
                    },
                },
                ckpt_path,
            )
        if on_epoch is not None:
            on_epoch(report)
    model.eval()
    return TrainResult(model, history, ckpt_path)


# --------------------------------------------------------------------------------------------------
# evaluation / inference


def evaluate(
    model: nn.Module, examples: Sequence[Example], batch_size: int = 1
) -> tuple[float, dict[str, float], np.ndarray]:
    """L1 x 100 of the raw (unclipped) predictions, in eval mode, without teacher forcing.

    Returns (mean over all valid frames and visemes of all utterances, {utterance_id: its mean},
    per-viseme mean over all frames (16,)). ``model(audio, lengths, n_frames, fps=fps)`` must
    follow the :class:`AudioCurveModel` convention; batches (padded) only group equal-fps examples.
    """
    if not examples:
        raise ValueError("no examples to evaluate")
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
                    pred, _ = model(audio, lengths, n_frames, fps=fps)
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
    model: nn.Module, audio: np.ndarray, sample_rate: int, fps: float, n_frames: int | None = None
) -> np.ndarray:
    """(T, 16) curves in [0, 1] for audio of any rate, (samples,) or (samples, channels).

    The audio is downmixed and resampled to 16 kHz; ``n_frames`` defaults to
    ``round(duration * fps)`` with the duration of the input audio.
    """
    audio = np.asarray(audio)
    duration = audio.shape[0] / float(sample_rate)
    x = resample_audio(audio, int(sample_rate), SAMPLE_RATE)
    t = round(duration * fps) if n_frames is None else int(n_frames)
    if t <= 0:
        return np.zeros((0, N_VISEMES), dtype=np.float32)
    was_training = model.training
    model.eval()
    try:
        with torch.no_grad():
            a, lengths = _audio_tensors(x)
            pred, _ = model(a, lengths, torch.tensor([t], dtype=torch.long), fps=float(fps))
    finally:
        model.train(was_training)
    return np.clip(pred[0, :t].numpy(), 0.0, 1.0).astype(np.float32)


# --------------------------------------------------------------------------------------------------
# save / load


def save_model(model: nn.Module, config: TrainConfig, path: str | Path, lineage: dict[str, Any]) -> Path:
    """One file: weights, TrainConfig JSON, feature config, head frame rate, lineage JSON.

    For wav2vec2 presets the Wav2Vec2 architecture config is stored too, so loading needs neither
    the original pretrained model nor the network. Written atomically.
    """
    if not isinstance(model, AudioCurveModel):
        raise TypeError("save_model expects an AudioCurveModel (as returned by train_model)")
    feats = model.features
    w2v_config = feats.model.config.to_json_string() if isinstance(feats, Wav2Vec2Extractor) else None
    blob = {
        "format": _MODEL_FORMAT,
        "config": config.model_dump_json(),
        "feature_config": feats.config.model_dump_json(),
        "curve_fps": float(model.head.curve_fps),
        "wav2vec2_config": w2v_config,
        "lineage": json.dumps(lineage, sort_keys=True, default=str),
        "state_dict": model.state_dict(),
    }
    path = Path(path)
    _atomic_torch_save(blob, path)
    return path


def load_model(path: str | Path) -> tuple[AudioCurveModel, TrainConfig, dict[str, Any]]:
    """Inverse of :func:`save_model` (``torch.load(weights_only=True)``); the model is in eval mode."""
    blob = torch.load(Path(path), map_location="cpu", weights_only=True)
    if not isinstance(blob, dict) or blob.get("format") != _MODEL_FORMAT:
        raise ValueError(f"{path} is not a saved visemeflow curve model")
    config = TrainConfig.model_validate_json(blob["config"])
    fcfg = FeatureConfig.model_validate_json(blob["feature_config"])
    if blob["wav2vec2_config"] is not None:
        from transformers import Wav2Vec2Config, Wav2Vec2Model

        w2v = Wav2Vec2Model(Wav2Vec2Config.from_dict(json.loads(blob["wav2vec2_config"])))
        features: nn.Module = Wav2Vec2Extractor(fcfg, model=w2v)
    else:
        features = build_feature_extractor(fcfg)
    model = _assemble(config, features, float(blob["curve_fps"]))
    model.load_state_dict(blob["state_dict"])
    model.eval()
    return model, config, json.loads(blob["lineage"])
