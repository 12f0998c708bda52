"""JALI-like procedural viseme curves: one test per rule, config validation, and property tests."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from visemeflow.phonetics.types import VisemeSegment
from visemeflow.procedural import (
    ProceduralConfig,
    apply_word_lookahead,
    bridge_tongue_only,
    generate_procedural_curves,
    key_envelopes,
    merge_repeated_visemes,
    merge_with_holds,
    peak_amplitudes,
    segment_keys,
    smoothstep,
)
from visemeflow.articulation import close_lips
from visemeflow.visemes import N_VISEMES, VISEMES, viseme_index

CFG = ProceduralConfig()
RAW = ProceduralConfig(closure_rule=False)   # the JALI key rules alone, before the lip rules of articulation.py
FINE_FPS = 1000.0  # 1 ms frames: timing checks do not depend on where frames happen to fall


def seg(viseme: str, start: float, end: float, word: int | None = 0) -> VisemeSegment:
    return VisemeSegment(viseme, start, end, word)


def channel(segments, viseme: str, seconds: float = 2.0, fps: float = FINE_FPS, config=RAW) -> np.ndarray:
    """One viseme's curve (frames,) by the key rules alone (the lip rules are tested on their own)."""
    curves = generate_procedural_curves(segments, int(round(seconds * fps)), fps, config)
    return curves[:, viseme_index(viseme)]


def at(curve: np.ndarray, t: float, fps: float = FINE_FPS) -> float:
    return float(curve[int(round(t * fps))])


# --- rule 1: merge -------------------------------------------------------------------------------


def test_merge_joins_same_viseme_across_short_gap_pop_man():
    # "pop man": final /p/ of pop (word 0) and /m/ of man (word 1), 10 ms apart
    segments = [seg("MBP", 0.10, 0.16, 0), seg("OHH", 0.16, 0.30, 0), seg("MBP", 0.30, 0.36, 0),
                seg("MBP", 0.37, 0.45, 1), seg("AHH", 0.45, 0.60, 1)]
    merged = merge_repeated_visemes(segments, 0.05)
    assert [s.viseme for s in merged] == ["MBP", "OHH", "MBP", "AHH"]
    assert (merged[2].start_s, merged[2].end_s, merged[2].word_index) == (0.30, 0.45, 0)
    # one closure: the MBP curve stays at 1 from the apex of p through m, with no dip between
    mbp = channel(segments, "MBP")
    assert np.all(mbp[int(0.30 * FINE_FPS):int((0.30 + 0.75 * 0.15) * FINE_FPS)] == 1.0)


def test_merge_keeps_apart_distant_or_different_visemes_and_chains():
    far = [seg("MBP", 0.0, 0.1), seg("MBP", 0.2, 0.3)]
    assert len(merge_repeated_visemes(far, 0.05)) == 2
    different = [seg("MBP", 0.0, 0.1), seg("FFF", 0.1, 0.2)]
    assert len(merge_repeated_visemes(different, 0.05)) == 2
    chain = [seg("SSS", 0.0, 0.1), seg("SSS", 0.12, 0.2), seg("SSS", 0.22, 0.3)]
    assert [(s.start_s, s.end_s) for s in merge_repeated_visemes(chain, 0.05)] == [(0.0, 0.3)]


# --- rule 2: envelope timing ---------------------------------------------------------------------


def test_envelope_zero_before_onset_peak_at_apex_sustain_then_decay_to_zero():
    start, end = 1.0, 1.2
    ahh = channel([seg("AHH", start, end)], "AHH")
    onset, sustain_end = start - CFG.onset_s, start + CFG.sustain_fraction * (end - start)
    decay_end = sustain_end + CFG.decay_s
    t = np.arange(len(ahh)) / FINE_FPS
    assert np.all(ahh[t < onset - 1e-6] == 0.0)
    assert np.all(np.diff(ahh[(t > onset) & (t < start)]) > 0)  # rising
    assert at(ahh, start) == 1.0  # apex at the start of the sound
    assert np.all(ahh[(t >= start) & (t <= sustain_end - 1e-6)] == 1.0)
    assert np.all(np.diff(ahh[(t > sustain_end) & (t < decay_end)]) < 0)  # decaying
    assert np.all(ahh[t > decay_end + 1e-6] == 0.0)
    # smooth, not linear: ease-in at a quarter of the ramp, half-way at the middle
    assert at(ahh, onset + 0.25 * CFG.onset_s) == pytest.approx(smoothstep(np.array(0.25)), abs=1e-6)
    assert at(ahh, onset + 0.25 * CFG.onset_s) < 0.2
    assert at(ahh, onset + 0.5 * CFG.onset_s) == pytest.approx(0.5, abs=1e-6)


