"""pyarrow schemas of every table; the single source of column names and dtypes."""

from collections.abc import Iterable, Mapping

import numpy as np
import pyarrow as pa

from visemeflow.schemas.sources import CURVE_SOURCES, CurveSource  # noqa: F401 (re-exported)
from visemeflow.visemes import N_VISEMES, VISEMES


class C:
    """Column names."""

    UTTERANCE_ID = "utterance_id"
    SPEAKER = "speaker"
    LANGUAGE = "language"
    INVENTORY = "inventory"
    AUDIO_PATH = "audio_path"
    VIDEO_PATH = "video_path"
    ALIGNMENT_PATH = "alignment_path"
    ALIGNMENT_FORMAT = "alignment_format"
    LANDMARK_PATH = "landmark_path"
    SAMPLE_RATE = "sample_rate"
    DURATION_S = "duration_s"
    FPS = "fps"
    N_FRAMES = "n_frames"
    CONTENT_HASH = "content_hash"
    SPLIT = "split"

    INDEX = "index"
    PART = "part"
    LABEL = "label"
    PHONEME = "phoneme"
    VISEME = "viseme"
    START_S = "start_s"
    END_S = "end_s"
    WORD = "word"
    WORD_INDEX = "word_index"
    STRESS = "stress"

    SOURCE = "source"
    VARIANT = "variant"
    FRAME = "frame"
    TIME_S = "time_s"

    MOUTH_ERROR_PX = "mouth_error_px"
    LANDMARKS_VALID = "landmarks_valid"
    FLOW_VALID_FRACTION = "flow_valid_fraction"
    LOSS_PREFIX = "loss_"
    POSE_COLUMNS = ("rot_x", "rot_y", "rot_z", "trans_x", "trans_y", "trans_z")

    RUN = "run"
    MODEL = "model"
    CONDITION = "condition"
    EPOCH = "epoch"
    L1 = "l1"
    L1_X100 = "l1_x100"
    L1_PREFIX = "l1_"

    STAGE = "stage"
    ERROR_TYPE = "error_type"
    MESSAGE = "message"
    PATH = "path"
    TIME = "time"


NO_ALIGNMENT = "none"
"""`alignment_format` of an utterance without phones (a captured take, a video without an alignment; its
`alignment_path` is ""): ingest keeps it, procedural skips it."""


def has_alignment(row: Mapping[str, object]) -> bool:
    """Whether an `utterances` row (or any dict with its columns) has an alignment, so phones and procedural
    curves: by `alignment_format` (not NO_ALIGNMENT), or by a non-empty `alignment_path` when the row has no
    format column."""
    if C.ALIGNMENT_FORMAT in row and row[C.ALIGNMENT_FORMAT] is not None:
        return row[C.ALIGNMENT_FORMAT] != NO_ALIGNMENT
    return bool(row.get(C.ALIGNMENT_PATH))


UTTERANCES = pa.schema([
    pa.field(C.UTTERANCE_ID, pa.string(), nullable=False),
    pa.field(C.SPEAKER, pa.string(), nullable=False),
    pa.field(C.LANGUAGE, pa.string()),
    pa.field(C.INVENTORY, pa.string()),
    pa.field(C.AUDIO_PATH, pa.string(), nullable=False),
    pa.field(C.VIDEO_PATH, pa.string()),
    pa.field(C.ALIGNMENT_PATH, pa.string(), nullable=False),
    pa.field(C.ALIGNMENT_FORMAT, pa.string(), nullable=False),
    pa.field(C.LANDMARK_PATH, pa.string()),
    pa.field(C.SAMPLE_RATE, pa.int32(), nullable=False),
    pa.field(C.DURATION_S, pa.float64(), nullable=False),
    pa.field(C.FPS, pa.float32(), nullable=False),
    pa.field(C.N_FRAMES, pa.int32(), nullable=False),
    pa.field(C.CONTENT_HASH, pa.string(), nullable=False),
    pa.field(C.SPLIT, pa.string(), nullable=False),
])

PHONES = pa.schema([
    pa.field(C.UTTERANCE_ID, pa.string(), nullable=False),
    pa.field(C.INDEX, pa.int32(), nullable=False),   # interval number in the alignment file
    pa.field(C.PART, pa.int16(), nullable=False),    # sub-span of an interval mapped to several visemes
    pa.field(C.LABEL, pa.string(), nullable=False),
    pa.field(C.PHONEME, pa.string()),
    pa.field(C.VISEME, pa.string()),                 # null for silence and transparent phones
    pa.field(C.START_S, pa.float64(), nullable=False),
    pa.field(C.END_S, pa.float64(), nullable=False),
    pa.field(C.WORD, pa.string()),
    pa.field(C.WORD_INDEX, pa.int32()),
    pa.field(C.STRESS, pa.int8()),                   # ARPAbet stress digit or pinyin tone
])

