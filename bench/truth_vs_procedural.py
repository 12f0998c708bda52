"""How far the procedural curves are from the synthetic ground truth, per corpus (printed, never asserted).

Run: .venv/bin/python bench/truth_vs_procedural.py [CORPUS]   (default: examples/corpus)

For every utterance: the true curves (Cohen-Massaro dynamics, `visemeflow.synth.dynamics`) and the procedural
curves (JALI-like rules) from the same phones at 25 fps, then L1 x 100 between them and how often the top viseme
agrees on frames where the procedural curves are active (max > 0.3). The two are different model families on
purpose: the procedural curves should be a plausible but imperfect guess of the truth.
"""

import sys
import time
from pathlib import Path

import numpy as np

from visemeflow.ingest import IngestConfig, discover_corpus, ingest_utterance
from visemeflow.phonetics.types import VisemeSegment
from visemeflow.procedural import generate_procedural_curves
from visemeflow.synth.dynamics import generate_ground_truth
from visemeflow.timebase import frame_count

FPS = 25.0


def main() -> int:
    corpus = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[1] / "examples" / "corpus"
    l1, agree, t_truth, t_proc, frames = [], [], 0.0, 0.0, 0
    for entry in discover_corpus(corpus).entries:
        result = ingest_utterance(entry, IngestConfig())
        segments = [VisemeSegment(p["viseme"], p["start_s"], p["end_s"], p["word_index"], p["phoneme"] or "")
                    for p in result.phones if p["viseme"] is not None]
        n = frame_count(result.utterance["duration_s"], FPS)
        t0 = time.perf_counter()
        truth = generate_ground_truth(segments, n, FPS, entry.speaker, entry.utterance_id)
        t1 = time.perf_counter()
        proc = generate_procedural_curves(segments, n, FPS)
        t2 = time.perf_counter()
        t_truth, t_proc, frames = t_truth + t1 - t0, t_proc + t2 - t1, frames + n
        active = proc.max(axis=1) > 0.3
        l1.append(np.abs(truth - proc).mean() * 100)
        agree.append((truth.argmax(axis=1) == proc.argmax(axis=1))[active].mean())
    print(f"corpus {corpus}: {len(l1)} utterances, {frames} frames at {FPS:g} fps")
    print(f"{'metric':<52}{'value':>10}")
    print(f"{'L1 x 100, procedural vs truth (mean over utterances)':<52}{np.mean(l1):>10.2f}")
    print(f"{'top viseme agrees on active frames':<52}{np.mean(agree):>10.1%}")
    print(f"{'truth generation (frames/s)':<52}{frames / t_truth:>10,.0f}")
    print(f"{'procedural generation, side by side (frames/s)':<52}{frames / t_proc:>10,.0f}")
    print(f"{'  procedural / truth speed':<52}{t_truth / t_proc:>9.1f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
