"""The Parquet store and the schemas/ids it relies on."""

import errno
import io
import multiprocessing
import re
import zlib
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest

from visemeflow.schemas import (
    CURVES,
    PHONES,
    REJECTS,
    UTTERANCES,
    C,
    InvalidIdError,
    curves_array,
    curves_table,
    id_path_parts,
    make_utterance_id,
    normalize_utterance_id,
    shard_of,
    split_utterance_id,
    table_from_rows,
    utterance_id_from_path_parts,
    validate_name,
    validate_utterance_id,
)
from visemeflow.storage import NonFiniteValueError, Store, StoreError
from visemeflow.visemes import N_VISEMES, VISEMES

BAD_IDS = ["../x", "a/../../b", "a/.hidden", "a/b/c", "a", "", "/a", "a/", "./a", "a/..", "a\\b/c", "spk/na\x00me",
           "spk/a\\..\\..\\b", "spk/line\nbreak", "spk/tab\tname", "spk/\u202egnp.exe", " spk/a", "spk/a ", "spk/..",
           "u\u0308/a", "spk/" + "x" * 201]


def curves_of(utterance_id: str, n: int = 10, source: str = "procedural", variant: str = "v1", seed: int = 0, fps=30.0):
    values = np.random.default_rng(seed).random((n, N_VISEMES), dtype=np.float32)
    return values, curves_table(utterance_id, source, variant, values, fps)


def phone_rows(utterance_id: str, n: int, tag: str = "x") -> pa.Table:
    rows = [{C.UTTERANCE_ID: utterance_id, C.INDEX: i, C.PART: 0, C.LABEL: f"{tag}{i}", C.PHONEME: "AA",
             C.VISEME: "AAA", C.START_S: 0.1 * i, C.END_S: 0.1 * i + 0.1} for i in range(n)]
    return table_from_rows(rows, PHONES)


def visible_files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob("*") if p.is_file())


# ---- schemas and ids ---------------------------------------------------------------------------

def test_curves_table_and_array_round_trip():
    values, table = curves_of("spk/u1", n=7, fps=25.0)
    assert table.schema.equals(CURVES)
    assert table.column_names[:5] == [C.UTTERANCE_ID, C.SOURCE, C.VARIANT, C.FRAME, C.TIME_S]
    assert table.column_names[5:] == list(VISEMES)
    assert table.column(C.FRAME).to_pylist() == list(range(7))
    assert table.column(C.TIME_S).to_pylist() == pytest.approx([k / 25.0 for k in range(7)])
    out = curves_array(table)
    assert out.dtype == np.float32 and out.shape == (7, N_VISEMES)
    np.testing.assert_array_equal(out, values)
    assert curves_array(curves_table("s/e", "tracked", "v", np.zeros((0, N_VISEMES)), 30)).shape == (0, N_VISEMES)


def test_curves_table_rejects_bad_input():
    with pytest.raises(ValueError, match="shape"):
        curves_table("s/u", "procedural", "v", np.zeros((5, 15)), 30)
    with pytest.raises(ValueError, match="source"):
        curves_table("s/u", "guessed", "v", np.zeros((5, N_VISEMES)), 30)


def test_table_from_rows_fills_nullable_columns():
    table = table_from_rows([{C.UTTERANCE_ID: "s/u", C.INDEX: 0, C.PART: 0, C.LABEL: "", C.START_S: 0.0, C.END_S: 1.0}], PHONES)
    assert table.schema.equals(PHONES) and table.column(C.VISEME).to_pylist() == [None]


@pytest.mark.parametrize("bad", BAD_IDS)
def test_bad_utterance_ids_are_rejected(bad, tmp_path):
    with pytest.raises(InvalidIdError):
        validate_utterance_id(bad)
    with pytest.raises(InvalidIdError):
        Store(tmp_path).curve_path("procedural", "v1", bad)
    with pytest.raises(InvalidIdError):
        Store(tmp_path).write_curves(curves_of(bad)[1])
    with pytest.raises(InvalidIdError):
        split_utterance_id(bad)
    assert not (tmp_path / "curves").exists() and not (tmp_path.parent / "x.parquet").exists()


@pytest.mark.parametrize("good", ["LJ/LJ001-0001", "s1/bwbg8n", "SSB1624/SSB16240001", "a_b/c.d-e", "A/b..c"])
def test_good_utterance_ids(good, tmp_path):
    assert validate_utterance_id(good) == good
    speaker, name = split_utterance_id(good)
    assert Store(tmp_path).curve_path("procedural", "v1", good) == (
        tmp_path.resolve() / "curves" / "procedural" / "v1" / speaker / f"{name}.parquet")


