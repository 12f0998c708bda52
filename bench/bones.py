"""Bone animation against blendshape animation on the demo rig (printed, never asserted; issue 16).

For each bone count (default 8, 16, 32, 64): the SSDR solve of the demo rig's 16 visemes (`bones.solve_bones`,
wall and CPU seconds: run with OMP_NUM_THREADS=1 for one core), then the vertex error of the bone animation (blend,
then linear blend skinning) against the blendshape animation, in millimetres RMS (the rig is in centimetres:
x 10), over the rig's "face" and "lips" regions (and all vertices, eyes, teeth and mouth interior included):
- per viseme at full weight (one-hot curves), and the mean over the 16;
- over real sequences: the synthetic true curves of examples/corpus/LJ (their alignments through the ingest stage
  and `generate_ground_truth`, as bench/realspeech.py builds them), every frame of every utterance pooled.

    OMP_NUM_THREADS=1 .venv/bin/python bench/bones.py [--bones 8 16 32 64] [--iterations 5] [--init-iterations 20]
        [--utterances 24] [--no-lock]

Each bone count is measured twice from one SSDR solve, side by side: SSDR's fit as it is (`lip_share=0`), and after
the refit that puts `--lip-share` of the fit's weight on the mouth (`bones.refine_for_lips`, the default of
`solve_bones`); the ratio columns are refit / SSDR, and the MBP column is the inner lips' gap at MBP's full weight
(the blendshape's in the header).

The eyes, teeth and mouth interior are printed per region too: with the default locked parts (`solve_bones`'s
`lock_parts`) the eyes and the teeth get bones of their own; `--no-lock` is plain SSDR over every vertex.

Targets (issue 16): lips below 0.5 mm RMS at 64 bones; SSDR under 60 s for 64 bones on one core.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from realspeech import read_corpus  # noqa: E402

from visemeflow.animation.bones import LIP_SHARE, bone_animation, lip_emphasis, refine_for_lips, solve_bones, \
    viseme_meshes
from visemeflow.animation.lips import inner_lip_pairs, pair_gap_mm
from visemeflow.rig.character import character_from_rig
from visemeflow.rig import load_demo_rig
from visemeflow.visemes import VISEMES

ROOT = Path(__file__).resolve().parent.parent
FPS = 30.0


def corpus_curves(limit: int) -> dict[str, np.ndarray]:
    """The synthetic true curves (T, 16) of examples/corpus/LJ's first `limit` utterances, by utterance id."""
    utterances = [u for u in read_corpus(ROOT / "examples" / "corpus") if u.speaker == "LJ"][:limit]
    return {u.uid: u.truth for u in utterances}


