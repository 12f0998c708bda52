"""Our TextGrid reader vs the `textgrid` package, side by side: files each reads, agreement, speed as a ratio.

Run: .venv/bin/python bench/textgrid_readers.py [--repeat 7]

Sets: the demo corpus (examples/corpus/*/*.TextGrid) and the real files under ../shared/data (ljspeech_mfa: MFA
long format; charsiu_mandarin: short format; praatio_examples: long and short, one with a point tier; grid_s1:
word alignments in `.align` files, no TextGrid, listed so the count is visible). "variants" rewrites every real and
demo TextGrid in each text layout and encoding Praat writes (long, short, the older `ooTextFile short` header,
UTF-8 with a BOM, UTF-16 BE and LE with a BOM) with `format_textgrid`, in a temporary folder.

Both readers start from the path (ours: read the bytes, decode, parse; the package: `TextGrid.fromFile`). Speed is
timed on the files both read, best of `--repeat` passes. "agree" counts files where both give the same tier names,
kinds, labels and times (within 1e-4 s; the package rounds times to 5 digits and drops zero-length intervals, so
those are dropped from ours before comparing); "exact" counts files where the package's result is exactly ours
(no time rounded, no interval dropped).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import textgrid as reference

from visemeflow.phonetics.textgrid import STYLES, TextGridData, format_textgrid, read_textgrid

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"

ENCODINGS = {"utf-8": b"", "utf-8 BOM": b"\xef\xbb\xbf", "utf-16-be BOM": b"\xfe\xff", "utf-16-le BOM": b"\xff\xfe"}


def read_reference(path: Path):
    return reference.TextGrid.fromFile(str(path))


def agrees(ours: TextGridData, ref) -> bool:
    """Same tiers, labels and times within 1e-4 s, after dropping what the package drops (zero-length intervals)."""
    return compare(ours, ref, exact=False)


def identical(ours: TextGridData, ref) -> bool:
    """Same tiers, every item and every time exactly as ours read it (nothing rounded, nothing dropped)."""
    return compare(ours, ref, exact=True)


def compare(ours: TextGridData, ref, exact: bool) -> bool:
    if [t.name for t in ours.tiers] != [t.name for t in ref.tiers]:
        return False
    for tier, ref_tier in zip(ours.tiers, ref.tiers, strict=True):
        if tier.kind == "IntervalTier":
            if not isinstance(ref_tier, reference.IntervalTier):
                return False
            items = [(a, b, s) for a, b, s in tier.items if exact or round(b, 5) > round(a, 5)]
            theirs = [(iv.minTime, iv.maxTime, iv.mark) for iv in ref_tier]
        else:
            if not isinstance(ref_tier, reference.PointTier):
                return False
            items = list(tier.items)
            theirs = [(p.time, p.time, p.mark) for p in ref_tier]
        if len(items) != len(theirs):
            return False
        for (a, b, s), (c, d, m) in zip(items, theirs, strict=True):
            close = (a, b) == (c, d) if exact else abs(a - c) <= 1e-4 and abs(b - d) <= 1e-4
            if not close or s != m:
                return False
    return True


def attempt(read: Callable, path: Path):
    try:
        return read(path)
    except Exception as exc:  # noqa: BLE001 - a failure of either reader is what is counted
        return exc


def best_time(read: Callable, files: list[Path], repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for f in files:
            read(f)
        best = min(best, time.perf_counter() - t0)
    return best


def variants(sources: list[Path], folder: Path) -> list[Path]:
    out = []
    for i, src in enumerate(sources):
        grid = read_textgrid(src)
        for style in STYLES:
            text = format_textgrid(grid.tiers, grid.start_s, grid.end_s, style=style)
            for enc, bom in ENCODINGS.items():
                if style != "long" and enc != "utf-8" and enc != "utf-16-be BOM":
                    continue  # the encodings are checked on the long layout; short layouts in UTF-8 and Praat's UTF-16
                codec = enc.split()[0]
                path = folder / f"{i:03d}-{src.stem}-{style.replace(' ', '_')}-{enc.replace(' ', '_')}.TextGrid"
                path.write_bytes(bom + text.encode(codec))
                out.append(path)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    if not SHARED.is_dir():
        print(f"error: {SHARED} is missing", file=sys.stderr)
        return 1
    sets = {
        "demo (examples/corpus)": sorted(REPO.glob("examples/corpus/*/*.TextGrid")),
        "ljspeech_mfa": sorted((SHARED / "ljspeech_mfa").rglob("*.TextGrid")),
        "charsiu_mandarin": sorted((SHARED / "charsiu_mandarin").rglob("*.TextGrid")),
        "praatio_examples": sorted((SHARED / "praatio_examples").rglob("*.TextGrid")),
        "grid_s1 (.align only)": sorted((SHARED / "grid_s1").rglob("*.TextGrid")),
    }
    with tempfile.TemporaryDirectory() as tmp:
        sources = [f for name, files in sets.items() for f in files]
        sets["variants (8 per file)"] = variants(sources, Path(tmp))
        header = ("set", "files", "ours reads", "textgrid reads", "agree", "exact", "ours ms/file", "textgrid ms/file",
                  "textgrid/ours")
        rows, failures = [], []
        tot = {"files": 0, "ours": 0, "ref": 0, "agree": 0, "exact": 0, "t_ours": 0.0, "t_ref": 0.0, "n_both": 0}
        for name, files in sets.items():
            ours = {f: attempt(read_textgrid, f) for f in files}
            ref = {f: attempt(read_reference, f) for f in files}
            ok_ours = [f for f in files if not isinstance(ours[f], Exception)]
            ok_ref = [f for f in files if not isinstance(ref[f], Exception)]
            both = [f for f in ok_ours if f in ok_ref]
            agree = sum(agrees(ours[f], ref[f]) for f in both)
            exact = sum(identical(ours[f], ref[f]) for f in both)
            for f in files:
                for who, res in (("ours", ours[f]), ("textgrid", ref[f])):
                    if isinstance(res, Exception):
                        failures.append(f"  {who} fails on {f.relative_to(REPO.parent) if f.is_relative_to(REPO.parent) else f.name}: "
                                        f"{type(res).__name__}: {str(res)[:90]}")
            t_ours = best_time(read_textgrid, both, args.repeat) if both else 0.0
            t_ref = best_time(read_reference, both, args.repeat) if both else 0.0
            per = (lambda t: f"{1000 * t / len(both):.3f}") if both else (lambda t: "-")
            rows.append((name, str(len(files)), str(len(ok_ours)), str(len(ok_ref)), f"{agree}/{len(both)}", f"{exact}/{len(both)}",
                         per(t_ours), per(t_ref), f"{t_ref / t_ours:.2f}x" if both else "-"))
            for k, v in (("files", len(files)), ("ours", len(ok_ours)), ("ref", len(ok_ref)), ("agree", agree), ("exact", exact),
                         ("t_ours", t_ours), ("t_ref", t_ref), ("n_both", len(both))):
                tot[k] += v
        rows.append(("all", str(tot["files"]), str(tot["ours"]), str(tot["ref"]), f"{tot['agree']}/{tot['n_both']}",
                     f"{tot['exact']}/{tot['n_both']}",
                     f"{1000 * tot['t_ours'] / tot['n_both']:.3f}", f"{1000 * tot['t_ref'] / tot['n_both']:.3f}",
                     f"{tot['t_ref'] / tot['t_ours']:.2f}x"))
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    for r in [header, tuple("-" * w for w in widths), *rows]:
        print("  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True))))
    print("textgrid/ours > 1 means ours is faster; times on the files both read, best of", args.repeat, "passes")
    if failures:
        print("failures:")
        print("\n".join(failures))
    return 0


if __name__ == "__main__":
    sys.exit(main())
