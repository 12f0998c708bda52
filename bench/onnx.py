"""ONNX Runtime vs torch: inference real-time factor on one core for 10 s of speech, per exportable preset,
with the file sizes (printed side by side, never asserted).

Run: .venv/bin/python bench/onnx.py [--presets fbank-blstm,...] [--wav2vec2 large|base|tiny] [--repeats 5]

Models are untrained (weights do not change the cost) at the presets' own widths (d_model 512; karras-lpc 256),
curve fps 30, saved with save_model and exported with export_onnx (opset 17, 16 kHz input, its own check on).
wav2vec2 presets need a local wav2vec2; none can be downloaded here, so a randomly initialised one is built
with make_tiny_wav2vec2 and the architecture of XLSR-53 (`large`: 24 layers, 1024 wide, the paper's model),
of wav2vec2-base (`base`: 12 x 768), or the test model (`tiny`). Only wav2vec2-blstm is in the default list:
the other wav2vec2 decoders differ by their head, which the fbank rows time.

Timing: 10.0 s of speech (LJ001-0001 and the start of LJ001-0002, 16 kHz). torch: predict_curves with
torch.set_num_threads(1) (features + head + clip, as the predict flow runs it). ONNX Runtime: one
CPUExecutionProvider session, intra_op_num_threads=1, inter_op_num_threads=1, sequential, all graph
optimisations; session creation is not timed. One warm-up run each, then the median of --repeats runs.
RTF = seconds per second of audio. `max|diff|` compares the two outputs on that clip.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

# run as a script, this file's folder is sys.path[0] and the file itself would shadow the `onnx` package
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]

import numpy as np  # noqa: E402
import soundfile as sf  # noqa: E402
import torch  # noqa: E402

from visemeflow.learning.features import make_tiny_wav2vec2  # noqa: E402
from visemeflow.learning.onnx_export import EXPORTABLE_PRESETS, _session, export_onnx  # noqa: E402
from visemeflow.learning.presets import PRESETS  # noqa: E402
from visemeflow.learning.train import TrainConfig, build_training_model, predict_curves, save_model  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "bench" / "out" / "onnx"
CORPUS = REPO / "examples" / "corpus" / "LJ"
SECONDS = 10.0
FPS = 30.0

WAV2VEC2_SIZES = {
    # the architecture of facebook/wav2vec2-large-xlsr-53 (weights random)
    "large": dict(hidden_size=1024, num_hidden_layers=24, num_attention_heads=16, intermediate_size=4096,
                  conv_dim=(512,) * 7, conv_kernel=(10, 3, 3, 3, 3, 2, 2), conv_stride=(5, 2, 2, 2, 2, 2, 2),
                  conv_bias=True, num_conv_pos_embeddings=128, num_conv_pos_embedding_groups=16),
    # wav2vec2-base sized, with the layer-norm feature encoder the extractor needs for padding invariance
    "base": dict(hidden_size=768, num_hidden_layers=12, num_attention_heads=12, intermediate_size=3072,
                 conv_dim=(512,) * 7, conv_kernel=(10, 3, 3, 3, 3, 2, 2), conv_stride=(5, 2, 2, 2, 2, 2, 2),
                 conv_bias=True, num_conv_pos_embeddings=128, num_conv_pos_embedding_groups=16),
    "tiny": {},
}
DEFAULT_PRESETS = [p for p in EXPORTABLE_PRESETS if PRESETS[p].feature not in ("wav2vec2", "whisper")] + [
    "wav2vec2-blstm", "whisper-base-blstm"]


def speech(seconds: float) -> np.ndarray:
    parts, n = [], round(seconds * 16000)
    for name in ("LJ001-0001.wav", "LJ001-0002.wav", "LJ001-0003.wav"):
        audio, rate = sf.read(CORPUS / name, dtype="float32")
        assert rate == 16000
        parts.append(audio)
        if sum(map(len, parts)) >= n:
            break
    return np.concatenate(parts)[:n]


def median_seconds(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def time_onnx(path: Path, audio: np.ndarray, repeats: int) -> tuple[float, np.ndarray]:
    """Median seconds of one ONNX Runtime call on one thread, and its curves (frames, 16)."""
    sess = _session(path, threads=1)
    x = audio[None]
    seconds = median_seconds(lambda: sess.run(["curves"], {"audio": x}), repeats)
    return seconds, sess.run(["curves"], {"audio": x})[0][0]


def mb(n_bytes: int) -> str:
    return f"{n_bytes / 1e6:.2f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", default=",".join(DEFAULT_PRESETS))
    ap.add_argument("--wav2vec2", choices=sorted(WAV2VEC2_SIZES), default="large")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    presets = [p for p in args.presets.split(",") if p]
    bad = [p for p in presets if p not in EXPORTABLE_PRESETS]
    if bad:
        print(f"not exportable: {', '.join(bad)}", file=sys.stderr)
        return 2
    OUT.mkdir(parents=True, exist_ok=True)
    audio = speech(SECONDS)
    w2v = None
    if any(PRESETS[p].feature == "wav2vec2" for p in presets):
        w2v = OUT / f"wav2vec2-{args.wav2vec2}"
        if not (w2v / "config.json").exists():
            make_tiny_wav2vec2(w2v, seed=0, **WAV2VEC2_SIZES[args.wav2vec2])

    print(f"torch {torch.__version__}, onnxruntime {__import__('onnxruntime').__version__}; {SECONDS:.0f} s of "
          f"speech, curves at {FPS:.0f} fps, one thread each; median of {args.repeats} (after one warm-up)")
    header = (f"{'preset':<22}{'params':>11}{'.pt MB':>9}{'.onnx MB':>10}{'export s':>10}"
              f"{'torch RTF':>11}{'ORT RTF':>9}{'ORT/torch':>11}{'max|diff|':>11}")
    print(header)
    print("-" * len(header))
    for preset in presets:
        torch.manual_seed(0)
        config = TrainConfig(preset=preset, seed=0,
                             wav2vec2_model=str(w2v) if PRESETS[preset].feature == "wav2vec2" else None)
        model = build_training_model(config, curve_fps=FPS).eval()
        suffix = f"-{args.wav2vec2}" if PRESETS[preset].feature == "wav2vec2" else ""
        pt = save_model(model, config, OUT / f"{preset}{suffix}.pt", {"source": "bench/onnx.py (untrained)"})
        report = export_onnx(pt, OUT / f"{preset}{suffix}.onnx")
        params = sum(p.numel() for p in model.parameters())

        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            t_torch = median_seconds(lambda: predict_curves(model, audio, 16000, FPS), args.repeats)
            want = predict_curves(model, audio, 16000, FPS)
        finally:
            torch.set_num_threads(threads)
        t_ort, got = time_onnx(report.path, audio, args.repeats)
        diff = float(np.abs(got - want).max()) if got.shape == want.shape else float("nan")
        print(f"{preset + suffix:<22}{params:>11,}{mb(pt.stat().st_size):>9}{mb(report.size_bytes):>10}"
              f"{report.export_seconds:>10.1f}{t_torch / SECONDS:>11.2e}{t_ort / SECONDS:>9.2e}"
              f"{t_ort / t_torch:>11.2f}{diff:>11.1e}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
