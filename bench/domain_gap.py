"""Closing the domain gap: which training data makes a model hold on real speech of speakers it never heard
(issue 14, item 3). Printed, never asserted.

Run: .venv/bin/python bench/domain_gap.py [--steps 2400] [--d-model 128] [--lrs 1e-3] [--losses l1,closure:4]
     [--recipes synthetic,real,lj+synthetic,mixed,mixed+aug]

Training data (all shippable):
- synthetic: the espeak-ng scale corpus of bench/learning_data.py (700 English + 500 Mandarin utterances, 36
  voice/rate speakers; targets: synthetic Cohen-Massaro curves from the alignment), its training split;
- real: the LJSpeech examples of `examples/corpus/LJ` (one female English speaker; targets: the same synthetic
  curves from their MFA alignments) and FACEGOOD takes 02-04 (one female Mandarin speaker, ~5.6 min; targets: the
  animator's captured curves, converted to our 16 visemes by `visemeflow.shapes.capture`), cut into 8 s pieces.
Recipes: `synthetic`, `real`, `lj+synthetic` (the LJ examples and the espeak corpus: every target in the style of
our alignment-driven curves), `mixed` (all of it), and each with `+aug` (train-time augmentation, probability 0.5).
With the MBROLA voices installed (bench/mbrola_data.py, non-free, not installed by make): `mbrola`,
`synthetic+mbrola`, `mixed+mbrola` (`--mbrola-utterances`, default 600).
One fbank-blstm each (`--d-model`), seed 0, one utterance per step, the same budget of `--steps` steps for every
recipe (so a small real set is seen for more epochs), at each learning rate of `--lrs` (the preset's is 1e-4, which
underfits at these budgets: its predictions stay within a few hundredths of the mean curve) and with each training
loss of `--losses`:
- `l1`: the paper's masked L1;
- `closure:W`: L1 with each frame weighted 1 + W * (target MBP + target FFF), so the brief full closures weigh as
  much as the long vowels around them (`train_model(loss=...)`);
- `activation:W`: L1 with each weight weighted 1 + W * its target (every viseme's activations alike).

Beside the recipes, with no training at all: the procedural curves of phones recognised in the audio by PocketSphinx's
English model (`predict --model phones`, `visemeflow.phonetics.recognise`), at each closure bias of
`--recogniser-bias`.

Judged on real speech of speakers no recipe trained on:
- GRID s1 (10 clips, male English; phones from the word alignment and CMUdict) and the charsiu Mandarin
  utterance (AISHELL-3 speaker SSB1624 -- excluded from training): MBP and FFF closure recall, false MBP closures
  (the share of the other phones whose top viseme is MBP: recall alone rewards lips kept shut) and top-2 agreement
  (`visemeflow.learning.realspeech`, no curve truth needed); the first rows score the curves of the alignment itself
  (its synthetic truth and the procedural curves): the ceiling of the definitions;
- FACEGOOD take 05 (held out; the same speaker as takes 02-04, so a held-out *take*, not a held-out speaker): L1 x 100
  against the captured curves and the mean per-viseme correlation, with the floor of the training takes' mean curve.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from learning_data import corpus_data, load_data  # noqa: E402
from mbrola_data import available as mbrola_available  # noqa: E402
from mbrola_data import ensure_corpus as ensure_mbrola_corpus  # noqa: E402
from realspeech import FPS, SAMPLE_RATE, SHARED, read_corpus  # noqa: E402
from judging import make_loss  # noqa: E402

from visemeflow.shapes.capture import fit_visemes  # noqa: E402
from visemeflow.ingest.audio import read_audio  # noqa: E402
from visemeflow.ingest.captured import read_channel_table, read_take  # noqa: E402
from visemeflow.learning.features import resample_audio  # noqa: E402
from visemeflow.learning.realspeech import compare_curves, pool, score_utterance  # noqa: E402
from visemeflow.learning.train import Example, TrainConfig, predict_curves, train_model  # noqa: E402
from visemeflow.phonetics.recognise import shared_recogniser  # noqa: E402
from visemeflow.procedural.recognised import recognised_curves  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
FACEGOOD = SHARED / "facegood_audio2face"
TRAIN_TAKES = ("1114_2_02", "1114_2_03", "1114_2_04")
HELD_OUT_TAKE = "1114_2_05"
PIECE_S = 8.0
RECIPES = ("synthetic", "real", "lj+synthetic", "mixed", "mixed+aug")
LOSSES = ("l1", "closure:4")


def facegood_take(name: str) -> tuple[np.ndarray, np.ndarray]:
    """(16 kHz audio, (T, 16) captured viseme curves at 30 fps) of one FACEGOOD take."""
    table = read_channel_table(ROOT / "examples" / "facegood" / "voice2face_arkit.csv")
    take = read_take(FACEGOOD / f"bs_value_{name}.npy", "npy", table=table,
                     names=FACEGOOD / "shirley_1015_bs_name.npy", fps=FPS)
    samples, rate = read_audio(FACEGOOD / f"{name}.wav")
    return resample_audio(samples, rate, SAMPLE_RATE), fit_visemes(take.arkit).curves


def pieces(uid: str, audio: np.ndarray, curves: np.ndarray) -> list[Example]:
    """A long take cut into PIECE_S-second examples (the last piece takes what is left)."""
    n = min(len(curves), int(len(audio) / SAMPLE_RATE * FPS))
    step = int(PIECE_S * FPS)
    out = []
    for k, start in enumerate(range(0, n - int(FPS), step)):
        end = min(start + step, n)
        out.append(Example(f"{uid}/{k:03d}", audio[int(start / FPS * SAMPLE_RATE):int(end / FPS * SAMPLE_RATE)],
                           curves[start:end].astype(np.float32), FPS))
    return out


def grid_corpus(tmp: Path) -> Path:
    """GRID s1's clips (video with audio + word alignment) in the corpus layout, copied under `tmp`."""
    folder = tmp / "grid" / "s1"
    folder.mkdir(parents=True)
    for align in sorted((SHARED / "grid_s1" / "align").glob("*.align")):
        shutil.copyfile(align, folder / align.name)
        shutil.copyfile(SHARED / "grid_s1" / "video" / f"{align.stem}.mpg", folder / f"{align.stem}.mpg")
    return folder.parent


