"""Training and inference on the CPU and on CUDA side by side: seconds per epoch, utterances per second, and the
GPU's speed-up over the CPU of the same machine, per preset and batch size (printed, never asserted).

Run: .venv/bin/python bench/devices.py [--presets fbank-blstm,lpc-blstm] [--batch-sizes 1,8] [--utterances 32]
     [--epochs 2] [--d-model 512] [--threads N] [--precision auto]

Data: `--utterances` synthetic utterances of 1-3 s with random target curves at 25 fps (as
`bench/wav2vec2_cache.py`): only the cost is measured, never what is learned. Each row trains the preset at width
`--d-model` (512: the presets' default) for `--epochs` epochs and reports the fastest epoch after the first (the first
pays for feature caching, cuDNN's algorithm search and allocations), so `--epochs` must be at least 2. CUDA trains
under autocast (`--precision`, as `visemeflow train --device cuda`); the CPU in float32 on `--threads` threads
(default: all the process may use). Last, the inference real-time factor of each trained model on 10 s of audio
(`predict_curves`, float32, after a warm-up) on each device. Without CUDA only the CPU rows are printed.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import torch

from visemeflow.learning.train import TrainConfig, predict_curves, train_model
from wav2vec2_cache import SR, FPS, examples


def epoch_seconds(train, config: TrainConfig, device: str, precision: str) -> tuple[float, torch.nn.Module]:
    result = train_model(train, [], config, device=device, precision=precision)
    return min(h.seconds for h in result.history[1:]), result.model


def real_time_factor(model: torch.nn.Module, device: str) -> float:
    audio = (0.1 * np.random.default_rng(0).standard_normal(10 * SR)).astype(np.float32)
    model = model.to(device)
    predict_curves(model, audio, SR, FPS)  # warm-up
    if device == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    predict_curves(model, audio, SR, FPS)
    if device == "cuda":
        torch.cuda.synchronize()
    return (time.perf_counter() - t0) / 10.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", default="fbank-blstm,lpc-blstm")
    ap.add_argument("--batch-sizes", default="1,8")
    ap.add_argument("--utterances", type=int, default=32)
    ap.add_argument("--epochs", type=int, default=2)
    ap.add_argument("--d-model", type=int, default=512)
    ap.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
    ap.add_argument("--precision", default="auto")
    args = ap.parse_args()
    if args.epochs < 2:
        ap.error("--epochs must be at least 2 (the first epoch is not timed)")
    torch.set_num_threads(args.threads)
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    train = examples(args.utterances)
    audio_s = sum(len(ex.audio) for ex in train) / SR
    gpu = torch.cuda.get_device_name() if "cuda" in devices else "no CUDA device: CPU rows only"
    print(f"devices: {args.utterances} utterances ({audio_s:.1f} s of audio), d_model {args.d_model}, CPU on "
          f"{args.threads} thread(s) (float32), CUDA: {gpu} ({args.precision})", flush=True)
    print(f"{'preset':<18} {'batch':>5} " + " ".join(f"{d + ' s/epoch':>14} {d + ' utt/s':>11}" for d in devices)
          + (f" {'speed-up':>8}" if len(devices) > 1 else ""))
    rtf: dict[str, dict[str, float]] = {}
    for preset in args.presets.split(","):
        for batch in (int(b) for b in args.batch_sizes.split(",")):
            config = TrainConfig(preset=preset, epochs=args.epochs, d_model=args.d_model, seed=0, batch_size=batch)
            secs = {}
            for device in devices:
                secs[device], model = epoch_seconds(train, config, device, args.precision)
                if batch == 1:
                    rtf.setdefault(preset, {})[device] = real_time_factor(model, device)
            line = f"{preset:<18} {batch:>5} " + " ".join(
                f"{secs[d]:>14.3f} {len(train) / secs[d]:>11.1f}" for d in devices)
            if len(devices) > 1:
                line += f" {secs['cpu'] / secs['cuda']:>7.1f}x"
            print(line, flush=True)
    for preset, per in rtf.items():
        print(f"inference real-time factor, {preset} (10 s of audio): "
              + ", ".join(f"{d} {v:.4f}" for d, v in per.items())
              + (f" ({per['cpu'] / per['cuda']:.1f}x)" if len(per) > 1 else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
