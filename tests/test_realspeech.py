"""Real-speech metrics without curve truth (`visemeflow.learning.realspeech`): hand-built curves and phones whose
answers are known."""

import math

import numpy as np
import pyarrow as pa
import pytest

from visemeflow.learning.realspeech import (
    Phone,
    Recall,
    activation_agreement,
    closure_recall,
    compare_curves,
    phone_frames,
    phones_of,
    pool,
    scale_phones,
    score_phones,
    score_utterance,
)
from visemeflow.schemas import PHONES, table_from_rows
from visemeflow.visemes import VISEME_INDEX, VISEMES

FPS = 10.0


def curves(n=10, **peaks):
    """(n, 16) zeros with `VISEME=[(frame, value), ...]` set."""
    c = np.zeros((n, 16), np.float32)
    for name, points in peaks.items():
        for frame, value in points:
            c[frame, VISEME_INDEX[name]] = value
    return c


def test_phone_frames_follow_k_over_fps_with_half_open_intervals():
    assert phone_frames(0.3, 0.6, FPS, 10).tolist() == [3, 4, 5]       # 0.6 itself belongs to the next phone
    assert phone_frames(0.0, 0.1, FPS, 10).tolist() == [0]
    assert phone_frames(0.25, 0.55, FPS, 10).tolist() == [3, 4, 5]
    # 1/3 s at 30 fps: 10/30 is exactly the float start, so frame 10 is in
    assert phone_frames(10 / 30, 20 / 30, 30.0, 100).tolist() == list(range(10, 20))
    # shorter than a frame, between frames 4 (0.40) and 5 (0.50): the frame nearest its midpoint 0.47
    assert phone_frames(0.46, 0.48, FPS, 10).tolist() == [5]
    assert phone_frames(0.41, 0.43, FPS, 10).tolist() == [4]
    # a zero-length phone still has its frame; a phone past the curves has none
    assert phone_frames(0.7, 0.7, FPS, 10).tolist() == [7]
    assert phone_frames(0.95, 1.2, FPS, 10).tolist() == [9]            # starts inside the last frame's span
    assert phone_frames(0.96, 0.99, FPS, 10).tolist() == [9]           # nearest frame clamped to the curves
    assert phone_frames(1.0, 1.2, FPS, 10) is None
    assert phone_frames(0.0, 0.5, FPS, 0) is None


def test_closure_recall_takes_the_highest_peak_within_the_phone_not_the_mean():
    phones = [Phone(0.0, 0.3, "MBP"), Phone(0.3, 0.6, "AAA"), Phone(0.6, 1.0, "MBP")]
    # first b/p/m: a one-frame closure (0.9) inside a vowel held at 0.5: its mean (0.3) is below AAA's (0.5),
    # its peak is the highest: a hit. Second: AAA peaks higher (0.95) than MBP (0.8) within the phone: a miss.
    c = curves(AAA=[(0, .5), (1, .5), (2, .5), (3, .9), (8, .95)], MBP=[(1, .9), (7, .8)])
    recall = closure_recall(c, FPS, phones)
    assert recall["MBP"] == Recall(1, 2) and recall["MBP"].share == 0.5
    assert recall["FFF"] == Recall(0, 0) and recall["FFF"].share is None   # no f/v phone: undefined
    scores, skipped = score_phones(c, FPS, phones)
    assert [s.top for s in scores] == ["MBP", "AAA", "AAA"] and skipped == 0
    assert [(s.first_frame, s.last_frame, s.apex_frame) for s in scores] == [(0, 2, 2), (3, 5, 5), (6, 9, 8)]


def test_false_closures_count_the_other_phones_where_the_closure_viseme_is_on_top():
    phones = [Phone(0.0, 0.2, "MBP"), Phone(0.2, 0.4, "AAA"), Phone(0.4, 0.6, "EH"), Phone(0.6, 0.8, None),
              Phone(0.8, 1.0, "FFF")]
    # MBP tops the b/p/m phone, the AAA phone (strictly) and ties with EH on the EH phone; FFF tops nothing
    c = curves(MBP=[(0, .9), (2, .8), (4, .5), (7, 1.0)], AAA=[(3, .5)], EH=[(5, .5)], FFF=[(9, .2)], SSS=[(8, .3)])
    s = score_utterance(c, FPS, phones)
    assert s.closure == {"MBP": Recall(1, 1), "FFF": Recall(0, 1)}
    assert s.false_closure == {"MBP": Recall(1, 3), "FFF": Recall(0, 3)}   # silence is no phone of another viseme
    # a face that always shows MBP most has perfect closure recall and closes on every other phone too
    shut = np.tile(np.where(np.array(VISEMES) == "MBP", 0.6, 0.1), (10, 1))
    s = score_utterance(shut, FPS, phones)
    assert s.closure["MBP"] == Recall(1, 1) and s.false_closure["MBP"] == Recall(3, 3)
    pooled = pool([s, s])
    assert pooled.false_closure["MBP"] == Recall(6, 6)


