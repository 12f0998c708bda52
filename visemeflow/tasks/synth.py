"""Synthetic-corpus task: one utterance's true curves, video, audio, landmarks and camera."""

import json
import shutil
import tempfile
from contextlib import nullcontext
from pathlib import Path

import soundfile as sf
from prefect import get_run_logger, task

from visemeflow.atomic import atomic_write, atomic_write_text
from visemeflow.hashing import stable_hash
from visemeflow.ingest.audio import read_audio
from visemeflow.ingest import CorpusEntry, IngestConfig, ingest_utterance
from visemeflow.location import is_url, local_input, put_file
from visemeflow.phonetics.types import VisemeSegment
from visemeflow.rig import load_rig
from visemeflow.schemas import C, CurveSource, Curves, split_utterance_id
from visemeflow.storage import Store
from visemeflow.synth.take import SynthConfig, camera_record, make_take, render_take
from visemeflow.tasks.code_version import code_digest
from visemeflow.tasks.common import CACHE_POLICY, RESULT_SERIALIZER
from visemeflow.timebase import frame_count
from visemeflow.tracking.landmarks import write_landmarks
from visemeflow.tracking.video import write_video

SOURCE = CurveSource.GROUND_TRUTH


def truth_variant(config: SynthConfig) -> str:
    """`cm-seed0`: Cohen-Massaro dynamics with the seed; a hash is added when other constants differ."""
    name = f"cm-seed{config.truth.seed}"
    if config.truth != type(config.truth)(seed=config.truth.seed):
        name += "-" + stable_hash(config.truth, size=4)
    return name


@task(cache_policy=CACHE_POLICY, persist_result=True, result_serializer=RESULT_SERIALIZER,
      task_run_name="synth[{entry[utterance_id]}]", retries=0)
def synth_utterance(
    entry: dict, out_root: str, rig_path: str, rig_hash: str, config: SynthConfig, store_root: str
) -> dict[str, object]:
    """Render one utterance of the source corpus into the synthetic corpus, true curves into the store."""
    source = CorpusEntry(**entry)
    ingested = ingest_utterance(source, IngestConfig())
    segments = [
        VisemeSegment(p[C.VISEME], p[C.START_S], p[C.END_S], p[C.WORD_INDEX], p[C.PHONEME] or "")
        for p in ingested.phones if p[C.VISEME] is not None
    ]
    n_frames = frame_count(ingested.utterance[C.DURATION_S], config.fps)
    rig = load_rig(rig_path)
    take = make_take(rig, segments, n_frames, source.speaker, source.utterance_id, config)

    # The output is a corpus: its folders are the id's speaker and name as they are (not store paths). On object
    # storage the files are written in a local folder first, then each uploaded whole, the video last: the flow
    # takes an utterance whose video is there as rendered.
    speaker, name = split_utterance_id(source.utterance_id)
    remote = is_url(out_root)
    with tempfile.TemporaryDirectory(prefix="visemeflow-synth-") if remote else nullcontext(out_root) as base:
        folder = Path(base) / speaker
        folder.mkdir(parents=True, exist_ok=True)
        alignment = folder / (name + Path(source.alignment_path).suffix)
        audio = folder / f"{name}.wav"
        atomic_write(alignment, lambda tmp: shutil.copyfile(local_input(source.alignment_path), tmp))
        samples, rate = read_audio(local_input(source.audio_path))
        atomic_write(audio, lambda tmp: sf.write(tmp, samples, rate, subtype="PCM_16", format="WAV"))
        video = write_video(folder / f"{name}.{config.video_ext}", render_take(rig, take), config.fps, samples, rate)
        landmarks = write_landmarks(take.landmarks, folder / f"{name}.landmarks.parquet")
        camera = folder / f"{name}.camera.json"
        atomic_write_text(camera, json.dumps(camera_record(take), indent=1))
        if remote:
            alignment, audio, camera, landmarks, video = (
                put_file(f, f"{out_root}/{speaker}/{Path(f).name}") for f in (alignment, audio, camera, landmarks, video))

    variant = truth_variant(config)
    Store(store_root).save_curves(Curves(
        take.curves, config.fps, source.utterance_id, SOURCE, variant,
        f"{SOURCE}:{source.content_hash}:{stable_hash(config)}:{rig_hash}:{code_digest(__name__)}",
    ))
    get_run_logger().info("%s: %d frames -> %s", source.utterance_id, n_frames, video)
    return {"utterance_id": source.utterance_id, "frames": n_frames, "video": str(video),
            "landmarks": str(landmarks), "variant": variant}
