"""JALI-like procedural viseme curves from timed viseme segments (paper 4.1).

The names below are imported from their modules on first use, so `procedural.config` (read by the CLI and the
flows' parameters) imports without the curve code and numpy."""

from visemeflow.lazy import lazy_exports

_EXPORTS = {
    "ProceduralConfig": ".config",
    **dict.fromkeys((
        "DEFAULT_CONFIG", "ArticulationKeys", "KeyFrames", "apply_word_lookahead", "bridge_tongue_only",
        "combine_channels", "generate_procedural_curves", "key_envelopes", "key_frames", "merge_repeated_visemes",
        "merge_with_holds", "peak_amplitudes", "segment_keys", "smoothstep",
    ), ".jali"),
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS)
