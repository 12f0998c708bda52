"""Table schemas (the only place column names are written) and identifier rules.

The names below are imported from their modules on first use, so the identifier rules (`schemas.ids`) and the curve
sources (`schemas.sources`) import without pyarrow."""

from visemeflow.lazy import lazy_exports

_EXPORTS = {
    "Curves": ".curves",
    "fps_of_table": ".curves",
    "InvalidIdError": ".ids",
    "encode_path_part": ".ids",
    "id_path_parts": ".ids",
    "make_utterance_id": ".ids",
    "normalize_utterance_id": ".ids",
    "readable_path_parts": ".ids",
    "shard_of": ".ids",
    "split_utterance_id": ".ids",
    "utterance_id_from_path_parts": ".ids",
    "validate_name": ".ids",
    "validate_utterance_id": ".ids",
    "CURVES": ".tables",
    "LOSS_TERMS": ".tables",
    "METRICS": ".tables",
    "PHONES": ".tables",
    "REJECTS": ".tables",
    "TABLE_SCHEMAS": ".tables",
    "TRACKING_FRAMES": ".tables",
    "UTTERANCES": ".tables",
    "C": ".tables",
    "CurveSource": ".sources",
    "curves_array": ".tables",
    "curves_table": ".tables",
    "table_from_rows": ".tables",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS)
