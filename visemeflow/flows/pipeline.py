"""The `pipeline` flow: every stage that exists, in order, on one corpus."""

from prefect import flow

from visemeflow.flows.ingest import ingest_flow
from visemeflow.flows.params import (
    IngestParams,
    PipelineParams,
    ProceduralParams,
    TrackParams,
)
from visemeflow.flows.procedural import procedural_flow
from visemeflow.flows.track import track_flow
from visemeflow.schemas import C
from visemeflow.storage import Store


@flow(name="pipeline", flow_run_name="pipeline[{params.corpus}]")
def pipeline_flow(params: PipelineParams) -> dict[str, dict]:
    """Ingest the corpus, generate procedural curves, track the videos; each stage a subflow with cached tasks."""
    common = {"store": params.store, "n_shards": params.n_shards}
    result = {"ingest": ingest_flow(IngestParams(corpus=params.corpus, config=params.ingest, **common))}
    result["procedural"] = procedural_flow(ProceduralParams(config=params.procedural, **common))
    videos = Store(params.store).read_table("utterances").column(C.VIDEO_PATH).drop_null()
    if len(videos):
        result["track"] = track_flow(TrackParams(config=params.tracking, rig=params.rig, **common))
    return result
