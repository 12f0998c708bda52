"""The `visemeflow` command's read-only subcommands on a store written directly."""

import csv
import io
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from visemeflow.cli import app
from visemeflow.schemas import REJECTS, C, curves_table, table_from_rows
from visemeflow.storage import Store
from visemeflow.tasks.common import reject_row
from visemeflow.visemes import VISEMES, viseme_index

runner = CliRunner()
UID = "spk/utt-1"


@pytest.fixture
def store(tmp_path):
    curves = np.zeros((31, 16), dtype=np.float32)
    curves[5:15, viseme_index("MBP")] = 1.0
    curves[10:25, viseme_index("AHH")] = 0.5
    s = Store(tmp_path / "store")
    s.write_curves(curves_table(UID, "procedural", "jali", curves, 30.0), fps=30.0)
    return s


def test_curves_show_summarises_each_viseme(store):
    result = runner.invoke(app, ["curves", "show", UID, "--store", str(store.root)])
    assert result.exit_code == 0, result.output
    assert "31 frames" in result.output and "variant jali" in result.output
    rows = {line.split()[0]: line.split()[1:] for line in result.output.splitlines()[2:] if line.split()}
    assert rows["MBP"][0] == "1.00" and rows["AHH"][0] == "0.50" and rows["UUU"][0] == "0.00"
    assert int(rows["MBP"][2]) == 10  # frames 5..14, MBP tops AHH everywhere it is on


def test_curves_export_csv_and_json(store, tmp_path):
    result = runner.invoke(app, ["curves", "export", UID, "--store", str(store.root), "--format", "csv"])
    assert result.exit_code == 0, result.output
    rows = list(csv.DictReader(io.StringIO(result.output)))
    assert len(rows) == 31 and list(rows[0]) == [C.FRAME, C.TIME_S, *VISEMES]
    assert float(rows[6]["MBP"]) == 1.0 and float(rows[30][C.TIME_S]) == pytest.approx(1.0)

    out = tmp_path / "c.json"
    result = runner.invoke(app, ["curves", "export", UID, "--store", str(store.root), "--format", "json", "--out", str(out)])
    assert result.exit_code == 0, result.output
    data = json.loads(out.read_text())
    assert data["visemes"] == list(VISEMES) and data["fps"] == pytest.approx(30.0)
    assert data["curves"]["AHH"][10] == 0.5 and len(data["time_s"]) == 31


def test_unknown_utterance_and_format_are_clear_errors(store):
    result = runner.invoke(app, ["curves", "show", "spk/nope", "--store", str(store.root)])
    assert result.exit_code == 2 and "spk/nope" in result.output
    result = runner.invoke(app, ["curves", "export", UID, "--store", str(store.root), "--format", "xml"])
    assert result.exit_code == 2 and "unknown format" in result.output


def test_rejects_lists_reasons(store):
    assert "no rejects" in runner.invoke(app, ["rejects", "--store", str(store.root)]).output
    row = reject_row("spk/bad", "ingest", "UnknownPhoneme", "spk/bad: x.TextGrid: unknown arpabet phoneme 'QQ'", "x.TextGrid")
    store.write_shard("rejects", 0, table_from_rows([row], REJECTS), stage="ingest")
    result = runner.invoke(app, ["rejects", "--store", str(store.root)])
    assert result.exit_code == 0 and "[ingest] UnknownPhoneme: spk/bad" in result.output
    # an unexpected error's reason carries its traceback: one line unless asked for whole
    trace = "Traceback (most recent call last):\n  File \"x.py\", line 1, in f\nZeroDivisionError: division by zero"
    bug = reject_row("spk/bug", "track", "ZeroDivisionError", f"spk/bug: division by zero\n{trace}", None)
    store.write_shard("rejects", 0, table_from_rows([bug], REJECTS), stage="track")
    short = runner.invoke(app, ["rejects", "--store", str(store.root), "--stage", "track"]).output.splitlines()
    assert short == ["[track] ZeroDivisionError: spk/bug: division by zero",
                     "1 reason goes on over more lines (a traceback): --full shows them"]
    whole = runner.invoke(app, ["rejects", "--store", str(store.root), "--stage", "track", "--full"]).output
    assert whole == f"[track] ZeroDivisionError: spk/bug: division by zero\n{trace}\n"


# ---- the curve exporters (visemeflow/animation/export.py), used by `curves export` and `predict --out` ----------

def _track(curves, fps=30.0, uid="spk/x"):
    from visemeflow.animation import CurveTrack

    table = curves_table(uid, "predicted", "m", curves, fps)
    return CurveTrack(uid, "predicted", "m", curves, table.column(C.TIME_S).to_numpy(), table.column(C.FRAME).to_numpy())


