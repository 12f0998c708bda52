"""Small builders of test inputs: wav files, Praat TextGrid text (long and short format), corpora, the held-out
real speech and the remeshed transfer target; and the real glTF clients (Khronos validator) the GLB tests share.

Interval lists for the TextGrid builders are `(start, end, label)` tuples, the order Praat writes and
`Tier.items` holds; `make_corpus` takes `(label, start, end)` phones per utterance id.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pygltflib as gl
import pytest
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


def render_videos(root: Path, utterances: Sequence[tuple[str, str]]) -> Path:
    """Demo utterances (speaker, name) rendered as talking-face videos (with their audio and alignments) under
    `root / "videos"`; returns that corpus folder."""
    from visemeflow.flows.params import SynthParams
    from visemeflow.flows.synth import synth_flow

    for speaker, name in utterances:
        (root / "source" / speaker).mkdir(parents=True, exist_ok=True)
        for ext in (".wav", ".TextGrid"):
            shutil.copyfile(DEMO_CORPUS / speaker / f"{name}{ext}", root / "source" / speaker / f"{name}{ext}")
    synth_flow(SynthParams(corpus=root / "source", out=root / "videos", store=root / "truth"))
    return root / "videos"


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
    out["curve_files"] = sorted(str(p)[len(str(s.root)) + 1:] for p in s.curve_files())   # a folder's or a bucket's
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


# ---- real speech with forced alignments ------------------------------------------------------------------------
SPEECH_FPS = 30.0
SPEECH_RATE = 16000


@dataclass
class AlignedSpeech:
    """One aligned utterance as the real-speech metrics take it: 16 kHz audio and its phones."""

    uid: str
    audio: np.ndarray          # (samples,) float32 at SPEECH_RATE
    phones: list               # learning.realspeech.Phone
    n: int                     # curve frames at SPEECH_FPS


def read_aligned_speech(root: Path) -> list[AlignedSpeech]:
    """Every utterance of a corpus folder, read by the product's ingestion (`discover_corpus`, `ingest_utterance`)."""
    from visemeflow.ingest import IngestConfig, discover_corpus, ingest_utterance
    from visemeflow.ingest.audio import read_audio
    from visemeflow.learning.features import resample_audio
    from visemeflow.learning.realspeech import phones_of
    from visemeflow.timebase import frame_count

    out = []
    for entry in discover_corpus(root).entries:
        result = ingest_utterance(entry, IngestConfig())
        rows = sorted(result.phones, key=lambda p: (p["start_s"], p["index"], p["part"]))
        samples, rate = read_audio(entry.audio_path)
        out.append(AlignedSpeech(entry.utterance_id, resample_audio(samples, rate, SPEECH_RATE), phones_of(rows),
                                 frame_count(result.utterance["duration_s"], SPEECH_FPS)))
    return out


def held_out_speech(tmp: Path) -> dict[str, list[AlignedSpeech]]:
    """Real speakers no shipped model trained on, from ../shared/data: GRID s1's 10 clips (video + word alignment),
    the charsiu Mandarin utterance and praatio's two examples, copied into corpus folders under `tmp` (the product
    refuses links to outside a corpus). The sets of examples/train_default_model.py's recorded figures."""
    grid = tmp / "grid" / "s1"
    grid.mkdir(parents=True)
    for align in sorted((SHARED_DATA / "grid_s1" / "align").glob("*.align")):
        shutil.copyfile(align, grid / align.name)
        shutil.copyfile(SHARED_DATA / "grid_s1" / "video" / f"{align.stem}.mpg", grid / f"{align.stem}.mpg")
    zh = tmp / "charsiu" / "SSB1624"
    zh.mkdir(parents=True)
    shutil.copyfile(SHARED_DATA / "charsiu_mandarin" / "SSB16240001_16k.wav", zh / "SSB16240001.wav")
    shutil.copyfile(SHARED_DATA / "charsiu_mandarin" / "SSB16240001.TextGrid", zh / "SSB16240001.TextGrid")
    praatio = tmp / "praatio" / "praatio"
    praatio.mkdir(parents=True)
    for name, grid_name in (("bobby", "bobby_phones.TextGrid"), ("mary", "mary.TextGrid")):
        shutil.copyfile(SHARED_DATA / "praatio_examples" / f"{name}.wav", praatio / f"{name}.wav")
        shutil.copyfile(SHARED_DATA / "praatio_examples" / grid_name, praatio / f"{name}.TextGrid")
    return {"GRID s1": read_aligned_speech(grid.parent), "Mandarin": read_aligned_speech(zh.parent),
            "praatio": read_aligned_speech(praatio.parent)}


