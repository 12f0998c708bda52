"""The models that `predict` and `evaluate` run, by name: a trained model file of the store, or `phones`, the curves
of phones recognised in the audio (`visemeflow.procedural.recognised` in a `learning.recognised.CurveFunctionModel`),
which has no file.

Naming and hashing a model needs no torch: torch is imported only when a model is loaded, so a run whose tasks are
all cached (a second `predict` of the same file) never pays for it."""

from __future__ import annotations

from typing import TYPE_CHECKING

from visemeflow.hashing import file_hash
from visemeflow.procedural.recognised import RECOGNISED_MODEL, recognised_curves, recognised_model_hash
from visemeflow.storage import Store

if TYPE_CHECKING:
    import torch

RECOGNISED_PRESET = "phones (pocketsphinx, no training)"


def is_trained(name: str) -> bool:
    """Whether the name is a model file of the store (every name but `phones`)."""
    return name != RECOGNISED_MODEL


def model_hash(store: Store, name: str) -> str:
    """What a model's outputs depend on besides the audio: the file's content hash, or the recogniser's settings."""
    return file_hash(store.model_file(name)) if is_trained(name) else recognised_model_hash()


def load_curve_model(store: Store, name: str, device: str = "cpu") -> tuple[torch.nn.Module, str, bool]:
    """(model on `device`, its preset, whether it was trained with augmentation)."""
    if not is_trained(name):
        from visemeflow.learning.recognised import CurveFunctionModel

        return CurveFunctionModel(recognised_curves, RECOGNISED_PRESET), RECOGNISED_PRESET, False
    from visemeflow.learning.train import load_model

    model, config, _ = load_model(store.model_file(name), device=device)
    return model, config.preset, config.train_augment
