"""Captured animation as `captured` curves: channel tables (FACEGOOD's xlsx and its CSV), the take readers (Live
Link Face CSV, channel CSV, NPY + names), their errors, and the `import_curves` flow on synthetic takes and on the
real FACEGOOD takes in `../shared/data/facegood_audio2face` (those tests fail, not skip, without the data)."""

import csv
import re
import shutil
import time

import numpy as np
import pytest

from factories import REPO, SHARED_DATA, make_corpus, write_wav
from visemeflow.shapes.capture import curve_shares, fit_visemes
from visemeflow.shapes.conventions import ARKIT_52, arkit_weights
from visemeflow.shapes.livelink import write_livelink_csv
from visemeflow.ingest.captured import (
    CaptureConfig,
    CaptureReadError,
    Take,
    detect_format,
    discover_takes,
    import_take,
    livelink_frame_rate,
    read_channel_csv,
    read_channel_npy,
    read_channel_table,
    read_expression_rows,
    read_livelink_take,
    read_take,
    write_expression_csv,
)
from visemeflow.schemas import C, UTTERANCES, curves_array, table_from_rows
from visemeflow.storage import Store
from visemeflow.visemes import N_VISEMES, VISEMES, viseme_index

# numpy warns that the FACEGOOD .npy files (written by Python 2) need extra header parsing
pytestmark = pytest.mark.filterwarnings("ignore:Reading `.npy` or `.npz` file required additional header parsing")

FACEGOOD = SHARED_DATA / "facegood_audio2face"
XLSX = FACEGOOD / "Voice2Face_blendshape2ARkit.xlsx"
SHIPPED_CSV = REPO / "examples" / "facegood" / "voice2face_arkit.csv"
TAKES = ("1114_2_02", "1114_2_03", "1114_2_04", "1114_2_05")


def need_facegood():
    assert FACEGOOD.is_dir(), f"{FACEGOOD} missing: the shared data must be present"


def speech_curves(n: int, seed: int = 0) -> np.ndarray:
    """(n, 16) curves that move between a few visemes like speech."""
    rng = np.random.default_rng(seed)
    curves = np.zeros((n, N_VISEMES), np.float32)
    t = np.arange(n)
    for k, viseme in enumerate(("AHH", "MBP", "OHH", "IEE", "FFF", "UUU")):
        centre = (k + 0.5) * n / 6
        curves[:, viseme_index(viseme)] = 0.8 * np.exp(-0.5 * ((t - centre) / (n / 18)) ** 2)
    return np.clip(curves + rng.uniform(0, 0.01, curves.shape).astype(np.float32), 0, 1)


def write_rows(path, header, rows):
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        writer.writerows(rows)
    return path


# ---- channel tables ----------------------------------------------------------------------------------------------
def test_facegood_xlsx_reads_as_an_expression_table():
    need_facegood()
    table = read_channel_table(XLSX)
    rules = {arkit: (op, terms) for arkit, op, terms in table.rules}
    assert rules["jawOpen"] == ("max", (("mouth_stretch_c", 1.0),))
    assert [c for c, _ in rules["mouthFunnel"][1]] == ["mouth_funnel_dl", "mouth_funnel_dr", "mouth_funnel_ul",
                                                       "mouth_funnel_ur"]
    assert rules["mouthSmileLeft"][1] == (("mouth_lipCornerPull_l", 1.0),)
    assert len(rules) == 27 and not any(name.startswith(("eye", "brow", "cheek", "nose")) for name in rules)
    assert {"eyeBlinkLeft", "browDownLeft", "tongueOut", "cheekPuff"} <= set(table.ignored)  # 'browDownleft' in the sheet
    names = [str(n) for n in np.load(FACEGOOD / "shirley_1015_bs_name.npy", encoding="latin1")]
    assert set(table.channels) <= set(names)


def test_the_shipped_facegood_csv_is_the_xlsx_converted(tmp_path):
    need_facegood()
    fresh = write_expression_csv(read_expression_rows(XLSX), tmp_path / "fresh.csv")

    def body(path):
        return [ln for ln in path.read_text(encoding="utf-8").splitlines() if not ln.startswith("#")]

    assert body(SHIPPED_CSV) == body(fresh)
    assert read_channel_table(SHIPPED_CSV).rules == read_channel_table(XLSX).rules
    assert (SHIPPED_CSV.parent / "LICENSE").read_bytes() == (FACEGOOD / "LICENSE").read_bytes()
    assert "MIT" in (SHIPPED_CSV.parent / "SOURCE.txt").read_text(encoding="utf-8")


