"""What the viewer sees of the lips: b/p/m closures, f/v lip-teeth contact and vowel opening measured in millimetres on
a character's mesh, per source of curves, with and without the closure rule (issue 24, item 3). Printed, never
asserted.

Run: .venv/bin/python bench/lips.py [--quick] [--threads 2]

The top-viseme scores (`visemeflow.learning.realspeech`, bench/realspeech.py) ask "is MBP the strongest viseme at
this b/p/m phone"; a curve that is the same for any audio can answer yes everywhere. Here the curves drive the
character (`animation.lips.LipProbe.measure`: inner-lip gap of the three inner-lip landmark pairs, lower lip to upper
incisors) and each aligned phone is judged on the mesh (`learning.lipscore.score_lips`):

- b/p/m: closed when the smallest gap within the phone is below 1.5 mm (`CLOSED_MM`); the median of those gaps;
- f/v: contact when the lower lip comes within 2 mm of the upper teeth (`CONTACT_MM`); the median distance;
- open vowels (AA/AH: visemes AAA, AHH): the widest gap within the phone over the character's widest single shape
  (AHH alone), median and max, and the share in 0.6..1.1;
- false closed: vowels whose gap stays below 1.5 mm (a mouth that never opened).

Curves, each raw and through the closure rule (`articulation.close_lips`, what the animation stage applies before
any curves drive a character; `raw` = the curves as the source makes them):
- `procedural`: the JALI-like curves of the alignment (`ProceduralConfig(closure_rule=False)` for raw; the procedural
  stage stores them with the rule);
- `synthetic truth`: the Cohen-Massaro curves of the alignment (`synth.dynamics.generate_ground_truth`): what the demo
  renders and the tracker recovers (tracked curves approximate them at L1 x 100 ~5.7; tracking itself means
  rendering and fitting videos, minutes per utterance, so tracked curves are not measured here);
- `default model`: the shipped learned model (`visemeflow.learning.default_model`, whisper-base-blstm; it trained on the 24
  LJ examples: in-sample there, held out on GRID, Mandarin and praatio);
- `phones`: `predict --model phones`, procedural curves of the phones PocketSphinx recognises in the audio (raw:
  without the rule);
- `mean curve`: the frame-weighted mean of the examples corpus' synthetic truth, the same for any audio (the
  mean-curve baseline).

Characters: the demo character (ICT face, `load_demo_rig()`), and, without `--quick`, a transferred one: the ICT
narrow face of another identity, Loop-subdivided, turned, scaled 1.15 and moved (bench/transfer.py's
`remeshed_face`), with the 16 visemes deformation-transferred onto it (`authoring.transfer.transfer_visemes`, ~30 s).
Its probe: the transfer's 68 landmarks, the carried teeth (the template's `teeth` region, carried rigidly with the
mouth interior) and, as lips, the target vertices nearest the template's `lips` region placed by the known
construction (the transfer returns no regions).

Corpora (alignments from Montreal Forced Aligner / Charsiu / GRID word alignment + CMUdict / praatio's TextGrids,
read by the product's ingestion): the examples corpus (24 LJSpeech + 1 Mandarin), GRID s1 (10 clips), the charsiu
Mandarin utterance (the same AISHELL-3 utterance as the examples' SSB1624, as distributed) and praatio's two
examples. `--quick`: three LJ utterances and the Mandarin one on the demo character only (a CI smoke run).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from domain_gap import grid_corpus  # noqa: E402
from realspeech import FPS, SAMPLE_RATE, SHARED, Utterance, read_corpus  # noqa: E402

from visemeflow.animation.lips import LipProbe  # noqa: E402
from visemeflow.articulation import close_lips  # noqa: E402
from visemeflow.learning.default_model import default_model_path  # noqa: E402
from visemeflow.learning.lipscore import pool_lips, score_lips  # noqa: E402
from visemeflow.learning.train import load_model, predict_curves  # noqa: E402
from visemeflow.procedural.config import ProceduralConfig  # noqa: E402
from visemeflow.procedural.recognised import recognised_curves  # noqa: E402
from visemeflow.rig import load_demo_rig, rig_data_path  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RAW = ProceduralConfig(closure_rule=False)


def read_set(root: Path) -> list[Utterance]:
    """The corpus's utterances with their procedural curves before the lip rules (the rule is applied per row)."""
    return read_corpus(root, procedural=RAW)


def corpora(tmp: Path, quick: bool) -> dict[str, list[Utterance]]:
    examples = read_set(ROOT / "examples" / "corpus")
    if quick:   # three LJ utterances and the Mandarin one: every source and measure, a fraction of the time
        return {"examples (LJ 3 + Mandarin 1)": examples[:3] + examples[-1:]}
    sets = {"examples (LJ 24 + Mandarin 1)": examples}
    sets["GRID s1 (10)"] = read_set(grid_corpus(tmp))
    zh = tmp / "charsiu" / "SSB1624"
    zh.mkdir(parents=True)
    shutil.copyfile(SHARED / "charsiu_mandarin" / "SSB16240001_16k.wav", zh / "SSB16240001.wav")
    shutil.copyfile(SHARED / "charsiu_mandarin" / "SSB16240001.TextGrid", zh / "SSB16240001.TextGrid")
    sets["charsiu Mandarin (1)"] = read_set(zh.parent)
    praatio = SHARED / "praatio_examples"
    folder = tmp / "praatio" / "praatio"
    folder.mkdir(parents=True)
    for name, grid in (("bobby", "bobby_phones.TextGrid"), ("mary", "mary.TextGrid")):
        shutil.copyfile(praatio / f"{name}.wav", folder / f"{name}.wav")
        shutil.copyfile(praatio / grid, folder / f"{name}.TextGrid")
    try:
        sets["praatio examples (2)"] = read_set(folder.parent)
    except Exception as exc:  # noqa: BLE001 -- a reader's refusal is reported, the rest goes on
        print(f"praatio examples left out: {type(exc).__name__}: {exc}")
    return sets


