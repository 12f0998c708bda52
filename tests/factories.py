"""Small builders of test inputs: wav files, Praat TextGrid text (long and short format), corpora.

Interval lists for the TextGrid builders are `(start, end, label)` tuples, the order Praat writes and
`Tier.items` holds; `make_corpus` takes `(label, start, end)` phones per utterance id.
"""

import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import soundfile as sf

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
DEMO_CORPUS = REPO / "examples" / "corpus"

Interval = tuple[float, float, str]


def write_wav(path: Path | str, seconds: float, rate: int = 16000) -> Path:
    """A quiet 220 Hz tone of `seconds` (rounded to whole samples) as 16-bit PCM; parent folders are made."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    n = int(round(seconds * rate))
    t = np.arange(n, dtype=np.float64) / rate
    sf.write(path, 0.05 * np.sin(2 * np.pi * 220.0 * t), rate, subtype="PCM_16")
    return path


def _quote(text: str) -> str:
    return '"' + text.replace('"', '""') + '"'


def _tiers(intervals: Sequence[Interval], tier: str, words: Sequence[Interval] | None) -> list[tuple[str, Sequence[Interval]]]:
    tiers: list[tuple[str, Sequence[Interval]]] = []
    if words is not None:
        tiers.append(("words", words))
    tiers.append((tier, intervals))
    return tiers


def textgrid_long(
    intervals: Sequence[Interval], xmax: float, tier: str = "phones", words: Sequence[Interval] | None = None,
    xmin: float = 0.0,
) -> str:
    """Praat long-format TextGrid text: an optional `words` interval tier, then `tier` with `intervals`."""
    tiers = _tiers(intervals, tier, words)
    out = [
        'File type = "ooTextFile"', 'Object class = "TextGrid"', "",
        f"xmin = {xmin!r}", f"xmax = {xmax!r}", "tiers? <exists> ", f"size = {len(tiers)} ", "item []: ",
    ]
    for i, (name, items) in enumerate(tiers, start=1):
        out += [
            f"    item [{i}]:", '        class = "IntervalTier" ', f"        name = {_quote(name)} ",
            f"        xmin = {xmin!r} ", f"        xmax = {xmax!r} ", f"        intervals: size = {len(items)} ",
        ]
        for j, (a, b, text) in enumerate(items, start=1):
            out += [
                f"        intervals [{j}]:", f"            xmin = {a!r} ", f"            xmax = {b!r} ",
                f"            text = {_quote(text)} ",
            ]
    return "\n".join(out) + "\n"


def textgrid_short(
    intervals: Sequence[Interval], xmax: float, tier: str = "phones", words: Sequence[Interval] | None = None,
    xmin: float = 0.0,
) -> str:
    """The same TextGrid as `textgrid_long`, in Praat's short text format."""
    tiers = _tiers(intervals, tier, words)
    out = ['File type = "ooTextFile"', 'Object class = "TextGrid"', "", repr(xmin), repr(xmax), "<exists>", str(len(tiers))]
    for name, items in tiers:
        out += ['"IntervalTier"', _quote(name), repr(xmin), repr(xmax), str(len(items))]
        for a, b, text in items:
            out += [repr(a), repr(b), _quote(text)]
    return "\n".join(out) + "\n"


def make_corpus(
    root: Path | str,
    utterances: Mapping[str, Sequence[tuple[str, float, float]]],
    *,
    duration: float | Mapping[str, float] | None = None,
    rate: int = 16000,
    fmt: str = "long",
    tier: str = "phones",
) -> Path:
    """A folder corpus: `<speaker>/<name>.wav` + `.TextGrid` per utterance id `speaker/name`.

    Phones are `(label, start, end)`. The audio lasts `duration` (one value, or one per id), by default
    the end of the last phone, which is also the TextGrid's xmax.
    """
    root = Path(root)
    build = textgrid_long if fmt == "long" else textgrid_short
    for utterance_id, phones in utterances.items():
        speaker, name = utterance_id.split("/")
        end = max((e for _, _, e in phones), default=1.0)
        seconds = duration.get(utterance_id, end) if isinstance(duration, Mapping) else (duration or end)
        folder = root / speaker
        folder.mkdir(parents=True, exist_ok=True)
        write_wav(folder / f"{name}.wav", seconds, rate)
        text = build([(s, e, label) for label, s, e in phones], end, tier=tier)
        (folder / f"{name}.TextGrid").write_text(text, encoding="utf-8")
    return root


