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
