"""Audio-to-curves models on real voices in 16 languages, none of them heard in training: the syllables that KDE's
alphabet tutor KLettres ships, each recorded by a native speaker ("BA", "MA", "DO", "ЛЮ", "AAP", ...). Printed,
never asserted.

Run: .venv/bin/python bench/syllables.py [--root /] [--models default,default-fbank[,PATH.pt]]
     [--languages cs,de,...] [--min-weight 0.2]

Data: the Debian package `klettres-data` (4:22.12, GPL-2+; `apt-get install klettres-data`, files under
/usr/share/klettres, or `--root DIR` where the .deb was extracted with `dpkg -x`). This repository holds none of it;
it is read at run time. Each language's `sounds.xml` names every syllable's recording (.ogg): the name is the text,
so what the lips must do is known without an alignment. The languages whose syllables are written in Latin or
Cyrillic letters are judged (16 sets: cs da de en en_GB es fr hu it lt nds nl pt_BR ru tn uk; Indonesian's
recordings are not in the package); Arabic, Hebrew and Malayalam are left out (their letters' lip shapes need a
pronunciation this bench does not have). The package does not say how many speakers recorded each set.

What is judged, per recording (`visemeflow.learning.syllables`, whose docstring gives the rules): on labial
syllables (B, P, M; Б, П, М), an MBP closure where that letter is spoken; on the others (no labial, no F, V, W,
Ф, В), a false MBP closure in the vowel's nucleus, the rendered lips closed there (below 1.5 mm), and the median
rendered gap there; and the chance column: the other syllables with a closure in the onset window that a labial's
closure is looked for in. Curves at 30 fps as `predict_curves` gives them (the Whisper encoder's outputs cached in
bench/out/syllables/cache); the closure rule and the demo character's mesh as the animation stage applies them
(bench/judging.py's probe).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import soundfile as sf
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from encoders import CachedPredictor  # noqa: E402
from judging import FPS, probe  # noqa: E402
from realspeech import SAMPLE_RATE, fraction  # noqa: E402
from report import print_grid  # noqa: E402

from visemeflow.articulation import close_lips  # noqa: E402
from visemeflow.learning.default_model import SHIPPED_MODELS, shipped_model_path  # noqa: E402
from visemeflow.learning.features import resample_audio  # noqa: E402
from visemeflow.learning.syllables import klettres_syllables, kind_of, score_syllable, speech_span, summarise  # noqa: E402
from visemeflow.learning.train import load_model  # noqa: E402

DATA = Path("usr/share/klettres")
CACHE = Path(__file__).resolve().parent / "out" / "syllables" / "cache"
LANGUAGES = ("cs", "da", "de", "en", "en_GB", "es", "fr", "hu", "it", "lt", "nds", "nl", "pt_BR", "ru", "tn", "uk")


def load(path: Path) -> np.ndarray:
    audio, rate = sf.read(path, dtype="float32", always_2d=True)
    return resample_audio(audio.mean(axis=1), rate, SAMPLE_RATE)


def cells(scores) -> list[str]:
    s = summarise(scores)
    return [fraction(r.hits, r.total) for r in (s.labial_closed, s.other_onset, s.other_false, s.other_mesh_closed)] \
        + [f"{s.median_open_mm:.1f}" if s.median_open_mm is not None else "-"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, default=Path("/"),
                    help="where klettres-data is installed or extracted (dpkg -x): DIR/usr/share/klettres")
    ap.add_argument("--models", default="default,default-fbank",
                    help="comma-separated: shipped model names or .pt files")
    ap.add_argument("--languages", default=",".join(LANGUAGES))
    ap.add_argument("--min-weight", type=float, default=0.2, help="MBP weight a closure frame needs")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    data = args.root / DATA
    if not (data / "fr" / "sounds.xml").is_file():
        print(f"the KLettres recordings are not under {data}; install them with\n    sudo apt-get install "
              f"klettres-data\nor extract the .deb with `dpkg -x klettres-data_*.deb DIR` and pass --root DIR. "
              f"Nothing measured.")
        return
    models = {}
    for name in [m.strip() for m in args.models.split(",") if m.strip()]:
        path = shipped_model_path(name) if name in SHIPPED_MODELS else Path(name)
        models[name] = load_model(path)[0]

    started = time.perf_counter()
    predict = CachedPredictor(CACHE)
    lips = probe()
    languages = [lang.strip() for lang in args.languages.split(",") if lang.strip()]
    results: dict[str, dict[str, list]] = {name: {} for name in models}
    counts = {}
    for lang in languages:
        items = klettres_syllables(data, lang)
        kinds = [kind_of(text) for text, _ in items]
        counts[lang] = (len(items), kinds.count("labial"), kinds.count("other"))
        for text, path in items:
            audio = load(path)
            n = int(len(audio) / SAMPLE_RATE * FPS)
            span = speech_span(audio, SAMPLE_RATE)
            for name, model in models.items():
                curves = predict(model, audio, n)
                gap = lips.measure(close_lips(curves)).gap_mm
                results[name].setdefault(lang, []).append(
                    score_syllable(text, curves, FPS, span, gap, args.min_weight))
        print(f"  [{time.perf_counter() - started:5.0f} s] {lang}: {counts[lang][0]} syllables", flush=True)

    header = ["language", "syllables (labial / other)", "model", "labial: MBP closure", "other: MBP at onset",
              "other: false MBP",
              "other: mesh closed", "other: median gap mm"]
    rows = []
    for lang in [*languages, "all"]:
        for name in models:
            judged = (results[name][lang] if lang != "all"
                      else [j for per in results[name].values() for j in per])
            n_all = counts[lang] if lang != "all" else tuple(sum(c[i] for c in counts.values()) for i in range(3))
            rows.append([lang, f"{n_all[0]} ({n_all[1]} / {n_all[2]})", name, *cells(judged)])
    print_grid(header, rows)
    print(f"{time.perf_counter() - started:.0f} s. Data: Debian klettres-data (GPL-2+), read from {data}; closure "
          f"frame: MBP top and >= {args.min_weight:g}.")


if __name__ == "__main__":
    main()
