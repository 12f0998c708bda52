"""Benchmark: the animation package (engine exports, preview video, deformation) on the ICT demo rig, on one CPU core.

Run:  .venv/bin/python bench/animation.py [--minutes 1] [--repeats 5] [--preview-seconds 5] [--solve] [--out DIR]
                                           [--no-pin]

Prints one table per section and never asserts; the exit status is 0 whatever the figures are. One core: the
OMP/MKL/OpenBLAS thread counts are set to 1 before numpy is imported, `torch.set_num_threads(1)`, USD's work
pool limited to 1 (`pxr.Work.SetConcurrencyLimit(1)`), and the whole process pinned to one CPU with
`os.sched_setaffinity` (so libx264's own threads share that core too; `--no-pin` leaves the affinity alone).
The machine is shared with other jobs: timings are noisy (the load average is printed before and after).

Input: the shipped demo rig (`visemeflow.rig.load_demo_rig()`, 21,984 vertices, 16 viseme shapes) as a character
(`character_from_rig`, bound with `conventions.bind`: the identity `visemeflow16` table), and smooth random
curves: per viseme a sum of raised-cosine bumps (0.7 per second on average, half-widths 60..200 ms, heights
0.2..0.9), clipped to [0, 1], seeded; `--minutes` minutes at 30 fps (default 1: 1,800 frames).

1. Export time per minute of 30 fps animation, each writer on its own, its inputs prepared beforehand
   (`binding.weights(curves)`, `arkit_weights(curves)`, a `CurveTrack`): glb (`gltf.write_glb`), usd (binary
   crate) and usda (text) (`usd.write_usd`), livelink (`livelink.write_livelink_csv`), json
   (`webjson.write_web_json`), curves-csv and curves-json (`export.write_export`). Best and median of
   `--repeats` calls, divided by the minutes, with VISEMEFLOW_FSYNC=0 and =1 (the default: file and folder
   fsync'd) side by side, the two modes alternating call by call. Target: < 0.5 s per format per minute,
   judged on the median with fsync on (what a user gets). A last row times `package.export_animation` with
   every blendshape-mode format of `EXPORTERS` (not the bone-mode pose tables) and the audio (a 16 kHz
   tone) in one call: checks, binding and writes.
2. File size per minute (MB = 1e6 bytes), and its split: a 1-frame file of the same format is the fixed part
   (for glb and usd: the mesh and its shapes; for the others: header and names), the rest is the animation.
3. ARKit mapping residual per viseme: the comment lines at the top of `visemeflow/shapes/data/arkit_visemes.csv`
   (relative ||A w - d|| / ||d|| and the largest vertex error, written by `examples/build_arkit_table.py`).
   With `--solve` and `../shared/data/ict_facekit` present, `build_arkit_table.solve()` runs again (20-30 s)
   and its residuals are shown beside the shipped ones, with whether the fresh table equals the shipped one.
4. Preview video (`preview.render_preview`, H.264 + AAC) of a `--preview-seconds` clip at size 360 with 1, 3 and
   4 sources (different seeds, so every panel is rendered; default 5 s: a 10 s clip takes about 3 minutes for
   the three rows on this 2-core machine), a title, phone captions and a synthetic tone muxed:
   video frames/s (the report's `frames_per_second`: deform, render, text, encode, write), panels/s, the process
   CPU seconds (all threads), and the MP4 size scaled to a minute.
5. Deformation: `apply.deform` frames/s over the whole take for chunks of 64, 256 and 1,024 frames (each block
   only touched, not kept), the memory of one chunk (chunk x V x 3 x 4 bytes) and the peak traced by tracemalloc
   over the first 3 chunks of a plain `for start, block in deform(...)` loop (about 3 chunks: the previous block,
   still bound to the loop variable, the new block and its matmul temporary), and what a one-hour take (108,000
   frames) needs whole (`deform_all`) against chunked.
6. Capture fit: `capture.fit_visemes` (ARKit weights -> our 16 visemes, per-frame NNLS through the shipped Gram
   table) frames/s on `arkit_weights` of the take's curves, best of `--repeats`. Target: > 300 frames/s.

Files go to `--out` (default bench/out/animation, git-ignored) and are left there to be looked at.
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_name] = "1"

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from cpu import pin_one_core  # noqa: E402  (bench/, this script's folder)
import torch  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from report import met  # noqa: E402  (bench/report.py, beside this script)
from visemeflow.animation.apply import deform  # noqa: E402
from visemeflow.shapes.capture import fit_visemes  # noqa: E402
from visemeflow.rig.character import Character, character_from_rig  # noqa: E402
from visemeflow.shapes.conventions import arkit_weights, bind  # noqa: E402
from visemeflow.animation.export import CurveTrack, write_export  # noqa: E402
from visemeflow.animation.gltf import write_glb  # noqa: E402
from visemeflow.shapes.livelink import write_livelink_csv  # noqa: E402
from visemeflow.animation.package import EXPORTERS, AnimateConfig, bone_only_formats, export_animation  # noqa: E402
from visemeflow.animation.preview import render_preview  # noqa: E402
from visemeflow.animation.usd import write_usd  # noqa: E402
from visemeflow.animation.webjson import write_web_json  # noqa: E402
from visemeflow.rig import load_demo_rig  # noqa: E402
from visemeflow.visemes import VISEMES  # noqa: E402

FPS = 30.0
TARGET_EXPORT_S = 0.5  # per format per minute of 30 fps animation
TARGET_FIT_FPS = 300.0  # capture.fit_visemes, frames per second on one core
ARKIT_TABLE = REPO / "visemeflow" / "shapes" / "data" / "arkit_visemes.csv"
ICT = REPO.parent / "shared" / "data" / "ict_facekit"
AUDIO_RATE = 16000
MB = 1e6
BLENDSHAPE_FORMATS = tuple(f for f in EXPORTERS if f not in bone_only_formats())


# ---- output --------------------------------------------------------------------------------------
def table(title: str, header: tuple[str, ...], rows: list[tuple[str, ...]], notes: list[str] = ()) -> None:
    """A boxed table: the first column left-aligned, the others right-aligned; notes printed under it."""
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    line = "+-" + "-+-".join("-" * w for w in widths) + "-+"

    def show(r) -> None:
        cells = [str(c).ljust(w) if i == 0 else str(c).rjust(w) for i, (c, w) in enumerate(zip(r, widths))]
        print("| " + " | ".join(cells) + " |")

    print()
    print(title)
    print(line)
    show(header)
    print(line)
    for r in rows:
        show(r)
    print(line)
    for n in notes:
        print(n)


def mb(n_bytes: float) -> str:
    return f"{n_bytes / MB:.3f}"


# ---- inputs --------------------------------------------------------------------------------------
def smooth_curves(n_frames: int, fps: float, seed: int, rate_per_s: float = 0.7) -> np.ndarray:
    """(n_frames, 16) float32 in [0, 1]: per viseme a sum of raised-cosine bumps, clipped."""
    rng = np.random.default_rng(seed)
    duration = n_frames / fps
    t = np.arange(n_frames) / fps
    curves = np.zeros((n_frames, len(VISEMES)), np.float64)
    for v in range(len(VISEMES)):
        for _ in range(rng.poisson(rate_per_s * duration) or 1):
            centre, half, height = rng.uniform(0, duration), rng.uniform(0.06, 0.2), rng.uniform(0.2, 0.9)
            lo, hi = np.searchsorted(t, centre - half), np.searchsorted(t, centre + half)
            curves[lo:hi, v] += height * 0.5 * (1 + np.cos(np.pi * (t[lo:hi] - centre) / half))
    return np.clip(curves, 0.0, 1.0).astype(np.float32)


def tone(seconds: float, rate: int = AUDIO_RATE) -> np.ndarray:
    """A 220 Hz tone with a 4 Hz syllable-like envelope, float32 mono in [-0.5, 0.5]."""
    t = np.arange(int(round(seconds * rate))) / rate
    return (0.5 * np.sin(2 * np.pi * 220 * t) * (0.5 + 0.5 * np.sin(2 * np.pi * 4 * t) ** 2)).astype(np.float32)


def phones_for(seconds: float, seed: int) -> list[tuple[float, float, str]]:
    """Synthetic phone captions, 60..160 ms each."""
    rng = np.random.default_rng(seed)
    labels = ["AA", "B", "IY", "S", "T", "OW", "M", "EH", "R", "UW", "F", "K"]
    out, t = [], 0.0
    while t < seconds:
        d = float(rng.uniform(0.06, 0.16))
        out.append((t, min(seconds, t + d), labels[int(rng.integers(len(labels)))]))
        t += d
    return out


def set_fsync(on: bool) -> None:
    os.environ["VISEMEFLOW_FSYNC"] = "1" if on else "0"


# ---- 1 + 2: exports ------------------------------------------------------------------------------
def writers(character: Character, weights: np.ndarray, arkit: np.ndarray, curves: np.ndarray,
            out: Path, stem: str) -> dict[str, tuple[Path, Callable[[], object]]]:
    """format -> (path, a call writing it) for the given frames."""
    n = len(curves)
    track = CurveTrack("bench", "bench", "random", curves, np.arange(n) / FPS, np.arange(n))
    p = {fmt: out / f"{stem}{suffix}" for fmt, suffix in (
        ("glb", ".glb"), ("usd", ".usd"), ("usda", ".usda"), ("livelink", ".livelink.csv"),
        ("json", ".web.json"), ("curves-csv", ".curves.csv"), ("curves-json", ".curves.json"))}
    return {
        "glb": (p["glb"], lambda: write_glb(p["glb"], character, weights, FPS, name=stem)),
        "usd": (p["usd"], lambda: write_usd(p["usd"], character, weights, FPS, name=stem)),
        "usda": (p["usda"], lambda: write_usd(p["usda"], character, weights, FPS, name=stem)),
        "livelink": (p["livelink"], lambda: write_livelink_csv(p["livelink"], arkit, FPS)),
        "json": (p["json"], lambda: write_web_json(p["json"], character.shape_names, weights, FPS, name=stem)),
        "curves-csv": (p["curves-csv"], lambda: write_export(track, p["curves-csv"], "csv")),
        "curves-json": (p["curves-json"], lambda: write_export(track, p["curves-json"], "json")),
    }


def timed(fn: Callable[[], object]) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def export_section(character: Character, binding, curves: np.ndarray, minutes: float, repeats: int,
                   out: Path) -> None:
    weights = binding.weights(curves)
    arkit = arkit_weights(curves)
    calls = writers(character, weights, arkit, curves, out, "take")
    audio = (tone(len(curves) / FPS), AUDIO_RATE)
    config = AnimateConfig(formats=BLENDSHAPE_FORMATS, audio=True)
    calls[f"export_animation (all {len(BLENDSHAPE_FORMATS)} + wav)"] = (None, lambda: export_animation(
        out / "package", "take", character, binding, curves, FPS, config, utterance_id="bench", audio=audio))

    rows = []
    for fmt, (_, call) in calls.items():
        call()  # warm-up: imports, caches, the file exists (the rename replaces it, as in real use)
        seconds = {False: [], True: []}
        for _ in range(repeats):
            for on in (False, True):
                set_fsync(on)
                seconds[on].append(timed(call) / minutes)
        set_fsync(True)
        best0, med0 = min(seconds[False]), statistics.median(seconds[False])
        best1, med1 = min(seconds[True]), statistics.median(seconds[True])
        target = fmt in EXPORTERS or fmt in ("usda",)
        rows.append((fmt, f"{best0:.3f}", f"{med0:.3f}", f"{best1:.3f}", f"{med1:.3f}",
                     f"{(med1 - med0) * 1e3:+.0f}", "< 0.5" if target else "",
                     met(med1 < TARGET_EXPORT_S) if target else ""))
    table(f"1. Export time, seconds per minute of {FPS:g} fps animation ({len(curves)} frames in the take, "
          f"{repeats} repeats per mode)",
          ("format", "fsync=0 best", "fsync=0 median", "fsync=1 best", "fsync=1 median", "fsync cost ms",
           "target", "met?"), rows,
          ["   seconds per minute = seconds per file of the take / its minutes (the fixed mesh cost is counted once",
           "   per file: with --minutes < 1 it is over-counted, with more it is spread).",
           "   fsync=1 is the default (VISEMEFLOW_FSYNC unset): file + folder flushed before/after the rename; the",
           "   target is judged on the fsync=1 median. Inputs (bound weights, ARKit weights, CurveTrack) are made",
           "   before timing; the last row is one export_animation call doing checks, binding and every format."])

    # 2. sizes: 1-frame file = fixed part
    one = writers(character, weights[:1], arkit[:1], curves[:1], out, "one_frame")
    rows = []
    for fmt, (path, _) in writers(character, weights, arkit, curves, out, "take").items():
        one[fmt][1]()
        whole, fixed = path.stat().st_size, one[fmt][0].stat().st_size
        anim = whole - fixed
        rows.append((fmt, mb(fixed + anim / minutes), mb(fixed), mb(anim / minutes),
                     f"{anim / max(1, len(curves) - 1):.0f}", f"{anim / whole:.0%}"))
    table("2. File size per minute (MB = 1e6 bytes); fixed part = a 1-frame file (glb/usd: mesh + 16 shapes)",
          ("format", "MB per minute", "fixed MB", "animation MB/min", "bytes/frame", "animation share"), rows,
          ["   MB per minute = fixed + animation per minute (a 1-minute file); animation share is of the take's file."])


# ---- 3: ARKit residuals --------------------------------------------------------------------------
def parse_residuals(path: Path) -> dict[str, tuple[float, float]]:
    """{viseme: (relative residual, max vertex error mm)} from the table's `#   AAA: 2.12e-04 relative, 0.007 mm`."""
    out = {}
    for line in path.read_text(encoding="utf-8").splitlines():
        if not line.startswith("#"):
            break
        body = line.lstrip("# ").strip()
        name, _, rest = body.partition(":")
        if name in VISEMES and "relative" in rest:
            rel, mm = rest.split(",")
            out[name] = (float(rel.split()[0]), float(mm.split()[0]))
    return out


