"""Benchmark: phoneme-guided viseme tracking (paper 4.3-4.4), fast vs faithful solver, guided vs unguided, on one core.

Run:  .venv/bin/python bench/tracking.py [--utterances N] [--faithful-frames F] [--rgb-whole K] [--grid]
                                        [--flow-sizes [PRESET:]PX,...]

Prints tables and never asserts; the exit status is 0 whatever the figures are. Threads are pinned to one
(OMP/MKL/OpenBLAS env set before numpy and torch are imported, torch.set_num_threads(1)), so every frames/s is
per core. A short warm-up solve runs first so that no timed solve pays torch's first-call costs.

Table 1, synthetic corpus with known truth. Built in-process (no Prefect) exactly as the `synth` task does: each
utterance of examples/corpus (the first N with --utterances) is ingested, its phones with a viseme become
VisemeSegments, `make_take(rig, segments, frame_count(duration, 25), speaker, uid, SynthConfig())` gives the true
curves (`take.curves`), the noisy detected landmarks (1.5 px noise, 2 % missed frames) and their exact projections
(`take.true_landmarks`); the frames are rendered (`render_take`) for the flow and rgb rows only; the procedural
curves (`generate_procedural_curves`) guide the tracker; the camera is the take's own intrinsics. Rows:
  procedural         the procedural curves themselves, posed by the tracker's rigid initial fit (`initial_pose`:
                     200 Adam steps on the landmarks with the procedural weights held fixed), so their keypoint
                     error is that of the curves, not of a guessed pose; no frames/s (nothing is solved).
  unguided fast      `solve_fast`, TrackingConfig(guidance=False, use_flow=False): w3 = w4 = 0.
  guided fast        `solve_fast`, TrackingConfig(use_flow=False).
  unguided faithful  `solve_faithful`, TrackingConfig(solver="faithful", guidance=False, use_flow=False).
  guided faithful    `solve_faithful`, TrackingConfig(solver="faithful", use_flow=False).
  guided faithful soft  the same with box="soft": the paper's L_range penalty and truncation at the end instead of
                     projection after every step (the paper-exact form, which overshoots: see TrackingConfig.box).
  guided fast+flow   `solve_fast`, TrackingConfig(): the default pipeline config (L_flow on, DIS optical flow of
                     the rendered frames built as `visemeflow.tracking.utterance.flow_term` builds it, on the
                     lower face).
  ... lm             the row above it with fast_method="lm": the fast solver's Levenberg-Marquardt method beside
                     the default Adam (50 pose + 200 joint steps with cosine decay), same objective.
  guided fast+flow face  the flow row with flow_region="face": DIS on the whole face instead of the lower face.
  guided fast+flow PX    with --flow-sizes: the flow row with TrackingConfig(flow_max_roi_px=PX), the face shrunk
                     until its longer side is at most PX pixels before DIS runs on its lower part (the rendered
                     face spans about 230 px, as the 700x700 talking heads' 242x256 do; the default is 256).
                     An item PRESET:PX (e.g. fast:160) also sets TrackingConfig(flow_preset=PRESET): row
                     "guided fast+flow PRESET PX".
  guided fast+rgb    `solve_fast`, TrackingConfig(use_flow=False, use_rgb=True), L_rgb from
                     `visemeflow.tracking.photo.PhotoTerm` on the rendered frames.
Block (a) runs the cheap rows on every utterance, whole. Block (b) is the faithful subset: the first F frames
(--faithful-frames, default 40) of each of the first 3 utterances, each cut to an independent problem (landmarks,
procedural curves and frames truncated); all rows run on it, so fast and faithful sit side by side (the faithful
solver is ~1 frame/s; the rgb row is only run here because it is ~1-4 frames/s). With --rgb-whole K (default 0)
block (c) also runs the rgb row on the first K utterances whole, one line each, since its cost per frame grows
with the utterance's length.
Columns (pooled over every frame of the block, i.e. frame-weighted):
  mouth px det   mean over frames of `result.mouth_error_px`: the mean distance of the 20 mouth landmarks 48-67
                 of the tracked face to the DETECTED (noisy) landmarks; frames without a detection are skipped.
  mouth px true  the same distance to the exact projections `take.true_landmarks` (every frame); the noise floor
                 of the detected column is about 1.5 px * sqrt(pi/2) = 1.9 px for a perfect fit.
  L1x100         mean |tracked - true| over frames and the 16 visemes, x 100.
  top1 / top2    at phoneme apex frames (per viseme segment, the frame nearest its midpoint): the share whose TRUE
                 top viseme (argmax of take.curves) is the tracked top viseme / among the tracked top two.
  fps            frames / result.seconds (solver only: pose initialisation + optimisation).
  fps+prep       frames / (result.seconds + the per-utterance precompute the row needs: the DIS flow field, or
                 the PhotoTerm construction); rendering the frames is not counted.
Then the ratios of the issue: fast vs faithful speed-up at their L1 (target >= 20x at equal or lower L1), guided vs
unguided keypoint error (target within 10 %), guided minus unguided top-2 accuracy (should be clearly > 0), fast
frames/s without rgb (target >= 30 per core) and with rgb (target >= 3).

Table 2 (--grid), real video: the GRID s1 clips in ../shared/data/grid_s1 (video/*.mpg, align/*.align,
landmarks/*.mediapipe478.csv) are copied into a temporary corpus <tmp>/corpus/s1/, and `pipeline_flow` (ingest,
procedural, track with the default TrackingConfig except `guidance`; L_flow on, identity fitted from the landmarks)
runs twice inside `prefect_api.prefect_server()` (a temporary local server), into one store for guided and one for unguided tracking. From each
store: for every phone whose viseme is MBP (phones table), its midpoint frame; the share where MBP is the tracked
top viseme and among the top two (the procedural curves as reference); per clip the mean mouth keypoint error
(tracking_frames) and the identity-fit rms (re-computed with `visemeflow.tracking.utterance.rig_and_camera`, the same
deterministic call the track task makes, because the flow does not store it).
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_name] = "1"
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")

import argparse
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from visemeflow.ingest import IngestConfig, discover_corpus, ingest_utterance
from visemeflow.phonetics.types import VisemeSegment
from visemeflow.procedural import generate_procedural_curves
from visemeflow.rig import VisemeRig, load_demo_rig
from visemeflow.synth.take import SynthConfig, SyntheticTake, make_take, render_take
from visemeflow.tracking.utterance import flow_config_of, flow_term
from visemeflow.timebase import frame_count
from visemeflow.render.camera import Intrinsics
from visemeflow.tracking.landmarks import LandmarkTrack
from visemeflow.tracking.photo import PhotoTerm
from visemeflow.tracking.solver import (
    TrackingConfig,
    TrackingProblem,
    TrackingResult,
    initial_pose,
    mouth_errors,
    solve_faithful,
    solve_fast,
)
from visemeflow.visemes import VISEMES, viseme_index

torch.set_num_threads(1)

ROOT = Path(__file__).resolve().parents[1]
CORPUS = ROOT / "examples" / "corpus"
GRID = ROOT.parent / "shared" / "data" / "grid_s1"
FPS = 25.0
FAITHFUL_UTTERANCES = 3

# name -> (solver, TrackingConfig, needs): needs is None, "flow" or "rgb"
METHODS: dict[str, tuple[str, TrackingConfig | None, str | None]] = {
    "procedural": ("none", None, None),
    "unguided fast": ("fast", TrackingConfig(guidance=False, use_flow=False), None),
    "guided fast": ("fast", TrackingConfig(use_flow=False), None),
    "unguided faithful": ("faithful", TrackingConfig(solver="faithful", guidance=False, use_flow=False), None),
    "guided faithful": ("faithful", TrackingConfig(solver="faithful", use_flow=False), None),
    "guided faithful soft": ("faithful", TrackingConfig(solver="faithful", use_flow=False, box="soft"), None),
    "guided fast+flow": ("fast", TrackingConfig(), "flow"),
    "guided fast+rgb": ("fast", TrackingConfig(use_flow=False, use_rgb=True), "rgb"),
    # the fast solver's other method, Levenberg-Marquardt, beside the default Adam (issue 29)
    "unguided fast lm": ("fast", TrackingConfig(guidance=False, use_flow=False, fast_method="lm"), None),
    "guided fast lm": ("fast", TrackingConfig(use_flow=False, fast_method="lm"), None),
    "guided fast+flow lm": ("fast", TrackingConfig(fast_method="lm"), "flow"),
    # L_flow's optical flow on the whole face rather than the default lower face (issue 29)
    "guided fast+flow face": ("fast", TrackingConfig(flow_region="face"), "flow"),
}
FULL_ROWS = ("procedural", "unguided fast", "unguided fast lm", "guided fast", "guided fast lm",
             "guided fast+flow", "guided fast+flow lm", "guided fast+flow face")
SUBSET_ROWS = tuple(METHODS)


@dataclass
class Utterance:
    uid: str
    segments: list[VisemeSegment]
    take: SyntheticTake
    procedural: np.ndarray
    camera: Intrinsics
    frames: np.ndarray | None = None     # (T, H, W, 3) uint8, rendered on demand

    @property
    def n(self) -> int:
        return len(self.procedural)

    def apex_frames(self) -> np.ndarray:
        """Per viseme segment, the frame nearest its midpoint (segments ending past the clip are dropped)."""
        mids = np.array([round(0.5 * (s.start_s + s.end_s) * FPS) for s in self.segments], dtype=int)
        return mids[(mids >= 0) & (mids < self.n)]

    def cut(self, frames: int) -> Utterance:
        """The first `frames` frames as an independent utterance (truth, detections, procedural, pixels)."""
        k = min(frames, self.n)
        t = self.take
        track = LandmarkTrack(t.landmarks.points[:k], t.landmarks.valid[:k], t.landmarks.fps, t.landmarks.source)
        take = SyntheticTake(t.curves[:k], t.camera, t.poses[:k], t.scene, track, t.true_landmarks[:k])
        segments = [s for s in self.segments if round(0.5 * (s.start_s + s.end_s) * FPS) < k]
        return Utterance(self.uid, segments, take, self.procedural[:k],
                         self.camera, None if self.frames is None else self.frames[:k].copy())


@dataclass
class Tally:
    """Pooled metrics of one method over some utterances."""

    frames: int = 0
    det_sum: float = 0.0
    det_count: int = 0
    true_sum: float = 0.0
    true_count: int = 0
    l1_sum: float = 0.0
    apex: int = 0
    top1: int = 0
    top2: int = 0
    seconds: float = 0.0
    prep_seconds: float = 0.0
    weak_apex: int = 0
    timed: bool = True
    per_utterance: list[tuple[str, float, float]] = field(default_factory=list)  # uid, L1x100, det px

    def add(self, u: Utterance, curves: np.ndarray, det: np.ndarray, true: np.ndarray,
            seconds: float | None, prep: float = 0.0) -> None:
        self.frames += u.n
        self.det_sum += float(np.nansum(det))
        self.det_count += int(np.isfinite(det).sum())
        self.true_sum += float(np.nansum(true))
        self.true_count += int(np.isfinite(true).sum())
        err = np.abs(curves - u.take.curves)
        self.l1_sum += float(err.sum())
        apex = u.apex_frames()
        truth_top = u.take.curves[apex].argmax(axis=1)
        order = np.argsort(-curves[apex], axis=1, kind="stable")
        self.apex += len(apex)
        self.weak_apex += int((u.take.curves[apex].max(axis=1) < 0.2).sum())
        self.top1 += int((order[:, 0] == truth_top).sum())
        self.top2 += int(((order[:, 0] == truth_top) | (order[:, 1] == truth_top)).sum())
        if seconds is None:
            self.timed = False
        else:
            self.seconds += seconds
            self.prep_seconds += prep
        self.per_utterance.append((u.uid, 100 * float(err.mean()), float(np.nanmean(det))))

    @property
    def det(self) -> float:
        return self.det_sum / max(self.det_count, 1)

    @property
    def true(self) -> float:
        return self.true_sum / max(self.true_count, 1)

    @property
    def l1(self) -> float:
        return 100 * self.l1_sum / max(self.frames * len(VISEMES), 1)

    @property
    def acc1(self) -> float:
        return self.top1 / max(self.apex, 1)

    @property
    def acc2(self) -> float:
        return self.top2 / max(self.apex, 1)

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.timed and self.seconds > 0 else float("nan")

    @property
    def fps_prep(self) -> float:
        total = self.seconds + self.prep_seconds
        return self.frames / total if self.timed and total > 0 else float("nan")


# ---- data -------------------------------------------------------------------------------------------------------

def load_utterances(rig: VisemeRig, limit: int | None) -> list[Utterance]:
    entries = list(discover_corpus(CORPUS).entries)
    if limit is not None:
        entries = entries[:limit]
    out = []
    for entry in entries:
        ingested = ingest_utterance(entry, IngestConfig())
        segments = [VisemeSegment(p["viseme"], p["start_s"], p["end_s"], p["word_index"], p["phoneme"] or "")
                    for p in ingested.phones if p["viseme"] is not None]
        n = frame_count(ingested.utterance["duration_s"], FPS)
        take = make_take(rig, segments, n, entry.speaker, entry.utterance_id, SynthConfig())
        procedural = generate_procedural_curves(segments, n, FPS)
        c = take.camera
        camera = Intrinsics(c.fx, c.fy, c.cx, c.cy, c.width, c.height)
        out.append(Utterance(entry.utterance_id, segments, take, procedural, camera))
    return out


def render(rig: VisemeRig, u: Utterance) -> np.ndarray:
    return np.stack(list(render_take(rig, u.take)))


# ---- solving ----------------------------------------------------------------------------------------------------

def problem_of(rig: VisemeRig, u: Utterance, **terms) -> TrackingProblem:
    return TrackingProblem(rig, u.camera, u.take.landmarks.points, u.take.landmarks.valid, u.procedural, **terms)


def true_mouth_errors(rig: VisemeRig, u: Utterance, curves, rotation, translation) -> np.ndarray:
    """(T,) mean distance of the tracked mouth landmarks to the exact (noise-free) projections."""
    exact = u.take.true_landmarks
    truth = TrackingProblem(rig, u.camera, exact, np.isfinite(exact).all(axis=2), u.procedural)
    return mouth_errors(truth, curves, rotation, translation)


def run_method(name: str, rig: VisemeRig, u: Utterance, tally: Tally) -> TrackingResult | None:
    solver, config, needs = METHODS[name]
    if solver == "none":
        problem = problem_of(rig, u)
        rot, trans = initial_pose(problem, TrackingConfig())
        rot, trans = rot.numpy(), trans.numpy()
        curves = u.procedural.astype(np.float32)
        tally.add(u, curves, mouth_errors(problem, curves, rot, trans),
                  true_mouth_errors(rig, u, curves, rot, trans), None)
        return None
    prep = 0.0
    terms = {}
    if needs == "flow" and u.n > 1:
        start = time.perf_counter()
        terms["flow"], _ = flow_term(u.frames, rig, u.take.landmarks, flow_config_of(config), config.flow_region)
        prep = time.perf_counter() - start
    elif needs == "rgb":
        start = time.perf_counter()
        terms["rgb"] = PhotoTerm(rig, u.camera, u.frames, u.take.landmarks.points)
        prep = time.perf_counter() - start
    problem = problem_of(rig, u, **terms)
    result = (solve_fast if solver == "fast" else solve_faithful)(problem, config)
    tally.add(u, result.curves, result.mouth_error_px,
              true_mouth_errors(rig, u, result.curves, result.rotation, result.translation), result.seconds, prep)
    return result


def warm_up(rig: VisemeRig, u: Utterance) -> None:
    """One small solve of each kind, so that torch's first-call costs land in no timed row."""
    small = u.cut(8)
    problem = problem_of(rig, small)
    solve_fast(problem, TrackingConfig(use_flow=False, fast_iterations=5, pose_iterations=5))
    solve_faithful(problem, TrackingConfig(solver="faithful", use_flow=False, iterations=3, pose_iterations=5))


