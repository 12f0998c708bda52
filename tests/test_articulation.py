"""The lip rules (visemeflow/articulation.py) judged where the viewer sees them: millimetres on the demo character's
mesh (animation/lips.py), per aligned phone (learning/lipscore.py), and in the preview's lip band."""

import numpy as np
import pytest

from visemeflow.rig.character import character_from_rig
from visemeflow.animation.lips import LipProbe, is_bilabial
from visemeflow.animation.preview import CLOSED_COLOR, OPEN_AT_CLOSURE_COLOR, PreviewFrames
from visemeflow.articulation import CLOSED_MM, CONTACT_MM, OPENING, close_lips, opening
from visemeflow.learning.lipscore import pool_lips, score_lips
from visemeflow.learning.realspeech import Phone
from visemeflow.rig import load_demo_rig
from visemeflow.visemes import N_VISEMES, VISEMES, viseme_index


@pytest.fixture(scope="module")
def rig():
    return load_demo_rig()


@pytest.fixture(scope="module")
def probe(rig):
    return LipProbe.from_rig(rig)


def blend(**weights) -> np.ndarray:
    row = np.zeros((1, N_VISEMES), np.float32)
    for name, w in weights.items():
        row[0, viseme_index(name)] = w
    return row


def test_the_demo_character_measures_as_documented(probe):
    one = np.vstack([np.zeros(N_VISEMES), np.eye(N_VISEMES)]).astype(np.float32)
    lips = probe.measure(one)
    gap = dict(zip(("neutral",) + VISEMES, lips.gap_mm))
    teeth = dict(zip(("neutral",) + VISEMES, lips.teeth_mm))
    assert gap["neutral"] == pytest.approx(1.1, abs=0.1) and gap["MBP"] < CLOSED_MM
    assert gap["AHH"] == pytest.approx(29.5, abs=0.3) and gap["AHH"] == max(gap.values())
    assert teeth["FFF"] < 0.5 < CONTACT_MM < teeth["AHH"] / 10
    # the OPENING table is the rig's own vertical inner-lip opening relative to AHH's
    ids = rig_pairs = probe.pairs_delta[:, :, :, 1]            # (16, 2, 3) y of the deltas at the pairs, mm
    vertical = -(ids[:, 1] - ids[:, 0]).mean(axis=1)           # lower lip down, upper lip up: opening
    relative = np.clip(vertical / vertical[viseme_index("AHH")], 0, None)
    np.testing.assert_allclose(OPENING, relative, atol=0.05)
    assert rig_pairs.shape == (N_VISEMES, 2, 3)


def test_a_bilabial_closes_the_mouth_whatever_is_co_active(probe):
    """The issue's cases: MBP 1 with OHH 0.6 (12-22 mm apart before), MBP 1 with WWW 0.95 (the Mandarin "b")."""
    for others in ({"OHH": 0.6}, {"OHH": 0.7, "AAA": 0.4}, {"WWW": 0.95}, {"AHH": 1.0, "EH": 1.0}):
        raw = blend(MBP=1.0, **others)
        assert probe.measure(raw).gap_mm[0] > CLOSED_MM, others       # the raw blend is open
        assert probe.measure(close_lips(raw)).gap_mm[0] < CLOSED_MM, others
    # a half-way MBP closes half-way: continuous, no jump
    half = probe.measure(close_lips(blend(MBP=0.5, AHH=1.0))).gap_mm[0]
    assert CLOSED_MM < half < probe.measure(blend(AHH=1.0)).gap_mm[0]


def test_a_labiodental_reaches_the_upper_teeth(probe):
    for others in ({"AHH": 1.0}, {"OHH": 0.8, "IEE": 0.5}):
        raw = blend(FFF=1.0, **others)
        assert probe.measure(raw).teeth_mm[0] > CONTACT_MM, others
        assert probe.measure(close_lips(raw)).teeth_mm[0] <= CONTACT_MM, others


def test_no_blend_opens_wider_than_the_widest_shape(probe):
    widest = probe.single_shape_gap("AHH")
    rng = np.random.default_rng(0)
    curves = rng.random((500, N_VISEMES)).astype(np.float32)
    curves[:, viseme_index("MBP")] = 0
    curves[:, viseme_index("FFF")] = 0
    assert probe.measure(curves).gap_mm.max() > 1.5 * widest        # raw sums open far past AHH
    bounded = close_lips(curves)
    assert opening(bounded).max() <= 1.0 + 1e-5
    assert probe.measure(bounded).gap_mm.max() <= 1.1 * widest


