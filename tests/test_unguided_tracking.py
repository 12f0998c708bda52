"""Tracking on the frames' true times and without phoneme guidance, on real clips: a GRID clip (25 fps, constant) and
`talking_heads/1.mp4` (variable frame rate, first frame 33 ms after the audio) with their reference landmark CSVs,
in a tmp store through the track flow. Tests on ../shared/data fail (not skip) when it is missing."""

import shutil

import numpy as np
import pytest
import torch
from factories import SHARED_DATA

from visemeflow.hashing import files_hash
from visemeflow.rig import evaluate_rig, load_demo_rig
from visemeflow.schemas import PHONES, UTTERANCES, C, curves_array, table_from_rows
from visemeflow.schemas.ids import shard_of
from visemeflow.schemas.tables import NO_ALIGNMENT
from visemeflow.tracking.facemesh import mediapipe478_table, read_mediapipe478
from visemeflow.tracking.identity import mouth_opening as points_opening
from visemeflow.tracking.landmarks import mouth_opening, read_landmarks
from visemeflow.tracking.solver import TrackingConfig
from visemeflow.tracking.utterance import FrameTimeline, TrackingInputError, VideoInput, track_video
from visemeflow.tracking.video import frame_times, probe_video, read_video_frames, write_video
from visemeflow.visemes import N_VISEMES

GRID = SHARED_DATA / "grid_s1"
GRID_CLIP = "bbaf2n"
TALKING = SHARED_DATA / "talking_heads"
N_SHARDS = 2
CONFIG = TrackingConfig(fast_iterations=120)   # fewer than the default 200: test time; the flow default otherwise


def _need(*paths):
    for path in paths:
        assert path.is_file(), f"missing test data {path}"


def grid_files(name=GRID_CLIP):
    files = (GRID / "video" / f"{name}.mpg", GRID / "align" / f"{name}.align",
             GRID / "landmarks" / f"{name}.mediapipe478.csv")
    _need(*files)
    return files


def rig_opening(rig, curves: np.ndarray) -> np.ndarray:
    """(T,) inner-lip gap over mouth width of the rig's own landmarks under the curves (frontal view): how far the
    curves open the mouth, whichever visemes they use."""
    ids = np.asarray(rig.landmark_ids)
    has = ids >= 0
    points = np.full((len(curves), 68, 3), np.nan)
    points[:, has] = evaluate_rig(rig, torch.as_tensor(curves, dtype=torch.float32), ids[has]).numpy()
    return points_opening(points[:, :, :2])


def utterance_row(uid: str, video, landmarks, fps: float, n_frames: int, audio=None) -> dict:
    """An `utterances` row of a clip without an alignment, as ingest writes one."""
    info = probe_video(video)
    return {
        C.UTTERANCE_ID: uid, C.SPEAKER: uid.split("/")[0], C.LANGUAGE: "en", C.INVENTORY: None,
        C.AUDIO_PATH: str(audio or video), C.VIDEO_PATH: str(video), C.ALIGNMENT_PATH: "",
        C.ALIGNMENT_FORMAT: NO_ALIGNMENT, C.LANDMARK_PATH: str(landmarks) if landmarks else None,
        C.SAMPLE_RATE: info.audio_rate or 16000, C.DURATION_S: info.container_duration_s or info.duration_s,
        C.FPS: fps, C.N_FRAMES: n_frames, C.CONTENT_HASH: files_hash([str(video)] + ([str(landmarks)] if landmarks else [])),
        C.SPLIT: "train",
    }


def zeroed_video_with_audio(path):
    """A video (with an audio stream) whose container and index are intact but whose media data are zero bytes."""
    frames = [np.full((48, 64, 3), 20 * k, np.uint8) for k in range(10)]
    write_video(path, frames, 25, audio=np.zeros(6400, np.float32), audio_rate=16000)
    data = bytearray(path.read_bytes())
    at = data.index(b"mdat")
    size = int.from_bytes(data[at - 4:at], "big")
    data[at + 4:at - 4 + size] = bytes(size - 8)
    path.write_bytes(bytes(data))
    return path


