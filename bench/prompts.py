"""Audio-to-curves models on real read speech in five languages none of them trained on: the Asterisk telephone
prompts (English, Spanish, French, Italian, Russian; four professional voices). Printed, never asserted.

Run: .venv/bin/python bench/prompts.py [--root /] [--models default[,default-fbank,PATH.pt]] [--utterances 20]
     [--languages en,es,fr,it,ru] [--seed 0] [--tolerance 0.1] [--hear wide] [--retime 24,25]

Data: the Debian packages `asterisk-core-sounds-<lang>-wav` (the prompts, 8 kHz 16-bit WAV, about 25 min per
language) and `asterisk-core-sounds-<lang>` (their transcripts, `/usr/share/doc/asterisk-core-sounds-<lang>/
core-sounds-<lang>.txt.gz`, one `name: text` line per prompt), version 1.6.1-1; licence CC-BY-SA-3.0 (en, es, fr)
and CC-BY-3.0 (it, ru), per each package's copyright file. Voices: Allison Smith (en_US and es_MX), June Wallack
(fr_CA), Carlo (it_IT, male), IvrvoiceRU (ru_RU). This repository holds neither audio nor text: both are read at run
time from the installed packages (`apt-get install asterisk-core-sounds-en asterisk-core-sounds-en-wav ...`) or from
`--root DIR`, a folder the .debs were extracted into with `dpkg -x`. Without them the bench prints the install
command and exits.

Which prompts: per language, a seeded random pick (`--seed`) of `--utterances` among the prompts of 1.5-8 s whose
text has at least 4 words and a b/p/m letter (Cyrillic б/п/м), and no digit, bracket or slash (a `[tone]` is no
speech; a number is read in words the text does not give).

Alignment (made here, each run, into a temporary corpus folder read by bench/realspeech.py's `read_corpus`):
- English: pocketsphinx forced alignment of the transcript (`visemeflow.phonetics.forcealign.align_transcript`, the
  product's own aligner): every phone placed in the audio.
- Spanish, French, Italian, Russian: no forced aligner here knows them, so bench/thirdlang.py's method: the words by
  dynamic time warping of the recording's MFCCs against espeak-ng's word-by-word synthesis, each word's espeak-ng
  phones spread evenly over it (`NORMALISE` maps espeak's IPA to the product's table). Rough: word boundaries within
  ~50-150 ms, phones inside a word off by the order of a phone, so the strict per-phone closure figures understate a
  model there; `MBP within +-T s` is the tolerant reading.
The audio is 8 kHz telephone speech (nothing above 4 kHz), resampled to 16 kHz: a channel none of the models
trained on, on top of the voices and languages. `--hear wide` gives the models the same prompts in wide band instead
(`asterisk-core-sounds-<lang>-g722`: G.722 at 16 kHz, 50-7000 Hz, decoded by PyAV; the same recordings, 2 ms apart),
and `--align wide` gives them to the aligner (default: what the models hear), so the 8-kHz channel's share of a
figure can be told from the voice's and the aligner's.

Rows and columns as bench/thirdlang.py's: per language, each model of `--models` (its curves at 30 fps,
`predict_curves`, the Whisper encoder's outputs cached in bench/out/prompts/cache), and `procedural (alignment)`, the
alignment's own procedural curves (the ceiling of the definitions); b/p/m phones whose top viseme is MBP, false MBP
closures (other phones whose top is MBP), other phones with MBP the top viseme at their middle frame (what a viewer
sees mid-phone), the false closures next to a b/p/m phone, f/v phones whose top is FFF, top-2 agreement, and b/p/m
phones with MBP the top viseme of a frame within `--tolerance` s. Then all languages pooled. `--retime 24,25`: the
mesh columns of each model's pooled curves retimed from 30 fps to those rates, by linear interpolation and by
`animation.apply.resample_visemes` (the exports' retiming: each closure's key pose kept whole), side by side.
"""

from __future__ import annotations

import argparse
import gzip
import random
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import soundfile as sf
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from encoders import CachedPredictor  # noqa: E402
from judging import probe  # noqa: E402
from realspeech import FPS, SAMPLE_RATE, fraction, read_corpus  # noqa: E402
from report import print_grid  # noqa: E402
from thirdlang import align_words, header, row, with_gaps, word_phones, words_of  # noqa: E402

from visemeflow.animation.apply import resample, resample_visemes  # noqa: E402
from visemeflow.articulation import CLOSED_MM, close_lips  # noqa: E402
from visemeflow.ingest.audio import read_audio  # noqa: E402
from visemeflow.learning.default_model import SHIPPED_MODELS, shipped_model_path  # noqa: E402
from visemeflow.learning.features import resample_audio  # noqa: E402
from visemeflow.learning.lipscore import pool_lips, score_lips  # noqa: E402
from visemeflow.learning.realspeech import phone_frames  # noqa: E402
from visemeflow.learning.train import load_model  # noqa: E402
from visemeflow.phonetics.inventory import UnknownPhonemeError, map_phone  # noqa: E402
from visemeflow.phonetics.textgrid import Tier, format_textgrid  # noqa: E402

