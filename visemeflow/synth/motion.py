"""Small natural head motion and lighting changes for the rendered ground-truth videos."""

from dataclasses import dataclass

import numpy as np

from visemeflow.synth.dynamics import band_limited_noise
from visemeflow.synth.config import SceneConfig  # noqa: F401 (re-exported)



@dataclass(frozen=True)
class SceneTrack:
    """Per-frame head pose and light: rotations (T, 3) axis-angle rad, translations (T, 3) cm,
    light directions (T, 3) unit vectors toward the light, intensities (T,)."""

    rotations: np.ndarray
    translations: np.ndarray
    light_dirs: np.ndarray
    intensities: np.ndarray


def scene_track(n_frames: int, fps: float, rng: np.random.Generator, config: SceneConfig = SceneConfig()) -> SceneTrack:
    """A smooth random head-pose and lighting trajectory of `n_frames` frames."""
    n = max(n_frames, 2)
    motion = band_limited_noise(rng, n, fps, config.motion_hz, dims=9)
    rotations = np.deg2rad(config.rotation_deg) * motion[:n_frames, 0:3]
    translations = config.translation_cm * motion[:n_frames, 3:6]
    base = np.array([0.3, 0.4, 1.0])
    wander = np.deg2rad(config.light_deg) * motion[:n_frames, 6:9]
    light = base / np.linalg.norm(base) + wander
    light /= np.linalg.norm(light, axis=1, keepdims=True)
    lo, hi = config.brightness
    intensity = np.full(n_frames, rng.uniform(lo, hi))
    return SceneTrack(rotations, translations, light, intensity)