@pytest.fixture(scope="module")
def rig():
    return load_demo_rig()


@pytest.fixture(scope="module")
def tracked(tmp_path_factory, prefect_harness):
    """Two track flow runs over: `s1/bbaf2n` (GRID, aligned: guided), `s1/late` (aligned, its phones run past the
    video), and clips without an alignment: `s1/bare` (the GRID clip, landmarks in the store as the landmarks
    stage leaves them), `th/1` (the VFR clip), `th/silent` (no audio track, no audio file), `th/zeroed` (no
    decodable frame)."""
    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.params import IngestParams, ProceduralParams, TrackParams
    from visemeflow.flows.procedural import procedural_flow
    from visemeflow.flows.track import track_flow
    from visemeflow.storage import Store

    tmp = tmp_path_factory.mktemp("unguided")
    corpus, raw, store_root = tmp / "corpus" / "s1", tmp / "raw", tmp / "store"
    corpus.mkdir(parents=True)
    raw.mkdir()
    video, align, landmarks = grid_files()
    for name in (GRID_CLIP, "late"):
        for src, suffix in ((video, ".mpg"), (align, ".align"), (landmarks, ".mediapipe478.csv")):
            shutil.copyfile(src, corpus / f"{name}{suffix}")
    ingest_flow(IngestParams(corpus=corpus.parent, store=store_root, n_shards=N_SHARDS))
    procedural_flow(ProceduralParams(store=store_root, n_shards=N_SHARDS))
    store = Store(store_root)

    # s1/late: its phones now end at 4 s, past the 3 s video (as if the label file ran past it)
    phones = store.read_table("phones", utterance_ids=["s1/late"]).to_pylist()
    phones[-1][C.END_S] = 4.0
    store.replace_utterance_rows("phones", shard_of("s1/late", N_SHARDS), "s1/late",
                                 table_from_rows(phones, PHONES))

    _need(TALKING / "1.mp4", TALKING / "1.mediapipe478.csv")
    shutil.copyfile(video, raw / "bare.mpg")
    # s1/bare has no landmark file: its points come from the store, as the landmarks stage writes them
    store.write_landmarks("s1/bare", mediapipe478_table(read_mediapipe478(landmarks)), provenance="reference")
    shutil.copyfile(TALKING / "1.mp4", raw / "1.mp4")
    shutil.copyfile(TALKING / "1.mediapipe478.csv", raw / "1.mediapipe478.csv")
    vfr = probe_video(raw / "1.mp4")
    write_video(raw / "silent.mp4", read_video_frames(raw / "1.mp4", 0, 10), 30)
    zeroed_video_with_audio(raw / "zeroed.mp4")
    rows = [
        utterance_row("s1/bare", raw / "bare.mpg", None, 25.0, 75),
        utterance_row("th/1", raw / "1.mp4", raw / "1.mediapipe478.csv", vfr.nominal_fps, vfr.grid_frames),
        utterance_row("th/silent", raw / "silent.mp4", None, 30.0, 10),
        utterance_row("th/zeroed", raw / "zeroed.mp4", None, 25.0, 10),
    ]
    for row in rows:
        uid = row[C.UTTERANCE_ID]
        store.replace_utterance_rows("utterances", shard_of(uid, N_SHARDS), uid, table_from_rows([row], UTTERANCES))

    params = TrackParams(store=store_root, n_shards=N_SHARDS, config=CONFIG)
    first = track_flow(params)
    second = track_flow(params)
    # new landmarks from the landmarks stage: that utterance is tracked again, the others stay cached
    store.write_landmarks("s1/bare", mediapipe478_table(read_mediapipe478(landmarks)), provenance="redetected")
    third = track_flow(params)
    assert third["tracked"] == 1 and third["cached"] == 2, third
    return store, first, second


