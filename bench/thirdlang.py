"""Audio-to-curves models on real speech in two languages none of them trained on: Dutch and Czech voice recordings
of the game Fish Fillets NG. Printed, never asserted.

Run: .venv/bin/python bench/thirdlang.py [--root /] [--models default[,default-fbank,PATH.pt]] [--utterances 10]
     [--tolerance 0.1]

Data: the Debian packages `fillets-ng-data-nl` and `fillets-ng-data-cs` (the voices, .ogg, 22.05 kHz) and
`fillets-ng-data` (the transcripts: `script/<level>/dialogs_<lang>.lua`), version 1.0.1-1.1, license GPL-2: this
repository holds neither audio nor transcript text, only the ids of the 20 utterances judged (`UTTERANCES`: 10 per
language, two speakers each -- the small and the big fish); both are read at run time from the installed packages
(`apt-get install fillets-ng-data fillets-ng-data-nl fillets-ng-data-cs`, files under /usr/share/games/fillets-ng)
or from `--root DIR`, a folder the three .debs were extracted into with `dpkg -x`. Without them the bench prints
the install command and exits.

Alignment (made here, each run, into a temporary corpus folder of `<lang>/<id>.wav` + `.TextGrid`, read by
bench/realspeech.py's `read_corpus`): no forced aligner knows these languages, so the words are placed by dynamic
time warping (librosa, cosine distance) of the recording's MFCCs (12 + deltas, 10-ms hop, each coefficient
standardised per utterance) against espeak-ng's synthesis of the transcript word by word (`espeak-ng -v nl|cs`, the
words concatenated, so their boundaries in the synthesis are known exactly); a word's span is the median recording
time warped onto its first and last synthetic sample. Its phones are espeak-ng's IPA for the word (`--ipa`, stress
marks dropped; symbols the product's IPA table lacks mapped to the nearest it has: `NORMALISE`), spread evenly over
the word. Rough, and checked against no human alignment: MFCC DTW of a synthetic voice against a human one puts
word boundaries within ~50-150 ms on clean read speech, and these are expressive, cartoon-voiced recordings (expect
worse, and the odd word stretched into a reverberant tail); phones inside a word are a uniform split, off by the
order of a phone (50-100 ms). The b/p/m phones are in the right word and order, not at the right millisecond, so
the strict per-phone closure figures understate a model: `MBP within +-T s` is the tolerant reading.

Rows: per language, each model of `--models` (`default`, `default-fbank`: the shipped models; or a .pt file written
by `save_model`), its curves as `predict_curves` gives them at 30 fps (the Whisper encoder's outputs cached in
bench/out/thirdlang/cache), and `procedural (alignment)`: the alignment's own procedural curves, the ceiling of the
definitions. Columns (`visemeflow.learning.realspeech`): b/p/m phones whose top viseme (the highest peak over the
phone's frames, strictly) is MBP; false MBP closures (other non-silent phones whose top is MBP); other phones with
MBP the top viseme at their middle frame (mid-phone: what a viewer sees there); the false closures next to a b/p/m
phone (a closure's ramp into its neighbour, or an alignment boundary a frame or two off); f/v phones whose
top is FFF; top-2 agreement (the phone's viseme among the top 2 at its middle frame, every non-silent phone); and
b/p/m phones with MBP the top viseme of some frame within `--tolerance` s of the phone.
"""

from __future__ import annotations

import argparse
import io
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import soundfile as sf
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from encoders import CachedPredictor  # noqa: E402
from realspeech import FPS, SAMPLE_RATE, fraction, read_corpus  # noqa: E402
from report import print_grid  # noqa: E402

from visemeflow.ingest.audio import read_audio  # noqa: E402
from visemeflow.learning.default_model import SHIPPED_MODELS, shipped_model_path  # noqa: E402
from visemeflow.learning.features import resample_audio  # noqa: E402
from visemeflow.learning.realspeech import pool, score_phones, score_utterance  # noqa: E402
from visemeflow.learning.train import load_model  # noqa: E402
from visemeflow.phonetics.textgrid import Tier, format_textgrid  # noqa: E402
from visemeflow.visemes import VISEME_INDEX  # noqa: E402

GAME = Path("usr/share/games/fillets-ng")
PACKAGES = ("fillets-ng-data", "fillets-ng-data-nl", "fillets-ng-data-cs")
CACHE = Path(__file__).resolve().parent / "out" / "thirdlang" / "cache"
LANGUAGES = ("nl", "cs")
NAMES = {"nl": "Dutch (nl)", "cs": "Czech (cs)"}