# ---- printing ---------------------------------------------------------------------------------------------------

def fmt(value: float, spec: str) -> str:
    return "-" if not np.isfinite(value) else format(value, spec)


def print_table(title: str, tallies: dict[str, Tally]) -> None:
    print(title)
    w = max([22, *(len(name) + 1 for name in tallies)])
    head = (f"{'method':<{w}}{'frames':>7}{'mouth px det':>14}{'mouth px true':>15}{'L1x100':>8}"
            f"{'top1@apex':>11}{'top2@apex':>11}{'fps':>9}{'fps+prep':>10}")
    print(head)
    print("-" * len(head))
    for name, t in tallies.items():
        print(f"{name:<{w}}{t.frames:>7}{fmt(t.det, '.3f'):>14}{fmt(t.true, '.3f'):>15}{fmt(t.l1, '.2f'):>8}"
              f"{fmt(100 * t.acc1, '.1f') + '%':>11}{fmt(100 * t.acc2, '.1f') + '%':>11}"
              f"{fmt(t.fps, '.2f'):>9}{fmt(t.fps_prep, '.2f'):>10}")
    first = next(iter(tallies.values()))
    print(f"({first.apex} apex frames; at {first.weak_apex} of them the true top weight is below 0.2)")
    print()


def verdict(ok: bool) -> str:
    return "met" if ok else "NOT met"