def test_a_tie_for_the_top_is_not_a_hit_and_flat_curves_earn_nothing():
    phones = [Phone(0.0, 0.5, "FFF"), Phone(0.5, 1.0, "FFF")]
    tie = curves(FFF=[(1, .7), (6, .7)], SSS=[(2, .7)])
    assert closure_recall(tie, FPS, phones)["FFF"] == Recall(1, 2)
    flat = np.full((10, 16), 0.3, np.float32)
    assert closure_recall(flat, FPS, phones)["FFF"] == Recall(0, 2)
    assert activation_agreement(flat, FPS, phones).overall == Recall(0, 2)
    saturated = curves(FFF=[(k, 1.0) for k in range(10)], AAA=[(k, 1.0) for k in range(10)])
    assert closure_recall(saturated, FPS, phones)["FFF"].hits == 0


def test_a_phone_shorter_than_a_frame_is_judged_on_its_nearest_frame():
    phones = [Phone(0.41, 0.43, "MBP")]
    assert closure_recall(curves(MBP=[(4, .6)], AAA=[(5, .9)]), FPS, phones)["MBP"] == Recall(1, 1)
    assert closure_recall(curves(MBP=[(5, .9)], AAA=[(4, .6)]), FPS, phones)["MBP"] == Recall(0, 1)
    assert activation_agreement(curves(MBP=[(4, .6)]), FPS, phones).overall == Recall(1, 1)


def test_activation_agreement_is_top_two_at_the_apex_frame_per_phone_and_per_viseme():
    phones = [Phone(0.0, 0.3, "AAA"),    # apex frame 2 (midpoint 0.15 -> floor(1.5 + 0.5) = 2)
              Phone(0.3, 0.6, "MBP"),    # apex frame 5 (0.45 -> 5)
              Phone(0.6, 0.8, "AAA"),    # apex frame 7
              Phone(0.8, 1.0, "SSS")]    # apex frame 9
    c = curves(AAA=[(2, .5), (7, .2), (1, .99)],   # AAA at frame 1 (not the apex) must not matter
               EH=[(2, .6), (7, .4), (9, .9)],
               IEE=[(7, .3), (9, .8)],
               MBP=[(4, 1.0), (5, .1)],           # a peak before the apex: in the closure recall, not the agreement
               SSS=[(9, .7)])
    a = activation_agreement(c, FPS, phones)
    # AAA at frame 2: second (EH .6 > .5): in. MBP at 5: first: in. AAA at 7: third (EH, IEE above): out.
    # SSS at 9: third (EH .9, IEE .8): out.
    assert a.overall == Recall(2, 4) and a.share == 0.5
    assert a.per_viseme == {"AAA": Recall(1, 2), "MBP": Recall(1, 1), "SSS": Recall(0, 1)}
    assert list(a.per_viseme) == [v for v in VISEMES if v in a.per_viseme]          # in the fixed viseme order
    assert activation_agreement(c, FPS, phones, k=3).overall == Recall(4, 4)
    assert activation_agreement(c, FPS, phones, k=1).overall == Recall(1, 4)
    # a tie with the second place counts against the phone's viseme
    tied = curves(AAA=[(2, .5)], EH=[(2, .6)], OHH=[(2, .5)])
    assert activation_agreement(tied, FPS, phones[:1]).overall == Recall(0, 1)


def test_silence_is_ignored_and_phones_come_from_the_phones_table():
    rows = [
        {"utterance_id": "s/u", "index": 0, "part": 0, "label": "sil", "phoneme": None, "viseme": None,
         "start_s": 0.0, "end_s": 0.3},
        {"utterance_id": "s/u", "index": 1, "part": 0, "label": "B", "phoneme": "B", "viseme": "MBP",
         "start_s": 0.3, "end_s": 0.5},
        {"utterance_id": "s/u", "index": 2, "part": 0, "label": "", "phoneme": None, "viseme": None,
         "start_s": 0.5, "end_s": 0.7},
        {"utterance_id": "s/u", "index": 3, "part": 0, "label": "F", "phoneme": "F", "viseme": "FFF",
         "start_s": 0.7, "end_s": 1.0},
    ]
    table = table_from_rows(rows, PHONES)
    c = curves(MBP=[(0, 1.0), (3, .8), (4, .8), (6, 1.0)], FFF=[(8, .4), (9, .4)], AAA=[(7, .5)])
    s = score_utterance(c, FPS, table)
    assert s.closure == {"MBP": Recall(1, 1), "FFF": Recall(0, 1)}   # silence frames 0 and 6 never count
    assert s.agreement.overall.total == 2 and s.agreement.per_viseme == {"FFF": Recall(1, 1), "MBP": Recall(1, 1)}
    assert score_utterance(c, FPS, rows) == s                          # row dicts give the same
    silent = score_utterance(c, FPS, [rows[0], rows[2]])
    assert silent.closure["MBP"].share is None and silent.agreement.share is None
    assert silent.agreement.overall == Recall(0, 0)
    two = pa.concat_tables([table, table_from_rows([{**rows[1], "utterance_id": "s/v"}], PHONES)])
    with pytest.raises(ValueError, match="several utterances"):
        phones_of(two)


