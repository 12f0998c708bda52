"""Learned curves that close the lips on voices the model never heard: training recipes for whisper-base-blstm
(issue 25, items 3 and 6), each judged on real speech of speakers no recipe trained on. Printed, never asserted.

Run: .venv/bin/python bench/encoders.py [--steps 2400] [--d-model 128] [--recipes lj,lj+cls,lj+fg,lj+fg+cls]
     [--espeak 200,100] [--threads 2] [--baseline] [--variants pitch:-3,speed:0.8] [--mbp-peaks 0.067,16]
     [--grid-phones spread|aligned] [--rooms 4] [--esx nl,cs:200] [--extra DIR] [--mbp-others 6] [--release-cut 12] [--save DIR]

Model: whisper-base-blstm (frozen Whisper-base encoder from the `visemeflow[whisper]` weights, last layer; Linear
512 -> d, one BLSTM of d/2 per direction, linear output, L1), seed 0, one utterance per step, `--steps` steps at
learning rate 1e-3. The encoder's outputs are kept in `bench/out/encoders/cache` (EncoderOutputCache), so a second
run encodes nothing it has seen.

Training data (all shippable; nothing of the judged speakers):
- `lj`: the 24 LJSpeech utterances of `examples/corpus/LJ` (public domain, MIT alignments); targets: the procedural
  curves of the alignment, *with* the closure rule (read afresh: `ProceduralConfig()`);
- `fg`: FACEGOOD takes 1114_2_02..04 (MIT), the animator's captured curves converted to our visemes, 8-s pieces
  (bench/domain_gap.py);
- `es`: the espeak-ng corpus of bench/learning_data.py at `--espeak EN,ZH` utterances (synthetic voices made here),
  its training split; targets: procedural curves of its alignment with the closure rule;
- `esx`: espeak-ng voices speaking Dutch and Czech (`--esx LANGS:N`, default nl,cs:200: N utterances per language,
  bench/espeak_langs.py: random sequences of common words, half of them with two b/p/m words, the language's voice
  and 5 variants at 130/160/200 wpm), all of them; targets: procedural curves of espeak's own phone timings with the
  closure rule and the `--closure-ramps` of the LJ targets; the alignment feeds `+cls`;
- `ljt`: the LJ examples with the synthetic (Cohen-Massaro) truth of the alignment as targets instead;
- `ljv`: the LJ examples in other voices (`--variants`, default pitch -3/+3 semitones and speed 0.8/1.25, each a
  fixed copy made once with `learning.augment.apply_condition`: a pitch shift moves the formants as a shorter or
  longer vocal tract would; a speed change resamples the targets and the per-frame visemes by the same factor);
- `ljr`: the LJ examples as heard in rooms (`--rooms` K copies of each, fixed, made once with
  `learning.rooms.apply_room`, seeded per utterance and copy: a synthetic impulse response of exponentially decaying
  noise, RT60 0.2-0.8 s, direct-to-reverberant ratio -3..+10 dB, behind a direct path at sample 0, so nothing moves
  in time and the targets and per-frame visemes stay as they are; level kept);
- `ljrc`: the same rooms (the same draws) followed by a channel: a zero-phase band-pass (low edge 80-400 Hz, high
  edge 3-7.5 kHz: telephone to wide band), a spectral tilt of -3..+3 dB per octave and white noise 20-40 dB below;
- `x`: an aligned corpus folder of your own (`--extra DIR`: wav + TextGrid per utterance, read as the product reads
  a corpus), e.g. the Kokoro voices of bench/kokoro_voices.py; targets as `esx`'s;
- `+cls` / `+clsW`: the auxiliary viseme-classification loss (`TrainConfig.viseme_loss_weight`, 0.5 or W) on the
  examples with an alignment (LJ, espeak; the FACEGOOD pieces have none and add only the curve loss).
A part named twice is seen twice as often. `--losses`: the curve loss (bench/domain_gap.py's `l1`, `closure:W`, ...);
`--seeds`: one row per training seed (20 b/p/m phones judged: seeds show how much of a difference is noise).

Judged on (none trained on by any recipe): GRID s1 (10 clips, male English), the charsiu Mandarin utterance
(AISHELL-3 SSB1624), praatio's examples (bobby, mary: American English) -- top-viseme closure recall of MBP and FFF,
false MBP closures and top-2 agreement (`visemeflow.learning.realspeech`), and the lips on the demo character's mesh
after the closure rule (`articulation.close_lips`, as the animation stage applies it; `animation.lips.LipProbe`,
`learning.lipscore`): b/p/m closed below 1.5 mm, their median gap, the median open-vowel opening (x AHH) and vowels
that never open; FACEGOOD take 1114_2_05 (a held-out take of the captured speaker): L1 x 100 against the captured
curves with the training takes' mean curve as floor, and the Pearson correlation of the predicted mouth opening (the
inner-lip gap on the demo mesh) with the animator's jawOpen channel. RTF: seconds per second of audio of `predict`
on a 30-s file on one CPU thread (encoder included). `--save DIR` writes each trained model (with its `--mbp-peaks`
in the config) to `DIR/<recipe>_<loss>_s<seed>_<layers>.pt`, a file bench/thirdlang.py's `--models` reads (Dutch and
Czech).
"""

