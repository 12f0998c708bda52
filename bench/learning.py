"""Audio-to-curves models on the espeak-ng scale corpus: validation L1 x 100 per preset and floor, a
dataset-size sweep, training frames/s and inference real-time factor on one core (printed, never asserted).

Run: .venv/bin/python bench/learning.py [--epochs 8] [--presets fbank-blstm,...] [--sizes 50,150,450,ALL]

Corpus: 700 English + 500 Mandarin espeak-ng utterances (36 voice/rate speakers, ~2.4 s each), true
curves from the synthetic Cohen-Massaro dynamics at 30 fps, product split (10 % validation, ~120
utterances). See bench/learning_data.py. Trained models are cached in bench/out/learning/models and
reused by bench/robustness.py; delete that folder to retrain.

Rows:
- floors: `mean-curve` (the training set's mean curve every frame) and `procedural` (the JALI-like
  curves from the alignment: needs the text and phone timing, which the audio models do not get);
- presets trained from scratch on FBank / MFCC / LPC features (wav2vec2 presets need weights that
  cannot be downloaded here: see the README for what to expect with them);
- training frames/s: curve frames trained per second over 60 steps of a fresh model (`--threads` threads, one
  utterance per step, features precomputed); RTF: inference seconds per second of audio (features + model) with
  torch on one thread, whole validation set.

The sweep trains fbank-blstm on nested subsets (the sweep flow's `nested_subsets`) at an equal budget of
optimisation steps (paper Fig. 5), and writes bench/out/learning/sweep.png (the sweep flow's plot).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from learning_data import OUT, load_data, trained_model

from visemeflow.flows.sweep import nested_subsets, plot_sweep
from visemeflow.learning.train import TrainConfig, evaluate, train_model
from visemeflow.visemes import N_VISEMES

DEFAULT_PRESETS = ["fbank-blstm", "mfcc-blstm", "lpc-blstm", "fbank-lstm", "fbank-tcn", "fbank-transformer",
                   "karras-lpc", "faceformer-fbank"]


def real_time_factor(model, examples) -> float:
    """Inference seconds per audio second on one thread (features + head, batch of one utterance)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        evaluate(model, examples[:3])  # warm-up
        t0 = time.perf_counter()
        evaluate(model, examples)
        secs = time.perf_counter() - t0
    finally:
        torch.set_num_threads(threads)
    return secs / sum(len(ex.audio) / 16000 for ex in examples)


def training_frames_per_s(preset: str, examples, steps: int = 60) -> float:
    """Curve frames trained per second over `steps` one-utterance steps of a fresh model (features precomputed)."""
    config = TrainConfig(preset=preset, epochs=1, max_steps_per_epoch=steps, seed=1)
    return train_model(examples, [], config).history[0].frames_per_s


def floor_l1(pred: dict[str, np.ndarray], examples) -> float:
    err = sum(float(np.abs(pred[ex.utterance_id] - ex.curves).sum()) for ex in examples)
    return 100.0 * err / (sum(len(ex.curves) for ex in examples) * N_VISEMES)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--english", type=int, default=700)
    ap.add_argument("--mandarin", type=int, default=500)
    ap.add_argument("--epochs", type=int, default=8, help="epochs of every trained preset on the full training set")
    ap.add_argument("--presets", default=",".join(DEFAULT_PRESETS))
    ap.add_argument("--sizes", default="30,100,300,ALL", help="sweep sizes (ALL = the whole training set); '' skips")
    ap.add_argument("--sweep-epochs", type=float, default=3.0,
                    help="sweep budget in epochs of the full training set (equal steps for every size)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    data = load_data(args.english, args.mandarin)
    train, val = data.train, data.val
    hours = sum(len(ex.audio) for ex in train + val) / 16000 / 3600
    print(f"corpus: {len(train)} train + {len(val)} validation utterances, {hours:.2f} h of audio, "
          f"{sum(len(ex.curves) for ex in train)} training frames at 30 fps\n", flush=True)

    rows = []
    mean_model, _ = trained_model("mean-curve", TrainConfig(preset="mean-curve", epochs=1), train, val)
    mean_l1 = evaluate(mean_model, val)[0]
    rows.append(("mean-curve (floor)", mean_l1, "-", "-", "-", "-"))
    proc_l1 = floor_l1(data.procedural, val)
    rows.append(("procedural from alignment (floor)", proc_l1, "-", "-", "-", "-"))

    for preset in [p for p in args.presets.split(",") if p]:
        t0 = time.perf_counter()
        model, history = trained_model(preset, TrainConfig(preset=preset, epochs=args.epochs), train, val)
        l1 = evaluate(model, val)[0]
        fps = training_frames_per_s(preset, train)  # measured apart: epochs of a long run share the machine
        rtf = real_time_factor(model, val)
        rows.append((preset, l1, f"{args.epochs}", f"{fps:.0f}", f"{rtf:.4f}",
                     " ".join(f"{h['val_l1_x100']:.2f}" for h in history)))
        print(f"{preset}: val L1x100 {l1:.2f} ({time.perf_counter() - t0:.0f} s)", flush=True)

    print("\n| model | val L1 x 100 | vs mean-curve | epochs | train frames/s | RTF (1 thread) | val L1 by epoch |")
    print("|---|---|---|---|---|---|---|")
    for name, l1, epochs, fps, rtf, curve in rows:
        print(f"| {name} | {l1:.2f} | {100 * (l1 / mean_l1 - 1):+.0f}% | {epochs} | {fps} | {rtf} | {curve} |")

    sizes = [s for s in args.sizes.split(",") if s]
    if sizes:
        sizes_n = [len(train) if s == "ALL" else int(s) for s in sizes]
        steps = int(args.sweep_epochs * len(train))
        rows_by_id = [{"utterance_id": ex.utterance_id} for ex in train]
        by_id = {ex.utterance_id: ex for ex in train}
        subsets = nested_subsets(rows_by_id, sizes_n)
        print(f"\nsweep: fbank-blstm, {steps} steps for every size (one utterance per step)", flush=True)
        points = []
        for size, subset in subsets.items():
            examples = [by_id[r["utterance_id"]] for r in subset]
            config = TrainConfig(preset="fbank-blstm", epochs=max(1, math.ceil(steps / size)),
                                 max_steps_per_epoch=min(size, steps))
            # no validation inside the run (hundreds of epochs for the small sizes): judged once at the end
            model, _ = trained_model(f"sweep-n{size}", config, examples, [], verbose=False)
            l1 = evaluate(model, val)[0]
            points.append((size, l1))
            print(f"  {size:5d} utterances: val L1x100 {l1:.2f}", flush=True)
        plot = plot_sweep(points, OUT / "sweep.png", f"fbank-blstm: val L1 x 100 by training size ({steps} steps)")
        print("\n| training utterances | val L1 x 100 |\n|---|---|")
        for size, l1 in points:
            print(f"| {size} | {l1:.2f} |")
        print(f"plot: {plot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