UTTERANCES = (
    ("nl", "cellar", "pra-m-reseni"),
    ("nl", "party2", "pt2-m-piknik3"),
    ("nl", "windoze", "win-m-ven"),
    ("nl", "computer", "poc-m-zezadu"),
    ("nl", "columns", "sl-m-trvat"),
    ("nl", "propulsion", "poh-v-setkani"),
    ("nl", "map", "map-v-ukol"),
    ("nl", "linux", "v-prepinani"),
    ("nl", "viking2", "dr-v-nato"),
    ("nl", "cellar", "pra-v-nahore"),
    ("cs", "broom", "kos-m-uklid2"),
    ("cs", "creatures", "kor-m-bizarni"),
    ("cs", "puzzle", "puc-m-pld1"),
    ("cs", "airplane", "let-m-oko"),
    ("cs", "ending", "z-m-dlouho"),
    ("cs", "hardware", "pz-v-dat"),
    ("cs", "viking2", "dr1-v-leif"),
    ("cs", "cannons", "del-v-mec"),
    ("cs", "computer", "poc-v-nenajde"),
    ("cs", "bathroom", "br-v-lazen"),
)
"""(language, level, dialog id) of the utterances judged: `sound/<level>/<lang>/<id>.ogg` and the dialogStr after
`dialogId("<id>", ...)` in `script/<level>/dialogs_<lang>.lua`. A seeded random pick among the lines of 2.5-6 s with
at least 4 words, a b/p/m letter, no digits, acronyms or ellipsis, and a length 0.8-1.5x espeak-ng's reading."""

NORMALISE = {"eː": "e", "aː": "a", "ɛɪ": "ɛ", "œy": "œ", "r̝̊": "r", "r̝": "r", "ɔː": "ɔ", "oː": "o", "l̩": "l",
             "eʊ": "e", "ɡ": "g"}
"""espeak-ng's IPA for nl / cs -> the nearest symbol of the product's IPA table (long vowels and diphthongs to their
first vowel, the Czech fricative trill to r, syllabic l to l, the IPA script g to the ASCII g)."""

HOP = 160           # 10 ms at 16 kHz
MIN_WORD_S = 0.03


def missing(game: Path) -> list[Path]:
    """The files of UTTERANCES not under `game`."""
    out = []
    for lang, level, uid in UTTERANCES:
        for path in (game / "sound" / level / lang / f"{uid}.ogg", game / "script" / level / f"dialogs_{lang}.lua"):
            if not path.exists():
                out.append(path)
    return out


def transcript(game: Path, lang: str, level: str, uid: str) -> str:
    """The translated line of dialog `uid` (the dialogStr following its dialogId)."""
    text = (game / "script" / level / f"dialogs_{lang}.lua").read_text(encoding="utf-8")
    string = r'"((?:[^"\\]|\\.)*)"'
    found = re.search(rf'dialogId\("{re.escape(uid)}",\s*{string},\s*{string}\)\s*dialogStr\({string}\)', text)
    if found is None:
        raise SystemExit(f"no dialogStr for {uid!r} in {level}/dialogs_{lang}.lua")
    return re.sub(r"\\(.)", r"\1", found.group(3))


def words_of(text: str) -> list[str]:
    return [w for w in (re.sub(r"^[^\w']+|[^\w']+$", "", t) for t in text.split()) if w]


def espeak(args: list[str]) -> bytes:
    return subprocess.run(["espeak-ng", *args], capture_output=True, check=True).stdout


def word_phones(word: str, lang: str) -> list[str]:
    """espeak-ng's IPA phones of one word, without stress marks or language-switch marks, normalised."""
    ipa = espeak(["-q", "--ipa", "--sep=_", "-v", lang, word]).decode("utf-8")
    ipa = re.sub(r"\([a-z-]+\)", "", ipa).replace("ˈ", "").replace("ˌ", "")
    return [NORMALISE.get(p, p) for p in re.split(r"[_\s]+", ipa) if p]


def word_audio(word: str, lang: str) -> np.ndarray:
    """espeak-ng's synthesis of one word at 16 kHz, silence trimmed."""
    import librosa

    samples, rate = sf.read(io.BytesIO(espeak(["-v", lang, "--stdout", word])), dtype="float32")
    samples = librosa.resample(samples, orig_sr=rate, target_sr=SAMPLE_RATE)
    return librosa.effects.trim(samples, top_db=40)[0]


