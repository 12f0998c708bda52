"""Table schemas (the only place column names are written) and identifier rules."""

from visemeflow.schemas.ids import (
    InvalidIdError,
    shard_of,
    split_utterance_id,
    validate_name,
    validate_utterance_id,
)
from visemeflow.schemas.tables import (
    CURVES,
    LOSS_TERMS,
    METRICS,
    PHONES,
    REJECTS,
    TABLE_SCHEMAS,
    TRACKING_FRAMES,
    UTTERANCES,
    C,
    curves_array,
    curves_table,
    table_from_rows,
)

__all__ = [
    "C",
    "CURVES",
    "LOSS_TERMS",
    "METRICS",
    "PHONES",
    "REJECTS",
    "TABLE_SCHEMAS",
    "TRACKING_FRAMES",
    "UTTERANCES",
    "InvalidIdError",
    "curves_array",
    "curves_table",
    "shard_of",
    "split_utterance_id",
    "table_from_rows",
    "validate_name",
    "validate_utterance_id",
]
