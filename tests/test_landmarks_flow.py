"""The `landmarks` stage on an ingested store: one cached task per utterance with a video and no landmark file,
rejects for videos without a usable face, the store's landmark files read back by the tracker's reader.

Uses ../shared/data/grid_s1 (fails, never skips, when it is missing)."""

import shutil
from pathlib import Path

import numpy as np
import pytest

from factories import SHARED_DATA, make_corpus
from visemeflow.tracking.facemesh import LIP_IDS, read_mediapipe478
from visemeflow.tracking.landmarks import read_landmarks
from visemeflow.tracking.video import read_video_frames, write_video

GRID = SHARED_DATA / "grid_s1"
HELLO = [("sil", 0.0, 0.2), ("HH", 0.2, 0.3), ("AH0", 0.3, 0.45), ("L", 0.45, 0.55), ("OW1", 0.55, 0.8), ("", 0.8, 1.0)]


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> Path:
    """1 s utterances with 25-frame videos: `s/face` (GRID bbaf2n), `s/noise` (no face), `s/brief` (the face on
    10 of 25 frames), `s/given` (a video with its own landmark file: not the stage's to detect)."""
    video, reference = GRID / "video" / "bbaf2n.mpg", GRID / "landmarks" / "bbaf2n.mediapipe478.csv"
    assert video.is_file() and reference.is_file(), f"test data {GRID} is missing"
    root = tmp_path_factory.mktemp("landmarks-corpus")
    make_corpus(root, {f"s/{name}": HELLO for name in ("face", "noise", "brief", "given")})
    frames = read_video_frames(video, 0, 25)
    write_video(root / "s" / "face.mp4", frames, 25)
    brief = frames.copy()
    brief[10:] = 90
    write_video(root / "s" / "brief.mp4", brief, 25)
    noise = np.random.default_rng(1).integers(0, 256, (25, 96, 128, 3), dtype=np.uint8)
    write_video(root / "s" / "noise.mp4", noise, 25)
    shutil.copyfile(root / "s" / "face.mp4", root / "s" / "given.mp4")
    shutil.copyfile(reference, root / "s" / "given.mediapipe478.csv")
    return root


@pytest.mark.flow
def test_landmarks_flow_detects_caches_and_rejects(corpus, tmp_path, prefect_harness):
    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.landmarks import LandmarksParams, landmarks_flow
    from visemeflow.flows.params import IngestParams
    from visemeflow.schemas import C
    from visemeflow.storage import Store

    store_root = tmp_path / "store"
    ingest_flow(IngestParams(corpus=corpus, store=store_root, n_shards=2))
    params = LandmarksParams(store=store_root, n_shards=2)
    first = landmarks_flow(params)
    assert first["utterances"] == 3 and first["detected"] == 1 and first["rejected"] == 2
    assert first["frames"] == 25 and first["frames_without_face"] == 0

    store = Store(store_root)
    rejects = {r[C.UTTERANCE_ID]: r for r in store.read_table("rejects", "landmarks").to_pylist()}
    assert set(rejects) == {"s/noise", "s/brief"}
    assert rejects["s/noise"][C.ERROR_TYPE] == "NoFace"
    assert "noise.mp4: no face found on any of its 25 frames" in rejects["s/noise"][C.MESSAGE]
    assert rejects["s/brief"][C.ERROR_TYPE] == "FaceMostlyLost"
    assert "only 10 of its 25 frames (40.0%)" in rejects["s/brief"][C.MESSAGE]
    assert rejects["s/brief"][C.PATH].endswith("brief.mp4")
    assert not store.has_landmarks("s/given") and not store.has_landmarks("s/noise")

    # the stored file: the 478 points per frame and the 68 the tracker reads from it
    path = store.landmark_path("s/face")
    stored = read_mediapipe478(path)
    reference = read_mediapipe478(GRID / "landmarks" / "bbaf2n.mediapipe478.csv")
    assert stored.n_frames == 25 and stored.detected.all()
    np.testing.assert_allclose(stored.times, np.arange(25) / 25, atol=1e-9)
    lips = list(LIP_IDS)
    err = np.linalg.norm(stored.points[:, lips] - reference.points[:25, lips], axis=-1)
    assert np.median(err) < 1.5   # the re-encoded clip against MediaPipe's run on the original
    track = read_landmarks(path)
    assert track.n_frames == 25 and track.valid.all() and track.source == "mediapipe478"

    before = path.stat().st_mtime_ns
    second = landmarks_flow(params)
    assert second["cached"] == 1 and second["detected"] == 0 and second["rejected"] == 2
    assert path.stat().st_mtime_ns == before

    path.unlink()   # a deleted file is detected again, not hidden by the cache
    third = landmarks_flow(params)
    assert third["detected"] == 1 and store.has_landmarks("s/face")

    # by hand: one utterance again (`visemeflow rerun ID --stage landmarks`), even when cached
    from visemeflow.flows.params import RerunParams
    from visemeflow.flows.rerun import rerun_flow
    from visemeflow.tasks.landmarks import LandmarksError

    before = path.stat().st_mtime_ns
    report = rerun_flow(RerunParams(utterance_id="s/face", stage="landmarks", store=store_root))
    assert report["utterance_id"] == "s/face" and path.stat().st_mtime_ns > before
    with pytest.raises(LandmarksError, match="brief.mp4"):
        rerun_flow(RerunParams(utterance_id="s/brief", stage="landmarks", store=store_root))
    ids = sorted(r[C.UTTERANCE_ID] for r in store.read_table("rejects", "landmarks").to_pylist())
    assert ids == ["s/brief", "s/noise"]   # the other utterance's reject kept, this one's listed once


