"""Plain records for alignments: time spans in seconds, labels as written in the source file."""

from dataclasses import dataclass, field

Seconds = float


@dataclass(frozen=True, slots=True)
class PhoneInterval:
    """One labelled span of a phone tier, as read from the alignment file."""

    label: str
    start_s: Seconds
    end_s: Seconds
    word: str | None = None
    word_index: int | None = None

    @property
    def duration_s(self) -> Seconds:
        return self.end_s - self.start_s


@dataclass(frozen=True, slots=True)
class WordInterval:
    """One labelled span of a word tier (or a GRID .align line)."""

    label: str
    start_s: Seconds
    end_s: Seconds


@dataclass(frozen=True, slots=True)
class Alignment:
    """Phones (and words when the file has them) of one utterance; `end_s` is the file's xmax."""

    phones: tuple[PhoneInterval, ...]
    words: tuple[WordInterval, ...] = field(default_factory=tuple)
    start_s: Seconds = 0.0
    end_s: Seconds = 0.0
    source: str = ""


@dataclass(frozen=True, slots=True)
class VisemeSegment:
    """A span during which one viseme is articulated: the unit the procedural rules work on.

    `word_index` groups segments of one word (for look-ahead); None for phones outside any word.
    """

    viseme: str
    start_s: Seconds
    end_s: Seconds
    word_index: int | None = None
    phoneme: str = ""

    @property
    def duration_s(self) -> Seconds:
        return self.end_s - self.start_s
