"""The Parquet store: one folder of tables and per-utterance curve files."""

from visemeflow.storage.store import NonFiniteValueError, Store, StoreError

__all__ = ["NonFiniteValueError", "Store", "StoreError"]
