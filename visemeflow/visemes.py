"""The 16 visemes of the paper (Fig. 2), in the one fixed order every array and table uses."""

from typing import Final

VISEMES: Final[tuple[str, ...]] = (
    "AAA", "AHH", "EH", "FFF", "GK", "IEE", "LNTD", "MBP",
    "OHH", "RRR", "SCHWA", "SSH", "SSS", "TTH", "UUU", "WWW",
)
N_VISEMES: Final[int] = len(VISEMES)
VISEME_INDEX: Final[dict[str, int]] = {name: i for i, name in enumerate(VISEMES)}


def viseme_index(name: str) -> int:
    """Column of `name` in a (frames, 16) curve array; ValueError for a name not among the 16."""
    try:
        return VISEME_INDEX[name]
    except KeyError:
        raise ValueError(f"unknown viseme {name!r}; expected one of {', '.join(VISEMES)}") from None