from __future__ import annotations

import argparse
import re
import shutil
import sys
import tempfile
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from domain_gap import (  # noqa: E402
    FACEGOOD,
    HELD_OUT_TAKE,
    ROOT,
    TRAIN_TAKES,
    facegood_take,
    grid_corpus,
    pieces,
)
from realspeech import FPS, SAMPLE_RATE, SHARED, Utterance, read_corpus  # noqa: E402
from judging import HEADER, judge, make_loss, row  # noqa: E402

from visemeflow.shapes.conventions import ARKIT_52  # noqa: E402
from visemeflow.ingest.captured import read_channel_table, read_take  # noqa: E402
from visemeflow.learning.features import EncoderOutputCache, WhisperExtractor  # noqa: E402
from visemeflow.learning.model import ClosurePeaks, ReleaseCut  # noqa: E402
from visemeflow.learning.presets import PRESETS  # noqa: E402
from visemeflow.learning.realspeech import frame_visemes  # noqa: E402
from visemeflow.procedural import ProceduralConfig  # noqa: E402
from visemeflow.learning.rooms import apply_room  # noqa: E402
from visemeflow.learning.train import (  # noqa: E402
    Example,
    TrainConfig,
    _audio_hash,
    predict_curves,
    save_model,
    train_model,
)

CACHE = Path(__file__).resolve().parent / "out" / "encoders" / "cache"
AUX_WEIGHT = 0.5
LR = 1e-3


def labelled(u: Utterance, targets: str = "procedural") -> Example:
    """An aligned utterance as a training example: procedural targets (closure rule) or the synthetic truth
    (`targets="truth"`), and per-frame visemes."""
    curves = u.procedural if targets == "procedural" else u.truth
    return Example(u.uid, u.audio, curves.astype(np.float32), FPS, frame_visemes(u.phones, u.n, FPS))


def grid_aligned_corpus(tmp: Path) -> Path:
    """GRID s1's clips with phone timings measured in the audio: each clip's transcript forced-aligned by
    pocketsphinx (`visemeflow.phonetics.forcealign`), written as a wav and a TextGrid (words, phones) under `tmp`.
    GRID's own `.align` holds word timings only, and phones spread evenly over a word give the b of "blue" a third
    of the word whatever its real length."""
    import soundfile as sf

    from visemeflow.ingest.audio import read_audio
    from visemeflow.phonetics.forcealign import align_transcript, alignment_tiers
    from visemeflow.phonetics.textgrid import format_textgrid

    folder = tmp / "grid-aligned" / "s1"
    folder.mkdir(parents=True)
    texts = dict(line.split("\t", 1) for line in (SHARED / "grid_s1" / "transcripts.tsv").read_text().splitlines()
                 if "\t" in line)
    for align in sorted((SHARED / "grid_s1" / "align").glob("*.align")):
        audio, rate = read_audio(SHARED / "grid_s1" / "video" / f"{align.stem}.mpg")
        done = align_transcript(audio, rate, texts[align.stem].strip(), source=align.stem)
        duration = len(audio) / rate
        sf.write(folder / f"{align.stem}.wav", audio, rate)
        (folder / f"{align.stem}.TextGrid").write_text(format_textgrid(alignment_tiers(done, duration), 0.0, duration))
    return folder.parent


