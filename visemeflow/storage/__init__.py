"""The Parquet store: one folder of tables and per-utterance curve files."""

from visemeflow.storage.store import Store, StoreError

__all__ = ["Store", "StoreError"]
