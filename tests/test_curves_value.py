"""`Curves`, the one value a curve travels as (issue 27 item 3): the array, its rate and what it belongs to; the
store writes its rate into the file and gives it back, and the tasks that used to guess the rate from frame times
(animate, train) read the recorded one."""

import numpy as np
import pyarrow as pa
import pytest

from visemeflow.schemas import CURVES, Curves, curves_table, fps_of_table
from visemeflow.storage import Store
from visemeflow.tasks.animate import curves_and_fps
from visemeflow.visemes import N_VISEMES


def curves(n=7, fps=29.97, uid="spk/a", source="procedural", variant="default", provenance="made by a test"):
    values = np.random.default_rng(0).random((n, N_VISEMES)).astype(np.float32)
    return Curves(values, fps, uid, source, variant, provenance)


def test_a_stored_value_comes_back_equal_with_its_rate_and_provenance(tmp_path):
    store = Store(tmp_path / "store")
    c = curves()
    store.save_curves(c)
    back = store.load_curves("spk/a", "procedural")
    assert back == c and back.fps == 29.97 and back.provenance == "made by a test"
    assert back.values.dtype == np.float32 and back.duration_s == pytest.approx(7 / 29.97)
    # the table the store holds is the ordinary `curves` table, with the rate in its metadata
    assert store.read_curves("spk/a", "procedural").schema.equals(CURVES)


def test_the_recorded_rate_wins_over_the_frame_times_and_the_tasks_read_it(tmp_path):
    """An NTSC rate: (n - 1) / last time recovers it only to float rounding; the recorded one is exact, and
    animate's reader (which guessed from the times before) now gives it."""
    store = Store(tmp_path / "store")
    store.save_curves(curves(n=3, fps=30000 / 1001))
    values, fps, path = curves_and_fps(store, "spk/a", "procedural", "default")
    assert fps == 30000 / 1001 and values.shape == (3, N_VISEMES) and path.endswith(".parquet")


def test_files_without_a_recorded_rate_fall_back_to_the_frame_times_then_the_default(tmp_path):
    store = Store(tmp_path / "store")
    c = curves(n=5, fps=25.0)
    store.write_curves(curves_table(c.utterance_id, c.source, c.variant, c.values, 25.0), fps=None)  # an old writer
    assert store.load_curves("spk/a", "procedural").fps == 25.0
    one = curves(n=1, fps=25.0, uid="spk/b")
    store.write_curves(curves_table(one.utterance_id, one.source, one.variant, one.values, 25.0), fps=None)
    assert store.load_curves("spk/b", "procedural").fps == 30.0                       # the package default
    assert store.load_curves("spk/b", "procedural", default_fps=24.0).fps == 24.0     # the caller's (train: the row's)
    table = curves_table("x/y", "procedural", "v", np.zeros((4, N_VISEMES)), 50.0)
    assert fps_of_table(table) == 50.0


def test_bad_values_are_refused_naming_the_utterance():
    with pytest.raises(ValueError, match="spk/a.*shape"):
        Curves(np.zeros((4, 15)), 30.0, "spk/a", "procedural", "v")
    with pytest.raises(ValueError, match="spk/a.*frame rate"):
        Curves(np.zeros((4, N_VISEMES)), float("nan"), "spk/a", "procedural", "v")
    two = pa.concat_tables([curves().to_table(), curves(uid="spk/b").to_table()])
    with pytest.raises(ValueError, match="one utterance"):
        Curves.from_table(two)