def test_smoothstep_ends_exactly():
    x = np.array([-1.0, 0.0, 0.5, 1.0, 2.0])
    assert smoothstep(x).tolist() == [0.0, 0.0, 0.5, 1.0, 1.0]


# --- rule 3: lip-heavy timing --------------------------------------------------------------------


def test_lip_heavy_starts_earlier_and_releases_later_than_plain_viseme():
    start, end = 1.0, 1.2
    uuu = channel([seg("UUU", start, end)], "UUU")
    ahh = channel([seg("AHH", start, end)], "AHH")
    between_onsets = start - (CFG.onset_s + CFG.lip_onset_s) / 2
    assert at(uuu, between_onsets) > 0.0 and at(ahh, between_onsets) == 0.0
    assert np.flatnonzero(uuu)[0] < np.flatnonzero(ahh)[0]
    late_sustain = start + 0.85 * (end - start)  # past AHH's 0.75 sustain, inside UUU's 0.9
    assert at(uuu, late_sustain) == 1.0 and at(ahh, late_sustain) < 1.0
    assert np.flatnonzero(uuu)[-1] > np.flatnonzero(ahh)[-1]


def test_closure_ramps_of_their_own_shorten_only_the_closures():
    """`closure_onset_s`/`closure_decay_s` (training targets whose closures stay out of the neighbouring phones):
    MBP rises and falls within them; other visemes keep theirs; None keeps the general ramps."""
    start, end = 1.0, 1.1
    short = RAW.model_copy(update={"closure_onset_s": 0.04, "closure_decay_s": 0.05})
    mbp = channel([seg("MBP", start, end)], "MBP", config=short)
    first, last = np.flatnonzero(mbp)[[0, -1]] / FINE_FPS
    sustain_end = start + RAW.sustain_fraction * (end - start)
    assert first == pytest.approx(start - 0.04, abs=2e-3) and last == pytest.approx(sustain_end + 0.05, abs=2e-3)
    default = channel([seg("MBP", start, end)], "MBP")
    assert np.flatnonzero(default)[0] / FINE_FPS == pytest.approx(start - RAW.onset_s, abs=2e-3)
    ahh = channel([seg("AHH", start, end)], "AHH", config=short)
    assert np.array_equal(ahh, channel([seg("AHH", start, end)], "AHH"))


# --- rule 4: closures full, short vowels lighter --------------------------------------------------


@pytest.mark.parametrize("fps", [25.0, 30.0, 60.0])
@pytest.mark.parametrize("viseme", ["MBP", "FFF"])
def test_short_closure_reaches_full_amplitude_on_a_sampled_frame(fps, viseme):
    for phase in np.linspace(0.0, 1.0, 17):  # every position of the 20 ms closure relative to the frames
        start = 0.5 + phase / fps
        curve = channel([seg(viseme, start, start + 0.020)], viseme, fps=fps)
        assert curve.max() == 1.0, (fps, phase)


def test_short_vowel_is_lighter_than_long_vowel():
    durations = np.array([0.02, 0.04, 0.06, 0.08, 0.3])
    ahh = np.full(len(durations), viseme_index("AHH"))
    assert peak_amplitudes(ahh, durations, CFG).tolist() == pytest.approx([0.5, 0.5, 0.75, 1.0, 1.0])
    mbp = np.full(len(durations), viseme_index("MBP"))
    assert peak_amplitudes(mbp, durations, CFG).tolist() == [1.0] * len(durations)
    short = channel([seg("AHH", 1.0, 1.03)], "AHH")
    long = channel([seg("AHH", 1.0, 1.2)], "AHH")
    assert short.max() == pytest.approx(0.5) and long.max() == 1.0


# --- rule 5: tongue-only --------------------------------------------------------------------------


def test_tongue_only_has_reduced_peak():
    assert channel([seg("LNTD", 1.0, 1.2)], "LNTD").max() == pytest.approx(CFG.tongue_peak)
    assert channel([seg("GK", 1.0, 1.2)], "GK").max() == pytest.approx(CFG.tongue_peak)


def test_tongue_only_run_keeps_preceding_lip_shape():
    segments = [seg("AHH", 0.20, 0.40), seg("LNTD", 0.40, 0.46), seg("AHH", 0.46, 0.70)]
    keys = bridge_tongue_only(segment_keys(segments, FINE_FPS, CFG), CFG)
    assert keys.sustain_end_s[0] == pytest.approx(0.46)
    assert keys.decay_end_s[0] == pytest.approx(0.46 + CFG.decay_s)
    ahh = channel(segments, "AHH")
    assert np.all(ahh[int(0.20 * FINE_FPS):int(0.62 * FINE_FPS)] == 1.0)  # high through the LNTD
    unbridged = channel(segments, "AHH", config=CFG.model_copy(update={"max_bridge_s": 0.0}))
    assert unbridged[int(0.40 * FINE_FPS):int(0.46 * FINE_FPS)].min() < 0.8


