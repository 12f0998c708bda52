"""A curve model without weights: a function of the audio (`(audio, sample_rate, fps, n_frames) -> (n_frames, 16)`)
in the calling convention of a trained model (16 kHz audio, lengths, frame counts -> curves, mask), so that
`predict_curves`, `evaluate` and the real-speech metrics treat both alike. `phones` (the curves of the phones
recognised in the audio, `visemeflow.procedural.recognised`) is one: `visemeflow.tasks.models` builds it."""

from collections.abc import Callable

import numpy as np
import torch

from visemeflow.learning.train import SAMPLE_RATE
from visemeflow.timebase import DEFAULT_FPS
from visemeflow.visemes import N_VISEMES

__all__ = ["CurveFunctionModel"]

CurveFunction = Callable[[np.ndarray, int, float, int], np.ndarray]


class CurveFunctionModel(torch.nn.Module):
    """`curves(audio, SAMPLE_RATE, fps, n_frames)` of each utterance of a batch, as a model's forward."""

    def __init__(self, curves: CurveFunction, preset: str) -> None:
        super().__init__()
        self.curves, self.preset = curves, preset

    def forward(self, audio: torch.Tensor, lengths: torch.Tensor, n_frames: torch.Tensor, targets=None,
                fps: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        fps = DEFAULT_FPS if fps is None else float(fps)
        out = torch.zeros(audio.shape[0], int(n_frames.max()) if len(n_frames) else 0, N_VISEMES)
        for b in range(audio.shape[0]):
            n = int(n_frames[b])
            curves = self.curves(audio[b, : int(lengths[b])].cpu().numpy(), SAMPLE_RATE, fps, n)
            out[b, :n] = torch.from_numpy(np.asarray(curves, np.float32))
        mask = torch.arange(out.shape[1])[None, :] < n_frames.cpu()[:, None]
        return out, mask
