"""How synthetic videos are made (`SynthConfig`), apart from the renderer, so that reading it (the CLI's options, the
synth flow's parameters) imports no torch. `synth.take` renders it."""

from __future__ import annotations

from typing import TYPE_CHECKING

from pydantic import BaseModel, ConfigDict, Field

from visemeflow.synth.dynamics import GroundTruthConfig
from visemeflow.synth.motion import SceneConfig

if TYPE_CHECKING:
    from visemeflow.render.raster import Camera


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
