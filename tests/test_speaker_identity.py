"""One identity per speaker in the track flow: fitted once per (speaker, image size) on a fixed choice of clips,
cached, part of every clip's tracking cache key; `rerun --stage track` uses the same one."""

import shutil

import numpy as np
import pytest
from factories import SHARED_DATA

from visemeflow.schemas import C, Curves
from visemeflow.visemes import N_VISEMES

pytestmark = [pytest.mark.flow, pytest.mark.usefixtures("prefect_harness")]

GRID = SHARED_DATA / "grid_s1"
CLIPS = ("bbaf2n", "bgin3a", "bwbg8n")


def grid_corpus(root):
    """Three GRID clips of speaker s1 (video, alignment, MediaPipe landmarks beside the video)."""
    speaker = root / "s1"
    speaker.mkdir(parents=True)
    for clip in CLIPS:
        shutil.copyfile(GRID / "video" / f"{clip}.mpg", speaker / f"{clip}.mpg")
        shutil.copyfile(GRID / "align" / f"{clip}.align", speaker / f"{clip}.align")
        shutil.copyfile(GRID / "landmarks" / f"{clip}.mediapipe478.csv", speaker / f"{clip}.mediapipe478.csv")
    return root


def ingest(corpus, store):
    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.params import IngestParams, ProceduralParams
    from visemeflow.flows.procedural import procedural_flow

    ingest_flow(IngestParams(corpus=corpus, store=store, n_shards=1))
    procedural_flow(ProceduralParams(store=store, n_shards=1))


@pytest.fixture
def counted(monkeypatch):
    """Identity fits and per-clip tracking calls (the tracking itself faked: only what it is given matters)."""
    from visemeflow.tasks import track as track_task

    calls = {"fits": [], "tracked": {}}
    real_fit = track_task.fit_speaker_identity

    def fit(rig, modes, clips, image_size, total_frames=10, **options):
        calls["fits"].append(sorted(uid for uid, _ in clips))
        return real_fit(rig, modes, clips, image_size, total_frames, **options)

    def track_one(store, utterance, procedural_variant, rig, config, on_step=None, identity=None):
        uid = utterance[C.UTTERANCE_ID]
        calls["tracked"][uid] = identity
        curves = np.zeros((int(utterance[C.N_FRAMES]), N_VISEMES), np.float32)
        store.save_curves(Curves(curves, utterance[C.FPS], uid, track_task.SOURCE, config.variant,
                                 track_task.tracked_provenance(utterance, config, identity)))
        return {"utterance_id": uid, "frames": int(utterance[C.N_FRAMES]), "seconds": 0.0, "mouth_error_px": 1.0,
                "variant": config.variant, "guided": True, "unguided_reason": None, "interpolated_frames": 0}

    def track_many(store, utterances, procedural_variant, rig, config, identities=None, on_step=None):
        # the joint path (TrackParams.joint_frames): each utterance with its own identity
        identities = identities or [None] * len(utterances)
        return [track_one(store, u, procedural_variant, rig, config, identity=i) for u, i in zip(utterances, identities)]

    monkeypatch.setattr(track_task, "fit_speaker_identity", fit)
    monkeypatch.setattr(track_task, "track_one", track_one)
    monkeypatch.setattr(track_task, "track_many", track_many)
    return calls


