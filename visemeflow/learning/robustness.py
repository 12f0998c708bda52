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

Real-speech metrics (:mod:`visemeflow.learning.realspeech`): on validation utterances with a phone alignment, the
closure recall of MBP and FFF and the activation agreement of the model's curves, on clean audio and on each
augmented copy (the phones of a ``speed`` copy are scaled by its time factor, as its curves are resampled). The
curves judged are those `predict` writes: :func:`~visemeflow.learning.train.predict_curves` clipped to [0, 1], as
many frames as the example's target curves (the frames `evaluate` scores). They need no curve truth.

Lip metrics (:mod:`visemeflow.learning.lipscore`): the same curves as a character shows them, judged on its mesh in
millimetres. The geometry lives in `animation/` (which this package may not import): :func:`lip_evaluation` takes
the measuring function (`LipProbe.measure`, curves -> per-frame gap and lip-to-teeth distance) from the caller (the
`evaluate` task) and applies the closure rule (`visemeflow.articulation.close_lips`) first, as animation does.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np
from torch import nn

from visemeflow.articulation import close_lips
from visemeflow.learning.augment import DEFAULT_CONFIG, AugmentConfig, augment_utterance
from visemeflow.learning.lipscore import LipScores, pool_lips, score_lips
from visemeflow.learning.realspeech import Phone, RealSpeechScores, pool, score_utterance
from visemeflow.learning.robustness_table import COLUMNS, robustness_table, table_columns, table_csv, table_markdown
from visemeflow.learning.train import SAMPLE_RATE, Example, predict_curves, resample_curves

__all__ = ["COLUMNS", "augment_examples", "example_curves", "lip_evaluation", "realspeech_evaluation",
           "robustness_table", "table_columns", "table_csv", "table_markdown"]

# (T, 16) curves -> ((T,) inner-lip gap mm, (T,) lower-lip-to-upper-teeth mm or None): `LipProbe.measure` unpacked
LipMeasure = Callable[[np.ndarray], tuple[np.ndarray, "np.ndarray | None"]]


def augment_examples(
    examples: Sequence[Example], condition: str, seed: int = 0, config: AugmentConfig = DEFAULT_CONFIG
) -> list[Example]:
    """The augmented copy of each (16 kHz) example under ``condition``: new id, audio, and curves (resampled for speed)."""
    out = []
    for ex in examples:
        aug = augment_utterance(ex.audio, SAMPLE_RATE, ex.utterance_id, condition, seed, config)
        out.append(Example(aug.utterance_id, aug.audio, resample_curves(ex.curves, aug.time_factor), ex.fps))
    return out


def example_curves(model: nn.Module, example: Example) -> np.ndarray:
    """The curves `predict` would write for the example's (16 kHz) audio, as many frames as its target curves."""
    return predict_curves(model, example.audio, SAMPLE_RATE, example.fps, n_frames=len(example.curves))


def realspeech_evaluation(
    model: nn.Module, examples: Sequence[Example], phones: Mapping[str, Sequence[Phone]],
    curves: Mapping[str, np.ndarray] | None = None,
) -> tuple[RealSpeechScores, dict[str, RealSpeechScores]]:
    """(pooled, per utterance) closure recall and activation agreement of the model on the examples that have
    phones (``phones``: utterance id -> phones on that example's own time axis); the others are not scored.
    ``curves`` (utterance id -> :func:`example_curves`) reuses predictions already made."""
    curves = curves or {}
    per = {ex.utterance_id: score_utterance(curves[ex.utterance_id] if ex.utterance_id in curves
                                            else example_curves(model, ex), ex.fps, phones[ex.utterance_id])
           for ex in examples if ex.utterance_id in phones}
    return pool(per.values()), per


def lip_evaluation(
    curves: Mapping[str, np.ndarray], fps: Mapping[str, float], phones: Mapping[str, Sequence[Phone]],
    measure: LipMeasure, widest_mm: float, closure_rule: bool = True,
) -> tuple[LipScores, dict[str, LipScores]]:
    """(pooled, per utterance) lip scores of predicted curves (utterance id -> (T, 16)) on a character's mesh.

    ``measure`` maps curves to per-frame millimetres on the character (``LipProbe.measure``, unpacked), ``widest_mm``
    is its widest single shape's gap (``LipProbe.single_shape_gap("AHH")``). With ``closure_rule`` (the default:
    what a character shows, the animation stage applies it to curves of every source) the curves pass through
    :func:`visemeflow.articulation.close_lips` first; without it, the model's own curves are judged. Utterances
    without phones are not scored."""
    per = {}
    for uid, c in curves.items():
        if uid not in phones:
            continue
        gap, teeth = measure(close_lips(c) if closure_rule else np.asarray(c, np.float32))
        per[uid] = score_lips(gap, teeth, fps[uid], phones[uid], widest_mm)
    return pool_lips(per.values()), per
