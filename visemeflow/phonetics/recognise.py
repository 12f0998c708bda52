"""Phones recognised from the audio alone: timed ARPAbet phones of any English voice, with no alignment and no
training of ours.

PocketSphinx (CMU, BSD-2) decodes the audio with CMU's English acoustic model, which its wheel carries (no
download), in its all-phone mode: every phone may follow every other, weighed by the phone-trigram language model
that comes with it. Its acoustic model was trained on many real speakers, which no model of ours can be here; that
is the point: `bench/recogniser.py` and `bench/domain_gap.py` measure the procedural curves of these phones against
the learned models on speakers nothing was trained on.

`closure_bias` multiplies the language model's probability of every b/p/m and f/v phone (1: the stock model); more
closures are heard, and more falsely (`bench/domain_gap.py --recogniser-bias` prints the trade-off).

Errors are :class:`RecogniserError` naming the audio: samples that are not finite, pocketsphinx not installed.
"""

from __future__ import annotations

import atexit
import functools
import math
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visemeflow.phonetics.inventory import UnknownPhonemeError, map_phone, split_interval
from visemeflow.phonetics.types import VisemeSegment

SAMPLE_RATE = 16000
FRAME_S = 0.01  # pocketsphinx's frame rate is 100 per second
# Frame i is analysed over [i * 10 ms, i * 10 ms + 25.625 ms] (its default window): it describes the sound at the
# window's centre, 12.8 ms after the frame's start. Times are moved there, which the LJ alignments confirm: b/p/m
# phones closed 46 -> 59 of 154, false closures 5.6 -> 5.8% (bench/recogniser.py, "frame starts").
WINDOW_CENTRE_S = 0.025625 / 2
LM_WEIGHT = 2.0  # all-phone decoding: the language model weighs less than in word decoding (its default 6.5)
CLOSURE_PHONES = {"B": "MBP", "P": "MBP", "M": "MBP", "F": "FFF", "V": "FFF"}
SILENCE = "SIL"
CMN = "batch"


class RecogniserError(ValueError):
    """Phones could not be recognised from this audio (the message names it)."""


@dataclass(frozen=True, slots=True)
class RecognisedPhone:
    label: str       # ARPAbet without stress ("B", "IY"); "" for silence and noise
    start_s: float
    end_s: float


def _pocketsphinx():
    try:
        import pocketsphinx
    except ImportError as exc:  # pragma: no cover - a dependency of the package; this guards broken installs
        raise RecogniserError("phone recognition needs pocketsphinx (`pip install pocketsphinx`, which brings its "
                              "English model)") from exc
    return pocketsphinx