def make_curve_store(root, n=6, seed=0):
    """A store with `n` one-second utterances (write_wav tones) and random `ground_truth`/`cm` curves at 25 fps;
    the first two in the 'val' split."""
    from visemeflow.schemas import UTTERANCES, C, curves_table, table_from_rows
    from visemeflow.storage import Store

    s = Store(root)
    rows = []
    rng = np.random.default_rng(seed)
    for i in range(n):
        uid = f"spk/u{i}"
        wav = write_wav(root.parent / f"{root.name}-audio" / f"u{i}.wav", 1.0)
        rows.append({C.UTTERANCE_ID: uid, C.SPEAKER: "spk", C.AUDIO_PATH: str(wav), C.ALIGNMENT_PATH: "x",
                     C.ALIGNMENT_FORMAT: "textgrid", C.SAMPLE_RATE: 16000, C.DURATION_S: 1.0, C.FPS: 25.0,
                     C.N_FRAMES: 25, C.CONTENT_HASH: str(i), C.SPLIT: "val" if i < 2 else "train"})
        s.write_curves(curves_table(uid, "ground_truth", "cm", rng.random((25, 16)).astype(np.float32), 25.0))
    s.write_shard("utterances", 0, table_from_rows(rows, UTTERANCES))
    return s


LJ_NAMES = ["LJ001-0002", "LJ001-0003", "LJ001-0005", "LJ001-0008", "LJ001-0010", "LJ001-0012"]


def make_lj_corpus(root: Path, speakers: int = 2, names: list[str] = LJ_NAMES) -> Path:
    """A corpus of demo LJSpeech utterances (hard links) under several speakers, plus the Mandarin one."""
    for s in range(speakers):
        folder = root / f"spk{s}"
        folder.mkdir(parents=True)
        for name in names:
            for ext in (".wav", ".TextGrid"):
                src = DEMO_CORPUS / "LJ" / f"{name}{ext}"
                # TextGrids are copied (tests edit them); audio is linked to save disk.
                (shutil.copyfile if ext == ".TextGrid" else os.link)(src, folder / f"{name}{ext}")
    zh = root / "zh"
    zh.mkdir()
    for ext in (".wav", ".TextGrid"):
        shutil.copyfile(DEMO_CORPUS / "SSB1624" / f"SSB16240001{ext}", zh / f"SSB16240001{ext}")
    return root


def run_pipeline(corpus: Path, store: Path, n_shards: int = 4) -> dict:
    from visemeflow.flows.params import PipelineParams
    from visemeflow.flows.pipeline import pipeline_flow

    return pipeline_flow(PipelineParams(corpus=corpus, store=store, n_shards=n_shards))


def snapshot(store: Path) -> dict[str, list[dict]]:
    """Every table, curve file and tracking diagnostic, sorted, without reject timestamps: what 'identical' means."""
    from visemeflow.schemas import C
    from visemeflow.storage import Store

    s = Store(store)
    out = {}
    for table in ("utterances", "phones"):
        out[table] = sorted(s.read_table(table).to_pylist(), key=lambda r: tuple(str(v) for v in r.values()))
    out["rejects"] = sorted(
        ({k: v for k, v in r.items() if k != C.TIME} for r in s.read_table("rejects").to_pylist()), key=str
    )
    out["curves"] = sorted(s.scan_curves().to_pylist(), key=lambda r: (r[C.UTTERANCE_ID], r[C.VARIANT], r[C.FRAME]))
    out["curve_files"] = sorted(os.path.relpath(p, s.root) for p in s.curve_files())
    out["tracking_frames"] = sorted(s.read_tracking_frames().to_pylist(),
                                    key=lambda r: (r[C.UTTERANCE_ID], r[C.VARIANT], r[C.FRAME]))
    return out


def kill_cli_when(args: list[str], prefect_api_url: str, ready: Callable[[], bool], timeout_s: float = 300) -> None:
    """Run `visemeflow ARGS` in a child process on the given Prefect API and SIGKILL it as soon as `ready()`.

    Fails if the command ended before it could be killed (a test that kills too late proves nothing).
    """
    env = {**os.environ, "PREFECT_API_URL": prefect_api_url, "PREFECT_LOGGING_LEVEL": "WARNING"}
    proc = subprocess.Popen([sys.executable, "-m", "visemeflow.cli", *args], cwd=REPO, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline and proc.poll() is None and not ready():
            time.sleep(0.002)
        assert proc.poll() is None, f"visemeflow {args[0]} ended before it could be killed"
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
