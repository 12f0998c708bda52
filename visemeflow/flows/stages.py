"""Every stage once: its flow, what its deployment's default parameters name, its description and schedule.

`visemeflow serve`'s deployments (`visemeflow.ops.serve.build_deployments`) and `prefect.yaml`
(`visemeflow.ops.serve.render_prefect_yaml`, checked against the file by a test) are made from this table; a new
stage is its flow module, a row here and its command in `cli.py`. Flows are named by module and attribute and
imported only when asked for, so reading the table imports no flow (serve's confined copies need the names).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Stage:
    """One stage: the flow `module:flow_attr` (its Prefect name is `name`), whether its deployment's defaults name
    the corpus besides the store, whether it runs on the schedule, and what the UI says of it."""

    name: str
    module: str
    flow_attr: str
    description: str = ""
    on_corpus: bool = False
    scheduled: bool = False

    @property
    def entrypoint(self) -> str:
        """`visemeflow/flows/x.py:x_flow`, as prefect.yaml names it."""
        return f"{self.module.replace('.', '/')}.py:{self.flow_attr}"

    def flow(self) -> Any:
        """The flow object (imports its module)."""
        return getattr(importlib.import_module(self.module), self.flow_attr)


def _stage(name: str, description: str = "", module: str | None = None, **kwargs: Any) -> Stage:
    return Stage(name, f"visemeflow.flows.{module or name}", f"{name}_flow", description, **kwargs)


STAGES: tuple[Stage, ...] = (
    _stage("pipeline", "Every stage on the corpus; unchanged utterances are cache hits.", on_corpus=True,
           scheduled=True),
    _stage("ingest", on_corpus=True),
    _stage("procedural"),
    _stage("landmarks", "MediaPipe FaceMesh landmarks of every video without a landmark file."),
    _stage("track"),
    _stage("train"),
    _stage("sweep"),
    _stage("evaluate", "Models judged on validation and on volume/pitch/speed/noise copies (robustness table)."),
    _stage("predict", "Curves of new audio files from a trained model (the form asks for model and files)."),
    _stage("import_curves", "Captured animation (Live Link CSV, channel files) as `captured` curves of real speech "
                            "(the form asks for the takes)."),
    _stage("animate", "Stored curves on characters: GLB, USD, Live Link CSV, web JSON and the audio."),
    _stage("speak", "Audio files to talking characters: predict, then animate (the form asks for model, files and "
                    "characters).", module="animate"),
    _stage("preview", "One utterance's preview MP4: the character driven by each source side by side.",
           module="animate"),
    _stage("rerun", "One utterance through one stage (ingest, procedural, landmarks, track, animate), even when "
                    "cached."),
)


def stage_named(name: str) -> Stage:
    """The stage of that name; ValueError listing the names otherwise."""
    for stage in STAGES:
        if stage.name == name:
            return stage
    raise ValueError(f"unknown stage {name!r}; stages: {', '.join(s.name for s in STAGES)}")