def test_the_rule_leaves_what_it_need_not_touch():
    rng = np.random.default_rng(1)
    curves = (rng.random((200, N_VISEMES)) * 0.3).astype(np.float32)
    curves[:, [viseme_index("MBP"), viseme_index("FFF")]] = 0
    curves *= np.minimum(1.0, 0.99 / np.maximum(opening(curves), 1e-9))[:, None]   # under the bound
    np.testing.assert_allclose(close_lips(curves), curves, atol=1e-6)
    mixed = rng.random((200, N_VISEMES)).astype(np.float32)
    once = close_lips(mixed)
    assert once.min() >= 0 and once.max() <= 1 and once.dtype == np.float32
    np.testing.assert_allclose(close_lips(once), once, atol=1e-6)     # idempotent: a second pass changes nothing
    full = mixed.copy()
    full[:, viseme_index("MBP")] = 1.0
    only = close_lips(full)                                          # at MBP = 1: the MBP shape alone
    assert (only[:, viseme_index("MBP")] == 1).all() and np.delete(only, viseme_index("MBP"), axis=1).max() == 0
    np.testing.assert_array_equal(close_lips(mixed, bilabial=False, labiodental=False, bound_opening=False),
                                  np.clip(mixed, 0, 1))
    assert (mixed == rng.random(0).sum() + mixed).all()             # the input was not modified
    with pytest.raises(ValueError, match=r"\(frames, 16\)"):
        close_lips(np.zeros((4, 15)))


def test_phone_scores_see_closures_and_the_mean_curve_fails(probe):
    fps, widest = 30.0, probe.single_shape_gap("AHH")
    phones = [Phone(0.0, 0.2, None), Phone(0.2, 0.3, "MBP"), Phone(0.3, 0.5, "AHH"), Phone(0.5, 0.6, "FFF"),
              Phone(0.6, 0.8, "IEE"), Phone(0.8, 0.9, "MBP")]
    curves = np.zeros((30, N_VISEMES), np.float32)
    curves[6:9, viseme_index("MBP")] = 1
    curves[6:16, viseme_index("AHH")] = np.linspace(0.5, 1.0, 10)   # co-active: open unless the rule applies
    curves[15:18, viseme_index("FFF")] = 1
    curves[17:24, viseme_index("IEE")] = 1
    curves[24:27, viseme_index("MBP")] = 1
    curves[24:27, viseme_index("OHH")] = 0.6

    def scores(c):
        m = probe.measure(c)
        return score_lips(m.gap_mm, m.teeth_mm, fps, phones, widest)

    raw, ruled = scores(curves), scores(close_lips(curves))
    assert raw.closed.total == 2 and raw.closed.hits == 0
    assert ruled.closed.hits == 2 and ruled.contact.hits == 1 and ruled.false_closed.hits == 0
    assert 0.6 <= ruled.median_vowel_opening <= 1.1
    mean = np.repeat(curves.mean(axis=0, keepdims=True), len(curves), axis=0)
    baseline = scores(close_lips(mean))
    assert baseline.closed.hits == 0 and baseline.median_gap_mm > 3
    pooled = pool_lips([raw, ruled])
    assert pooled.closed.total == 4 and pooled.summary()["closed"] == 0.5


def test_the_preview_writes_each_panels_lip_gap_under_it(rig):
    character = character_from_rig(rig)
    raw = np.repeat(blend(MBP=1.0, OHH=0.6), 4, axis=0)
    frames = PreviewFrames(character, {"raw": raw, "closure rule": close_lips(raw)}, 30,
                           phones=[(0.0, 1.0, "M")], size=128)
    assert frames.lip_height > 0
    canvas = next(iter(frames)).copy()
    left, right = (canvas[frames.lip_box(k)].reshape(-1, 3) for k in range(2))

    def has(pixels, color):
        return (np.abs(pixels.astype(int) - color).sum(axis=1) < 40).sum() > 10

    assert has(left, OPEN_AT_CLOSURE_COLOR) and not has(left, CLOSED_COLOR)
    assert has(right, CLOSED_COLOR) and not has(right, OPEN_AT_CLOSURE_COLOR)
    vertices = character.neutral + raw[0] @ character.deltas.reshape(character.n_shapes, -1).reshape(
        character.n_shapes, -1, 3).transpose(1, 0, 2)
    assert frames.lip_gap_mm(vertices) > 5
    assert is_bilabial("M") and is_bilabial("b") and is_bilabial("p0") and not is_bilabial("AH0")