def print_ratios(full: dict[str, Tally], sub: dict[str, Tally], f: int) -> None:
    print("Ratios (targets of the issue)")
    for kind in ("guided", "unguided"):
        fast, faithful = sub[f"{kind} fast"], sub[f"{kind} faithful"]
        speed = fast.fps / faithful.fps
        ok = speed >= 20 and fast.l1 <= faithful.l1
        print(f"  {kind:<8} fast vs faithful, subset:  {speed:7.1f}x faster ({fast.fps:.1f} vs {faithful.fps:.2f} "
              f"frames/s), L1x100 {fast.l1:.2f} vs {faithful.l1:.2f}  -> >= 20x at equal or lower L1: {verdict(ok)}")
    for label, block, solver in (("all", full, "fast"), ("subset", sub, "fast"), ("subset", sub, "faithful")):
        g, u = block[f"guided {solver}"], block[f"unguided {solver}"]
        rel = g.det / u.det - 1
        rel_true = g.true / u.true - 1
        print(f"  guided vs unguided mouth error, {solver:<8} ({label:<6}): det {g.det:.3f} vs {u.det:.3f} px "
              f"({100 * rel:+.1f}%), true {g.true:.3f} vs {u.true:.3f} px ({100 * rel_true:+.1f}%)"
              f"  -> within 10%: {verdict(rel <= 0.10)}")
    for label, block, solver in (("all", full, "fast"), ("subset", sub, "fast"), ("subset", sub, "faithful")):
        g, u = block[f"guided {solver}"], block[f"unguided {solver}"]
        d2, d1 = 100 * (g.acc2 - u.acc2), 100 * (g.acc1 - u.acc1)
        print(f"  guided - unguided top-2 accuracy, {solver:<8} ({label:<6}): {d2:+.1f} points "
              f"({100 * g.acc2:.1f}% vs {100 * u.acc2:.1f}%; top-1 {d1:+.1f})  -> clearly higher: {verdict(d2 >= 5)}")
    for name in ("guided fast", "unguided fast", "guided fast+flow"):
        t = full[name]
        print(f"  {name + ' frames/s, all utterances':<44} {t.fps:7.1f} (with precompute {t.fps_prep:.1f})"
              f"  -> >= 30 per core: {verdict(t.fps >= 30)}")
    t = sub["guided fast+rgb"]
    print(f"  {f'guided fast+rgb frames/s, subset ({f} frames)':<44} {t.fps:7.1f} (with precompute {t.fps_prep:.1f})"
          f"  -> >= 3 per core: {verdict(t.fps >= 3)}")
    print()