UNICODE_IDS = ["Speaker One/take 1", "Sprecher_ü/Äpfel", "张三/一", "spk/it's (2), #3 & more!", "spk/100%", "A/b~c",
               "مريم/جملة", "spk/utt__pitch_p2.10"]


@pytest.mark.parametrize("good", UNICODE_IDS)
def test_unicode_ids_round_trip_through_the_store(good, tmp_path):
    """Ids of any script, with spaces and punctuation: stable ASCII store paths, the same id read back."""
    store = Store(tmp_path)
    assert validate_utterance_id(good) == good
    path = store.curve_path("procedural", "v1", good)
    assert path.parent.parent == tmp_path.resolve() / "curves" / "procedural" / "v1"
    assert path.relative_to(tmp_path.resolve()).as_posix().isascii() and " " not in str(path.relative_to(tmp_path.resolve()))
    assert Store.utterance_id_of(path) == good and utterance_id_from_path_parts(*id_path_parts(good)) == good
    values, table = curves_of(good, n=5)
    assert store.write_curves(table, provenance="p") == path
    np.testing.assert_array_equal(curves_array(store.read_curves(good, "procedural")), values)
    assert store.curve_ids("procedural", "v1") == [good]
    assert store.scan_curves(utterance_ids=[good]).num_rows == 5
    assert store.augmented_audio_path("pitch-s0", good).parent == path.parent.parent.parent.parent.parent \
        / "augmented" / "pitch-s0" / path.parent.name


def test_path_encoding_is_fixed():
    """Store paths of ids are a file format: these must never change (older stores must stay readable)."""
    assert id_path_parts("LJ/LJ001-0001") == ("LJ", "LJ001-0001")
    assert id_path_parts("a_b/c.d-e") == ("a_b", "c.d-e")
    assert id_path_parts("张三/一") == ("%E5%BC%A0%E4%B8%89", "%E4%B8%80")
    assert id_path_parts("Speaker One/a%b") == ("Speaker%20One", "a%25b")
    assert id_path_parts("Sprecher_ü/x") == ("Sprecher_%C3%BC", "x")


def test_files_a_person_opens_are_named_as_the_id_reads_and_stay_apart():
    """`--out` of animate and speak: `my voice/take 1.glb`, not `my%20voice/take%201.glb`; only what a file system
    refuses (and `%`) is encoded, so different ids never share a file."""
    from visemeflow.schemas import readable_path_parts
    from visemeflow.tasks.animate import package_dir

    assert readable_path_parts("predict/my voice stereo") == ("predict", "my voice stereo")
    assert readable_path_parts("张三/一") == ("张三", "一")
    assert readable_path_parts('a/x: "y"?') == ("a", "x%3A %22y%22%3F")
    assert readable_path_parts("a/x%20y") != readable_path_parts("a/x y")
    store = Store(Path("/tmp/unused-store"))
    assert package_dir(store, "/out", "ict_visemes", "predict/my voice") == Path("/out/ict_visemes/predict/my voice")
    assert package_dir(store, None, "ict_visemes", "predict/my voice") == \
        store.root / "animations" / "ict_visemes" / "predict" / "my%20voice"


def test_ids_are_nfc_normalised_where_they_are_made():
    decomposed = "Sprecher_u\u0308"
    with pytest.raises(InvalidIdError, match="NFC"):
        validate_utterance_id(decomposed + "/a")
    assert make_utterance_id(decomposed, "a") == "Sprecher_\u00fc/a"
    assert normalize_utterance_id(decomposed + "/a") == "Sprecher_\u00fc/a"


@pytest.mark.parametrize("bad, why", [
    ("a/..", "starts with '.'"), ("../a", "starts with '.'"), ("a\\b/c", "backslash"), ("a/b/c", "exactly one '/'"),
    ("spk/a\x07b", "U+0007"), ("spk/a\u202eb", "U+202E"), ("spk/a ", "space"), ("spk/" + "字" * 80, "too long"),
])
def test_bad_ids_say_why(bad, why):
    with pytest.raises(InvalidIdError, match=re.escape(why)):
        validate_utterance_id(bad)