# ---- the flow ------------------------------------------------------------------------------------------------------
@pytest.mark.flow
def test_clips_without_alignment_are_tracked_unguided_and_counted(tracked):
    store, first, second = tracked
    assert first["utterances"] == 6 and first["tracked"] == 3 and first["rejected"] == 3
    assert first["unguided"] == 2 and first["unguided_why"] == "2: no alignment"
    assert first["variant"] == "guided-fast" and first["variants"] == "guided-fast, unguided-fast"
    assert first["interpolated_frames"] == 49          # th/1: 184 grid frames, 135 shown
    # a second run finds each utterance's curves under its own variant: all cached
    assert second["cached"] == 3 and second["tracked"] == 0 and second["unguided"] == 2
    assert store.curve_variants("tracked", "s1/bbaf2n") == ["guided-fast"]
    for uid in ("s1/bare", "th/1"):
        assert store.curve_variants("tracked", uid) == ["unguided-fast"]
    assert "guided-fast" not in [v for uid in ("s1/bare", "th/1") for v in store.curve_variants("tracked", uid)]


@pytest.mark.flow
def test_bad_clips_are_rejects_naming_the_clip(tracked):
    store, first, _ = tracked
    rejects = {r[C.UTTERANCE_ID]: r for r in store.read_table("rejects", "track").to_pylist()}
    assert set(rejects) == {"s1/late", "th/silent", "th/zeroed"}
    late, silent, zeroed = rejects["s1/late"], rejects["th/silent"], rejects["th/zeroed"]
    assert late[C.ERROR_TYPE] == "AlignmentPastVideo" and late[C.PATH].endswith("late.align")
    assert "runs to 4.000 s" in late[C.MESSAGE] and "late.mpg ends at 3.000 s" in late[C.MESSAGE]
    assert silent[C.ERROR_TYPE] == "MissingAudio" and silent[C.PATH].endswith("silent.mp4")
    assert "no audio track" in silent[C.MESSAGE] and silent[C.MESSAGE].startswith("th/silent: ")
    assert zeroed[C.ERROR_TYPE] == "UnreadableVideo" and zeroed[C.PATH].endswith("zeroed.mp4")
    assert zeroed[C.MESSAGE].startswith("th/zeroed: ") and zeroed[C.MESSAGE].count("zeroed.mp4") == 1
    assert "video decoding failed" in zeroed[C.MESSAGE]


@pytest.mark.flow
def test_unguided_grid_curves_follow_the_mouth(tracked, rig):
    store, _, _ = tracked
    unguided = curves_array(store.read_curves("s1/bare", "tracked", "unguided-fast"))
    guided = curves_array(store.read_curves("s1/bbaf2n", "tracked", "guided-fast"))
    assert unguided.shape == guided.shape == (75, N_VISEMES)
    opening = mouth_opening(read_landmarks(grid_files()[2])).ratio
    r_unguided = np.corrcoef(rig_opening(rig, unguided), opening)[0, 1]
    r_guided = np.corrcoef(rig_opening(rig, guided), opening)[0, 1]
    print(f"GRID {GRID_CLIP}: r(rig opening, landmark opening) unguided {r_unguided:.3f}, guided {r_guided:.3f}")
    assert r_unguided > 0.9, r_unguided
    assert r_guided > 0.8, r_guided
    # different curves (no phoneme prior) opening the mouth alike
    assert np.abs(unguided - guided).mean() > 0.01
    assert np.corrcoef(rig_opening(rig, unguided), rig_opening(rig, guided))[0, 1] > 0.85


