"""Operations around the flows: serving deployments with a local Prefect server, cleaning what can be made again.

The task runners (thread pool, Dask) belong to the flows that use them: `visemeflow.flows.runners`.
"""
