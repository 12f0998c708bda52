"""A real ARKit-named character end to end: the ICT Face Model's own shapes under ARKit names (built from
`../shared/data/ict_facekit` by examples/build_arkit_character.py), detected as ARKit, animated by the `animate`
flow through the measured ARKit table, and the GLB accepted by the Khronos validator."""

import sys
from pathlib import Path

import numpy as np
import pytest
from factories import REPO, SHARED_DATA, make_curve_store, validate

from visemeflow.articulation import close_lips
from visemeflow.animation.apply import resample_visemes
from visemeflow.shapes.conventions import arkit_weights, bind, detect_convention
from visemeflow.animation.gltf import write_glb
from visemeflow.animation.load import load_character
from visemeflow.animation.package import AnimateConfig
from visemeflow.animation.usd import read_usd_weights
from visemeflow.schemas import curves_array

sys.path.insert(0, str(REPO / "examples"))
from build_arkit_character import build_character  # noqa: E402

ICT = SHARED_DATA / "ict_facekit"


@pytest.fixture(scope="module")
def arkit_glb(tmp_path_factory):
    assert ICT.is_dir(), f"{ICT} missing: the shared data must be present"
    character = build_character(ICT)
    path = tmp_path_factory.mktemp("characters") / "ict_arkit.glb"
    write_glb(path, character, np.zeros((1, character.n_shapes), np.float32), 30.0, name="rest")
    return path


def test_the_ict_arkit_character_is_detected_and_every_viseme_reaches_its_shapes(arkit_glb):
    character = load_character(arkit_glb)
    assert character.n_shapes == 32 and "jawOpen" in character.shape_names
    assert character.vertex_colors is None or character.vertex_colors.shape == (character.n_vertices, 3)
    assert detect_convention(character) == "arkit52"
    binding = bind(character)
    assert binding.missing == () and binding.unmapped == ()
    curves = np.eye(16, dtype=np.float32)
    table = arkit_weights(curves)
    weights = binding.weights(curves)
    from visemeflow.shapes.conventions import ARKIT_52

    for j, name in enumerate(character.shape_names):
        np.testing.assert_allclose(weights[:, j], table[:, ARKIT_52.index(name)], atol=1e-6)


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_animating_the_arkit_character_writes_files_the_validator_and_usd_accept(tmp_path, arkit_glb):
    from visemeflow.flows.animate import AnimateParams, animate_flow

    store = make_curve_store(tmp_path / "store", n=1)
    result = animate_flow(AnimateParams(store=store.root, characters=[arkit_glb], source="ground_truth",
                                        config=AnimateConfig(formats=("glb", "usd"), fps=30.0)))
    (report,) = result["packages_written"]
    assert report["convention"] == "arkit52" and report["frames"] == 29
    issues = validate(Path(report["files"]["glb"]))["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0
    curves = close_lips(resample_visemes(curves_array(store.read_curves("spk/u0", "ground_truth", "cm")), 25.0, 30.0))   # what the exports play: the lip rules on
    names, weights, fps = read_usd_weights(report["files"]["usd"])
    character = load_character(arkit_glb)
    assert names == character.shape_names and fps == 30.0
    # a glTF character is in metres, and its USD says so (it said 0.01 for every character: a head 2 mm wide)
    from pxr import Usd, UsdGeom

    assert UsdGeom.GetStageMetersPerUnit(Usd.Stage.Open(report["files"]["usd"])) == 1.0
    np.testing.assert_allclose(weights, bind(character).weights(curves), atol=1e-6)


def test_the_shipped_arkit_shapes_are_the_kits_and_make_the_character_without_it(tmp_path):
    """A new user without ../shared gets the same character from the package's ict_arkit.npz (float16 offsets of the
    vertices the shapes move: within 0.001 cm, 0.01 mm, of the raw kit's)."""
    from build_arkit_character import main

    assert ICT.is_dir(), f"{ICT} missing: the shared data must be present"
    shipped, raw = build_character(), build_character(ICT)
    assert shipped.shape_names == raw.shape_names and len(shipped.shape_names) == 32
    assert np.abs(shipped.deltas - raw.deltas).max() <= 1e-3
    np.testing.assert_array_equal(shipped.neutral, raw.neutral)
    assert main(["--out", str(tmp_path / "c" / "ict_arkit.glb")]) == 0
    character = load_character(tmp_path / "c" / "ict_arkit.glb")
    assert detect_convention(character) == "arkit52" and character.n_shapes == 32
    width = float(np.ptp(character.neutral[:, 0]))   # the ICT rig's centimetres written as glTF's metres
    assert 0.15 < width < 0.25 and character.mm_per_unit == 1000.0, width
    np.testing.assert_allclose(character.neutral, shipped.neutral * 0.01, rtol=1e-6, atol=1e-7)
    issues = validate(tmp_path / "c" / "ict_arkit.glb")["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]
