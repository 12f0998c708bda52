"""Shared by bench/learning.py and bench/robustness.py: the espeak-ng scale corpus as training examples,
and trained models cached on disk so that one bench reuses the other's models.

Data: `write_espeak_corpus` (GRID-grammar English + pinyin Mandarin, 12 espeak voices at 130/160/200 wpm)
ingested with the product's `ingest_utterance`; the targets are the synthetic true curves
(`generate_ground_truth`, Cohen-Massaro dynamics per speaker, the same as `visemeflow synth` writes) at
30 fps; the split is the product's (`assign_split`, 10 % validation by a stable hash of the id). Nothing is
rendered: learning needs audio and curves only.

Cache layout under `bench/out/learning/` (ignored by git):
  corpus/                         the espeak corpus (wav + TextGrid)
  examples-<key>.npz              audio, true and procedural curves of every utterance
  models/<name>.pt, <name>.json   saved models (`save_model`) and their training history
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import soundfile as sf

from visemeflow.hashing import stable_hash
from visemeflow.ingest import IngestConfig, discover_corpus, ingest_utterance
from visemeflow.ingest.utterance import assign_split
from visemeflow.learning.features import resample_audio
from visemeflow.learning.train import (
    Example,
    TrainConfig,
    load_model,
    save_model,
    train_model,
)
from visemeflow.phonetics.types import VisemeSegment
from visemeflow.procedural import generate_procedural_curves
from visemeflow.synth.dynamics import generate_ground_truth
from visemeflow.timebase import frame_count

OUT = Path(__file__).resolve().parent / "out" / "learning"
FPS = 30.0
SAMPLE_RATE = 16000


class Data:
    """Train/validation examples and the procedural curves of each utterance (the procedural floor)."""

    def __init__(self, train: list[Example], val: list[Example], procedural: dict[str, np.ndarray]):
        self.train, self.val, self.procedural = train, val, procedural


def written_once(root: Path, what: str, write) -> Path:
    """`root`, written by `write(root)` (which returns the utterance ids) unless a finished copy is there."""
    done = root / ".complete"
    if not done.exists():
        t0 = time.perf_counter()
        ids = write(root)
        done.write_text(str(len(ids)))
        print(f"{what}: {len(ids)} utterances in {time.perf_counter() - t0:.1f} s -> {root}", flush=True)
    return root


def ensure_corpus(n_english: int, n_mandarin: int, seed: int = 0) -> Path:
    from visemeflow.synth.sentences import write_espeak_corpus

    return written_once(OUT / f"corpus-en{n_english}-zh{n_mandarin}-s{seed}", "espeak corpus",
                        lambda root: write_espeak_corpus(root, n_english, n_mandarin, seed))


def load_data(n_english: int, n_mandarin: int, seed: int = 0, val_fraction: float = 0.1) -> Data:
    return corpus_data(ensure_corpus(n_english, n_mandarin, seed), val_fraction)


def corpus_data(corpus: Path, val_fraction: float = 0.1) -> Data:
    """Examples (16 kHz audio, synthetic true curves at 30 fps) of any aligned corpus under `OUT`, cached."""
    cache = OUT / f"examples-{stable_hash(corpus.name, FPS, val_fraction, 'v1', size=6)}.npz"
    if not cache.exists():
        t0 = time.perf_counter()
        ids, splits, audio, truth, proc = [], [], [], [], []
        for entry in discover_corpus(corpus).entries:
            result = ingest_utterance(entry, IngestConfig())
            segments = [VisemeSegment(p["viseme"], p["start_s"], p["end_s"], p["word_index"], p["phoneme"] or "")
                        for p in result.phones if p["viseme"] is not None]
            n = frame_count(result.utterance["duration_s"], FPS)
            samples, rate = sf.read(entry.audio_path, dtype="float32", always_2d=False)
            ids.append(entry.utterance_id)
            splits.append(assign_split(entry.utterance_id, val_fraction))
            audio.append(resample_audio(samples, rate, SAMPLE_RATE))
            truth.append(generate_ground_truth(segments, n, FPS, entry.speaker, entry.utterance_id))
            proc.append(generate_procedural_curves(segments, n, FPS))
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_name(cache.stem + ".tmp.npz")
        np.savez(
            tmp, ids=np.array(ids), splits=np.array(splits),
            audio=np.concatenate(audio), audio_len=np.array([len(a) for a in audio]),
            truth=np.concatenate(truth), proc=np.concatenate(proc), frames=np.array([len(t) for t in truth]),
        )
        tmp.replace(cache)
        print(f"examples: {len(ids)} utterances prepared in {time.perf_counter() - t0:.1f} s", flush=True)
    with np.load(cache) as npz:
        z = {k: npz[k] for k in npz.files}  # each npz[k] access would decode the array again
    a_off = np.concatenate([[0], np.cumsum(z["audio_len"])])
    f_off = np.concatenate([[0], np.cumsum(z["frames"])])
    train, val, procedural = [], [], {}
    for i, uid in enumerate(z["ids"].tolist()):
        ex = Example(uid, z["audio"][a_off[i]:a_off[i + 1]], z["truth"][f_off[i]:f_off[i + 1]], FPS)
        procedural[uid] = z["proc"][f_off[i]:f_off[i + 1]]
        (val if z["splits"][i] == "val" else train).append(ex)
    return Data(train, val, procedural)


def trained_model(name: str, config: TrainConfig, train: list[Example], val: list[Example],
                  augment_audio=None, verbose: bool = True):
    """(model, history as dicts): loaded from the cache when this name + config + data were trained before."""
    key = stable_hash(config, [ex.utterance_id for ex in train], [ex.utterance_id for ex in val], size=6)
    path = OUT / "models" / f"{name}-{key}.pt"
    meta = path.with_suffix(".json")
    if path.exists() and meta.exists():
        model, _, _ = load_model(path)
        return model, json.loads(meta.read_text())["history"]

    def report(epoch) -> None:
        if verbose:
            val_text = "-" if epoch.val_l1_x100 is None else f"{epoch.val_l1_x100:.2f}"
            print(f"  {name} epoch {epoch.epoch}: train {epoch.train_l1_x100:.2f} val {val_text} "
                  f"({epoch.seconds:.0f} s, {epoch.frames_per_s:.0f} frames/s)", flush=True)

    result = train_model(train, val, config, checkpoint_dir=OUT / "checkpoints" / f"{name}-{key}",
                         on_epoch=report, augment_audio=augment_audio)
    save_model(result.model, config, path, {"bench": name, "train": len(train), "val": len(val)})
    meta.write_text(json.dumps({"config": config.model_dump(mode="json"),
                                "history": [asdict(h) for h in result.history]}, indent=1))
    return result.model, [asdict(h) for h in result.history]