def mfcc(samples: np.ndarray) -> np.ndarray:
    import librosa

    m = librosa.feature.mfcc(y=samples, sr=SAMPLE_RATE, n_mfcc=13, n_fft=400, hop_length=HOP, n_mels=40)[1:]
    m = (m - m.mean(axis=1, keepdims=True)) / (m.std(axis=1, keepdims=True) + 1e-8)
    return np.vstack([m, librosa.feature.delta(m)])


def align_words(audio: np.ndarray, words: list[str], lang: str) -> list[tuple[float, float, str]]:
    """(start, end, word) in the recording: DTW of its MFCCs against the word-by-word synthesis."""
    import librosa

    pad = np.zeros(int(0.2 * SAMPLE_RATE), np.float32)
    parts, bounds, n = [pad], [], len(pad)
    for w in words:
        s = word_audio(w, lang)
        bounds.append((n, n + len(s)))
        parts.append(s)
        n += len(s)
    parts.append(pad)
    # a whisper of fixed noise, so that silent frames have finite, comparable MFCCs
    ref = np.concatenate(parts) + 1e-4 * np.random.RandomState(0).randn(n + len(pad))
    rec = audio + 1e-4 * np.random.RandomState(1).randn(len(audio))
    a = mfcc(ref.astype(np.float32))
    _, path = librosa.sequence.dtw(X=a, Y=mfcc(rec.astype(np.float32)), metric="cosine")
    path = path[::-1]
    duration = len(audio) / SAMPLE_RATE

    def warp(sample: int) -> float:
        frame = min(int(round(sample / HOP)), a.shape[1] - 1)
        return float(np.median(path[path[:, 0] == frame, 1])) * HOP / SAMPLE_RATE

    out: list[tuple[float, float, str]] = []
    for (s0, s1), w in zip(bounds, words, strict=True):
        t0, t1 = warp(s0), min(warp(s1), duration)
        t1 = max(t1, t0 + MIN_WORD_S)
        if out and t0 < out[-1][1]:      # no overlap with the word before
            t0, t1 = out[-1][1], max(t1, out[-1][1] + MIN_WORD_S)
        out.append((t0, t1, w))
    return out


def spread_phones(words: list[tuple[float, float, str]], lang: str) -> list[tuple[float, float, str]]:
    out = []
    for t0, t1, w in words:
        ps = word_phones(w, lang)
        step = (t1 - t0) / max(len(ps), 1)
        out += [(t0 + k * step, t1 if k == len(ps) - 1 else t0 + (k + 1) * step, p) for k, p in enumerate(ps)]
    return out


def with_gaps(items: list[tuple[float, float, str]], end: float) -> tuple[tuple[float, float, str], ...]:
    """Intervals covering [0, end]: empty ones in the gaps."""
    out, t = [], 0.0
    for a, b, label in items:
        if a > t + 1e-6:
            out.append((t, a, ""))
        out.append((a, b, label))
        t = b
    if end > t + 1e-6:
        out.append((t, end, ""))
    return tuple(out)


def build_corpus(game: Path, tmp: Path, per_language: int) -> dict[str, Path]:
    """`<tmp>/<lang>/<lang>/<id>.wav` + `.TextGrid` for the first `per_language` utterances of each language."""
    roots = {}
    for lang in LANGUAGES:
        folder = tmp / lang / lang
        folder.mkdir(parents=True)
        roots[lang] = folder.parent
        for _, level, uid in [u for u in UTTERANCES if u[0] == lang][:per_language]:
            samples, rate = read_audio(game / "sound" / level / lang / f"{uid}.ogg")
            audio = resample_audio(samples, rate, SAMPLE_RATE)
            end = len(audio) / SAMPLE_RATE
            words = align_words(audio, words_of(transcript(game, lang, level, uid)), lang)
            phones = spread_phones(words, lang)
            sf.write(folder / f"{uid}.wav", audio, SAMPLE_RATE, subtype="PCM_16")
            tiers = [Tier(name, "IntervalTier", 0.0, end, with_gaps(items, end))
                     for name, items in (("words", words), ("phones", phones))]
            (folder / f"{uid}.TextGrid").write_text(format_textgrid(tiers, 0.0, end), encoding="utf-8")
    return roots


def mbp_within(curves: list[np.ndarray], utterances, tolerance: float) -> tuple[int, int]:
    """b/p/m phones with MBP the top viseme of a frame within `tolerance` s of the phone."""
    hits = total = 0
    for c, u in zip(curves, utterances, strict=True):
        top = c.argmax(axis=1) == VISEME_INDEX["MBP"]
        for p in u.phones:
            if p.viseme != "MBP":
                continue
            a = max(0, int((p.start_s - tolerance) * FPS))
            b = min(len(top), int(np.ceil((p.end_s + tolerance) * FPS)) + 1)
            total += 1
            hits += bool(top[a:b].any())
    return hits, total