def squared_errors(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(T, V) squared vertex distances in mm^2 (mesh in cm)."""
    return ((a - b) ** 2).sum(axis=-1) * 100.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bones", type=int, nargs="+", default=[8, 16, 32, 64])
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--init-iterations", type=int, default=20, help="Dem Bones' bone-initialisation iterations")
    parser.add_argument("--utterances", type=int, default=24)
    parser.add_argument("--lip-share", type=float, default=LIP_SHARE, help="the mouth's share of the refit")
    parser.add_argument("--no-lock", action="store_true",
                        help="plain SSDR over every vertex (no static / rigid bones for the eyes and teeth)")
    args = parser.parse_args()

    rig = load_demo_rig()
    character = character_from_rig(rig)
    regions = {"face": rig.regions["face"], "lips": rig.regions["lips"], "eyes": rig.regions["eyes"],
               "teeth": rig.regions["teeth"], "mouth interior": rig.regions["mouth_interior"],
               "all": np.arange(rig.n_vertices)}
    size = character.neutral.max(axis=0) - character.neutral.min(axis=0)
    print(f"demo rig: {rig.n_vertices} vertices, {len(rig.faces)} triangles, extent {size.round(2).tolist()} "
          f"(units: cm, a face ~{size[1]:.0f} tall), face {len(regions['face'])} / lips {len(regions['lips'])} "
          f"vertices; OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}, {os.cpu_count()} CPUs")
    start = time.perf_counter()
    sequences = corpus_curves(args.utterances)
    total = sum(len(c) for c in sequences.values())
    print(f"sequences: {len(sequences)} LJ utterances of examples/corpus, {total} frames at {FPS:g} fps "
          f"({total / FPS:.1f} s; curves built in {time.perf_counter() - start:.1f} s)")
    targets = viseme_meshes(character)
    deltas = character.deltas.astype(np.float64)
    still = {k: float(np.sqrt(squared_errors(character.neutral[None], targets)[:, ids].mean()))
             for k, ids in regions.items()}
    print(f"for scale, the visemes' own motion (neutral held): face {still['face']:.2f}, lips {still['lips']:.2f} "
          f"mm RMS at full weight\n")

    lips_ids = inner_lip_pairs(character).ravel()
    mbp = VISEMES.index("MBP")

    def mbp_gap(vertices: np.ndarray) -> float:
        return float(pair_gap_mm(vertices[mbp, lips_ids].reshape(3, 2, 3), character.mm_per_unit))

    print(f"MBP's inner-lip gap with the blendshapes: {mbp_gap(targets):.2f} mm\n")
    emphasis = lip_emphasis(character, args.lip_share)
    summary = []
    per_viseme = {}
    for n_bones in args.bones:
        plain = solve_bones(character, n_bones, iterations=args.iterations, init_iterations=args.init_iterations,
                            lock_parts=not args.no_lock, lip_share=0.0)
        started, cpu = time.perf_counter(), time.process_time()
        free = np.array([n.startswith("bone_") for n in plain.bone_names])
        refit = refine_for_lips(plain, targets, emphasis, free)
        refit_wall, refit_cpu = time.perf_counter() - started, time.process_time() - cpu
        for label, bones in (("SSDR", plain), ("refit", refit)):
            posed = bone_animation(bones, np.eye(16))
            full = squared_errors(posed, targets)            # (16, V)
            per_viseme[(n_bones, label)] = {k: np.sqrt(full[:, regions[k]].mean(axis=1)) for k in ("face", "lips")}
            sums = {k: 0.0 for k in regions}
            worst_lips = 0.0
            for curves in sequences.values():
                c = np.asarray(curves, np.float64)
                blend = character.neutral[None] + (c @ deltas.reshape(len(deltas), -1)).reshape(len(c), -1, 3)
                e = squared_errors(bone_animation(bones, c), blend)
                for k, ids in regions.items():
                    sums[k] += float(e[:, ids].mean(axis=1).sum())
                worst_lips = max(worst_lips, float(np.sqrt(e[:, regions["lips"]].mean(axis=1)).max()))
            seq = {k: np.sqrt(v / total) for k, v in sums.items()}
            full_regions = {k: float(np.sqrt(full[:, ids].mean())) for k, ids in regions.items()}
            print(f"{n_bones} bones, {label} ({', '.join(n for n in bones.bone_names if not n.startswith('bone_')) or 'none locked'}"
                  f"): full weight mm RMS by region: "
                  + ", ".join(f"{k} {v:.3f}" for k, v in full_regions.items()), flush=True)
            row = dict(bones=bones.n_bones, label=label, wall=plain.solve_seconds + (refit_wall if label == "refit" else 0),
                       cpu=plain.solve_cpu_seconds + (refit_cpu if label == "refit" else 0),
                       full_face=float(np.sqrt(full[:, regions["face"]].mean())),
                       full_lips=float(np.sqrt(full[:, regions["lips"]].mean())),
                       full_all=float(np.sqrt(full.mean())), seq_face=seq["face"], seq_lips=seq["lips"],
                       seq_all=seq["all"], worst_lips=worst_lips, mbp=mbp_gap(posed))
            summary.append(row)
            print(f"{n_bones} bones, {label}: {row['wall']:.1f} s wall, {row['cpu']:.1f} s CPU; full weight face "
                  f"{row['full_face']:.3f} lips {row['full_lips']:.3f}; sequences face {row['seq_face']:.3f} lips "
                  f"{row['seq_lips']:.3f} (worst frame lips {worst_lips:.3f}) mm RMS; MBP gap {row['mbp']:.2f} mm",
                  flush=True)

    print("\n| bones | fit | wall s | CPU s | full weight face | full weight lips | full weight all vertices | "
          "sequences face | sequences lips | sequences all | worst frame lips | MBP gap mm | lips refit / SSDR | "
          "face refit / SSDR |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for k, r in enumerate(summary):
        base = summary[k - 1] if r["label"] == "refit" else r
        print(f"| {r['bones']} | {r['label']} | {r['wall']:.1f} | {r['cpu']:.1f} | {r['full_face']:.3f} | "
              f"{r['full_lips']:.3f} | {r['full_all']:.3f} | {r['seq_face']:.3f} | {r['seq_lips']:.3f} | "
              f"{r['seq_all']:.3f} | {r['worst_lips']:.3f} | {r['mbp']:.2f} | {r['seq_lips'] / base['seq_lips']:.2f} | "
              f"{r['seq_face'] / base['seq_face']:.2f} |")
    print("\nper viseme at full weight, lips mm RMS:")
    print("| bones | " + " | ".join(VISEMES) + " |")
    print("|---" * (len(VISEMES) + 1) + "|")
    for (n_bones, label), figures in per_viseme.items():
        print(f"| {n_bones} {label} | " + " | ".join(f"{x:.2f}" for x in figures["lips"]) + " |")
    print("\nper viseme at full weight, face mm RMS:")
    for (n_bones, label), figures in per_viseme.items():
        print(f"| {n_bones} {label} | " + " | ".join(f"{x:.2f}" for x in figures["face"]) + " |")


if __name__ == "__main__":
    sys.exit(main())
