"""Robustness evaluation (paper Section 5.2, Tables 1-3): validation L1 x 100 on the clean validation set and on
augmented copies of it, and the tables that compare models.

Pure domain code (numpy/torch, no Prefect, no files). The augmented copy of a validation utterance under a
condition is deterministic for (utterance, condition, seed) (:func:`visemeflow.learning.augment.augment_utterance`);
its id traces to the source (``spk/utt__pitch_p2.10``) and for ``speed`` its target curves are resampled by the
same factor (:func:`visemeflow.learning.train.resample_curves`), so frames stay aligned.

Tables follow the paper: one row per model, columns ``validation`` and the four conditions, each condition also
as its ratio to ``validation`` (how much the model degrades). Rows are grouped as in the paper's tables: audio
features with the BLSTM decoder (Table 1), decoders (Table 2), baselines and floors (Table 3). The table itself is
built in :mod:`visemeflow.learning.robustness_table` (no torch), which the HTML dashboard uses too.
"""

from __future__ import annotations

from collections.abc import Sequence

from visemeflow.learning.augment import DEFAULT_CONFIG, AugmentConfig, augment_utterance
from visemeflow.learning.robustness_table import COLUMNS, robustness_table, table_columns, table_csv, table_markdown
from visemeflow.learning.train import SAMPLE_RATE, Example, resample_curves

__all__ = ["COLUMNS", "augment_examples", "robustness_table", "table_columns", "table_csv", "table_markdown"]


def augment_examples(
    examples: Sequence[Example], condition: str, seed: int = 0, config: AugmentConfig = DEFAULT_CONFIG
) -> list[Example]:
    """The augmented copy of each (16 kHz) example under ``condition``: new id, audio, and curves (resampled for speed)."""
    out = []
    for ex in examples:
        aug = augment_utterance(ex.audio, SAMPLE_RATE, ex.utterance_id, condition, seed, config)
        out.append(Example(aug.utterance_id, aug.audio, resample_curves(ex.curves, aug.time_factor), ex.fps))
    return out
