"""The `pipeline` flow: ingest, procedural curves, tracking and (when characters are given) animation, in order, on
one corpus (training, sweeps and evaluation are flows of their own: they need choices the corpus does not make)."""

from collections.abc import Callable

from prefect import flow
from prefect.states import Failed

from visemeflow.flows.common import finished
from visemeflow.flows.errors import StageFailed
from visemeflow.flows.ingest import ingest_flow
from visemeflow.flows.landmarks import LandmarksParams, landmarks_flow, utterances_needing_landmarks
from visemeflow.flows.params import (
    IngestParams,
    PipelineParams,
    ProceduralParams,
    TrackParams,
)
from visemeflow.flows.procedural import procedural_flow
from visemeflow.flows.track import track_flow
from visemeflow.flows.runners import run_on_runner
from visemeflow.schemas import C, CurveSource
from visemeflow.storage import Store


@flow(name="pipeline", flow_run_name="pipeline({params.corpus})")
def pipeline_flow(params: PipelineParams) -> dict[str, dict]:
    """Ingest the corpus, generate procedural curves, detect landmarks on videos without a landmark file, track the
    videos; each stage a subflow with cached tasks.

    A stage that ends Failed does not stop the later ones (they work on what it did); the pipeline then ends
    Failed with that stage's message and every stage's summary. An ingest that refused to run (no corpus at the
    path, or a store of another corpus whose utterances it would drop) ends the pipeline there.
    """
    common = {"store": params.store, "n_shards": params.n_shards}
    result: dict[str, dict] = {}
    failures: list[str] = []

    def run(stage: str, call: Callable[[], dict]) -> None:
        try:
            result[stage] = call()
        except StageFailed as exc:
            result[stage] = exc.summary
            failures.append(str(exc))

    run("ingest", lambda: ingest_flow(IngestParams(corpus=params.corpus, config=params.ingest, replace=params.replace,
                                                           **common)))
    if result["ingest"].get("refused"):   # no corpus there, or one the store is not of: nothing for later stages
        message = "pipeline: " + failures[0]
        return Failed(message=message, data=StageFailed(message, result))
    run("procedural", lambda: procedural_flow(ProceduralParams(config=params.procedural, **common)))
    videos = Store(params.store).read_table("utterances").column(C.VIDEO_PATH).drop_null()
    if len(videos) and utterances_needing_landmarks(Store(params.store)):
        marks = LandmarksParams(config=params.landmarks, runner=params.runner, **common)
        run("landmarks", lambda: run_on_runner(landmarks_flow, marks))
    if len(videos):
        track = TrackParams(config=params.tracking, rig=params.rig, runner=params.runner,
                            joint_frames=params.joint_frames, device=params.device, **common)
        run("track", lambda: run_on_runner(track_flow, track))
    if params.characters:
        from visemeflow.flows.animate import AnimateParams, animate_flow

        source = CurveSource.TRACKED if len(videos) else CurveSource.PROCEDURAL
        # every tracked variant this run wrote, in one animate run: the guided one first, and `unguided-...` for
        # videos without an alignment (each utterance from its own; one rejects table for the stage)
        written = (result.get("track") or {}).get("variants") or params.tracking.variant
        variants = sorted({v.strip() for v in written.split(",") if v.strip()},
                          key=lambda v: v != params.tracking.variant)
        run("animate", lambda: animate_flow(AnimateParams(
            store=params.store, n_shards=params.n_shards, characters=params.characters, source=source,
            variant=",".join(variants) if len(videos) else None, config=params.animate)))
    if failures:
        message = "pipeline: " + "; ".join(failures)
        return Failed(message=message, data=StageFailed(message, result))
    ids = Store(params.store).read_table("rejects").column(C.UTTERANCE_ID).to_pylist()
    failed = len({i for i in ids if i is not None}) + sum(i is None for i in ids)  # each utterance once
    return finished("pipeline", result, failed, result["ingest"].get("utterances", 0) + result["ingest"].get(
        "discovery_rejected", 0))
