"""Web-avatar JSON (visemeflow/animation/webjson.py): TalkingHead's animation template layout, read back."""

import json

import numpy as np
import pytest

from visemeflow.rig.character import character_from_rig
from visemeflow.animation.webjson import DECIMALS, read_web_json, write_web_json
from visemeflow.rig import load_demo_rig


def smooth_weights(n_frames: int, n_shapes: int, fps: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames)[:, None] / fps
    freq, phase = rng.uniform(0.2, 2.0, n_shapes), rng.uniform(0, 2 * np.pi, n_shapes)
    return (0.5 + 0.5 * np.sin(2 * np.pi * freq * t + phase)).astype(np.float32)


def talkinghead_key_times(template: dict) -> list[tuple[float, dict]]:
    """When each value of the template is reached, by TalkingHead's rule (animFactory): ts[0] = 0 carries the
    morph target's current value, ts[i + 1] = ts[i] + dt[i] carries vs[name][i]."""
    ts = [0.0]
    for step in template["dt"]:
        ts.append(ts[-1] + step)
    return [(ts[i + 1], {k: v[i] for k, v in template["vs"].items()}) for i in range(len(template["dt"]))]


@pytest.fixture(scope="module")
def demo_character():
    return character_from_rig(load_demo_rig())


def test_round_trip_with_the_characters_names(tmp_path, demo_character):
    fps = 30.0
    weights = smooth_weights(95, demo_character.n_shapes, fps)
    weights[0, 0], weights[1, 0] = 0.0, 1.0
    path = write_web_json(tmp_path / "hello.json", demo_character.shape_names, weights, fps, name="hello")
    names, read, read_fps = read_web_json(path)
    assert names == demo_character.shape_names
    assert read_fps == fps and read.shape == weights.shape and read.dtype == np.float32
    np.testing.assert_allclose(read, weights, rtol=0, atol=0.5 * 10.0 ** -DECIMALS + 1e-7)
    assert read[0, 0] == 0 and read[1, 0] == 1

    data = json.loads(path.read_text())
    assert list(data["vs"]) == list(demo_character.shape_names)  # exactly the character's names, in its order
    assert data["name"] == "hello" and data["fps"] == 30 and data["frames"] == 95 and data["delay"] == 0
    assert all(len(v) == 95 for v in data["vs"].values())
    assert all(len(repr(x).split(".")[-1]) <= DECIMALS for v in data["vs"].values() for x in v)


@pytest.mark.parametrize("fps", [30, 25, 60, 29.97])
def test_dt_puts_frame_k_at_k_over_fps(tmp_path, fps):
    n = 1800 if fps == 30 else 50
    weights = smooth_weights(n, 3, fps, seed=1)
    path = write_web_json(tmp_path / "a.json", ["viseme_PP", "jaw.open", "Mouth Smile"], weights, fps, name="a")
    data = json.loads(path.read_text())
    assert len(data["dt"]) == n and data["dt"][0] == 0
    np.testing.assert_allclose(data["dt"][1:], 1000 / fps, rtol=1e-15)
    # the template spans from the first frame (time 0) to the last one, (n - 1) / fps
    assert sum(data["dt"]) == pytest.approx((n - 1) * 1000 / fps, rel=1e-12)
    keys = talkinghead_key_times(data)
    for k in (0, 1, n // 2, n - 1):
        when, values = keys[k]
        assert when == pytest.approx(k * 1000 / fps, abs=1e-6)  # summed as TalkingHead sums: ns drift
        assert values["jaw.open"] == pytest.approx(weights[k, 1], abs=0.5 * 10.0 ** -DECIMALS + 1e-7)


def test_reads_fps_from_dt_without_the_field(tmp_path):
    path = write_web_json(tmp_path / "a.json", ["a", "b"], smooth_weights(4, 2, 25), 25, name="a")
    data = json.loads(path.read_text())
    del data["fps"], data["frames"]
    path.write_text(json.dumps(data))
    assert read_web_json(path)[2] == pytest.approx(25)


def test_bad_input_and_bad_files(tmp_path):
    good = smooth_weights(5, 2, 30)
    for names, weights, fps, match in [(["a", "a"], good, 30, "twice"), (["a", ""], good, 30, "non-empty"),
                                       (["a"], good, 30, r"\(frames > 0, 1\)"), (["a", "b"], good * 2, 30, r"\[0, 1\]"),
                                       (["a", "b"], good, -1, "fps"), (["a", "b"], good[:0], 30, "frames > 0")]:
        with pytest.raises(ValueError, match=match):
            write_web_json(tmp_path / "x.json", names, weights, fps, name="x")
    assert not (tmp_path / "x.json").exists()

    path = write_web_json(tmp_path / "ok.json", ["a", "b"], good, 30, name="ok")
    data = json.loads(path.read_text())
    for change, match in [(lambda d: d["vs"]["b"].pop(), r'"vs"\.b must hold 5 values'),
                          (lambda d: d["vs"]["a"].__setitem__(2, None), r'"vs"\.a holds None'),
                          (lambda d: d.__setitem__("frames", 7), r'"frames" says 7'),
                          (lambda d: d.pop("dt"), "not a TalkingHead animation template")]:
        broken = json.loads(json.dumps(data))
        change(broken)
        (tmp_path / "bad.json").write_text(json.dumps(broken))
        with pytest.raises(ValueError, match=r"bad\.json: " + match):
            read_web_json(tmp_path / "bad.json")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ValueError, match=r"bad\.json: not a readable JSON"):
        read_web_json(tmp_path / "bad.json")