@pytest.mark.flow
def test_vfr_clip_is_tracked_on_its_frames_true_times(tracked, rig):
    store, _, _ = tracked
    table = store.read_curves("th/1", "tracked", "unguided-fast")
    curves = curves_array(table)
    assert curves.shape == (184, N_VISEMES)
    assert np.allclose(table.column(C.TIME_S).to_numpy(), np.arange(184) / 30.0)
    times = frame_times(TALKING / "1.mp4")
    shown = np.round(times * 30).astype(int)                  # the grid frame each decoded frame is shown at
    opening = mouth_opening(read_landmarks(TALKING / "1.mediapipe478.csv")).ratio
    tracked_opening = rig_opening(rig, curves)
    r_true = np.corrcoef(tracked_opening[shown], opening)[0, 1]
    r_index = np.corrcoef(tracked_opening[:135], opening)[0, 1]    # frame i read as grid frame i: wrong
    print(f"1.mp4: r(rig opening, landmark opening) on true times {r_true:.3f}, frame i as grid frame i {r_index:.3f}")
    assert r_true > 0.9, r_true
    assert r_index < r_true - 0.5, (r_index, r_true)
    # diagnostics: the 49 grid frames the video lacks (frame 0 before the first frame, one per dropped frame)
    frames = store.read_tracking_frames("unguided-fast", ["th/1"]).sort_by(C.FRAME).to_pylist()
    assert len(frames) == 184
    lacking = {r[C.FRAME] for r in frames if r[C.LOSS_PREFIX + "lmk"] is None}
    assert lacking == set(range(184)) - set(shown.tolist()) and 0 in lacking and len(lacking) == 49
    assert all(not r[C.LANDMARKS_VALID] and r[C.MOUTH_ERROR_PX] is None for r in frames if r[C.FRAME] in lacking)
    assert all(r[C.LANDMARKS_VALID] and r[C.MOUTH_ERROR_PX] < 6 for r in frames if r[C.FRAME] not in lacking)
    # a frame the video lacks lies between its neighbours (linear interpolation in time)
    gap = next(k for k in sorted(lacking) if k > 0)
    assert np.allclose(curves[gap], 0.5 * (curves[gap - 1] + curves[gap + 1]), atol=0.02)


# ---- the frame timeline and bad input, without solving --------------------------------------------------------------
def test_frame_timeline_on_the_real_clips():
    _need(TALKING / "1.mp4")
    vfr = FrameTimeline(frame_times(TALKING / "1.mp4"), 30.0, 184)
    index = vfr.video_frame()
    assert not vfr.uniform and (index < 0).sum() == 49 and index[0] == -1
    assert np.array_equal(index[index >= 0], np.arange(135))
    ramp = np.arange(184, dtype=np.float64)[:, None] / 30.0 * np.ones((1, 3))
    assert np.allclose(vfr.to_frames(ramp)[:, 0], np.clip(vfr.times, 0, 183 / 30))
    back = vfr.to_grid(vfr.to_frames(ramp))         # exact inside the frames' span, held outside it
    assert np.allclose(back[1:-1], ramp[1:-1]) and np.allclose(back[[0, -1], 0], vfr.times[[0, -1]])
    grid = FrameTimeline(frame_times(grid_files()[0]), 25.0, 75)
    assert grid.uniform and np.array_equal(grid.video_frame(), np.arange(75))


def test_bad_input_is_a_tracking_input_error_naming_the_file(tmp_path, rig):
    video, _, landmarks = grid_files()
    procedural = np.zeros((75, N_VISEMES), np.float32)

    def error(**kw):
        args = dict(video_path=str(video), landmark_path=str(landmarks), fps=25.0, n_frames=75)
        with pytest.raises(TrackingInputError) as caught:
            track_video(VideoInput(**{**args, **kw}), procedural if kw.get("n_frames", 75) == 75 else None,
                        rig, CONFIG)
        return caught.value

    late = error(alignment_path="x.align", alignment_end_s=3.5)
    assert late.error_type == "AlignmentPastVideo" and late.path == "x.align" and str(video) in late.reason
    short = error(n_frames=90)
    assert short.error_type == "ShortVideo" and short.path == str(video) and "3.600 s" in str(short)
    missing = error(audio_path=str(tmp_path / "gone.wav"))
    assert missing.error_type == "MissingAudio" and missing.path.endswith("gone.wav")
    silent = write_video(tmp_path / "silent.mp4", read_video_frames(video, 0, 5), 25)
    no_track = error(video_path=str(silent), audio_path=str(silent), n_frames=5)
    assert no_track.error_type == "MissingAudio" and no_track.path == str(silent)
    with pytest.raises(TrackingInputError, match="procedural curves have 75 frames, the video 74"):
        track_video(VideoInput(str(video), str(landmarks), 25.0, 74), procedural, rig, CONFIG)


