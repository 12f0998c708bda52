"""Benchmark: ingestion + procedural viseme curves on a scaled corpus, bare and as a Prefect flow, vs OpenFaceFX.

Run:  .venv/bin/python bench/ingest_procedural.py [--utterances N] [--keep DIR] [--profile]

It prints one table (metric, value, target, met?) and never asserts anything: the exit status is 0 whatever
the figures are. What it measures:

1. Corpus. N utterances (default 12,000) over `--speakers` speakers (default 40) are laid out as
   `<speaker>/<name>.TextGrid + .wav` in a temp folder (or `--keep DIR`). Utterance i is template
   i mod 25 of the demo corpus `examples/corpus` (24 English LJSpeech utterances with ARPAbet MFA
   TextGrids, 1 Mandarin AISHELL-3 utterance with a pinyin TextGrid): the TextGrid is copied byte for
   byte and the wav is a hard link to the demo file, so the corpus costs almost no disk (copies of one
   template therefore share a content hash, which is harmless: hashes are only compared per utterance
   id). The real audio total is printed. Because the wavs of one template share an inode, the content
   hashing of discovery reads them from the page cache: that row measures hashing, not disk reads.

2. Pure compute (no Prefect, one process, one utterance at a time, shard by shard in the order the flow
   groups them), each step timed on its own with time.perf_counter:
     discovery   `discover_corpus(root)`: listing the folders and hashing every file (blake2b);
     ingestion   `ingest_utterance(entry, IngestConfig())` per entry: TextGrid parse, audio header,
                 checks, phone -> viseme mapping;
     segments    phone rows (`IngestedUtterance.phones` dicts) -> `VisemeSegment`s, visemeless rows skipped;
     generation  `generate_procedural_curves(segments, n_frames, fps, ProceduralConfig())`;
     writes      `Store.write_curves(curves_table(uid, "procedural", "jali", curves, fps))` (one zstd
                 Parquet file per utterance, written atomically; each shard's files flushed once at its end,
                 `atomic.group_sync`, as the procedural task does: that flush is counted with the writes).
   Then the curve writes alone side by side: as many 200-frame files written with an fsync each (the faithful
   path) and in 8 groups of one flush each, interleaved group by group.
   Their sum is the "pure compute" the flow is compared with. The Parquet writes of the `utterances` and
   `phones` shard tables are timed too but shown apart (the flow does them; the targets do not count them).

3. The Prefect flow. `pipeline_flow(PipelineParams(corpus=root, store=..., n_shards=8))` inside
   `prefect_api.prefect_server()` (a throw-away local server, or the one VISEMEFLOW_BENCH_API_URL names; its
   start-up is not timed, only the flow call).
   Overhead ratio = flow wall time / pure compute of step 2. The flow is then called a second time on the
   unchanged corpus (every shard a cache hit) and timed again.

4. The peer, OpenFaceFX (MIT, numpy only; `pip install openfacefx` into the venv: it is not a project
   dependency, and the script installs it after saying so when it is missing, unless --no-install).
   Its path from phone timings to per-frame viseme weights is
     `openfacefx.load_mfa_textgrid(path)` -> list[PhonemeSegment] (regex parse of the "phones" tier of a
     long-format MFA TextGrid), then
     `openfacefx.build_viseme_curves(segments, fps=fps)` -> (times, matrix[frames, 15]): the dense
     dominance-function (Cohen-Massaro) blend with closure enforcement, before its keyframe reduction
     (`reduce_to_track`, which `generate_from_alignment` adds and we leave out: we produce dense frames).
   It reads only ARPAbet long-format TextGrids (the Mandarin template is a short-format pinyin TextGrid it
   cannot parse), so both sides are compared on the same English utterances only, at the same fps, each
   side counting the frames it produced. Both sides are run again here, side by side for each utterance
   (ours, then the peer's), so that they run under the same conditions; the ingest work repeated for this
   is not part of step 2's figures. Two rows:
     excl. parsing  ours: generate_procedural_curves on prebuilt segments;
                    peer: build_viseme_curves on prebuilt PhonemeSegments;
     incl. parsing  ours: ingest_utterance (TextGrid parse + audio header + checks + mapping) + segments +
                    generation; peer: load_mfa_textgrid + build_viseme_curves.
   An extra row times the peer's opt-in JALI mode (`CoartParams(jali=True)`), the closest to our rules.

`--profile` runs step 2 under cProfile instead (steps 3 and 4 skipped) and prints the top functions.
Memory stays bounded: the phone rows of one shard at a time are held, never the whole corpus's.
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import io
import os
import pstats
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

# Prefect reads these when imported (only the flow step imports it).
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from report import met, print_table  # noqa: E402  (bench/report.py)

from visemeflow.atomic import group_sync  # noqa: E402

DEMO_CORPUS = REPO / "examples" / "corpus"
N_SHARDS = 8
VARIANT = "jali"

TARGET_PURE_S = 60.0          # ingest + procedural of 12,000 utterances, excluding Prefect start-up
TARGET_PURE_N = 12000
TARGET_OVERHEAD = 1.5
TARGET_PEER_RATIO = 3.0


# ---- corpus --------------------------------------------------------------------------------------
def build_corpus(root: Path, n: int, n_speakers: int) -> str:
    """Lay out n utterances over n_speakers speakers; returns how the wavs were linked."""
    templates = sorted(DEMO_CORPUS.glob("*/*.TextGrid"))
    pairs = [(tg, tg.with_suffix(".wav")) for tg in templates if tg.with_suffix(".wav").exists()]
    if not pairs:
        raise SystemExit(f"no TextGrid + wav pairs under {DEMO_CORPUS}")
    link = "hard links"
    for i in range(n):
        tg, wav = pairs[i % len(pairs)]
        speaker = f"spk{i % n_speakers:03d}"
        folder = root / speaker
        folder.mkdir(parents=True, exist_ok=True)
        stem = f"{speaker}_{i:06d}_{tg.stem}"
        shutil.copyfile(tg, folder / f"{stem}.TextGrid")
        target = folder / f"{stem}.wav"
        try:
            os.link(wav, target)
        except OSError:  # another file system: a symlink costs no disk either
            os.symlink(wav, target)
            link = "symlinks"
    return link


# ---- pure compute --------------------------------------------------------------------------------
@dataclass
class Pure:
    n: int = 0
    rejected: int = 0
    discovery_s: float = 0.0
    ingest_s: list[float] = field(default_factory=list)
    segments_s: list[float] = field(default_factory=list)
    generate_s: list[float] = field(default_factory=list)
    write_s: list[float] = field(default_factory=list)
    frames: list[int] = field(default_factory=list)
    english: list[bool] = field(default_factory=list)
    entries: list = field(default_factory=list)
    fps: list[float] = field(default_factory=list)
    audio_s: float = 0.0
    tables_s: float = 0.0
    flush_s: float = 0.0   # each shard's one flush of its curve files (atomic.group_sync), counted with the writes
    writes_each_s: float = 0.0    # curve_writes_side_by_side: n files fsynced one by one ...
    writes_group_s: float = 0.0   # ... and one flush per shard

    @property
    def compute_s(self) -> float:
        return (self.discovery_s + sum(self.ingest_s) + sum(self.segments_s) + sum(self.generate_s)
                + sum(self.write_s) + self.flush_s)


def curve_writes_side_by_side(work: Path, n: int, shards: int = N_SHARDS, frames: int = 200) -> tuple[float, float]:
    """Seconds to write `n` one-utterance curve files (`frames` frames, 30 fps) into a fresh store, each file
    fsynced on its own (the faithful path) and in `shards` groups of one flush each (`atomic.group_sync`, what the
    procedural task does), interleaved group by group so both see the same disk."""
    from visemeflow.schemas import curves_table
    from visemeflow.storage import Store

    rng = np.random.default_rng(0)
    tables = [curves_table(f"s{i % 40:02d}/u{i:06d}", "procedural", VARIANT,
                           rng.random((frames, 16)).astype(np.float32), 30.0) for i in range(n)]
    stores = {"each": Store(work / "writes-each"), "group": Store(work / "writes-group")}
    seconds = {"each": 0.0, "group": 0.0}
    for part in np.array_split(np.arange(n), shards):
        for how, store in stores.items():
            t = time.perf_counter()
            with group_sync() if how == "group" else contextlib.nullcontext():
                for i in part:
                    store.write_curves(tables[i], provenance="bench", fps=30.0)
            seconds[how] += time.perf_counter() - t
    return seconds["each"], seconds["group"]


def run_pure(root: Path, store_root: Path) -> Pure:
    """Step 2: per-utterance timings of every step (and what the peer needs to run on the same files)."""
    from visemeflow.ingest import IngestConfig, IngestError, discover_corpus, ingest_utterance
    from visemeflow.phonetics.types import VisemeSegment
    from visemeflow.procedural import ProceduralConfig, generate_procedural_curves
    from visemeflow.schemas import PHONES, UTTERANCES, C, curves_table, shard_of, table_from_rows
    from visemeflow.storage import Store

    clock = time.perf_counter
    out = Pure()
    store = Store(store_root)
    config, pconfig = IngestConfig(), ProceduralConfig()
    t = clock()
    found = discover_corpus(root)
    out.discovery_s = clock() - t

    shards: dict[int, list] = {}
    for entry in found.entries:
        shards.setdefault(shard_of(entry.utterance_id, N_SHARDS), []).append(entry)

    for shard in sorted(shards):
        utterance_rows, phone_rows = [], []
        with contextlib.ExitStack() as block:   # as the procedural task: the shard's curve files flushed once
            block.enter_context(group_sync())
            for entry in shards[shard]:
                t0 = clock()
                try:
                    result = ingest_utterance(entry, config)
                except IngestError:
                    out.rejected += 1
                    continue
                t1 = clock()
                u = result.utterance
                segments = [
                    VisemeSegment(p[C.VISEME], p[C.START_S], p[C.END_S], p[C.WORD_INDEX], p[C.PHONEME] or "")
                    for p in result.phones if p[C.VISEME] is not None
                ]
                segments.sort(key=lambda s: s.start_s)
                t2 = clock()
                fps, n_frames = float(u[C.FPS]), int(u[C.N_FRAMES])
                curves = generate_procedural_curves(segments, n_frames, fps, pconfig)
                t3 = clock()
                store.write_curves(curves_table(entry.utterance_id, "procedural", VARIANT, curves, fps),
                                   provenance=f"bench:{entry.content_hash}", fps=fps)
                t4 = clock()
                out.ingest_s.append(t1 - t0)
                out.segments_s.append(t2 - t1)
                out.generate_s.append(t3 - t2)
                out.write_s.append(t4 - t3)
                out.frames.append(n_frames)
                out.fps.append(fps)
                out.audio_s += float(u[C.DURATION_S])
                is_english = u[C.INVENTORY] == "arpabet"
                out.english.append(is_english)
                out.entries.append(entry)
                utterance_rows.append(u)
                phone_rows.extend(result.phones)
            t = clock()
            block.close()
            out.flush_s += clock() - t
        t = clock()
        store.write_shard("phones", shard, table_from_rows(phone_rows, PHONES))
        store.write_shard("utterances", shard, table_from_rows(utterance_rows, UTTERANCES))
        out.tables_s += clock() - t
        del utterance_rows, phone_rows
    out.n = len(out.frames)
    return out


# ---- the peer ------------------------------------------------------------------------------------
def import_peer(install: bool):
    try:
        import openfacefx
        return openfacefx
    except ImportError:
        pass
    cmd = [sys.executable, "-m", "pip", "install", "openfacefx"]
    if not install:
        print(f"openfacefx is not installed: peer rows skipped. Install it with: {' '.join(cmd)}", flush=True)
        return None
    print(f"openfacefx (the peer, MIT, numpy only) is not installed in {sys.prefix}; installing it for this "
          f"benchmark only (it is not a visemeflow dependency): {' '.join(cmd)}", flush=True)
    if subprocess.run(cmd).returncode != 0:
        print(f"could not install openfacefx: peer rows skipped. Install it by hand: {' '.join(cmd)}", flush=True)
        return None
    import importlib
    importlib.invalidate_caches()
    import openfacefx
    return openfacefx


@dataclass
class Peer:
    version: str = ""
    n: int = 0
    parse_s: float = 0.0        # load_mfa_textgrid
    build_s: float = 0.0        # build_viseme_curves, default params
    frames: int = 0
    jali_n: int = 0
    jali_s: float = 0.0         # build_viseme_curves, CoartParams(jali=True)
    jali_frames: int = 0
    ours_parse_s: float = 0.0   # ingest_utterance + rows -> segments
    ours_gen_s: float = 0.0     # generate_procedural_curves
    ours_frames: int = 0
    ours_jali_gen_s: float = 0.0
    ours_jali_frames: int = 0


def run_peer(off, pure: Pure, limit: int, jali_limit: int) -> Peer:
    """Step 4: both sides side by side, utterance by utterance, on the English utterances of the corpus
    (the first `limit`, 0 = all), so that both run under the same conditions (caches, allocator, clock)."""
    from openfacefx.coarticulation import CoartParams

    from visemeflow.ingest import IngestConfig, ingest_utterance
    from visemeflow.phonetics.types import VisemeSegment
    from visemeflow.procedural import ProceduralConfig, generate_procedural_curves
    from visemeflow.schemas import C

    clock = time.perf_counter
    config, pconfig, jali_params = IngestConfig(), ProceduralConfig(), CoartParams(jali=True)
    entries = [e for e, english in zip(pure.entries, pure.english) if english]
    if limit:
        entries = entries[:limit]
    peer = Peer(version=getattr(off, "__version__", "?"), n=len(entries))
    for k, entry in enumerate(entries):
        # ours: parse (+ audio header, checks, mapping) then generation
        t0 = clock()
        u = ingest_utterance(entry, config)
        segments = [
            VisemeSegment(p[C.VISEME], p[C.START_S], p[C.END_S], p[C.WORD_INDEX], p[C.PHONEME] or "")
            for p in u.phones if p[C.VISEME] is not None
        ]
        segments.sort(key=lambda s: s.start_s)
        t1 = clock()
        fps, n_frames = float(u.utterance[C.FPS]), int(u.utterance[C.N_FRAMES])
        curves = generate_procedural_curves(segments, n_frames, fps, pconfig)
        t2 = clock()
        # peer: parse then the dense per-frame blend, at the same fps
        phone_segments = off.load_mfa_textgrid(entry.alignment_path)
        t3 = clock()
        _, matrix = off.build_viseme_curves(phone_segments, fps=fps)
        t4 = clock()
        peer.ours_parse_s += t1 - t0
        peer.ours_gen_s += t2 - t1
        peer.ours_frames += curves.shape[0]
        peer.parse_s += t3 - t2
        peer.build_s += t4 - t3
        peer.frames += matrix.shape[0]
        if not jali_limit or k < jali_limit:
            t5 = clock()
            _, matrix = off.build_viseme_curves(phone_segments, fps=fps, params=jali_params)
            peer.jali_s += clock() - t5
            peer.jali_frames += matrix.shape[0]
            peer.jali_n += 1
            peer.ours_jali_gen_s += t2 - t1
            peer.ours_jali_frames += curves.shape[0]
    return peer


# ---- the flow ------------------------------------------------------------------------------------
@dataclass
class FlowRuns:
    first_s: float = 0.0
    second_s: float = 0.0
    first: dict = field(default_factory=dict)
    second: dict = field(default_factory=dict)


def run_flow(root: Path, store_root: Path, prefect_home: Path) -> FlowRuns:
    prefect_home.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("PREFECT_HOME", str(prefect_home))
    from prefect_api import prefect_server

    from visemeflow.flows.params import PipelineParams
    from visemeflow.flows.pipeline import pipeline_flow

    runs = FlowRuns()
    params = PipelineParams(corpus=root, store=store_root, n_shards=N_SHARDS)
    print("starting the Prefect test harness (not timed) ...", flush=True)
    with prefect_server():
        print("flow run 1 (cold) ...", flush=True)
        t = time.perf_counter()
        runs.first = pipeline_flow(params)
        runs.first_s = time.perf_counter() - t
        print(f"  {runs.first_s:.1f} s; flow run 2 (cached) ...", flush=True)
        t = time.perf_counter()
        runs.second = pipeline_flow(params)
        runs.second_s = time.perf_counter() - t
        print(f"  {runs.second_s:.1f} s", flush=True)
    return runs


# ---- report --------------------------------------------------------------------------------------
def rate(count: float, seconds: float) -> float:
    return count / seconds if seconds > 0 else float("inf")


def fmt_rate(value: float, unit: str) -> str:
    return f"{value:,.0f} {unit}"


def report(args, link: str, pure: Pure, peer: Peer | None, flow: FlowRuns | None, wall_s: float) -> None:
    frames = sum(pure.frames)
    ingest_s, seg_s, gen_s, write_s = (sum(x) for x in (pure.ingest_s, pure.segments_s, pure.generate_s, pure.write_s))
    write_s += pure.flush_s
    n_speakers = min(args.speakers, args.utterances)
    n_english = sum(pure.english)
    scaled = f" (linear proj. to {TARGET_PURE_N:,}: {pure.compute_s * TARGET_PURE_N / max(pure.n, 1):.1f} s)" \
        if pure.n and pure.n != TARGET_PURE_N else ""
    rows: list[tuple[str, str, str, str]] = [
        ("## corpus", "", "", ""),
        ("utterances (speakers)", f"{pure.n:,} ingested of {args.utterances:,} ({n_speakers} speakers)"
         + (f", {pure.rejected} rejected" if pure.rejected else ""), "", ""),
        ("audio", f"{pure.audio_s / 3600:.2f} h (mean {pure.audio_s / max(pure.n, 1):.2f} s/utt)", "", ""),
        ("curve frames at 30 fps", f"{frames:,}", "", ""),
        ("English (ARPAbet) / Mandarin utterances", f"{n_english:,} / {pure.n - n_english:,}", "", ""),
        ("## pure compute, no Prefect (1 process, 1 utterance at a time)", "", "", ""),
        ("discovery + content hashing", f"{pure.discovery_s:.2f} s = {fmt_rate(rate(pure.n, pure.discovery_s), 'utt/s')}", "", ""),
        ("ingestion (ingest_utterance)", f"{ingest_s:.2f} s = {fmt_rate(rate(pure.n, ingest_s), 'utt/s')}", "", ""),
        ("phone rows -> VisemeSegments", f"{seg_s:.2f} s", "", ""),
        ("procedural generation", f"{gen_s:.2f} s = {fmt_rate(rate(frames, gen_s), 'frames/s')}", "", ""),
        ("curves_table + write_curves (Parquet)", f"{write_s:.2f} s = {fmt_rate(rate(pure.n, write_s), 'utt/s')}"
         f" (of it {pure.flush_s:.2f} s: one flush per shard)", "", ""),
        ("  curve files alone: fsync each / one flush per shard",
         f"{pure.writes_each_s:.2f} s / {pure.writes_group_s:.2f} s = "
         f"{pure.writes_each_s / max(pure.writes_group_s, 1e-9):.2f}x", "", ""),
        ("procedural incl. segments + writes", f"{seg_s + gen_s + write_s:.2f} s = "
         f"{fmt_rate(rate(frames, seg_s + gen_s + write_s), 'frames/s')}", "", ""),
        ("pure compute total (sum of the 5 above)", f"{pure.compute_s:.2f} s{scaled}",
         f"< {TARGET_PURE_S:.0f} s for {TARGET_PURE_N:,}",
         ("" if pure.n == TARGET_PURE_N else "proj. ")
         + met(pure.compute_s * TARGET_PURE_N / max(pure.n, 1) < TARGET_PURE_S) if pure.n else ""),
        ("(apart) utterances+phones shard tables", f"{pure.tables_s:.2f} s (not in the total)", "", ""),
    ]
    if flow is not None:
        ratio = flow.first_s / pure.compute_s if pure.compute_s else float("inf")
        ing1, proc1 = flow.first.get("ingest", {}), flow.first.get("procedural", {})
        ing2, proc2 = flow.second.get("ingest", {}), flow.second.get("procedural", {})
        rows += [
            ("## Prefect: pipeline_flow(n_shards=8) on a local Prefect server (its start-up not timed)", "", "", ""),
            ("flow run 1 (cold) wall time", f"{flow.first_s:.2f} s (ingested {ing1.get('ingested', '?')}, "
             f"generated {proc1.get('generated', '?')})", "", ""),
            ("overhead ratio = flow run 1 / pure compute", f"{ratio:.2f}x", f"<= {TARGET_OVERHEAD}x",
             met(ratio <= TARGET_OVERHEAD)),
            ("  flow run 1 / (pure compute + shard tables)", f"{flow.first_s / (pure.compute_s + pure.tables_s):.2f}x",
             "", ""),
            ("flow run 2 (all cached) wall time", f"{flow.second_s:.2f} s (cached shards: ingest "
             f"{ing2.get('cached_shards', '?')}/{ing2.get('shards', '?')}, procedural "
             f"{proc2.get('cached_shards', '?')}/{proc2.get('shards', '?')})", "", ""),
        ]
    if peer is not None:
        ours_gen = rate(peer.ours_frames, peer.ours_gen_s)
        peer_gen = rate(peer.frames, peer.build_s)
        ours_full = rate(peer.ours_frames, peer.ours_parse_s + peer.ours_gen_s)
        peer_full = rate(peer.frames, peer.parse_s + peer.build_s)
        ours_j = rate(peer.ours_jali_frames, peer.ours_jali_gen_s)
        peer_j = rate(peer.jali_frames, peer.jali_s)
        rows += [
            (f"## peer: OpenFaceFX {peer.version}, both sides run side by side on the same {peer.n:,} English TextGrids, same fps", "", "", ""),
            ("frames produced (ours / peer)", f"{peer.ours_frames:,} / {peer.frames:,}", "", ""),
            ("[a] excl. parsing: ours (generation)", fmt_rate(ours_gen, "frames/s"), "", ""),
            ("[a] excl. parsing: peer (build_viseme_curves)", fmt_rate(peer_gen, "frames/s"), "", ""),
            ("[a] ours / peer", f"{ours_gen / peer_gen:.1f}x", f">= {TARGET_PEER_RATIO:.0f}x",
             met(ours_gen / peer_gen >= TARGET_PEER_RATIO)),
            ("[b] incl. parsing: ours (ingest+segments+gen)", fmt_rate(ours_full, "frames/s"), "", ""),
            ("[b] incl. parsing: peer (load_mfa_textgrid+build)", fmt_rate(peer_full, "frames/s"), "", ""),
            ("[b] ours / peer", f"{ours_full / peer_full:.1f}x", f">= {TARGET_PEER_RATIO:.0f}x",
             met(ours_full / peer_full >= TARGET_PEER_RATIO)),
            (f"[c] peer JALI mode, excl. parsing ({peer.jali_n:,} utt)", fmt_rate(peer_j, "frames/s"), "", ""),
            ("[c] ours / peer JALI mode", f"{ours_j / peer_j:.1f}x", "", ""),
        ]
    notes = [
        f"corpus: copies of the {len(list(DEMO_CORPUS.glob('*/*.TextGrid')))} demo TextGrids, wavs as {link}; "
        f"whole benchmark {wall_s:.0f} s wall.",
        "pure compute: discover_corpus + ingest_utterance + rows->VisemeSegment + generate_procedural_curves + "
        "curves_table/Store.write_curves, each timed alone, summed.",
    ]
    if peer is not None:
        notes += [
            "[a] ours: generate_procedural_curves(segments, n_frames, fps) on prebuilt VisemeSegments -> (frames, 16);"
            " peer: openfacefx.build_viseme_curves(PhonemeSegments, fps) -> (frames, 15), default CoartParams.",
            "[b] ours: ingest_utterance (TextGrid read+parse, wav header, checks, phone->viseme map) + segments + "
            "generation; peer: openfacefx.load_mfa_textgrid(path) + build_viseme_curves. Neither writes anything.",
            "[c] peer: build_viseme_curves(..., params=CoartParams(jali=True)) (its JALI rules and timing table); "
            "ours as in [a] on the same utterances.",
            "The peer's keyframe reduction (reduce_to_track, part of generate_from_alignment) is not run: "
            "both sides stop at dense per-frame weights.",
        ]
    print()
    print_table(rows, notes)


# ---- main ----------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--utterances", type=int, default=TARGET_PURE_N, help="corpus size (default 12000)")
    ap.add_argument("--speakers", type=int, default=40, help="speakers the utterances are spread over (default 40)")
    ap.add_argument("--keep", type=Path, default=None,
                    help="build the corpus and stores in DIR (must be empty or absent) and keep them")
    ap.add_argument("--profile", action="store_true",
                    help="run the pure compute under cProfile and print the top functions (no flow, no peer)")
    ap.add_argument("--skip-flow", action="store_true", help="do not run the Prefect flow")
    ap.add_argument("--skip-peer", action="store_true", help="do not run OpenFaceFX")
    ap.add_argument("--no-install", action="store_true", help="do not pip-install openfacefx when it is missing")
    ap.add_argument("--peer-utterances", type=int, default=0,
                    help="run the peer on at most this many English utterances (default 0 = all)")
    ap.add_argument("--peer-jali-utterances", type=int, default=0,
                    help="run the peer's JALI mode on at most this many of them (default 0 = all)")
    args = ap.parse_args(argv)
    if args.utterances < 1 or args.speakers < 1:
        ap.error("--utterances and --speakers must be >= 1")

    start = time.perf_counter()
    if args.keep is not None:
        work = args.keep.resolve()
        if work.exists() and any(work.iterdir()):
            ap.error(f"--keep {work} is not empty")
        work.mkdir(parents=True, exist_ok=True)
        cleanup = None
    else:
        cleanup = tempfile.TemporaryDirectory(prefix="visemeflow-bench-")
        work = Path(cleanup.name)
    try:
        corpus = work / "corpus"
        print(f"building a corpus of {args.utterances:,} utterances in {corpus} ...", flush=True)
        link = build_corpus(corpus, args.utterances, args.speakers)

        off = None
        if not (args.skip_peer or args.profile):
            off = import_peer(install=not args.no_install)

        print("pure compute (no Prefect) ...", flush=True)
        if args.profile:
            profiler = cProfile.Profile()
            profiler.enable()
            pure = run_pure(corpus, work / "store-pure")
            profiler.disable()
            buf = io.StringIO()
            stats = pstats.Stats(profiler, stream=buf).strip_dirs()
            stats.sort_stats("tottime").print_stats(25)
            stats.sort_stats("cumulative").print_stats(30)
            print(buf.getvalue())
            print("(timings below are inflated by cProfile)")
        else:
            pure = run_pure(corpus, work / "store-pure")
        print(f"  {pure.compute_s:.1f} s", flush=True)
        print("curve writes side by side (fsync each file / one flush per shard) ...", flush=True)
        pure.writes_each_s, pure.writes_group_s = curve_writes_side_by_side(work, pure.n)

        peer = None
        if off is not None:
            print("peer: OpenFaceFX ...", flush=True)
            peer = run_peer(off, pure, args.peer_utterances, args.peer_jali_utterances)

        flow = None
        if not (args.skip_flow or args.profile):
            flow = run_flow(corpus, work / "store-flow", work / "prefect-home")

        report(args, link, pure, peer, flow, time.perf_counter() - start)
        if args.keep is not None:
            kept = [p for p in (corpus, work / "store-pure", work / "store-flow") if p.exists()]
            print("kept: " + ", ".join(str(p) for p in kept))
    finally:
        if cleanup is not None:
            cleanup.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
