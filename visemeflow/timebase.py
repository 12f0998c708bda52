"""Frame clock shared by every stage: frame k of a curve is sampled at time k / fps."""

import math

DEFAULT_FPS = 30.0
"""The curve rate wherever none is given: audio-only utterances at ingest, predictions, exports, model heads."""


def frame_count(duration_s: float, fps: float) -> int:
    """Number of frames covering `duration_s` at `fps` (at least one)."""
    if not (math.isfinite(duration_s) and duration_s >= 0):
        raise ValueError(f"duration must be a finite non-negative number of seconds, got {duration_s!r}")
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps!r}")
    return max(1, int(round(duration_s * fps)))