# ---- Table 1 ----------------------------------------------------------------------------------------------------

def add_flow_sizes(items: list[str]) -> tuple[str, ...]:
    """Rows of the flow row at other `flow_max_roi_px` values, each item `PX` or `PRESET:PX` (--flow-sizes; PRESET
    also sets `flow_preset`), added to METHODS; their names."""
    names = []
    for item in items:
        preset, _, px = item.rpartition(":")
        config = TrackingConfig(flow_max_roi_px=int(px), **({"flow_preset": preset} if preset else {}))
        name = f"guided fast+flow {preset + ' ' if preset else ''}{int(px)}"
        METHODS[name] = ("fast", config, "flow")
        names.append(name)
    return tuple(names)


def synthetic(rig: VisemeRig, limit: int | None, faithful_frames: int, rgb_whole: int,
              flow_sizes: tuple[str, ...] = ()) -> None:
    started = time.perf_counter()
    utterances = load_utterances(rig, limit)
    warm_up(rig, utterances[0])
    total = sum(u.n for u in utterances)
    print(f"Table 1: synthetic corpus ({len(utterances)} utterances of {CORPUS.relative_to(ROOT)}, {total} frames "
          f"at {FPS:g} fps, {SynthConfig().width}x{SynthConfig().height}, landmark noise "
          f"{SynthConfig().landmark_noise_px:g} px, miss rate {SynthConfig().landmark_miss_rate:.0%})")
    print()

    full = {name: Tally() for name in FULL_ROWS + flow_sizes}
    subset_source: list[Utterance] = []
    render_seconds = 0.0
    rgb_rows: list[tuple[str, Tally]] = []
    for k, u in enumerate(utterances):
        for name in ("procedural", "unguided fast", "unguided fast lm", "guided fast", "guided fast lm"):
            run_method(name, rig, u, full[name])
        start = time.perf_counter()
        u.frames = render(rig, u)
        render_seconds += time.perf_counter() - start
        for name in ("guided fast+flow", "guided fast+flow lm", "guided fast+flow face") + flow_sizes:
            run_method(name, rig, u, full[name])
        if k < FAITHFUL_UTTERANCES:
            subset_source.append(u.cut(faithful_frames))
        if k < rgb_whole:
            whole = Tally()
            run_method("guided fast+rgb", rig, u, whole)
            rgb_rows.append((u.uid, whole))
        u.frames = None
        print(f"  [{time.perf_counter() - started:6.0f} s] {u.uid}: {u.n} frames", file=sys.stderr, flush=True)
    print_table(f"(a) all {len(utterances)} utterances, whole (frames rendered for the flow row: "
                f"{total / render_seconds:.0f} frames/s, not counted)", full)

    sub = {name: Tally() for name in SUBSET_ROWS}
    for u in subset_source:
        for name in SUBSET_ROWS:
            run_method(name, rig, u, sub[name])
            print(f"  [{time.perf_counter() - started:6.0f} s] subset {u.uid} {name}", file=sys.stderr, flush=True)
    ids = ", ".join(u.uid for u in subset_source)
    print_table(f"(b) faithful subset: first {faithful_frames} frames of each of {ids}", sub)

    if rgb_rows:
        print("(c) guided fast+rgb on whole utterances")
        print(f"{'utterance':<22}{'frames':>7}{'mouth px det':>14}{'L1x100':>8}{'fps':>9}")
        for uid, t in rgb_rows:
            print(f"{uid:<22}{t.frames:>7}{t.det:>14.3f}{t.l1:>8.2f}{t.fps:>9.2f}")
        print()

    print("Per-utterance L1x100 / mouth px det on the subset (guided fast | guided faithful | unguided faithful)")
    for i, u in enumerate(subset_source):
        cells = []
        for name in ("guided fast", "guided faithful", "unguided faithful"):
            _, l1, det = sub[name].per_utterance[i]
            cells.append(f"{l1:6.2f} / {det:6.3f}")
        print(f"  {u.uid:<22}" + " | ".join(cells))
    print()
    print_ratios(full, sub, faithful_frames)
    print(f"Table 1 took {time.perf_counter() - started:.0f} s")
    print()


