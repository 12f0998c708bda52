"""Lip closures of an audio-to-curves model judged against the speaker's own lips in the video. Printed, never
asserted.

Run: .venv/bin/python bench/video_closures.py [--models default,procedural[,PATH.pt]] [--grid-phones spread|aligned]
     [--closed 0.01]

The learning benches (bench/encoders.py) count a *false closure* wherever a model's top viseme over a phone that is
not b/p/m is MBP. On GRID s1 (held out from every recipe) all of the shipped default's false closures sit at the
phone right after a b/p/m, mostly the /l/ of "blue", "please", "place". Whether the speaker's lips are still shut
there is in the clips themselves: GRID s1 is video, with FaceMesh landmarks (`../shared/data/grid_s1/landmarks`).

For each GRID s1 clip: the model's curves at 30 fps (bench/encoders.py's `CachedPredictor`, the Whisper encoder's
outputs cached), each phone scored as the learning benches score it (`visemeflow.learning.realspeech.score_phones`),
and the speaker's lips measured with the tracker's own `visemeflow.tracking.landmarks.mouth_opening` ratio (the mean gap
of the three inner-lip pairs along the normal of the mouth-corner line, over the mouth's width), at every video frame
(25 fps) whose time lies inside the phone. A phone's lips are *closed in the video* when that ratio falls to
`--closed` (default 0.01, 1% of the mouth's width) or below at one of its frames, and *open* otherwise; a phone with
no video frame inside it (shorter than 40 ms) is left out of the video columns.

Phone timings: `spread` (GRID's word timings, each word's phones spread evenly over it: the figures the learning
benches record) or `aligned` (pocketsphinx's forced alignment in the audio: bench/encoders.py's
`grid_aligned_corpus`).

Printed per model: b/p/m phones (closed in the video; the model's MBP on top), the false closures by the phone's
state in the video, the false closures over the phones whose lips stay open throughout (what a viewer would see
as the character closing where the speaker did not), and each false closure with its ratio.

Then, needing no alignment, what the viewer sees on the demo character against what the speaker's lips do, frame
by frame, on GRID s1 and the two talking_heads clips (English speakers; `1.mp4` has a variable frame rate, so every
landmark row is placed at its own time stamp): the model's curves through the product's closure rules
(`visemeflow.articulation.close_lips`) on the demo rig's mesh (`visemeflow.animation.lips.LipProbe`: closed below
1.5 mm), sampled at each video frame's time. Only frames of speech count: within 0.25 s of audio above -35 dB of the
clip's loudest 50-ms window (a stop's closure is silent). *Speaker closures*: runs of video frames whose ratio is at
or below `--closed`; one is *shown* when the mesh is closed at a frame within 40 ms of it. *Open frames*: ratio at
or above `--open` (default 0.08); the mesh closed at one is a closure the speaker did not make.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from encoders import CACHE, CachedPredictor, held_out_sets  # noqa: E402
from realspeech import FPS, SHARED  # noqa: E402

from realspeech import SAMPLE_RATE  # noqa: E402

from visemeflow.animation.lips import CLOSED_MM, LipProbe  # noqa: E402
from visemeflow.articulation import close_lips  # noqa: E402
from visemeflow.ingest.audio import read_audio  # noqa: E402
from visemeflow.learning.default_model import SHIPPED_MODELS, shipped_model_path  # noqa: E402
from visemeflow.learning.features import resample_audio  # noqa: E402
from visemeflow.rig import load_demo_rig  # noqa: E402
from visemeflow.learning.realspeech import score_phones  # noqa: E402
from visemeflow.learning.train import load_model  # noqa: E402
from visemeflow.tracking.landmarks import mouth_opening, read_landmarks  # noqa: E402

LANDMARKS = SHARED / "grid_s1" / "landmarks"
TALKING_HEADS = SHARED / "talking_heads"
SPEECH_DB, HANGOVER_S, NEAR_S = -35.0, 0.25, 0.04


def video_opening(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(times s, inner-lip gap / mouth width) of every frame of a FaceMesh landmark file with a detected face, each
    at its own time stamp (the file's `time_s`)."""
    import pyarrow.csv as pacsv

    rows = pacsv.read_csv(path, convert_options=pacsv.ConvertOptions(include_columns=["frame", "time_s"]))
    ratio = mouth_opening(read_landmarks(path)).ratio     # one row per frame number, rows missing left NaN
    times = np.full(len(ratio), np.nan)
    times[rows.column("frame").to_numpy()] = rows.column("time_s").to_numpy()
    ratio = np.where(np.isfinite(times), ratio, np.nan)
    keep = np.isfinite(ratio)
    return times[keep], ratio[keep]


