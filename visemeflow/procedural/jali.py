"""JALI-like procedural viseme curves (Edwards et al. 2016; paper 4.1) from timed viseme segments.

Each (merged) segment becomes an articulation key: a smooth onset ramp up to the apex at the segment start, a
sustain at the peak, and a smooth decay. The rules below adjust key timing and amplitude by viseme class
and context; the curve of a viseme channel is the maximum of its keys' envelopes.
"""

from collections.abc import Sequence
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from visemeflow.articulation import close_lips
from visemeflow.phonetics.types import VisemeSegment
from visemeflow.procedural.config import ProceduralConfig
from visemeflow.visemes import N_VISEMES, VISEMES, viseme_index

DEFAULT_CONFIG = ProceduralConfig()

# Slack added to a closure's one-frame hold so float rounding of k / fps cannot skip the peak frame.
_FRAME_HOLD_SLACK_S = 1e-9
# Stand-in for a zero-length ramp, so a ramp of length 0 becomes a step instead of a division by zero.
_MIN_RAMP_S = 1e-12


class ArticulationKeys(NamedTuple):
    """One key per (merged) segment, all arrays (keys,); the apex is at `start_s`; `word` is -1 for none."""

    channel: np.ndarray
    start_s: np.ndarray
    end_s: np.ndarray
    word: np.ndarray
    onset_start_s: np.ndarray
    sustain_end_s: np.ndarray
    decay_end_s: np.ndarray
    peak: np.ndarray


class ChannelTable(NamedTuple):
    """Per-viseme rule constants, all arrays (16,), indexed by viseme column."""

    onset_s: np.ndarray
    sustain_fraction: np.ndarray
    decay_s: np.ndarray
    is_closure: np.ndarray
    is_tongue: np.ndarray
    is_lip_heavy: np.ndarray
    is_blocker: np.ndarray


def _mask(names: frozenset[str]) -> np.ndarray:
    """Boolean (16,) mask of the visemes in `names`."""
    return np.array([v in names for v in VISEMES], dtype=bool)


@lru_cache(maxsize=64)
def channel_table(config: ProceduralConfig) -> ChannelTable:
    """Rule constants per viseme column (cached: the config is frozen and hashable)."""
    lip = _mask(config.lip_heavy)
    closure = _mask(config.closure_visemes)
    onset = np.where(lip, config.lip_onset_s, config.onset_s)
    decay = np.where(lip, config.lip_decay_s, config.decay_s)
    if config.closure_onset_s is not None:
        onset = np.where(closure, config.closure_onset_s, onset)
    if config.closure_decay_s is not None:
        decay = np.where(closure, config.closure_decay_s, decay)
    return ChannelTable(
        onset_s=onset,
        sustain_fraction=np.where(lip, config.lip_sustain_fraction, config.sustain_fraction),
        decay_s=decay,
        is_closure=_mask(config.closure_visemes),
        is_tongue=_mask(config.tongue_only),
        is_lip_heavy=lip,
        is_blocker=_mask(config.lookahead_blockers),
    )


def merge_with_holds(segments: Sequence[VisemeSegment], max_gap_s: float) -> tuple[list[VisemeSegment], np.ndarray]:
    """Merged segments (see `merge_repeated_visemes`) and, per merged segment, the start of its last part (s).

    The articulation is held through every part: the sustain of a merged segment lasts at least as long as its
    last part's own sustain would, so "pop man" keeps the lips closed from the p to the m.
    """
    merged: list[VisemeSegment] = []
    last_start: list[float] = []
    for seg in segments:
        prev = merged[-1] if merged else None
        if prev is not None and prev.viseme == seg.viseme and seg.start_s - prev.end_s <= max_gap_s:
            phoneme = "+".join(p for p in (prev.phoneme, seg.phoneme) if p)
            merged[-1] = VisemeSegment(prev.viseme, prev.start_s, max(prev.end_s, seg.end_s),
                                       prev.word_index, phoneme)
            last_start[-1] = seg.start_s
        else:
            merged.append(seg)
            last_start.append(seg.start_s)
    return merged, np.asarray(last_start, np.float64)