# ---- Table 2 ----------------------------------------------------------------------------------------------------

def grid_corpus(tmp: Path) -> tuple[Path, list[str]]:
    folder = tmp / "corpus" / "s1"
    folder.mkdir(parents=True)
    clips = sorted(p.stem for p in (GRID / "video").glob("*.mpg"))
    kept = []
    for clip in clips:
        align = GRID / "align" / f"{clip}.align"
        marks = GRID / "landmarks" / f"{clip}.mediapipe478.csv"
        if not (align.exists() and marks.exists()):
            continue
        shutil.copyfile(GRID / "video" / f"{clip}.mpg", folder / f"{clip}.mpg")
        shutil.copyfile(align, folder / f"{clip}.align")
        shutil.copyfile(marks, folder / f"{clip}.mediapipe478.csv")
        kept.append(clip)
    return folder.parent, kept


def mbp_counts(store, variant: str | None, source: str, phones, fps: dict[str, float]) -> tuple[int, int, int]:
    from visemeflow.schemas import curves_array

    mbp = viseme_index("MBP")
    total = top1 = top2 = 0
    cache: dict[str, np.ndarray] = {}
    for p in phones:
        uid = p["utterance_id"]
        if uid not in cache:
            cache[uid] = curves_array(store.read_curves(uid, source, variant))
        curves = cache[uid]
        j = min(max(round(0.5 * (p["start_s"] + p["end_s"]) * fps[uid]), 0), len(curves) - 1)
        order = np.argsort(-curves[j], kind="stable")
        total += 1
        top1 += int(order[0] == mbp)
        top2 += int(mbp in order[:2])
    return total, top1, top2


