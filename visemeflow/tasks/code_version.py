"""The version of the code a task runs: a digest of the source of the package's modules that its module imports.

A task's own source (Prefect's `TASK_SOURCE`) is a thin wrapper; what decides its outputs lives in the domain
modules it calls (`procedural/jali.py`, `tracking/solver.py`, a feature extractor). The scope of a task is its
module and every module of the package that module imports, directly or through others, read from the import
statements (those inside functions included), plus the `__init__.py` of each package on the way, since Python runs
them, and the modules a package's `__init__.py` exports names of on first use (`visemeflow.lazy`: its table names
them in quotes). So an edit to `procedural/jali.py` changes the procedural task's digest (and, through the curves' provenance,
those of the stages that read its curves), while an edit to the dashboards changes no task's digest: no task module
imports them. Every stage reads the rows ingest made (`utterances`, `phones`), which record no code, so ingest's
scope is in every task's. Non-Python files (rig JSON, lookup tables) and third-party libraries are not part of it.
"""

import functools
import re
from collections.abc import Iterator
from pathlib import Path

import visemeflow
from visemeflow.hashing import new_hasher

PACKAGE = "visemeflow"
ROOT = Path(visemeflow.__file__).resolve().parent
# the stages whose outputs reach every other stage without a provenance that records their code
UPSTREAM = ("visemeflow.tasks.ingest",)
_FROM = re.compile(r"^\s*from\s+(\.*)([\w.]*)\s+import\s+(.+)$")
# a package whose __init__ imports its names on first use (visemeflow.lazy): the modules its table names, quoted
_LAZY_MODULE = re.compile(r"""["'](\.[\w.]+|visemeflow(?:\.\w+)+)["']""")
_IMPORT = re.compile(r"^\s*import\s+(.+)$")


def module_path(module: str, root: Path) -> Path | None:
    """Source file of a module of the package under `root` (a package's `__init__.py`); None when it has none."""
    parts = module.split(".")[1:]
    base = root.joinpath(*parts)
    for path in (base / "__init__.py", base.with_suffix(".py")) if parts else (root / "__init__.py",):
        if path.is_file():
            return path
    return None


def _parents(module: str) -> list[str]:
    parts = module.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


def _statements(text: str) -> Iterator[str]:
    """Each import statement of a source text on one line (backslash and parenthesised continuations joined).

    Read from the lines, not with `ast.parse`: tasks run in threads, and CPython 3.11's parser fails ("AST
    constructor recursion depth mismatch") when two threads parse at once. A line of a docstring that reads like an
    import only widens the scope (a module that does not exist is skipped)."""
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i].split("#", 1)[0]
        while line.rstrip().endswith("\\") and i + 1 < len(lines):
            i += 1
            line = line.rstrip()[:-1] + " " + lines[i].split("#", 1)[0]
        if (_FROM.match(line) or _IMPORT.match(line)) and "(" in line:
            while ")" not in line and i + 1 < len(lines):
                i += 1
                line += " " + lines[i].split("#", 1)[0]
        if _FROM.match(line) or _IMPORT.match(line):
            yield line.replace("(", " ").replace(")", " ")
        i += 1


def _names(listed: str) -> list[str]:
    """`a.b as c, d` -> ["a.b", "d"]."""
    return [part.split()[0] for part in listed.split(",") if part.split()]


def _imported(module: str, path: Path) -> set[str]:
    """Modules of the package named by the import statements of one source file (absolute or relative)."""
    is_package = path.name == "__init__.py"
    found: set[str] = set()
    text = path.read_text(encoding="utf-8")
    if is_package and "lazy_exports(" in text:
        # names exported on first use import their modules then: as an eager __init__ would, they are in scope
        found.update(module + name if name.startswith(".") else name for name in _LAZY_MODULE.findall(text))
    for statement in _statements(text):
        m = _FROM.match(statement)
        if m is None:
            found.update(_names(_IMPORT.match(statement).group(1)))
            continue
        dots, name, listed = m.groups()
        if dots:
            anchor = module.split(".")
            anchor = anchor[:len(anchor) - len(dots) + (1 if is_package else 0)]
            base = ".".join(anchor + ([name] if name else []))
        else:
            base = name
        found.add(base)
        # `from visemeflow.procedural import jali` names a module; `from ... import Config` a name (skipped below)
        found.update(f"{base}.{alias}" for alias in _names(listed) if alias != "*")
    return {name for name in found if name == PACKAGE or name.startswith(PACKAGE + ".")}


def imported_modules(module: str, root: Path = ROOT) -> set[str]:
    """`module` and the modules of the package it imports transitively (with their parent packages), under `root`."""
    seen: set[str] = set()
    todo = [module]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        path = module_path(name, root)
        if path is None:  # a name imported from a module (a class, a function), not a module
            continue
        seen.add(name)
        todo.extend(_parents(name))
        todo.extend(_imported(name, path))
    return seen


def task_scope(module: str, root: Path = ROOT) -> set[str]:
    """The modules whose code decides the outputs of the tasks in `module`: its imports and those of `UPSTREAM`."""
    if module != PACKAGE and not module.startswith(PACKAGE + "."):
        raise ValueError(f"{module} is outside the {PACKAGE} package: a task keyed on its code lives in it")
    if module_path(module, root) is None:
        raise ValueError(f"{module}: no such module under {root}")
    return imported_modules(module, root).union(*(imported_modules(m, root) for m in UPSTREAM))


def source_digest(module: str, root: Path = ROOT) -> str:
    """Digest of the source of the modules in the `task_scope` of `module`, under `root`."""
    h = new_hasher()
    for name in sorted(task_scope(module, root)):
        h.update(name.encode() + b"\0")
        h.update(module_path(name, root).read_bytes() + b"\0")
    return h.hexdigest()


@functools.lru_cache(maxsize=None)
def code_digest(module: str) -> str:
    """`source_digest` of the installed package, computed once per module and process: a running process keeps the
    code it imported, so its results are of that code even when the files change under it."""
    return source_digest(module, ROOT)
