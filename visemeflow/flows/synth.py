"""The `synth` flow: a corpus of audio + alignments becomes talking-face videos with known true curves."""

from pathlib import Path

from prefect import flow, get_run_logger

from visemeflow.dashboards.artifacts import publish_rejects, publish_stage_summary
from visemeflow.flows.common import collect
from visemeflow.flows.params import SynthParams
from visemeflow.hashing import file_hash
from visemeflow.location import as_text, input_exists, is_url
from visemeflow.rig import demo_rig_path
from visemeflow.schemas import REJECTS, table_from_rows
from visemeflow.storage import Store
from visemeflow.tasks.common import reject_row, result_storage
from visemeflow.tasks.ingest import discover_corpus_task
from visemeflow.tasks.synth import SOURCE, synth_utterance, truth_variant

STAGE = "synth"


@flow(name="synth", flow_run_name="synth({params.corpus})")
def synth_flow(params: SynthParams) -> dict[str, object]:
    """Render every utterance of the source corpus (one cached task each) into `params.out`."""
    store = Store(params.store)
    rig_path = (params.rig or demo_rig_path()).resolve()
    rig_hash = file_hash(rig_path)
    variant = truth_variant(params.config)
    found = discover_corpus_task(as_text(params.corpus))
    out = as_text(params.out)
    futures = []
    for entry in found["entries"]:
        uid = entry["utterance_id"]
        speaker, name = uid.split("/")
        video = (f"{out}/{speaker}/{name}.{params.config.video_ext}" if is_url(out)
                 else Path(out) / speaker / f"{name}.{params.config.video_ext}")
        present = input_exists(video) and store.has_curves(SOURCE, variant, uid)
        futures.append(
            synth_utterance.with_options(result_storage=result_storage(store.root), refresh_cache=not present)
            .submit(entry, out, str(rig_path), rig_hash, params.config, str(store.root))
        )
    reports, errors = collect(futures, STAGE, kept_when_cached=("utterance_id", "frames"), cached_key="cached",
                              unit="utterances")
    rejects = [reject_row(r["utterance_id"], STAGE, r["error_type"], r["message"], r["path"]) for r in found["rejects"]]
    rejects += [reject_row(None, STAGE, "SynthFailed", e, None) for e in errors]
    store.write_shard("rejects", 0, table_from_rows(rejects, REJECTS), stage=STAGE)
    summary = {
        "utterances": len(found["entries"]), "rendered": sum(1 for r in reports if not r["cached"]),
        "cached": sum(r["cached"] for r in reports), "frames": sum(r.get("frames", 0) for r in reports),
        "failed": len(errors), "variant": variant, "out": str(out),
    }
    publish_stage_summary(STAGE, {k: v for k, v in summary.items() if isinstance(v, int)}, {"variant": variant, "out": str(out)})
    publish_rejects(STAGE, store.read_table("rejects", STAGE))
    get_run_logger().info("synth: %s", summary)
    return summary
