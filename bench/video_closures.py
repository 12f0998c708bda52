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

from visemeflow.learning.default_model import SHIPPED_MODELS, shipped_model_path  # noqa: E402
from visemeflow.learning.realspeech import score_phones  # noqa: E402
from visemeflow.learning.train import load_model  # noqa: E402
from visemeflow.tracking.landmarks import mouth_opening, read_landmarks  # noqa: E402

LANDMARKS = SHARED / "grid_s1" / "landmarks"


def video_opening(clip: str) -> tuple[np.ndarray, np.ndarray]:
    """(times s, inner-lip gap / mouth width) of every frame of a GRID s1 clip with a detected face."""
    path = LANDMARKS / f"{clip}.mediapipe478.csv"
    track = read_landmarks(path, fps=25.0)
    ratio = mouth_opening(track).ratio
    times = np.arange(len(ratio)) / 25.0
    keep = np.isfinite(ratio)
    return times[keep], ratio[keep]


def phone_rows(model, predict, utterances) -> list[dict]:
    rows = []
    for u in utterances:
        curves = u.procedural if model is None else predict(model, u.audio, u.n)
        times, ratio = video_opening(u.uid.split("/")[-1])
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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", default="default,procedural",
                    help="comma-separated: shipped model names, .pt files, or `procedural` (the alignment's own curves)")
    ap.add_argument("--grid-phones", choices=("spread", "aligned"), default="spread")
    ap.add_argument("--closed", type=float, default=0.01, help="inner-lip gap / mouth width at or below: closed")
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
    for name in [m.strip() for m in args.models.split(",") if m.strip()]:
        if name == "procedural":
            report("procedural (the alignment's own curves, ProceduralConfig's defaults)",
                   phone_rows(None, predict, grid), args.closed)
            continue
        path = shipped_model_path(name) if name in SHIPPED_MODELS else Path(name)
        report(name, phone_rows(load_model(path)[0], predict, grid), args.closed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