@dataclass
class Sets:
    synthetic: object              # learning_data.Data: train / val Examples of the espeak corpus (or None)
    real: list[Example]            # LJ examples + FACEGOOD training-take pieces
    held_out: list                 # realspeech.Utterance of GRID s1 and the charsiu Mandarin utterance
    test_audio: np.ndarray         # FACEGOOD take 05
    test_curves: np.ndarray
    floor: np.ndarray              # (16,) mean curve of the FACEGOOD training takes
    mbrola: list[Example] | None = None   # MBROLA voices (bench/mbrola_data.py), training split; None: not installed


def load_sets(synthetic: bool = True, mbrola_utterances: int = 0) -> Sets:
    """The training sets and the held-out real speech (see the module); `synthetic=False` skips the espeak corpus
    (for judging a trained model only); `mbrola_utterances` > 0 adds an MBROLA corpus of that size."""
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        lj = [u for u in read_corpus(ROOT / "examples" / "corpus") if u.speaker == "LJ"]
        held_out = read_corpus(grid_corpus(tmp))
        zh = tmp / "zh" / "SSB1624"
        zh.mkdir(parents=True)
        shutil.copyfile(SHARED / "charsiu_mandarin" / "SSB16240001_16k.wav", zh / "SSB16240001.wav")
        shutil.copyfile(SHARED / "charsiu_mandarin" / "SSB16240001.TextGrid", zh / "SSB16240001.TextGrid")
        held_out += read_corpus(zh.parent)
    captured = [e for name in TRAIN_TAKES for e in pieces(f"facegood/{name}", *facegood_take(name))]
    real = [Example(u.uid, u.audio, u.truth.astype(np.float32), FPS) for u in lj] + captured
    test_audio, test_curves = facegood_take(HELD_OUT_TAKE)
    floor = np.concatenate([e.curves for e in captured]).mean(axis=0)
    mbrola = corpus_data(ensure_mbrola_corpus(mbrola_utterances)).train if synthetic and mbrola_utterances else None
    return Sets(load_data(700, 500) if synthetic else None, real, held_out, test_audio, test_curves, floor, mbrola)


def judge(sets: Sets, predict) -> dict:
    """Real-speech figures of `predict(audio, n_frames) -> (n, 16)` on the held-out sets."""
    scores = pool(score_utterance(predict(u.audio, len(u.truth)), FPS, u.phones) for u in sets.held_out)
    comparison = compare_curves(predict(sets.test_audio, len(sets.test_curves)), sets.test_curves, FPS)
    return {"mbp": scores.closure["MBP"], "fff": scores.closure["FFF"], "false_mbp": scores.false_closure["MBP"],
            "agreement": scores.agreement.overall,
            "captured_l1_x100": comparison.l1_x100, "captured_mean_pearson": comparison.mean_pearson}


def row(name: str, j: dict) -> str:
    def share(r) -> str:
        return f"{r.hits}/{r.total} ({100 * (r.share or 0):.0f}%)"

    return (f"| {name} | {share(j['mbp'])} | {share(j['false_mbp'])} | {share(j['fff'])} | {share(j['agreement'])} | "
            f"{j['captured_l1_x100']:.2f} | {j['captured_mean_pearson']:.2f} |")


HEADER = ("| model | MBP closure (GRID + Mandarin) | false MBP closures | FFF closure | top-2 agreement | "
          "FACEGOOD take 05 L1 x 100 | mean correlation |\n|---|---|---|---|---|---|---|")