def merge_repeated_visemes(segments: Sequence[VisemeSegment], max_gap_s: float) -> list[VisemeSegment]:
    """Merge consecutive segments of one viseme at most `max_gap_s` apart ("pop man": one MBP closure)."""
    return merge_with_holds(segments, max_gap_s)[0]


def peak_amplitudes(channel: np.ndarray, duration_s: np.ndarray, config: ProceduralConfig) -> np.ndarray:
    """Peak per key (keys,): closures 1, tongue-only `tongue_peak`, others scaled down when short."""
    table = channel_table(config)
    peak = np.clip(duration_s / config.full_peak_duration_s, config.min_peak, 1.0)
    peak = np.where(table.is_tongue[channel], config.tongue_peak, peak)
    return np.where(table.is_closure[channel], 1.0, peak)


def segment_keys(
    segments: Sequence[VisemeSegment], fps: float, config: ProceduralConfig, last_part_start_s: np.ndarray | None = None
) -> ArticulationKeys:
    """One articulation key per segment, with class-dependent onset, sustain, decay and peak.

    `last_part_start_s` (from `merge_with_holds`) keeps a merged segment at its peak through its last part.
    """
    n = len(segments)
    channel = np.fromiter((viseme_index(s.viseme) for s in segments), np.intp, n)
    start = np.fromiter((s.start_s for s in segments), np.float64, n)
    end = np.fromiter((s.end_s for s in segments), np.float64, n)
    word = np.fromiter((-1 if s.word_index is None else s.word_index for s in segments), np.int64, n)
    if np.any(end < start) or np.any(np.diff(start) < 0):
        raise ValueError("segments must be sorted by start time and have end_s >= start_s")
    table = channel_table(config)
    duration = end - start
    sustain_end = start + table.sustain_fraction[channel] * duration
    apex = start
    if last_part_start_s is not None:
        apex = np.asarray(last_part_start_s, np.float64)
        sustain_end = np.maximum(sustain_end, apex + table.sustain_fraction[channel] * (end - apex))
    # A closure shorter than a frame would otherwise fall between two samples and never show.
    held = apex + 1.0 / fps + _FRAME_HOLD_SLACK_S
    sustain_end = np.where(table.is_closure[channel], np.maximum(sustain_end, held), sustain_end)
    return ArticulationKeys(
        channel=channel, start_s=start, end_s=end, word=word,
        onset_start_s=start - table.onset_s[channel],
        sustain_end_s=sustain_end,
        decay_end_s=sustain_end + table.decay_s[channel],
        peak=peak_amplitudes(channel, duration, config),
    )


def bridge_tongue_only(keys: ArticulationKeys, config: ProceduralConfig) -> ArticulationKeys:
    """Hold the preceding non-tongue key at its peak through a short run of tongue-only keys."""
    is_tongue = channel_table(config).is_tongue[keys.channel]
    lips = np.flatnonzero(~is_tongue)
    before, after = lips[:-1], lips[1:]
    bridged = (after - before > 1) & (keys.start_s[after] - keys.end_s[before] <= config.max_bridge_s)
    before, after = before[bridged], after[bridged]
    sustain_end = keys.sustain_end_s.copy()
    sustain_end[before] = np.maximum(sustain_end[before], keys.start_s[after])
    decay_end = sustain_end + (keys.decay_end_s - keys.sustain_end_s)
    return keys._replace(sustain_end_s=sustain_end, decay_end_s=decay_end)


def apply_word_lookahead(keys: ArticulationKeys, config: ProceduralConfig) -> ArticulationKeys:
    """Start a lip-heavy key's onset at its word start when nothing earlier in the word blocks the lips."""
    table = channel_table(config)
    n = len(keys.channel)
    index = np.arange(n)
    new_word = np.ones(n, dtype=bool)
    new_word[1:] = keys.word[1:] != keys.word[:-1]
    new_word |= keys.word < 0
    first = np.maximum.accumulate(np.where(new_word, index, 0))
    blockers_before = np.concatenate(([0], np.cumsum(table.is_blocker[keys.channel])[:-1]))
    unblocked = blockers_before == blockers_before[first]
    anticipates = table.is_lip_heavy[keys.channel] & (keys.word >= 0) & (first < index) & unblocked
    earliest = np.maximum(keys.start_s[first], keys.start_s - config.max_lookahead_s)
    onset_start = np.where(anticipates, np.minimum(keys.onset_start_s, earliest), keys.onset_start_s)
    return keys._replace(onset_start_s=onset_start)


