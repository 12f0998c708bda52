"""What the default model does with the mouth in pauses: aligned silences of held-out real speech (GRID s1, the
Mandarin utterance, praatio's speakers) and one second of digital silence or white noise (-60, -45 dBFS) put between
two copies of an utterance. Printed, never asserted.

Run: .venv/bin/python bench/pauses.py [--quick]      (--quick: praatio's two speakers and digital silence only)

Per set, over the pause's frames (aligned silences of at least 0.3 s, 0.1 s in from each end; the inserted second,
0.1 s in): the largest viseme weight of each frame (median, 90th percentile), the viseme most often on top, and on the
demo character after the closure rule the inner-lip gap's distance from the rest mouth's (median, 90th percentile,
share of frames more than 2 mm from rest). A mouth at rest in a pause reads 0 in every column.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "2")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from encoders import held_out_sets  # noqa: E402
from realspeech import FPS, SAMPLE_RATE  # noqa: E402

from visemeflow.animation.lips import LipProbe  # noqa: E402
from visemeflow.articulation import close_lips  # noqa: E402
from visemeflow.learning.default_model import default_model_path  # noqa: E402
from visemeflow.learning.train import load_model, predict_curves  # noqa: E402
from visemeflow.rig import load_demo_rig  # noqa: E402
from visemeflow.visemes import VISEMES  # noqa: E402

MIN_PAUSE_S = 0.3
EDGE_S = 0.1


def pause_frames(phones, n: int) -> np.ndarray:
    """(n,) bool: frames inside aligned silences of at least MIN_PAUSE_S, EDGE_S in from each end."""
    covered = np.zeros(n, bool)
    for p in phones:
        if p.viseme is not None:
            covered[max(int(np.floor(p.start_s * FPS)), 0):min(int(np.ceil(p.end_s * FPS)), n)] = True
    out, k, edge = np.zeros(n, bool), 0, int(round(EDGE_S * FPS))
    while k < n:
        if covered[k]:
            k += 1
            continue
        j = k
        while j < n and not covered[j]:
            j += 1
        if (j - k) / FPS >= MIN_PAUSE_S:
            out[k + edge:j - edge] = True
        k = j
    return out


def row(name: str, curves: list[np.ndarray], masks: list[np.ndarray], probe: LipProbe, rest: float) -> str:
    c = np.concatenate([x[m] for x, m in zip(curves, masks)])
    if not len(c):
        return f"| {name} | 0 | | | | | | |"
    top, off = c.max(axis=1), np.abs(probe.measure(close_lips(c)).gap_mm - rest)
    leader = VISEMES[int(np.bincount(c.argmax(axis=1), minlength=len(VISEMES)).argmax())]
    return (f"| {name} | {len(c)} | {np.median(top):.2f} | {np.percentile(top, 90):.2f} | {leader} | "
            f"{np.median(off):.2f} | {np.percentile(off, 90):.2f} | {np.mean(off > 2.0):.0%} |")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="praatio's speakers and digital silence only")
    args = parser.parse_args(argv)
    model = load_model(default_model_path())[0]
    probe = LipProbe.from_rig(load_demo_rig())
    rest = float(probe.measure(np.zeros((1, len(VISEMES)), np.float32)).gap_mm[0])
    print(f"default model; demo character, rest gap {rest:.2f} mm\n")
    print("| pauses | frames | top weight median | p90 | most on top | gap from rest mm median | p90 | > 2 mm |")
    print("|---|---|---|---|---|---|---|---|")
    sets = held_out_sets(Path(tempfile.mkdtemp(prefix="pauses-")))
    if args.quick:
        sets = {"praatio": sets["praatio"]}
    for name, utterances in sets.items():
        curves = [predict_curves(model, u.audio, SAMPLE_RATE, FPS, n_frames=u.n) for u in utterances]
        print(row(f"aligned silences, {name}", curves, [pause_frames(u.phones, u.n) for u in utterances], probe, rest),
              flush=True)
    rng = np.random.default_rng(0)
    chosen = sets["praatio"] if args.quick else sets["GRID s1"][:4] + sets["praatio"]
    levels = (("digital silence", None),) if args.quick else \
        (("digital silence", None), ("white noise -60 dBFS", -60), ("white noise -45 dBFS", -45))
    for label, level in levels:
        curves, masks = [], []
        for u in chosen:
            pad = np.zeros(SAMPLE_RATE, np.float32) if level is None else \
                (rng.standard_normal(SAMPLE_RATE) * 10 ** (level / 20)).astype(np.float32)
            audio = np.concatenate([u.audio, pad, u.audio]).astype(np.float32)
            n = round(len(audio) / SAMPLE_RATE * FPS)
            curves.append(predict_curves(model, audio, SAMPLE_RATE, FPS, n_frames=n))
            mask = np.zeros(n, bool)
            first = round(len(u.audio) / SAMPLE_RATE * FPS) + round(EDGE_S * FPS)
            mask[first:first + round((1 - 2 * EDGE_S) * FPS)] = True
            masks.append(mask)
        print(row(f"1 s of {label} inserted ({len(chosen)} utterances)", curves, masks, probe, rest), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
