"""The curve sources, apart from the table schemas (pyarrow), so that naming one (a flow's parameters, the CLI)
imports no pyarrow."""

from enum import StrEnum


class CurveSource(StrEnum):
    """Where a stored curve came from (the `source` column and the store's folder): the one spelling of each."""

    PROCEDURAL = "procedural"
    TRACKED = "tracked"
    PREDICTED = "predicted"
    GROUND_TRUTH = "ground_truth"
    CAPTURED = "captured"


CURVE_SOURCES = tuple(s.value for s in CurveSource)
