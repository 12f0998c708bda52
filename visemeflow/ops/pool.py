"""The entrypoints of prefect.yaml's work-pool deployments: `visemeflow/ops/pool.py:<stage>_flow` for every stage of
`visemeflow.flows.stages.STAGES`.

Each is the stage's flow with the fields of its params model as flat parameters, named as the stage (`rerun/pool`),
as `visemeflow serve` serves them (`visemeflow.ops.serve.flat_flow`): `prefect deployment run 'rerun/pool' --param
utterance_id=...` is accepted, and a run naming some fields keeps the deployment's `store` (docs/serve.md). Paths are
checked against VISEMEFLOW_SERVE_ROOTS only where the worker's environment sets it (prefect.yaml's deployments ran the
stage flows unconfined, and a worker has no `serve --store` to take folders from).

Built when asked for (`__getattr__`), so loading this file imports no stage's flow: Prefect's engine imports the one
its run needs. Prefect loads the file as a script (its own module, not `visemeflow.ops.pool`); the flows are built and
cached in `visemeflow.ops.serve` either way.
"""

from prefect import Flow

from visemeflow.ops.serve import SERVED_FLOWS, pool_flow

def __getattr__(name: str) -> Flow:
    if name in SERVED_FLOWS:
        return pool_flow(name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *SERVED_FLOWS})