def test_one_identity_fit_per_speaker_cached_keyed_and_used_by_rerun(tmp_path, counted):
    from visemeflow.flows.params import RerunParams, TrackParams
    from visemeflow.flows.rerun import rerun_flow
    from visemeflow.flows.track import track_flow
    from visemeflow.tracking.solver import TrackingConfig

    corpus, store = grid_corpus(tmp_path / "corpus"), tmp_path / "store"
    ingest(corpus, store)
    params = TrackParams(store=store, config=TrackingConfig(speaker_identity=True, identity_clips=2))
    first = track_flow(params)
    assert first["tracked"] == 3
    assert counted["fits"] == [["s1/bbaf2n", "s1/bgin3a"]]          # one fit, the first 2 clips by id
    identities = counted["tracked"]
    assert set(identities) == {f"s1/{c}" for c in CLIPS}
    digests = {i.digest for i in identities.values()}
    assert len(digests) == 1 and None not in identities.values()
    (identity,) = {i for i in identities.values()}
    assert identity.clips == ("s1/bbaf2n", "s1/bgin3a") and identity.image_size == (360, 288)

    counted["fits"].clear(), counted["tracked"].clear()
    assert track_flow(params)["cached"] == 3 and not counted["fits"] and not counted["tracked"]

    # rerun of one utterance: the same (cached) speaker identity
    rerun_flow(RerunParams(utterance_id="s1/bwbg8n", stage="track", store=store))
    assert not counted["fits"] and counted["tracked"]["s1/bwbg8n"].digest == identity.digest

    # a changed landmark file of a chosen clip: a new identity, and every clip of the speaker tracked again
    counted["tracked"].clear()
    table = corpus / "s1" / "bgin3a.mediapipe478.csv"
    lines = table.read_text().splitlines()
    x = lines[0].split(",").index("x_0")
    rows = [line.split(",") for line in lines[1:]]
    for row in rows:        # the face 1.5 px further right in every frame
        row[x:x + 478] = [v if v in ("", "nan") else f"{float(v) + 1.5:.4f}" for v in row[x:x + 478]]
    table.write_text("\n".join([lines[0], *(",".join(row) for row in rows)]) + "\n")
    ingest(corpus, store)
    again = track_flow(params)
    assert len(counted["fits"]) == 1 and again["tracked"] == 3
    assert {i.digest for i in counted["tracked"].values()} != {identity.digest}


def test_identity_off_or_without_neutral_frames_fits_per_clip(tmp_path, counted):
    from visemeflow.flows.params import TrackParams
    from visemeflow.flows.track import track_flow
    from visemeflow.tracking.solver import TrackingConfig

    corpus, store = grid_corpus(tmp_path / "corpus"), tmp_path / "store"
    ingest(corpus, store)
    track_flow(TrackParams(store=store))                       # the default: per clip, as before
    assert not counted["fits"] and set(counted["tracked"].values()) == {None}

    counted["tracked"].clear()
    from visemeflow.tasks import track as track_task

    real = track_task.speaker_identity
    track_task_patch = pytest.MonkeyPatch()
    try:   # a speaker none of whose clips has a neutral frame: the clips are fitted one by one, as without it
        track_task_patch.setattr(track_task, "speaker_identity", lambda *a, **k: None)
        track_flow(TrackParams(store=store, config=TrackingConfig(speaker_identity=True)))
    finally:
        track_task_patch.undo()
    assert set(counted["tracked"].values()) == {None} and len(counted["tracked"]) == 3
    assert real is track_task.speaker_identity


def test_curves_another_config_wrote_over_are_tracked_again(tmp_path, counted):
    """One variant folder holds the tracked curves of every flow region, preset and size: after `track
    --flow-region face`, a track with the default settings again must not take the face run's curves for its
    own cached ones (it did: "cached", with the other run's curves on disk)."""
    from visemeflow.flows.params import TrackParams
    from visemeflow.flows.track import track_flow
    from visemeflow.storage import Store
    from visemeflow.tasks import track as track_task
    from visemeflow.tracking.solver import TrackingConfig

    corpus, store = grid_corpus(tmp_path / "corpus"), tmp_path / "store"
    ingest(corpus, store)
    default, face = TrackingConfig(), TrackingConfig(flow_region="face")
    assert default.variant == face.variant
    assert track_flow(TrackParams(store=store, config=default))["tracked"] == 3
    assert track_flow(TrackParams(store=store, config=face))["tracked"] == 3
    again = track_flow(TrackParams(store=store, config=default))
    assert again["tracked"] == 3 and again["cached"] == 0
    stored = Store(store)
    for uid in counted["tracked"]:
        row = next(r for r in stored.read_table("utterances").to_pylist() if r[C.UTTERANCE_ID] == uid)
        assert stored.curves_provenance(track_task.SOURCE, default.variant, uid) == \
            track_task.tracked_provenance(row, default, None)
    assert track_flow(TrackParams(store=store, config=default))["cached"] == 3