CURVES = pa.schema(
    [
        pa.field(C.UTTERANCE_ID, pa.string(), nullable=False),
        pa.field(C.SOURCE, pa.string(), nullable=False),
        pa.field(C.VARIANT, pa.string(), nullable=False),
        pa.field(C.FRAME, pa.int32(), nullable=False),
        pa.field(C.TIME_S, pa.float64(), nullable=False),
    ]
    + [pa.field(v, pa.float32(), nullable=False) for v in VISEMES]
)

LOSS_TERMS = ("lmk", "rgb", "sup", "act", "flow", "diff", "range")

TRACKING_FRAMES = pa.schema(
    [
        pa.field(C.UTTERANCE_ID, pa.string(), nullable=False),
        pa.field(C.VARIANT, pa.string(), nullable=False),
        pa.field(C.FRAME, pa.int32(), nullable=False),
        pa.field(C.MOUTH_ERROR_PX, pa.float32()),          # null where no mouth landmark was detected
        pa.field(C.LANDMARKS_VALID, pa.bool_(), nullable=False),
        pa.field(C.FLOW_VALID_FRACTION, pa.float32()),     # null when L_flow is off
    ]
    + [pa.field(C.LOSS_PREFIX + t, pa.float32()) for t in LOSS_TERMS]   # unweighted; null when the term is off
    + [pa.field(c, pa.float32(), nullable=False) for c in C.POSE_COLUMNS]
)

METRICS = pa.schema(
    [
        pa.field(C.RUN, pa.string(), nullable=False),          # what produced the row: a training run, an evaluation
        pa.field(C.MODEL, pa.string(), nullable=False),
        pa.field(C.CONDITION, pa.string(), nullable=False),    # validation, train, volume, pitch, speed, noise, ...
        pa.field(C.UTTERANCE_ID, pa.string()),                  # null: the aggregate over the condition's utterances
        pa.field(C.EPOCH, pa.int32()),                          # null outside training
        pa.field(C.L1, pa.float64(), nullable=False),
        pa.field(C.L1_X100, pa.float64(), nullable=False),
    ]
    # per-viseme mean L1 of the aggregate rows, on the scale of `l1` (not x 100); null on per-utterance rows
    + [pa.field(C.L1_PREFIX + v, pa.float64()) for v in VISEMES]
)

REJECTS = pa.schema([
    pa.field(C.UTTERANCE_ID, pa.string()),
    pa.field(C.STAGE, pa.string(), nullable=False),
    pa.field(C.ERROR_TYPE, pa.string(), nullable=False),
    pa.field(C.MESSAGE, pa.string(), nullable=False),
    pa.field(C.PATH, pa.string()),
    pa.field(C.TIME, pa.timestamp("us", tz="UTC"), nullable=False),
])

TABLE_SCHEMAS: dict[str, pa.Schema] = {
    "utterances": UTTERANCES,
    "phones": PHONES,
    "rejects": REJECTS,
}


def table_from_rows(rows: Iterable[Mapping[str, object]], schema: pa.Schema) -> pa.Table:
    """A table of `schema` from row dicts keyed by column name; missing nullable columns become null."""
    rows = list(rows)
    columns = {f.name: [r.get(f.name) for r in rows] for f in schema}
    table = pa.Table.from_pydict(columns, schema=schema)
    for f in schema:
        if not f.nullable and table.column(f.name).null_count:
            raise ValueError(f"column {f.name!r} may not be null ({table.column(f.name).null_count} null rows)")
    return table


def curves_table(utterance_id: str, source: str, variant: str, curves: np.ndarray, fps: float) -> pa.Table:
    """The wide `curves` table of one utterance from a (frames, 16) array sampled at frame k / fps."""
    curves = np.asarray(curves)
    if curves.ndim != 2 or curves.shape[1] != N_VISEMES:
        raise ValueError(f"{utterance_id}: curves must have shape (frames, {N_VISEMES}), got {curves.shape}")
    if source not in CURVE_SOURCES:
        raise ValueError(f"{utterance_id}: curve source {source!r} is not one of {CURVE_SOURCES}")
    n = curves.shape[0]
    frames = np.arange(n, dtype=np.int32)
    columns = [
        pa.array(np.full(n, utterance_id, dtype=object), pa.string()),
        pa.array(np.full(n, source, dtype=object), pa.string()),
        pa.array(np.full(n, variant, dtype=object), pa.string()),
        pa.array(frames),
        pa.array(frames / float(fps)),
    ] + [pa.array(np.ascontiguousarray(curves[:, i], dtype=np.float32)) for i in range(N_VISEMES)]
    return pa.Table.from_arrays(columns, schema=CURVES)


def curves_array(table: pa.Table) -> np.ndarray:
    """(frames, 16) float32 array of a curves table, in frame order as stored."""
    return np.stack([table.column(v).to_numpy() for v in VISEMES], axis=1).astype(np.float32, copy=False)
