"""The models that `predict` and `evaluate` run, by name: a trained model file of the store, or `phones`, the curves
of phones recognised in the audio (`visemeflow.procedural.recognised`), which has no file.

`phones` is wrapped in the calling convention of a trained model (16 kHz audio, lengths, frame counts -> curves,
mask), so `predict_curves`, `evaluate` and the real-speech metrics treat both alike."""

import torch

from visemeflow.hashing import file_hash
from visemeflow.learning.train import SAMPLE_RATE, load_model
from visemeflow.procedural.recognised import RECOGNISED_MODEL, recognised_curves, recognised_model_hash
from visemeflow.storage import Store
from visemeflow.visemes import N_VISEMES
from visemeflow.timebase import DEFAULT_FPS


class RecognisedPhonesModel(torch.nn.Module):
    """`phones` as a model: each utterance's curves from the phones recognised in its audio."""

    preset = "phones (pocketsphinx, no training)"

    def forward(self, audio: torch.Tensor, lengths: torch.Tensor, n_frames: torch.Tensor, targets=None,
                fps: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        fps = DEFAULT_FPS if fps is None else float(fps)
        out = torch.zeros(audio.shape[0], int(n_frames.max()) if len(n_frames) else 0, N_VISEMES)
        for b in range(audio.shape[0]):
            n = int(n_frames[b])
            curves = recognised_curves(audio[b, : int(lengths[b])].cpu().numpy(), SAMPLE_RATE, fps, n)
            out[b, :n] = torch.from_numpy(curves)
        mask = torch.arange(out.shape[1])[None, :] < n_frames.cpu()[:, None]
        return out, mask


def is_trained(name: str) -> bool:
    """Whether the name is a model file of the store (every name but `phones`)."""
    return name != RECOGNISED_MODEL


def model_hash(store: Store, name: str) -> str:
    """What a model's outputs depend on besides the audio: the file's content hash, or the recogniser's settings."""
    return file_hash(store.model_path(name)) if is_trained(name) else recognised_model_hash()


def load_curve_model(store: Store, name: str, device: str = "cpu") -> tuple[torch.nn.Module, str, bool]:
    """(model on `device`, its preset, whether it was trained with augmentation)."""
    if not is_trained(name):
        return RecognisedPhonesModel(), RecognisedPhonesModel.preset, False
    model, config, _ = load_model(store.model_path(name), device=device)
    return model, config.preset, config.train_augment