def arkit_section(solve: bool) -> None:
    shipped = parse_residuals(ARKIT_TABLE)
    from visemeflow.shapes.conventions import builtin_table

    table_rows = builtin_table("arkit52")
    fresh, fresh_table, note = None, None, []
    if solve and ICT.is_dir():
        sys.path.insert(0, str(REPO / "examples"))
        import build_arkit_table

        start = time.perf_counter()
        fresh_table, fresh = build_arkit_table.solve(ICT)
        same = build_arkit_table.parse_table(build_arkit_table.table_text(fresh_table, fresh), "fresh") == table_rows
        note.append(f"   --solve: build_arkit_table.solve() on {ICT} took {time.perf_counter() - start:.1f} s; "
                    f"fresh table {'equals' if same else 'DIFFERS FROM'} the shipped one")
    elif solve:
        note.append(f"   --solve: {ICT} not found; only the shipped residuals are shown")
    else:
        note.append("   shipped residuals parsed from the table's comment lines; --solve recomputes them "
                    "(build_arkit_table.solve(), 20-30 s)")
    header = ("viseme", "ARKit shapes", "relative", "max error mm") + (
        ("fresh relative", "fresh max mm") if fresh else ())
    rows = []
    for v in VISEMES:
        rel, mm = shipped.get(v, (float("nan"), float("nan")))
        row = (v, str(len(table_rows.get(v, {}))), f"{rel:.2e}", f"{mm:.3f}")
        if fresh:
            row += (f"{fresh[v][0]:.2e}", f"{fresh[v][1]:.3f}")
        rows.append(row)
    rels = [shipped[v][0] for v in VISEMES if v in shipped]
    mms = [shipped[v][1] for v in VISEMES if v in shipped]
    note.insert(0, f"   shipped: worst relative {max(rels):.2e}, mean {np.mean(rels):.2e}; worst vertex error "
                   f"{max(mms):.3f} mm (the ICT mesh is in cm)")
    table(f"3. ARKit mapping residual per viseme ({ARKIT_TABLE.relative_to(REPO)}; ||A w - d|| / ||d||)",
          header, rows, note)