GRID_PHONES = "spread"   # held-out GRID phone timings: "spread" over .align's words (the recorded figures) or
#                          "aligned" in the audio by pocketsphinx (`--grid-phones aligned`)


def held_out_sets(tmp: Path, grid_phones: str = GRID_PHONES) -> dict[str, list[Utterance]]:
    if grid_phones not in ("aligned", "spread"):
        raise ValueError(f"grid_phones must be aligned or spread, got {grid_phones!r}")
    sets = {"GRID s1": read_corpus(grid_aligned_corpus(tmp) if grid_phones == "aligned" else grid_corpus(tmp))}
    zh = tmp / "charsiu" / "SSB1624"
    zh.mkdir(parents=True)
    shutil.copyfile(SHARED / "charsiu_mandarin" / "SSB16240001_16k.wav", zh / "SSB16240001.wav")
    shutil.copyfile(SHARED / "charsiu_mandarin" / "SSB16240001.TextGrid", zh / "SSB16240001.TextGrid")
    sets["Mandarin"] = read_corpus(zh.parent)
    folder = tmp / "praatio" / "praatio"
    folder.mkdir(parents=True)
    for name, grid in (("bobby", "bobby_phones.TextGrid"), ("mary", "mary.TextGrid")):
        shutil.copyfile(SHARED / "praatio_examples" / f"{name}.wav", folder / f"{name}.wav")
        shutil.copyfile(SHARED / "praatio_examples" / grid, folder / f"{name}.TextGrid")
    sets["praatio"] = read_corpus(folder.parent)
    return sets


CROP_S = (0.3, 1.0)    # `ljw`: the speech of a crop lasts 0.3-1.0 s ...
CROP_PAD_S = 0.3       # ... with this much silence either side


@dataclass
class Sets:
    lj: list[Example]
    lj_truth: list[Example]        # the same utterances with the synthetic (Cohen-Massaro) truth as targets
    lj_variants: list[Example]     # the same utterances in other voices (`ljv`)
    facegood: list[Example]
    espeak: list[Example]
    held_out: dict[str, list[Utterance]]
    test_audio: np.ndarray
    test_curves: np.ndarray
    test_jaw: np.ndarray           # (T,) the animator's jawOpen of the held-out take
    floor: np.ndarray
    espeak_langs: list[Example] = field(default_factory=list)  # `esx`: espeak-ng in Dutch/Czech/...
    rooms: int = 0                                             # copies of each LJ utterance in `ljr` / `ljrc`
    lj_rooms: list[Example] = field(default_factory=list)      # the LJ utterances heard in rooms (`ljr`), made
    lj_channels: list[Example] = field(default_factory=list)   # ... and through a channel (`ljrc`): on first use
    lj_crops: list[Example] = field(default_factory=list)      # short pieces of them in silence (`ljw`)
    lj_utterances: list[Utterance] = field(default_factory=list)  # the LJ utterances of `lj` (phones for `ljw`)
    crop_s: tuple[float, float] = CROP_S                         # `ljw`: seconds of speech in a crop (low, high)
    extra: list[Example] = field(default_factory=list)           # `x`: the aligned corpus of `--extra DIR`


VARIANTS = "pitch:-3,pitch:3,speed:0.8,speed:1.25"


def voice_variants(examples: list[Example], variants: str = VARIANTS) -> list[Example]:
    """`ljv`: each example under each `condition:value` of `variants` (learning.augment.apply_condition), targets
    and per-frame visemes resampled by the speed factor."""
    from visemeflow.learning.augment import apply_condition
    from visemeflow.learning.train import resample_curves

    out = []
    for spec in (v for v in variants.split(",") if v):
        condition, value = spec.split(":")
        for e in examples:
            audio, factor = apply_condition(e.audio, SAMPLE_RATE, condition, float(value),
                                            np.random.default_rng(0))
            curves = resample_curves(e.curves, factor)
            visemes = None
            if e.visemes is not None:   # nearest original frame of each new frame, as resample_curves places it
                pos = np.minimum(np.round(np.arange(len(curves)) * factor).astype(np.int64), len(e.visemes) - 1)
                visemes = e.visemes[pos]
            out.append(Example(f"{e.utterance_id}__{condition}_{value}", audio, curves, e.fps, visemes))
    return out


