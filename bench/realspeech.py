"""Real-speech metrics of audio-to-curves models on real utterances with forced alignments: no curve truth
needed (visemeflow.learning.realspeech). Printed, never asserted.

Run: .venv/bin/python bench/realspeech.py [--espeak-epochs 8] [--lj-epochs 8] [--folds 4] [--threads 2]

Data (real speech, Montreal Forced Aligner / Charsiu alignments), read by the product's ingestion
(`discover_corpus` + `ingest_utterance`, inventory detected):
- `LJ (examples)`: examples/corpus/LJ, 24 LJSpeech utterances (the demo's copies: 16 kHz, byte-identical TextGrids);
- `LJ (shared)`: ../shared/data/ljspeech_mfa, the same 24 utterances as distributed (22.05 kHz), copied into a
  temporary corpus folder (the product reads `<speaker>/<name>.wav` + `.TextGrid`);
- `Mandarin`: ../shared/data/charsiu_mandarin, one AISHELL-3 utterance (pinyin; examples/corpus/SSB1624 is the
  same utterance, so it is not counted twice).
- for reference, `espeak validation`: the 120 validation utterances of bench/learning.py's espeak-ng corpus
  (synthetic voices: the espeak model's own domain; not real speech).

Rows (curves at 30 fps, frame k at k / 30 s, as many frames as `frame_count(duration, 30)`):
- `fbank-blstm (espeak)`: bench/learning.py's model (fbank-blstm, D = 512, `--espeak-epochs` epochs on the 1,080
  training utterances of the espeak-ng corpus, synthetic true curves); cached in bench/out/learning/models and
  shared with bench/learning.py and bench/robustness.py (trained here when missing);
- `mean-curve (espeak)`: that corpus's mean curve (the L1 floor of bench/learning.py);
- `fbank-blstm (LJ, k-fold)`: fbank-blstm with D = 128 (the demo's width) trained on real LJSpeech audio whose
  targets are the synthetic true curves of its alignment (`generate_ground_truth`: what the demo renders and then
  tracks; the demo store's tracked curves approximate them at L1 x 100 ~5.7, and building that store means
  rendering and tracking 25 videos, minutes this bench does not spend). `--folds` folds over the 24 LJ utterances:
  each utterance is predicted by the model that did not train on it (the demo's own model trains on 23 of them,
  so its numbers on these files would be in-sample). Mandarin: the fold-0 model (English only: out of language);
- `mean-curve (LJ folds)`: per fold, the frame-weighted mean of its training targets;
- `phones recognised by pocketsphinx (no training)`: `predict --model phones`, the procedural curves of the phones
  PocketSphinx's English model recognises in the audio (no alignment; none of these voices trained it);
- `procedural (alignment)`: the JALI-like curves from the alignment itself (needs the phones: not a model of the
  audio; MBP and FFF always reach full closure, so its closure recall is the ceiling of the definition);
- `synthetic truth (alignment)`: the LJ models' targets themselves (Cohen-Massaro dynamics): what perfect
  learning of those targets would score.

Columns: MBP closure and FFF closure (hits / phones: the phone's top predicted viseme, highest peak over its frames,
strictly, is MBP / FFF), their false closures (the share of all other non-silent phones whose top is MBP / FFF:
recall alone rewards a mouth kept shut), agreement (the phone's viseme among the top 2 at its middle frame, over
every non-silent phone; and for the b/p/m phones alone: the softer "MBP in the top 2 at the apex"), L1 x 100 against the synthetic truth (over every frame of the set), the mean per-viseme
Pearson r against it (per utterance, then averaged; constant columns, such as every column of a mean curve, have no
r: `-`), and the most frequent top visemes at b/p/m phones. Predictions are `predict_curves` (clipped to [0, 1]),
as `visemeflow predict` writes them.
"""

from __future__ import annotations

import argparse
import collections
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from learning_data import ensure_corpus, load_data, trained_model

from visemeflow.ingest import IngestConfig, discover_corpus, ingest_utterance
from visemeflow.ingest.audio import read_audio
from visemeflow.learning.features import resample_audio
from visemeflow.learning.realspeech import (
    CLOSURE_VISEMES,
    RealSpeechScores,
    compare_curves,
    phones_of,
    pool,
    score_phones,
    score_utterance,
)
from visemeflow.learning.train import Example, TrainConfig, predict_curves
from visemeflow.phonetics.types import VisemeSegment
from visemeflow.procedural import ProceduralConfig, generate_procedural_curves
from visemeflow.procedural.recognised import recognised_curves
from visemeflow.synth.dynamics import generate_ground_truth
from visemeflow.timebase import frame_count

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared" / "data"
FPS = 30.0
SAMPLE_RATE = 16000