def one_frame_closures(n_frames: int = 240, every: int = 11) -> tuple[np.ndarray, list[int]]:
    """Speech-like curves at 30 fps: open vowels with a b/p/m every `every` frames that a learned model closes for one
    frame only (MBP 0.95 at its peak, 0.4 on either side, the vowels yielding there as ClosurePeaks leaves them)."""
    rng = np.random.default_rng(5)
    curves = np.zeros((n_frames, N_VISEMES), np.float32)
    vowels = [viseme_index(v) for v in ("AHH", "OHH", "EH", "AAA")]
    curves[np.arange(n_frames), rng.choice(vowels, n_frames)] = rng.uniform(0.5, 0.9, n_frames)
    peaks = list(range(5, n_frames - 5, every))
    for k in peaks:
        curves[k - 1:k + 2, viseme_index("MBP")] = (0.4, 0.95, 0.4)
        curves[k, [i for i in range(N_VISEMES) if VISEMES[i] != "MBP"]] *= 0.05 ** 6
    return curves, peaks


@pytest.mark.parametrize("fps", [24.0, 25.0, 23.976, 50.0, 60.0, 12.0])
def test_retiming_keeps_every_one_frame_closure_shut_on_the_mesh(probe, fps):
    from visemeflow.animation.apply import resample, resample_visemes

    curves, peaks = one_frame_closures()
    at30 = probe.measure(close_lips(curves)).gap_mm
    assert (at30[peaks] < CLOSED_MM).all()
    kept = probe.measure(close_lips(resample_visemes(curves, 30.0, fps))).gap_mm
    nearest = np.rint(np.array(peaks) / 30.0 * fps).astype(int)
    assert (kept[nearest] < CLOSED_MM).all(), f"{fps} fps: closures lost at {nearest[kept[nearest] >= CLOSED_MM]}"
    linear = resample(curves, 30.0, fps)
    if fps in (24.0, 25.0, 23.976):   # a frame of 30 fps between two new ones: plain interpolation opens the lips
        lost = [k for k in peaks if probe.measure(close_lips(linear[[round(k / 30.0 * fps)]])).gap_mm[0] >= CLOSED_MM]
        assert len(lost) >= len(peaks) // 2
    # only the frames that took a key differ from plain interpolation, and every key keeps its whole pose
    differs = np.flatnonzero(np.abs(resample_visemes(curves, 30.0, fps) - linear).max(axis=1) > 1e-6)
    assert set(differs) <= set(nearest.tolist())
    np.testing.assert_array_equal(resample_visemes(curves, 30.0, fps)[nearest], curves[peaks])


def test_contact_keys_are_the_peaks_where_mbp_or_fff_leads_strongest_first():
    from visemeflow.articulation import contact_keys

    c = np.zeros((9, N_VISEMES), np.float32)
    c[:, viseme_index("AHH")] = 0.5
    c[1:4, viseme_index("MBP")] = (0.6, 0.8, 0.6)     # a closure, peak at 2
    c[5:8, viseme_index("FFF")] = (0.7, 0.9, 0.9)     # an f held two frames: its plateau's first frame
    c[8, viseme_index("MBP")] = 0.3                    # a peak that does not lead: AHH is larger
    assert contact_keys(c).tolist() == [6, 2]
    assert contact_keys(np.zeros((0, N_VISEMES))).size == 0
    assert contact_keys(np.zeros((4, N_VISEMES))).size == 0   # rest: nothing leads
    with pytest.raises(ValueError, match="16"):
        contact_keys(np.zeros((3, 5)))


@pytest.mark.parametrize("n_frames", [8, 9, 10, 11, 12, 13])
def test_a_closure_on_the_last_frame_survives_retiming(probe, n_frames):
    """An utterance that ends on a one-frame closure: its key lands on the last new frame, whatever the length."""
    from visemeflow.animation.apply import resample_visemes

    curves = np.zeros((n_frames, N_VISEMES), np.float32)
    curves[:, viseme_index("AHH")] = 0.8
    curves[-2:, viseme_index("MBP")] = (0.4, 0.95)
    curves[-1, viseme_index("AHH")] = 0.8 * 0.05 ** 6
    retimed = resample_visemes(curves, 30.0, 24.0)
    assert probe.measure(close_lips(retimed[-1:])).gap_mm[0] < CLOSED_MM
