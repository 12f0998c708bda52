"""What a training recipe of the learning benches trains with (`make_loss`) and how its model is judged on real
held-out speech (`judge`, `row`, `HEADER`; bench/encoders.py's module docstring says what each figure is).

Apart from the benches' data loaders because it imports nothing but numpy, torch and visemeflow's learning, lip
and rig modules: a machine with torch alone (the lent GPU, bench/whisper_tuning.py) runs it on packed data.
Printed, never asserted.
"""

from __future__ import annotations

import numpy as np
import torch

from visemeflow.animation.lips import LipProbe
from visemeflow.articulation import close_lips
from visemeflow.learning.lipscore import pool_lips, score_lips
from visemeflow.learning.realspeech import compare_curves, pool, score_utterance
from visemeflow.rig import load_demo_rig
from visemeflow.visemes import VISEME_INDEX

FPS = 30.0  # the curves' frame rate in every learning bench (realspeech.FPS)


def make_loss(spec: str):
    """The training objective of a `--losses` word (see the module docstring); None is the paper's L1."""
    kind, _, weight = spec.partition(":")
    if kind == "l1":
        return None
    w = float(weight or 4)
    closure = [VISEME_INDEX["MBP"], VISEME_INDEX["FFF"]]

    def weighted(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        m = mask.to(pred.dtype)[..., None]
        if kind == "closure":
            weights = 1 + w * target[..., closure].sum(-1, keepdim=True)
        elif kind == "sym":
            # closures weigh where either the target or the prediction has them: a closure held into the next
            # phone costs as much as one missed
            weights = 1 + w * torch.maximum(target[..., closure], pred.detach()[..., closure]).sum(-1, keepdim=True)
        elif kind == "activation":
            weights = 1 + w * target
        else:
            raise SystemExit(f"unknown loss {spec!r}: l1, closure:W, sym:W or activation:W")
        return ((pred - target).abs() * weights * m).sum() / (m.sum() * pred.shape[-1]).clamp(min=1)

    return weighted



_PROBE: LipProbe | None = None


def probe() -> LipProbe:
    global _PROBE
    if _PROBE is None:
        _PROBE = LipProbe.from_rig(load_demo_rig())
    return _PROBE


def judge(sets, predict) -> dict:
    """All figures of `predict(audio, n_frames) -> (n, 16)` on `sets` (anything with `held_out` {name: utterances
    with uid, audio, n, phones}, `test_audio`, `test_curves`, `test_jaw` and `floor`: encoders.Sets)."""
    p = probe()
    widest = p.single_shape_gap("AHH")
    utts = [u for us in sets.held_out.values() for u in us]
    curves = {u.uid: predict(u.audio, u.n) for u in utts}
    scores = pool(score_utterance(curves[u.uid], FPS, u.phones) for u in utts)
    per_set = {name: pool(score_utterance(curves[u.uid], FPS, u.phones) for u in us).closure["MBP"]
               for name, us in sets.held_out.items()}
    lips = []
    for u in utts:
        m = p.measure(close_lips(curves[u.uid]))
        lips.append(score_lips(m.gap_mm, m.teeth_mm, FPS, u.phones, widest))
    lip = pool_lips(lips).summary()
    test = predict(sets.test_audio, len(sets.test_curves))
    comparison = compare_curves(test, sets.test_curves, FPS)
    floor = compare_curves(np.tile(sets.floor, (len(sets.test_curves), 1)), sets.test_curves, FPS)
    gap = p.measure(close_lips(test)).gap_mm
    n = min(len(gap), len(sets.test_jaw))
    jaw = float(np.corrcoef(gap[:n], sets.test_jaw[:n])[0, 1]) if np.std(gap[:n]) > 0 else float("nan")
    return {"mbp": scores.closure["MBP"], "fff": scores.closure["FFF"], "false_mbp": scores.false_closure["MBP"],
            "agreement": scores.agreement.overall, "mbp_per_set": per_set, "lips": lip,
            "captured_l1_x100": comparison.l1_x100, "floor_l1_x100": floor.l1_x100, "jaw_r": jaw}


def share(r) -> str:
    return f"{r.hits}/{r.total} ({100 * (r.share or 0):.0f}%)"


HEADER = ("| recipe | MBP closure | false MBP | FFF closure | top-2 agreement | MBP GRID / zh / praatio | "
          "mesh b/p/m closed | median b/p/m gap mm | vowel opening (x AHH) | vowels never open | "
          "FACEGOOD 05 L1 x100 (vs floor) | jaw r | train s |\n" + "|---" * 13 + "|")


def row(name: str, j: dict, seconds: float | None = None) -> str:
    lip = j["lips"]
    per = " / ".join(f"{r.hits}/{r.total}" for r in j["mbp_per_set"].values())
    below = 100 * (1 - j["captured_l1_x100"] / j["floor_l1_x100"])

    def pct(x):
        return "-" if x is None else f"{100 * x:.0f}%"

    def num(x, d=2):
        return "-" if x is None else f"{x:.{d}f}"

    return (f"| {name} | {share(j['mbp'])} | {share(j['false_mbp'])} | {share(j['fff'])} | {share(j['agreement'])} | "
            f"{per} | {pct(lip['closed'])} | {num(lip['median_gap_mm'])} | {num(lip['vowel_opening'])} | "
            f"{pct(lip['false_closed'])} | {j['captured_l1_x100']:.2f} ({below:+.0f}% below) | {j['jaw_r']:.2f} | "
            f"{'-' if seconds is None else f'{seconds:.0f}'} |")
