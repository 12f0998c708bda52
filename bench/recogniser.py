"""Curves from recognised phones (`predict --model phones`) on real speech, side by side with the shipped learned
model, under the robustness conditions of `evaluate` (volume, pitch, speed, noise). Printed, never asserted.

Run: .venv/bin/python bench/recogniser.py [--seed 0] [--threads 1]

Real speech, with forced alignments for the metrics only (no curve truth needed; `visemeflow.learning.realspeech`):
- LJ: the 24 LJSpeech examples of examples/corpus (one woman, read English); both shipped learned models trained on
  them, so their LJ rows are in-sample; nothing of pocketsphinx's was trained on them;
- held out: GRID s1's 10 clips (a man; phones from the word alignment and CMUdict), the charsiu Mandarin utterance
  and praatio's two examples (bobby, mary; bench/encoders.py's held-out sets): speakers no model of ours heard
  (English phones only for the recogniser: Mandarin is out of language).

Rows: the recogniser as shipped (phone times at the centre of its analysis window, closure bias 1), beside the frame
starts as pocketsphinx reports them (shift 0) and a closure bias of 16; the shipped learned model (`default`); the
alignment's own procedural curves (the ceiling of the definitions); with `--models`, the shipped learned models:
`default` (whisper-base-blstm) and `default-fbank` (the previous default). Each condition of the robustness evaluation is
drawn per utterance as `evaluate` does (`augment_utterance`, the paper's ranges, `--seed`); speed copies score against
phones scaled by their factor. Columns: b/p/m closure recall (MBP strictly the top viseme within the phone), false
closures (share of the other phones), FFF closure recall, top-2 agreement, real-time factor of the curves.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from realspeech import FPS, SAMPLE_RATE, read_corpus  # noqa: E402

from visemeflow.learning.augment import augment_utterance  # noqa: E402
from visemeflow.learning.default_model import default_model_path, shipped_model_path  # noqa: E402
from visemeflow.learning.realspeech import pool, scale_phones, score_utterance  # noqa: E402
from visemeflow.learning.train import load_model, predict_curves  # noqa: E402
from visemeflow.phonetics.recognise import shared_recogniser  # noqa: E402
from visemeflow.procedural.recognised import recognised_curves  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
CONDITIONS = ("clean", "volume", "pitch", "speed", "noise")


def held_out() -> list:
    from encoders import held_out_sets

    with tempfile.TemporaryDirectory() as tmp:
        return [u for us in held_out_sets(Path(tmp)).values() for u in us]


def share(r) -> str:
    return f"{r.hits}/{r.total} ({100 * (r.share or 0):.0f}%)"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--models", default="", help="only these curve sources (comma-separated row names' first word: "
                    "phones, default, default-fbank); default: all")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    sets = {"LJ (24, in the learned models' training)": [u for u in read_corpus(ROOT / "examples" / "corpus")
                                                         if u.speaker == "LJ"],
            "GRID s1 + Mandarin + praatio (held out)": held_out()}
    default = load_model(default_model_path())[0]
    fbank = load_model(shipped_model_path("default-fbank"))[0]
    methods = {
        "phones (as shipped)": lambda a, n: recognised_curves(a, SAMPLE_RATE, FPS, n),
        "phones, frame starts (shift 0)": lambda a, n: recognised_curves(
            a, SAMPLE_RATE, FPS, n, recogniser=shared_recogniser(shift_s=0.0)),
        "phones, closure bias 16": lambda a, n: recognised_curves(
            a, SAMPLE_RATE, FPS, n, recogniser=shared_recogniser(closure_bias=16.0)),
        "default (learned, shipped: whisper-base-blstm)": lambda a, n: predict_curves(default, a, SAMPLE_RATE, FPS,
                                                                                      n_frames=n),
        "default-fbank (the previous default, fbank-blstm)": lambda a, n: predict_curves(fbank, a, SAMPLE_RATE, FPS,
                                                                                         n_frames=n),
    }
    if args.models:
        wanted = args.models.split(",")
        methods = {k: v for k, v in methods.items() if k.split(" ")[0].rstrip(",") in wanted}
    robust = [k for k in methods if k.startswith(("phones (as shipped)", "default"))]
    print(f"data in {time.perf_counter() - t0:.0f} s", flush=True)
    for set_name, utts in sets.items():
        print(f"\n### {set_name}: {len(utts)} utterances, {sum(u.n for u in utts) / FPS:.0f} s\n")
        print("| curves | condition | MBP closure | false MBP | FFF closure | top-2 agreement | real-time factor |")
        print("|---|---|---|---|---|---|---|")
        ceiling = pool(score_utterance(u.procedural, FPS, u.phones) for u in utts)
        print(f"| alignment's procedural curves (ceiling) | clean | {share(ceiling.closure['MBP'])} | "
              f"{share(ceiling.false_closure['MBP'])} | {share(ceiling.closure['FFF'])} | "
              f"{share(ceiling.agreement.overall)} | - |")
        for condition in CONDITIONS:
            copies = []
            for u in utts:
                if condition == "clean":
                    copies.append((u.audio, u.phones))
                else:
                    a = augment_utterance(u.audio, SAMPLE_RATE, u.uid, condition, args.seed)
                    copies.append((a.audio, scale_phones(u.phones, a.time_factor)))
            for name, method in methods.items():
                if condition != "clean" and name not in robust:
                    continue
                started, seconds = time.perf_counter(), sum(len(a) for a, _ in copies) / SAMPLE_RATE
                scores = pool(score_utterance(method(a, round(len(a) / SAMPLE_RATE * FPS)), FPS, phones)
                              for a, phones in copies)
                rtf = (time.perf_counter() - started) / seconds
                print(f"| {name} | {condition} | {share(scores.closure['MBP'])} | "
                      f"{share(scores.false_closure['MBP'])} | {share(scores.closure['FFF'])} | "
                      f"{share(scores.agreement.overall)} | {rtf:.3f} |", flush=True)
    print(f"\ntotal {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