def test_tongue_only_run_too_long_is_not_bridged():
    segments = [seg("AHH", 0.20, 0.40), seg("LNTD", 0.40, 0.60), seg("GK", 0.60, 0.80), seg("AHH", 0.80, 1.0)]
    keys = bridge_tongue_only(segment_keys(segments, FINE_FPS, CFG), CFG)
    assert keys.sustain_end_s[0] == pytest.approx(0.20 + CFG.sustain_fraction * 0.2)
    assert at(channel(segments, "AHH"), 0.60) == 0.0


# --- rule 6: word look-ahead ----------------------------------------------------------------------


def stew(uuu_word: int) -> list[VisemeSegment]:
    return [seg("SSS", 0.50, 0.62, 3), seg("LNTD", 0.62, 0.70, 3), seg("UUU", 0.70, 0.95, uuu_word)]


def test_lookahead_lip_heavy_anticipates_from_word_start():
    uuu = channel(stew(uuu_word=3), "UUU")
    normal_onset = 0.70 - CFG.lip_onset_s
    t = np.arange(len(uuu)) / FINE_FPS
    assert np.all(uuu[(t > 0.50 + 1e-6) & (t < normal_onset)] > 0.0)  # rounding from the /s/ on
    assert np.all(uuu[t < 0.50 - 1e-6] == 0.0)  # not before the word
    keys = apply_word_lookahead(segment_keys(stew(3), FINE_FPS, CFG), CFG)
    assert keys.onset_start_s[2] == pytest.approx(0.50)


def test_no_lookahead_across_word_boundary():
    uuu = channel(stew(uuu_word=4), "UUU")
    t = np.arange(len(uuu)) / FINE_FPS
    assert np.all(uuu[t < 0.70 - CFG.lip_onset_s - 1e-6] == 0.0)


def test_no_lookahead_past_a_lip_closure_in_the_word():
    segments = [seg("MBP", 0.50, 0.62), seg("LNTD", 0.62, 0.70), seg("UUU", 0.70, 0.95)]
    uuu = channel(segments, "UUU")
    assert at(uuu, 0.70 - CFG.lip_onset_s - 0.01) == 0.0


def test_lookahead_is_capped_before_own_start():
    segments = [seg("AHH", 0.0, 0.5), seg("LNTD", 0.5, 0.6), seg("UUU", 0.6, 0.8)]
    uuu = channel(segments, "UUU")
    earliest = 0.6 - CFG.max_lookahead_s
    assert at(uuu, earliest - 0.01) == 0.0 and at(uuu, earliest + 0.02) > 0.0


# --- rule 7: combination --------------------------------------------------------------------------


def test_channel_is_max_of_keys_and_silence_is_exactly_zero():
    segments = [seg("AHH", 0.5, 0.7, 0), seg("AHH", 3.0, 3.03, 1)]
    fps = 30.0
    curves = generate_procedural_curves(segments, 150, fps)
    assert curves.shape == (150, N_VISEMES) and curves.dtype == np.float32 and curves.flags.c_contiguous
    ahh = curves[:, viseme_index("AHH")]
    assert ahh.max() == 1.0 and ahh[int(3.0 * fps)] == pytest.approx(0.5)
    assert np.all(curves[int(1.2 * fps):int(2.6 * fps)] == 0.0)
    others = np.delete(curves, viseme_index("AHH"), axis=1)
    assert np.all(others == 0.0)


def test_empty_input_gives_zeros():
    assert generate_procedural_curves([], 10, 30.0).tolist() == np.zeros((10, 16)).tolist()
    assert generate_procedural_curves([seg("AHH", 0.0, 0.1)], 0, 30.0).shape == (0, N_VISEMES)


def test_rejects_unknown_viseme_and_unsorted_segments():
    with pytest.raises(ValueError, match="unknown viseme"):
        generate_procedural_curves([seg("sil", 0.0, 0.1)], 10, 30.0)
    with pytest.raises(ValueError, match="sorted"):
        generate_procedural_curves([seg("AHH", 0.5, 0.6), seg("EH", 0.1, 0.2)], 30, 30.0)


# --- config ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("field", ["onset_s", "decay_s", "lip_onset_s", "lip_decay_s", "merge_max_gap_s",
                                   "max_bridge_s", "max_lookahead_s"])
def test_config_rejects_negative_times(field):
    with pytest.raises(ValidationError, match=rf"{field}\n\s+Input should be greater than or equal to 0"):
        ProceduralConfig(**{field: -0.1})


@pytest.mark.parametrize("kwargs", [{"fps": 0.0}, {"sustain_fraction": 1.5}, {"min_peak": -0.1},
                                    {"full_peak_duration_s": 0.0}, {"lip_heavy": {"UUU", "OOO"}},
                                    {"tongue_only": {"MBP"}}, {"onset": 0.1}])
