"""The `pipeline` flow: every stage that exists, in order, on one corpus."""

from prefect import flow

from visemeflow.flows.ingest import ingest_flow
from visemeflow.flows.params import IngestParams, PipelineParams, ProceduralParams
from visemeflow.flows.procedural import procedural_flow


@flow(name="pipeline", flow_run_name="pipeline[{params.corpus}]")
def pipeline_flow(params: PipelineParams) -> dict[str, dict]:
    """Ingest the corpus, then generate procedural curves; each stage is a subflow with cached tasks."""
    common = {"store": params.store, "n_shards": params.n_shards}
    ingest = ingest_flow(IngestParams(corpus=params.corpus, config=params.ingest, **common))
    procedural = procedural_flow(ProceduralParams(config=params.procedural, **common))
    return {"ingest": ingest, "procedural": procedural}
