"""Prediction task: the viseme curves of one audio file (or a video's audio track) from one trained model, written
to the store as source `predicted`, variant = the model's name. The reserved model name `phones` is no trained
model: phones recognised in the audio and the procedural rules (`visemeflow.tasks.models`)."""

import functools
import time

from prefect import get_run_logger, task
from prefect.cache_policies import TASK_SOURCE, Inputs

from visemeflow.ingest.audio import AudioError, AudioFile
from visemeflow.schemas import CurveSource, Curves
from visemeflow.storage import Store
from visemeflow.tasks.code_version import code_digest
from visemeflow.tasks.common import CODE, RESULT_SERIALIZER, DataOnlyCache, result_storage
from visemeflow.tasks.models import load_curve_model

SOURCE = CurveSource.PREDICTED
# INPUTS + TASK_SOURCE + CODE like every task, but not keyed on where the audio lies: its content hash is an input, so
# the same sound under another folder (same utterance id) is a cache hit, and a changed file under the same path is not.
# Nor on where the model runs (`device`): curves predicted on the CPU stay valid for a GPU run.
PREDICT_CACHE_POLICY = Inputs(exclude=["audio_path", "device"]) + TASK_SOURCE + CODE


@functools.lru_cache(maxsize=2)
def _model(store_root: str, name: str, model_hash: str, device: str = "cpu"):
    """The loaded model `name` on `device` (one load for all the files of a run); the hash keys a retrained
    model apart."""
    return load_curve_model(Store(store_root), name, device)[0]


@task(cache_policy=DataOnlyCache(policy=PREDICT_CACHE_POLICY), persist_result=True, result_serializer=RESULT_SERIALIZER,
      task_run_name="predict[{utterance_id}]")
def predict_audio(store_root: str, model_name: str, model_hash: str, audio_path: str, audio_hash: str,
                  utterance_id: str, fps: float, device: str = "auto") -> dict:
    """Predict one file's curves and store them; returns where they are and the real-time factor of this run.

    `model_hash` and `audio_hash` (content hashes of the model file and the audio file) key the cache, so a
    retrained model or changed audio recomputes; the real-time factor is that of the run that computed it (on
    `device`: auto, cpu, cuda or cuda:N, resolved here, where the work runs).
    """
    # torch and the model code load here, where the work runs: a run whose prediction is cached never imports them
    from visemeflow.learning.device import resolve_device
    from visemeflow.learning.longform import predict_long
    from visemeflow.learning.train import predict_curves

    store = Store(store_root)
    model = _model(store_root, model_name, model_hash, str(resolve_device(device)))
    logger = get_run_logger()
    started = time.perf_counter()
    source = AudioFile(audio_path)
    duration = source.n_samples / source.rate
    if round(duration * fps) <= 0:   # no frame of curves (predict_long's count): a reject, not a crash in the store
        raise AudioError(audio_path, "AudioTooShort",
                         f"{1000 * duration:.0f} ms of audio makes no frame of curves at {fps:g} fps (a frame is "
                         f"{1000 / fps:.0f} ms)")

    def progress(done: int, total: int) -> None:
        if total > 1:
            logger.info("%s: chunk %d/%d of %.0f s of audio", utterance_id, done, total, duration)

    # In chunks read from the file as needed: the peak memory of a two-hour file is that of a minute of it.
    curves = predict_long(lambda a, r, n: predict_curves(model, a, r, fps, n_frames=n), source, fps,
                          on_chunk=progress)
    seconds = time.perf_counter() - started
    path = store.save_curves(Curves(curves, fps, utterance_id, SOURCE, model_name,
                                    prediction_provenance(model_name, model_hash, audio_hash, fps)))
    rtf = seconds / max(duration, 1e-9)
    logger.info("%s: %d frames of %.2f s of audio in %.3f s (real-time factor %.4f)", utterance_id,
                len(curves), duration, seconds, rtf)
    return {"utterance_id": utterance_id, "path": str(path), "frames": int(len(curves)), "duration_s": duration,
            "seconds": seconds, "real_time_factor": rtf}


def prediction_provenance(model_name: str, model_hash: str, audio_hash: str, fps: float) -> str:
    """What stored predicted curves were made from: the model's and the audio's content hashes, the frame rate and
    the code."""
    return f"{SOURCE}:{model_name}:{model_hash}:{audio_hash}:{float(fps)!r}:{code_digest(__name__)}"


def prediction_task_for(store: Store, model_name: str, utterance_id: str, provenance: str):
    """`predict_audio` with the store's result storage; recomputed unless the stored curves were made from
    `provenance` (`prediction_provenance`): a missing file, or one another file of the same name or another frame
    rate wrote since, is made again rather than served as a cache hit."""
    return predict_audio.with_options(
        result_storage=result_storage(store.root),
        refresh_cache=store.curves_provenance(SOURCE, model_name, utterance_id) != provenance,
    )