# ---- 4: preview ----------------------------------------------------------------------------------
def preview_section(character: Character, binding, seconds: float, out: Path) -> None:
    n = int(round(seconds * FPS))
    labels = ["procedural", "tracked", "predicted", "reference"]
    sources = {label: binding.weights(smooth_curves(n, FPS, seed=100 + i)) for i, label in enumerate(labels)}
    audio = (tone(seconds), AUDIO_RATE)
    phones = phones_for(seconds, seed=7)
    rows = []
    for k in (1, 3, 4):
        chosen = {label: sources[label] for label in labels[:k]}
        path = out / f"preview_{k}.mp4"
        cpu = time.process_time()
        report = render_preview(path, character, chosen, FPS, audio=audio, phones=phones,
                                title=f"benchmark: {k} source(s)", size=360)
        cpu = time.process_time() - cpu
        rows.append((str(k), f"{report.width}x{report.height}", str(report.frames), f"{report.seconds_render:.1f}",
                     f"{report.frames_per_second:.2f}", f"{report.frames_per_second * k:.2f}",
                     f"{cpu:.1f}", mb(path.stat().st_size * 60.0 / seconds)))
    table(f"4. Preview MP4 (render_preview, size 360, {seconds:g} s clip = {n} frames, title + phones + "
          f"{AUDIO_RATE // 1000} kHz tone as AAC)",
          ("sources", "video", "frames", "wall s", "frames/s", "panels/s", "CPU s", "MB per minute"), rows,
          ["   frames/s = PreviewReport.frames_per_second (deform + render + text + H.264/AAC encode + write);",
           "   CPU s counts every thread of the process (libx264 threads share the pinned core when pinned)."])