@functools.cache
def _biased_lm(bias: float) -> str:
    """The stock phone language model in ARPA text with log10(bias) added to every n-gram ending in a closure phone
    (written once per process and bias)."""
    ps = _pocketsphinx()
    folder = Path(tempfile.mkdtemp(prefix="visemeflow-phone-lm-"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    stock = folder / "stock.arpa"
    # With NGramModel.readfile the model's LogMath can be freed before write() and the file holds garbage now and
    # then; a LogMath of our own, alive throughout, writes the same file every time.
    logmath = ps.LogMath()
    model = ps.NGramModel(ps.Config(), logmath, ps.get_model_path("en-us/en-us-phone.lm.bin"))
    model.write(str(stock), ps.NGramModel.str_to_type("arpa"))
    del model, logmath
    add = math.log10(bias)
    lines, order = [], 0
    for line in stock.read_text().splitlines():
        if line.startswith("\\"):  # "\\2-grams:" starts the bigrams; "\\end\\" ends them
            order = int(line[1:].split("-")[0]) if line.endswith("-grams:") else 0
        elif order and line.strip():
            fields = line.split()  # log10 probability, the n words (the last is the one predicted), [backoff]
            if not -99.5 <= float(fields[0]) <= 0:
                raise RecogniserError(f"pocketsphinx wrote an unreadable phone language model ({line!r} in {stock})")
            if fields[order] in CLOSURE_PHONES:
                fields[0] = f"{float(fields[0]) + add:.4f}"
            line = "\t".join(fields)
        lines.append(line)
    out = folder / f"closure-bias-{bias:g}.arpa"
    out.write_text("\n".join(lines) + "\n")
    stock.unlink()
    return str(out)


class PhoneRecogniser:
    """All-phone decoding with pocketsphinx's English model; a fresh decoder for each audio, so any thread may call."""

    def __init__(self, lm_weight: float = LM_WEIGHT, closure_bias: float = 1.0,
                 shift_s: float = WINDOW_CENTRE_S) -> None:
        if not (math.isfinite(lm_weight) and lm_weight > 0):
            raise ValueError(f"lm_weight must be a positive number, got {lm_weight!r}")
        if not (math.isfinite(closure_bias) and closure_bias > 0):
            raise ValueError(f"closure_bias must be a positive number, got {closure_bias!r}")
        if not (math.isfinite(shift_s) and abs(shift_s) < 0.5):
            raise ValueError(f"shift_s must be a number of seconds below 0.5 in size, got {shift_s!r}")
        ps = _pocketsphinx()
        lm = (ps.get_model_path("en-us/en-us-phone.lm.bin") if closure_bias == 1.0
              else _biased_lm(float(closure_bias)))
        self.lm_weight, self.closure_bias, self.shift_s = float(lm_weight), float(closure_bias), float(shift_s)
        # A decoder carries state from one utterance into the next (its cepstral mean, its noise estimate): the
        # phones of a file would depend on what was decoded before it. Each call gets a fresh decoder (0.15 s), and
        # "batch" normalises each utterance by its own cepstral mean.
        self._config = dict(allphone=lm, lm=None, lw=self.lm_weight, beam=1e-20, pbeam=1e-20, cmn=CMN,
                            loglevel="FATAL")
        ps.Decoder(**self._config)  # a bad setting fails here, not at the first file

    @property
    def settings(self) -> str:
        """What decides the output (for cache keys): the package's version and the decoding settings."""
        from importlib.metadata import version

        return (f"pocketsphinx {version('pocketsphinx')} en-us allphone lw={self.lm_weight:g} "
                f"bias={self.closure_bias:g} shift={self.shift_s:g} cmn={CMN}")

    def recognise(self, audio: np.ndarray, sample_rate: int, source: str = "<audio>") -> list[RecognisedPhone]:
        """Timed phones of `audio` ((samples,) or (samples, channels), any rate, float in [-1, 1]) covering it."""
        if not sample_rate > 0:
            raise RecogniserError(f"{source}: sample rate must be positive, got {sample_rate}")
        x = np.asarray(audio, dtype=np.float64)
        if x.ndim == 2:
            x = x.mean(axis=1)
        if x.ndim != 1:
            raise RecogniserError(f"{source}: audio must be (samples,) or (samples, channels), got shape {x.shape}")
        if not np.isfinite(x).all():
            bad = int(np.flatnonzero(~np.isfinite(x))[0])
            raise RecogniserError(f"{source}: audio sample {bad} ({bad / sample_rate:.3f} s) is not a finite number")
        if sample_rate != SAMPLE_RATE:
            from scipy.signal import resample_poly

            g = math.gcd(int(sample_rate), SAMPLE_RATE)
            x = resample_poly(x, SAMPLE_RATE // g, int(sample_rate) // g)
        duration = len(x) / SAMPLE_RATE
        # too short to hold a phone (5 frames), or digital silence (under 2 steps of 16 bits, where batch
        # normalisation would make phones of nothing): silence
        if len(x) < SAMPLE_RATE * 0.05 or np.abs(x).max() < 2 / 32768:
            return [RecognisedPhone("", 0.0, duration)] if duration > 0 else []
        pcm = (np.clip(x, -1.0, 1.0) * 32767).astype("<i2").tobytes()
        decoder = _pocketsphinx().Decoder(**self._config)
        decoder.start_utt()
        decoder.process_raw(pcm, full_utt=True)
        decoder.end_utt()
        segments = [(s.word, s.start_frame, s.end_frame) for s in decoder.seg()]
        phones = []
        for k, (word, first, last) in enumerate(segments):
            start = 0.0 if k == 0 else min(first * FRAME_S + self.shift_s, duration)
            end = duration if k == len(segments) - 1 else min((last + 1) * FRAME_S + self.shift_s, duration)
            start = max(start, phones[-1].end_s if phones else 0.0)
            if end > start:
                phones.append(RecognisedPhone("" if word == SILENCE or word.startswith("+") else word, start, end))
        return phones


@functools.lru_cache(maxsize=4)
def shared_recogniser(lm_weight: float = LM_WEIGHT, closure_bias: float = 1.0,
                      shift_s: float = WINDOW_CENTRE_S) -> PhoneRecogniser:
    """One recogniser per setting and process (a biased language model is written once)."""
    return PhoneRecogniser(lm_weight, closure_bias, shift_s)


def viseme_segments(phones: Sequence[RecognisedPhone], source: str = "<audio>") -> list[VisemeSegment]:
    """The viseme segments of recognised phones, as an alignment's: silence dropped, a phone of several visemes split
    by the ARPAbet table's weights. Each phone is its own word (recognition finds no word boundaries)."""
    out: list[VisemeSegment] = []
    for index, phone in enumerate(phones):
        if not phone.label:
            continue
        try:
            m = map_phone(phone.label, "arpabet")
        except UnknownPhonemeError as exc:
            raise RecogniserError(f"{source}: the recogniser gave {phone.label!r} at {phone.start_s:.2f} s, which the "
                                  "ARPAbet table does not know") from exc
        visemes = m.visemes or ((None, 1.0),)
        for (viseme, _), (a, b) in zip(visemes, split_interval(phone.start_s, phone.end_s, [w for _, w in visemes])):
            if viseme is not None:
                out.append(VisemeSegment(viseme, a, b, index, m.phoneme or ""))
    return out
