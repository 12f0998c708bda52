"""Audio augmentations of the robustness evaluation and training (visemeflow.learning.augment)."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys

import numpy as np
import pytest
from pydantic import ValidationError

from visemeflow.learning.augment import (
    CONDITIONS,
    AugmentConfig,
    TrainAugment,
    apply_condition,
    augment_utterance,
    augmented_id,
    draw_value,
    parse_augmented_id,
    source_id,
    train_augment_hook,
)
from visemeflow.learning.train import Example, TrainConfig, resample_curves, train_model
from visemeflow.schemas.ids import validate_utterance_id

SR = 16000
FPS = 25.0
IDS = [f"spk{i % 3}/utt_{i:03d}" for i in range(200)]


def _noise(seconds: float, std: float, seed: int = 0) -> np.ndarray:
    return (std * np.random.default_rng(seed).standard_normal(int(seconds * SR))).astype(np.float32)


def _peak_hz(audio: np.ndarray) -> float:
    n_fft = 1 << 20  # zero-padded: 0.015 Hz bins at 16 kHz
    spectrum = np.abs(np.fft.rfft(audio.astype(np.float64) * np.hanning(len(audio)), n_fft))
    return float(np.argmax(spectrum) * SR / n_fft)


# --------------------------------------------------------------------------------------------------
# config and draws


def test_config_defaults_are_the_papers_ranges_and_validated():
    c = AugmentConfig()
    assert [c.range_of(k) for k in CONDITIONS] == [(-10, 10), (-3, 3), (0.7, 1.3), (0.0, 0.005)]
    for bad in ({"volume_db": (3, -3)}, {"speed": (0.0, 1.2)}, {"speed": (-1.0, 1.0)},
                {"noise_std": (-0.001, 0.005)}, {"pitch_semitones": (float("nan"), 1.0)}, {"gain": (0, 1)}):
        with pytest.raises(ValidationError):
            AugmentConfig(**bad)
    assert AugmentConfig(speed=(1.1, 1.1)).range_of("speed") == (1.1, 1.1)
    with pytest.raises(ValidationError):
        c.speed = (1.0, 1.0)  # frozen


@pytest.mark.parametrize("condition", CONDITIONS)
def test_drawn_values_lie_in_range_and_cover_it(condition):
    low, high = AugmentConfig().range_of(condition)
    values = np.array([draw_value(condition, u, seed=0) for u in IDS])
    assert values.min() >= low and values.max() <= high
    span = high - low
    assert values.min() < low + 0.05 * span and values.max() > high - 0.05 * span
    assert abs(values.mean() - (low + high) / 2) < 0.1 * span
    assert len(np.unique(values)) == len(IDS)


def test_draws_are_deterministic_and_depend_on_seed_id_and_condition():
    a = draw_value("pitch", "spk/utt", seed=3)
    assert a == draw_value("pitch", "spk/utt", seed=3)
    assert a != draw_value("pitch", "spk/utt", seed=4)
    assert a != draw_value("pitch", "spk/utt2", seed=3)
    # same uniform position in a different range would show up as an exact affine relation
    v = draw_value("volume", "spk/utt", seed=3)
    assert not np.isclose(v / 10, a / 3)
    cfg = AugmentConfig(pitch_semitones=(0.0, 1.0))
    assert 0.0 <= draw_value("pitch", "spk/utt", seed=3, config=cfg) <= 1.0


def test_draws_are_the_same_in_another_process():
    # a fresh interpreter with a different str/bytes hash salt draws the same values (no hash())
    code = "from visemeflow.learning.augment import draw_value as d; print(repr([d(c, 'spk/utt', 3) for c in "
    code += repr(CONDITIONS) + "]))"
    env = {**os.environ, "PYTHONHASHSEED": "12345"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == repr([draw_value(c, "spk/utt", 3) for c in CONDITIONS])


@pytest.mark.parametrize("condition", CONDITIONS)
def test_augment_utterance_is_bit_identical_for_same_inputs(condition):
    audio = _noise(1.0, 0.05)
    a = augment_utterance(audio, SR, "spk/utt", condition, seed=1)
    b = augment_utterance(audio.copy(), SR, "spk/utt", condition, seed=1)
    assert a.audio.dtype == np.float32 and np.array_equal(a.audio, b.audio)
    assert (a.value, a.time_factor, a.utterance_id) == (b.value, b.time_factor, b.utterance_id)
    assert a.source_id == "spk/utt" and a.condition == condition
    assert a.value == draw_value(condition, "spk/utt", seed=1)
    c = augment_utterance(audio, SR, "spk/utt", condition, seed=2)
    assert c.value != a.value and not np.array_equal(c.audio, a.audio)
    assert not np.array_equal(a.audio[: len(audio)], audio)


# --------------------------------------------------------------------------------------------------
# the four conditions


def test_volume_changes_rms_by_drawn_db():
    audio = _noise(2.0, 0.05)
    rms = np.sqrt(np.mean(audio.astype(np.float64) ** 2))
    values = []
    for u in IDS[:10]:
        aug = augment_utterance(audio, SR, u, "volume", seed=0)
        out_rms = np.sqrt(np.mean(aug.audio.astype(np.float64) ** 2))
        assert 20 * np.log10(out_rms / rms) == pytest.approx(aug.value, abs=0.01)
        assert aug.time_factor == 1.0 and len(aug.audio) == len(audio)
        values.append(aug.value)
    assert min(values) < -2 and max(values) > 2  # both directions exercised
    # no silent clipping: +10 dB on a 0.5 peak gives a 1.58 peak
    loud, _ = apply_condition(np.full(100, 0.5, np.float32), SR, "volume", 10.0)
    assert loud.max() == pytest.approx(0.5 * 10 ** 0.5, rel=1e-6)


@pytest.mark.parametrize("semitones", [-3.0, 3.0, None])
def test_pitch_moves_a_440_hz_tone_by_the_semitones(semitones):
    t = np.arange(3 * SR) / SR
    tone = (0.3 * np.sin(2 * np.pi * 440.0 * t)).astype(np.float32)
    if semitones is None:  # the drawn value of augment_utterance
        aug = augment_utterance(tone, SR, "spk/tone", "pitch", seed=0)
        out, factor, semitones = aug.audio, aug.time_factor, aug.value
        assert abs(semitones) > 0.3  # a shift the test can tell from none
    else:
        out, factor = apply_condition(tone, SR, "pitch", semitones)
    assert factor == 1.0 and out.dtype == np.float32 and len(out) == len(tone)
    assert _peak_hz(tone) == pytest.approx(440.0, rel=1e-3)
    assert _peak_hz(out) == pytest.approx(440.0 * 2 ** (semitones / 12), rel=0.01)


def _click_frame(audio: np.ndarray) -> float:
    energy = np.convolve(audio.astype(np.float64) ** 2, np.ones(64), mode="same")
    return float(np.argmax(energy)) / SR * FPS


@pytest.mark.parametrize("factor", [0.7, 0.83, 1.0, 1.17, 1.3])
def test_speed_keeps_audio_and_curves_aligned(factor):
    n_frames, click = 75, 41  # 3 s at 25 fps; click at frame 41 (1.64 s)
    audio = np.zeros(n_frames * SR // int(FPS) + 7, np.float32)  # odd length on purpose
    start = round(click / FPS * SR)
    audio[start : start + 32] = 0.5
    curves = np.zeros((n_frames, 16), np.float32)
    curves[click] = 1.0
    out, time_factor = apply_condition(audio, SR, "speed", factor)
    assert time_factor == factor and out.dtype == np.float32
    assert len(out) == round(len(audio) / factor)
    new_curves = resample_curves(curves, time_factor)
    spike = int(np.argmax(new_curves[:, 0]))
    assert abs(spike - click / factor) <= 0.5
    assert abs(round(_click_frame(out)) - spike) <= 1
    assert abs(_click_frame(out) - click / factor) < 0.5  # in fact well within a frame


def test_speed_length_is_exact_for_drawn_factors_and_short_audio():
    for i, u in enumerate(IDS[:6]):
        audio = _noise(1.0 + 0.013 * i, 0.05, seed=i)
        aug = augment_utterance(audio, SR, u, "speed", seed=0)
        assert 0.7 <= aug.time_factor == aug.value <= 1.3
        assert len(aug.audio) == round(len(audio) / aug.value)
        n_frames = 31 + i
        assert resample_curves(np.zeros((n_frames, 16)), aug.time_factor).shape[0] == round(n_frames / aug.value)
    for n in (0, 1, 100, 511):  # shorter than the STFT window
        for f in (0.7, 1.3):
            out, _ = apply_condition(_noise(1.0, 0.05)[:n], SR, "speed", f)
            assert len(out) == round(n / f)
        out, _ = apply_condition(_noise(1.0, 0.05)[:n], SR, "pitch", 2.0)
        assert len(out) == n


def test_noise_adds_gaussian_noise_of_the_drawn_std():
    t = np.arange(3 * SR) / SR
    audio = (0.1 * np.sin(2 * np.pi * 220.0 * t)).astype(np.float32)
    values = []
    for u in IDS[:8]:
        aug = augment_utterance(audio, SR, u, "noise", seed=0)
        assert 0.0 <= aug.value <= 0.005 and aug.time_factor == 1.0
        added = aug.audio.astype(np.float64) - audio.astype(np.float64)
        assert added.std() == pytest.approx(aug.value, rel=0.05)
        assert abs(added.mean()) < 5 * aug.value / np.sqrt(len(audio)) + 1e-7
        values.append(aug.value)
    assert max(values) > 0.003
    with pytest.raises(ValueError, match="rng"):
        apply_condition(audio, SR, "noise", 0.001)
    a, _ = apply_condition(audio, SR, "noise", 0.001, np.random.default_rng(5))
    b, _ = apply_condition(audio, SR, "noise", 0.001, np.random.default_rng(5))
    assert np.array_equal(a, b)


def test_bad_inputs_are_refused():
    audio = _noise(0.1, 0.05)
    with pytest.raises(ValueError, match=r"'reverb'.*volume, pitch, speed, noise"):
        apply_condition(audio, SR, "reverb", 1.0)
    with pytest.raises(ValueError, match="reverb"):
        draw_value("reverb", "spk/utt", 0)
    with pytest.raises(ValueError, match="mono"):
        apply_condition(np.zeros((2, 100), np.float32), SR, "volume", 1.0)
    with pytest.raises(ValueError, match="speed"):
        apply_condition(audio, SR, "speed", 0.0)


# --------------------------------------------------------------------------------------------------
# ids


@pytest.mark.parametrize(
    ("condition", "value", "expected"),
    [
        ("pitch", 2.1, "spk/utt__pitch_p2.10"),
        ("volume", -3.5249, "spk/utt__volume_m3.52"),
        ("volume", -0.004, "spk/utt__volume_p0.00"),
        ("speed", 1.1236, "spk/utt__speed_1.124"),
        ("noise", 0.0031234, "spk/utt__noise_0.00312"),
    ],
)
def test_augmented_id_format(condition, value, expected):
    aid = augmented_id("spk/utt", condition, value)
    assert aid == expected
    assert validate_utterance_id(aid) == aid
    assert source_id(aid) == "spk/utt"
    src, cond, v = parse_augmented_id(aid)
    assert (src, cond) == ("spk/utt", condition) and v == pytest.approx(value, abs=10 ** -(len(aid.split(".")[-1])))


def test_augmented_ids_round_trip():
    for u in IDS[:20] + ["a/b", "spk-1/x.y_z", "spk/name__pitch_p1.00"]:
        for c in CONDITIONS:
            aug_id = augmented_id(u, c, draw_value(c, u, seed=9))
            assert validate_utterance_id(aug_id) == aug_id
            assert source_id(aug_id) == u
    assert source_id("spk/utt") == "spk/utt"  # no suffix: unchanged
    assert parse_augmented_id("spk/utt") is None
    assert parse_augmented_id("spk/utt__speed_p1.000") is None  # speed is unsigned
    with pytest.raises(ValueError):
        augmented_id("not-an-id", "pitch", 1.0)
    with pytest.raises(ValueError):
        augmented_id("spk/utt", "speed", float("nan"))


# --------------------------------------------------------------------------------------------------
# training hook


def test_train_hook_probability_and_determinism():
    audio = _noise(1.0, 0.05)
    never = train_augment_hook(probability=0.0)
    out, factor = never(audio, np.random.default_rng(0))
    assert out is audio and factor == 1.0

    always = train_augment_hook(probability=1.0)
    seen = set()
    for seed in range(12):
        out, factor = always(audio, np.random.default_rng(seed))
        again, factor2 = always(audio, np.random.default_rng(seed))
        assert np.array_equal(out, again) and factor == factor2 and out.dtype == np.float32
        assert len(out) != len(audio) or not np.array_equal(out, audio)
        assert len(out) == round(len(audio) / factor)
        if factor != 1.0:
            assert 0.7 <= factor <= 1.3
            seen.add("speed")
        else:
            seen.add("other")
    assert seen == {"speed", "other"}

    half = train_augment_hook()  # probability 0.5
    rng = np.random.default_rng(1)
    changed = sum(half(audio, rng)[0] is not audio for _ in range(40))
    assert 10 <= changed <= 30

    only_speed = train_augment_hook(conditions=["speed"], probability=1.0,
                                    config=AugmentConfig(speed=(1.2, 1.25)))
    out, factor = only_speed(audio, np.random.default_rng(3))
    assert 1.2 <= factor <= 1.25 and len(out) == round(len(audio) / factor)

    with pytest.raises(ValueError, match="reverb"):
        train_augment_hook(conditions=("reverb",))
    with pytest.raises(ValueError):
        train_augment_hook(probability=1.5)


def test_train_hook_pickles():
    hook = train_augment_hook(probability=1.0, conditions=("pitch", "noise"))
    clone = pickle.loads(pickle.dumps(hook))
    assert isinstance(clone, TrainAugment) and clone == hook
    audio = _noise(0.5, 0.05)
    a, fa = hook(audio, np.random.default_rng(7))
    b, fb = clone(audio, np.random.default_rng(7))
    assert np.array_equal(a, b) and fa == fb


def _examples() -> list[Example]:
    rng = np.random.default_rng(0)
    out = []
    for i, seconds in enumerate((1.0, 1.4)):
        n = int(seconds * SR)
        env = 0.05 + 0.5 * (0.5 + 0.5 * np.sin(2 * np.pi * 1.3 * np.arange(n) / SR))
        audio = (0.3 * env * rng.standard_normal(n)).astype(np.float32)
        frames = round(seconds * FPS)
        curves = np.clip(rng.uniform(0, 1, (frames, 16)), 0, 1).astype(np.float32)
        out.append(Example(f"spk/utt{i}", audio, curves, FPS))
    return out


def test_train_model_runs_with_the_hook():
    train = _examples()
    cfg = TrainConfig(preset="fbank-blstm", epochs=2, d_model=8, train_augment=True)
    res = train_model(train, train[:1], cfg, augment_audio=train_augment_hook(probability=1.0))
    assert [r.epoch for r in res.history] == [1, 2]
    assert all(np.isfinite(r.train_l1_x100) and np.isfinite(r.val_l1_x100) for r in res.history)
