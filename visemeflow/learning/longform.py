"""Curves of long audio in bounded memory: the file is read and predicted in chunks, each with context on both
sides, and only each chunk's centre is kept.

Why chunks: a model sees the whole input at once (the BLSTM runs over every frame, the encoders' outputs of every
window are held), so memory grows with the file: two hours of audio took 6.7 GB. In chunks of ``chunk_s`` seconds
read from the file as they are needed, the peak is that of one chunk whatever the length.

Why context: the decoder is bidirectional, so a frame's curves depend on audio around it. Each chunk is predicted
with ``context_s`` seconds of audio before and after it, and that margin is dropped; a frame at a seam sees at
least ``context_s`` seconds on either side, as it does inside a whole-file run. Features normalised over each
input (fbank's ``normalize``) see a chunk's statistics instead of the file's: the previous default's curves of
3 minutes of speech move by 0.005 on average, 0.044 at most (tests/test_longform.py); ``bench/memory.py`` measures
the peak memory and the difference for the default model: Whisper's features depend on where the speech sits in
its 30-s window, so its chunked curves differ from a whole-file run by 0.014 on average (single frames up to 0.7)
while they match the animator's curves of a 112-s take as well (README). With the defaults (50 s + 2 x 5 s) a
chunk is three Whisper windows.

Frames: frame ``k`` of the result is the time ``k / fps``, as :func:`visemeflow.learning.train.predict_curves`
gives for the whole file; chunk boundaries fall on whole frames, and a chunk's audio starts at the sample nearest
its first (context) frame, so every chunk's frame times line up with the whole file's.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

import numpy as np

from visemeflow.visemes import N_VISEMES

__all__ = ["CHUNK_S", "CONTEXT_S", "AudioSource", "predict_long"]

CHUNK_S = 50.0
CONTEXT_S = 5.0


class AudioSource(Protocol):
    """Mono float32 samples of a file, read by range (``visemeflow.ingest.audio.AudioFile`` is one)."""

    rate: int
    n_samples: int

    def read(self, start: int, stop: int) -> np.ndarray:
        """(stop - start,) float32 samples ``[start, stop)``, mono."""
        ...


class _ArraySource:
    def __init__(self, samples: np.ndarray, rate: int) -> None:
        self.samples, self.rate, self.n_samples = samples, int(rate), len(samples)

    def read(self, start: int, stop: int) -> np.ndarray:
        return self.samples[start:stop]


def predict_long(predict: Callable[[np.ndarray, int, int], np.ndarray], source: AudioSource | np.ndarray,
                 fps: float, sample_rate: int | None = None, chunk_s: float = CHUNK_S, context_s: float = CONTEXT_S,
                 on_chunk: Callable[[int, int], None] | None = None) -> np.ndarray:
    """(round(duration * fps), 16) float32 curves of `source`, predicted chunk by chunk.

    `predict(samples, rate, n_frames)` gives the curves of a piece of audio (frame k at k / fps from the piece's
    first sample), e.g. ``lambda a, r, n: predict_curves(model, a, r, fps, n_frames=n)``. `source` is an
    :class:`AudioSource` or an array of samples (then `sample_rate` is required). Audio no longer than one chunk
    plus its context is predicted in one piece, exactly as the whole file. `on_chunk(done, total)` reports progress.
    """
    if isinstance(source, np.ndarray):
        if sample_rate is None:
            raise ValueError("predict_long needs sample_rate with an array of samples")
        source = _ArraySource(source, sample_rate)
    if not (chunk_s > 0 and context_s >= 0 and fps > 0):
        raise ValueError(f"need chunk_s > 0, context_s >= 0, fps > 0; got {chunk_s}, {context_s}, {fps}")
    rate, n_samples = source.rate, source.n_samples
    total = round(n_samples / rate * fps)
    if total <= 0:
        return np.zeros((0, N_VISEMES), np.float32)
    step, ctx = max(1, round(chunk_s * fps)), round(context_s * fps)
    if total <= step + 2 * ctx:
        out = predict(source.read(0, n_samples), rate, total)
        if on_chunk:
            on_chunk(1, 1)
        return np.asarray(out, np.float32)
    chunks = math.ceil(total / step)
    out = np.empty((total, N_VISEMES), np.float32)
    for i in range(chunks):
        f0, f1 = i * step, min(total, (i + 1) * step)
        # Every piece is a full chunk plus context, shifted inward at the ends of the file: a short last piece
        # would be normalised over a few seconds only (features with per-input statistics drift on it).
        a0 = min(max(0, f0 - ctx), total - (step + 2 * ctx))
        a1 = a0 + step + 2 * ctx
        s0, s1 = round(a0 * rate / fps), min(n_samples, round(a1 * rate / fps))
        piece = predict(source.read(s0, s1), rate, a1 - a0)
        out[f0:f1] = piece[f0 - a0: f1 - a0]
        if on_chunk:
            on_chunk(i + 1, chunks)
    return out
