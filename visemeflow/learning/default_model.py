"""The models shipped with the package, so that `visemeflow predict AUDIO` works on a fresh machine without training.

- `default` (`visemeflow/learning/data/default.pt`): whisper-base-blstm, the frozen Whisper-base encoder (its
  weights come from the `visemeflow[whisper]` extra; the file holds the decoder and the encoder's digest) under a
  small BLSTM decoder; written by `examples/train_default_model.py` (recipe, data lineage and real-speech figures
  in `visemeflow/learning/data/README.md`, the README and the file itself).
- `default-fbank` (`default-fbank.pt`): the previous default, fbank-blstm (no extra needed; its lips barely move
  on voices it never heard).

The predict and speak flows install a shipped model into a store under its name the first time it is asked for;
a user's own model of that name in the store takes precedence.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

DEFAULT_MODEL = "default"
SHIPPED_MODELS: dict[str, str] = {DEFAULT_MODEL: "default.pt", "default-fbank": "default-fbank.pt"}


def shipped_model_path(name: str) -> Path:
    """The file of a shipped model by name (KeyError for a name that is not shipped; the file may be missing from a
    source tree where it was never trained)."""
    resource = resources.files("visemeflow.learning").joinpath("data", SHIPPED_MODELS[name])
    return resource if isinstance(resource, Path) else Path(str(resource))


def default_model_path() -> Path:
    """The shipped default model's file."""
    return shipped_model_path(DEFAULT_MODEL)


def is_shipped(name: str) -> bool:
    return name in SHIPPED_MODELS
