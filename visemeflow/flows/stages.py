"""Every stage once: its flow, what its deployment's default parameters name, its description and schedule, and
whether `rerun` takes one utterance through it.

`visemeflow serve`'s deployments (`visemeflow.ops.serve.build_deployments`) and `prefect.yaml`
(`visemeflow.ops.serve.render_prefect_yaml`, checked against the file by a test) are made from this table; a new
stage is its flow module, a row here and its command in `cli/__init__.py` (and, to be rerun for one utterance,
`rerun=True` and a `rerun_one` in its flow module). Flows are named by module and attribute and
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
    rerun: bool = False
    needs_video: bool = False   # its utterances are videos: one without has nothing for it (rerun refuses it up front)
    reads: tuple[str, ...] = ()  # the corpus stages whose output it reads for an utterance (rerun says what follows)

    @property
    def entrypoint(self) -> str:
        """`visemeflow/flows/x.py:x_flow`, as prefect.yaml names it."""
        return f"{self.module.replace('.', '/')}.py:{self.flow_attr}"

    def flow(self) -> Any:
        """The flow object (imports its module)."""
        return getattr(importlib.import_module(self.module), self.flow_attr)

    def rerun_one(self) -> Any:
        """`rerun_one(store, utterance_id, last settings, force)` of the stage's flow module (stages with `rerun`)."""
        if not self.rerun:
            raise ValueError(f"the {self.name} stage cannot be rerun for one utterance; stages: {', '.join(RERUNNABLE)}")
        return importlib.import_module(self.module).rerun_one


def _stage(name: str, description: str = "", module: str | None = None, **kwargs: Any) -> Stage:
    return Stage(name, f"visemeflow.flows.{module or name}", f"{name}_flow", description, **kwargs)


STAGES: tuple[Stage, ...] = (
    _stage("pipeline", "Every stage on the corpus; unchanged utterances are cache hits.", on_corpus=True,
           scheduled=True),
    _stage("ingest", on_corpus=True, rerun=True),
    _stage("procedural", rerun=True, reads=("ingest",)),
    _stage("landmarks", "MediaPipe FaceMesh landmarks of every video without a landmark file.", rerun=True,
           needs_video=True, reads=("ingest",)),
    _stage("track", rerun=True, needs_video=True, reads=("ingest", "procedural", "landmarks")),
    _stage("train"),
    _stage("sweep"),
    _stage("evaluate", "Models judged on validation and on volume/pitch/speed/noise copies (robustness table)."),
    _stage("predict", "Curves of new audio files from a trained model (the form asks for model and files)."),
    _stage("import_curves", "Captured animation (Live Link CSV, channel files) as `captured` curves of real speech "
                            "(the form asks for the takes)."),
    _stage("animate", "Stored curves on characters: GLB, USD, Live Link CSV, web JSON and the audio.", rerun=True),
    _stage("speak", "Audio files to talking characters: predict, then animate (the form asks for model, files and "
                    "characters).", module="animate"),
    _stage("preview", "One utterance's preview MP4: the character driven by each source side by side.",
           module="animate"),
    _stage("rerun", "One utterance through one stage (ingest, procedural, landmarks, track, animate), even when "
                    "cached."),
)

RERUNNABLE: tuple[str, ...] = tuple(stage.name for stage in STAGES if stage.rerun)
"""The stages `rerun` takes one utterance through (RerunParams.stage)."""


def later_stages(name: str) -> tuple[Stage, ...]:
    """The stages that read stage `name`'s output for an utterance, in table order: what a rerun of it leaves as it
    was."""
    return tuple(stage for stage in STAGES if name in stage.reads)


def stage_named(name: str) -> Stage:
    """The stage of that name; ValueError listing the names otherwise."""
    for stage in STAGES:
        if stage.name == name:
            return stage
    raise ValueError(f"unknown stage {name!r}; stages: {', '.join(s.name for s in STAGES)}")
