"""The package's layers (DESIGN.md): what each part may import, read from the source's import statements.

Domain packages never import Prefect, the store, tasks or flows; flows never import `ops/` (which serves them);
and the parts import each other without a cycle.
"""

import ast
from collections import defaultdict

from factories import REPO

PACKAGE = REPO / "visemeflow"
BASE = {"visemes", "articulation", "hashing", "hashmemo", "lazy", "timebase", "atomic", "location", "logs"}
DOMAIN = {"phonetics", "procedural", "render", "rig", "shapes", "tracking", "learning", "animation", "authoring", "synth",
          "ingest"}
# part -> the parts of ours it may import (besides itself and BASE): DESIGN.md's table, with the exceptions named
ALLOWED = {
    **{name: set() for name in BASE},
    "schemas": set(),
    "phonetics": set(),
    "render": set(),
    "rig": set(),
    "shapes": {"rig"},
    "procedural": {"phonetics"},
    "tracking": {"rig", "render"},
    "learning": {"schemas"},  # the utterance-id rules, for augmented ids
    # tracking: the preview's source-video panel reads the clip and its landmark file with tracking's readers
    # (tracking.video, tracking.landmarks); nothing of the tracker itself
    "animation": {"rig", "shapes", "render", "tracking"},
    # deformation transfer and its automatic markers (FaceMesh on rendered faces: tracking), once per character
    "authoring": {"rig", "shapes", "render", "tracking", "animation"},
    "synth": {"phonetics", "procedural", "rig", "render", "tracking"},  # the landmark track it writes per video
    "ingest": {"phonetics", "schemas", "shapes", "tracking"},  # tracking.video: the audio track of a video
    "storage": {"schemas"},
    "dashboards": {"schemas", "storage", "learning", "ingest"},  # the robustness table; the one audio reader
    "tasks": DOMAIN | {"schemas", "storage"},
    "flows": DOMAIN | {"schemas", "storage", "tasks", "dashboards"},
    "ops": DOMAIN | {"schemas", "storage", "tasks", "flows"},
    # the command: flows, and for commands that run no flow (curves show, rejects, export-model) the parts they read
    "cli": DOMAIN | {"schemas", "storage", "flows", "dashboards", "ops"},
}
WITH_PREFECT = {"tasks", "flows", "dashboards", "ops", "cli"}


def imports_by_part() -> dict[str, dict[str, set[str]]]:
    """part -> {imported top-level module or part of ours -> files that import it}."""
    found: dict[str, dict[str, set[str]]] = defaultdict(lambda: defaultdict(set))
    for path in PACKAGE.rglob("*.py"):
        part = path.relative_to(PACKAGE).parts[0].removesuffix(".py")
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                head = name.split(".")
                target = head[1] if head[0] == "visemeflow" and len(head) > 1 else head[0]
                found[part][target].add(path.name)
    return found


def test_every_part_imports_only_the_layers_below_it():
    found = imports_by_part()
    assert set(found) - {"__init__"} <= set(ALLOWED), "a new part: give it its row in ALLOWED"
    ours = set(ALLOWED)
    for part, targets in found.items():
        if part == "__init__":
            continue
        bad = {t: sorted(files) for t, files in targets.items()
               if t in ours and t != part and t not in ALLOWED[part] | BASE}
        assert not bad, f"visemeflow/{part} imports {bad}, outside its layer"


def test_only_the_orchestration_parts_import_prefect():
    found = imports_by_part()
    with_prefect = {part for part, targets in found.items() if "prefect" in targets or "prefect_dask" in targets}
    assert with_prefect <= WITH_PREFECT, with_prefect - WITH_PREFECT
    assert "flows" in with_prefect and "tasks" in with_prefect  # the reading finds them


def test_the_parts_import_each_other_without_a_cycle():
    found = imports_by_part()
    graph = {part: {t for t in targets if t in found and t != part} for part, targets in found.items()}
    state: dict[str, int] = {}

    def visit(node: str, trail: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            assert state.get(nxt) != 1, "import cycle: " + " -> ".join([*trail, node, nxt])
            if nxt not in state:
                visit(nxt, [*trail, node])
        state[node] = 2

    for part in sorted(graph):
        if part not in state:
            visit(part, [])
    assert graph["flows"] and "ops" not in graph["flows"]