SOUNDS = Path("usr/share/asterisk/sounds")
DOCS = Path("usr/share/doc")
CACHE = Path(__file__).resolve().parent / "out" / "prompts" / "cache"
VOICES = {"en": "en_US_f_Allison", "es": "es_MX_f_Allison", "fr": "fr_CA_f_June", "it": "it_IT_m_Carlo",
          "ru": "ru_RU_f_IvrvoiceRU"}
ESPEAK = {"es": "es", "fr": "fr", "it": "it", "ru": "ru"}
NAMES = {"en": "English (en_US, Allison)", "es": "Spanish (es_MX, Allison)", "fr": "French (fr_CA, June)",
         "it": "Italian (it_IT, Carlo)", "ru": "Russian (ru_RU)"}
LABIAL = re.compile(r"[bpmбпм]", re.IGNORECASE)
NORMALISE = {"ɡ": "g", "ː": "", "ɾ": "r", "ʲ": ""}
"""espeak-ng IPA -> the product's table: the script g to ASCII g; length marks and palatalisation dropped (a
palatalised Russian consonant looks like its plain one); the tap as r."""


def packages(lang: str, bands: set[str] = frozenset({"narrow"})) -> str:
    return " ".join([f"asterisk-core-sounds-{lang}"] +
                    [f"asterisk-core-sounds-{lang}-{BANDS[b]}" for b in sorted(bands)])


BANDS = {"narrow": "wav", "wide": "g722"}
"""The package suffix, and the file suffix, of each band: 8-kHz WAV and wide-band G.722."""


def read_band(wav: Path, band: str) -> np.ndarray:
    """A prompt at 16 kHz, from its 8-kHz WAV or the G.722 file beside it (same name)."""
    if band == "narrow":
        samples, rate = read_audio(wav)
        return resample_audio(samples, rate, SAMPLE_RATE)
    import av

    with av.open(str(wav.with_suffix(".g722")), format="g722") as container:
        frames = [f.to_ndarray() for f in container.decode(audio=0)]
        rate = container.streams.audio[0].rate
    samples = np.concatenate(frames, axis=1)[0].astype(np.float32) / 32768.0
    return resample_audio(samples, rate, SAMPLE_RATE)


def prompts(root: Path, lang: str) -> dict[str, str]:
    """name -> text of a language's transcript file (the first line of a name wins)."""
    path = root / DOCS / f"asterisk-core-sounds-{lang}" / f"core-sounds-{lang}.txt.gz"
    out: dict[str, str] = {}
    with gzip.open(path, "rt", encoding="utf-8", errors="replace") as f:
        for line in f:
            if line.startswith(";") or ":" not in line:
                continue
            name, text = line.split(":", 1)
            out.setdefault(name.strip(), text.strip())
    return out


def pick(root: Path, lang: str, count: int, seed: int) -> list[tuple[str, Path, str]]:
    """(name, wav path, text) of the prompts judged (module docstring)."""
    folder = root / SOUNDS / VOICES[lang]
    usable = []
    for name, text in sorted(prompts(root, lang).items()):
        wav = folder / f"{name}.wav"
        if ("/" in name or not wav.is_file() or re.search(r"[\d\[\]/()]", text) or len(words_of(text)) < 4
                or not LABIAL.search(text)):
            continue
        if 1.5 <= sf.info(wav).duration <= 8.0:
            usable.append((name, wav, text))
    random.Random(seed).shuffle(usable)
    return usable[:count]


def ipa_phones(phone: str) -> list[str]:
    """One espeak-ng phone as phones of the product's IPA table: `NORMALISE` applied and espeak's own marks dropped
    (`-` of French liaison, `"` and `^`); a cluster the table lacks as one symbol (Russian `ja`, Italian `ss`) split
    into its symbols."""
    clean = "".join(NORMALISE.get(c, c) for c in re.sub(r'[-"^]', "", phone))
    if not clean:
        return []
    try:
        map_phone(clean, "ipa")
        return [clean]
    except UnknownPhonemeError:
        return list(clean)


LABIODENTAL = {"f", "v"}


