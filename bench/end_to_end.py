"""Benchmark: video -> tracked curves end to end on one core (issue 15): decoding, FaceMesh detection, identity
fit, optical flow and the solver, per clip, with the share of each step.

Run:  .venv/bin/python bench/end_to_end.py [--repeats R] [--clips N] [--no-pin] [--compare] [--joint N]
                                            [--compare-flow PRESET:ROI] [--compare-config JSON] [--compare-storage]
                                            [--compare-mesh JSON] [--compare-overheads] [--compare-times]

Prints tables and never asserts; the exit status is 0 whatever the figures are. Threads are pinned to one
(OMP/MKL/OpenBLAS env set before numpy and torch are imported, torch.set_num_threads(1)) and the process to one
CPU (os.sched_setaffinity, so MediaPipe's and FFmpeg's own threads share it), as bench/tracking.py and
bench/landmarks.py do: every frames/s is per core.

Clips: ../shared/data/grid_s1/video/*.mpg with their align/*.align (360x288, 25 fps, 75 frames: guided) and
../shared/data/talking_heads/{1,4}.mp4 (700x700; no alignment: unguided; 1.mp4 variable frame rate). They are
copied into a temporary corpus and ingested in-process (`ingest_utterance`), the GRID procedural curves made as the
procedural task makes them (`generate_procedural_curves` of the phones' viseme segments on the utterance's grid);
none of that is timed. What is timed is what the pipeline runs per utterance, the product's own functions:
  landmarks stage  `tasks.landmarks.landmarks_one` (FaceMesh `detect_video` on the file, the 478-point table
                   written to a temporary Store)
  track stage      `tracking.utterance.track_video` on the `VideoInput` `tasks.track.track_one` builds (the stored
                   landmark file, the alignment's end), default TrackingConfig (fast solver, L_flow on), the demo
                   rig; guided with the procedural curves, unguided (None) without an alignment.
(Writing the tracked curves and diagnostics to the store is not timed: a few kB.) `--joint N`: the track stage
as the pipeline runs it by default, `tracking.utterance.track_videos` on groups of N clips of a set (one joint
solve; the pipeline's `--joint-frames 400` makes groups of 5 GRID clips), a group's time shared over its clips.

Steps are split by wrapping the functions those two call (exclusive time: a step's time excludes the steps it
calls), so the split is of exactly the code the pipeline runs:
  decode           every video decode and demux: frame times, decoded frames (in the landmarks stage and in
                   tracking), `probe_video` (frame count: GRID's .mpg stores none, so probing decodes the clip)
  detection        MediaPipe FaceMesh (graph start, face-detector probes, the mesh per frame) and the face choice
  landmark I/O     writing the 478-point table to the store (Parquet) and reading it back (`load_track`)
  identity         `rig_and_camera` without its probe: the identity + focal fit on neutral frames; with
                   TrackingConfig(speaker_identity=True) applying the speaker's identity, plus the clip's share
                   (by frames) of its (speaker, image size) group's one fit (`tasks.track.speaker_identity`, timed
                   apart, best of R: --compare-config '{"speaker_identity": true}')
  flow             `flow_term`: DIS optical flow both ways and the forward-backward masks on the face region
  solver           `solve_fast`: pose initialisation and the Adam iterations
  other            the rest (checks, interpolation onto the curve grid of a variable-rate clip, ...)
--compare-overheads: "before" runs three pieces as they were until 2026-11-29, kept below as references: FaceMesh's
landmarks read by Python's loop over the message, the backward flow's forward-backward mask made for every pair
(the fast solver never reads it; here forced right after the flow, from the stored flows, which adds their float16
-> float32 conversion, about 0.1 ms a frame on the talking heads), and the flow sampled by three index arrays;
"after" the product's code. The curves must be identical (the largest difference is printed).
--compare-times: "before" has the track stage decode the clip for its frame times (`frame_times`), as it did until
2026-12-05; "after" reads them from the packets (`video.packet_frame_times`) and checks them against the flow's own
decoding. The curves must be identical.
Frames: a clip's frames are its curve grid's; a variable-rate clip (talking_heads/1.mp4: 135 frames on a 184-frame
grid) holds fewer, and the frames/s of the frames the videos hold is printed beside it.
--compare also runs every clip with the fast solver's other method, TrackingConfig(fast_method="lm")
(Levenberg-Marquardt, issue 29), as "after", beside the default Adam with cosine decay (50 pose + 200 joint
steps, "before"); same code otherwise. Before and after alternate clip by clip in the same run. Their accuracy is printed
side by side: the mean mouth keypoint error (the 20 mouth points of the tracked face to the detected landmarks,
px) per set, and on GRID the MBP activation: at the midpoint frame of every phone whose viseme is MBP (b, p, m),
the share where MBP is the tracked top viseme and among the top two; and the largest curve difference per clip.
Each clip runs R times (default 3); per clip the run with the least total wall time is kept (its steps), the
spread is (slowest - fastest) / fastest of the R totals. Wall clock on a shared machine also counts other jobs'
turns on the core: the CPU-time total (all of the process's threads) is printed too.
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_name] = "1"

import argparse  # noqa: E402
import functools  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402

from cpu import pin_one_core  # noqa: E402  (bench/, this script's folder)
import torch  # noqa: E402

torch.set_num_threads(1)

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import visemeflow.tracking.facemesh as facemesh_mod  # noqa: E402
import visemeflow.tracking.optical_flow as optical_flow  # noqa: E402
import visemeflow.tracking.utterance as utterance_mod  # noqa: E402
import visemeflow.tracking.video as video_mod  # noqa: E402
import visemeflow.tasks.landmarks as landmarks_task  # noqa: E402
from visemeflow.ingest import discover_corpus, ingest_utterance  # noqa: E402
from visemeflow.ingest.config import IngestConfig  # noqa: E402
from visemeflow.phonetics.types import VisemeSegment  # noqa: E402
from visemeflow.procedural import generate_procedural_curves  # noqa: E402
from visemeflow.rig import load_demo_rig  # noqa: E402
from visemeflow.schemas import C  # noqa: E402
from visemeflow.storage import Store  # noqa: E402
from visemeflow.tracking.facemesh import FaceMeshConfig  # noqa: E402
from visemeflow.tracking.solver import TrackingConfig  # noqa: E402
from visemeflow.tracking.utterance import VideoInput, track_video, track_videos, video_size  # noqa: E402
from visemeflow.tasks.track import identity_clips, speaker_identity  # noqa: E402

DATA = REPO.parent / "shared" / "data"
GRID = DATA / "grid_s1"
HEADS = DATA / "talking_heads"
STEPS = ("decode", "detection", "landmark I/O", "identity", "flow", "solver", "other")


# ---- exclusive-time profiler over wrapped functions ---------------------------------------------------------------

class Profile:
    """Exclusive wall time per step of the wrapped functions (a step's time excludes the wrapped calls it makes)."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self.cpu: dict[str, float] = defaultdict(float)
        self._stack: list[list[float]] = []     # [start wall, start CPU, wall of wrapped children, their CPU]

    def enter(self) -> None:
        self._stack.append([time.perf_counter(), time.process_time(), 0.0, 0.0])

    def leave(self, step: str) -> None:
        start, start_cpu, children, children_cpu = self._stack.pop()
        elapsed, elapsed_cpu = time.perf_counter() - start, time.process_time() - start_cpu
        self.seconds[step] += elapsed - children
        self.cpu[step] += elapsed_cpu - children_cpu
        if self._stack:
            self._stack[-1][2] += elapsed
            self._stack[-1][3] += elapsed_cpu


PROFILE = Profile()
PAPER_FRAMES = 16 * 3600 * 25
"""The paper's corpus: 16 hours of 25-fps video."""


def _wrap(fn, step: str):
    @functools.wraps(fn)
    def timed(*args, **kwargs):
        PROFILE.enter()
        try:
            return fn(*args, **kwargs)
        finally:
            PROFILE.leave(step)
    return timed


def _wrap_iter(fn, step: str):
    """A generator function whose every `next` counts to `step` (decoding frames one at a time)."""
    @functools.wraps(fn)
    def timed(*args, **kwargs):
        it = iter(fn(*args, **kwargs))
        while True:
            PROFILE.enter()
            try:
                item = next(it)
            except StopIteration:
                return
            finally:
                PROFILE.leave(step)
            yield item
    return timed


def install_profile() -> None:
    """Wrap, in the modules that call them, the functions each step consists of."""
    patches = [
        # decoding (every module that imported the functions keeps its own reference)
        (video_mod, "_decode_timed", _wrap, "decode"),
        (video_mod, "_packet_times", _wrap, "decode"),
        (video_mod, "probe_video", _wrap, "decode"),
        (utterance_mod, "probe_video", _wrap, "decode"),
        (utterance_mod, "read_timed_frames", _wrap, "decode"),
        (utterance_mod, "frame_times", _wrap, "decode"),
        (video_mod, "frame_times", _wrap, "decode"),
        (video_mod, "read_timed_frames", _wrap, "decode"),
        (video_mod, "iter_video_frames", _wrap_iter, "decode"),
        (video_mod, "iter_timed_frames", _wrap_iter, "decode"),      # the landmarks stage's (imported when run)
        (utterance_mod, "iter_timed_frames", _wrap_iter, "decode"),  # the flow's
        (utterance_mod, "packet_frame_times", _wrap, "decode"),
        # detection: the landmarks stage's detect_video (decode inside it is subtracted)
        (landmarks_task, "detect_video", _wrap, "detection"),
        (landmarks_task, "mediapipe478_table", _wrap, "landmark I/O"),
        (Store, "write_landmarks", _wrap, "landmark I/O"),
        (utterance_mod, "load_track", _wrap, "landmark I/O"),
        (utterance_mod, "rig_and_camera", _wrap, "identity"),
        (utterance_mod, "flow_term", _wrap, "flow"),
        (utterance_mod, "solve_fast", _wrap, "solver"),
        (utterance_mod, "solve_fast_many", _wrap, "solver"),
    ]
    for owner, name, wrapper, step in patches:
        if hasattr(owner, name):
            setattr(owner, name, wrapper(getattr(owner, name), step))


# ---- the pieces as they were, for --compare-overheads ------------------------------------------------------------

def landmark_xyz_loop(face) -> np.ndarray:
    """FaceMesh's landmarks as read until 2026-11-29: Python's loop over the message."""
    return np.array([(p.x, p.y, p.z) for p in face.landmark], dtype=np.float64).reshape(-1, 3)


def sample_flows_indexed(flows: np.ndarray, valid, pts: np.ndarray):
    """`optical_flow._sample_flows` until 2026-11-29: the four neighbours read by three index arrays."""
    p, n = pts.shape[:2]
    h, w = flows.shape[1:3]
    out = np.zeros((p, n, 2), dtype=np.float32)
    ok = np.isfinite(pts).all(axis=2)
    ok &= (pts[..., 0] >= 0) & (pts[..., 0] <= w - 1) & (pts[..., 1] >= 0) & (pts[..., 1] <= h - 1)
    pair, idx = np.nonzero(ok)
    if len(idx) == 0:
        return out, ok
    x, y = pts[pair, idx, 0], pts[pair, idx, 1]
    x0 = np.minimum(np.floor(x).astype(np.intp), w - 1)
    y0 = np.minimum(np.floor(y).astype(np.intp), h - 1)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    ax, ay = (x - x0)[:, None], (y - y0)[:, None]
    f00 = flows[pair, y0, x0].astype(np.float64)
    f01 = flows[pair, y0, x1].astype(np.float64)
    f10 = flows[pair, y1, x0].astype(np.float64)
    f11 = flows[pair, y1, x1].astype(np.float64)
    val = (1 - ay) * ((1 - ax) * f00 + ax * f01) + ay * ((1 - ax) * f10 + ax * f11)
    good = np.isfinite(val).all(axis=1)
    if valid is not None:
        good &= valid[pair, y0, x0] & valid[pair, y0, x1] & valid[pair, y1, x0] & valid[pair, y1, x1]
    ok[pair, idx] = good
    out[pair[good], idx[good]] = val[good].astype(np.float32)
    return out, ok


def with_backward_masks(estimate):
    """`estimate_optical_flow` that makes every backward mask at once, as it did until 2026-11-29."""
    @functools.wraps(estimate)
    def eager(*args, **kwargs):
        field = estimate(*args, **kwargs)
        field.backward_valid
        return field
    return eager


# ---- clips --------------------------------------------------------------------------------------------------------

@dataclass
class Clip:
    set_name: str
    utterance: dict
    procedural: np.ndarray | None
    alignment_end_s: float | None
    mbp_times: list[float] = field(default_factory=list)    # midpoints of the MBP phones, seconds
    video_frames: int = 0    # frames the video holds (its landmark rows); a variable-rate clip's grid has more
    runs: dict[str, list[tuple[float, float, dict]]] = field(default_factory=dict)   # path: (wall, cpu, steps)

    @property
    def uid(self) -> str:
        return self.utterance[C.UTTERANCE_ID]

    @property
    def frames(self) -> int:
        return int(self.utterance[C.N_FRAMES])


def build_corpus(tmp: Path, limit: int | None) -> list[Clip]:
    grid_dir, heads_dir = tmp / "corpus" / "s1", tmp / "corpus" / "talking_heads"
    grid_dir.mkdir(parents=True)
    heads_dir.mkdir(parents=True)
    videos = sorted((GRID / "video").glob("*.mpg"))[:limit]
    for v in videos:
        align = GRID / "align" / f"{v.stem}.align"
        if align.is_file():
            shutil.copyfile(v, grid_dir / v.name)
            shutil.copyfile(align, grid_dir / align.name)
    for name in ("1.mp4", "4.mp4"):
        if (HEADS / name).is_file():
            shutil.copyfile(HEADS / name, heads_dir / name)
    discovery = discover_corpus(tmp / "corpus")
    clips = []
    for entry in discovery.entries:
        ingested = ingest_utterance(entry, IngestConfig())
        u = ingested.utterance
        segments = [VisemeSegment(p["viseme"], p["start_s"], p["end_s"], p["word_index"], p["phoneme"] or "")
                    for p in ingested.phones if p["viseme"] is not None]
        guided = bool(ingested.phones)
        procedural = generate_procedural_curves(segments, int(u[C.N_FRAMES]), float(u[C.FPS])) if guided else None
        end = max(float(p["end_s"]) for p in ingested.phones) if guided else None
        name = "GRID 360x288 guided" if entry.speaker == "s1" else "talking_heads 700x700 unguided"
        mbp = [0.5 * (p["start_s"] + p["end_s"]) for p in ingested.phones if p["viseme"] == "MBP"]
        clips.append(Clip(name, u, procedural, end, mbp))
    return clips


def fit_identities(clips: list[Clip], store: Store, rig, config: TrackingConfig, mesh: FaceMeshConfig,
                   repeats: int) -> tuple[dict, dict]:
    """With `config.speaker_identity`: each (speaker, image size) group's identity, fitted as the track flow's
    identity task fits it (`tasks.track.speaker_identity` on the landmarks stage's files of the first
    `identity_clips` clips by id), best of `repeats` timed; and per clip its share of that time (wall, CPU; in
    proportion to its frames), which run_clip adds to its identity step. ({}, {}) without the option."""
    if not config.speaker_identity:
        return {}, {}
    groups: dict[tuple, list[Clip]] = {}
    for clip in clips:
        landmarks_task.landmarks_one(store, clip.utterance, mesh)
        key = (clip.utterance[C.SPEAKER], *video_size(clip.utterance[C.VIDEO_PATH]))
        groups.setdefault(key, []).append(clip)
    identities, shares = {}, {}
    for key, members in sorted(groups.items()):
        rows = identity_clips([{C.UTTERANCE_ID: c.uid, C.LANDMARK_PATH: str(store.landmark_path(c.uid)),
                                C.FPS: c.utterance[C.FPS]} for c in members], config.identity_clips)
        best = None
        for _ in range(repeats):
            wall, cpu = time.perf_counter(), time.process_time()
            identity = speaker_identity(rows, key[1:], rig, config.identity_frames)
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            best = (wall, cpu) if best is None or wall < best[0] else best
        frames = sum(c.frames for c in members)
        print(f"speaker identity {key[0]} {key[1]}x{key[2]}: {len(members)} clips, "
              + ("none (no neutral frame)" if identity is None else
                 f"{identity.frames} frames of {len(identity.clips)} clips, rms {identity.rms_px:.2f} px, focal "
                 f"{identity.focal:.0f} px")
              + f"; fit {best[0]:.3f} s wall, {best[1]:.3f} s CPU (best of {repeats})")
        for c in members:
            identities[c.uid] = identity
            shares[c.uid] = (best[0] * c.frames / frames, best[1] * c.frames / frames)
    return identities, shares


def run_clip(clip: Clip, store: Store, rig, config: TrackingConfig, mesh: FaceMeshConfig,
             identity=None, share: tuple[float, float] = (0.0, 0.0)) -> tuple[float, float, dict]:
    """One clip through the landmarks stage and the track stage, as the pipeline runs them (with the speaker's
    `identity` when given, `share` of its fit's wall and CPU seconds counted to the identity step)."""
    u = clip.utterance
    PROFILE.reset()
    wall, cpu = time.perf_counter(), time.process_time()
    PROFILE.enter()
    landmarks_task.landmarks_one(store, u, mesh)
    video = VideoInput(u[C.VIDEO_PATH], str(store.landmark_path(clip.uid)), u[C.FPS], int(u[C.N_FRAMES]),
                       audio_path=u.get(C.AUDIO_PATH), alignment_path=u.get(C.ALIGNMENT_PATH) or None,
                       alignment_end_s=clip.alignment_end_s)
    tracked = track_video(video, clip.procedural, rig, config, identity=identity)
    PROFILE.leave("other")
    wall, cpu = time.perf_counter() - wall + share[0], time.process_time() - cpu + share[1]
    clip.video_frames = pq.read_metadata(store.landmark_path(clip.uid)).num_rows
    PROFILE.seconds["identity"] += share[0]
    PROFILE.cpu["identity"] += share[1]
    steps = dict(PROFILE.seconds)
    steps.update({f"cpu {k}": v for k, v in PROFILE.cpu.items()})
    steps["_curves"] = tracked.result.curves
    steps["_mouth"] = tracked.result.mouth_error_px
    return wall, cpu, steps


def run_group(clips: list[Clip], store: Store, rig, config: TrackingConfig, mesh: FaceMeshConfig,
              identities: dict, shares: dict) -> list[tuple[float, float, dict]]:
    """`--joint N`: the clips through the landmarks stage one by one, then the track stage on all of them in one
    joint solve (`track_videos`, as the track flow's `track-joint` tasks run groups); the group's wall, CPU and
    steps shared over its clips by frames."""
    PROFILE.reset()
    wall, cpu = time.perf_counter(), time.process_time()
    PROFILE.enter()
    videos = []
    for clip in clips:
        u = clip.utterance
        landmarks_task.landmarks_one(store, u, mesh)
        videos.append((VideoInput(u[C.VIDEO_PATH], str(store.landmark_path(clip.uid)), u[C.FPS], int(u[C.N_FRAMES]),
                                  audio_path=u.get(C.AUDIO_PATH), alignment_path=u.get(C.ALIGNMENT_PATH) or None,
                                  alignment_end_s=clip.alignment_end_s), clip.procedural))
    tracked = track_videos(videos, rig, config, [identities.get(c.uid) for c in clips])
    PROFILE.leave("other")
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    for clip in clips:
        clip.video_frames = pq.read_metadata(store.landmark_path(clip.uid)).num_rows
    frames = sum(c.frames for c in clips)
    out = []
    for clip, result in zip(clips, tracked):
        if isinstance(result, Exception):
            raise result
        part = clip.frames / frames
        share = shares.get(clip.uid, (0.0, 0.0))
        steps = {k: v * part for k, v in PROFILE.seconds.items()}
        steps.update({f"cpu {k}": v * part for k, v in PROFILE.cpu.items()})
        steps["identity"] = steps.get("identity", 0.0) + share[0]
        steps["cpu identity"] = steps.get("cpu identity", 0.0) + share[1]
        steps["_curves"] = result.result.curves
        steps["_mouth"] = result.result.mouth_error_px
        out.append((wall * part + share[0], cpu * part + share[1], steps))
    return out


# ---- printing -----------------------------------------------------------------------------------------------------

def print_set(name: str, clips: list[Clip], path: str) -> dict[str, float]:
    frames = sum(c.frames for c in clips)
    runs = [c.runs[path] for c in clips]
    best = [min(r, key=lambda x: x[0]) for r in runs]
    wall = sum(b[0] for b in best)
    cpu = sum(b[1] for b in best)
    spreads = [(max(x[0] for x in r) - min(x[0] for x in r)) / min(x[0] for x in r) for r in runs]
    steps = {s: sum(b[2].get(s, 0.0) for b in best) for s in STEPS}
    steps_cpu = {s: sum(b[2].get(f"cpu {s}", 0.0) for b in best) for s in STEPS}
    print(f"{name} [{path}]: {len(clips)} clips, {frames} frames; best of {len(runs[0])} runs per clip, summed")
    head = (f"  {'step':<14}{'wall s':>8}{'share':>8}{'frames/s':>10}{'ms/frame':>10}   "
            f"{'CPU s':>8}{'share':>8}{'frames/s':>10}")
    print(head)
    print("  " + "-" * (len(head) - 2))

    def rate(sec: float) -> str:
        return f"{frames / sec:>10.1f}" if sec > 0 else f"{'-':>10}"

    for s in STEPS:
        sec, c = steps[s], steps_cpu[s]
        print(f"  {s:<14}{sec:>8.3f}{100 * sec / wall:>7.1f}%{rate(sec)}{1000 * sec / frames:>10.2f}   "
              f"{c:>8.3f}{100 * c / cpu:>7.1f}%{rate(c)}")
    print(f"  {'total':<14}{wall:>8.3f}{100.0:>7.1f}%{rate(wall)}{1000 * wall / frames:>10.2f}   "
          f"{cpu:>8.3f}{100.0:>7.1f}%{rate(cpu)}")
    video_frames = sum(c.video_frames for c in clips)
    if video_frames != frames:
        print(f"  the videos hold {video_frames} frames (a variable-rate clip's grid has frames its video lacks): "
              f"{video_frames / wall:.1f} video frames/s wall, {video_frames / cpu:.1f} CPU")
    print(f"  the paper's 16 h of video (1.44 M frames) at this rate: {PAPER_FRAMES / (video_frames / wall) / 3600:.1f} "
          "core-hours")
    print(f"  spread of a clip's total over its runs: median {100 * float(np.median(spreads)):.1f}%, "
          f"max {100 * max(spreads):.1f}%")
    return {"frames": frames, "wall": wall, "cpu": cpu, **steps}


def mbp_shares(clips: list[Clip], path: str) -> tuple[int, int, int]:
    """(MBP phones, MBP top-1, MBP in top-2) at the phones' midpoint frames of the tracked curves (first run)."""
    from visemeflow.visemes import viseme_index

    mbp = viseme_index("MBP")
    total = top1 = top2 = 0
    for clip in clips:
        curves = clip.runs[path][0][2]["_curves"]
        for t in clip.mbp_times:
            j = min(max(round(t * float(clip.utterance[C.FPS])), 0), len(curves) - 1)
            order = np.argsort(-curves[j], kind="stable")
            total += 1
            top1 += int(order[0] == mbp)
            top2 += int(mbp in order[:2])
    return total, top1, top2


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--clips", type=int, default=None, help="only the first N GRID clips (default all 10)")
    parser.add_argument("--no-pin", action="store_true")
    parser.add_argument("--compare", action="store_true", help="also run the path as it was before (see the doc)")
    parser.add_argument("--compare-flow", default=None, metavar="PRESET:ROI",
                        help="instead of --compare's solvers: the default L_flow (TrackingConfig's flow_preset and "
                             "flow_max_roi_px) as before, TrackingConfig(flow_preset=PRESET, flow_max_roi_px=ROI) "
                             "as after (ROI empty: native size)")
    parser.add_argument("--compare-mesh", default=None, metavar="JSON",
                        help="instead of --compare's solvers: the default FaceMeshConfig against one with these "
                             "fields changed, e.g. '{\"refine_landmarks\": false}' (same TrackingConfig)")
    parser.add_argument("--compare-config", default=None, metavar="JSON",
                        help="instead of --compare's solvers: the default TrackingConfig as before, the default updated "
                             "with JSON as after, e.g. '{\"pose_iterations\": 50, \"fast_iterations\": 100}'; "
                             "'{\"speaker_identity\": true}': one identity per speaker and image size, fitted once "
                             "(timed, its time shared over the group's clips by frames, in their identity step)")
    parser.add_argument("--compare-storage", action="store_true",
                        help="instead of --compare's solvers: the flows converted to float16 by NumPy as before "
                             "(until 2026-11-28), by OpenCV's vectorised conversion as after (the same values)")
    parser.add_argument("--compare-overheads", action="store_true",
                        help="instead of --compare's solvers: FaceMesh's landmarks read by a loop, every backward "
                             "flow mask made and the flow sampled by index arrays, as before (until 2026-11-29); "
                             "the product's code as after (the same curves)")
    parser.add_argument("--compare-times", action="store_true",
                        help="instead of --compare's solvers: the track stage's frame times decoded from the video "
                             "as before (until 2026-12-05), read from its packets and checked by the flow's pass as "
                             "after (the same curves)")
    parser.add_argument("--joint", type=int, default=None, metavar="N",
                        help="the track stage on groups of N clips of a set in one joint solve, as the pipeline "
                             "runs it (landmarks per clip; a group's time shared over its clips by frames)")
    args = parser.parse_args()
    if (args.compare_flow or args.compare_config or args.compare_storage or args.compare_mesh or args.compare_overheads
            or args.compare_times):
        args.compare = True
    if not (GRID / "video").is_dir():
        print(f"missing benchmark data: {GRID}")
        return 0
    print("end-to-end bench:", "not pinned" if args.no_pin else pin_one_core(),
          f"| torch {torch.__version__}, {torch.get_num_threads()} thread(s)")
    config, mesh, rig = TrackingConfig(), FaceMeshConfig(), load_demo_rig()
    print(f"TrackingConfig: solver {config.solver}, method {config.fast_method} (at most {config.lm_pose_iterations} "
          f"pose + {config.lm_flow_rounds} x {config.lm_iterations} it; adam {config.pose_iterations} + "
          f"{config.fast_iterations} it), flow {config.use_flow}; FaceMeshConfig: refine {mesh.refine_landmarks}, probe every "
          f"{mesh.probe_every}")
    paths = ("before", "after") if args.compare else ("after",)
    configs = {"before": config, "after": config.model_copy(update={"fast_method": "lm"})}
    label = "before (default, fast_method=adam) -> after (lm)"
    if args.compare_flow:
        preset, roi = args.compare_flow.split(":")
        configs = {"before": config, "after": config.model_copy(
            update={"flow_preset": preset, "flow_max_roi_px": int(roi) if roi else None})}
        label = (f"before (flow {config.flow_preset}, {config.flow_max_roi_px} px) -> after (flow {preset}, "
                 f"{roi or 'native'} px)")
    if args.compare_config:
        import json

        update = json.loads(args.compare_config)
        configs = {"before": config, "after": config.model_copy(update=update)}
        label = f"before (default TrackingConfig) -> after ({update})"
    if args.compare_storage:
        configs = {"before": config, "after": config}
        label = "before (flows to float16 by NumPy) -> after (by OpenCV)"
    if args.compare_overheads:
        configs = {"before": config, "after": config}
        label = "before (landmarks by a loop, every backward mask, flows sampled by index arrays) -> after"
    if args.compare_times:
        configs = {"before": config, "after": config}
        label = "before (frame times decoded) -> after (read from the packets, checked by the flow's decoding)"
    meshes = {"before": mesh, "after": mesh}
    if args.compare_mesh:
        import json

        update = json.loads(args.compare_mesh)
        configs, meshes = {"before": config, "after": config}, {"before": mesh, "after": mesh.model_copy(update=update)}
        label = f"before (default FaceMeshConfig) -> after ({update})"
    if not args.compare:
        configs = {"after": config}          # the default alone (not --compare's other method)
    vectorised = optical_flow._CONVERT_FP16
    packet_times: list = []

    def no_packet_times(path) -> None:     # before: the track stage decodes the clip for its frame times
        return None

    current = (facemesh_mod._landmark_xyz, optical_flow._sample_flows, utterance_mod.estimate_optical_flow)
    previous = (landmark_xyz_loop, sample_flows_indexed, with_backward_masks(utterance_mod.estimate_optical_flow))

    def storage(path: str) -> None:
        optical_flow._CONVERT_FP16 = None if args.compare_storage and path == "before" else vectorised
        pieces = previous if args.compare_overheads and path == "before" else current
        facemesh_mod._landmark_xyz, optical_flow._sample_flows, utterance_mod.estimate_optical_flow = pieces
        utterance_mod.packet_frame_times = (no_packet_times if args.compare_times and path == "before"
                                            else packet_times[0])
    with tempfile.TemporaryDirectory(prefix="visemeflow-e2e-") as tmp_name:
        tmp = Path(tmp_name)
        clips = build_corpus(tmp, args.clips)
        install_profile()
        packet_times = [utterance_mod.packet_frame_times]      # timed as decoding
        store = Store(tmp / "store")
        run_clip(clips[0], store, rig, config, mesh)            # warm-up: MediaPipe's and torch's first-use costs
        fitted = {path: fit_identities(clips, store, rig, configs[path], meshes[path], args.repeats) for path in paths}
        started = time.perf_counter()
        groups: list[list[Clip]] = []
        for clip in clips:
            if args.joint and groups and groups[-1][0].set_name == clip.set_name and len(groups[-1]) < args.joint:
                groups[-1].append(clip)
            else:
                groups.append([clip])
        for r in range(args.repeats):
            for group in groups:
                for path in paths:
                    storage(path)
                    if args.joint:
                        for clip, run in zip(group, run_group(group, store, rig, configs[path], meshes[path],
                                                              *fitted[path])):
                            clip.runs.setdefault(path, []).append(run)
                        continue
                    clip = group[0]
                    identity, share = fitted[path][0].get(clip.uid), fitted[path][1].get(clip.uid, (0.0, 0.0))
                    clip.runs.setdefault(path, []).append(run_clip(clip, store, rig, configs[path], meshes[path],
                                                                   identity, share))
            print(f"  [{time.perf_counter() - started:6.0f} s] run {r + 1} of {args.repeats}", file=sys.stderr,
                  flush=True)
    print()
    sets: dict[str, list[Clip]] = {}
    for clip in clips:
        sets.setdefault(clip.set_name, []).append(clip)
    totals = {}
    for name, members in sets.items():
        for path in paths:
            totals[(name, path)] = print_set(name, members, path)
            print()
    if args.compare:
        print(f"{label}: best runs; wall | CPU frames/s; solver, flow frames/s")
        for name in sets:
            b, a = totals[(name, "before")], totals[(name, "after")]
            print(f"  {name:<32} total {b['frames'] / b['wall']:.1f} -> {a['frames'] / a['wall']:.1f} | "
                  f"{b['frames'] / b['cpu']:.1f} -> {a['frames'] / a['cpu']:.1f};  solver "
                  f"{b['frames'] / b['solver']:.0f} -> {a['frames'] / a['solver']:.0f}, flow "
                  f"{b['frames'] / max(b['flow'], 1e-9):.0f} -> {a['frames'] / max(a['flow'], 1e-9):.0f} frames/s")
        print()
        print("accuracy, before -> after: mean mouth keypoint error to the detections (px, over frames with one); "
              "MBP at MBP phone midpoints (top-1, in top-2)")
        for name, members in sets.items():
            line = f"  {name:<32}"
            for path in paths:
                errors = np.concatenate([c.runs[path][0][2]["_mouth"] for c in members])
                line += f" {path} {np.nanmean(errors):.3f} px"
                mbp = mbp_shares(members, path)
                if mbp[0]:
                    line += f", MBP {mbp[1]}/{mbp[0]} top-1, {mbp[2]}/{mbp[0]} top-2;"
            print(line)
        print()
    print("per clip (best run): frames, total wall s, frames/s; decode / detection / flow / solver s; curves")
    for clip in clips:
        every = [run[2]["_curves"] for run in clip.runs["after"]]
        same = all(np.array_equal(every[0], c) for c in every)
        gap = (f", max |after - before| {np.abs(clip.runs['after'][0][2]['_curves'] - clip.runs['before'][0][2]['_curves']).max():.3f}"
               if args.compare else "")
        for path in paths:
            wall, _, steps = min(clip.runs[path], key=lambda r: r[0])
            print(f"  {clip.uid:<22}{path:<7}{clip.frames:>5}{wall:>8.3f}{clip.frames / wall:>8.1f}   "
                  f"{steps.get('decode', 0):.3f} / {steps.get('detection', 0):.3f} / {steps.get('flow', 0):.3f} / "
                  f"{steps.get('solver', 0):.3f}   "
                  f"{'identical in every run' if same else 'DIFFER between runs'}{gap if path == 'after' else ''}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
