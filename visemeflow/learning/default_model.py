"""The model shipped with the package, so that `visemeflow predict AUDIO` works on a fresh machine without training.

`visemeflow/learning/data/default.pt` is written by `examples/train_default_model.py` (its recipe, data lineage and
real-speech figures are in `visemeflow/learning/data/README.md` and the README). The predict and speak flows
install it into a store as the model `default` the first time it is asked for; a user's own model named
`default` in the store takes precedence.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

DEFAULT_MODEL = "default"


def default_model_path() -> Path:
    """The shipped model file (it may be missing from a source tree where it was never trained)."""
    resource = resources.files("visemeflow.learning").joinpath("data", "default.pt")
    return resource if isinstance(resource, Path) else Path(str(resource))