ROOMS = 4   # copies of each LJ utterance in `ljr` / `ljrc`


def room_copies(examples: list[Example], copies: int = ROOMS, channel: bool = False) -> list[Example]:
    """`ljr` (`channel=False`) / `ljrc`: `copies` fixed copies of each example through a synthetic room
    (`learning.rooms.apply_room`), the k-th copy of an utterance drawn from a generator seeded by (k, its id), so
    `ljr` and `ljrc` share their rooms; targets and per-frame visemes unchanged (the room moves nothing in time)."""
    out = []
    for e in examples:
        for k in range(copies):
            rng = np.random.default_rng([k, zlib.crc32(e.utterance_id.encode("utf-8"))])
            audio = apply_room(e.audio, SAMPLE_RATE, rng, channel=channel)
            out.append(Example(f"{e.utterance_id}__room{'ch' * channel}_{k}", audio, e.curves, e.fps, e.visemes))
    return out


def ramps(text: str) -> float | tuple[float, float]:
    """`--closure-ramps`: one number (onset = decay) or ONSET,DECAY, in seconds."""
    values = [float(x) for x in text.split(",")]
    if len(values) not in (1, 2):
        raise argparse.ArgumentTypeError(f"{text!r}: SECONDS or ONSET,DECAY")
    return values[0] if len(values) == 1 else (values[0], values[1])


def load_sets(espeak: tuple[int, int] | None = None, closure_ramp_s: float | tuple[float, float] | None = None,
              variants: str = VARIANTS, grid_phones: str = GRID_PHONES, rooms: int = ROOMS,
              esx: str = "") -> Sets:
    """Training sets and held-out speech (module docstring); `espeak` = (English, Mandarin) utterances or None;
    `closure_ramp_s`: the LJ targets' MBP/FFF onset and decay (`ProceduralConfig.closure_onset_s`/`closure_decay_s`;
    one number for both or (onset, decay); None: the procedural default's ramps); `variants`: the voices of `ljv`; `rooms`: the copies of each LJ
    utterance in `ljr` and `ljrc`; `esx`: `LANGS:N` of the `esx` corpus (bench/espeak_langs.py), "" for none."""
    onset, decay = closure_ramp_s if isinstance(closure_ramp_s, tuple) else (closure_ramp_s, closure_ramp_s)
    targets = ProceduralConfig(closure_onset_s=onset, closure_decay_s=decay)
    lj_utts = [u for u in read_corpus(ROOT / "examples" / "corpus", procedural=targets) if u.speaker == "LJ"]
    lj, lj_truth = [labelled(u) for u in lj_utts], [labelled(u, "truth") for u in lj_utts]
    lj_variants = voice_variants(lj, variants)
    with tempfile.TemporaryDirectory() as tmp:
        held = held_out_sets(Path(tmp), grid_phones)
    facegood = [e for name in TRAIN_TAKES for e in pieces(f"facegood/{name}", *facegood_take(name))]
    es: list[Example] = []
    if espeak:
        from learning_data import ensure_corpus

        from visemeflow.ingest.utterance import assign_split

        root = ensure_corpus(*espeak)
        es = [labelled(u) for u in read_corpus(root) if assign_split(u.uid, 0.1) == "train"]
    esx_examples: list[Example] = []
    if esx:
        from espeak_langs import ensure_corpus as ensure_esx

        langs, _, count = esx.partition(":")
        root = ensure_esx(tuple(langs.split(",")), int(count or 200))
        esx_examples = [labelled(u) for u in read_corpus(root, procedural=targets)]
    test_audio, test_curves = facegood_take(HELD_OUT_TAKE)
    table = read_channel_table(ROOT / "examples" / "facegood" / "voice2face_arkit.csv")
    take = read_take(FACEGOOD / f"bs_value_{HELD_OUT_TAKE}.npy", "npy", table=table,
                     names=FACEGOOD / "shirley_1015_bs_name.npy", fps=FPS)
    jaw = np.asarray(take.arkit)[:, ARKIT_52.index("jawOpen")]
    floor = np.concatenate([e.curves for e in facegood]).mean(axis=0)
    return Sets(lj, lj_truth, lj_variants, facegood, es, held, test_audio, test_curves, jaw, floor, esx_examples,
                rooms, lj_utterances=lj_utts)