def labiodental_nasals(phones: list[str]) -> list[str]:
    """`m` before f or v as `ɱ`, the labiodental nasal: espeak-ng writes a nasal assimilated to a following f as m
    (Spanish "conferencia" `komfeɾenθja`, "enfermo" `emfeɾmo`, Italian "informazioni"), but the lips do not close
    there: the lower lip meets the upper teeth for the f, and the nasal is made in the same place ([ɱ], FFF in the
    product's IPA table). Judged as m, the model's FFF at such a phone counted as a b/p/m phone left open."""
    return ["ɱ" if p == "m" and k + 1 < len(phones) and phones[k + 1] in LABIODENTAL else p
            for k, p in enumerate(phones)]


def espeak_phones(words: list[tuple[float, float, str]], lang: str) -> list[tuple[float, float, str]]:
    out = []
    for t0, t1, w in words:
        ps = labiodental_nasals([q for p in word_phones(w.lower(), ESPEAK[lang]) for q in ipa_phones(p)])
        step = (t1 - t0) / max(len(ps), 1)
        out += [(t0 + k * step, t1 if k == len(ps) - 1 else t0 + (k + 1) * step, p) for k, p in enumerate(ps)]
    return out


def align(audio: np.ndarray, text: str, lang: str, source: str):
    """(words, phones) as (start, end, label) lists."""
    if lang == "en":
        from visemeflow.phonetics.forcealign import align_transcript

        done = align_transcript(audio, SAMPLE_RATE, text, source=source)
        return ([(w.start_s, w.end_s, w.label) for w in done.words],
                [(p.start_s, p.end_s, p.label) for p in done.phones])
    words = align_words(audio, words_of(text), ESPEAK[lang])
    return words, espeak_phones(words, lang)


def build_corpus(root: Path, tmp: Path, languages: list[str], count: int, seed: int, hear: str = "narrow",
                 align_band: str = "narrow") -> dict[str, Path]:
    """`<tmp>/<lang>/<lang>/<name>.wav` (the band heard) + `.TextGrid` (aligned on `align_band`) for the prompts of
    each language."""
    roots = {}
    for lang in languages:
        folder = tmp / lang / lang
        folder.mkdir(parents=True)
        roots[lang] = folder.parent
        for name, wav, text in pick(root, lang, count, seed):
            audio = read_band(wav, hear)
            end = len(audio) / SAMPLE_RATE
            try:
                words, phones = align(audio if align_band == hear else read_band(wav, align_band), text, lang,
                                      f"{VOICES[lang]}/{name}.{BANDS[align_band]}")
            except ValueError as exc:     # a word neither dictionary nor espeak-ng can spell: that prompt is left out
                print(f"  {lang} {name}: not aligned ({exc}); left out")
                continue
            sf.write(folder / f"{name}.wav", audio, SAMPLE_RATE, subtype="PCM_16")
            tiers = [Tier(tier, "IntervalTier", 0.0, end, with_gaps(items, end))
                     for tier, items in (("words", words), ("phones", phones))]
            (folder / f"{name}.TextGrid").write_text(format_textgrid(tiers, 0.0, end), encoding="utf-8")
    return roots


MESH_COLUMNS = ["mesh: b/p/m closed (< 1.5 mm)", "mesh: other phones closed mid-phone"]