def test_channel_tables_in_both_forms_and_errors_naming_file_and_line(tmp_path):
    weights = write_rows(tmp_path / "w.csv", ["channel", "arkit", "weight"],
                         [["jaw", "jawOpen", "1"], ["lips", "mouthFunnel", "0.5"], ["round", "mouthFunnel", "0.5"]])
    table = read_channel_table(weights)
    values = np.array([[0.4, 0.2, 0.6], [1.0, 0.0, 0.0]])
    out = table.apply(("jaw", "lips", "round"), values)
    assert out[0, ARKIT_52.index("jawOpen")] == pytest.approx(0.4)
    assert out[0, ARKIT_52.index("mouthFunnel")] == pytest.approx(0.4)  # 0.5 * 0.2 + 0.5 * 0.6
    expression = write_rows(tmp_path / "e.csv", ["arkit", "expression", "status"],
                            [["JawOpen", "jaw", ""], ["mouthPucker", "MAX( a , b )", "valid"],
                             ["eyeBlinkLeft", "blink", "Invalid"]])
    table = read_channel_table(expression)
    out = table.apply(("jaw", "a", "b", "blink"), np.array([[0.1, 0.3, 0.7, 1.0]]))
    assert out[0, ARKIT_52.index("jawOpen")] == pytest.approx(0.1)
    assert out[0, ARKIT_52.index("mouthPucker")] == pytest.approx(0.7)
    assert out[0, ARKIT_52.index("eyeBlinkLeft")] == 0 and table.ignored == ("eyeBlinkLeft",)
    cases = [
        (["arkit", "expression"], [["jawWide", "x"]], r"line 2: 'jawWide' is not an ARKit-52 blendshape name"),
        (["arkit", "expression"], [["jawOpen", "sum(a,b)"]], r"line 2: 'sum\(a,b\)' is not a channel name or max"),
        (["arkit", "expression"], [["jawOpen", "a"], ["jawopen", "b"]], r"line 3: jawOpen is driven twice"),
        (["arkit", "expression", "status"], [["jawOpen", "a", "maybe"]], r"line 2: status 'maybe'"),
        (["channel", "arkit", "weight"], [["a", "jawOpen", "lots"]], r"line 2: weight 'lots' is not a number"),
        (["name", "value"], [["a", "1"]], r"expected the header"),
    ]
    for k, (header, rows, message) in enumerate(cases):
        path = write_rows(tmp_path / f"bad{k}.csv", header, rows)
        with pytest.raises(CaptureReadError, match=rf"bad{k}\.csv: {message}"):
            read_channel_table(path)


def test_xlsx_errors_name_the_file(tmp_path):
    fake = tmp_path / "table.xlsx"
    fake.write_bytes(b"not a zip")
    with pytest.raises(CaptureReadError, match=r"table\.xlsx: cannot open as an \.xlsx"):
        read_channel_table(fake)


# ---- take readers ------------------------------------------------------------------------------------------------
def test_channel_csv_and_npy_readers_map_channels_and_report_unmapped_ones(tmp_path):
    table = read_channel_table(write_rows(tmp_path / "t.csv", ["channel", "arkit", "weight"],
                                          [["jaw", "jawOpen", "1"], ["pucker", "mouthPucker", "1"]]))
    t = np.arange(30) / 30.0
    rows = [[f"{s:.6f}", f"{0.5 * s:.4f}", "0.2", f"{s:.3f}", "0"] for s in t]
    path = write_rows(tmp_path / "take.csv", ["time_s", "jaw", "pucker", "brow", "flat"], rows)
    take = read_channel_csv(path, table)
    assert take.fps == pytest.approx(30.0) and take.n_frames == 30 and take.format == "csv"
    assert take.arkit[10, ARKIT_52.index("jawOpen")] == pytest.approx(0.5 * t[10], abs=1e-4)
    assert take.unmapped == ("brow",)  # varies but drives nothing; 'flat' does not vary
    assert detect_format(path) == "csv"
    values = np.random.default_rng(0).uniform(0, 1, (40, 3))
    np.save(tmp_path / "v.npy", values)
    (tmp_path / "names.txt").write_text("jaw\npucker\nextra\n", encoding="utf-8")
    take = read_channel_npy(tmp_path / "v.npy", tmp_path / "names.txt", table, fps=25)
    assert take.fps == 25 and take.n_frames == 40 and take.unmapped == ("extra",)
    np.testing.assert_allclose(take.arkit[:, ARKIT_52.index("mouthPucker")], values[:, 1], atol=1e-6)
    np.save(tmp_path / "names.npy", np.array(["jaw", "pucker", "extra"]))
    assert read_take(tmp_path / "v.npy", names=tmp_path / "names.npy", table=table, fps=25).n_frames == 40
    # without a table, channels must be ARKit names (any case)
    path = write_rows(tmp_path / "arkit.csv", ["frame", "JawOpen", "mouthFunnel"], [[0, 0.1, 0.2], [1, 0.3, 0.4]])
    take = read_channel_csv(path, None, fps=60)
    assert take.arkit[1, ARKIT_52.index("jawOpen")] == pytest.approx(0.3)