# ---- 5: deformation ------------------------------------------------------------------------------
def deform_section(character: Character, weights: np.ndarray, repeats: int) -> None:
    v = character.n_vertices
    frame_bytes = v * 3 * 4
    hour = int(3600 * FPS)
    rows = []
    for chunk in (64, 256, 1024):
        def run() -> float:
            touched = 0.0
            for _, block in deform(character, weights, chunk):
                touched += float(block[-1, -1, -1])  # touched, not kept
            return touched

        run()
        best = min(timed(run) for _ in range(repeats))
        tracemalloc.start()
        for start, _block in deform(character, weights, chunk):  # as a consumer loops: the loop variable
            if start >= 2 * chunk:                                 # holds the last block while the next is made
                break
        del _block
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        rows.append((str(chunk), f"{len(weights) / best:.0f}", f"{best:.2f}", mb(chunk * frame_bytes), mb(peak),
                     f"{peak / (chunk * frame_bytes):.2f}"))
    table(f"5. Deformation (apply.deform, V = {v:,} vertices, {character.n_shapes} shapes; take of "
          f"{len(weights):,} frames, best of {repeats})",
          ("chunk frames", "frames/s", "take s", "chunk MB", "traced peak MB", "peak / chunk"), rows,
          [f"   one frame = V x 3 x 4 bytes = {frame_bytes:,} bytes. A 1-hour take at {FPS:g} fps ({hour:,} frames):",
           f"     whole (deform_all): {hour * frame_bytes / MB:,.0f} MB ({hour * frame_bytes / 2**30:.1f} GiB);",
           *[f"     chunked by {c:>4}: {c * frame_bytes / MB:,.1f} MB per chunk, about 3x that at the peak, "
             f"whatever the take's length ({-(-hour // c):,} chunks)" for c in (64, 256, 1024)],
           "   (traced peak over the first 3 chunks of a plain `for start, block in deform(...)` loop: about three",
           "   chunks, the previous block still bound to the loop variable while deform makes the next one (its",
           "   matmul result, then the neutral added to it); a chunk longer than the take is the take's length.)"])


