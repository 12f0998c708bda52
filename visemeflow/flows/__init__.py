"""Prefect flows: the wiring of tasks, one module per stage plus `pipeline` and `rerun`."""
