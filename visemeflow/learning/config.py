"""What a training run is asked for (`TrainConfig`) and the ranges of the audio augmentations (`AugmentConfig`),
apart from the code that trains and augments, so that reading a config (the
CLI's options, a flow's parameters, a model file's lineage) imports no torch. `visemeflow.learning.train` runs it."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    field_validator,
    model_serializer,
    model_validator,
)

from visemeflow.hashing import without_added_defaults

if TYPE_CHECKING:
    from visemeflow.learning.presets import Preset


class TrainConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    preset: str = Field("fbank-blstm", description="Model preset, e.g. fbank-blstm, whisper-base-blstm, wav2vec2-blstm, "
                                                  "mean-curve.")
    epochs: int = Field(10, ge=0, description="Passes over the training utterances.")
    seed: int = Field(0, description="Seed of initialisation, order and augmentation.")
    d_model: int | None = Field(None, ge=2, description="Model width; default: the preset's.")
    lr: float | None = Field(None, gt=0, description="Learning rate; default: the preset's.")
    dropout: float | None = Field(None, ge=0, lt=1, description=(
        "Dropout on the decoder's output (and between its layers) in training; default: the preset's (0). The "
        "network at inference is the same; the model file records the value (so an earlier version of visemeflow "
        "refuses it)."))
    max_steps_per_epoch: int | None = Field(None, ge=1)
    wav2vec2_model: str | None = Field(None, description="wav2vec2 model path or hub id (wav2vec2 presets).")
    # whisper presets: "package", a CTranslate2 / Hugging Face folder or a hub id, instead of the preset's own
    whisper_source: str | None = None
    # whisper presets: which encoder outputs feed the decoder, "last" (the preset's) or "weighted" (a learned
    # softmax-weighted sum of every layer); None: the preset's own
    whisper_layers: Literal["last", "weighted"] | None = None
    whisper_tune_layers: int = Field(0, ge=0, le=64, description=(
        "Whisper presets: train the encoder's top N blocks (and its final LayerNorm) with the head; 0 keeps the "
        "encoder frozen. Each tuned whisper-base block adds about 12 MB to the model file; training utterances "
        "must then be at most 30 s (21 s with --train-augment, whose speed changes lengthen them)."))
    whisper_tune_lr: float = Field(1e-5, gt=0, description="Learning rate of the tuned Whisper blocks.")
    # train-time audio augmentation (volume, pitch, speed, noise at the paper's ranges): with this
    # probability each training step sees one randomly drawn condition (visemeflow.learning.augment)
    train_augment: bool = False
    train_augment_probability: float = Field(0.5, ge=0, le=1)
    # utterances per optimisation step: 1 is the paper's recipe; more pads length-bucketed batches (module docstring)
    batch_size: int = Field(1, ge=1, description="Utterances per optimisation step: 1 is the paper's recipe; more pads "
                                                 "length-bucketed batches.")
    # batch_size > 1: a length bucket holds this many batches (1: batches as drawn, sorted only inside)
    bucket_batches: int = Field(8, ge=1)
    # auxiliary viseme classification (0: off, the paper's recipe): a linear layer on the decoder's features predicts
    # each frame's viseme (Example.visemes), cross-entropy weighted by this, added to the curve loss; the layer
    # serves training only (model files hold the curve model alone). Curve heads (CurveModel) only.
    viseme_loss_weight: float = Field(0.0, ge=0)
    # inference only: narrow the MBP channel to its peaks within this half window, s (0: off, the paper's model;
    # visemeflow.learning.model.ClosurePeaks); a training run never applies it, a loaded model does in eval mode
    mbp_peaks_half_window_s: float = Field(0.0, ge=0, le=0.5)
    mbp_peaks_power: float = Field(16.0, gt=0, le=64)
    # inference only, with the peaks: the MBP channel moved this much earlier first, s (ClosurePeaks.lead_s)
    mbp_lead_s: float = Field(0.0, ge=0, le=0.1)
    # inference only, with the peaks: where MBP leads a frame, the other visemes capped at (1 - MBP) ** this (0: off)
    mbp_others_power: float = Field(0.0, ge=0, le=16)
    # inference only: end each closure at its release, a rise of the 400-3400 Hz band's energy of at least this many dB
    # within 20 ms near the MBP peak (0: off; visemeflow.learning.model.ReleaseCut)
    mbp_release_rise_db: float = Field(0.0, ge=0, le=60)

    @model_serializer(mode="wrap")
    def _without_unchanged_additions(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        return without_added_defaults(handler(self), _ADDED_DEFAULTS)

    @field_validator("dropout")
    @classmethod
    def _no_dropout_is_none(cls, value: float | None) -> float | None:
        return None if value == 0 else value   # 0 is every preset's own: the same config, the same hash

    @model_validator(mode="after")
    def _dropout_needs_a_decoder(self) -> TrainConfig:
        if self.dropout is not None:
            from visemeflow.learning.presets import get_preset

            if get_preset(self.preset).architecture in ("karras", "mean"):
                raise ValueError(f"--dropout: the preset {self.preset} has no decoder whose output it would drop "
                                 "(curve and faceformer presets have one)")
        return self

    @model_validator(mode="after")
    def _tune_lr_needs_tuned_layers(self) -> TrainConfig:
        if self.whisper_tune_layers == 0 and self.whisper_tune_lr != _ADDED_DEFAULTS["whisper_tune_lr"]:
            raise ValueError("whisper_tune_lr is the learning rate of tuned Whisper blocks: set whisper_tune_layers "
                             "(--tune-layers) too")
        return self

    def resolved_preset(self) -> Preset:
        from visemeflow.learning.presets import get_preset

        p = get_preset(self.preset)
        if self.dropout is not None:
            p = p.model_copy(update={"decoder": p.decoder.model_copy(update={"dropout": self.dropout})})
        return p.model_copy(update={"lr": self.lr}) if self.lr is not None else p


_ADDED_DEFAULTS: dict[str, Any] = {"dropout": None, "batch_size": 1, "bucket_batches": 8, "whisper_source": None,
                                   "viseme_loss_weight": 0.0, "whisper_layers": None,
                                   "whisper_tune_layers": 0, "whisper_tune_lr": 1e-5,
                                   "mbp_peaks_half_window_s": 0.0, "mbp_peaks_power": 16.0,
                                   "mbp_lead_s": 0.0, "mbp_others_power": 0.0, "mbp_release_rise_db": 0.0}


CONDITIONS: tuple[str, ...] = ("volume", "pitch", "speed", "noise")


def _check_condition(condition: str) -> str:
    if condition not in CONDITIONS:
        raise ValueError(f"unknown augmentation condition {condition!r}; allowed: {', '.join(CONDITIONS)}")
    return condition


class AugmentConfig(BaseModel):
    """Ranges ``(low, high)`` the values are drawn from (uniformly); defaults: paper Section 5.2."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    volume_db: tuple[float, float] = (-10.0, 10.0)  # gain in dB
    pitch_semitones: tuple[float, float] = (-3.0, 3.0)  # pitch shift in semitones
    speed: tuple[float, float] = (0.7, 1.3)  # speed factor (> 1 faster / shorter)
    noise_std: tuple[float, float] = (0.0, 0.005)  # std of the added Gaussian noise

    @field_validator("volume_db", "pitch_semitones", "speed", "noise_std")
    @classmethod
    def _ordered_finite(cls, v: tuple[float, float]) -> tuple[float, float]:
        low, high = v
        if not (math.isfinite(low) and math.isfinite(high)):
            raise ValueError(f"range bounds must be finite, got {v}")
        if low > high:
            raise ValueError(f"range low must be <= high, got {v}")
        return v

    @model_validator(mode="after")
    def _positive(self) -> AugmentConfig:
        if self.speed[0] <= 0:
            raise ValueError(f"speed factors must be > 0, got {self.speed}")
        if self.noise_std[0] < 0:
            raise ValueError(f"noise std must be >= 0, got {self.noise_std}")
        return self

    def range_of(self, condition: str) -> tuple[float, float]:
        """The ``(low, high)`` range of ``condition``."""
        field = {"volume": "volume_db", "pitch": "pitch_semitones", "speed": "speed", "noise": "noise_std"}
        return getattr(self, field[_check_condition(condition)])
