"""Names a package exports, imported from their module on first use (PEP 562), so that importing one light
submodule of a package (its config, read by the CLI and the flows' parameters) does not import the heavy rest."""

import importlib
from collections.abc import Callable, Mapping
from typing import Any


def lazy_exports(namespace: dict[str, Any], exports: Mapping[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """`__getattr__` and `__dir__` for a package whose `namespace` (its `globals()`) exports each name of `exports`
    from the module named beside it, relative to the package when the name starts with a dot:
    `__getattr__, __dir__ = lazy_exports(globals(), {"Name": ".submodule", "Other": "visemeflow.rig"})`."""
    package = namespace["__name__"]

    def __getattr__(name: str) -> Any:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module, package), name)
        namespace[name] = value   # later lookups find it without this function
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(exports))

    return __getattr__, __dir__