def test_store_paths_not_made_by_the_store_are_not_ids():
    for speaker, name in (("a%2Fb", "c"), ("x", "%2E%2E"), ("x", "%E5%BC"), ("%41", "b")):
        with pytest.raises((InvalidIdError, UnicodeDecodeError)):
            utterance_id_from_path_parts(speaker, name)


@pytest.mark.parametrize("bad", ["..", ".", ".x", "a/b", "", "a b", "ü"])
def test_bad_names_are_rejected(bad, tmp_path):
    with pytest.raises(InvalidIdError):
        validate_name(bad)
    with pytest.raises(InvalidIdError):
        Store(tmp_path).curve_path("procedural", bad, "s/u")
    if bad:  # an empty stage means "no stage"
        with pytest.raises(InvalidIdError):
            Store(tmp_path).shard_path("rejects", 0, stage=bad)


def test_shard_of_is_stable_and_in_range():
    assert shard_of("LJ/LJ001-0001", 16) == 15
    assert shard_of("SSB1624/SSB16240001", 1000) == 537
    assert shard_of("LJ/LJ001-0001", 16) == zlib.crc32(b"LJ/LJ001-0001") % 16
    for n in (1, 2, 7, 64):
        shards = [shard_of(f"spk{i % 3}/utt{i:04d}", n) for i in range(500)]
        assert all(0 <= s < n for s in shards)
        assert len(set(shards)) == n  # 500 ids spread over every shard


# ---- curves ------------------------------------------------------------------------------------

def test_write_and_read_curves_round_trip(tmp_path):
    store = Store(tmp_path / "store")
    values, table = curves_of("spk/u1", n=12)
    path = store.write_curves(table, provenance="procedural v1 cfg=abc", fps=30.0)
    assert path == store.curve_path("procedural", "v1", "spk/u1") and path.is_file()
    assert store.has_curves("procedural", "v1", "spk/u1")
    back = store.read_curves("spk/u1", "procedural")
    assert back.equals(table)
    np.testing.assert_array_equal(curves_array(back), values)
    assert store.read_curves("spk/u1", "procedural", "v1").equals(table)
    assert store.curves_provenance("procedural", "v1", "spk/u1") == "procedural v1 cfg=abc"
    assert store.curves_provenance("procedural", "v1", "spk/u2") is None
    assert pq.read_schema(path).metadata[b"visemeflow.fps"] == b"30.0"
    # a rewrite replaces the file whole
    values2, table2 = curves_of("spk/u1", n=5, seed=1)
    store.write_curves(table2, provenance="second")
    np.testing.assert_array_equal(curves_array(store.read_curves("spk/u1", "procedural")), values2)
    assert store.curves_provenance("procedural", "v1", "spk/u1") == "second"
    assert visible_files(tmp_path / "store" / "curves") == ["u1.parquet"]


def test_read_curves_lookup_errors(tmp_path):
    store = Store(tmp_path)
    with pytest.raises(LookupError, match="spk/u1"):
        store.read_curves("spk/u1", "procedural")
    store.write_curves(curves_of("spk/u1", variant="a")[1])
    store.write_curves(curves_of("spk/u1", variant="b")[1])
    assert store.curve_variants("procedural", "spk/u1") == ["a", "b"]
    with pytest.raises(LookupError, match="2 variants"):
        store.read_curves("spk/u1", "procedural")
    with pytest.raises(LookupError, match="'c'"):
        store.read_curves("spk/u1", "procedural", "c")
    # what a user can do next: the variants there are, the sources that hold the utterance, no variant to name
    with pytest.raises(LookupError, match=r"no procedural curves of variant 'c' .*; its variants: a, b$"):
        store.read_curves("spk/u1", "procedural", "c")
    with pytest.raises(LookupError, match=r"^spk/u1: no tracked curves in .*; it has procedural curves "
                                          r"\(--source procedural\)$"):
        store.read_curves("spk/u1", "tracked")
    with pytest.raises(LookupError, match=r"^spk/nope: no procedural curves in [^;]*$"):
        store.read_curves("spk/nope", "procedural")


def test_write_curves_holds_one_utterance(tmp_path):
    mixed = pa.concat_tables([curves_of("s/a")[1], curves_of("s/b")[1]])
    with pytest.raises(ValueError, match="one utterance"):
        Store(tmp_path).write_curves(mixed)


