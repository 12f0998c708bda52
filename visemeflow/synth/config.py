"""How synthetic videos are made (`SynthConfig`, with the true dynamics' `GroundTruthConfig` and the head's
`SceneConfig`), apart from the renderer, so that reading it (the CLI's options, the
synth flow's parameters) imports no torch. `synth.take` renders it."""

from __future__ import annotations

from typing import TYPE_CHECKING

from pydantic import BaseModel, ConfigDict, Field


if TYPE_CHECKING:
    from visemeflow.render.raster import Camera


class GroundTruthConfig(BaseModel):
    """Constants of the ground-truth dynamics; times in seconds."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    seed: int = Field(0, description="Base seed; each utterance's randomness is derived from it and the utterance id.")
    rest_dominance: float = Field(0.25, gt=0, description="Dominance of the neutral face, which wins in pauses.")
    anticipation_s: tuple[float, float] = Field(
        (0.07, 0.11), description="Range of the speaker's anticipatory time constant (dominance rise before a phone)."
    )
    carryover_s: tuple[float, float] = Field(
        (0.05, 0.09), description="Range of the speaker's carry-over time constant (dominance decay after a phone)."
    )
    strength: tuple[float, float] = Field(
        (0.75, 1.0), description="Range of the speaker's articulation strength (peak weight of a full vowel)."
    )
    timing_shift_s: float = Field(0.015, ge=0, description="Std. dev. of the speaker's lead (+) or lag of articulation.")
    stiffness_hz: tuple[float, float] = Field(
        (6.0, 9.0), description="Range of the natural frequency of the articulators' second-order response."
    )
    damping: float = Field(0.9, gt=0, description="Damping ratio of the second-order response (1 = critical).")
    flank_power: float = Field(
        1.5, gt=0, description="Shape c of the dominance flanks exp(-(tau / tau0) ** c); 1 is Cohen-Massaro's exponential."
    )
    closure_dominance: float = Field(8.0, gt=0, description="Dominance multiplier of lip closures, so they close.")
    closure_sharpness: float = Field(
        0.4, gt=0, description="Factor on the flank time constants of lip closures (smaller = sharper)."
    )
    tongue_weight: float = Field(0.5, ge=0, le=1, description="Target weight of tongue-only visemes.")
    jitter: float = Field(0.02, ge=0, description="Std. dev. of the band-limited jitter on active visemes.")
    jitter_hz: float = Field(3.0, gt=0, description="Bandwidth of the jitter.")
    internal_rate_hz: float = Field(400.0, gt=0, description="Simulation rate of the second-order response.")


class SceneConfig(BaseModel):
    """How much the head moves and the light changes over an utterance."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    rotation_deg: float = Field(2.5, ge=0, description="Std. dev. of head rotation about each axis, degrees.")
    translation_cm: float = Field(0.4, ge=0, description="Std. dev. of head translation along each axis, cm.")
    motion_hz: float = Field(0.4, gt=0, description="Bandwidth of the head motion.")
    light_deg: float = Field(12.0, ge=0, description="Std. dev. of the light direction's wander, degrees.")
    brightness: tuple[float, float] = Field((0.85, 1.1), description="Range of the overall light intensity.")


class SynthConfig(BaseModel):
    """How synthetic videos are made."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    width: int = Field(360, ge=32, le=4096, description="Frame width in pixels (GRID is 360x288; 640x480 also common).")
    height: int = Field(288, ge=32, le=4096, description="Frame height in pixels.")
    fps: float = Field(25.0, gt=0, description="Video frame rate (GRID records 25 fps).")
    fov_deg: float = Field(25.0, gt=1, lt=170, description="Vertical field of view of the camera.")
    fill: float = Field(0.8, gt=0, le=2, description="Share of the image height the rig's face spans.")
    landmark_noise_px: float = Field(1.5, ge=0, description="Std. dev. of the detector-like landmark noise, pixels.")
    landmark_miss_rate: float = Field(0.02, ge=0, le=1, description="Share of frames where the detector finds no face.")
    video_ext: str = Field("mp4", pattern="^(mp4|avi)$", description="Video container: mp4 (H.264) or avi (MJPEG).")
    truth: GroundTruthConfig = Field(default_factory=GroundTruthConfig)
    scene: SceneConfig = Field(default_factory=SceneConfig)

    def camera(self) -> Camera:
        from visemeflow.render.raster import Camera

        return Camera.default(self.width, self.height, self.fov_deg)
