"""Viseme curves of audio alone, through phones recognised in it (`visemeflow.phonetics.recognise`) and the
procedural rules: no alignment, no trained model, any English voice.

This is the model name `phones` of `visemeflow predict`, `speak` and `animate` (a reserved name: no trained model
may take it). On speakers nothing of ours was trained on it closes the lips at more b/p/m phones, and falsely at
fewer other phones, than any learned recipe of `bench/domain_gap.py` (figures in the README); it knows English
phones only, and a learned model trained on the speaker's own data does better still.
"""

from __future__ import annotations

import numpy as np

from visemeflow.hashing import stable_hash
from visemeflow.phonetics.recognise import PhoneRecogniser, shared_recogniser, viseme_segments
from visemeflow.procedural.config import RECOGNISED_MODEL, ProceduralConfig
from visemeflow.procedural.jali import DEFAULT_CONFIG, generate_procedural_curves
from visemeflow.visemes import N_VISEMES



def recognised_curves(audio: np.ndarray, sample_rate: int, fps: float, n_frames: int | None = None, *,
                      recogniser: PhoneRecogniser | None = None, config: ProceduralConfig = DEFAULT_CONFIG,
                      source: str = "<audio>") -> np.ndarray:
    """(T, 16) float32 curves of `audio` ((samples,) or (samples, channels), any rate); T defaults to
    round(duration * fps), as a learned model's `predict_curves`."""
    audio = np.asarray(audio)
    t = round(audio.shape[0] / float(sample_rate) * fps) if n_frames is None else int(n_frames)
    if t <= 0:
        return np.zeros((0, N_VISEMES), dtype=np.float32)
    phones = (recogniser or shared_recogniser()).recognise(audio, sample_rate, source)
    return generate_procedural_curves(viseme_segments(phones, source), t, fps, config).astype(np.float32)


def recognised_model_hash(recogniser: PhoneRecogniser | None = None, config: ProceduralConfig = DEFAULT_CONFIG) -> str:
    """What `phones` curves depend on besides the audio (a cache key in place of a model file's hash)."""
    return stable_hash(RECOGNISED_MODEL, (recogniser or shared_recogniser()).settings, config)