# ---- the transfer target of another topology (tests/test_transfer.py, bench/transfer.py) ------------------------
TURN = np.deg2rad(20.0)
ROTATION = np.array([[np.cos(TURN), 0, np.sin(TURN)], [0, 1, 0], [-np.sin(TURN), 0, np.cos(TURN)]])
REMESHED_IDENTITY = (0.8, 0.6, -0.7)
"""Identity-mode coefficients of the remeshed target's face."""


def identity_face(demo, modes: np.ndarray, values) -> np.ndarray:
    """(V, 3) the demo rig's neutral moved by the first len(values) identity modes (K, V, 3) times `values`."""
    c = np.zeros(len(modes))
    c[: len(values)] = values
    return demo.neutral + np.tensordot(c, modes, axes=1)


def placed(points: np.ndarray) -> np.ndarray:
    """Where the remeshed target puts the face: turned 20 degrees about y, scaled 1.15 and moved."""
    return 1.15 * points @ ROTATION.T + np.array([3.0, -2.0, 5.0])


def remeshed_face(demo, modes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, triangles, 68 landmark ids): the ICT narrow face (vertices 0..6705) of another identity,
    Loop-subdivided (every vertex moves, 4 triangles for each), `placed`; its landmarks are the nearest vertices."""
    import trimesh
    from scipy.spatial import cKDTree

    face = identity_face(demo, modes, REMESHED_IDENTITY)
    keep = np.zeros(len(face), bool)
    keep[:6706] = True
    faces = demo.faces[keep[demo.faces].all(axis=1)]
    used = np.unique(faces)
    local = np.full(len(face), -1)
    local[used] = np.arange(len(used))
    vertices, faces = trimesh.remesh.subdivide_loop(face[used], local[faces], iterations=1)
    _, landmarks = cKDTree(placed(vertices)).query(placed(face[demo.landmark_ids]))
    return placed(vertices), faces, landmarks


# ---- GLB readers and clients independent of the module under test ---------------------------------------------
JS = REPO / "tools" / "js"
NODE_MODULES = JS / "node_modules"
VALIDATE = JS / "validate_gltf.mjs"


def glb_arrays(path: Path) -> tuple[gl.GLTF2, Callable[[int], np.ndarray]]:
    """The document and a reader of tightly packed accessors (dense, or sparse over zeros as we write them),
    independent of the module under test."""
    g = gl.GLTF2.load(str(path))
    blob = g.binary_blob()
    dtypes = {gl.FLOAT: "<f4", gl.UNSIGNED_BYTE: "<u1", gl.UNSIGNED_SHORT: "<u2", gl.UNSIGNED_INT: "<u4"}
    widths = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}

    def packed(view_index: int, byte_offset: int, dtype: str, count: int, width: int) -> np.ndarray:
        view = g.bufferViews[view_index]
        assert view.byteStride is None
        assert np.dtype(dtype).itemsize * width * count <= view.byteLength
        return np.frombuffer(blob, dtype, count * width, view.byteOffset + byte_offset).reshape(count, width)

    def read(index: int) -> np.ndarray:
        acc = g.accessors[index]
        dtype, width = dtypes[acc.componentType], widths[acc.type]
        if acc.sparse is None:
            return packed(acc.bufferView, acc.byteOffset, dtype, acc.count, width)
        assert acc.bufferView is None
        values = np.zeros((acc.count, width), dtype)
        ids = packed(acc.sparse.indices.bufferView, acc.sparse.indices.byteOffset,
                     dtypes[acc.sparse.indices.componentType], acc.sparse.count, 1)[:, 0]
        values[ids] = packed(acc.sparse.values.bufferView, acc.sparse.values.byteOffset, dtype, acc.sparse.count,
                             width)
        return values

    return g, read


def node_or_fail() -> str:
    """The node executable, with the pinned JS packages installed; otherwise the test fails with the command."""
    node = shutil.which("node")
    if node is None:
        pytest.fail("node is not installed: run `sh scripts/system-deps.sh` as root (or `apt-get install -y nodejs "
                    "npm`); `make test` and .ci/run run it first")
    for package in ("gltf-validator", "three"):
        if not (NODE_MODULES / package / "package.json").is_file():
            pytest.fail(f"{NODE_MODULES / package} is missing: run `make js-deps` (npm ci --prefix tools/js); "
                        "`make test` runs it first")
    return node


def validate(path: Path) -> dict:
    """The Khronos validator's report for `path`; its infos and hints are printed."""
    node = node_or_fail()
    done = subprocess.run([node, str(VALIDATE), str(path)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    issues = report["issues"]
    print(f"\ngltf-validator {report['validatorVersion']} on {path.name}: {issues['numErrors']} errors, "
          f"{issues['numWarnings']} warnings, {issues['numInfos']} infos, {issues['numHints']} hints")
    for m in issues["messages"]:
        print(f"  severity {m['severity']} {m['code']} at {m.get('pointer', '-')}: {m['message']}")
    return report


# ---- shared by the prediction, animation and training tests ----------------------------------------------------
DEMO_AUDIO = DEMO_CORPUS / "SSB1624" / "SSB16240001.wav"
"""A real Mandarin utterance of the demo corpus (AISHELL-3 speaker SSB1624, 16 kHz)."""


def tiny_character(names, seed=0, name="tiny"):
    """A 16-vertex character whose shapes are the given names, random deltas: animation packages in seconds."""
    from visemeflow.rig.character import make_character

    rng = np.random.default_rng(seed)
    grid = np.stack(np.meshgrid(np.arange(4.0), np.arange(4.0)), -1).reshape(-1, 2)
    neutral = np.c_[grid, np.zeros(len(grid))]
    faces = [[i, i + 1, i + 4] for i in range(11) if i % 4 != 3]
    return make_character(name, neutral, faces, names, rng.normal(0, 0.1, size=(len(names), len(neutral), 3)))


def tiny_model(store, name: str = "tiny", seed: int = 0) -> None:
    """An untrained small model saved where training would put it (prediction needs weights, not good ones)."""
    import torch

    from visemeflow.learning.train import TrainConfig, build_training_model, save_model

    torch.manual_seed(seed)
    config = TrainConfig(preset="fbank-tcn", d_model=8, seed=seed)
    save_model(build_training_model(config, curve_fps=25.0), config, store.model_path(name), {"source": "none"})


TRAIN_SR = 16000
TRAIN_FPS = 25.0


def _envelope(t: np.ndarray, freq: float, phase: float) -> np.ndarray:
    return 0.05 + 0.95 * (0.5 + 0.5 * np.sin(2 * np.pi * freq * t + phase))


def envelope_examples(n: int, seed: int, learnable: bool = True) -> list:
    """Training examples at TRAIN_SR / TRAIN_FPS: noise whose loudness follows a slow envelope; targets = a fixed
    affine map of that envelope (random curves when not `learnable`)."""
    from visemeflow.learning.train import Example

    rng = np.random.default_rng(seed)
    w = np.random.default_rng(123).uniform(0.2, 1.0, 16)
    b = np.random.default_rng(321).uniform(0.0, 0.2, 16)
    out = []
    for i in range(n):
        dur = float(rng.uniform(1.0, 2.0))
        samples = int(dur * TRAIN_SR)
        n_frames = round(dur * TRAIN_FPS)
        freq, phase = float(rng.uniform(0.7, 2.0)), float(rng.uniform(0, 2 * np.pi))
        t = np.arange(samples) / TRAIN_SR
        audio = (0.3 * _envelope(t, freq, phase) * rng.standard_normal(samples)).astype(np.float32)
        if learnable:
            env = _envelope(np.arange(n_frames) / TRAIN_FPS, freq, phase)
            curves = np.clip(env[:, None] * w[None] + b[None], 0, 1)
        else:
            curves = rng.uniform(0, 1, (n_frames, 16))
        out.append(Example(f"utt{seed}_{i}", audio, curves.astype(np.float32), TRAIN_FPS))
    return out


def params_of(model) -> dict:
    """A copy of a model's state dict."""
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def assert_same_params(a: dict, b: dict) -> None:
    """Two state dicts equal to the bit."""
    import torch

    assert a.keys() == b.keys()
    for k, v in a.items():
        assert torch.equal(v, b[k]), k


def usd_validation_errors(stage) -> list[str]:
    """usd-core's own validators' errors on `stage` (its warnings left out)."""
    from pxr import UsdValidation

    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    return [f"{e.GetType()}: {e.GetMessage()}" for e in errors
            if e.GetType() == UsdValidation.ValidationErrorType.Error]


def stop_process(proc: "subprocess.Popen") -> None:
    """SIGTERM a child (a `visemeflow serve`) that is still running, wait up to 60 s, then kill it."""
    import signal
    import subprocess

    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()


def start_serve(args: list[str], env: dict, cwd: Path, log: Path, timeout_s: float = 240) -> "subprocess.Popen":
    """`visemeflow serve ARGS` in a child process writing to `log`, returned once its deployments are served (fails
    if it exits or takes longer than `timeout_s`); stop it with `stop_process`."""
    with log.open("w") as out:
        serve = subprocess.Popen([sys.executable, "-m", "visemeflow.cli", "serve", *args], env=env, cwd=cwd,
                                 stdout=out, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + timeout_s
    while "deployments are being served" not in log.read_text():
        if serve.poll() is not None or time.monotonic() > deadline:
            stop_process(serve)
            raise AssertionError(log.read_text())
        time.sleep(0.5)
    return serve


def two_frames_apart(path: Path, gap_s: float) -> Path:
    """A 64x64 MJPEG .mkv of two grey frames, the second stamped `gap_s` after the first, with 1 s of silence."""
    import av
    from fractions import Fraction

    with av.open(str(path), "w", format="matroska") as c:
        vs = c.add_stream("mjpeg", rate=25)
        vs.width = vs.height = 64
        vs.pix_fmt = "yuvj420p"
        vs.codec_context.time_base = Fraction(1, 25)
        audio = c.add_stream("pcm_s16le", rate=16000, layout="mono")
        for pts in (0, int(round(gap_s * 25))):
            frame = av.VideoFrame.from_ndarray(np.full((64, 64, 3), 128, np.uint8), format="rgb24")
            frame.pts = pts
            for packet in vs.encode(frame):
                c.mux(packet)
        for packet in vs.encode(None):
            c.mux(packet)
        silence = av.AudioFrame.from_ndarray(np.zeros((1, 16000), np.int16), format="s16", layout="mono")
        silence.sample_rate, silence.pts, silence.time_base = 16000, 0, Fraction(1, 16000)
        for packet in [*audio.encode(silence), *audio.encode(None)]:
            c.mux(packet)
    return path