def test_csv_export_reads_back_the_exact_float32_weights_in_arrows_layout():
    import pyarrow.csv as pacsv

    from visemeflow.animation import curves_csv

    rng = np.random.default_rng(1)
    curves = (rng.random((40, 16)) ** 9).astype(np.float32)
    curves[0] = [0.0, 1.0, 0.5, 1e-6, 9.9e-7, 1e-7, 3e-9, 1e-30, 1e-45, 0.999999, 0.1, 0.2, 0.3, 1 / 3, 2 / 3, 0.0]
    text = curves_csv(_track(curves, fps=25.0))
    back = pacsv.read_csv(io.BytesIO(text.encode()))
    assert back.column_names == [C.FRAME, C.TIME_S, *VISEMES]
    assert np.array_equal(np.stack([back.column(v).to_numpy().astype(np.float32) for v in VISEMES], 1), curves)
    # the same text Arrow's CSV writer gave before the exporter moved out of the CLI
    table = curves_table("spk/x", "predicted", "m", curves, 25.0)
    buf = io.BytesIO()
    pacsv.write_csv(table.select([C.FRAME, C.TIME_S, *VISEMES]), buf)
    assert text == buf.getvalue().decode()


def test_json_export_and_errors(tmp_path):
    from visemeflow.animation import CurveTrack, curves_json, export_text, write_export

    curves = np.zeros((3, 16), dtype=np.float32)
    curves[1, viseme_index("MBP")] = 0.1234567
    data = json.loads(curves_json(_track(curves)))
    assert data["fps"] == pytest.approx(30.0) and data["curves"]["MBP"] == [0.0, 0.123457, 0.0]
    assert data["utterance_id"] == "spk/x" and data["source"] == "predicted" and data["variant"] == "m"
    assert json.loads(curves_json(_track(curves[:1])))["fps"] is None
    with pytest.raises(ValueError, match="unknown format 'xml'"):
        export_text(_track(curves), "xml")
    with pytest.raises(ValueError, match="spk/y: curves must be"):
        CurveTrack("spk/y", "p", "v", np.zeros((3, 15), np.float32), np.zeros(3), np.arange(3))
    with pytest.raises(ValueError, match="3 frames of curves but 2 times"):
        CurveTrack("spk/y", "p", "v", curves, np.zeros(2), np.arange(3))
    bad = curves.copy()
    bad[2, 0] = np.nan
    with pytest.raises(ValueError, match="AAA has NaN"):
        curves_json(_track(bad))
    path = write_export(_track(curves), tmp_path / "deep" / "x.json")  # format from the suffix, folders made
    assert json.loads(path.read_text())["visemes"] == list(VISEMES)
    assert not [p for p in (tmp_path / "deep").iterdir() if p.name.startswith(".")]  # no temporary file left