def short_crops(utterances: list[Utterance], examples: list[Example],
                seconds: tuple[float, float] = CROP_S) -> list[Example]:
    """`ljw`: each LJ utterance cut at phone boundaries into pieces of 0.3-1.0 s of speech (seeded per utterance),
    each faded in and out over 10 ms and put between 0.3 s of silence, as an isolated word or syllable is heard;
    targets and per-frame visemes are the utterance's own over the piece, at rest (zero, no viseme) in the
    silence. Whisper sees every piece inside its 30-s window of silence, as it sees a lone syllable."""
    out = []
    pad = int(round(CROP_PAD_S * FPS))
    fade = int(0.01 * SAMPLE_RATE)
    for u, e in zip(utterances, examples, strict=True):
        rng = np.random.default_rng(zlib.crc32(u.uid.encode("utf-8")))
        voiced = [p for p in u.phones if p.viseme is not None]
        i = 0
        while i < len(voiced):
            want = rng.uniform(*seconds)
            j = i
            while j + 1 < len(voiced) and voiced[j].end_s - voiced[i].start_s < want:
                j += 1
            f0, f1 = int(round(voiced[i].start_s * FPS)), min(int(round(voiced[j].end_s * FPS)), len(e.curves))
            i = j + 1
            if f1 - f0 < 3:
                continue
            audio = e.audio[int(f0 / FPS * SAMPLE_RATE):int(f1 / FPS * SAMPLE_RATE)].copy()
            ramp = np.linspace(0.0, 1.0, fade, dtype=np.float32)
            audio[:fade] *= ramp[:len(audio[:fade])]
            audio[-fade:] *= ramp[::-1][-len(audio[-fade:]):]
            silence = np.zeros(int(pad / FPS * SAMPLE_RATE), np.float32)
            curves = np.concatenate([np.zeros((pad, 16), np.float32), e.curves[f0:f1],
                                     np.zeros((pad, 16), np.float32)])
            visemes = np.concatenate([np.full(pad, -1), e.visemes[f0:f1], np.full(pad, -1)]).astype(np.int64)
            out.append(Example(f"{e.utterance_id}__crop{len(out):03d}", np.concatenate([silence, audio, silence]),
                               curves, e.fps, visemes))
    return out


def recipe_data(sets: Sets, recipe: str) -> list[Example]:
    parts = [p for p in recipe.split("+") if not p.startswith("cls")]
    if "ljr" in parts and not sets.lj_rooms:      # made once, on first use (~3 s for 4 copies)
        sets.lj_rooms = room_copies(sets.lj, sets.rooms)
    if "ljrc" in parts and not sets.lj_channels:
        sets.lj_channels = room_copies(sets.lj, sets.rooms, channel=True)
    if "ljw" in parts and not sets.lj_crops:
        sets.lj_crops = short_crops(sets.lj_utterances, sets.lj, sets.crop_s)
    data = {"lj": sets.lj, "ljt": sets.lj_truth, "ljv": sets.lj_variants, "fg": sets.facegood,
            "es": sets.espeak, "esx": sets.espeak_langs, "ljr": sets.lj_rooms, "ljrc": sets.lj_channels,
            "ljw": sets.lj_crops, "x": sets.extra}
    unknown = [p for p in parts if p not in data or (p == "es" and not sets.espeak)
               or (p == "esx" and not sets.espeak_langs) or (p == "x" and not sets.extra)]
    if unknown:
        raise SystemExit(f"unknown recipe part(s) {unknown} in {recipe!r} (es needs --espeak, esx --esx, "
                         "x --extra)")
    return [e for p in parts for e in data[p]]


