"""Viseme blendshape rigs: load (folder of meshes, GLB morph targets, compact npz), validate, evaluate; ICT recipes."""

from pathlib import Path

from visemeflow.rig.io import (
    MeshData,
    load_rig,
    load_rig_folder,
    load_rig_glb,
    load_rig_npz,
    read_landmarks_json,
    read_mesh,
    read_obj,
    save_rig_npz,
)
from visemeflow.rig.model import (
    N_LANDMARKS,
    RigError,
    RigTensors,
    VisemeRig,
    evaluate_rig,
    rig_tensors,
    validate_rig,
)
from visemeflow.rig.recipes import (
    Recipes,
    combine_shapes,
    load_ict_recipes,
    parse_recipes,
    recipe_shapes,
)


def demo_rig_path() -> Path:
    """The shipped demo rig, `examples/rig/ict_visemes.npz` of the source checkout (ICT Face Model, MIT)."""
    return Path(__file__).resolve().parents[2] / "examples" / "rig" / "ict_visemes.npz"


def load_demo_rig() -> VisemeRig:
    """The shipped ICT demo rig (see examples/rig/SOURCE.txt); RigError when the checkout does not have it."""
    path = demo_rig_path()
    if not path.is_file():
        raise RigError(f"{path}: demo rig not found (rebuild with examples/build_demo_rig.py)")
    return load_rig_npz(path)


__all__ = [
    "N_LANDMARKS",
    "MeshData",
    "Recipes",
    "RigError",
    "RigTensors",
    "VisemeRig",
    "combine_shapes",
    "demo_rig_path",
    "evaluate_rig",
    "load_demo_rig",
    "load_ict_recipes",
    "load_rig",
    "load_rig_folder",
    "load_rig_glb",
    "load_rig_npz",
    "parse_recipes",
    "read_landmarks_json",
    "read_mesh",
    "read_obj",
    "recipe_shapes",
    "rig_tensors",
    "save_rig_npz",
    "validate_rig",
]