def grid() -> None:
    from prefect_api import prefect_server

    from visemeflow.flows.params import PipelineParams
    from visemeflow.flows.pipeline import pipeline_flow
    from visemeflow.schemas import C
    from visemeflow.storage import Store
    from visemeflow.tracking.utterance import load_track, rig_and_camera

    if not (GRID / "video").is_dir():
        print(f"Table 2: skipped, {GRID} not found")
        return
    rig = load_demo_rig()
    with tempfile.TemporaryDirectory(prefix="visemeflow-bench-") as tmp_name:
        tmp = Path(tmp_name)
        corpus, clips = grid_corpus(tmp)
        runs = {}
        started = time.perf_counter()
        with prefect_server():
            harness = time.perf_counter() - started
            for label, guidance in (("guided", True), ("unguided", False)):
                config = TrackingConfig(guidance=guidance)
                store = tmp / f"store-{label}"
                start = time.perf_counter()
                summary = pipeline_flow(PipelineParams(corpus=corpus, store=store, tracking=config))
                runs[label] = (Store(store), config.variant, summary, time.perf_counter() - start)
                print(f"  [{time.perf_counter() - started:6.0f} s] GRID {label} done", file=sys.stderr, flush=True)

        guided_store = runs["guided"][0]
        utterances = guided_store.read_table("utterances").to_pylist()
        fps = {u[C.UTTERANCE_ID]: float(u[C.FPS]) for u in utterances}
        frames = sum(int(u[C.N_FRAMES]) for u in utterances)
        phones = [p for p in guided_store.read_table("phones").to_pylist() if p[C.VISEME] == "MBP"]
        print(f"Table 2: GRID s1, {len(clips)} real clips ({frames} frames, 360x288, MediaPipe landmarks), "
              f"pipeline_flow per store (Prefect harness start-up {harness:.0f} s, not counted)")
        for label, (store, variant, summary, wall) in runs.items():
            track = summary.get("track", {})
            rejects = store.read_table("rejects").to_pylist()
            print(f"  {label:<9} variant {variant}: tracked {track.get('tracked')}, rejected {track.get('rejected')}, "
                  f"pipeline wall {wall:.1f} s ({frames / wall:.1f} frames/s incl. ingest, procedural, video "
                  f"decoding, flow, identity fit, Prefect); rejects: "
                  f"{'; '.join(r[C.MESSAGE] for r in rejects) or 'none'}")
        print()
        print(f"MBP phones (b/p/m): {len(phones)}, over {len({p[C.UTTERANCE_ID] for p in phones})} clips; "
              "at each phone's midpoint frame")
        head = f"{'curves':<26}{'phones':>7}{'MBP top-1':>11}{'MBP in top-2':>14}"
        print(head)
        print("-" * len(head))
        rows = [("procedural (guidance)", guided_store, None, "procedural")]
        rows += [(f"tracked {label}", store, variant, "tracked") for label, (store, variant, _, _) in runs.items()]
        for name, store, variant, source in rows:
            n, t1, t2 = mbp_counts(store, variant, source, phones, fps)
            print(f"{name:<26}{n:>7}{100 * t1 / max(n, 1):>10.1f}%{100 * t2 / max(n, 1):>13.1f}%")
        print()

        errors = {}
        for label, (store, variant, _, _) in runs.items():
            table = store.read_tracking_frames(variant).to_pydict()
            for uid, err in zip(table[C.UTTERANCE_ID], table[C.MOUTH_ERROR_PX]):
                if err is not None:
                    errors.setdefault((label, uid), []).append(err)
        head = (f"{'clip':<12}{'frames':>7}{'MBP':>5}{'mouth px guided':>17}{'mouth px unguided':>19}"
                f"{'identity rms px':>17}")
        print(head)
        print("-" * len(head))
        sums = {"guided": [], "unguided": []}
        rms_all = []
        for u in sorted(utterances, key=lambda r: r[C.UTTERANCE_ID]):
            uid = u[C.UTTERANCE_ID]
            try:
                track = load_track(u[C.LANDMARK_PATH], u[C.FPS], int(u[C.N_FRAMES]), u[C.VIDEO_PATH])
                _, _, info = rig_and_camera(u[C.VIDEO_PATH], rig, track)
                rms = info.get("identity_rms_px", float("nan"))
            except (ValueError, RuntimeError, OSError, FloatingPointError) as exc:  # report, never stop the table
                rms = float("nan")
                print(f"  {uid}: identity fit failed: {exc}", file=sys.stderr)
            rms_all.append(rms)
            cells = []
            for label in ("guided", "unguided"):
                values = errors.get((label, uid), [])
                sums[label] += values
                cells.append(float(np.mean(values)) if values else float("nan"))
            n_mbp = sum(1 for p in phones if p[C.UTTERANCE_ID] == uid)
            print(f"{uid.split('/')[-1]:<12}{int(u[C.N_FRAMES]):>7}{n_mbp:>5}{fmt(cells[0], '.3f'):>17}"
                  f"{fmt(cells[1], '.3f'):>19}{fmt(rms, '.3f'):>17}")
        g = float(np.mean(sums["guided"])) if sums["guided"] else float("nan")
        un = float(np.mean(sums["unguided"])) if sums["unguided"] else float("nan")
        print(f"{'all frames':<12}{frames:>7}{len(phones):>5}{fmt(g, '.3f'):>17}{fmt(un, '.3f'):>19}"
              f"{fmt(float(np.nanmean(rms_all)), '.3f'):>17}")
        print(f"guided vs unguided mouth error: {100 * (g / un - 1):+.1f}%  -> within 10%: {verdict(g / un - 1 <= 0.10)}")
        print()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--utterances", type=int, default=None, help="Use only the first N utterances (default all).")
    parser.add_argument("--faithful-frames", type=int, default=40,
                        help=f"Frames of each of the first {FAITHFUL_UTTERANCES} utterances the faithful rows run on.")
    parser.add_argument("--rgb-whole", type=int, default=0,
                        help="Also run the rgb row on the first K utterances whole (slow: ~1-2 frames/s).")
    parser.add_argument("--grid", action="store_true", help="Also run Table 2 on the GRID s1 clips (real video).")
    parser.add_argument("--flow-sizes", default="", metavar="[PRESET:]PX,...",
                        help="Also run the flow row with the face shrunk to at most PX pixels for DIS "
                             "(PRESET:PX also picks the DIS preset, e.g. fast:160).")
    args = parser.parse_args()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s); solver defaults: fast "
          f"{TrackingConfig().fast_iterations} it (+{TrackingConfig().rgb_iterations} rgb it), faithful "
          f"{TrackingConfig().iterations} it x {len(TrackingConfig().passes)} passes per frame, pose init "
          f"{TrackingConfig().pose_iterations} it")
    print()
    sizes = [v.strip() for v in args.flow_sizes.split(",") if v.strip()]
    synthetic(load_demo_rig(), args.utterances, args.faithful_frames, args.rgb_whole, add_flow_sizes(sizes))
    if args.grid:
        grid()
    return 0


if __name__ == "__main__":
    sys.exit(main())