# ---- 6: capture fit ------------------------------------------------------------------------------
def fit_section(curves: np.ndarray, repeats: int) -> None:
    arkit = arkit_weights(curves)
    fit_visemes(arkit[:2])  # warm-up: the shipped table is read and cached
    best = min(timed(lambda: fit_visemes(arkit)) for _ in range(repeats))
    rate = len(arkit) / best
    table(f"6. Capture fit (capture.fit_visemes, ARKit 52 -> 16 visemes; {len(arkit):,} frames, best of {repeats})",
          ("frames", "seconds", "frames/s", "target", "met?"),
          [(f"{len(arkit):,}", f"{best:.3f}", f"{rate:,.0f}", f"> {TARGET_FIT_FPS:.0f}", met(rate > TARGET_FIT_FPS))])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=1.0, help="length of the take, minutes at 30 fps")
    parser.add_argument("--repeats", type=int, default=5, help="calls per format and fsync mode")
    parser.add_argument("--preview-seconds", type=float, default=5.0, help="length of the preview clip")
    parser.add_argument("--solve", action="store_true", help="re-solve the ARKit table (needs ../shared/data)")
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "out" / "animation")
    parser.add_argument("--no-pin", action="store_true", help="do not pin the process to one CPU")
    args = parser.parse_args(argv)

    torch.set_num_threads(1)
    from pxr import Work

    Work.SetConcurrencyLimit(1)
    pinned = "not pinned (--no-pin)" if args.no_pin else pin_one_core()
    args.out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    load_before = os.getloadavg()

    rig = load_demo_rig()
    character = character_from_rig(rig)
    binding = bind(character)
    n_frames = int(round(args.minutes * 60 * FPS))
    curves = smooth_curves(n_frames, FPS, seed=0)
    print(f"character {character.name}: {character.n_vertices:,} vertices, {len(character.faces):,} triangles, "
          f"{character.n_shapes} shapes, convention {binding.convention}")
    print(f"curves: {n_frames:,} frames at {FPS:g} fps ({args.minutes:g} min), mean weight {curves.mean():.3f}, "
          f"{(curves > 0.01).mean():.0%} of values > 0.01")
    print(f"threads: torch {torch.get_num_threads()}, OMP/MKL/OpenBLAS 1, USD work 1; {pinned}; "
          f"{os.cpu_count()} CPUs on the machine")
    print(f"load average before: {load_before[0]:.2f} {load_before[1]:.2f} {load_before[2]:.2f} -- the machine is "
          "shared with other jobs, timings are noisy")
    print(f"files under {args.out}")

    export_section(character, binding, curves, args.minutes, args.repeats, args.out)
    arkit_section(args.solve)
    preview_section(character, binding, args.preview_seconds, args.out)
    deform_section(character, binding.weights(curves), max(1, min(args.repeats, 3)))
    fit_section(curves, args.repeats)

    load_after = os.getloadavg()
    print()
    print(f"load average after: {load_after[0]:.2f} {load_after[1]:.2f} {load_after[2]:.2f}; "
          f"total {time.perf_counter() - started:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