def recipe_config(recipe: str, n_train: int, steps: int, d_model: int, seed: int = 0,
                  layers: str | None = None, preset: str = "whisper-base-blstm",
                  dropout: float | None = None) -> TrainConfig:
    """`+cls` adds the auxiliary viseme loss at weight 0.5, `+clsW` at weight W."""
    epochs = -(-steps // n_train)
    cls = [p for p in recipe.split("+") if p.startswith("cls")]
    weight = (float(cls[0][3:]) if cls[0][3:] else AUX_WEIGHT) if cls else 0.0
    return TrainConfig(preset=preset, d_model=d_model, epochs=epochs, seed=seed, lr=LR,
                       max_steps_per_epoch=min(n_train, -(-steps // epochs)), viseme_loss_weight=weight,
                       whisper_layers=layers, dropout=dropout)


class CachedPredictor:
    """`predict(model, audio, n)` as predict_curves gives it, with the frozen encoder's outputs from the cache."""

    def __init__(self, directory: Path = CACHE) -> None:
        self.cache = EncoderOutputCache(directory)

    def __call__(self, model, audio: np.ndarray, n: int) -> np.ndarray:
        feats = model.features
        if not isinstance(feats, WhisperExtractor):
            return predict_curves(model, audio, SAMPLE_RATE, FPS, n_frames=n)
        a = torch.from_numpy(np.ascontiguousarray(audio, np.float32))[None]
        lengths = torch.tensor([a.shape[1]])
        with torch.no_grad():
            enc = self.cache.get_or_encode(feats, feats.encoder_fingerprint(), a, _audio_hash(audio), "cpu-fp32")
            f, fl = feats(a, lengths, encoded=enc)
            pred, mask = model.head(f, fl, torch.tensor([n]), fps=FPS)
            pred = model.finish(pred, mask, a, lengths, FPS)    # as the model's own eval-mode forward
        return np.clip(pred[0, :n].numpy(), 0.0, 1.0).astype(np.float32)


def rtf(model, seconds: float = 30.0) -> float:
    """predict_curves seconds per second of audio on one thread, 30 s of speech (LJ concatenated), encoder included."""
    import soundfile as sf

    parts = [sf.read(p, dtype="float32")[0] for p in sorted((ROOT / "examples/corpus/LJ").glob("*.wav"))]
    audio = np.concatenate(parts)[: int(seconds * SAMPLE_RATE)]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        predict_curves(model, audio[:SAMPLE_RATE], SAMPLE_RATE, FPS)
        t0 = time.perf_counter()
        predict_curves(model, audio, SAMPLE_RATE, FPS)
        return (time.perf_counter() - t0) / seconds
    finally:
        torch.set_num_threads(threads)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=2400)
    parser.add_argument("--d-model", type=int, default=128)
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads (1: with another process busy, 2 OpenMP threads on 2 cores ran ~40x "
                             "slower here)")
    parser.add_argument("--losses", default="l1", help="training losses (bench/domain_gap.py): l1, closure:W, ...")
    parser.add_argument("--seeds", default="0", help="training seeds (comma-separated): one row each")
    parser.add_argument("--recipes", default="lj,lj+cls,lj+fg,lj+fg+cls")
    parser.add_argument("--espeak", default="", help="EN,ZH utterances of the espeak corpus for `es` recipes")
    parser.add_argument("--esx", default="nl,cs:200",
                        help="LANGS:N of the `esx` corpus (espeak-ng in nl, cs, de, pl; N per language), made only "
                             "when a recipe has `esx`")
    parser.add_argument("--closure-ramps", type=ramps, default=None, metavar="SECONDS[,DECAY]",
                        help="onset and decay, s, of the MBP/FFF ramps in the LJ targets: one number for both or "
                             "ONSET,DECAY (default: procedural's)")
    parser.add_argument("--crop-seconds", default=f"{CROP_S[0]},{CROP_S[1]}", metavar="LOW,HIGH",
                        help="`ljw`: seconds of speech in each crop, drawn uniformly in [LOW, HIGH]")
    parser.add_argument("--grid-phones", default=GRID_PHONES, choices=("spread", "aligned"),
                        help="held-out GRID phone timings: spread over its word timings, or aligned by pocketsphinx")
    parser.add_argument("--variants", default=VARIANTS,
                        help="the voices of `ljv`: condition:value pairs (learning.augment conditions)")
    parser.add_argument("--rooms", type=int, default=ROOMS,
                        help="copies of each LJ utterance in `ljr` (rooms) and `ljrc` (rooms + channel)")
    parser.add_argument("--save", type=Path, default=None, metavar="DIR",
                        help="write each trained model to DIR (for bench/thirdlang.py --models DIR/NAME.pt)")
    parser.add_argument("--mbp-peaks", default="0,0", metavar="SECONDS,POWER",
                        help="narrow each trained model's MBP channel to its peaks (learning.model.ClosurePeaks)")
    parser.add_argument("--extra", type=Path, default=None, metavar="DIR",
                        help="an aligned corpus folder (wav + TextGrid per utterance, read as the product reads one) "
                             "for the recipe part `x`; targets: procedural curves with the closure rule and the "
                             "--closure-ramps of the LJ targets")
    parser.add_argument("--mbp-others", type=float, default=0.0, metavar="K",
                        help="with --mbp-peaks: cap the other visemes at (1 - MBP) ** K where MBP leads (the "
                             "shipped default's 6; `ClosurePeaks.others_power`); 0: no cap")
    parser.add_argument("--release-cut", type=float, default=0.0, metavar="DB",
                        help="end each closure at its release, a rise of the 400-3400 Hz band of DB dB within 20 ms "
                             "(the shipped default's 12; `learning.model.ReleaseCut`); 0: off")
    parser.add_argument("--baseline", action="store_true", help="also judge the shipped fbank default and floors")
    parser.add_argument("--rtf", action="store_true", help="time the first recipe's model on one thread")
    parser.add_argument("--layers", default="last", help="encoder outputs into the decoder, comma-separated: "
                                                         "last, weighted (a learned sum of every layer): one row each")
    parser.add_argument("--presets", default="whisper-base-blstm",
                        help="whisper presets, comma-separated: the decoder under the frozen encoder (the paper's "
                             "Table 2: whisper-base-blstm, -lstm, -tcn, -transformer): one row each")
    parser.add_argument("--dropout", type=float, default=0.0,
                        help="dropout on the decoder's output in training (TrainConfig.dropout; 0: the preset's)")
    args = parser.parse_args()
    presets = [p for p in args.presets.split(",") if p]
    unknown = [p for p in presets if p not in PRESETS or PRESETS[p].feature != "whisper"]
    if unknown:
        raise SystemExit(f"--presets: {unknown} are not whisper presets (have: "
                         f"{', '.join(k for k, v in PRESETS.items() if v.feature == 'whisper')})")
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    espeak = tuple(int(x) for x in args.espeak.split(",")) if args.espeak else None
    uses_esx = any("esx" in r.split("+") for r in args.recipes.split(","))
    sets = load_sets(espeak, args.closure_ramps, args.variants, args.grid_phones, args.rooms,
                     args.esx if uses_esx else "")
    sets.crop_s = tuple(float(x) for x in args.crop_seconds.split(","))
    if args.extra is not None:
        onset, decay = args.closure_ramps if isinstance(args.closure_ramps, tuple) else (args.closure_ramps,) * 2
        sets.extra = [labelled(u) for u in read_corpus(args.extra, procedural=ProceduralConfig(
            closure_onset_s=onset, closure_decay_s=decay))]
    print(f"data in {time.perf_counter() - t0:.0f} s: LJ {len(sets.lj)}, FACEGOOD pieces {len(sets.facegood)}, "
          f"espeak {len(sets.espeak)}, esx {len(sets.espeak_langs)}, extra {len(sets.extra)}; held out: "
          + ", ".join(f"{k} {len(v)}" for k, v in sets.held_out.items()), flush=True)
    predict = CachedPredictor()
    rows = []
    if args.baseline:
        from visemeflow.learning.default_model import default_model_path
        from visemeflow.learning.train import load_model

        rows.append(row("procedural curves of the alignment (ceiling; FACEGOOD: floor)", judge(
            sets, lambda a, n: next((u.procedural for us in sets.held_out.values() for u in us if u.audio is a),
                                    np.tile(sets.floor, (n, 1)).astype(np.float32)))))
        rows.append(row("synthetic truth of the alignment (Cohen-Massaro; FACEGOOD: floor)", judge(
            sets, lambda a, n: next((u.truth for us in sets.held_out.values() for u in us if u.audio is a),
                                    np.tile(sets.floor, (n, 1)).astype(np.float32)))))
        rows.append(row("mean curve of the FACEGOOD training takes (floor)",
                        judge(sets, lambda a, n: np.tile(sets.floor, (n, 1)).astype(np.float32))))
        for path in (default_model_path(), default_model_path().with_name("default-fbank.pt")):
            if path.is_file():
                m, cfg, _ = load_model(path)
                rows.append(row(f"shipped {path.name} ({cfg.preset})", judge(sets, lambda a, n, m=m: predict(m, a, n))))
        for r in rows:
            print(r, flush=True)
    runs = [(r, loss, int(seed), layers, preset) for r in args.recipes.split(",") if r
            for loss in args.losses.split(",") for seed in args.seeds.split(",") for layers in args.layers.split(",")
            for preset in presets]
    for recipe, loss, seed, layers, preset in runs:
        train = recipe_data(sets, recipe)
        started = time.perf_counter()
        config = recipe_config(recipe, len(train), args.steps, args.d_model, seed, layers, preset, args.dropout)
        model = train_model(train, [], config, encoder_cache=CACHE, loss=make_loss(loss)).model
        window_s, power = (float(x) for x in args.mbp_peaks.split(","))
        model.closure_peaks = ClosurePeaks(window_s, power, others_power=args.mbp_others) if window_s > 0 else None
        model.release_cut = ReleaseCut(args.release_cut) if args.release_cut > 0 else None
        model.eval()
        secs = time.perf_counter() - started
        if args.save is not None:
            args.save.mkdir(parents=True, exist_ok=True)
            peaks = {"mbp_peaks_half_window_s": window_s, "mbp_peaks_power": power,
                     "mbp_others_power": args.mbp_others} if window_s > 0 else {}
            peaks.update({"mbp_release_rise_db": args.release_cut} if args.release_cut > 0 else {})
            decoder = ("" if preset == "whisper-base-blstm" else f"{preset.removeprefix('whisper-base-')}_") + (
                f"drop{args.dropout:g}_" if args.dropout else "")
            saved = save_model(model, config.model_copy(update=peaks),
                               args.save / re.sub(r"[^\w.+-]", "_", f"{decoder}{recipe}_{loss}_s{seed}_{layers}.pt"),
                               {"script": "bench/encoders.py", "preset": preset, "recipe": recipe, "loss": loss, "seed": seed,
                                "layers": layers, "steps": args.steps, "d_model": args.d_model,
                                "closure_ramps_s": args.closure_ramps, "rooms": args.rooms, "esx": args.esx,
                                "extra": str(args.extra) if args.extra else None,
                                "mbp_peaks": [window_s, power]})
            print(f"saved {saved}", flush=True)
        rows.append(row(f"{preset}{f' dropout {args.dropout:g}' if args.dropout else ''}, {recipe}, {loss}, seed {seed}, {layers} layer(s) ({len(train)} ex, "
                        f"{args.steps} steps, "
                        f"d {args.d_model})", judge(sets, lambda a, n, m=model: predict(m, a, n)), secs))
        print(rows[-1], flush=True)
        if args.rtf:
            print(f"RTF (one thread, 30 s): {rtf(model):.3f}", flush=True)
            args.rtf = False
    print()
    print(HEADER)
    for r in rows:
        print(r)
    print(f"\ntargets: MBP >= 90% with false <= 3%; FFF >= 70%; FACEGOOD L1 >= 30% below the floor, jaw r >= 0.7; "
          f"mesh b/p/m closed >= 90%. total {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
