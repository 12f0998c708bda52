"""Peak memory of predicting long audio: the whole file at once (the faithful path, as `predict` did before) against
chunks read from the file as needed (`visemeflow.learning.longform`, what `predict` does now), side by side on the
same file, each in a fresh process so that its peak resident memory (VmHWM) is its own.

    .venv/bin/python bench/memory.py [--model default-fbank] [--minutes 10,60,120] [--skip-whole-above 60]

The audio is the LJ examples (16 kHz) repeated to each length and written as a 16-bit WAV. Printed per length: peak
memory of each path and their ratio, seconds and real-time factor of each, and how far the chunked curves are from
the whole-file ones (max and mean absolute difference of the 16 weights). Figures, never asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import soundfile as sf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

FPS = 30.0


def peak_mb() -> float:
    """This process's peak resident memory (VmHWM). Not ru_maxrss: Linux carries the parent's peak into a child
    across exec, so a child spawned by a parent that held the test input would report the parent's size."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmHWM in /proc/self/status (Linux only)")


def child(mode: str, model_name: str, wav: str, out: str) -> None:
    """One measurement in this (fresh) process: predict `wav` whole or chunked, save the curves, print JSON."""
    from visemeflow.ingest.audio import AudioFile, read_audio
    from visemeflow.learning.default_model import shipped_model_path
    from visemeflow.learning.longform import predict_long
    from visemeflow.learning.train import load_model, predict_curves

    model = load_model(shipped_model_path(model_name))[0]
    base = peak_mb()
    started = time.perf_counter()
    if mode == "whole":
        samples, rate = read_audio(wav)
        curves = predict_curves(model, samples, rate, FPS)
    else:
        curves = predict_long(lambda a, r, n: predict_curves(model, a, r, FPS, n_frames=n), AudioFile(wav), FPS)
    seconds = time.perf_counter() - started
    np.save(out, curves)
    print(json.dumps({"seconds": seconds, "peak_mb": peak_mb(), "model_mb": base}))


def measure(mode: str, model: str, wav: Path, out: Path) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    done = subprocess.run([sys.executable, __file__, "--child", mode, model, str(wav), str(out)],
                          capture_output=True, text=True, env=env)
    if done.returncode != 0:
        return {"error": (done.stderr.strip().splitlines() or ["killed"])[-1]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def speech(seconds: float) -> np.ndarray:
    from visemeflow.ingest.audio import read_audio

    pieces = [read_audio(w)[0] for w in sorted((ROOT / "examples" / "corpus" / "LJ").glob("*.wav"))]
    audio = np.concatenate(pieces)
    n = int(seconds * 16000)
    return np.tile(audio, -(-n // len(audio)))[:n]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="default-fbank", help="a shipped model: default (Whisper) or default-fbank")
    ap.add_argument("--minutes", default="10,60,120")
    ap.add_argument("--skip-whole-above", type=float, default=float("inf"),
                    help="minutes above which the whole-file path is not run (it may not fit in memory)")
    args = ap.parse_args()
    print(f"model {args.model}, OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', '1')}, {os.cpu_count()} cores")
    print("| audio | whole file: peak MB, s, RTF | chunked: peak MB, s, RTF | peak ratio whole/chunked | "
          "curves max / mean abs diff |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for minutes in (float(m) for m in args.minutes.split(",")):
            wav = Path(tmp) / f"{minutes:g}min.wav"
            sf.write(wav, speech(minutes * 60), 16000, subtype="PCM_16")
            dur = minutes * 60
            runs = {}
            for mode in ("whole", "chunked"):
                if mode == "whole" and minutes > args.skip_whole_above:
                    runs[mode] = {"error": "not run"}
                    continue
                runs[mode] = measure(mode, args.model, wav, Path(tmp) / f"{mode}.npy")

            def cell(r: dict) -> str:
                if "error" in r:
                    return r["error"]
                return f"{r['peak_mb']:.0f}, {r['seconds']:.0f}, {r['seconds'] / dur:.3f}"

            ratio = diff = "-"
            if "error" not in runs["whole"] and "error" not in runs["chunked"]:
                ratio = f"{runs['whole']['peak_mb'] / runs['chunked']['peak_mb']:.1f}x"
                d = np.abs(np.load(Path(tmp) / "whole.npy") - np.load(Path(tmp) / "chunked.npy"))
                diff = f"{d.max():.3f} / {d.mean():.4f}"
            print(f"| {minutes:g} min | {cell(runs['whole'])} | {cell(runs['chunked'])} | {ratio} | {diff} |",
                  flush=True)
            wav.unlink()
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(*sys.argv[2:6])
        sys.exit(0)
    sys.exit(main())