def false_mbp_where(curves: list[np.ndarray], utterances) -> tuple[int, int, int, int]:
    """Where false MBP closures fall: (other phones with MBP the top viseme at their middle frame, which is what
    a viewer sees mid-phone; other phones; false closures by the per-phone maximum, the `false MBP` column; of
    those, the ones next to a b/p/m phone, where a closure's ramp reaches into the neighbour or the alignment's
    boundary is off by a frame or two)."""
    mid = others = false = beside = 0
    mbp = VISEME_INDEX["MBP"]
    for c, u in zip(curves, utterances, strict=True):
        scores, _ = score_phones(c, FPS, u.phones)
        for i, s in enumerate(scores):
            if s.viseme == "MBP":
                continue
            others += 1
            mid += int(np.argmax(c[s.apex_frame])) == mbp
            if s.top == "MBP" and s.top_unique:
                false += 1
                beside += any(scores[j].viseme == "MBP" for j in (i - 1, i + 1) if 0 <= j < len(scores))
    return mid, others, false, beside


def header(tolerance: float) -> list[str]:
    """The columns of `row`."""
    return ["model", "b/p/m: MBP top", "false MBP", "false MBP at mid-phone", "false MBP next to b/p/m",
            "f/v: FFF top", "top-2 agreement", f"MBP within +-{tolerance:g} s"]


def row(name: str, curves: list[np.ndarray], utterances, tolerance: float) -> list[str]:
    s = pool(score_utterance(c, FPS, u.phones) for c, u in zip(curves, utterances, strict=True))
    mid, others, false, beside = false_mbp_where(curves, utterances)

    def cell(r) -> str:
        return fraction(r.hits, r.total) if r is not None else "-"

    return [name, cell(s.closure.get("MBP")), cell(s.false_closure.get("MBP")), fraction(mid, others),
            fraction(beside, false), cell(s.closure.get("FFF")), cell(s.agreement.overall),
            fraction(*mbp_within(curves, utterances, tolerance))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, default=Path("/"),
                    help="where the packages are installed or extracted (dpkg -x): DIR/usr/share/games/fillets-ng")
    ap.add_argument("--models", default="default", help="comma-separated: shipped model names or .pt files")
    ap.add_argument("--utterances", type=int, default=10, help="the first N of each language (at most 10)")
    ap.add_argument("--tolerance", type=float, default=0.1, help="seconds either side of a b/p/m phone")
    args = ap.parse_args()
    torch.set_num_threads(1)

    game = args.root / GAME
    lacking = missing(game)
    if lacking:
        print(f"the Fish Fillets NG voice data are not under {game} ({lacking[0]} and {len(lacking) - 1} more "
              f"missing); install them with\n    sudo apt-get install {' '.join(PACKAGES)}\nor extract the three "
              f".debs with `dpkg -x PKG.deb DIR` and pass --root DIR. Nothing measured.")
        return
    if shutil.which("espeak-ng") is None:
        print("espeak-ng is needed for the alignment: sudo apt-get install espeak-ng. Nothing measured.")
        return

    models = {}
    for name in [m.strip() for m in args.models.split(",") if m.strip()]:
        path = shipped_model_path(name) if name in SHIPPED_MODELS else Path(name)
        models[name] = load_model(path)[0]

    started = time.perf_counter()
    tmp = Path(tempfile.mkdtemp(prefix="thirdlang-"))
    try:
        roots = build_corpus(game, tmp, args.utterances)
        corpora = {lang: read_corpus(root) for lang, root in roots.items()}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    aligned = time.perf_counter() - started

    predict = CachedPredictor(CACHE)
    columns = header(args.tolerance)
    rows = []
    for lang, utts in corpora.items():
        seconds = sum(len(u.audio) for u in utts) / SAMPLE_RATE
        rows.append(f"{NAMES[lang]}: {len(utts)} utterance{'s' * (len(utts) != 1)}, {seconds:.1f} s of speech")
        for name, model in models.items():
            rows.append(row(name, [predict(model, u.audio, u.n) for u in utts], utts, args.tolerance))
        rows.append(row("procedural (alignment)", [u.procedural for u in utts], utts, args.tolerance))

    print_grid(columns, rows)
    print(f"alignment (espeak-ng + DTW) and ingestion {aligned:.1f} s; all {time.perf_counter() - started:.1f} s. "
          f"Data: Debian fillets-ng-data{{,-nl,-cs}} 1.0.1 (GPL-2), read from {game}.")


if __name__ == "__main__":
    main()
