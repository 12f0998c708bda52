"""`Curves`: one utterance's viseme curves as a value that carries its frame rate.

Curves used to travel as a pyarrow table, an ``(array, fps)`` pair or a ``CurveTrack``, with the rate written to the
Parquet file's metadata that nothing read back, and guessed again from the frame times in two places with different
fallbacks. A :class:`Curves` is the array, its rate and what it belongs to; :meth:`Curves.to_table` and
:meth:`Curves.from_table` are the one conversion, and the store returns and takes it (`Store.load_curves`,
`Store.save_curves`).

The rate of a stored table, in order: the file's ``visemeflow.fps`` metadata (every writer since it existed sets
it); else the frame times, ``(n - 1) / time_s[-1]`` for two or more frames (frames are at ``k / fps``, so this is
exact up to float rounding, kept to 6 decimals); else the ``default`` given (a one-frame table has no spacing).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa

from visemeflow.schemas.tables import CURVES, C, curves_array, curves_table
from visemeflow.timebase import DEFAULT_FPS
from visemeflow.visemes import N_VISEMES

__all__ = ["FPS_KEY", "PROVENANCE_KEY", "Curves", "fps_of_table"]

FPS_KEY = b"visemeflow.fps"               # Parquet schema metadata: the curves' frame rate, repr(float)
PROVENANCE_KEY = b"visemeflow.provenance"  # Parquet schema metadata: what made the curves


def fps_of_table(table: pa.Table, default: float = DEFAULT_FPS) -> float:
    """The frame rate of a curves table (module docstring: metadata, then frame times, then ``default``)."""
    meta = table.schema.metadata or {}
    if FPS_KEY in meta:
        fps = float(meta[FPS_KEY].decode())
        if math.isfinite(fps) and fps > 0:
            return fps
    if table.num_rows > 1:
        last = float(table.column(C.TIME_S)[-1].as_py())
        if last > 0:
            return round((table.num_rows - 1) / last, 6)
    return float(default)


@dataclass(frozen=True)
class Curves:
    """``values`` (frames, 16) float32 at ``fps`` frames per second (frame ``k`` at time ``k / fps``) of one
    utterance, from one ``source`` (a `CurveSource`) and ``variant``; ``provenance`` says what made them."""

    values: np.ndarray
    fps: float
    utterance_id: str
    source: str
    variant: str
    provenance: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        values = np.asarray(self.values, dtype=np.float32)
        if values.ndim != 2 or values.shape[1] != N_VISEMES:
            raise ValueError(f"{self.utterance_id}: curves must have shape (frames, {N_VISEMES}), got {values.shape}")
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"{self.utterance_id}: frame rate must be positive and finite, got {self.fps}")
        object.__setattr__(self, "values", values)
        object.__setattr__(self, "fps", float(self.fps))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Curves):
            return NotImplemented
        return ((self.fps, self.utterance_id, self.source, self.variant)
                == (other.fps, other.utterance_id, other.source, other.variant)
                and np.array_equal(self.values, other.values))

    __hash__ = None  # type: ignore[assignment]  # an array inside: equal by value, not hashable

    @property
    def n_frames(self) -> int:
        return int(self.values.shape[0])

    @property
    def duration_s(self) -> float:
        """Seconds the frames cover: ``n_frames / fps``."""
        return self.n_frames / self.fps

    def to_table(self) -> pa.Table:
        """The wide `curves` table, with the rate and provenance in its schema metadata (as the store writes it)."""
        table = curves_table(self.utterance_id, self.source, self.variant, self.values, self.fps)
        return table.replace_schema_metadata({FPS_KEY: repr(self.fps).encode(),
                                              PROVENANCE_KEY: self.provenance.encode()})

    @classmethod
    def from_table(cls, table: pa.Table, default_fps: float = DEFAULT_FPS) -> Curves:
        """The curves of a one-utterance `curves` table; its rate as :func:`fps_of_table` finds it."""
        table = table if table.schema.equals(CURVES) else table.cast(CURVES).replace_schema_metadata(
            table.schema.metadata)
        key = []
        for column in (C.UTTERANCE_ID, C.SOURCE, C.VARIANT):
            values = table.column(column).unique().to_pylist()
            if len(values) != 1:
                raise ValueError(f"a Curves value holds one utterance, source and variant; {column} has {values[:3]}")
            key.append(values[0])
        meta = table.schema.metadata or {}
        return cls(curves_array(table), fps_of_table(table, default_fps), key[0], key[1], key[2],
                   meta.get(PROVENANCE_KEY, b"").decode())
