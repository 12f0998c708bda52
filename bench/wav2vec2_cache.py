"""The frozen wav2vec2 CNN encoder's output cache in training: seconds per epoch with and without it, side by side
(printed, never asserted), and whether the trained weights are the same.

Run: .venv/bin/python bench/wav2vec2_cache.py [--encoder tiny|xlsr-cnn|xlsr53] [--epochs 4] [--utterances 8]
     [--batch-size 1] [--device cpu|cuda|auto] [--precision auto|fp32|bf16|fp16] [--threads 1] [--repeats 3]
     [--seconds 1,3]

Model: the `wav2vec2-blstm` preset (d_model 16 unless --d-model) on a randomly initialised Wav2Vec2 (no weights can be
downloaded here):
- tiny: `visemeflow.learning.features.make_tiny_wav2vec2` (3 conv layers of 32 channels, 2 transformer layers of
  32), what the tests use;
- xlsr-cnn: XLSR-53's CNN feature encoder (7 conv layers of 512 channels, strides 5,2,2,2,2,2,2) with the tiny
  transformer: the encoder's cost as in the paper's model, the rest small;
- xlsr53: the whole XLSR-53 architecture (24 layers of 1024, 315 M parameters): for a GPU.
Data: `--utterances` synthetic utterances of 1-3 s (`--seconds`; noise under a slow envelope), random target curves
at 25 fps.

Rows: `off` runs the encoder at every step (the behaviour before the cache); `memory` keeps its outputs for the run
(the default of `train_model`); `disk, warm` is a second run reading the files a first `disk` run wrote (every
epoch skips the encoder). Columns: epoch 1 (the cache fills), later epochs (the fastest one), steps/s in it, the
speed-up of later epochs against `off` (each timing the fastest of `--repeats` runs: the machine may be shared),
and whether the final weights equal `off`'s bit for bit (batch size 1) or their largest difference (batches: the
uncached batch runs the CNN on zero-padded audio). On CUDA also the run's peak GPU memory, and whether two runs of a
row give the same weights (cuDNN's and autocast's kernels need not be deterministic). Then the CNN encoder's time
measured on its own: its forward without gradient against the whole wav2vec2 model's forward + backward, one 2 s
utterance, fastest of 3 (what the cache takes out of a step, roughly: in training the CNN's large activations also
slow what follows them, so the measured speed-up can exceed this share). Last line: the inference real-time factor
of the trained model (seconds per second of audio, `predict_curves` one utterance at a time, float32, after a
warm-up).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from visemeflow.learning.device import resolve_device
from visemeflow.learning.features import EncoderOutputCache, make_tiny_wav2vec2
from visemeflow.learning.train import Example, TrainConfig, predict_curves, train_model

SR, FPS = 16000, 25.0
XLSR_CNN = {"conv_dim": (512,) * 7, "conv_kernel": (10, 3, 3, 3, 3, 2, 2), "conv_stride": (5, 2, 2, 2, 2, 2, 2),
            "conv_bias": True}
XLSR53 = {**XLSR_CNN, "hidden_size": 1024, "num_hidden_layers": 24, "num_attention_heads": 16,
          "intermediate_size": 4096, "num_conv_pos_embeddings": 128, "num_conv_pos_embedding_groups": 16}


def examples(n: int, seed: int = 0, seconds: tuple[float, float] = (1.0, 3.0)) -> list[Example]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        dur = float(rng.uniform(*seconds))
        t = np.arange(int(dur * SR)) / SR
        env = 0.5 + 0.5 * np.sin(2 * np.pi * rng.uniform(0.7, 2.0) * t)
        audio = (0.3 * env * rng.standard_normal(t.size)).astype(np.float32)
        out.append(Example(f"u{i}", audio, rng.uniform(0, 1, (round(dur * FPS), 16)).astype(np.float32), FPS))
    return out


def run(train, config, device, precision, cache) -> dict:
    """One training run. The model comes back on the CPU, so that runs kept for the table hold no GPU memory and
    each run's peak counts only what it allocated itself (above what was allocated when it started)."""
    device = resolve_device(device)
    base = 0
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)
        base = torch.cuda.memory_allocated(device)
    t0 = time.perf_counter()
    result = train_model(train, [], config, device=device, precision=precision, encoder_cache=cache)
    total = time.perf_counter() - t0
    secs = [h.seconds for h in result.history]
    later = secs[1:] or secs
    steps = result.history[-1].steps
    peak = (torch.cuda.max_memory_allocated(device) - base) / 1e9 if device.type == "cuda" else None
    state = {k: v.detach().float().cpu() for k, v in result.model.state_dict().items()}
    return {"model": result.model.cpu(), "epoch1": secs[0], "later": min(later), "steps_per_s": steps / min(later),
            "total": total, "state": state, "peak_gb": peak}


