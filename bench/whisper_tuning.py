"""Frozen against fine-tuned Whisper (issue 25 item 7): does training the encoder's top blocks
(`TrainConfig.whisper_tune_layers`) help on speakers no recipe trained on, and what does training cost on a GPU
(whisper-base, and a random-init whisper-small for the cost alone)? Printed, never asserted.

Two steps, because the lent GPU machine has torch but not our data, and a call carries at most 64 MiB:

  .venv/bin/python bench/whisper_tuning.py pack .devbench/tuning.pt.gz
      here: the shipped recipe's training data (`lj+fg`: the 24 LJSpeech examples with 0.05-s closure ramps in
      their procedural targets, FACEGOOD takes 02-04 in 8-s pieces), the held-out sets (GRID s1, the charsiu
      Mandarin utterance, praatio's two speakers, FACEGOOD take 05 with its jawOpen) as bench/encoders.py loads
      them, audio as 16-bit; and the whisper-base encoder's weights as float16 (their values as the package file
      holds them, so the encoder digest is the package's), gzipped: about 46 MB (the LJ audio is read from the repository's wavs).
  python bench/whisper_tuning.py run .devbench/tuning.pt.gz --device cuda [--tune 0,2,6] [--seeds 0,1] [--steps 2400]
      [--cost] [--save DIR]
      anywhere: one row per (tuned blocks, seed) of bench/encoders.py's judge (judging.py), the default recipe
      (whisper-base-blstm, weighted layers, d 128, lr 1e-3, one utterance per step, closure:4 loss, viseme loss 0.1,
      MBP peaks 0.067 s / 16 at inference), tuned blocks at `--tune-lr` (default 1e-5); training seconds and peak
      GPU memory per row. `--cost`: training steps per second and peak memory for whisper-base and a random-init
      whisper-small (12 blocks, d 768) with 0, 2 and all blocks tuned, batches of 1 and 8 eight-second utterances.
      `--save DIR` writes each trained model (bench/thirdlang.py --models judges them on Dutch and Czech).
"""

from __future__ import annotations

import argparse
import copy
import gzip
import math
import sys
import time
import wave
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from judging import HEADER, judge, make_loss, row  # noqa: E402

from visemeflow.learning import features as F  # noqa: E402
from visemeflow.learning.model import ClosurePeaks  # noqa: E402
from visemeflow.learning.train import Example, TrainConfig, predict_curves, save_model, train_model  # noqa: E402
from visemeflow.learning.whisper import WhisperDims, WhisperEncoder  # noqa: E402

FPS, SAMPLE_RATE = 30.0, 16000
ROOT = Path(__file__).resolve().parent.parent
SMALL = WhisperDims(n_mels=80, d_model=768, n_layers=12, n_heads=12, d_ffn=3072, n_ctx=1500)


def _int16(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.round(np.clip(a, -1, 1) * 32767).astype(np.int16))


def _float(a: torch.Tensor) -> np.ndarray:
    return a.numpy().astype(np.float32) / 32767


