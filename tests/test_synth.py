"""The synthetic corpus: takes (curves, landmarks, frames) and the `synth` flow feeding the pipeline."""

import json
import shutil

import numpy as np
import pytest

from factories import DEMO_CORPUS
from visemeflow.phonetics.types import VisemeSegment
from visemeflow.rig import load_demo_rig
from visemeflow.synth.take import SynthConfig, make_take, render_take
from visemeflow.visemes import viseme_index

SEGMENTS = [VisemeSegment("MBP", 0.30, 0.38, 0), VisemeSegment("AHH", 0.38, 0.60, 0), VisemeSegment("UUU", 0.60, 0.80, 0)]


@pytest.fixture(scope="module")
def rig():
    return load_demo_rig()


def test_take_is_reproducible_and_landmarks_follow_the_mouth(rig):
    config = SynthConfig(landmark_noise_px=0.0, landmark_miss_rate=0.0)
    a = make_take(rig, SEGMENTS, 30, "spk", "spk/u", config)
    b = make_take(rig, SEGMENTS, 30, "spk", "spk/u", config)
    assert np.array_equal(a.curves, b.curves) and np.array_equal(a.landmarks.points, b.landmarks.points, equal_nan=True)
    pts = a.true_landmarks
    gap = np.linalg.norm(pts[:, 62] - pts[:, 66], axis=1)  # inner lips, Multi-PIE ids
    k_closed = int(np.argmax(a.curves[:, viseme_index("MBP")]))
    k_open = int(np.argmax(a.curves[:, viseme_index("AHH")]))
    assert gap[k_open] > gap[k_closed] + 2.0  # pixels: the jaw opens visibly between the closure and the vowel


def test_landmark_noise_and_misses(rig):
    config = SynthConfig(landmark_noise_px=1.5, landmark_miss_rate=0.2)
    take = make_take(rig, SEGMENTS, 200, "spk", "spk/u", config)
    valid = take.landmarks.valid
    missed = ~valid.any(axis=1)
    assert 0.1 < missed.mean() < 0.3
    err = (take.landmarks.points - take.true_landmarks)[valid]
    assert 1.2 < err.std() < 1.8


def test_frames_show_the_face_where_the_landmarks_are(rig):
    config = SynthConfig(landmark_noise_px=0.0, landmark_miss_rate=0.0)
    take = make_take(rig, SEGMENTS, 6, "spk", "spk/u", config)
    frames = list(render_take(rig, take))
    assert len(frames) == 6 and frames[0].shape == (288, 360, 3) and frames[0].dtype == np.uint8
    background = frames[0][0, 0]
    face = np.any(frames[0] != background, axis=2)
    assert 0.05 < face.mean() < 0.8
    pts = take.true_landmarks[0]
    inside = [face[int(round(y)), int(round(x))] for x, y in pts[np.isfinite(pts).all(axis=1)]]
    assert np.mean(inside) > 0.95
    assert not np.array_equal(frames[0], frames[5])  # the mouth and head move


@pytest.mark.flow
def test_synth_flow_then_pipeline_on_the_synthetic_corpus(tmp_path, prefect_harness):
    from visemeflow.flows.params import PipelineParams, SynthParams
    from visemeflow.flows.pipeline import pipeline_flow
    from visemeflow.flows.synth import synth_flow
    from visemeflow.schemas import C, curves_array
    from visemeflow.storage import Store
    from visemeflow.tracking.landmarks import read_landmarks
    from visemeflow.tracking.video import probe_video

    source = tmp_path / "source" / "zh"
    source.mkdir(parents=True)
    for ext in (".wav", ".TextGrid"):
        shutil.copyfile(DEMO_CORPUS / "SSB1624" / f"SSB16240001{ext}", source / f"SSB16240001{ext}")
    out, store = tmp_path / "synth", tmp_path / "store"
    summary = synth_flow(SynthParams(corpus=source.parent, out=out, store=store))
    assert summary["rendered"] == 1 and summary["failed"] == 0

    folder = out / "zh"
    video = probe_video(folder / "SSB16240001.mp4")
    truth = Store(store).read_curves("zh/SSB16240001", "ground_truth")
    assert video.fps == 25 and video.n_frames == truth.num_rows == 43  # 1.73 s of audio at 25 fps
    assert video.has_audio
    track = read_landmarks(folder / "SSB16240001.landmarks.parquet")
    assert track.points.shape == (43, 68, 2)
    camera = json.loads((folder / "SSB16240001.camera.json").read_text())
    assert camera["width"] == 360 and len(camera["translations"]) == 43

    again = synth_flow(SynthParams(corpus=source.parent, out=out, store=store))
    assert again["cached"] == 1 and again["rendered"] == 0

    result = pipeline_flow(PipelineParams(corpus=out, store=store, n_shards=2))
    assert result["ingest"]["ingested"] == 1 and result["procedural"]["generated"] == 1
    row = Store(store).read_table("utterances").to_pylist()[0]
    assert row[C.FPS] == 25 and row[C.N_FRAMES] == 43 and row[C.VIDEO_PATH].endswith(".mp4")
    assert row[C.LANDMARK_PATH].endswith(".landmarks.parquet")
    procedural = curves_array(Store(store).read_curves("zh/SSB16240001", "procedural"))
    gt = curves_array(truth)
    assert procedural.shape == gt.shape
    active = procedural.max(axis=1) > 0.5
    assert (procedural.argmax(axis=1) == gt.argmax(axis=1))[active].mean() > 0.4