def largest_difference(a: dict, b: dict) -> float:
    return max(float((a[k] - b[k]).abs().max()) for k in a)


def encoder_share(w2v_path: Path, device: torch.device) -> tuple[float, float]:
    """(CNN forward seconds, wav2vec2 forward + backward seconds) for one 2 s utterance, fastest of 3."""
    from transformers import Wav2Vec2Model

    model = Wav2Vec2Model.from_pretrained(str(w2v_path)).to(device)
    model.freeze_feature_encoder()
    model.train()
    x = torch.randn(1, 2 * SR, generator=torch.Generator().manual_seed(0)).to(device)

    def timed(fn) -> float:
        best = float("inf")
        for _ in range(3):
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            t0 = time.perf_counter()
            fn()
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            best = min(best, time.perf_counter() - t0)
        return best

    def cnn() -> None:
        with torch.no_grad():
            model.feature_extractor(x)

    def step() -> None:
        model(x).last_hidden_state.sum().backward()
        model.zero_grad(set_to_none=True)

    return timed(cnn), timed(step)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--encoder", choices=["tiny", "xlsr-cnn", "xlsr53"], default="tiny")
    ap.add_argument("--epochs", type=int, default=4)
    ap.add_argument("--utterances", type=int, default=8)
    ap.add_argument("--batch-size", type=int, default=1)
    ap.add_argument("--d-model", type=int, default=16)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--precision", default="auto")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seconds", default="1,3", help="utterance durations drawn uniformly in MIN,MAX seconds")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    work = Path(tempfile.mkdtemp(prefix="w2v-cache-bench-"))
    overrides = {"tiny": {}, "xlsr-cnn": XLSR_CNN, "xlsr53": XLSR53}[args.encoder]
    w2v = make_tiny_wav2vec2(work / "w2v", seed=0, **overrides)
    low, high = (float(x) for x in args.seconds.split(","))
    train = examples(args.utterances, seconds=(low, high))
    config = TrainConfig(preset="wav2vec2-blstm", epochs=args.epochs, d_model=args.d_model, seed=0,
                         wav2vec2_model=str(w2v), batch_size=args.batch_size)
    device = resolve_device(args.device)
    audio_s = sum(len(ex.audio) for ex in train) / SR
    print(f"wav2vec2 encoder cache: {args.encoder} encoder, {len(train)} utterances ({audio_s:.1f} s of audio), "
          f"{args.epochs} epochs, batch {args.batch_size}, {device} ({args.precision}), {args.threads} thread(s)",
          flush=True)

    run_to_run = []

    def fastest(cache) -> dict:
        runs = [run(train, config, device, args.precision, cache()) for _ in range(max(1, args.repeats))]
        if len(runs) > 1:
            run_to_run.append(largest_difference(runs[0]["state"], runs[1]["state"]))
        best = min(runs, key=lambda r: r["later"])
        return {**best, "epoch1": min(r["epoch1"] for r in runs)}

    rows = {"off": fastest(lambda: False), "memory": fastest(lambda: True)}
    run(train, config, device, args.precision, EncoderOutputCache(work / "enc"))  # writes the files
    rows["disk, warm"] = fastest(lambda: EncoderOutputCache(work / "enc"))

    ref = rows["off"]
    header = f"{'cache':<11} {'epoch 1 s':>9} {'later s/epoch':>13} {'steps/s':>8} {'speed-up':>8} {'same weights':>13}"
    if device.type == "cuda":
        header += f" {'peak GB':>8}"
    print(header)
    for name, r in rows.items():
        diff = largest_difference(r["state"], ref["state"])
        same = "yes" if diff == 0.0 else f"{diff:.1e}"
        line = (f"{name:<11} {r['epoch1']:>9.3f} {r['later']:>13.3f} {r['steps_per_s']:>8.2f} "
                f"{ref['later'] / r['later']:>7.2f}x {same:>13}")
        if device.type == "cuda":
            line += f" {r['peak_gb']:>8.2f}"
        print(line)
    if run_to_run:
        print(f"two runs of the same row, same seed: largest weight difference {max(run_to_run):.1e} "
              f"({'bit-identical' if max(run_to_run) == 0 else 'the kernels are not deterministic here'})")
    cnn_s, step_s = encoder_share(w2v, device)
    print(f"CNN encoder alone vs a whole wav2vec2 forward + backward (2 s utterance): {cnn_s:.3f} s of {step_s:.3f} s "
          f"({cnn_s / step_s:.1%})")
    model = ref["model"].to(device)
    predict_curves(model, train[0].audio, SR, FPS)  # warm-up
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    for ex in train:
        predict_curves(model, ex.audio, SR, FPS)
    print(f"inference real-time factor: {(time.perf_counter() - t0) / audio_s:.4f} ({device}, float32)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