def test_scan_curves_with_filters(tmp_path):
    store = Store(tmp_path)
    expected = {}
    for i in range(30):
        uid = f"spk{i % 4}/utt{i:03d}"
        for source, variant in (("procedural", "v1"), ("procedural", "v2"), ("tracked", "fit")):
            values, table = curves_of(uid, n=3 + i % 5, source=source, variant=variant, seed=i)
            store.write_curves(table)
            expected[(source, variant, uid)] = values
    everything = store.scan_curves()
    assert everything.num_rows == sum(len(v) for v in expected.values())
    assert everything.schema.equals(CURVES)
    v1 = store.scan_curves("procedural", "v1")
    assert set(v1.column(C.VARIANT).to_pylist()) == {"v1"} and set(v1.column(C.SOURCE).to_pylist()) == {"procedural"}
    assert v1.num_rows == sum(len(v) for (s, var, _), v in expected.items() if (s, var) == ("procedural", "v1"))
    assert store.scan_curves("procedural").num_rows == 2 * v1.num_rows
    picked = ["spk1/utt005", "spk3/utt007"]
    sub = store.scan_curves("tracked", "fit", utterance_ids=picked)
    assert sorted(set(sub.column(C.UTTERANCE_ID).to_pylist())) == picked
    for uid in picked:
        part = sub.filter(pa.compute.equal(sub.column(C.UTTERANCE_ID), uid)).sort_by(C.FRAME)
        np.testing.assert_array_equal(curves_array(part), expected[("tracked", "fit", uid)])
    cols = store.scan_curves("procedural", "v2", columns=[C.UTTERANCE_ID, "MBP"])
    assert cols.column_names == [C.UTTERANCE_ID, "MBP"] and cols.num_rows == v1.num_rows
    assert store.scan_curves("predicted").num_rows == 0
    assert store.scan_curves("predicted", columns=["AAA"]).column_names == ["AAA"]
    assert store.scan_curves(utterance_ids=[]).num_rows == 0
    assert store.read_table("phones", utterance_ids=[]).num_rows == 0


# ---- shards -------------------------------------------------------------------------------------

def test_write_shard_and_read_table(tmp_path):
    store = Store(tmp_path)
    assert store.read_table("phones").num_rows == 0 and store.read_table("phones").schema.equals(PHONES)
    store.write_shard("phones", 0, pa.concat_tables([phone_rows("s/a", 3), phone_rows("s/b", 2)]))
    store.write_shard("phones", 7, phone_rows("s/c", 4), metadata={b"k": b"v"})
    assert store.shard_path("phones", 7).name == "shard-0007.parquet"
    assert pq.read_schema(store.shard_path("phones", 7)).metadata[b"k"] == b"v"
    table = store.read_table("phones")
    assert table.num_rows == 9 and table.schema.equals(PHONES)
    assert store.read_table("phones", utterance_ids=["s/b", "s/c"]).num_rows == 6
    assert store.read_shard("phones", 7).equals(phone_rows("s/c", 4))
    assert store.read_shard("phones", 3).num_rows == 0
    store.delete_shard("phones", 7)
    assert store.read_table("phones").num_rows == 5
    with pytest.raises((KeyError, ValueError), match="nope"):
        store.write_shard("nope", 0, phone_rows("s/a", 1))


def test_rejects_per_stage(tmp_path):
    import datetime as dt

    store = Store(tmp_path)
    now = dt.datetime.now(dt.timezone.utc)

    def rejects(uid, stage):
        return table_from_rows([{C.UTTERANCE_ID: uid, C.STAGE: stage, C.ERROR_TYPE: "E", C.MESSAGE: "m", C.TIME: now}], REJECTS)

    store.write_shard("rejects", 0, rejects("s/a", "ingest"), stage="ingest")
    store.write_shard("rejects", 0, rejects("s/b", "procedural"), stage="procedural")
    assert store.read_table("rejects", stage="ingest").column(C.UTTERANCE_ID).to_pylist() == ["s/a"]
    assert sorted(store.read_table("rejects").column(C.UTTERANCE_ID).to_pylist()) == ["s/a", "s/b"]