@dataclass
class Utterance:
    uid: str
    speaker: str
    audio: np.ndarray          # 16 kHz mono float32
    phones: list               # realspeech.Phone
    truth: np.ndarray          # synthetic true curves of the alignment (n, 16)
    procedural: np.ndarray     # (n, 16)

    @property
    def n(self) -> int:
        return len(self.truth)


def read_corpus(root: Path, ids: set[str] | None = None,
                procedural: ProceduralConfig = ProceduralConfig()) -> list[Utterance]:
    """The aligned utterances of a corpus folder, with their synthetic truth and procedural curves (`procedural`:
    the rules' config, e.g. `closure_rule=False` for the curves before the lip rules)."""
    out = []
    for entry in discover_corpus(root).entries:
        if ids is not None and entry.utterance_id not in ids:
            continue
        result = ingest_utterance(entry, IngestConfig())
        rows = sorted(result.phones, key=lambda p: (p["start_s"], p["index"], p["part"]))
        segments = [VisemeSegment(p["viseme"], p["start_s"], p["end_s"], p["word_index"], p["phoneme"] or "")
                    for p in rows if p["viseme"] is not None]
        n = frame_count(result.utterance["duration_s"], FPS)
        samples, rate = read_audio(entry.audio_path)
        out.append(Utterance(entry.utterance_id, entry.speaker, resample_audio(samples, rate, SAMPLE_RATE),
                             phones_of(rows), generate_ground_truth(segments, n, FPS, entry.speaker, entry.utterance_id),
                             generate_procedural_curves(segments, n, FPS, procedural)))
    return out


def shared_corpus(tmp: Path) -> dict[str, Path]:
    """../shared/data's LJSpeech and Mandarin files in the corpus layout, copied under `tmp` (links to outside a
    corpus are refused by the product)."""
    out = {}
    lj = SHARED / "ljspeech_mfa"
    if (lj / "wav").is_dir():
        folder = tmp / "ljspeech_mfa" / "LJ"
        folder.mkdir(parents=True)
        for wav in sorted((lj / "wav").glob("*.wav")):
            grid = lj / "TextGrid" / f"{wav.stem}.TextGrid"
            if grid.exists():
                shutil.copyfile(wav, folder / wav.name)
                shutil.copyfile(grid, folder / grid.name)
        out["LJ (shared)"] = folder.parent
    zh = SHARED / "charsiu_mandarin"
    if (zh / "SSB16240001.TextGrid").exists():
        folder = tmp / "charsiu" / "SSB1624"
        folder.mkdir(parents=True)
        shutil.copyfile(zh / "SSB16240001_16k.wav", folder / "SSB16240001.wav")
        shutil.copyfile(zh / "SSB16240001.TextGrid", folder / "SSB16240001.TextGrid")
        out["Mandarin"] = folder.parent
    return out


def fraction(hits: int, total: int) -> str:
    return "-" if not total else f"{hits}/{total} ({100.0 * hits / total:.1f}%)"


def percent(hits: int, total: int) -> str:
    return "-" if not total else f"{100.0 * hits / total:.1f}%"