def test_capture_errors_name_the_file_and_what_is_wrong(tmp_path):
    table = read_channel_table(write_rows(tmp_path / "t.csv", ["channel", "arkit", "weight"],
                                          [["jaw", "jawOpen", "1"], ["lips", "mouthFunnel", "1"]]))
    nan = write_rows(tmp_path / "nan.csv", ["jaw", "lips"], [["0.1", "0.2"], ["nan", "0.1"]])
    with pytest.raises(CaptureReadError, match=r"nan\.csv: channel 'jaw' is nan at frame 1") as info:
        read_channel_csv(nan, table, fps=30)
    assert info.value.error_type == "NonFiniteCapture"
    missing = write_rows(tmp_path / "missing.csv", ["jaw", "teeth"], [["0.1", "0.2"]])
    with pytest.raises(CaptureReadError, match=r"missing\.csv: the channel table .* names channel\(s\) 'lips' that "
                                               r"this file lacks") as info:
        read_channel_csv(missing, table, fps=30)
    assert info.value.error_type == "UnknownChannel"
    with pytest.raises(CaptureReadError, match=r"missing\.csv: channel\(s\) 'jaw', 'teeth' are not ARKit-52 names"):
        read_channel_csv(missing, None, fps=30)
    with pytest.raises(CaptureReadError, match=r"missing\.csv: no time column"):
        read_channel_csv(missing, table)
    twice = write_rows(tmp_path / "twice.csv", ["jaw", "jaw"], [["0.1", "0.2"]])
    with pytest.raises(CaptureReadError, match=r"twice\.csv: channel 'jaw' appears twice"):
        read_channel_csv(twice, table, fps=30)
    cased = write_rows(tmp_path / "cased.csv", ["JawOpen", "jawOpen"], [["0.1", "0.2"]])
    with pytest.raises(CaptureReadError, match=r"cased\.csv: channels 'JawOpen' and 'jawOpen' both read as jawOpen"):
        read_channel_csv(cased, None, fps=30)
    text = write_rows(tmp_path / "text.csv", ["jaw", "lips"], [["0.1", "open"]])
    with pytest.raises(CaptureReadError, match=r"text\.csv: line 2: column 'lips' holds 'open'"):
        read_channel_csv(text, table, fps=30)
    np.save(tmp_path / "v.npy", np.zeros((5, 3)))
    (tmp_path / "names.txt").write_text("jaw\nlips\n", encoding="utf-8")
    with pytest.raises(CaptureReadError, match=r"v\.npy: 3 channels but the names file .*names\.txt lists 2"):
        read_channel_npy(tmp_path / "v.npy", tmp_path / "names.txt", table, fps=30)
    np.save(tmp_path / "cube.npy", np.zeros((5, 2, 2)))
    with pytest.raises(CaptureReadError, match=r"cube\.npy: expected a \(frames, channels\) array"):
        read_channel_npy(tmp_path / "cube.npy", tmp_path / "names.txt", table, fps=30)
    np.save(tmp_path / "objects.npy", np.array([{"jaw": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(CaptureReadError, match=r"objects\.npy: holds Python objects"):
        read_channel_npy(tmp_path / "objects.npy", tmp_path / "names.txt", table, fps=30)
    with pytest.raises(CaptureReadError, match=r"v\.npy: an \.npy capture has no clock"):
        read_channel_npy(tmp_path / "v.npy", tmp_path / "names.txt", table)


def test_live_link_frame_rate_comes_from_the_timecodes(tmp_path):
    curves = speech_curves(90)
    weights = arkit_weights(curves)
    for fps in (30, 60, 25, 24):
        path = write_livelink_csv(tmp_path / f"take{fps}.csv", weights, fps, start_seconds=3600 * 12 + 47.5)
        take = read_livelink_take(path)
        assert take.fps == pytest.approx(fps), fps
        assert take.n_frames == 90 and take.filled_frames == 0
        np.testing.assert_allclose(take.arkit, weights, atol=1e-6)
        assert detect_format(path) == "livelink"
    # every second row of a 60 fps timecode: a 30 fps capture on a 60 fps clock
    timecodes = [f"10:00:{s:02d}:{f:02d}.000" for s in range(2) for f in range(0, 60, 2)]
    rate, fps, times = livelink_frame_rate(timecodes)
    assert (rate, fps) == (60.0, 30.0) and times[-1] == pytest.approx(59 / 30)
    # dropped frames are filled on the regular grid
    path = write_livelink_csv(tmp_path / "full.csv", weights, 30)
    lines = path.read_text().splitlines()
    dropped = tmp_path / "dropped.csv"
    dropped.write_text("\n".join(lines[:20] + lines[23:]) + "\n")
    take = read_livelink_take(dropped)
    assert take.n_frames == 90 and take.filled_frames == 3 and take.fps == 30
    assert np.abs(take.arkit[19:23] - weights[19:23]).max() < 0.05
    assert read_livelink_take(dropped, fps=30).n_frames == 87  # a given rate is taken as it is
    backwards = tmp_path / "backwards.csv"
    backwards.write_text("\n".join(lines[:5] + [lines[3]] + lines[6:]) + "\n")
    with pytest.raises(CaptureReadError, match=r"backwards\.csv: line 6: timecode .* does not come after"):
        read_livelink_take(backwards)


# ---- import: one take, then the flow -------------------------------------------------------------------------------
def synthetic_takes(root, *, seconds=2.0, fps=30):
    """A folder of takes (Live Link) and a manifest of CSV / NPY takes, some bad; returns (manifest, known curves)."""
    n = int(round(seconds * fps))
    curves = speech_curves(n)
    weights = arkit_weights(curves)
    write_wav(root / "spk" / "good.wav", seconds)
    write_livelink_csv(root / "spk" / "good.livelink.csv", weights, fps)
    write_wav(root / "spk" / "short.wav", seconds)
    write_livelink_csv(root / "spk" / "short.livelink.csv", weights[: n // 2], fps)  # half the audio
    write_wav(root / "csv" / "a.wav", seconds)
    write_rows(root / "csv" / "a.csv", ["time_s"] + list(ARKIT_52),
               [[f"{k / fps:.6f}"] + [f"{v:.6f}" for v in row] for k, row in enumerate(weights)])
    values = weights[:, [ARKIT_52.index("jawOpen"), ARKIT_52.index("mouthPucker")]]
    np.save(root / "csv" / "b.npy", values.astype(np.float64))
    (root / "csv" / "b.names.txt").write_text("jaw\npucker\n", encoding="utf-8")
    write_rows(root / "csv" / "b.table.csv", ["channel", "arkit", "weight"],
               [["jaw", "jawOpen", "1"], ["pucker", "mouthPucker", "1"]])
    bad = weights.astype(np.float64).copy()
    bad[7, ARKIT_52.index("jawOpen")] = np.nan
    np.save(root / "csv" / "nan.npy", bad)
    (root / "csv" / "arkit.txt").write_text("\n".join(ARKIT_52) + "\n", encoding="utf-8")
    write_rows(root / "csv" / "odd.csv", ["time_s", "jaw_drop"], [[f"{k / fps:.6f}", "0.1"] for k in range(n)])
    manifest = write_rows(root / "takes.csv", ["utterance_id", "audio", "capture", "format", "channels", "names", "fps",
                                               "language", "split"], [
        ["csv/a", "csv/a.wav", "csv/a.csv", "", "", "", "", "en", "train"],
        ["csv/b", "csv/a.wav", "csv/b.npy", "npy", "csv/b.table.csv", "csv/b.names.txt", str(fps), "", "val"],
        ["csv/nan", "csv/a.wav", "csv/nan.npy", "npy", "", "csv/arkit.txt", str(fps), "", ""],
        ["csv/odd", "csv/a.wav", "csv/odd.csv", "csv", "", "", "", "", ""],
        ["csv/outside", "../elsewhere.wav", "csv/a.csv", "", "", "", "", "", ""],
    ])
    return manifest, curves


def test_import_take_checks_the_length_against_the_audio(tmp_path):
    manifest, curves = synthetic_takes(tmp_path)
    found = discover_takes(tmp_path)  # the folder holds takes.csv: read through it
    assert [t.utterance_id for t in found.takes] == ["csv/a", "csv/b", "csv/nan", "csv/odd"]
    assert [r.error_type for r in found.rejects] == ["PathOutsideCorpus"]
    folder = discover_takes(tmp_path / "spk")
    assert folder.takes == () and folder.rejects == ()
    (tmp_path / "takes.csv").rename(tmp_path / "manifest-elsewhere.csv")
    found = discover_takes(tmp_path)
    assert sorted(t.utterance_id for t in found.takes) == ["spk/good", "spk/short"]
    good = next(t for t in found.takes if t.utterance_id == "spk/good")
    imported = import_take(good, CaptureConfig())
    assert imported.fps == 30 and imported.curves.shape == (60, N_VISEMES) and imported.drift_frames == 0
    row = imported.utterance
    assert row[C.ALIGNMENT_FORMAT] == "none" and row[C.ALIGNMENT_PATH] == "" and row[C.N_FRAMES] == 60
    assert np.abs(imported.curves - curves).mean() < 0.03
    short = next(t for t in found.takes if t.utterance_id == "spk/short")
    with pytest.raises(CaptureReadError, match=r"short\.livelink\.csv: 30 frames at 30 fps .* the audio .*short\.wav "
                                               r"lasts 2\.000 s .* 30\.0 frames apart, more than the 2\.0 allowed"):
        import_take(short, CaptureConfig())
    assert import_take(short, CaptureConfig(max_drift_frames_per_s=20)).curves.shape == (30, N_VISEMES)
    missing = Take("spk/x", str(tmp_path / "spk" / "good.wav"), str(tmp_path / "spk" / "none.csv"), "csv")
    with pytest.raises(CaptureReadError, match=r"none\.csv: captured file not found"):
        import_take(missing, CaptureConfig())


@pytest.mark.usefixtures("prefect_harness")
def test_import_flow_stores_captured_curves_rejects_bad_takes_and_caches(tmp_path):
    from visemeflow.flows.import_curves import ImportCurvesParams, import_curves_flow

    manifest, curves = synthetic_takes(tmp_path / "takes")
    store_root = tmp_path / "store"
    params = ImportCurvesParams(takes=manifest, store=store_root, n_shards=2)
    state = import_curves_flow(params, return_state=True)
    summary = state.result()
    assert state.is_completed() and "3 of 5 utterances failed" in state.message
    store = Store(store_root)
    rejects = {r[C.UTTERANCE_ID]: r for r in store.read_table("rejects", "import_curves").to_pylist()}
    assert set(rejects) == {"csv/nan", "csv/odd", "csv/outside"}
    assert rejects["csv/nan"][C.ERROR_TYPE] == "NonFiniteCapture" and "nan.npy" in rejects["csv/nan"][C.MESSAGE]
    assert "csv/nan: " in rejects["csv/nan"][C.MESSAGE] and "frame 7" in rejects["csv/nan"][C.MESSAGE]
    assert rejects["csv/odd"][C.ERROR_TYPE] == "UnknownChannel" and "'jaw_drop'" in rejects["csv/odd"][C.MESSAGE]
    assert rejects["csv/outside"][C.ERROR_TYPE] == "PathOutsideCorpus"
    assert store.curve_ids("captured", "arkit-nnls") == ["csv/a", "csv/b"]
    a = store.read_curves("csv/a", "captured", "arkit-nnls")
    assert np.abs(curves_array(a) - curves).mean() < 0.03
    assert a.column(C.TIME_S)[1].as_py() == pytest.approx(1 / 30)
    assert store.curves_provenance("captured", "arkit-nnls", "csv/a").startswith("captured:auto:")
    rows = {r[C.UTTERANCE_ID]: r for r in store.read_table("utterances").to_pylist()}
    assert set(rows) == {"csv/a", "csv/b"}
    assert rows["csv/a"][C.ALIGNMENT_FORMAT] == "none" and rows["csv/a"][C.LANGUAGE] == "en"
    assert rows["csv/b"][C.SPLIT] == "val" and rows["csv/b"][C.N_FRAMES] == 60 and rows["csv/b"][C.FPS] == 30
    assert summary["imported"] == 2 and summary["frames"] == 120
    # again: every take (and every reject) is a cache hit
    state = import_curves_flow(params, return_state=True)
    again = state.result()
    assert again["cached"] == 2 and again["imported"] == 0 and again["rejected"] == 3
    assert all(r["cached"] for r in again["takes_report"])
    # deleted curves are made again; a take whose file went bad loses its curves and row
    store.delete_path(store.curve_path("captured", "arkit-nnls", "csv/a"))
    values = np.load(tmp_path / "takes" / "csv" / "b.npy")
    values[3, 0] = np.inf
    np.save(tmp_path / "takes" / "csv" / "b.npy", values)
    third = import_curves_flow(params, return_state=True).result()
    assert third["imported"] == 1 and store.has_curves("captured", "arkit-nnls", "csv/a")
    assert not store.has_curves("captured", "arkit-nnls", "csv/b")
    assert "csv/b" not in store.read_table("utterances").column(C.UTTERANCE_ID).to_pylist()
    assert "csv/b" in store.read_table("rejects", "import_curves").column(C.UTTERANCE_ID).to_pylist()


@pytest.mark.usefixtures("prefect_harness")
def test_when_every_take_is_rejected_the_run_says_why(tmp_path, monkeypatch):
    """Every take rejected: the command printed only its counts and "see the rejects table" (a new user's report);
    ingest said why in the same case. The run now logs each reject's reason and hints before it ends Failed."""
    import visemeflow.flows.import_curves as module
    from visemeflow.flows.import_curves import ImportCurvesParams, import_curves_flow

    manifest, _ = synthetic_takes(tmp_path / "takes")
    rows = manifest.read_text().splitlines()
    manifest.write_text("\n".join([rows[0]] + [r for r in rows if r.startswith("csv/odd,")]) + "\n")
    said = []

    class Logger:
        def __getattr__(self, level):
            return lambda message, *args: said.append((level, message % args if args else message))

    real = module.StageRun

    class Run(real):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.logger = Logger()

    monkeypatch.setattr(module, "StageRun", Run)
    state = import_curves_flow(ImportCurvesParams(takes=manifest, store=tmp_path / "store"), return_state=True)
    assert state.is_failed() and state.message == "import_curves: its one utterance failed (see the rejects table)"
    (warning,) = [m for level, m in said if level == "warning"]
    assert warning.startswith("import_curves: 1 rejected:\n") and "UnknownChannel" in warning
    assert "csv/odd" in warning and "'jaw_drop'" in warning


@pytest.mark.usefixtures("prefect_harness")
def test_a_take_of_an_ingested_utterance_adds_curves_and_keeps_its_row(tmp_path):
    from visemeflow.flows.import_curves import ImportCurvesParams, import_curves_flow
    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.params import IngestParams

    corpus = make_corpus(tmp_path / "corpus", {"spk/u1": [("sil", 0.0, 0.2), ("AA1", 0.2, 1.0), ("sil", 1.0, 2.0)]})
    store_root = tmp_path / "store"
    ingest_flow(IngestParams(corpus=corpus, store=store_root, n_shards=2))
    takes = tmp_path / "takes"
    (takes / "spk").mkdir(parents=True)
    shutil.copy(corpus / "spk" / "u1.wav", takes / "spk" / "u1.wav")
    write_livelink_csv(takes / "spk" / "u1.livelink.csv", arkit_weights(speech_curves(60)), 30)
    import_curves_flow(ImportCurvesParams(takes=takes, store=store_root, n_shards=2))
    store = Store(store_root)
    rows = store.read_table("utterances").to_pylist()
    assert len(rows) == 1 and rows[0][C.ALIGNMENT_FORMAT] == "textgrid"  # the corpus row stays as it is
    assert store.has_curves("captured", "arkit-nnls", "spk/u1")
    write_wav(takes / "spk" / "u1.wav", 2.0, rate=8000)  # other audio under the same id
    import_curves_flow(ImportCurvesParams(takes=takes, store=store_root, n_shards=2), return_state=True)
    rejects = store.read_table("rejects", "import_curves").to_pylist()
    assert [r[C.ERROR_TYPE] for r in rejects] == ["IdInUse"] and "spk/u1" in rejects[0][C.MESSAGE]
    assert not store.has_curves("captured", "arkit-nnls", "spk/u1")
    assert store.read_table("utterances").num_rows == 1


@pytest.mark.usefixtures("prefect_harness")
def test_ingest_keeps_imported_takes_and_procedural_skips_them(tmp_path):
    from visemeflow.flows.import_curves import ImportCurvesParams, import_curves_flow
    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.params import IngestParams, ProceduralParams
    from visemeflow.flows.procedural import procedural_flow

    manifest, _ = synthetic_takes(tmp_path / "takes")
    store_root = tmp_path / "store"
    import_curves_flow(ImportCurvesParams(takes=manifest, store=store_root, n_shards=4), return_state=True)
    corpus = make_corpus(tmp_path / "corpus", {"spk/u1": [("sil", 0.0, 0.2), ("AA1", 0.2, 1.0)],
                                               "spk/u2": [("M", 0.0, 0.3), ("IY1", 0.3, 0.8)]})
    ingest_flow(IngestParams(corpus=corpus, store=store_root, n_shards=4))
    store = Store(store_root)
    ids = sorted(store.read_table("utterances").column(C.UTTERANCE_ID).to_pylist())
    assert ids == ["csv/a", "csv/b", "spk/u1", "spk/u2"]  # the takes survive an ingest of another corpus
    result = procedural_flow(ProceduralParams(store=store_root, n_shards=4))
    assert result["utterances"] == 2
    assert sorted(store.curve_ids("procedural", result["variant"])) == ["spk/u1", "spk/u2"]
    assert store.curve_ids("captured", "arkit-nnls") == ["csv/a", "csv/b"]


def test_a_take_imported_while_an_ingest_runs_is_kept(tmp_path, monkeypatch):
    """An import that lands in a shard while an ingest of that shard runs (after the ingest read the shard, before
    it wrote it) is kept: the ingest writes its shard under the shard's lock and keeps the captured rows stored
    then, not those it saw at its start (it used to drop the take's row, and the take vanished from the store)."""
    from visemeflow.flows.import_curves import ImportCurvesParams, import_curves_flow
    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.params import IngestParams

    manifest, _ = synthetic_takes(tmp_path / "takes")
    takes = Store(tmp_path / "takes_store")        # the import as it would land, made beside
    import_curves_flow(ImportCurvesParams(takes=manifest, store=takes.root, n_shards=1), return_state=True)
    (take_row,) = [r for r in takes.read_table("utterances").to_pylist() if r[C.UTTERANCE_ID] == "csv/a"]
    corpus = make_corpus(tmp_path / "corpus", {"spk/u1": [("sil", 0.0, 0.2), ("AA1", 0.2, 1.0)]})
    store = Store(tmp_path / "store")
    write_shard, landed = Store.write_shard, []

    def import_lands(self, table_name, shard, table, *args, **kwargs):
        if table_name == "phones" and not landed:   # the ingest has read the shard and made its rows
            landed.append(shard)
            target = store.curve_path("captured", "arkit-nnls", "csv/a")
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(takes.curve_path("captured", "arkit-nnls", "csv/a"), target)
            store.replace_utterance_rows("utterances", shard, "csv/a", table_from_rows([take_row], UTTERANCES))
        return write_shard(self, table_name, shard, table, *args, **kwargs)

    monkeypatch.setattr(Store, "write_shard", import_lands)
    ingest_flow(IngestParams(corpus=corpus, store=store.root, n_shards=1))
    assert landed == [0]
    assert sorted(store.read_table("utterances").column(C.UTTERANCE_ID).to_pylist()) == ["csv/a", "spk/u1"]
    assert store.curve_ids("captured", "arkit-nnls") == ["csv/a"]


# ---- the real FACEGOOD takes -------------------------------------------------------------------------------------
def facegood_manifest(root):
    """The four FACEGOOD takes copied under `root` with a manifest (paths may not leave the manifest's folder)."""
    need_facegood()
    data = root / "facegood"
    shutil.copytree(FACEGOOD, data)
    rows = [[f"facegood/{name}", f"facegood/{name}.wav", f"facegood/bs_value_{name}.npy", "npy", "", "", "30", "zh",
             ""] for name in TAKES]
    return write_rows(root / "takes.csv", ["utterance_id", "audio", "capture", "format", "channels", "names", "fps",
                                           "language", "split"], rows)


@pytest.mark.usefixtures("prefect_harness")
def test_the_facegood_takes_import_as_curves_of_real_speech(tmp_path):
    from visemeflow.flows.import_curves import ImportCurvesParams, import_curves_flow

    manifest = facegood_manifest(tmp_path)
    params = ImportCurvesParams(takes=manifest, store=tmp_path / "store", channel_table=SHIPPED_CSV,
                                names=tmp_path / "facegood" / "shirley_1015_bs_name.npy")
    state = import_curves_flow(params, return_state=True)
    summary = state.result()
    assert state.is_completed() and summary["rejected"] == 0 and summary["imported"] == 4, state.message
    store = Store(params.store)
    utterances = {r[C.UTTERANCE_ID]: r for r in store.read_table("utterances").to_pylist()}
    all_curves, all_residuals, seconds = [], [], 0.0
    for name in TAKES:
        uid = f"facegood/{name}"
        row = utterances[uid]
        values = np.load(FACEGOOD / f"bs_value_{name}.npy", encoding="latin1")
        assert row[C.N_FRAMES] == len(values) and row[C.FPS] == 30 and row[C.LANGUAGE] == "zh"
        assert abs(row[C.N_FRAMES] - row[C.DURATION_S] * 30) < 1.0  # 30 fps, frame i at i / 30 s of the audio
        curves = curves_array(store.read_curves(uid, "captured", "arkit-nnls"))
        assert curves.shape == (len(values), N_VISEMES)
        assert np.isfinite(curves).all() and curves.min() >= 0 and curves.max() <= 1
        take = Take(uid, row[C.AUDIO_PATH], str(tmp_path / "facegood" / f"bs_value_{name}.npy"), "npy",
                    str(SHIPPED_CSV), str(tmp_path / "facegood" / "shirley_1015_bs_name.npy"), 30.0)
        capture = read_take(take.capture_path, "npy", table=read_channel_table(SHIPPED_CSV), names=take.names_path,
                            fps=30)
        assert "mouth_oh_c" in capture.unmapped  # FACEGOOD's table leaves its most varying channel out
        started = time.perf_counter()
        fit = fit_visemes(capture.arkit)
        seconds += time.perf_counter() - started
        np.testing.assert_array_equal(fit.curves, curves)
        all_curves.append(curves)
        all_residuals.append(fit.residual[fit.moving])
    curves, residual = np.concatenate(all_curves), np.concatenate(all_residuals)
    shares = curve_shares(curves)
    top = sorted(shares["top_share"].items(), key=lambda kv: -kv[1])
    print(f"\nFACEGOOD, 4 takes, {len(curves)} frames ({len(residual)} moving): conversion {len(curves) / seconds:,.0f} "
          f"frames/s; relative residual on moving frames mean {residual.mean():.4f}, median {np.median(residual):.4f}, "
          f"p90 {np.percentile(residual, 90):.4f}; frames with a viseme > 0.1: {100 * shares['active_share']:.1f}%; "
          f"AHH or AAA > 0.3: {100 * shares['jaw_open_share']:.1f}% of frames; top viseme of active frames: "
          + ", ".join(f"{v} {100 * s:.1f}%" for v, s in top if s >= 0.005)
          + f"; MBP top {100 * shares['top_share']['MBP']:.1f}%; mean curve "
          + ", ".join(f"{v} {m:.3f}" for v, m in shares["mean"].items() if m >= 0.005))
    # real speech moves the mouth: open-jaw visemes lead, several others take part
    assert 0.2 < shares["active_share"] < 0.9
    assert top[0][0] in ("AHH", "AAA", "SCHWA") and sum(s > 0.02 for _, s in top) >= 4
    assert 0.02 < shares["jaw_open_share"] < 0.5
    assert np.median(residual) < 0.05 and residual.mean() < 0.2
    assert set(VISEMES) == set(shares["top_share"])


@pytest.mark.usefixtures("prefect_harness")
def test_one_capture_file_is_a_take_of_one_and_a_file_that_is_no_manifest_is_one_line(tmp_path, monkeypatch):
    """`import-curves take.livelink.csv` (what its help names) read the file as a manifest: two tracebacks."""
    from typer.testing import CliRunner

    from visemeflow.cli import app

    synthetic_takes(tmp_path / "takes")
    one = discover_takes(tmp_path / "takes" / "spk" / "good.livelink.csv")
    assert [t.utterance_id for t in one.takes] == ["spk/good"] and not one.rejects
    assert one.takes[0].audio_path == str((tmp_path / "takes" / "spk" / "good.wav").resolve())
    assert one.takes[0].format == "livelink" and one.takes[0].content_hash
    monkeypatch.chdir(tmp_path / "takes" / "spk")      # the file named in its own folder: its folder is the speaker
    assert [t.utterance_id for t in discover_takes("good.livelink.csv").takes] == ["spk/good"]
    alone = tmp_path / "alone" / "x.livelink.csv"
    alone.parent.mkdir()
    shutil.copy(tmp_path / "takes" / "spk" / "good.livelink.csv", alone)
    found = discover_takes(alone)
    assert not found.takes and [r.error_type for r in found.rejects] == ["MissingAudio"]
    runner = CliRunner()
    done = runner.invoke(app, ["import-curves", str(tmp_path / "takes" / "spk" / "good.livelink.csv"),
                               "--store", str(tmp_path / "store")])
    assert done.exit_code == 0, done.output
    assert "takes 1, imported 1" in done.output and "residual_mean " in done.output
    assert not re.search(r"\d\.\d{6}", done.output), done.output      # figures rounded, not 0.00012544308265205473
    assert Store(tmp_path / "store").has_curves("captured", "arkit-nnls", "spk/good")
    bad = write_rows(tmp_path / "bad.csv", ["a", "b"], [["1", "2"]])
    done = runner.invoke(app, ["import-curves", str(bad), "--store", str(tmp_path / "store")])
    assert done.exit_code == 2 and done.output.count("\n") == 1, done.output
    assert done.output.startswith(f"error: manifest {bad}: missing column(s) ['audio', 'capture', 'utterance_id']")
    assert "or give one take, `<speaker>/<name>.livelink.csv" in done.output
