"""The `rerun` flow: one utterance through one stage, by hand, even when its cache is valid.

Each stage that can be rerun has `rerun=True` in its row of `flows/stages.py` and a `rerun_one(store, uid, last,
force)` in its flow module, which repeats that stage for one utterance with the settings the stage last ran with
(`last`, typed: `flows.params.SETTINGS`; None where it never ran)."""

from prefect import flow, get_run_logger

from visemeflow.flows.common import last_settings
from visemeflow.flows.errors import RerunError  # noqa: F401 (re-exported: what a caller catches)
from visemeflow.flows.params import RerunParams
from visemeflow.flows.stages import stage_named
from visemeflow.storage import Store


@flow(name="rerun", flow_run_name="rerun({params.utterance_id}:{params.stage})")
def rerun_flow(params: RerunParams) -> dict:
    """Rerun exactly one utterance through one stage with the settings that stage last ran with."""
    store = Store(params.store)
    uid = params.utterance_id
    rerun_one = stage_named(params.stage).rerun_one()
    report = rerun_one(store, uid, last_settings(store, params.stage), params.force)
    get_run_logger().info("rerun %s %s: %s", params.stage, uid, report)
    return report