def test_a_clip_is_probed_once_for_its_audio_and_camera(monkeypatch, rig):
    """track_video probes the video once (probing decodes a GRID .mpg to count its frames) and hands the result to
    the audio check and the camera fit."""
    import visemeflow.tracking.utterance as utterance

    video, _, landmarks = grid_files()
    probes = []
    probe = utterance.probe_video
    monkeypatch.setattr(utterance, "probe_video", lambda p: probes.append(p) or probe(p))
    config = TrackingConfig(fast_iterations=2, pose_iterations=2, use_flow=False)
    tracked = track_video(VideoInput(str(video), str(landmarks), 25.0, 75, audio_path=str(video)),
                          np.zeros((75, N_VISEMES), np.float32), rig, config)
    assert probes == [str(video)]
    assert tracked.camera_info["identity"] == "fitted"


def test_a_long_clip_reports_its_frames_and_solver_steps_as_it_goes(rig):
    """Tracking one clip said nothing for minutes; `on_step` hears the optical flow frame by frame and every solver
    step, and the task's StepLog turns that into throttled log lines with a rate and what is left."""
    from visemeflow.tasks.progress import StepLog

    video, _, landmarks = grid_files()
    heard = []
    config = TrackingConfig(fast_iterations=6, pose_iterations=2)
    track_video(VideoInput(str(video), str(landmarks), 25.0, 75, audio_path=str(video)),
                np.zeros((75, N_VISEMES), np.float32), rig, config, lambda *a: heard.append(a))
    flow = [(k, n) for phase, k, n in heard if phase == "optical flow"]
    solve = [(k, n) for phase, k, n in heard if phase == "solve"]
    assert flow == [(k, 75) for k in range(75)]
    assert solve == [(k, 6) for k in range(6)] and heard.index(("solve", 0, 6)) > heard.index(("optical flow", 74, 75))

    now = [0.0]
    lines = []
    log = StepLog("track[s1/x]", lines.append, interval=5.0, clock=lambda: now[0])
    for k in range(75):
        now[0] = k * 0.1                       # 10 frames a second
        log("optical flow", k, 75)
    for k in range(6):
        now[0] = 7.5 + k
        log("solve", k, 6)
    assert lines == ["track[s1/x]: optical flow 50/75 frames, 10/s, about 2 s left",
                     "track[s1/x]: solve 3/6 steps, 1/s, about 3 s left"]
    quiet = []
    off = StepLog("x", quiet.append, interval=float("inf"), clock=lambda: now[0])
    now[0] = 1e6
    off("solve", 3, 6)
    assert quiet == []