def transferred_probe() -> tuple[LipProbe, str]:
    """The probe of the remeshed identity face with the demo rig's visemes transferred onto it (bench/transfer.py)."""
    from scipy.spatial import cKDTree
    from transfer import REMESHED_IDENTITY, identity_face, placed, remeshed_face

    from visemeflow.authoring.transfer import CARRIED_REGIONS, transfer_visemes

    demo = load_demo_rig()
    modes = np.load(rig_data_path("ict_identities.npz"))["modes"].astype(np.float64)
    started = time.perf_counter()
    vertices, faces, landmarks = remeshed_face(demo, modes)
    result = transfer_visemes(demo, vertices, faces, target_landmarks=landmarks, name="remeshed")
    # carried parts follow the target's vertices, in template order (transfer_visemes)
    carried = np.zeros(len(demo.neutral), bool)
    for region in CARRIED_REGIONS:
        carried[demo.regions[region]] = True
    local = np.full(len(demo.neutral), -1, np.int64)
    local[np.flatnonzero(carried)] = len(vertices) + np.arange(int(carried.sum()))
    teeth = local[demo.regions["teeth"]]
    _, lips = cKDTree(vertices).query(placed(identity_face(demo, modes, REMESHED_IDENTITY))[demo.regions["lips"]])
    probe = LipProbe.from_arrays("remeshed", result.character.neutral, result.character.deltas, result.landmark_ids,
                                 {"teeth": teeth, "lips": np.unique(lips)})
    return probe, (f"transferred character (remeshed identity face, {len(result.character.neutral)} vertices; "
                   f"transfer {time.perf_counter() - started:.0f} s)")


def fmt(x, digits: int = 1, pct: bool = False) -> str:
    if x is None:
        return "-"
    return f"{100 * x:.{digits}f}%" if pct else f"{x:.{digits}f}"


def row(name: str, probe: LipProbe, widest: float, utts: list[Utterance], curves: dict[str, np.ndarray]) -> str:
    scores = []
    for u in utts:
        frames = probe.measure(curves[u.uid])
        scores.append(score_lips(frames.gap_mm, frames.teeth_mm, FPS, u.phones, widest))
    s = pool_lips(scores).summary()
    return (f"| {name} | {s['bilabials']} | {fmt(s['closed'], pct=True)} | {fmt(s['median_gap_mm'], 2)} | "
            f"{s['labiodentals']} | {fmt(s['fv_contact'], pct=True)} | {fmt(s['median_fv_mm'], 2)} | "
            f"{s['open_vowels']} | {fmt(s['vowel_opening'], 2)} | {fmt(s['max_vowel_opening'], 2)} | "
            f"{fmt(s['vowel_in_range'], pct=True)} | {fmt(s['false_closed'], pct=True)} |")


HEADER = ("| curves | b/p/m | closed (< 1.5 mm) | median gap mm | f/v | contact (<= 2 mm) | median f/v mm | AA/AH | "
          "opening median (x AHH) | max | in 0.6-1.1 | vowels never open |\n" + "|---" * 12 + "|")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="4 examples on the demo character only (CI smoke)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        sets = corpora(Path(tmp), args.quick)
    print(f"corpora read in {time.perf_counter() - t_start:.0f} s: "
          + ", ".join(f"{name} {sum(u.n for u in utts) / FPS:.0f} s" for name, utts in sets.items()), flush=True)
    demo = LipProbe.from_rig(load_demo_rig())
    probes = [(demo, "demo character (ICT face)")]
    if not args.quick:
        probes.append(transferred_probe())
        print(probes[-1][1], flush=True)
    examples = next(iter(sets.values()))
    mean = np.concatenate([u.truth for u in examples]).mean(axis=0).astype(np.float32)
    default = load_model(default_model_path())[0]

    t0 = time.perf_counter()
    sources: dict[str, dict[str, dict[str, np.ndarray]]] = {}
    for set_name, utts in sets.items():
        curves = {
            "procedural (alignment)": {u.uid: u.procedural for u in utts},
            "synthetic truth (alignment; what tracking recovers)": {u.uid: u.truth for u in utts},
            "default model (shipped, learned)": {
                u.uid: predict_curves(default, u.audio, SAMPLE_RATE, FPS, n_frames=u.n) for u in utts},
            "phones (recognised, --model phones)": {
                u.uid: recognised_curves(u.audio, SAMPLE_RATE, FPS, u.n, config=RAW) for u in utts},
            "mean curve (baseline: same curve for any audio)": {u.uid: np.tile(mean, (u.n, 1)) for u in utts},
        }
        sources[set_name] = curves
    print(f"curves in {time.perf_counter() - t0:.0f} s", flush=True)

    for probe, character in probes:
        widest = probe.single_shape_gap("AHH")
        neutral = probe.measure(np.zeros((1, 16), np.float32)).gap_mm[0]
        print(f"\n## {character}: widest single shape (AHH) {widest:.1f} mm, MBP alone "
              f"{probe.single_shape_gap('MBP'):.2f} mm, neutral {neutral:.2f} mm")
        for set_name, utts in sets.items():
            print(f"\n### {set_name}\n")
            print(HEADER)
            for label, curves in sources[set_name].items():
                for rule, f in (("raw", lambda c: c), ("closure rule", close_lips)):
                    print(row(f"{label}, {rule}", probe, widest, utts, {k: f(c) for k, c in curves.items()}))
    print(f"\ntotal {time.perf_counter() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