def row(name: str, utterances: list[Utterance], curves: dict[str, np.ndarray]) -> str:
    scores: list[RealSpeechScores] = []
    tops: collections.Counter = collections.Counter()
    for u in utterances:
        c = curves[u.uid]
        scores.append(score_utterance(c, FPS, u.phones))
        tops.update(s.top for s in score_phones(c, FPS, u.phones)[0] if s.viseme == "MBP")
    pooled = pool(scores)
    l1 = compare_curves(np.concatenate([curves[u.uid] for u in utterances]),
                        np.concatenate([u.truth for u in utterances]), FPS).l1_x100
    rs = [r for r in (compare_curves(curves[u.uid], u.truth, FPS).mean_pearson for u in utterances)
          if not np.isnan(r)]
    closure = " | ".join(f"{fraction(pooled.closure[v].hits, pooled.closure[v].total)} | "
                         f"{percent(pooled.false_closure[v].hits, pooled.false_closure[v].total)}"
                         for v in CLOSURE_VISEMES)
    agree = pooled.agreement.overall
    mbp = pooled.agreement.per_viseme.get("MBP")
    top = ", ".join(f"{v} {k}" for v, k in tops.most_common(3))
    r = f"{np.mean(rs):.2f}" if rs else "-"
    return (f"| {name} | {closure} | {fraction(agree.hits, agree.total)} | "
            f"{percent(mbp.hits, mbp.total) if mbp else '-'} | {l1:.2f} | {r} | {top} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--espeak-epochs", type=int, default=8, help="8: bench/learning.py's model (cache shared)")
    ap.add_argument("--lj-epochs", type=int, default=30, help="8 leaves the k-fold models underfit (r 0.09)")
    ap.add_argument("--lj-width", type=int, default=128)
    ap.add_argument("--folds", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t_start = time.perf_counter()

    with tempfile.TemporaryDirectory() as tmp:
        sets = {"LJ (examples)": [u for u in read_corpus(ROOT / "examples" / "corpus") if u.speaker == "LJ"]}
        for name, folder in shared_corpus(Path(tmp)).items():
            sets[name] = read_corpus(folder)
    # espeak-trained models (bench/learning.py's, cached)
    t0 = time.perf_counter()
    data = load_data(700, 500)
    sets["espeak validation"] = read_corpus(ensure_corpus(700, 500), {ex.utterance_id for ex in data.val})
    for name, utts in sets.items():
        phones = [p for u in utts for p in u.phones if p.viseme]
        counts = collections.Counter(p.viseme for p in phones)
        print(f"{name}: {len(utts)} utterances, {sum(u.n for u in utts) / FPS:.1f} s, {len(phones)} non-silent "
              f"phones ({counts['MBP']} b/p/m, {counts['FFF']} f/v)", flush=True)
    espeak = {
        "fbank-blstm (espeak)": trained_model("fbank-blstm", TrainConfig(preset="fbank-blstm", epochs=args.espeak_epochs),
                                              data.train, data.val)[0],
        "mean-curve (espeak)": trained_model("mean-curve", TrainConfig(preset="mean-curve", epochs=1),
                                             data.train, data.val)[0],
    }
    print(f"espeak models ready in {time.perf_counter() - t0:.0f} s", flush=True)

    # LJ k-fold models on real audio, synthetic truth of the alignment as targets
    t0 = time.perf_counter()
    lj = sorted(sets["LJ (examples)"], key=lambda u: u.uid)
    fold_of = {u.uid: i % args.folds for i, u in enumerate(lj)}
    fold_models, fold_means = {}, {}
    for k in range(args.folds):
        train = [Example(u.uid, u.audio, u.truth, FPS) for u in lj if fold_of[u.uid] != k]
        held = [Example(u.uid, u.audio, u.truth, FPS) for u in lj if fold_of[u.uid] == k]
        config = TrainConfig(preset="fbank-blstm", epochs=args.lj_epochs, d_model=args.lj_width)
        fold_models[k] = trained_model(f"lj-fold{k}of{args.folds}-fbank-blstm", config, train, held, verbose=False)[0]
        fold_means[k] = np.concatenate([ex.curves for ex in train]).mean(axis=0).astype(np.float32)
    print(f"LJ fold models ready in {time.perf_counter() - t0:.0f} s", flush=True)

    def predict(model, u: Utterance) -> np.ndarray:
        return predict_curves(model, u.audio, SAMPLE_RATE, FPS, n_frames=u.n)

    t0 = time.perf_counter()
    print()
    for name, utts in sets.items():
        curves: dict[str, dict[str, np.ndarray]] = {}
        for label, model in espeak.items():
            curves[label] = {u.uid: predict(model, u) for u in utts}
        fold = {u.uid: fold_of.get(u.uid, 0) for u in utts}    # same ids in both LJ sets; Mandarin: fold 0
        curves["fbank-blstm (LJ, k-fold)"] = {u.uid: predict(fold_models[fold[u.uid]], u) for u in utts}
        curves["mean-curve (LJ folds)"] = {u.uid: np.tile(fold_means[fold[u.uid]], (u.n, 1)) for u in utts}
        curves["phones recognised by pocketsphinx (no training)"] = {
            u.uid: recognised_curves(u.audio, SAMPLE_RATE, FPS, u.n) for u in utts}
        curves["procedural (alignment)"] = {u.uid: u.procedural for u in utts}
        curves["synthetic truth (alignment)"] = {u.uid: u.truth for u in utts}
        print(f"### {name}: {len(utts)} utterances")
        print()
        print("| curves | MBP closure | false MBP | FFF closure | false FFF | agreement (top-2 at apex) | "
              "b/p/m: MBP top-2 at apex | L1 x 100 vs synth. truth | mean r vs synth. truth | "
              "top viseme at b/p/m phones |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        for label, c in curves.items():
            print(row(label, utts, c))
        print()
    print(f"predictions and metrics in {time.perf_counter() - t0:.1f} s; total {time.perf_counter() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
