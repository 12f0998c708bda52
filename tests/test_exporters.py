"""Export formats are records of one table (`visemeflow.animation.formats.EXPORTERS`): the config's format check,
the package's file names and the writers all read it, so a new format is its writer and one `register_exporter`
call. This file adds one (`test-npy`: the shape weights as a NumPy array) and animates with it."""

import numpy as np
import pytest

from visemeflow.rig.character import character_from_rig
from visemeflow.shapes.conventions import bind
from visemeflow.animation.package import (
    EXPORTERS,
    AnimateConfig,
    Exporter,
    ExportTarget,
    bone_only_formats,
    export_animation,
    export_paths,
    register_exporter,
)
from visemeflow.rig import load_demo_rig


def write_npy(t: ExportTarget) -> None:
    np.save(t.path, t.weights)


NPY = Exporter("test-npy", ".weights.npy", write_npy)


@pytest.fixture(autouse=True)
def registered():
    """Registered for these tests only: tests elsewhere that go over every format see the shipped ones."""
    register_exporter(NPY)
    yield
    EXPORTERS.pop(NPY.name)


def test_a_registered_format_is_accepted_named_and_written(tmp_path):
    character = character_from_rig(load_demo_rig())
    binding = bind(character)
    curves = np.zeros((12, 16), np.float32)
    curves[3:8, 0] = 0.8
    config = AnimateConfig(formats="test-npy,curves-csv", fps=30.0)
    package = export_animation(tmp_path, "u", character, binding, curves, 30.0, config, utterance_id="s/u")
    assert package.files["test-npy"] == str(tmp_path / "u.weights.npy")
    np.testing.assert_array_equal(np.load(tmp_path / "u.weights.npy"), package.weights)
    assert (tmp_path / "u.curves.csv").is_file()
    assert export_paths(tmp_path, "u", ("test-npy", "glb"), "bones") == {
        "test-npy": tmp_path / "u.weights.npy", "glb": tmp_path / "u.bones.glb"}


def test_the_table_refuses_what_it_cannot_write():
    with pytest.raises(ValueError, match="unknown export format.*known: .*test-npy"):
        AnimateConfig(formats="test-nope")
    with pytest.raises(ValueError, match="already registered"):
        register_exporter(Exporter("test-npy", ".other.npy", write_npy))
    assert register_exporter(NPY) is NPY and EXPORTERS["test-npy"] is NPY
    with pytest.raises(ValueError, match="needs a writer"):
        register_exporter(Exporter("test-half", ".x", None))
    with pytest.raises(ValueError, match="bone-mode formats"):
        AnimateConfig(formats="pose-csv")
    assert set(bone_only_formats()) == {"pose-csv", "pose-json"}

