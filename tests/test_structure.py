"""Names defined once: the curve sources (schemas.CurveSource) and the default curve rate (timebase.DEFAULT_FPS)
are not spelled again across the package."""

import re

from factories import REPO

from visemeflow.schemas import CurveSource
from visemeflow.schemas.tables import CURVE_SOURCES

PACKAGE = REPO / "visemeflow"


def sources_of_the_package():
    for path in sorted(PACKAGE.rglob("*.py")):
        yield path, path.read_text(encoding="utf-8")


def test_no_module_spells_the_default_frame_rate_again():
    found = [f"{p.relative_to(REPO)}:{i}" for p, text in sources_of_the_package() if p.name != "timebase.py"
             for i, line in enumerate(text.splitlines(), 1)
             if re.search(r"fps.*[=(]\s*30(\.0)?\b|\b30\.0\b.*fps", line, re.I) and "TIMECODE" not in line]
    assert not found, f"use visemeflow.timebase.DEFAULT_FPS: {found}"


def test_stages_name_their_curve_source_by_the_enum():
    found = [f"{p.relative_to(REPO)}:{i}" for p, text in sources_of_the_package() if p.name != "tables.py"
             for i, line in enumerate(text.splitlines(), 1)
             if re.search(r"SOURCE\s*=\s*\"", line)]
    assert not found, f"use visemeflow.schemas.CurveSource: {found}"
    assert CURVE_SOURCES == tuple(s.value for s in CurveSource) and CurveSource("tracked") is CurveSource.TRACKED


def test_rerun_offers_every_stage_of_the_table_that_can_rerun_one_utterance():
    import inspect
    import typing

    from visemeflow.flows.params import SETTINGS, RerunParams
    from visemeflow.flows.stages import RERUNNABLE, STAGES, stage_named

    offered = typing.get_args(RerunParams.model_fields["stage"].annotation)
    assert offered == RERUNNABLE == ("ingest", "procedural", "landmarks", "track", "animate")
    for name in offered:   # each has its rerun_one and typed settings to repeat
        assert list(inspect.signature(stage_named(name).rerun_one()).parameters) == ["store", "uid", "last", "force"]
        assert name in SETTINGS
    unable = next(s for s in STAGES if not s.rerun)
    try:
        unable.rerun_one()
    except ValueError as exc:
        assert "cannot be rerun" in str(exc)
    else:
        raise AssertionError(f"{unable.name} has no rerun_one")


def test_no_test_module_imports_another():
    """Shared builders live in tests/factories.py: importing a test module runs its module-level code and
    re-collects nothing, but couples the files (a rename breaks the other)."""
    import ast

    tests = REPO / "tests"
    found = []
    for path in sorted(tests.glob("test_*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            found += [f"{path.name} imports {n}" for n in names if n.startswith("test_")]
    assert not found, found


def test_a_new_stage_is_its_flow_its_params_its_row_and_its_command(tmp_path, monkeypatch):
    """The four places a new stage is written (docs/reference.md, "Extending it"): serve's deployments,
    prefect.yaml, rerun and the command follow from them, nothing else is edited."""
    import inspect
    import textwrap

    import typer
    from typer.testing import CliRunner

    from visemeflow.cli.options import Opt, stage_command
    from visemeflow.flows.stages import STAGES, Stage
    from visemeflow.ops import serve

    # 1 and 2: the flow module and its params model (flows/params.py in the package)
    (tmp_path / "toy_stage.py").write_text(textwrap.dedent('''
        from pathlib import Path

        from prefect import flow
        from pydantic import BaseModel, Field


        class ToyParams(BaseModel):
            store: Path = Field(Path("visemeflow-out/store"), description="Folder of the Parquet store.")
            level: int = Field(3, ge=0, description="How loud.")


        @flow(name="toy")
        def toy_flow(params: ToyParams) -> dict:
            return {"level": params.level}


        def rerun_one(store, uid, last, force):
            return {"uid": uid, "force": force}
    '''))
    monkeypatch.syspath_prepend(str(tmp_path))
    import toy_stage

    # 3: its row in the stage table
    row = Stage("toy", "toy_stage", "toy_flow", "A toy stage.", rerun=True)
    monkeypatch.setattr(serve, "STAGES", (*STAGES, row))
    monkeypatch.setitem(serve.SERVED_FLOWS, "toy_flow", "toy_stage")
    yaml_text = serve.render_prefect_yaml()
    assert "entrypoint: visemeflow/ops/pool.py:toy_flow" in yaml_text and "description: A toy stage." in yaml_text
    assert list(inspect.signature(serve.pool_flow("toy_flow")).parameters) == ["store", "level"]   # flat
    deployments = serve.build_deployments(tmp_path / "store", None)
    assert [d.name for d in deployments].count("served") == len(STAGES) + 1
    assert row.rerun_one()(None, "spk/a", None, True) == {"uid": "spk/a", "force": True}

    # 4: its command
    app = typer.Typer()
    ran = []

    @app.callback()
    def main() -> None:
        pass

    @stage_command(app, toy_stage.ToyParams, [Opt("store"), Opt("level")])
    def toy(params) -> None:
        """A toy stage."""
        ran.append(params.level)

    assert CliRunner().invoke(app, ["toy", "--level", "5"]).exit_code == 0 and ran == [5]