def test_config_rejects_invalid_values(kwargs):
    with pytest.raises(ValidationError):
        ProceduralConfig(**kwargs)


def test_config_is_frozen_documented_and_hashable():
    with pytest.raises(ValidationError):
        CFG.onset_s = 0.2
    assert all(f.description for f in ProceduralConfig.model_fields.values())
    assert hash(CFG) == hash(ProceduralConfig())
    assert (CFG.onset_s, CFG.sustain_fraction, CFG.decay_s, CFG.fps) == (0.12, 0.75, 0.12, None)


# --- properties -----------------------------------------------------------------------------------


@st.composite
def utterances(draw):
    """Random sorted, non-overlapping segments, an fps in {25, 30, 60}, and a frame count."""
    t = draw(st.floats(0.0, 1.0))
    word = 0
    segments = []
    for _ in range(draw(st.integers(0, 20))):
        t += draw(st.floats(0.0, 1.0)) if segments else 0.0
        duration = draw(st.floats(0.01, 0.5))
        word += draw(st.integers(0, 1))
        word_index = draw(st.sampled_from([word, word, None]))
        segments.append(VisemeSegment(draw(st.sampled_from(VISEMES)), t, t + duration, word_index))
        t += duration
    fps = draw(st.sampled_from([25.0, 30.0, 60.0]))
    n_frames = draw(st.integers(0, math.ceil((t + 1.0) * fps)))
    return segments, fps, n_frames


def dense_reference(segments, n_frames, fps):
    """The same keys evaluated at every frame (keys x frames), without the per-key frame windows."""
    curves = np.zeros((n_frames, N_VISEMES))
    merged, last_part_start = merge_with_holds(segments, CFG.merge_max_gap_s)
    if not merged:
        return curves
    keys = apply_word_lookahead(bridge_tongue_only(segment_keys(merged, fps, CFG, last_part_start), CFG), CFG)
    times = np.arange(n_frames) / fps
    for i, c in enumerate(keys.channel):
        curves[:, c] = np.maximum(curves[:, c], key_envelopes(keys, np.full(n_frames, i), times))
    return close_lips(curves) if CFG.closure_rule else curves


@settings(max_examples=200, deadline=None)
@given(utterances())
def test_curves_well_formed_zero_in_silence_and_deterministic(utterance):
    segments, fps, n_frames = utterance
    curves = generate_procedural_curves(segments, n_frames, fps)
    assert curves.shape == (n_frames, N_VISEMES)
    assert curves.dtype == np.float32 and curves.flags.c_contiguous
    assert np.all(np.isfinite(curves)) and curves.min(initial=0.0) >= 0.0 and curves.max(initial=0.0) <= 1.0
    times = np.arange(n_frames) / fps
    distance = np.full(n_frames, np.inf)
    for s in segments:
        distance = np.minimum(distance, np.maximum.reduce([s.start_s - times, times - s.end_s, 0 * times]))
    assert np.all(curves[distance > 0.5] == 0.0)
    np.testing.assert_array_equal(curves, generate_procedural_curves(list(segments), n_frames, fps))
    np.testing.assert_allclose(curves, dense_reference(segments, n_frames, fps), atol=1e-6)


def test_merged_closure_holds_through_its_last_part():
    """A long f then a short f (merged): the lips are still fully closed at the second f's start."""
    segments = [VisemeSegment("FFF", 0.0, 0.5, 0), VisemeSegment("FFF", 0.5, 0.625, 0), VisemeSegment("AAA", 0.625, 1.1, 0)]
    curves = generate_procedural_curves(segments, 30, 25.0)
    assert curves[12:15, viseme_index("FFF")].max() == 1.0
    assert curves[:15, viseme_index("FFF")].min() == 1.0  # one closure, no dip between the parts


@settings(max_examples=100, deadline=None)
@given(utterances())
def test_every_closure_shows_a_full_frame(utterance):
    """By the key rules every closure (MBP, FFF) peaks at 1 on a frame; with the lip rules every MBP still does (an f
    yields to an m whose closure has begun: the lips leave the teeth to close)."""
    segments, fps, n_frames = utterance
    curves = generate_procedural_curves(segments, n_frames, fps, RAW)
    ruled = generate_procedural_curves(segments, n_frames, fps)
    for s in segments:
        last = math.ceil(s.start_s * fps) + 1
        if s.viseme == "MBP" and last < n_frames:
            assert ruled[math.floor(s.start_s * fps):last + 1, viseme_index("MBP")].max() == 1.0
        if s.viseme in CFG.closure_visemes and last < n_frames:
            assert curves[math.floor(s.start_s * fps):last + 1, viseme_index(s.viseme)].max() == 1.0