def phone_rows(model, predict, utterances) -> list[dict]:
    rows = []
    for u in utterances:
        curves = u.procedural if model is None else predict(model, u.audio, u.n)
        times, ratio = video_opening(LANDMARKS / f"{u.uid.split('/')[-1]}.mediapipe478.csv")
        scored, _ = score_phones(curves, FPS, u.phones)
        for s in scored:
            inside = (times >= s.start_s) & (times < s.end_s)
            rows.append({"uid": u.uid, "viseme": s.viseme, "start": s.start_s, "end": s.end_s,
                         "top": s.top if s.top_unique else "-",
                         "video": float(ratio[inside].min()) if inside.any() else float("nan")})
    return rows


def report(name: str, rows: list[dict], closed: float) -> None:
    mbp = [r for r in rows if r["viseme"] == "MBP"]
    other = [r for r in rows if r["viseme"] != "MBP"]
    seen = [r for r in other if np.isfinite(r["video"])]
    false = [r for r in other if r["top"] == "MBP"]
    false_closed = [r for r in false if r["video"] <= closed]
    false_open = [r for r in false if r["video"] > closed]
    open_ = [r for r in seen if r["video"] > closed]
    shut = [r for r in mbp if r["video"] <= closed]
    print(f"{name}")
    print(f"  b/p/m phones {len(mbp)}: closed in the video {len(shut)}; the model's MBP on top at "
          f"{sum(r['top'] == 'MBP' for r in mbp)} ({sum(r['top'] == 'MBP' for r in shut)} of the closed ones)")
    print(f"  other phones {len(other)} ({len(seen)} with a video frame inside): lips closed in the video at "
          f"{len(seen) - len(open_)}, open throughout at {len(open_)}")
    print(f"  false closures {len(false)}/{len(other)} ({len(false) / max(1, len(other)):.1%}): at lips closed in "
          f"the video {len(false_closed)}, at open lips {len(false_open)}, with no frame inside "
          f"{len(false) - len(false_closed) - len(false_open)}")
    print(f"  closing where the speaker's lips are open throughout: {len(false_open)}/{len(open_)} "
          f"({len(false_open) / max(1, len(open_)):.1%})")
    for r in false:
        state = "no frame" if not np.isfinite(r["video"]) else ("closed" if r["video"] <= closed else "open")
        print(f"    {r['uid']:<11} {r['viseme']:<5} {r['start']:6.3f}-{r['end']:6.3f} s  gap/width "
              f"{r['video']:6.3f}  {state}")
    print()