def mesh_cells(curves: list[np.ndarray], utterances, fps: float = FPS) -> list[str]:
    """The lips on the demo character after the closure rule (`articulation.close_lips`, as the animation stage
    applies it; `animation.lips.LipProbe`): b/p/m phones whose smallest lip gap is below 1.5 mm, and other phones
    whose lips are closed at their middle frame (what a viewer sees mid-phone); `curves` at `fps`."""
    p = probe()
    widest = p.single_shape_gap("AHH")
    lips, closed, others = [], 0, 0
    for c, u in zip(curves, utterances, strict=True):
        gap = p.measure(close_lips(c)).gap_mm
        lips.append(score_lips(gap, None, fps, u.phones, widest))
        for ph in u.phones:
            frames = None if ph.viseme in (None, "MBP") else phone_frames(ph.start_s, ph.end_s, fps, len(gap))
            if frames is not None:
                others += 1
                closed += bool(gap[frames[len(frames) // 2]] < CLOSED_MM)
    bilabial = pool_lips(lips).closed
    return [fraction(bilabial.hits, bilabial.total), fraction(closed, others)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, default=Path("/"),
                    help="where the packages are installed or extracted (dpkg -x): DIR/usr/share/asterisk/sounds")
    ap.add_argument("--models", default="default", help="comma-separated: shipped model names or .pt files")
    ap.add_argument("--languages", default=",".join(VOICES), help="comma-separated, of " + ",".join(VOICES))
    ap.add_argument("--utterances", type=int, default=20, help="prompts per language")
    ap.add_argument("--seed", type=int, default=0, help="which prompts (a seeded random pick)")
    ap.add_argument("--tolerance", type=float, default=0.1, help="seconds either side of a b/p/m phone")
    ap.add_argument("--hear", choices=sorted(BANDS), default="narrow",
                    help="what the models hear: the 8-kHz WAV (narrow) or the G.722 wide band (wide)")
    ap.add_argument("--align", choices=sorted(BANDS), default=None,
                    help="what the aligner hears (default: what the models hear)")
    ap.add_argument("--retime", default="", help="comma-separated frame rates (e.g. 24,25): the mesh columns again "
                    "with each model's 30-fps curves retimed to them, by linear interpolation and by resample_visemes")
    args = ap.parse_args()
    align_band = args.align or args.hear
    bands = {args.hear, align_band}
    torch.set_num_threads(1)

    languages = [x.strip() for x in args.languages.split(",") if x.strip()]
    unknown = [x for x in languages if x not in VOICES]
    if unknown:
        raise SystemExit(f"unknown language(s) {unknown}: use some of {','.join(VOICES)}")
    lacking = [x for x in languages if not (args.root / SOUNDS / VOICES[x]).is_dir()
               or not (args.root / DOCS / f"asterisk-core-sounds-{x}" / f"core-sounds-{x}.txt.gz").is_file()
               or any(not any((args.root / SOUNDS / VOICES[x]).glob(f"*.{BANDS[b]}")) for b in bands)]
    if lacking:
        print(f"the Asterisk prompts are not under {args.root} for {','.join(lacking)}; install them with\n"
              f"    sudo apt-get install {' '.join(packages(x, bands) for x in lacking)}\nor extract the .debs with "
              f"`dpkg -x PKG.deb DIR` and pass --root DIR. Nothing measured.")
        return
    if shutil.which("espeak-ng") is None:
        print("espeak-ng is needed for the alignment: sudo apt-get install espeak-ng. Nothing measured.")
        return

    models = {}
    for name in [m.strip() for m in args.models.split(",") if m.strip()]:
        path = shipped_model_path(name) if name in SHIPPED_MODELS else Path(name)
        models[name] = load_model(path)[0]

    started = time.perf_counter()
    tmp = Path(tempfile.mkdtemp(prefix="prompts-"))
    try:
        roots = build_corpus(args.root, tmp, languages, args.utterances, args.seed, args.hear, align_band)
        corpora = {lang: read_corpus(root) for lang, root in roots.items()}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    aligned = time.perf_counter() - started

    predict = CachedPredictor(CACHE)
    columns = header(args.tolerance) + MESH_COLUMNS
    rows: list = []
    pooled: dict[str, tuple[list, list]] = {}
    for lang, utts in corpora.items():
        seconds = sum(len(u.audio) for u in utts) / SAMPLE_RATE
        rows.append(f"{NAMES[lang]}: {len(utts)} prompt{'s' * (len(utts) != 1)}, {seconds:.1f} s of speech, "
                    f"{'pocketsphinx' if lang == 'en' else 'espeak-ng + DTW'} alignment on the {align_band} band; "
                    f"the models hear the {args.hear} band")
        sources = {name: [predict(model, u.audio, u.n) for u in utts] for name, model in models.items()}
        sources["procedural (alignment)"] = [u.procedural for u in utts]
        for name, curves in sources.items():
            rows.append(row(name, curves, utts, args.tolerance) + mesh_cells(curves, utts))
            pooled.setdefault(name, ([], []))[0].extend(curves)
            pooled[name][1].extend(utts)
    if len(corpora) > 1:
        rows.append(f"all {len(corpora)} languages pooled")
        rows += [row(name, curves, utts, args.tolerance) + mesh_cells(curves, utts)
                 for name, (curves, utts) in pooled.items()]

    print_grid(columns, rows)
    rates = [float(x) for x in args.retime.split(",") if x.strip()]
    if rates:
        retimed = []
        for name, (curves, utts) in pooled.items():
            retimed.append(mesh_cells(curves, utts) + [name, "30 (as made)"])
            for fps in rates:
                for how, fn in (("linear", resample), ("keys kept", resample_visemes)):
                    retimed.append(mesh_cells([fn(c, FPS, fps) for c in curves], utts, fps) + [name, f"{fps:g}, {how}"])
        print_grid(["model", "fps, retiming"] + MESH_COLUMNS, [r[-2:] + r[:-2] for r in retimed])
    suffixes = ",".join("-" + BANDS[b] for b in sorted(bands))
    print(f"alignment and ingestion {aligned:.1f} s; all {time.perf_counter() - started:.1f} s. Data: Debian "
          f"asterisk-core-sounds-{{{','.join(languages)}}}{{,{suffixes}}} 1.6.1 (CC-BY-SA-3.0 / CC-BY-3.0), read "
          f"from {args.root / SOUNDS}.")


if __name__ == "__main__":
    main()
