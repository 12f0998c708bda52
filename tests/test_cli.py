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