def test_replace_utterance_rows_replaces_exactly_one_utterance(tmp_path):
    store = Store(tmp_path)
    store.write_shard("phones", 2, pa.concat_tables([phone_rows("s/a", 3), phone_rows("s/b", 2), phone_rows("s/c", 1)]))
    store.replace_utterance_rows("phones", 2, "s/b", phone_rows("s/b", 4, tag="new"))
    table = store.read_shard("phones", 2)
    by_id = {}
    for row in table.to_pylist():
        by_id.setdefault(row[C.UTTERANCE_ID], []).append(row[C.LABEL])
    assert by_id == {"s/a": ["x0", "x1", "x2"], "s/b": ["new0", "new1", "new2", "new3"], "s/c": ["x0"]}
    store.replace_utterance_rows("phones", 2, "s/a", phone_rows("s/a", 0))  # remove
    assert sorted(set(store.read_shard("phones", 2).column(C.UTTERANCE_ID).to_pylist())) == ["s/b", "s/c"]
    store.replace_utterance_rows("phones", 5, "s/z", phone_rows("s/z", 2))  # new shard file
    assert store.read_shard("phones", 5).num_rows == 2
    assert store.read_table("utterances").schema.equals(UTTERANCES)


def test_a_whole_shard_write_waits_for_the_shards_lock_and_keeps_what_is_stored_then(tmp_path):
    """`write_shard` takes the lock `replace_utterance_rows` takes, and `keep` chooses among the rows stored when it
    holds it: an utterance replaced while a whole-shard writer was computing is not lost to it."""
    import threading

    store = Store(tmp_path)
    store.write_shard("phones", 2, pa.concat_tables([phone_rows("s/a", 3), phone_rows("s/b", 2)]))
    done = []

    def keep_b(stored):
        return stored.filter(pc.equal(stored.column(C.UTTERANCE_ID), "s/b"))

    writer = threading.Thread(target=lambda: done.append(
        store.write_shard("phones", 2, phone_rows("s/a", 1, tag="whole"), keep=keep_b)))
    with store.locked("phones-all-0002"):
        writer.start()
        writer.join(0.5)
        assert writer.is_alive() and not done        # it waits for the lock
        # what a rerun holding the lock writes meanwhile (here: by hand, as the lock is ours)
        pq.write_table(pa.concat_tables([phone_rows("s/a", 3), phone_rows("s/b", 4, tag="rerun")]),
                       store.shard_path("phones", 2))
    writer.join(30)
    assert done
    by_id = {}
    for row in store.read_shard("phones", 2).to_pylist():
        by_id.setdefault(row[C.UTTERANCE_ID], []).append(row[C.LABEL])
    assert by_id == {"s/a": ["whole0"], "s/b": ["rerun0", "rerun1", "rerun2", "rerun3"]}


# ---- no NaN or infinity is ever written ---------------------------------------------------------

@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_write_curves_refuses_non_finite_values(tmp_path, bad):
    store = Store(tmp_path)
    values, table = curves_of("张三/一", n=10, source="tracked", variant="guided-fast")
    path = store.write_curves(table, provenance="old")
    before = path.read_bytes()
    values = values.copy()
    values[6, VISEMES.index("MBP")] = bad
    values[8, 0] = bad
    with pytest.raises(NonFiniteValueError) as info:
        store.write_curves(curves_table("张三/一", "tracked", "guided-fast", values, 30.0), provenance="new")
    message = str(info.value)
    assert "张三/一" in message and "tracked/guided-fast" in message
    assert "frame 6" in message and "column MBP" in message and str(bad) in message
    assert path.read_bytes() == before  # the stored curves are untouched
    with pytest.raises(NonFiniteValueError, match="frame rate"):
        store.write_curves(table, fps=float("nan"))
    times = table.column(C.TIME_S).to_numpy().copy()
    times[0] = np.inf
    broken = table.set_column(table.schema.get_field_index(C.TIME_S), C.TIME_S, pa.array(times))
    with pytest.raises(NonFiniteValueError, match=f"frame 0, column {C.TIME_S}"):
        store.write_curves(broken)
    assert not store.curve_files("tracked", "other")


def test_write_metrics_refuses_non_finite_values(tmp_path):
    from visemeflow.schemas import METRICS

    store = Store(tmp_path)
    row = {C.RUN: "evaluate", C.MODEL: "m", C.CONDITION: "pitch", C.UTTERANCE_ID: None, C.L1: 0.1, C.L1_X100: 10.0}
    store.write_metrics("m", "evaluate", pa.Table.from_pylist([row], schema=METRICS))  # nulls are fine
    for column, bad in ((C.L1_X100, float("nan")), (C.L1_PREFIX + "AAA", float("inf"))):
        rows = [row, {**row, C.UTTERANCE_ID: "spk/u1", column: bad}]
        with pytest.raises(NonFiniteValueError) as info:
            store.write_metrics("m", "evaluate", pa.Table.from_pylist(rows, schema=METRICS))
        assert "model m" in str(info.value) and "spk/u1" in str(info.value) and column in str(info.value)
    assert store.read_metrics("m").num_rows == 1