@pytest.mark.flow
def test_landmarks_flow_ends_failed_when_no_video_has_a_face(corpus, tmp_path, prefect_harness):
    from visemeflow.flows.errors import StageFailed
    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.landmarks import LandmarksParams, landmarks_flow
    from visemeflow.flows.params import IngestParams

    only_noise = tmp_path / "corpus"
    (only_noise / "s").mkdir(parents=True)
    for ext in (".wav", ".TextGrid", ".mp4"):
        shutil.copyfile(corpus / "s" / f"noise{ext}", only_noise / "s" / f"noise{ext}")
    ingest_flow(IngestParams(corpus=only_noise, store=tmp_path / "store", n_shards=1))
    state = landmarks_flow(LandmarksParams(store=tmp_path / "store", n_shards=1), return_state=True)
    # the reason is in the message: a run of one file says why it failed
    assert state.is_failed() and state.message.startswith("landmarks: its one utterance failed: s/noise: ") and \
        state.message.endswith(" (see the rejects table)"), state.message
    with pytest.raises(StageFailed):
        state.result()


@pytest.mark.flow
def test_pipeline_detects_landmarks_before_tracking_a_video_without_a_landmark_file(corpus, tmp_path, prefect_harness):
    """`visemeflow pipeline` on a corpus whose video has no landmark file: the landmarks stage runs before track and
    the clip is tracked from the stored points; a second run of the pipeline is all cache hits."""
    from visemeflow.flows.params import PipelineParams
    from visemeflow.flows.pipeline import pipeline_flow
    from visemeflow.storage import Store

    clip = tmp_path / "corpus"
    (clip / "s").mkdir(parents=True)
    for ext in (".wav", ".TextGrid", ".mp4"):
        shutil.copyfile(corpus / "s" / f"face{ext}", clip / "s" / f"face{ext}")
    params = PipelineParams(corpus=clip, store=tmp_path / "store", n_shards=1)
    first = pipeline_flow(params)
    assert first["landmarks"]["detected"] == 1 and first["track"]["tracked"] == 1
    store = Store(tmp_path / "store")
    assert store.has_landmarks("s/face") and store.has_curves("tracked", "guided-fast", "s/face")
    second = pipeline_flow(params)
    assert second["landmarks"]["cached"] == 1 and second["track"]["cached"] == 1


@pytest.mark.flow
def test_pipeline_animates_an_unaligned_clip_from_its_unguided_curves(corpus, tmp_path, prefect_harness):
    """A video with its audio but no alignment and no landmark file, with a character: the pipeline ingests it without
    phones, detects its landmarks, tracks it unguided and animates the `unguided-fast` curves (not only the guided
    variant the configuration names)."""
    from visemeflow.flows.params import PipelineParams
    from visemeflow.flows.pipeline import pipeline_flow
    from visemeflow.rig import rig_data_path
    from visemeflow.storage import Store

    clip = tmp_path / "corpus"
    (clip / "s").mkdir(parents=True)
    for ext in (".wav", ".mp4"):
        shutil.copyfile(corpus / "s" / f"face{ext}", clip / "s" / f"face{ext}")
    from visemeflow.animation.package import AnimateConfig

    params = PipelineParams(corpus=clip, store=tmp_path / "store", n_shards=1,
                            characters=[rig_data_path("ict_visemes.npz")], animate=AnimateConfig(formats=("glb",)))
    result = pipeline_flow(params)
    assert result["ingest"]["unaligned"] == 1 and result["landmarks"]["detected"] == 1
    assert result["track"]["unguided"] == 1 and result["track"]["variants"] == "unguided-fast"
    store = Store(tmp_path / "store")
    assert store.has_curves("tracked", "unguided-fast", "s/face")
    assert result["animate"]["variant"] == "unguided-fast" and result["animate"]["packages"] == 1
    packages = [p for p in store.animation_dirs() if p.name == "face"]
    assert len(packages) == 1 and any(f.suffix == ".glb" for f in packages[0].iterdir())
