"""Live Link Face CSV (visemeflow/shapes/livelink.py): the app's header and timecodes, read back by column name."""

import csv

import numpy as np
import pytest

from visemeflow.shapes.conventions import ARKIT_52
from visemeflow.shapes.livelink import (
    DECIMALS,
    LIVELINK_COLUMNS,
    arkit_from_livelink,
    format_timecode,
    parse_timecode,
    read_livelink_csv,
    write_livelink_csv,
)

# The first line of a take recorded by the Live Link Face app (as published with open importers), verbatim
APP_HEADER = (
    "Timecode,BlendShapeCount,EyeBlinkLeft,EyeLookDownLeft,EyeLookInLeft,EyeLookOutLeft,EyeLookUpLeft,EyeSquintLeft,"
    "EyeWideLeft,EyeBlinkRight,EyeLookDownRight,EyeLookInRight,EyeLookOutRight,EyeLookUpRight,EyeSquintRight,"
    "EyeWideRight,JawForward,JawRight,JawLeft,JawOpen,MouthClose,MouthFunnel,MouthPucker,MouthRight,MouthLeft,"
    "MouthSmileLeft,MouthSmileRight,MouthFrownLeft,MouthFrownRight,MouthDimpleLeft,MouthDimpleRight,"
    "MouthStretchLeft,MouthStretchRight,MouthRollLower,MouthRollUpper,MouthShrugLower,MouthShrugUpper,"
    "MouthPressLeft,MouthPressRight,MouthLowerDownLeft,MouthLowerDownRight,MouthUpperUpLeft,MouthUpperUpRight,"
    "BrowDownLeft,BrowDownRight,BrowInnerUp,BrowOuterUpLeft,BrowOuterUpRight,CheekPuff,CheekSquintLeft,"
    "CheekSquintRight,NoseSneerLeft,NoseSneerRight,TongueOut,HeadYaw,HeadPitch,HeadRoll,LeftEyeYaw,LeftEyePitch,"
    "LeftEyeRoll,RightEyeYaw,RightEyePitch,RightEyeRoll"
)


