"""English forced alignment of a known transcript with pocketsphinx: word and phone spans measured in the audio.

Where only word timings exist (GRID's `.align`), `wordalign` spreads each word's dictionary phones over the word by
fixed weights; a bilabial's closure then gets a third of "blue" whatever its real length. This aligner places every
phone where the acoustic model finds it instead (pocketsphinx 5's `set_align_text`: the transcript's words from its
CMU dictionary, a first pass for the words and a second for their phones and states), at pocketsphinx's 10 ms frame
step. English only (its en-us model and dictionary). A word the dictionary lacks ("woodcutters") is spelled by
espeak-ng (`espeak-ng -q --ipa -v en-us`, the program the synthetic corpus uses) and its IPA turned into ARPAbet
(:data:`IPA_TO_ARPABET`); without espeak-ng, or when a symbol has no ARPAbet, the error names the word.

Pure: audio in, spans out (no files, no Prefect). Phones are ARPAbet without stress digits (`B`, `IY`), silence is
left out of the phone spans (gaps between them) and of the words.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from visemeflow.phonetics.types import PhoneInterval, WordInterval

__all__ = ["AlignmentError", "ForcedAlignment", "align_transcript", "alignment_tiers", "espeak_pronunciation",
           "ipa_to_arpabet", "transcript_words"]

SAMPLE_RATE = 16000
FRAME_S = 0.01               # pocketsphinx's frame step
_SILENCE = frozenset({"<sil>", "<s>", "</s>", "SIL", "[NOISE]", "+NOISE+", "+SPN+"})


class AlignmentError(ValueError):
    """A transcript that cannot be aligned to its audio; the message names the source and why."""


@dataclass(frozen=True)
class ForcedAlignment:
    words: tuple[WordInterval, ...]
    phones: tuple[PhoneInterval, ...]


def transcript_words(text: str) -> list[str]:
    """The words of a transcript as the dictionary spells them: lower case, punctuation but apostrophes dropped
    (words of other scripts are kept, so that the error can name them)."""
    return [w.strip("'") for w in re.sub(r"[^\w']+|_", " ", text.lower()).split() if w.strip("'")]


IPA_TO_ARPABET: dict[str, str] = {
    # vowels and diphthongs (espeak-ng en-us)
    "aɪ": "AY", "aʊ": "AW", "eɪ": "EY", "oʊ": "OW", "ɔɪ": "OY", "ɪɹ": "IH R", "ɛɹ": "EH R", "ʊɹ": "UH R",
    "ɑːɹ": "AA R", "ɔːɹ": "AO R", "oːɹ": "AO R", "iː": "IY", "uː": "UW", "ɑː": "AA", "ɔː": "AO", "ɜː": "ER",
    "i": "IY", "ɪ": "IH", "ɛ": "EH", "e": "EH", "æ": "AE", "a": "AA", "ɑ": "AA", "ɒ": "AA", "ɔ": "AO", "o": "OW",
    "ʊ": "UH", "u": "UW", "ʌ": "AH", "ə": "AH", "ɚ": "ER", "ɝ": "ER", "ɐ": "AH", "ᵻ": "IH", "ɜ": "ER",
    # consonants
    "tʃ": "CH", "dʒ": "JH", "p": "P", "b": "B", "t": "T", "d": "D", "k": "K", "ɡ": "G", "g": "G", "f": "F",
    "v": "V", "θ": "TH", "ð": "DH", "s": "S", "z": "Z", "ʃ": "SH", "ʒ": "ZH", "h": "HH", "m": "M", "n": "N",
    "ŋ": "NG", "l": "L", "ɹ": "R", "r": "R", "w": "W", "j": "Y", "ɾ": "T", "ʔ": "T", "x": "HH",
}
"""ARPAbet of the IPA espeak-ng writes for American English: a flap (`ɾ`) and a glottal stop (`ʔ`) are the /t/
(or /d/) they stand for; a syllabic mark, stress and length marks are dropped."""
_IPA_DROP = str.maketrans("", "", "ˈˌ̩̃ ‍‌-")


def ipa_to_arpabet(ipa: str) -> list[str] | None:
    """ARPAbet phones of an IPA string (longest symbols first), or None when a symbol has none."""
    ipa = ipa.translate(_IPA_DROP)
    out, i = [], 0
    keys = sorted(IPA_TO_ARPABET, key=len, reverse=True)
    while i < len(ipa):
        for key in keys:
            if ipa.startswith(key, i):
                out += IPA_TO_ARPABET[key].split()
                i += len(key)
                break
        else:
            if ipa[i] in "ːˑ":
                i += 1
                continue
            return None
    return out or None


def espeak_pronunciation(word: str) -> list[str] | None:
    """ARPAbet of `word` as espeak-ng (en-us) speaks it; None without espeak-ng or for a symbol without ARPAbet."""
    import shutil
    import subprocess

    program = shutil.which("espeak-ng")
    if program is None or not re.fullmatch(r"[a-z']+", word):
        return None
    try:
        done = subprocess.run([program, "-q", "--ipa", "-v", "en-us", word], capture_output=True, text=True,
                              timeout=30, check=True)
    except (OSError, subprocess.SubprocessError):
        return None
    return ipa_to_arpabet(done.stdout.strip())


def _decoder():
    from visemeflow.phonetics.recognise import _pocketsphinx

    ps = _pocketsphinx()
    return ps.Decoder(lm=None, hmm=ps.get_model_path("en-us/en-us"),
                      dict=ps.get_model_path("en-us/cmudict-en-us.dict"), loglevel="FATAL")


def align_transcript(audio: np.ndarray, sample_rate: int, text: str, source: str = "<audio>") -> ForcedAlignment:
    """Word and phone spans of `text` spoken in `audio` (mono float in -1..1 at `sample_rate`, resampled to 16 kHz
    here). :class:`AlignmentError` naming `source` for an empty transcript, a word the dictionary lacks, audio too
    short for it, or no alignment found."""
    words = transcript_words(text)
    if not words:
        raise AlignmentError(f"{source}: the transcript holds no words ({text!r})")
    audio = np.asarray(audio, dtype=np.float32)
    if audio.ndim != 1:
        raise AlignmentError(f"{source}: audio must be mono, got shape {audio.shape}")
    if not np.isfinite(audio).all():
        raise AlignmentError(f"{source}: the audio holds NaN or infinity")
    if sample_rate != SAMPLE_RATE:
        import librosa

        audio = librosa.resample(audio, orig_sr=sample_rate, target_sr=SAMPLE_RATE)
    if len(audio) < int(0.1 * SAMPLE_RATE):
        raise AlignmentError(f"{source}: {len(audio) / SAMPLE_RATE:.3f} s of audio is too short to align")
    decoder = _decoder()
    missing = []
    for word in dict.fromkeys(w for w in words if decoder.lookup_word(w) is None):
        phones = espeak_pronunciation(word)
        if phones is None:
            missing.append(word)
        else:
            decoder.add_word(word, " ".join(phones), True)
    if missing:
        raise AlignmentError(f"{source}: no English pronunciation for {', '.join(repr(w) for w in missing)} "
                             "(neither in pocketsphinx's CMU dictionary nor spelled by espeak-ng)")
    pcm = (np.clip(audio, -1.0, 1.0) * 32767.0).astype(np.int16).tobytes()
    try:
        decoder.set_align_text(" ".join(words))
        _decode(decoder, pcm)                     # the words
    except RuntimeError as exc:
        raise AlignmentError(f"{source}: pocketsphinx found no alignment of the transcript ({exc})") from None
    segments = decoder.seg()
    if segments is None:                          # no path through the transcript's words reached the audio's end
        level = 20 * math.log10(max(float(np.sqrt(np.mean(np.square(audio)))), 1e-10))
        if level < -60:
            raise AlignmentError(f"{source}: pocketsphinx heard none of the transcript's words in the audio: it is "
                                 f"silent ({level:.0f} dBFS RMS)")
        raise AlignmentError(f"{source}: pocketsphinx could not fit the transcript's {len(words)} words to the "
                             "audio: check that the transcript is what is said (no word more or less)")
    spans = [(_word(seg.word), seg.start_frame, seg.end_frame + 1) for seg in segments
             if _word(seg.word) not in _SILENCE]
    heard = [w for w, _, _ in spans]
    if heard != words:
        if heard == words[: len(heard)]:   # the search stopped short of the transcript's end
            last = spans[-1][2] * FRAME_S if spans else 0.0
            raise AlignmentError(f"{source}: pocketsphinx placed {len(heard)} of the transcript's {len(words)} "
                                 f"words and could not hear the rest ({' '.join(words[len(heard):])!r}, after "
                                 f"{last:.2f} s): check that the transcript is what is said, to the end")
        raise AlignmentError(f"{source}: the alignment's words {heard} are not the transcript's {words}")
    out_words = [WordInterval(w, a * FRAME_S, b * FRAME_S) for w, a, b in spans]
    try:
        decoder.set_alignment()
        _decode(decoder, pcm)                     # the phones and states within the words
        out_phones = _phones_of(decoder.get_alignment(), out_words)
    except RuntimeError:
        # the state pass can fail on a long utterance ("Alignment failed in frame N") where the word pass did not:
        # each word's phones are then aligned within its own span, or spread over it when even that fails
        out_phones = [p for i, w in enumerate(out_words) for p in _word_phones(decoder, pcm, w, i)]
    end = len(audio) / SAMPLE_RATE   # pocketsphinx's last frame may reach past the last sample
    out_words = [WordInterval(w.label, min(w.start_s, end), min(w.end_s, end)) for w in out_words]
    out_phones = [PhoneInterval(p.label, min(p.start_s, end), min(p.end_s, end), p.word, p.word_index)
                  for p in out_phones]
    return ForcedAlignment(tuple(out_words), tuple(p for p in out_phones if p.end_s > p.start_s))


def _word(name: str) -> str:
    """A dictionary word without its alternative-pronunciation mark: "the(2)" -> "the"."""
    return re.sub(r"\(\d+\)$", "", name)


def _decode(decoder, pcm: bytes) -> None:
    decoder.start_utt()
    decoder.process_raw(pcm, full_utt=True)
    decoder.end_utt()


def _phones_of(alignment, words: Sequence[WordInterval]) -> list[PhoneInterval]:
    """The phones of a state alignment, each with the word (and its index) whose span holds it."""
    out = []
    for entry in alignment or ():
        for phone in entry:
            if phone.name in _SILENCE:
                continue
            start, end = phone.start * FRAME_S, (phone.start + phone.duration) * FRAME_S
            index = next((i for i, w in enumerate(words) if w.start_s - 1e-6 <= start < w.end_s), None)
            out.append(PhoneInterval(phone.name, start, end, words[index].label if index is not None else None,
                                     index))
    if not out:
        raise RuntimeError("no phones in the state alignment")
    return out


def _word_phones(decoder, pcm: bytes, word: WordInterval, index: int) -> list[PhoneInterval]:
    """One word's phones aligned within its span; spread evenly over it (vowels twice a consonant's share, as
    `wordalign` does) when the aligner cannot place them."""
    a, b = int(round(word.start_s / FRAME_S)), int(round(word.end_s / FRAME_S))
    piece = pcm[a * 2 * SAMPLE_RATE // 100: b * 2 * SAMPLE_RATE // 100]
    try:
        decoder.set_align_text(word.label)
        _decode(decoder, piece)
        decoder.set_alignment()
        _decode(decoder, piece)
        phones = _phones_of(decoder.get_alignment(), [WordInterval(word.label, 0.0, word.end_s - word.start_s)])
        return [PhoneInterval(p.label, p.start_s + word.start_s, p.end_s + word.start_s, word.label, index)
                for p in phones]
    except RuntimeError:
        labels = decoder.lookup_word(word.label).split()
        weights = np.array([2.0 if lab[:1] in "AEIOU" else 1.0 for lab in labels])
        edges = word.start_s + (word.end_s - word.start_s) * np.concatenate([[0.0], np.cumsum(weights)]) / weights.sum()
        return [PhoneInterval(lab, float(edges[k]), float(edges[k + 1]), word.label, index)
                for k, lab in enumerate(labels)]


def alignment_tiers(alignment: ForcedAlignment, duration_s: float) -> Sequence:
    """`words` and `phones` interval tiers covering [0, duration_s] (gaps as empty labels), for
    `textgrid.format_textgrid`."""
    from visemeflow.phonetics.textgrid import Tier

    def tier(name: str, spans) -> Tier:
        items, t = [], 0.0
        for s in spans:
            if s.start_s > t + 1e-9:
                items.append((t, s.start_s, ""))
            items.append((s.start_s, s.end_s, s.label))
            t = s.end_s
        if duration_s > t + 1e-9:
            items.append((t, duration_s, ""))
        return Tier(name, "IntervalTier", 0.0, max(duration_s, t), tuple(items))

    return (tier("words", alignment.words), tier("phones", alignment.phones))