# ---- rejects of a stage replaced --------------------------------------------------------------------

def _rejects_of(*ids: str, stage: str = "track") -> pa.Table:
    import datetime as dt

    now = dt.datetime.now(dt.timezone.utc)
    return table_from_rows([{C.UTTERANCE_ID: u, C.STAGE: stage, C.ERROR_TYPE: "E", C.MESSAGE: f"bad {u}", C.TIME: now}
                            for u in ids], REJECTS)


def test_replace_stage_rejects_writes_new_shards_and_removes_the_others(tmp_path):
    store = Store(tmp_path)
    store.write_shard("rejects", 1, _rejects_of("s/a"), stage="track")
    store.write_shard("rejects", 4, _rejects_of("s/b"), stage="track")
    store.write_shard("rejects", 1, _rejects_of("s/z", stage="ingest"), stage="ingest")
    assert store.shards("rejects", "track") == [1, 4]
    assert store.replace_stage_rejects("track", {4: _rejects_of("s/c"), 6: _rejects_of("s/d")}) == [1]
    assert store.shards("rejects", "track") == [4, 6]
    assert sorted(store.read_table("rejects", "track").column(C.UTTERANCE_ID).to_pylist()) == ["s/c", "s/d"]
    assert store.read_table("rejects", "ingest").num_rows == 1  # other stages untouched
    assert store.replace_stage_rejects("track", {}) == [4, 6] and store.shards("rejects", "track") == []


def test_a_crash_while_replacing_rejects_keeps_them_readable(tmp_path, monkeypatch):
    """Killed between writing the new rejects and removing the old: the stage still has its rejects."""
    store = Store(tmp_path)
    store.write_shard("rejects", 1, _rejects_of("s/a"), stage="track")
    store.write_shard("rejects", 4, _rejects_of("s/b"), stage="track")

    class Killed(BaseException):
        pass

    def killed(*args, **kwargs):
        raise Killed()

    monkeypatch.setattr(Store, "delete_shard", killed)
    with pytest.raises(Killed):
        store.replace_stage_rejects("track", {2: _rejects_of("s/c")})
    assert sorted(store.read_table("rejects", "track").column(C.UTTERANCE_ID).to_pylist()) == ["s/a", "s/b", "s/c"]
    monkeypatch.undo()

    written = []
    monkeypatch.setattr(Store, "write_shard", lambda self, *a, **k: written.append(a) or killed())
    with pytest.raises(Killed):  # killed while writing the first new shard: the old rejects are all there
        store.replace_stage_rejects("track", {2: _rejects_of("s/d"), 3: _rejects_of("s/e")})
    assert sorted(store.read_table("rejects", "track").column(C.UTTERANCE_ID).to_pylist()) == ["s/a", "s/b", "s/c"]


def test_reject_messages_are_capped_by_every_writer_of_rejects(tmp_path):
    """A 7.5 MB message (an XML entity expanded into an error) is stored as its head and how much was cut."""
    store = Store(tmp_path)
    huge = "head " + "x" * 7_500_000

    def one(uid: str, message: str) -> pa.Table:
        table = _rejects_of(uid)
        return table.set_column(table.schema.get_field_index(C.MESSAGE), C.MESSAGE, pa.array([message]))

    store.write_shard("rejects", 0, one("s/a", huge), stage="track")
    store.replace_utterance_rows("rejects", 0, "s/b", one("s/b", huge), stage="track")
    store.replace_stage_rejects("ingest", {1: one("s/c", huge), 2: one("s/d", "short")})
    for stage, uid in (("track", "s/a"), ("track", "s/b"), ("ingest", "s/c")):
        [message] = store.read_table("rejects", stage, [uid]).column(C.MESSAGE).to_pylist()
        assert len(message) < 10_000
        head, _, tail = message.partition("... [")
        assert huge.startswith(head) and len(head) > 1000
        assert tail == f"{len(huge) - len(head)} characters cut]"
    assert store.read_table("rejects", "ingest", ["s/d"]).column(C.MESSAGE).to_pylist() == ["short"]


def test_the_track_flow_replaces_its_rejects_through_the_store():
    """The flow asks the store to replace the stage's rejects (new shards first), it deletes no shard by hand."""
    import inspect

    from visemeflow.flows import track

    source = inspect.getsource(track.track_flow)
    assert "replace_stage_rejects" in source and ".unlink(" not in source and ".glob(" not in source


