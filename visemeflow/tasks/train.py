"""Training task: one audio-to-curves model trained on curves and audio from the store.

Keyed on its inputs and code like every task, except where it runs: `device`, `precision` and `encoder_cache_dir`
are left out of the cache key (`TRAIN_CACHE_POLICY`), so a model trained on the CPU is a cache hit for a GPU run of
the same config and data, and the other way round.
"""

import math
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
from prefect import get_run_logger, task
from prefect.artifacts import create_table_artifact
from prefect.cache_policies import TASK_SOURCE, Inputs

from visemeflow.ingest.audio import read_audio
from visemeflow.learning.device import resolve_device
from visemeflow.learning.features import resample_audio
from visemeflow.learning.train import (
    CHECKPOINT_NAME,
    SAMPLE_RATE,
    EpochReport,
    Example,
    TrainConfig,
    evaluate,
    save_model,
    train_model,
)
from visemeflow.location import local_input
from visemeflow.schemas import METRICS, C
from visemeflow.tasks.progress import Progress
from visemeflow.storage import Store
from visemeflow.tasks.code_version import code_digest
from visemeflow.tasks.common import CODE, RESULT_SERIALIZER, DataOnlyCache, result_storage
from visemeflow.visemes import VISEMES

# INPUTS + TASK_SOURCE + CODE like every task, without the inputs that say where (not what) it computes
RUN_SETTINGS = ["device", "precision", "encoder_cache_dir"]
TRAIN_CACHE_POLICY = Inputs(exclude=RUN_SETTINGS) + TASK_SOURCE + CODE
CODE_FILE = "code_version"  # beside the checkpoint: the code digest of the training that wrote it


def load_audio(path: str) -> np.ndarray:
    """Mono 16 kHz float32 audio of an audio file or of a video's audio track (`ingest.audio.read_audio`).

    Raises `ingest.audio.NonFiniteAudioError` (`AudioAmplitudeError`), naming the file and the bad samples, for NaN
    or infinite samples (samples beyond `ingest.audio.MAX_FLOAT_AMPLITUDE`, which overflow the features).
    """
    audio, rate = read_audio(path)
    return resample_audio(audio, rate, SAMPLE_RATE)


def load_examples(store: Store, rows: list[dict], source: str, variant: str) -> list[Example]:
    """Audio (16 kHz mono) and target curves of the given utterance rows."""
    examples = []
    for row in rows:
        uid = row[C.UTTERANCE_ID]
        curves = store.load_curves(uid, source, variant, default_fps=float(row[C.FPS]))
        examples.append(Example(uid, load_audio(local_input(row[C.AUDIO_PATH])), curves.values, curves.fps))
    return examples


def checkpoint_of_this_code(store: Store, model_name: str) -> bool:
    """Remove the checkpoint of `model_name` unless this code wrote it, and record this code for the next; whether
    one was removed. Resuming another code's checkpoint (a finished one, after a fix) would keep its weights."""
    folder = store.checkpoint_dir(model_name)
    code, marker = code_digest(__name__), folder / CODE_FILE
    if marker.is_file() and marker.read_text(encoding="utf-8") == code:
        return False
    removed = (folder / CHECKPOINT_NAME).exists()
    if removed:
        store.delete_path(folder / CHECKPOINT_NAME)
    if not store.remote:   # object storage has no folders to make
        folder.mkdir(parents=True, exist_ok=True)
    store.write_file(marker, lambda tmp: tmp.write_text(code, encoding="utf-8"))
    return removed


def checkpoint_work_dir(store: Store, model_name: str) -> Path:
    """The local folder the training writes its checkpoint in: the store's checkpoint folder itself, or, for a store
    on object storage, a local folder holding a fresh copy of the store's checkpoint (none when the store has
    none), so that a training resumes on any machine from the last epoch any machine uploaded."""
    if not store.remote:
        return store.checkpoint_dir(model_name)
    work = store.local_work_dir(store.checkpoint_dir(model_name))
    stored, local = store.checkpoint_dir(model_name) / CHECKPOINT_NAME, work / CHECKPOINT_NAME
    local.unlink(missing_ok=True)
    if stored.is_file():
        shutil.copyfile(store.local_file(stored), local)
    return work


def upload_checkpoint(store: Store, model_name: str, work: Path) -> None:
    """After an epoch on a store on object storage: the checkpoint written in `work` replaces the store's."""
    if store.remote and (work / CHECKPOINT_NAME).is_file():
        store.write_file(store.checkpoint_dir(model_name) / CHECKPOINT_NAME,
                         lambda tmp: shutil.copyfile(work / CHECKPOINT_NAME, tmp))