def smoothstep(x: np.ndarray) -> np.ndarray:
    """Hermite ease 3x^2 - 2x^3 of x clipped to [0, 1]; exactly 0 at 0 and 1 at 1."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


class KeyFrames(NamedTuple):
    """The frames each key can touch, flattened to (samples,): owning key and frame number."""

    key: np.ndarray
    frame: np.ndarray


def key_frames(keys: ArticulationKeys, n_frames: int, fps: float) -> KeyFrames:
    """Frames within (a frame of) each key's support; keys x support instead of keys x all frames."""
    # One frame of margin each side: the envelope is exactly 0 there, so rounding cannot drop a frame.
    first = np.clip(np.floor(keys.onset_start_s * fps).astype(np.int64), 0, n_frames)
    last = np.clip(np.ceil(keys.decay_end_s * fps).astype(np.int64) + 1, 0, n_frames)
    counts = np.maximum(last - first, 0)
    key = np.repeat(np.arange(len(counts)), counts)
    offsets = np.cumsum(counts) - counts
    frame = first[key] + (np.arange(len(key)) - offsets[key])
    return KeyFrames(key=key, frame=frame)


def key_envelopes(keys: ArticulationKeys, key: np.ndarray, times_s: np.ndarray) -> np.ndarray:
    """Envelope of key `key[i]` at `times_s[i]`, (samples,); exactly 0 outside [onset start, decay end]."""
    start, sustain_end = keys.start_s[key], keys.sustain_end_s[key]
    rise_len = np.maximum(start - keys.onset_start_s[key], _MIN_RAMP_S)
    fall_len = np.maximum(keys.decay_end_s[key] - sustain_end, _MIN_RAMP_S)
    # Measured from the apex, so the apex itself is exactly 1 even for a zero-length onset.
    rise = smoothstep(1.0 + (times_s - start) / rise_len)
    fall = 1.0 - smoothstep((times_s - sustain_end) / fall_len)
    return keys.peak[key] * np.minimum(rise, fall)


def combine_channels(channel: np.ndarray, frame: np.ndarray, values: np.ndarray, n_frames: int) -> np.ndarray:
    """Per-viseme maximum of envelope samples at (frame, channel) -> curves (frames, 16) float32 in [0, 1]."""
    curves = np.zeros((n_frames, N_VISEMES), dtype=np.float32)
    flat = curves.reshape(-1)
    np.maximum.at(flat, frame * N_VISEMES + channel, np.clip(values, 0.0, 1.0).astype(np.float32))
    return curves


def generate_procedural_curves(
    segments: Sequence[VisemeSegment],
    n_frames: int,
    fps: float,
    config: ProceduralConfig = DEFAULT_CONFIG,
) -> np.ndarray:
    """Procedural viseme curves (frames, 16) float32 in [0, 1]; frame k is sampled at k / fps.

    `segments` are sorted, non-overlapping, real visemes only (silence and transparent phones removed). With
    `config.closure_rule` (the default) the lip rules of `visemeflow.articulation.close_lips` are applied last.
    """
    if n_frames < 0 or not fps > 0:
        raise ValueError(f"need n_frames >= 0 and fps > 0, got n_frames={n_frames}, fps={fps}")
    merged, last_part_start = merge_with_holds(segments, config.merge_max_gap_s)
    if not merged or n_frames == 0:
        return np.zeros((n_frames, N_VISEMES), dtype=np.float32)
    keys = segment_keys(merged, fps, config, last_part_start)
    keys = bridge_tongue_only(keys, config)
    keys = apply_word_lookahead(keys, config)
    samples = key_frames(keys, n_frames, fps)
    values = key_envelopes(keys, samples.key, samples.frame / fps)
    curves = combine_channels(keys.channel[samples.key], samples.frame, values, n_frames)
    return close_lips(curves) if config.closure_rule else curves
