"""Viseme blendshape rigs: load (folder of meshes, GLB morph targets, compact npz), validate, evaluate; ICT recipes.

`rig.gltf` is the package's one glTF reader (`read_gltf_mesh`); `animation.gltf` reads characters through it.
"""

from importlib import resources
from pathlib import Path

import numpy as np

from visemeflow.rig.gltf import GltfMesh, linear_to_srgb, read_gltf_mesh, srgb_to_linear
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


def rig_data_path(name: str) -> Path:
    """A file shipped in the package's `visemeflow/rig/data/` folder, as a filesystem path.

    Found through importlib.resources, so it is the installed package's copy (a wheel installs its package data
    unpacked, as real files), not the source checkout's.
    """
    resource = resources.files(__name__).joinpath("data", name)
    return resource if isinstance(resource, Path) else Path(str(resource))


def demo_rig_path() -> Path:
    """The shipped demo rig, package data `visemeflow/rig/data/ict_visemes.npz` (ICT Face Model, MIT)."""
    return rig_data_path("ict_visemes.npz")


def load_demo_rig() -> VisemeRig:
    """The shipped ICT demo rig (see visemeflow/rig/data/SOURCE.txt); RigError when the package lacks it."""
    path = demo_rig_path()
    if not path.is_file():
        raise RigError(f"{path}: demo rig not found (rebuild with examples/build_demo_rig.py)")
    return load_rig_npz(path)


def load_demo_arkit_shapes() -> tuple[list[str], np.ndarray]:
    """(ARKit names, (S, V, 3) float32 offsets on the demo rig's vertices): the ICT Face Model's 32 ARKit-style
    mouth, jaw, cheek and nose shapes, shipped as `data/ict_arkit.npz` (float16, the vertices they move), so that
    `examples/build_arkit_character.py` makes an ARKit-named head without the raw kit. RigError naming the file when
    it is missing or does not fit the demo rig."""
    path = rig_data_path("ict_arkit.npz")
    n_vertices = load_demo_rig().n_vertices
    try:
        with np.load(path, allow_pickle=False) as data:
            names = [str(n) for n in data["names"]]
            vertices, deltas = data["vertices"].astype(np.int64), data["deltas"].astype(np.float32)
    except (OSError, KeyError, ValueError) as exc:
        raise RigError(f"{path}: cannot read the demo ARKit shapes ({exc}); rebuild them with "
                       "examples/build_arkit_character.py --write-shapes") from None
    if deltas.shape != (len(names), len(vertices), 3) or (len(vertices) and not
                                                           (0 <= vertices.min() and vertices.max() < n_vertices)):
        raise RigError(f"{path}: shapes {deltas.shape} of {len(names)} names on {len(vertices)} vertex ids do not fit "
                       f"the demo rig's {n_vertices} vertices")
    full = np.zeros((len(names), n_vertices, 3), np.float32)
    full[:, vertices] = deltas
    return names, full


__all__ = [
    "N_LANDMARKS",
    "GltfMesh",
    "MeshData",
    "Recipes",
    "RigError",
    "RigTensors",
    "VisemeRig",
    "combine_shapes",
    "demo_rig_path",
    "evaluate_rig",
    "linear_to_srgb",
    "load_demo_arkit_shapes",
    "load_demo_rig",
    "load_ict_recipes",
    "load_rig",
    "load_rig_folder",
    "load_rig_glb",
    "load_rig_npz",
    "parse_recipes",
    "read_gltf_mesh",
    "read_landmarks_json",
    "read_mesh",
    "read_obj",
    "recipe_shapes",
    "rig_data_path",
    "rig_tensors",
    "save_rig_npz",
    "srgb_to_linear",
    "validate_rig",
]