def arkit_weights(n_frames: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    w = rng.random((n_frames, len(ARKIT_52))).astype(np.float32)
    w[:, 3] = 0.0
    w[:, 4] = 1.0
    return w


def test_round_trip_by_column_name(tmp_path):
    weights = arkit_weights(40)
    path = write_livelink_csv(tmp_path / "take.csv", weights, 30)
    names, values, timecodes = read_livelink_csv(path)
    assert names == LIVELINK_COLUMNS and values.shape == (40, 61) and values.dtype == np.float32
    # printed with 6 decimals: every weight comes back within half a unit of the last printed digit
    np.testing.assert_allclose(arkit_from_livelink(values), weights, rtol=0, atol=0.5 * 10.0 ** -DECIMALS + 1e-7)
    assert np.abs(arkit_from_livelink(values) - weights).max() > 0  # rounded, not stored exactly: the bound matters
    np.testing.assert_array_equal(values[:, 52:], 0)  # rotations
    # each ARKit name lands in its capitalised column
    jaw_left = LIVELINK_COLUMNS.index("JawLeft")
    np.testing.assert_allclose(values[:, jaw_left], weights[:, ARKIT_52.index("jawLeft")], atol=1e-6)
    mouth_right = LIVELINK_COLUMNS.index("MouthRight")
    np.testing.assert_allclose(values[:, mouth_right], weights[:, ARKIT_52.index("mouthRight")], atol=1e-6)
    assert len(timecodes) == 40


def test_header_is_the_apps(tmp_path):
    path = write_livelink_csv(tmp_path / "take.csv", arkit_weights(3), 60)
    lines = path.read_text().split("\n")
    assert lines[0] == APP_HEADER
    header = lines[0].split(",")
    assert len(header) == 63 and header[:2] == ["Timecode", "BlendShapeCount"]
    assert header.index("JawRight") < header.index("JawLeft")
    assert header.index("MouthRight") < header.index("MouthLeft")
    assert tuple(header[2:]) == LIVELINK_COLUMNS
    first = lines[1].split(",")
    assert first[0] == "00:00:00:00.000" and first[1] == "61" and len(first) == 63
    assert all(len(v.split(".")[1]) == DECIMALS for v in first[2:])
    assert lines[-1] == "" and len(lines) == 5  # one line per frame, "\n" line ends


@pytest.mark.parametrize("fps", [30, 60, 24, 29.97])
def test_timecodes_increase_and_parse_back(tmp_path, fps):
    n = int(3 * fps) + 5  # past a few second (and frame-counter) boundaries
    path = write_livelink_csv(tmp_path / "take.csv", arkit_weights(n), fps, start_seconds=3599.0)
    _, _, timecodes = read_livelink_csv(path)
    seconds = np.array([parse_timecode(tc, fps) for tc in timecodes])
    assert np.all(np.diff(seconds) > 0)
    np.testing.assert_allclose(seconds, 3599.0 + np.arange(n) / fps, rtol=0, atol=0.0005 / fps + 1e-9)
    assert timecodes[0] == "00:59:59:00.000"
    if fps == 30:
        assert timecodes[29:32] == ["00:59:59:29.000", "01:00:00:00.000", "01:00:00:01.000"]


def test_timecode_text():
    assert format_timecode(0, 30) == "00:00:00:00.000"
    assert format_timecode(12 * 3600 + 27 * 60 + 47 + 47.169 / 60, 60) == "12:27:47:47.169"  # a line of a real take
    assert parse_timecode("12:27:47:47.169", 60) == pytest.approx(12 * 3600 + 27 * 60 + 47 + 47.169 / 60)
    assert format_timecode(1 - 1e-12, 30) == "00:00:01:00.000"
    for k in range(0, 300):
        assert parse_timecode(format_timecode(k / 30, 30), 30) == pytest.approx(k / 30, abs=1e-12)
    with pytest.raises(ValueError, match="timecode"):
        parse_timecode("00:00:01.5", 30)


def test_shuffled_and_lower_camel_columns_read_the_same(tmp_path):
    weights = arkit_weights(12, seed=4)
    path = write_livelink_csv(tmp_path / "take.csv", weights, 30)
    reference = read_livelink_csv(path)
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    order = np.random.default_rng(2).permutation(len(rows[0]))
    shuffled = tmp_path / "shuffled.csv"
    with open(shuffled, "w", newline="") as f:
        csv.writer(f, lineterminator="\r\n").writerows([[row[i] for i in order] for row in rows])
    names, values, timecodes = read_livelink_csv(shuffled)
    assert names == reference[0] and timecodes == reference[2]
    np.testing.assert_array_equal(values, reference[1])

    camel = tmp_path / "camel.csv"
    rows[0] = [n[0].lower() + n[1:] if n in LIVELINK_COLUMNS[:52] else n for n in rows[0]]
    with open(camel, "w", newline="") as f:
        csv.writer(f).writerows(rows)
    np.testing.assert_array_equal(read_livelink_csv(camel)[1], reference[1])


def test_missing_columns_and_bad_rows_are_clear_errors(tmp_path):
    path = write_livelink_csv(tmp_path / "take.csv", arkit_weights(4), 30)
    text = path.read_text()
    lines = text.split("\n")

    def variant(name, new_lines):
        p = tmp_path / name
        p.write_text("\n".join(new_lines))
        return p

    header = lines[0].split(",")
    drop = header.index("MouthLeft")
    cut = [",".join(c for i, c in enumerate(line.split(",")) if i != drop) for line in lines]
    with pytest.raises(ValueError, match=r"cut\.csv.*missing 1 column\(s\): MouthLeft"):
        read_livelink_csv(variant("cut.csv", cut))
    with pytest.raises(ValueError, match=r"short\.csv, line 3: 62 fields, the header has 63"):
        read_livelink_csv(variant("short.csv", lines[:2] + [lines[2].rsplit(",", 1)[0]] + lines[3:]))
    bad = lines[3].split(",")
    bad[header.index("JawOpen")] = "abc"
    with pytest.raises(ValueError, match=r"bad\.csv, line 4: column 'JawOpen' holds 'abc', not a number"):
        read_livelink_csv(variant("bad.csv", lines[:3] + [",".join(bad)] + lines[4:]))
    bad[header.index("JawOpen")] = "nan"
    with pytest.raises(ValueError, match=r"nan\.csv, line 4: column 'JawOpen'.*not a finite number"):
        read_livelink_csv(variant("nan.csv", lines[:3] + [",".join(bad)] + lines[4:]))
    with pytest.raises(ValueError, match=r"twice"):
        read_livelink_csv(variant("twice.csv", [lines[0] + ",JawOpen"] + [line + ",0" for line in lines[1:-1]]))
    with pytest.raises(ValueError, match=r"empty\.csv: empty file"):
        read_livelink_csv(variant("empty.csv", []))


def test_bad_weights_are_refused(tmp_path):
    good = arkit_weights(3)
    for weights, fps, match in [(good[:, :51], 30, "52"), (good * 2, 30, r"\[0, 1\]"), (good, 0, "fps"),
                                (good, True, "fps")]:
        with pytest.raises(ValueError, match=match):
            write_livelink_csv(tmp_path / "x.csv", weights, fps)
    assert not list(tmp_path.iterdir())