# ---- store layout through the Store ---------------------------------------------------------------

def test_models_reports_and_shards_are_reached_through_the_store(tmp_path):
    store = Store(tmp_path)
    assert store.model_names() == [] and store.report_files() == [] and store.shards("phones") == []
    store.model_path("done").parent.mkdir(parents=True)
    store.model_path("done").write_bytes(b"x")
    store.checkpoint_dir("done").mkdir()
    store.checkpoint_dir("running").mkdir(parents=True)
    assert store.model_names() == ["done"] and store.has_model("done") and not store.has_model("running")
    assert store.finished_checkpoint_dirs() == [store.checkpoint_dir("done")]
    store.write_report_text("robustness.md", "| a |")
    store.write_report("sweep-x.png", lambda tmp: tmp.write_bytes(b"png" if tmp.suffix == ".png" else b"?"))
    assert store.report_path("sweep-x.png").read_bytes() == b"png"
    assert [p.name for p in store.report_files(prefix="sweep-", suffix=".png")] == ["sweep-x.png"]
    with pytest.raises(InvalidIdError):
        store.report_path("../x")
    for shard in (3, 0, 12):
        store.write_shard("phones", shard, phone_rows("s/a", 1))
    assert store.shards("phones") == [0, 3, 12] and store.has_shard("phones", 3)
    assert store.delete_shards_except("phones", {3}) == [0, 12] and store.shards("phones") == [3]
    store.write_shard("utterances", 0, UTTERANCES.empty_table(), metadata={b"k": b"v"})
    assert store.shard_metadata("utterances", 0)[b"k"] == b"v" and store.shard_metadata("utterances", 1) is None
    with pytest.raises(ValueError, match="not inside the store"):
        store.write_file(tmp_path.parent / "elsewhere.txt", lambda tmp: tmp.write_text("x"))
    with pytest.raises(ValueError):
        store.delete_path(store.root)


# ---- atomic writes -------------------------------------------------------------------------------

