"""The table of export formats (`EXPORTERS`): each format's name (`--format`), file suffixes and writer, as data the
config's check reads without importing a writer (each writer imports its own module when it runs). A new format is
its writer and one `register_exporter` call; `animation.package` writes a package through this table.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

    from visemeflow.rig.character import Character


@dataclass(frozen=True)
class ExportTarget:
    """What a blendshape-mode writer gets: the file to write and one package's played curves (T, 16) and shape
    weights (T, shapes) at `fps` on `character`."""

    path: Path
    character: Character
    curves: np.ndarray
    weights: np.ndarray
    fps: float
    stem: str
    utterance_id: str


@dataclass(frozen=True)
class Exporter:
    """One export format: its name (`--format`), the suffix of its file in blendshape mode and the writer of it
    (None: a bone-mode-only format), and the suffix bone mode writes it under (None: not written in bone mode;
    bone-mode files come from the solved bone rig, `export_bone_animation`)."""

    name: str
    suffix: str | None
    write: Callable[[ExportTarget], None] | None
    bone_suffix: str | None = None


def _glb(t: ExportTarget) -> None:
    from visemeflow.animation.gltf_asset import write_character_glb

    write_character_glb(t.path, t.character, t.weights, t.fps, name=t.stem)


def _usd(t: ExportTarget) -> None:
    from visemeflow.animation.usd import write_usd

    write_usd(t.path, t.character, t.weights, t.fps, name=t.stem)


def _usdz(t: ExportTarget) -> None:
    from visemeflow.animation.usd import write_usdz

    write_usdz(t.path, t.character, t.weights, t.fps, name=t.stem)


def _livelink(t: ExportTarget) -> None:
    from visemeflow.shapes.conventions import arkit_weights
    from visemeflow.shapes.livelink import write_livelink_csv

    write_livelink_csv(t.path, arkit_weights(t.curves), t.fps)


def _web_json(t: ExportTarget) -> None:
    from visemeflow.animation.webjson import write_web_json

    write_web_json(t.path, t.character.shape_names, t.weights, t.fps, name=t.stem)


def _curve_table(kind: str) -> Callable[[ExportTarget], None]:
    def write(t: ExportTarget) -> None:
        import numpy as np

        from visemeflow.animation.export import CurveTrack, write_export

        n = len(t.curves)
        write_export(CurveTrack(t.utterance_id, "", "", t.curves, np.arange(n) / t.fps, np.arange(n)), t.path, kind)
    return write


EXPORTERS: dict[str, Exporter] = {}
"""Every export format, by name: `AnimateConfig.formats`, the package paths and the writers all read this table."""


def register_exporter(exporter: Exporter) -> Exporter:
    """Add an export format (a new one is its writer and this one call); another format under a taken name is
    refused."""
    if EXPORTERS.get(exporter.name, exporter) != exporter:
        raise ValueError(f"export format {exporter.name!r} is already registered")
    if exporter.suffix is None and exporter.bone_suffix is None:
        raise ValueError(f"export format {exporter.name!r} has no suffix in either mode")
    if (exporter.suffix is None) != (exporter.write is None):
        raise ValueError(f"export format {exporter.name!r}: a blendshape-mode suffix needs a writer and vice versa")
    EXPORTERS[exporter.name] = exporter
    return exporter


for _e in (Exporter("glb", ".glb", _glb, ".bones.glb"), Exporter("usd", ".usd", _usd, ".bones.usd"),
           Exporter("usdz", ".usdz", _usdz),
           Exporter("livelink", ".livelink.csv", _livelink), Exporter("json", ".web.json", _web_json),
           Exporter("curves-csv", ".curves.csv", _curve_table("csv")),
           Exporter("curves-json", ".curves.json", _curve_table("json")),
           Exporter("pose-csv", None, None, ".poses.csv"), Exporter("pose-json", None, None, ".poses.json")):
    register_exporter(_e)



def export_formats() -> tuple[str, ...]:
    """The names of every registered export format."""
    return tuple(EXPORTERS)


def bone_only_formats() -> tuple[str, ...]:
    """Formats written only in bone mode (the pose tables)."""
    return tuple(name for name, e in EXPORTERS.items() if e.write is None)