def metrics_rows(run: str, model: str, condition: str, overall: float, per_utterance: dict[str, float],
                 per_viseme: np.ndarray, epoch: int | None = None) -> list[dict]:
    """Rows of the `metrics` table: the aggregate (with per-viseme L1) and one per utterance."""
    aggregate = {C.RUN: run, C.MODEL: model, C.CONDITION: condition, C.UTTERANCE_ID: None, C.EPOCH: epoch,
                 C.L1: overall / 100.0, C.L1_X100: overall}
    # per-viseme columns hold plain L1 like `l1` (per_viseme comes as L1 x 100 from `evaluate`)
    aggregate.update({C.L1_PREFIX + v: float(per_viseme[i]) / 100.0 for i, v in enumerate(VISEMES)})
    rows = [aggregate]
    for uid, value in sorted(per_utterance.items()):
        rows.append({C.RUN: run, C.MODEL: model, C.CONDITION: condition, C.UTTERANCE_ID: uid, C.EPOCH: epoch,
                     C.L1: value / 100.0, C.L1_X100: value})
    return rows


@task(cache_policy=DataOnlyCache(policy=TRAIN_CACHE_POLICY), persist_result=True, result_serializer=RESULT_SERIALIZER,
      task_run_name="train[{model_name}]")
def train_model_task(
    store_root: str, model_name: str, train_rows: list[dict], val_rows: list[dict], source: str, variant: str,
    lineage: dict, config: TrainConfig, device: str = "auto", precision: str = "auto",
    encoder_cache_dir: str | None = None,
) -> dict:
    """Train (or resume) one model; its checkpoints, weights, lineage and per-epoch validation metrics go to the store.

    Weights that turned NaN or infinite are never written (`learning.train.NonFiniteWeightsError`): the task fails,
    the last good checkpoint and any earlier model file of this name stay as they were.

    `device` (auto, cpu, cuda, cuda:N) and `precision` are resolved here, where the work runs (a Dask worker may
    not be the flow's machine); `encoder_cache_dir` keeps wav2vec2's frozen encoder outputs as files.
    """
    store = Store(store_root)
    logger = get_run_logger()
    where = resolve_device(device)  # DeviceError (one line) before any data is read
    train = load_examples(store, train_rows, source, variant)
    val = load_examples(store, val_rows, source, variant)
    history: list[EpochReport] = []
    # the terminal's progress line (epochs done, ETA): an epoch of a large corpus takes minutes
    line = Progress(f"train {model_name}", config.epochs, unit="epochs")

    def report(epoch: EpochReport) -> None:
        history.append(epoch)
        if not line.done and epoch.epoch > 1:  # resumed from a checkpoint: the epochs before it were done then
            line.resume(epoch.epoch - 1)
        line.advance()
        val = "-" if epoch.val_l1_x100 is None else f"{epoch.val_l1_x100:.3f}"  # no validation utterances
        logger.info("%s epoch %d: train L1x100 %.3f, val L1x100 %s, %.0f frames/s", model_name, epoch.epoch,
                    epoch.train_l1_x100, val, epoch.frames_per_s)

    if checkpoint_of_this_code(store, model_name):
        logger.info("%s: the checkpoint was written by other code; training starts over", model_name)
    logger.info("%s: training on %s (precision %s)", model_name, where, precision)
    work = checkpoint_work_dir(store, model_name)

    def epoch_done(epoch: EpochReport) -> None:
        upload_checkpoint(store, model_name, work)
        report(epoch)

    with line:
        result = train_model(train, val, config, checkpoint_dir=work, on_epoch=epoch_done,
                             device=where, precision=precision, encoder_cache=encoder_cache_dir or True)
    if store.remote:
        model_path = store.write_file(store.model_path(model_name),
                                      lambda tmp: save_model(result.model, config, tmp, lineage))
    else:
        model_path = save_model(result.model, config, store.model_path(model_name), lineage)
    # Validation metrics exist only with a validation set: no rows rather than NaN rows (the store refuses NaN).
    rows = []
    for epoch in result.history:
        if epoch.val_l1_x100 is not None and math.isfinite(epoch.val_l1_x100):
            rows.append({C.RUN: "train", C.MODEL: model_name, C.CONDITION: "validation", C.UTTERANCE_ID: None,
                         C.EPOCH: epoch.epoch, C.L1: epoch.val_l1_x100 / 100.0, C.L1_X100: epoch.val_l1_x100})
    overall = float("nan")
    if val:
        overall, per_utt, per_vis = evaluate(result.model, val)
        rows += metrics_rows("final", model_name, "validation", overall, per_utt, per_vis)
    store.write_metrics(model_name, "train", pa.Table.from_pylist(rows, schema=METRICS))
    create_table_artifact(
        key=f"loss-curve-{model_name.lower().replace('_', '-').replace('.', '-')}",
        table=[{"epoch": e.epoch, "train_l1_x100": round(e.train_l1_x100, 3),
                "val_l1_x100": None if e.val_l1_x100 is None else round(e.val_l1_x100, 3),
                "frames_per_s": round(e.frames_per_s)} for e in result.history],
        description=f"{model_name}: L1 x 100 per epoch",
    )
    return {"model": model_name, "epochs": len(result.history), "val_l1_x100": overall,
            "train": len(train), "val": len(val), "path": str(model_path)}


def training_task_for(store: Store, model_name: str):
    """`train_model_task` with the store's result storage; recomputed when the model file is missing from the store."""
    return train_model_task.with_options(
        result_storage=result_storage(store.root),
        refresh_cache=not store.has_model(model_name),
    )