def pack(path: Path) -> None:
    from encoders import load_sets

    from visemeflow.learning.whisper import load_whisper_encoder

    sets = load_sets(closure_ramp_s=0.05)

    def example(e: Example) -> dict:
        out = {"uid": e.utterance_id, "curves": torch.from_numpy(e.curves), "fps": e.fps,
               "visemes": None if e.visemes is None else torch.from_numpy(np.asarray(e.visemes))}
        wav = Path("examples/corpus") / f"{e.utterance_id}.wav"   # in the repository, which travels anyway
        if (ROOT / wav).is_file() and np.array_equal(_read_wav(ROOT / wav), e.audio):
            return {**out, "wav": str(wav)}
        return {**out, "audio": _int16(e.audio)}

    from visemeflow.learning.whisper import mel_filters

    enc = load_whisper_encoder("package")
    blob = {
        "mel_filters": mel_filters(enc.dims.n_mels),   # librosa's, which the GPU machine lacks
        "train": {"lj": [example(e) for e in sets.lj], "fg": [example(e) for e in sets.facegood]},
        "held_out": {name: [{"uid": u.uid, "audio": _int16(u.audio), "n": u.n, "phones": u.phones} for u in us]
                     for name, us in sets.held_out.items()},
        "test_audio": _int16(sets.test_audio), "test_curves": torch.from_numpy(sets.test_curves),
        "test_jaw": torch.from_numpy(np.asarray(sets.test_jaw, np.float32)),
        "floor": torch.from_numpy(np.asarray(sets.floor, np.float32)),
        "encoder": {"dims": enc.dims.to_dict(), "state": {k: v.half() if v.is_floating_point() else v
                                                          for k, v in enc.state_dict().items()},
                    "digest": enc.fingerprint()},
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    with gzip.open(path, "wb", compresslevel=9) as fh:   # 64 -> 51 MB: a device call carries 64 MiB in all
        torch.save(blob, fh)
    print(f"{path}: {path.stat().st_size / 1e6:.1f} MB")


class _Sets:
    """What judging.judge reads, from a packed file."""

    def __init__(self, blob: dict) -> None:
        class U:
            def __init__(self, d: dict) -> None:
                self.uid, self.audio, self.n, self.phones = d["uid"], _float(d["audio"]), d["n"], d["phones"]

        self.held_out = {name: [U(d) for d in us] for name, us in blob["held_out"].items()}
        self.test_audio = _float(blob["test_audio"])
        self.test_curves = blob["test_curves"].numpy()
        self.test_jaw = blob["test_jaw"].numpy()
        self.floor = blob["floor"].numpy()


def _serve_encoders(blob: dict) -> None:
    """`whisper_source="package"` answers with the packed whisper-base weights (a fresh copy each time: tuning
    changes an encoder in place), `"random-small"` with a random-init whisper-small."""
    from visemeflow.learning import whisper as W

    filters = blob["mel_filters"]
    W._MEL_CACHE[(filters.shape[0], W.N_FFT, W.SAMPLE_RATE)] = filters
    dims = WhisperDims(**blob["encoder"]["dims"])
    base = WhisperEncoder(dims)
    base.load_state_dict({k: v.float() for k, v in blob["encoder"]["state"].items()})
    if base.fingerprint() != blob["encoder"]["digest"]:
        raise SystemExit("the packed encoder's digest is not the package's: repack it")

    def load(source: str = "package") -> WhisperEncoder:
        if source == "random-small":
            torch.manual_seed(0)
            enc = WhisperEncoder(SMALL)
        elif source == "package":
            enc = copy.deepcopy(base)
        else:
            raise SystemExit(f"no packed encoder for source {source!r}")
        for q in enc.parameters():
            q.requires_grad_(False)
        return enc.eval()

    F.load_whisper_encoder = load


def _read_wav(path: Path) -> np.ndarray:
    """A 16-kHz 16-bit mono wav as float32 (x / 32768, as soundfile reads it), with the standard library alone."""
    with wave.open(str(path)) as w:
        if (w.getframerate(), w.getsampwidth(), w.getnchannels()) != (SAMPLE_RATE, 2, 1):
            return np.zeros(0, np.float32)
        return np.frombuffer(w.readframes(w.getnframes()), "<i2").astype(np.float32) / 32768


def _examples(items: list[dict]) -> list[Example]:
    return [Example(d["uid"], _read_wav(ROOT / d["wav"]) if "wav" in d else _float(d["audio"]), d["curves"].numpy(),
                    d["fps"], None if d["visemes"] is None else d["visemes"].numpy()) for d in items]


def _peak_mb(device: str) -> float:
    return torch.cuda.max_memory_allocated() / 2**20 if device.startswith("cuda") else math.nan


def cost(device: str, encoders: str = "base,small", steps: int = 10) -> None:
    """Steps per second and peak memory of training, 8-s utterances, per encoder, tuned blocks and batch size."""
    rng = np.random.default_rng(0)
    n = 8 * SAMPLE_RATE
    data = [Example(f"c{i}", (rng.standard_normal(n) * 0.1).astype(np.float32),
                    rng.random((int(8 * FPS), 16)).astype(np.float32), FPS) for i in range(8 * steps)]
    print("\n| encoder | tuned blocks | batch | steps/s | utterances/s | peak GPU MB |\n|---|---|---|---|---|---|")
    table = {"base": ("whisper-base (packed)", "package", (0, 2, 6)),
             "small": ("whisper-small (random init)", "random-small", (0, 2, 12))}
    for name, source, blocks in (table[k] for k in encoders.split(",")):
        preset = "whisper-base-blstm" if source == "package" else "whisper-small-blstm"
        for tune in blocks:
            for batch in (1, 8):
                if device.startswith("cuda"):
                    torch.cuda.empty_cache()
                    torch.cuda.reset_peak_memory_stats()
                cfg = TrainConfig(preset=preset, whisper_source=source, whisper_layers="weighted", d_model=128,
                                  whisper_tune_layers=tune, batch_size=batch, epochs=2)
                # batch x steps utterances: the first epoch encodes each once, the second is timed
                result = train_model(data[: batch * steps], [], cfg, device=device,
                                     encoder_cache=F.EncoderOutputCache())
                second = result.history[-1]
                rate = second.steps / second.seconds
                print(f"| {name} | {tune} | {batch} | {rate:.1f} | {rate * batch:.1f} | {_peak_mb(device):.0f} |",
                      flush=True)


def run(args: argparse.Namespace) -> None:
    if not args.data.exists():   # here, with the data: pack it first
        pack(args.data)
    with gzip.open(args.data, "rb") as fh:
        blob = torch.load(fh, weights_only=False)   # our own packed file (it holds the phones' objects)
    _serve_encoders(blob)
    sets = _Sets(blob)
    train = _examples(blob["train"]["lj"]) + _examples(blob["train"]["fg"])
    print(f"device {args.device} ({torch.cuda.get_device_name() if args.device.startswith('cuda') else 'cpu'}); "
          f"{len(train)} training examples; held out: "
          + ", ".join(f"{k} {len(v)}" for k, v in sets.held_out.items()), flush=True)
    rows = []
    print("\n" + HEADER.replace("| train s |", "| train s | peak GPU MB |").replace("|---" * 13, "|---" * 14),
          flush=True)
    for seed in (int(s) for s in args.seeds.split(",") if s):
        for tune in (int(t) for t in args.tune.split(",")):
            if args.device.startswith("cuda"):
                torch.cuda.empty_cache()
                torch.cuda.reset_peak_memory_stats()
            epochs = -(-args.steps // len(train))
            cfg = TrainConfig(preset="whisper-base-blstm", d_model=128, epochs=epochs, seed=seed, lr=1e-3,
                              max_steps_per_epoch=min(len(train), -(-args.steps // epochs)), viseme_loss_weight=0.1,
                              whisper_layers="weighted", whisper_tune_layers=tune, whisper_tune_lr=args.tune_lr)
            started = time.perf_counter()
            model = train_model(train, [], cfg, device=args.device, encoder_cache=F.EncoderOutputCache(),
                                loss=make_loss("closure:4")).model
            secs = time.perf_counter() - started
            peak = _peak_mb(args.device)
            model.closure_peaks = ClosurePeaks(0.067, 16)
            model.eval()
            if args.save is not None and str(tune) in args.save_tune.split(","):
                args.save.mkdir(parents=True, exist_ok=True)
                save_model(model, cfg.model_copy(update={"mbp_peaks_half_window_s": 0.067, "mbp_peaks_power": 16.0}),
                           args.save / f"tune{tune}_s{seed}.pt",
                           {"script": "bench/whisper_tuning.py", "recipe": "lj+fg+cls0.1", "loss": "closure:4",
                            "tune": tune, "tune_lr": args.tune_lr, "seed": seed, "steps": args.steps})

            def predict(audio: np.ndarray, n: int, model=model) -> np.ndarray:
                return predict_curves(model, audio, SAMPLE_RATE, FPS, n_frames=n)

            line = row(f"tune {tune} (lr {args.tune_lr:g}), seed {seed}", judge(sets, predict), secs)
            rows.append(line + f" {peak:.0f} |")
            print(rows[-1], flush=True)
    if args.cost:   # after the rows: a call cut short by its time limit keeps them
        cost(args.device, args.cost_encoders, args.cost_steps)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("pack", help="write the data and encoder file (here)")
    p.add_argument("path", type=Path)
    r = sub.add_parser("run", help="train and judge frozen against tuned (the GPU machine)")
    r.add_argument("data", type=Path)
    r.add_argument("--device", default="cuda")
    r.add_argument("--tune", default="0,2,6", help="tuned top blocks, comma-separated: one row each")
    r.add_argument("--tune-lr", type=float, default=1e-5)
    r.add_argument("--seeds", default="0,1")
    r.add_argument("--steps", type=int, default=2400)
    r.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    r.add_argument("--cost", action="store_true", help="also the training cost table")
    r.add_argument("--cost-encoders", default="base,small", help="the cost table's encoders: base, small")
    r.add_argument("--cost-steps", type=int, default=10, help="timed steps per row of the cost table")
    r.add_argument("--save", type=Path, default=None, metavar="DIR")
    r.add_argument("--save-tune", default="0,2", help="which tuned-block counts --save writes (a tuned whisper-base "
                                                      "block is 12 MB of the file)")
    args = parser.parse_args()
    if args.command == "pack":
        pack(args.path)
    else:
        if args.threads:
            torch.set_num_threads(args.threads)
        run(args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