def recipe_config(recipe: str, n_train: int, steps: int, d_model: int, lr: float | None = None) -> TrainConfig:
    """fbank-blstm at an equal budget of `steps` steps; augmented recipes at probability 0.5."""
    epochs = -(-steps // n_train)
    return TrainConfig(preset="fbank-blstm", d_model=d_model, epochs=epochs, seed=0, lr=lr,
                       max_steps_per_epoch=min(n_train, -(-steps // epochs)),
                       train_augment=recipe.endswith("+aug"), train_augment_probability=0.5)


def recipe_data(sets: Sets, recipe: str) -> list[Example]:
    lj = [e for e in sets.real if not e.utterance_id.startswith("facegood/")]
    data = {"synthetic": lambda: sets.synthetic.train, "real": lambda: sets.real,
            "lj+synthetic": lambda: lj + sets.synthetic.train, "mixed": lambda: sets.synthetic.train + sets.real,
            "mbrola": lambda: sets.mbrola, "synthetic+mbrola": lambda: sets.synthetic.train + sets.mbrola,
            "mixed+mbrola": lambda: sets.synthetic.train + sets.real + sets.mbrola}
    base = recipe.removesuffix("+aug")
    if base not in data:
        raise SystemExit(f"unknown recipe {recipe!r}: {', '.join(data)}, each optionally with +aug")
    return data[base]()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=2400, help="training steps (utterances) per recipe: equal budget")
    parser.add_argument("--lrs", default="1e-3", help="learning rates (comma-separated; 'preset' = the preset's 1e-4)")
    parser.add_argument("--losses", default=",".join(LOSSES), help="training losses: l1, closure:W, activation:W")
    parser.add_argument("--d-model", type=int, default=128)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--recipes", default=",".join(RECIPES),
                        help="also: mbrola, synthetic+mbrola, mixed+mbrola (needs the MBROLA voices)")
    parser.add_argument("--mbrola-utterances", type=int, default=600, help="size of the MBROLA corpus")
    parser.add_argument("--recogniser-bias", default="1,16",
                        help="closure biases of the recognised-phone rows (comma-separated; empty: none)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    recipes = [r for r in args.recipes.split(",") if r]
    wants_mbrola = [r for r in recipes if "mbrola" in r]
    if wants_mbrola and not mbrola_available():
        print(f"left out {', '.join(wants_mbrola)}: the MBROLA voices are not installed (bench/mbrola_data.py)")
        recipes = [r for r in recipes if r not in wants_mbrola]
    sets = load_sets(mbrola_utterances=args.mbrola_utterances if wants_mbrola and mbrola_available() else 0)
    print(f"data in {time.perf_counter() - t0:.0f} s: synthetic {len(sets.synthetic.train)} train utterances; real "
          f"{len(sets.real)} examples (LJ + FACEGOOD pieces); judged on {len(sets.held_out)} held-out utterances "
          f"and FACEGOOD {HELD_OUT_TAKE} ({len(sets.test_curves)} frames)", flush=True)
    by_audio = {id(u.audio): u for u in sets.held_out}

    def of_alignment(field: str):
        return lambda audio, n: (getattr(by_audio[id(audio)], field) if id(audio) in by_audio
                                 else np.tile(sets.floor, (n, 1)).astype(np.float32))

    rows = [row("alignment's synthetic truth (ceiling; FACEGOOD columns: floor)", judge(sets, of_alignment("truth"))),
            row("alignment's procedural curves (FACEGOOD columns: floor)", judge(sets, of_alignment("procedural"))),
            row("mean curve of the FACEGOOD training takes (floor)",
                judge(sets, lambda audio, n: np.tile(sets.floor, (n, 1)).astype(np.float32)))]
    for bias in [float(b) for b in args.recogniser_bias.split(",") if b]:
        recogniser = shared_recogniser(closure_bias=bias)
        rows.append(row(f"phones recognised by pocketsphinx, closure bias {bias:g} (no training)", judge(
            sets, lambda audio, n, r=recogniser: recognised_curves(audio, SAMPLE_RATE, FPS, n, recogniser=r))))
        print(rows[-1], flush=True)
    for recipe in recipes:
        train = recipe_data(sets, recipe)
        for lr_word in args.lrs.split(","):
            lr = None if lr_word == "preset" else float(lr_word)
            for loss in args.losses.split(","):
                started = time.perf_counter()
                model = train_model(train, sets.synthetic.val[:20], recipe_config(recipe, len(train), args.steps,
                                                                                  args.d_model, lr),
                                    loss=make_loss(loss)).model
                name = f"fbank-blstm, {recipe}, {loss}, lr {lr_word}"
                print(f"{name}: trained on {len(train)} examples in {time.perf_counter() - started:.0f} s", flush=True)
                rows.append(row(name, judge(
                    sets, lambda audio, n, model=model: predict_curves(model, audio, SAMPLE_RATE, FPS, n_frames=n))))
                print(rows[-1], flush=True)
    print()
    print(HEADER)
    for r in rows:
        print(r)
    print(f"\ntargets on held-out real speech: MBP closure >= 85%; captured L1 >= 25% below the floor. "
          f"total {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
