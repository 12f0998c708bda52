"""Operations: serving deployments with a local Prefect server, and task runners that scale out with Dask."""
