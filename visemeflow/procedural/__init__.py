"""JALI-like procedural viseme curves from timed viseme segments (paper 4.1)."""

from visemeflow.procedural.config import ProceduralConfig
from visemeflow.procedural.jali import (
    DEFAULT_CONFIG,
    ArticulationKeys,
    KeyFrames,
    apply_word_lookahead,
    bridge_tongue_only,
    combine_channels,
    generate_procedural_curves,
    key_envelopes,
    key_frames,
    merge_repeated_visemes,
    merge_with_holds,
    peak_amplitudes,
    segment_keys,
    smoothstep,
)

__all__ = [
    "DEFAULT_CONFIG",
    "ArticulationKeys",
    "KeyFrames",
    "ProceduralConfig",
    "apply_word_lookahead",
    "bridge_tongue_only",
    "combine_channels",
    "generate_procedural_curves",
    "key_envelopes",
    "key_frames",
    "merge_repeated_visemes",
    "merge_with_holds",
    "peak_amplitudes",
    "segment_keys",
    "smoothstep",
]