def test_the_flow_settings_of_the_tracking_config_reach_dis(monkeypatch, rig):
    """`TrackingConfig.flow_preset` / `flow_max_roi_px` / `flow_region` are what L_flow's DIS runs with (default:
    balanced, on the lower face, at the resolution that shrinks the whole face to 256 px; bench/end_to_end.py
    --compare-flow and --compare-config measured them)."""
    import visemeflow.tracking.utterance as utterance
    from visemeflow.tracking.optical_flow import clip_roi

    seen = []
    real = utterance.estimate_optical_flow

    def spy(frames, config, roi, scale_roi=None):
        seen.append((config, roi, scale_roi))
        return real(frames, config, roi, scale_roi=scale_roi)

    monkeypatch.setattr(utterance, "estimate_optical_flow", spy)
    video, _, landmarks = grid_files()
    for config in (TrackingConfig(fast_iterations=2, pose_iterations=2),
                   TrackingConfig(fast_iterations=2, pose_iterations=2, flow_preset="fast", flow_max_roi_px=64,
                                  flow_region="face")):
        tracked = track_video(VideoInput(str(video), str(landmarks), 25.0, 75), np.zeros((75, N_VISEMES), np.float32),
                              rig, config)
        assert np.isfinite(tracked.result.curves).all()
    assert [(c.preset, c.max_roi_px) for c, _, _ in seen] == [("balanced", 256), ("fast", 64)]
    track = utterance.load_track(str(landmarks), 25.0, 75, str(video))
    face, lower = (utterance.flow_roi(track, 360, 288, region) for region in ("face", "lower"))
    assert [(roi, scale_roi) for _, roi, scale_roi in seen] == [(lower, face), (face, face)]
    assert clip_roi(lower, 360, 288) == lower and lower[2] < face[2] and lower[3] < face[3]


def _track_4(rig, monkeypatch, quick):
    """talking_heads/4.mp4 tracked unguided on its reference landmarks (few solver steps), with the track stage's
    packet times replaced by `quick(real)`; (curves, the decoded frame_times calls, decoding passes)."""
    import visemeflow.tracking.utterance as utterance

    _need(TALKING / "4.mp4", TALKING / "4.mediapipe478.csv")
    real = utterance.packet_frame_times
    calls, passes = [], []
    monkeypatch.setattr(utterance, "packet_frame_times", lambda p: quick(real(p)))
    times = utterance.frame_times
    monkeypatch.setattr(utterance, "frame_times", lambda p: calls.append(p) or times(p))
    frames = utterance.iter_timed_frames
    monkeypatch.setattr(utterance, "iter_timed_frames", lambda p: passes.append(p) or frames(p))
    config = TrackingConfig(fast_iterations=4, pose_iterations=4)
    tracked = track_video(VideoInput(str(TALKING / "4.mp4"), str(TALKING / "4.mediapipe478.csv"), 30.0, 199),
                          None, rig, config)
    return tracked.result.curves, len(calls), len(passes)


def test_a_clip_whose_packets_give_its_frame_times_is_decoded_once_with_the_same_curves(rig, monkeypatch):
    """The track stage decoded a clip twice, once for its frame times and once for the flow (1.2 ms a 700x700 frame
    on talking_heads/4.mp4). The times now come from the packets, checked by the flow's one decoding pass; the curves
    are those of decoded times, bit for bit."""
    quick, n_times, n_passes = _track_4(rig, monkeypatch, lambda t: t)
    decoded, n_times_before, n_passes_before = _track_4(rig, monkeypatch, lambda t: None)
    assert (n_times, n_passes) == (0, 1) and (n_times_before, n_passes_before) == (1, 1)
    assert np.array_equal(quick, decoded)


@pytest.mark.parametrize("lie", ["later", "short", "long"])
def test_packet_times_that_the_decoded_frames_contradict_are_not_used(rig, monkeypatch, lie):
    """A container whose packets say other than its frames (a time off by a microsecond, a frame more or fewer than
    it decodes): the clip is prepared again on its decoded times, with the curves decoding gives."""
    def wrong(times):
        if lie == "later":
            return np.concatenate([times[:-1], times[-1:] + 1e-6])
        return times[:-1] if lie == "short" else np.append(times, times[-1] + 1 / 30)

    curves, n_times, n_passes = _track_4(rig, monkeypatch, wrong)
    decoded, _, _ = _track_4(rig, monkeypatch, lambda t: None)
    assert n_times == 1 and n_passes == 2
    assert np.array_equal(curves, decoded)
