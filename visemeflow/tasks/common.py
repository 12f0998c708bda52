"""What every task shares: the cache policy, result storage and reject rows."""

from datetime import datetime, timezone
from pathlib import Path

from prefect.cache_policies import INPUTS, TASK_SOURCE

from visemeflow.schemas import C
from visemeflow.storage import Store

# Deterministic tasks are keyed on their inputs (content hashes, configs, ids) and their own code.
CACHE_POLICY = INPUTS + TASK_SOURCE


def result_storage(store_root: str | Path) -> Path:
    """Folder of Prefect's persisted task results and cache records, kept inside the store."""
    return Store(store_root).results_dir()


def reject_row(utterance_id: str | None, stage: str, error_type: str, message: str, path: str | None) -> dict[str, object]:
    return {
        C.UTTERANCE_ID: utterance_id, C.STAGE: stage, C.ERROR_TYPE: error_type, C.MESSAGE: message,
        C.PATH: path, C.TIME: datetime.now(timezone.utc),
    }
