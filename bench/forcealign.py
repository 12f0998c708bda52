"""How close the built-in English forced aligner (`visemeflow.phonetics.forcealign`, pocketsphinx) puts phones to
the Montreal Forced Aligner's, on the 24 LJSpeech utterances of `../shared/data/ljspeech_mfa` (transcripts from its
metadata.csv, MFA's TextGrids as the reference). Printed, never asserted.

Run: .venv/bin/python bench/forcealign.py [--utterances 24]

Phones are compared in order where both aligners chose the same sequence for a word (ARPAbet without stress;
MFA's dictionary and pocketsphinx's CMU dictionary mostly agree); rows: the share of phone boundaries within 20 and
50 ms of MFA's, their median and 90th-percentile distance, and for the b/p/m phones the share whose MFA span
overlaps ours by at least half of the shorter; also the spread-over-words baseline (`wordalign`, MFA's own word
spans split by fixed weights: what GRID-style word timings give) and the aligner's seconds per second of audio.
"""

from __future__ import annotations

import re
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data" / "ljspeech_mfa"

from visemeflow.ingest.audio import read_audio  # noqa: E402
from visemeflow.phonetics.forcealign import align_transcript  # noqa: E402
from visemeflow.phonetics.textgrid import parse_textgrid_bytes  # noqa: E402
from visemeflow.phonetics.types import WordInterval  # noqa: E402
from visemeflow.phonetics.wordalign import load_cmudict, spread_words_to_phones  # noqa: E402

SILENCE = {"", "sil", "sp", "spn", "<eps>"}


def mfa(grid_path: Path) -> tuple[list[tuple[str, float, float]], list[WordInterval]]:
    grid = parse_textgrid_bytes(grid_path.read_bytes(), str(grid_path))
    phones = [(re.sub(r"\d", "", t).upper(), a, b) for a, b, t in grid.tier(("phones",)).items
              if t.strip().lower() not in SILENCE]
    words = [WordInterval(t, a, b) for a, b, t in grid.tier(("words",)).items if t.strip().lower() not in SILENCE]
    return phones, words


def matched(ours: list[tuple[str, float, float]], ref: list[tuple[str, float, float]]):
    """Pairs of (ours, ref) phones aligned by label sequence (difflib's longest matching blocks)."""
    import difflib

    sm = difflib.SequenceMatcher(a=[p[0] for p in ours], b=[p[0] for p in ref], autojunk=False)
    for block in sm.get_matching_blocks():
        for k in range(block.size):
            yield ours[block.a + k], ref[block.b + k]


def main() -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--utterances", type=int, default=24, help="the first N utterances (24: all)")
    args = parser.parse_args()
    texts = {line.split("|")[0]: line.split("|")[2] for line in (DATA / "metadata.csv").read_text().splitlines()}
    rows = {"pocketsphinx (forcealign)": ([], [], 0, 0), "words spread (wordalign, MFA's word spans)": ([], [], 0, 0)}
    seconds = audio_s = 0.0
    skipped = 0
    lexicon = load_cmudict()
    for grid_path in sorted((DATA / "TextGrid").glob("*.TextGrid"))[: args.utterances]:
        uid = grid_path.stem
        audio, rate = read_audio(DATA / "wav" / f"{uid}.wav")
        ref, ref_words = mfa(grid_path)
        started = time.perf_counter()
        done = align_transcript(audio, rate, texts[uid], source=uid)
        seconds += time.perf_counter() - started
        audio_s += len(audio) / rate
        ours = [(p.label, p.start_s, p.end_s) for p in done.phones]
        try:
            spread = [(re.sub(r"\d", "", p.label).upper(), p.start_s, p.end_s)
                      for p in spread_words_to_phones(ref_words, lexicon, uid, 2.0)]
        except ValueError:   # a word CMUdict lacks: that utterance is left out of the baseline's row
            spread, skipped = None, skipped + 1
        for name, candidate in zip(rows, (ours, spread)):
            if candidate is None:
                continue
            bounds, bpm, n_pairs, n_ref = rows[name]
            pairs = list(matched(candidate, ref))
            for (_, a0, a1), (label, b0, b1) in pairs:
                bounds += [abs(a0 - b0), abs(a1 - b1)]
                if label in ("B", "P", "M"):
                    overlap = min(a1, b1) - max(a0, b0)
                    bpm.append(overlap >= 0.5 * min(a1 - a0, b1 - b0))
            rows[name] = (bounds, bpm, n_pairs + len(pairs), n_ref + len(ref))
    print("| phones of | matched phones | boundaries within 20 ms | within 50 ms | median ms | p90 ms | "
          "b/p/m overlapping MFA's |\n|---|---|---|---|---|---|---|")
    for name, (bounds, bpm, n_pairs, n_ref) in rows.items():
        b = np.array(bounds)
        print(f"| {name} | {n_pairs}/{n_ref} | {100 * np.mean(b <= 0.02):.0f}% | {100 * np.mean(b <= 0.05):.0f}% | "
              f"{1000 * np.median(b):.0f} | {1000 * np.percentile(b, 90):.0f} | {sum(bpm)}/{len(bpm)} |")
    print(f"\n{skipped} utterance(s) left out of the spread baseline (a word CMUdict lacks)")
    print(f"aligner: {seconds:.1f} s for {audio_s:.0f} s of audio (real-time factor {seconds / audio_s:.3f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