def speech_mask(audio: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(len(times),) bool: within HANGOVER_S of a 50-ms window of `audio` (16 kHz) above SPEECH_DB of the loudest."""
    hop = int(0.05 * SAMPLE_RATE)
    n = len(audio) // hop
    rms = np.sqrt(np.mean(audio[:n * hop].reshape(n, hop).astype(np.float64) ** 2, axis=1)) + 1e-12
    loud = (np.arange(n) + 0.5) * 0.05
    loud = loud[20 * np.log10(rms / rms.max()) > SPEECH_DB]
    if len(loud) == 0:
        return np.zeros(len(times), bool)
    nearest = np.abs(times[:, None] - loud[None, :]).min(axis=1)
    return nearest <= HANGOVER_S


def frame_clips() -> list[tuple[str, np.ndarray, Path]]:
    """(name, 16-kHz audio, landmark file) of the clips judged frame by frame: GRID s1 and the talking heads."""
    clips = []
    for landmarks in sorted(LANDMARKS.glob("*.mediapipe478.csv")):
        clip = landmarks.name.removesuffix(".mediapipe478.csv")
        clips.append((f"GRID s1/{clip}", SHARED / "grid_s1" / "video" / f"{clip}.mpg", landmarks))
    for video in sorted(TALKING_HEADS.glob("*.mp4")):
        clips.append((f"talking_heads/{video.stem}", video, TALKING_HEADS / f"{video.stem}.mediapipe478.csv"))
    out = []
    for name, media, landmarks in clips:
        samples, rate = read_audio(media)
        out.append((name, resample_audio(samples, rate, SAMPLE_RATE).astype(np.float32), landmarks))
    return out


def frame_report(name: str, model, predict, clips, probe: LipProbe, closed: float, open_: float) -> None:
    print(f"{name}: on the demo character's mesh (closed below {CLOSED_MM:g} mm) against the speaker's lips, speech "
          f"frames only")
    print(f"  {'clip set':<14}{'speaker closures':>17}{'shown':>7}{'open frames':>13}{'mesh closed':>13}")
    pooled: dict[str, list[int]] = {}
    for clip, audio, landmarks in clips:
        n = int(np.ceil(len(audio) / SAMPLE_RATE * FPS))
        gap = probe.measure(close_lips(predict(model, audio, n))).gap_mm
        times, ratio = video_opening(landmarks)
        speech = speech_mask(audio, times)
        frame = np.clip(np.rint(times * FPS).astype(int), 0, len(gap) - 1)
        mesh_closed = gap[frame] < CLOSED_MM
        counts = pooled.setdefault(clip.split("/")[0], [0, 0, 0, 0])
        shut = (ratio <= closed) & speech
        edges = np.flatnonzero(np.diff(np.r_[0, shut.astype(int), 0]))
        for start, end in zip(edges[::2], edges[1::2]):
            near = (times >= times[start] - NEAR_S) & (times <= times[end - 1] + NEAR_S)
            counts[0] += 1
            counts[1] += int(mesh_closed[near].any())
        wide = (ratio >= open_) & speech
        counts[2] += int(wide.sum())
        counts[3] += int((wide & mesh_closed).sum())
    for group, (events, shown, wide, wrong) in pooled.items():
        print(f"  {group:<14}{events:>17}{shown:>4} ({shown / max(1, events):.0%}){wide:>10}"
              f"{wrong:>6} ({wrong / max(1, wide):.1%})")
    print()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", default="default,procedural",
                    help="comma-separated: shipped model names, .pt files, or `procedural` (the alignment's own curves)")
    ap.add_argument("--grid-phones", choices=("spread", "aligned"), default="spread")
    ap.add_argument("--closed", type=float, default=0.01, help="inner-lip gap / mouth width at or below: closed")
    ap.add_argument("--open", type=float, default=0.08, help="inner-lip gap / mouth width at or above: open")
    args = ap.parse_args()
    if not LANDMARKS.is_dir():
        print(f"missing benchmark data: {LANDMARKS}")
        return 0
    tmp = Path(tempfile.mkdtemp(prefix="video-closures-"))
    try:
        grid = held_out_sets(tmp, args.grid_phones)["GRID s1"]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    predict = CachedPredictor(CACHE)
    print(f"GRID s1, {len(grid)} clips, phones {args.grid_phones}; closed: inner-lip gap <= {args.closed:g} of the "
          f"mouth's width at a video frame inside the phone\n")
    models = {}
    for name in [m.strip() for m in args.models.split(",") if m.strip()]:
        if name == "procedural":
            report("procedural (the alignment's own curves, ProceduralConfig's defaults)",
                   phone_rows(None, predict, grid), args.closed)
            continue
        models[name] = load_model(shipped_model_path(name) if name in SHIPPED_MODELS else Path(name))[0]
        report(name, phone_rows(models[name], predict, grid), args.closed)
    if models:
        probe, clips = LipProbe.from_rig(load_demo_rig()), frame_clips()
        for name, model in models.items():
            frame_report(name, model, predict, clips, probe, args.closed, args.open)
    return 0


if __name__ == "__main__":
    sys.exit(main())