def test_a_failed_stage_prints_its_summary_and_exits_1(monkeypatch, capsys):
    import visemeflow.cli as cli
    from visemeflow.flows.errors import StageFailed

    def failing_pipeline():
        raise StageFailed("pipeline: track: all 2 utterances failed (see the rejects table)",
                          {"ingest": {"utterances": 2}, "track": {"utterances": 2, "rejected": 2}})

    monkeypatch.setattr(cli, "app", failing_pipeline)
    with pytest.raises(SystemExit) as exited:
        cli.main()
    assert exited.value.code == 1
    out, err = capsys.readouterr()
    assert out.splitlines() == ["ingest: utterances 2", "track: utterances 2, rejected 2"]
    assert err.strip() == "failed: pipeline: track: all 2 utterances failed (see the rejects table)"


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_animate_and_preview_commands_print_every_file_and_refuse_bad_options(tmp_path):
    from factories import make_curve_store

    store = make_curve_store(tmp_path / "store", n=1)
    result = runner.invoke(app, ["animate", "--store", str(store.root), "--source", "ground_truth",
                                 "--format", "livelink,curves-csv", "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    assert "spk/u0 -> ict_visemes [visemeflow16], 25 frames at 25 fps:" in result.output
    printed = [line.strip() for line in result.output.splitlines() if line.startswith("  ")]
    assert sorted(p.rsplit("/", 1)[-1] for p in printed) == ["u0.curves.csv", "u0.livelink.csv", "u0.wav"]
    assert all((tmp_path / "out").joinpath(p).is_file() for p in printed)
    bad = runner.invoke(app, ["animate", "--store", str(store.root), "--format", "glb,fbx"])
    assert bad.exit_code == 2 and "unknown export format(s) fbx" in bad.output
    # tracked curves in two variants (guided and unguided): animated without naming one; a wrong name is one line
    from visemeflow.schemas import curves_table

    for variant in ("guided-fast", "unguided-fast"):
        store.write_curves(curves_table("spk/u0", "tracked", variant, np.full((25, 16), 0.5, np.float32), 25.0))
    both = runner.invoke(app, ["animate", "--store", str(store.root), "--format", "curves-csv"])
    assert both.exit_code == 0 and "spk/u0 -> ict_visemes" in both.output, both.output
    bad = runner.invoke(app, ["animate", "--store", str(store.root), "--variant", "guided-fast,nope"])
    assert bad.exit_code == 2, bad.output
    assert f"no tracked curves of variant nope in the store {store.root}; it has guided-fast, unguided-fast" in bad.output
    bad = runner.invoke(app, ["animate", "--store", str(store.root), "--convention", "arkit"])
    assert bad.exit_code == 2 and "unknown convention 'arkit'; known: visemeflow16, arkit52, oculus15" in bad.output
    nothing = runner.invoke(app, ["speak", str(tmp_path / "x.wav"), "--model", "nope", "--store", str(store.root)])
    assert nothing.exit_code == 2 and "no model 'nope'" in nothing.output
    bad = runner.invoke(app, ["preview", "spk/u0", "--store", str(store.root), "--mode", "skeleton"])
    assert bad.exit_code == 2 and "--mode must be one of blendshape, bones, both, not 'skeleton'" in bad.output
    bad = runner.invoke(app, ["preview", "spk/u0", "--store", str(store.root), "--mode", "both", "--bones", "0"])
    assert bad.exit_code == 2 and "--bones: Input should be greater than or equal to 1" in bad.output


def test_export_model_writes_an_onnx_graph_that_onnxruntime_runs(tmp_path):
    import onnxruntime

    out = tmp_path / "default.onnx"
    result = runner.invoke(app, ["export-model", "default-fbank", "--out", str(out), "--store",
                                 str(tmp_path / "store")])
    assert result.exit_code == 0, result.output
    assert "onnxruntime vs torch max |diff|" in result.output and out.is_file()
    session = onnxruntime.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    (curves,) = session.run(None, {"audio": np.zeros((1, 16000), np.float32)})
    assert curves.shape == (1, 30, 16)
    missing = runner.invoke(app, ["export-model", "nope", "--out", str(out), "--store", str(tmp_path / "store")])
    assert missing.exit_code == 2 and "no model 'nope'" in missing.output
    bad = runner.invoke(app, ["export-model", "default", "--out", str(out), "--format", "fbx"])
    assert bad.exit_code == 2 and "unknown format 'fbx'" in bad.output


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_rerun_of_a_still_broken_utterance_prints_why_and_exits_1_and_a_mended_one_exits_0(tmp_path):
    """Also: a stage's command prints its own rejects, not an earlier stage's, and exits 1 on them with --strict."""
    from factories import make_corpus

    corpus = make_corpus(tmp_path / "corpus", {"s/a": [("HH", 0, .2), ("AH", .2, .5)],
                                               "s/b": [("M", 0, .2), ("AH", .2, .5)]})
    good = (corpus / "s" / "b.TextGrid").read_text()
    (corpus / "s" / "b.TextGrid").write_text("garbage")
    store = str(tmp_path / "store")
    done = runner.invoke(app, ["ingest", str(corpus), "--store", store])
    assert done.exit_code == 0 and "ingested 1" in done.output, done.output
    assert "1 rejected:" in done.output and "`visemeflow rejects --store" in done.output
    # the next stage's command does not repeat ingest's rejects as if they were its own
    later = runner.invoke(app, ["procedural", "--store", store])
    assert later.exit_code == 0 and "rejected:" not in later.output and "b.TextGrid" not in later.output, later.output
    # --strict (for schedulers): the same rejects make the command exit 1; a stage with none of its own exits 0
    strict = runner.invoke(app, ["ingest", str(corpus), "--store", store, "--strict"])
    assert strict.exit_code == 1 and "1 rejected:" in strict.output and "--strict: 1 rejected" in strict.output
    assert runner.invoke(app, ["procedural", "--store", store, "--strict"]).exit_code == 0
    mistyped = runner.invoke(app, ["rerun", "s/c", "--stage", "ingest", "--store", store])
    assert mistyped.exit_code == 2 and mistyped.output == f"error: s/c is not in the corpus {corpus}: no files for " \
                                                          "it\n"       # one line, before any flow
    again = runner.invoke(app, ["rerun", "s/b", "--stage", "ingest", "--store", store])
    assert again.exit_code == 1, again.output
    assert f"rejected s/b: {corpus / 's' / 'b.TextGrid'}: file ends early" in again.output
    (corpus / "s" / "b.TextGrid").write_text(good)
    mended = runner.invoke(app, ["rerun", "s/b", "--stage", "ingest", "--store", store])
    assert mended.exit_code == 0 and "ingested 1" in mended.output, mended.output
    assert Store(store).read_table("rejects", "ingest").num_rows == 0
    # its curves come from the next stage, which the rerun of ingest does not run: it says so (audio only here)
    assert mended.output.splitlines()[-1] == f"next, for its later stages: visemeflow rerun s/b --stage procedural " \
                                             f"--store {Store(store).root}"
    later = runner.invoke(app, ["rerun", "s/b", "--stage", "procedural", "--store", store])
    assert later.exit_code == 0 and "next, for" not in later.output, later.output     # no video: nothing to track


def test_curves_list_names_every_source_and_variant_with_its_count(store, tmp_path):
    store.write_curves(curves_table("spk/utt-2", "procedural", "jali", np.zeros((5, 16), np.float32), 30.0), fps=30.0)
    store.write_curves(curves_table(UID, "tracked", "unguided-fast", np.zeros((5, 16), np.float32), 30.0), fps=30.0)
    done = runner.invoke(app, ["curves", "list", "--store", str(store.root)])
    assert done.exit_code == 0, done.output
    assert [line.split() for line in done.output.splitlines()] == [["procedural", "jali", "2", "utterances"],
                                                                  ["tracked", "unguided-fast", "1", "utterance"]]
    assert "curves list" in runner.invoke(app, ["curves", "show", "--help"]).output
    empty = tmp_path / "empty"
    empty.mkdir()
    assert runner.invoke(app, ["curves", "list", "--store", str(empty)]).output == f"no curves in {empty}\n"
    missing = runner.invoke(app, ["curves", "list", "--store", str(tmp_path / "nope")])
    assert missing.exit_code == 2 and "no store at" in missing.output


def test_the_evaluation_table_explains_its_lip_column_only_when_it_has_one(capsys):
    from visemeflow.cli import _print_evaluation

    row = {"model": "demo", "preset": "fbank-blstm", "group": "models", "validation": 3.2, "volume": 3.3,
           "ratio_volume": 1.03}
    result = {"validation_utterances": 2, "source": "tracked", "variant": "guided-fast", "markdown": "r.md",
              "csv": "r.csv"}
    _print_evaluation({**result, "table": [{**row, "lip_closed_validation": 0.0}]})
    out = capsys.readouterr().out.splitlines()
    assert out[1].startswith("model") and out[1].endswith("b/p/m lips closed")
    assert out[2].split()[-1] == "0%"
    assert any(line.startswith("b/p/m lips closed: of the validation set's b/p/m phones") for line in out)
    _print_evaluation({**result, "table": [row]})
    assert "b/p/m lips closed" not in capsys.readouterr().out


def test_curves_of_an_utterance_the_store_no_longer_holds_come_with_a_warning(store):
    """An utterance rejected by a later ingest kept its curves, and `curves show/export` gave them without a word
    while `train` left them out (a new user's report). They still come (nothing stored is lost) with one warning
    line saying why, and `curves list` counts them apart."""
    from visemeflow.schemas import UTTERANCES

    row = {name: None for name in UTTERANCES.names}
    row.update({C.UTTERANCE_ID: "spk/utt-2", C.SPEAKER: "spk", C.CONTENT_HASH: "x", C.N_FRAMES: 5, C.FPS: 30.0,
                C.DURATION_S: 0.2, C.AUDIO_PATH: "a.wav", C.ALIGNMENT_PATH: "", C.ALIGNMENT_FORMAT: "none",
                C.VIDEO_PATH: "", C.SPLIT: "train", C.LANGUAGE: "en", C.SAMPLE_RATE: 16000})
    store.write_shard("utterances", 0, table_from_rows([row], UTTERANCES))
    store.write_shard("rejects", 0, table_from_rows([reject_row(UID, "ingest", "AlignmentAudioMismatch",
                                                                f"{UID}: labels run 0.3 s past the audio", "a.wav")],
                                                     REJECTS), stage="ingest")
    done = runner.invoke(app, ["curves", "show", UID, "--store", str(store.root)])
    assert done.exit_code == 0 and done.stderr == (f"warning: {UID} is no longer in the store's utterances (rejected "
                                                   f"since: {UID}: labels run 0.3 s past the audio); these curves are "
                                                   "from an earlier run\n")
    assert "31 frames" in done.stdout
    done = runner.invoke(app, ["curves", "export", UID, "--store", str(store.root)])
    assert done.exit_code == 0 and done.stderr.startswith(f"warning: {UID} is no longer") and "MBP" in done.stdout
    done = runner.invoke(app, ["curves", "list", "--store", str(store.root)])
    assert done.output == (f"procedural   jali                    1 utterance (1 of them no longer in the store's "
                           f"utterances, e.g. {UID}: rejected or gone from the corpus since; `visemeflow rejects`)\n")