def _half_writer(exc: BaseException):
    real = pq.write_table

    def write_half(table, where, *args, **kwargs):
        buf = io.BytesIO()
        real(table, buf, *args, **kwargs)
        data = buf.getvalue()
        with open(where, "wb") as fh:
            fh.write(data[: len(data) // 2])
        raise exc

    return write_half


@pytest.mark.parametrize("exc", [OSError(errno.ENOSPC, "No space left on device"), pa.ArrowInvalid("boom"),
                                 KeyboardInterrupt()])
def test_failed_write_leaves_previous_file_intact(tmp_path, monkeypatch, exc):
    store = Store(tmp_path)
    values, table = curves_of("spk/u1", n=8)
    path = store.write_curves(table, provenance="old")
    store.write_shard("phones", 0, phone_rows("s/a", 3))
    before_curves, before_shard = path.read_bytes(), store.shard_path("phones", 0).read_bytes()

    monkeypatch.setattr(pq, "write_table", _half_writer(exc))
    expected = StoreError if isinstance(exc, OSError) else type(exc)
    with pytest.raises(expected) as info:
        store.write_curves(curves_of("spk/u1", n=20, seed=5)[1], provenance="new")
    if expected is StoreError:
        assert str(path) in str(info.value) and "disk full" in str(info.value)
    with pytest.raises(expected):
        store.replace_utterance_rows("phones", 0, "s/a", phone_rows("s/a", 1))
    with pytest.raises(expected):
        store.write_shard("phones", 0, phone_rows("s/q", 1))
    monkeypatch.undo()

    assert path.read_bytes() == before_curves
    assert store.shard_path("phones", 0).read_bytes() == before_shard
    np.testing.assert_array_equal(curves_array(store.read_curves("spk/u1", "procedural")), values)
    assert store.curves_provenance("procedural", "v1", "spk/u1") == "old"
    assert store.scan_curves().num_rows == 8 and store.read_table("phones").num_rows == 3
    # no temporary file is left behind, hidden or not
    assert visible_files(tmp_path / "curves") == ["u1.parquet"]
    assert visible_files(tmp_path / "tables") == ["shard-0000.parquet"]


def _replace_many(root: str, speaker: str, n: int, barrier) -> None:
    store = Store(root)
    barrier.wait(60)  # start together, so the two writers really overlap
    for i in range(n):
        store.replace_utterance_rows("phones", 3, f"{speaker}/u{i:02d}", phone_rows(f"{speaker}/u{i:02d}", 1))


def test_two_processes_replacing_rows_lose_nothing(tmp_path):
    ctx = multiprocessing.get_context("spawn")
    barrier = ctx.Barrier(2)
    procs = [ctx.Process(target=_replace_many, args=(str(tmp_path), spk, 20, barrier)) for spk in ("A", "B")]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
    assert [p.exitcode for p in procs] == [0, 0]
    table = Store(tmp_path).read_shard("phones", 3)
    ids = table.column(C.UTTERANCE_ID).to_pylist()
    assert len(ids) == 40 and len(set(ids)) == 40
    assert visible_files(tmp_path / "tables") == ["shard-0003.parquet"]


def _rewrite_until(root: str, stop, started) -> None:
    store = Store(root)
    k = 0
    while not stop.is_set():
        k += 1
        n = 20 + (k % 9) * 40  # each version: its own length and value
        store.write_curves(curves_table("spk/u1", "procedural", "v1", np.full((n, N_VISEMES), k, np.float32), 30))
        store.write_shard("phones", 0, phone_rows("s/a", n, tag=f"v{k}-"))
        started.set()


def test_readers_see_whole_versions_while_a_writer_replaces_files(tmp_path):
    import time

    store = Store(tmp_path)
    ctx = multiprocessing.get_context("spawn")
    stop, started = ctx.Event(), ctx.Event()
    writer = ctx.Process(target=_rewrite_until, args=(str(tmp_path), stop, started))
    writer.start()
    try:
        assert started.wait(60)
        reads, deadline = 0, time.monotonic() + 1.5
        while time.monotonic() < deadline:
            curves = curves_array(store.read_curves("spk/u1", "procedural", "v1"))
            k = int(curves[0, 0])
            assert curves.shape == (20 + (k % 9) * 40, N_VISEMES) and (curves == k).all()
            labels = store.read_shard("phones", 0).column(C.LABEL).to_pylist()
            assert len({label.split("-")[0] for label in labels}) == 1
            reads += 1
    finally:
        stop.set()
        writer.join(30)
    assert writer.exitcode == 0 and reads > 20


# ---- unwritable store ----------------------------------------------------------------------------

def test_unwritable_store_names_the_path(tmp_path):
    (tmp_path / "afile").write_text("a regular file, not a folder")
    root = tmp_path / "afile" / "store"
    store = Store(root)
    calls = [
        lambda: store.write_curves(curves_of("spk/u1")[1]),
        lambda: store.write_shard("phones", 0, phone_rows("s/a", 1)),
        lambda: store.replace_utterance_rows("phones", 0, "s/a", phone_rows("s/a", 1)),
        lambda: store.write_run_config("ingest", {"fps": 30}),
    ]
    for call in calls:
        with pytest.raises(StoreError) as info:
            call()
        assert str(root) in str(info.value)
    # reads of a store that cannot exist are empty, not errors
    assert store.read_table("phones").num_rows == 0 and store.scan_curves().num_rows == 0


def test_run_config_round_trip(tmp_path):
    store = Store(tmp_path)
    assert store.read_run_config("ingest") is None
    store.write_run_config("ingest", {"fps": 30.0, "tiers": ["phones"]})
    assert store.read_run_config("ingest") == {"fps": 30.0, "tiers": ["phones"]}
    with pytest.raises(InvalidIdError):
        store.write_run_config("../etc", {})


def test_rerun_params_take_an_id_typed_in_decomposed_form_as_the_stored_one():
    import unicodedata

    from visemeflow.flows.params import RerunParams

    typed = unicodedata.normalize("NFD", "Sprecher_ü/Satz 1")
    assert typed != "Sprecher_ü/Satz 1"
    assert RerunParams(utterance_id=typed).utterance_id == "Sprecher_ü/Satz 1"
    with pytest.raises(ValueError, match="exactly one '/'"):
        RerunParams(utterance_id="a/b/c")


def test_reject_rows_are_capped_when_made_so_logs_quoting_them_stay_bounded():
    from visemeflow.tasks.common import reject_row

    huge = "entity " * 1_000_000
    row = reject_row("s/a", "ingest", "BadXra", huge, "s/a.xra")
    assert len(row[C.MESSAGE]) <= 4000 and row[C.MESSAGE].endswith("characters cut]")
    assert reject_row("s/a", "ingest", "BadXra", "short", None)[C.MESSAGE] == "short"
