"""Prefect tasks: thin wrappers that read from the store, call domain code and write to the store."""