def test_bad_inputs_are_refused():
    with pytest.raises(ValueError, match="unknown viseme 'XYZ'"):
        phones_of([{"start_s": 0.0, "end_s": 0.1, "viseme": "XYZ"}])
    with pytest.raises(ValueError, match="ends before it starts"):
        phones_of([Phone(0.2, 0.1, "MBP")])
    with pytest.raises(ValueError, match="finite"):
        phones_of([Phone(math.nan, 0.1, "MBP")])
    with pytest.raises(ValueError, match="shape"):
        closure_recall(np.zeros((10, 15)), FPS, [])
    bad = curves()
    bad[3, 2] = np.nan
    with pytest.raises(ValueError, match="frame 3"):
        activation_agreement(bad, FPS, [])


def test_phones_past_the_curves_are_skipped_and_scores_pool_by_phone():
    phones = [Phone(0.0, 0.5, "MBP"), Phone(0.5, 0.9, "FFF"), Phone(1.0, 1.2, "MBP")]   # the last after 10 frames
    a = score_utterance(curves(MBP=[(2, 1.0)], FFF=[(6, 1.0)]), FPS, phones)
    assert a.skipped == 1 and a.closure == {"MBP": Recall(1, 1), "FFF": Recall(1, 1)}
    b = score_utterance(curves(n=20, AAA=[(2, 1.0)], MBP=[(11, 1.0)]), FPS, phones)
    assert b.skipped == 0 and b.closure == {"MBP": Recall(1, 2), "FFF": Recall(0, 1)}
    pooled = pool([a, b])
    assert pooled.closure == {"MBP": Recall(2, 3), "FFF": Recall(1, 2)} and pooled.skipped == 1
    assert pooled.agreement.overall == a.agreement.overall + b.agreement.overall
    assert pooled.agreement.overall.total == 5
    assert pool([]).agreement.share is None and pool([]).closure == {}


def test_speed_scaled_phones_follow_the_faster_audio():
    phones = [Phone(0.5, 1.0, "MBP")]
    fast = scale_phones(phones, 1.25)            # played 1.25x faster: 0.4..0.8 s
    assert fast == [Phone(0.4, 0.8, "MBP")]
    c = curves(MBP=[(5, 1.0)], AAA=[(9, 1.0), (4, .5)])   # closure at 0.5 s in the fast audio
    assert closure_recall(c, FPS, fast)["MBP"] == Recall(1, 1)
    with pytest.raises(ValueError):
        scale_phones(phones, 0.0)


def test_compare_curves_l1_and_nan_safe_pearson():
    rng = np.random.default_rng(1)
    ref = rng.random((30, 16))
    ref[:, VISEME_INDEX["GK"]] = 0.25                       # constant in the reference
    pred = ref.copy()
    pred[:, VISEME_INDEX["AAA"]] = 1.0 - ref[:, VISEME_INDEX["AAA"]]      # anti-correlated
    pred[:, VISEME_INDEX["EH"]] = 3.0 * ref[:, VISEME_INDEX["EH"]] + 1.0  # affine: r = 1
    pred[:, VISEME_INDEX["MBP"]] = 0.5                      # constant in the prediction
    r = compare_curves(pred, ref, 30.0)
    assert r.frames == 30
    expected_l1 = 100 * np.abs(pred - ref).mean()
    assert r.l1_x100 == pytest.approx(expected_l1)
    assert r.pearson["AAA"] == pytest.approx(-1.0) and r.pearson["EH"] == pytest.approx(1.0)
    assert math.isnan(r.pearson["GK"]) and math.isnan(r.pearson["MBP"]) and r.defined == 14
    assert r.mean_pearson == pytest.approx((12 * 1.0 + 1.0 - 1.0) / 14)
    # lengths differing by a frame (rounding) are truncated; by more than a frame per second, refused
    assert compare_curves(np.vstack([pred, pred[:1]]), ref, 30.0).l1_x100 == pytest.approx(expected_l1)
    long_ref = rng.random((300, 16))
    assert compare_curves(long_ref[:291], long_ref, 30.0).frames == 291      # 9 frames over 9.7 s: allowed
    with pytest.raises(ValueError, match="one frame per second"):
        compare_curves(long_ref[:280], long_ref, 30.0)
    with pytest.raises(ValueError, match="one frame per second"):
        compare_curves(pred[:27], ref, 30.0)
    flat = compare_curves(np.zeros((5, 16)), np.ones((5, 16)), 30.0)
    assert flat.l1_x100 == pytest.approx(100.0) and math.isnan(flat.mean_pearson) and flat.defined == 0
    with pytest.raises(ValueError, match="no frame"):
        compare_curves(np.zeros((0, 16)), np.zeros((1, 16)), 30.0)
