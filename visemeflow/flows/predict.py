"""The `predict` flow: viseme curves of new audio from a trained model (paper 5.1), one cached task per file.

Each file becomes the utterance `predict/<file stem>` with curves of source `predicted`, variant = the model's name.
A task is keyed on the model file's and the audio file's content hashes (and the frame rate), so running the flow
again on the same files is all cache hits, and a retrained model or a changed file recomputes only what changed.
With `out`, CSV and JSON copies of each file's curves (`visemeflow.animation.export`) are written there. A markdown
artifact lists the outputs and the real-time factor of each file. The model runs on `device` (float32), which is not
part of the cache key: curves predicted on the CPU are a cache hit for a GPU run. A device this machine does not have
fails first, in one line (`visemeflow.learning.device.DeviceError`).

The model name `phones` is reserved: no trained model, but phones recognised in the audio (pocketsphinx's English
model) turned into curves by the procedural rules (`visemeflow.procedural.recognised`), keyed on the recogniser's
settings instead of a model file.
"""

import re
import unicodedata
from pathlib import Path

from prefect import flow, get_run_logger
from prefect.artifacts import create_markdown_artifact
from pydantic import BaseModel, ConfigDict, Field, field_validator

from visemeflow.animation.export import CurveTrack, write_export
from visemeflow.hashing import file_hash
from visemeflow.learning.default_model import DEFAULT_MODEL, is_shipped, shipped_model_path
from visemeflow.learning.device import DeviceWord, resolve_device
from visemeflow.schemas import C, curves_array
from visemeflow.schemas.ids import InvalidIdError, make_utterance_id, validate_name
from visemeflow.storage import Store
from visemeflow.tasks.models import is_trained, model_hash
from visemeflow.tasks.predict import SOURCE, prediction_task_for

EXPORT_FORMATS = ("csv", "json")
# as flows.params.DEFAULT_STORE; not imported from there, which loads every stage's config (a second per `predict`)
DEFAULT_STORE = Path("visemeflow-out/store")


class PredictParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    store: Path = Field(DEFAULT_STORE, description="Folder of the Parquet store.")
    model: str = Field(DEFAULT_MODEL, description="Name of a trained model in the store; `default`: the model shipped "
                                                   "with the package (installed into the store on first use); "
                                                   "`phones`: no model, phones recognised in the audio (English).")
    audio: list[Path] = Field(..., min_length=1, description="Audio files (any rate, any channel count) or videos.")
    fps: float = Field(30.0, gt=0, le=1000, description="Frame rate of the curves.")
    out: Path | None = Field(None, description="Folder for CSV and JSON copies of the curves (none: store only).")
    device: DeviceWord = Field("auto", description="Where the model runs: auto (a CUDA GPU when there is one), cpu, "
                                                   "cuda or cuda:N (float32; not part of the cache key).")

    @field_validator("model")
    @classmethod
    def _safe_model(cls, name: str) -> str:
        return validate_name(name, "model name")


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
        elif not store.has_model(model) or file_hash(store.model_path(model)) != file_hash(shipped):
            # a store made by an older release holds that release's shipped model under this name: the package's
            # own wins (the names of shipped models are reserved), so an upgrade is not silently ignored
            replaced = store.has_model(model)
            store.install_model(model, shipped)
            get_run_logger().info("%s the shipped %s model into %s", "updated" if replaced else "installed", model,
                                  store.model_path(model))
    if is_trained(model) and store.has_model(model):
        check_whisper_weights(store.model_path(model))


def check_whisper_weights(path: Path) -> None:
    """LookupError naming the `visemeflow[whisper]` extra when the model at `path` runs on the packaged Whisper
    weights and they are not installed."""
    import json

    import torch

    from visemeflow.learning.features import FeatureConfig

    blob = torch.load(path, map_location="cpu", weights_only=True)
    fcfg = FeatureConfig.model_validate_json(blob["feature_config"])
    if fcfg.kind != "whisper" or fcfg.whisper_source != "package":
        return
    from visemeflow.learning import whisper

    if (whisper.whisper_cache_dir() / whisper.PACKAGE_DIRNAME / "model.bin").is_file():
        return  # assembled before (loading verifies it)
    try:
        whisper._package_part_paths()
    except whisper.WhisperWeightsMissing:
        raise LookupError(f"model {json.loads(blob['config']).get('preset')} needs the Whisper-base weights, "
                          f"which are not installed: {whisper.PACKAGE_EXTRA_HINT}") from None


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


@flow(name="predict", flow_run_name="predict[{params.model}]")
def predict_flow(params: PredictParams) -> dict:
    """Predict the curves of each audio file with one model; curves to the store, optional CSV/JSON copies."""
    resolve_device(params.device)
    store = Store(params.store)
    ensure_model(store, params.model)
    if is_trained(params.model) and not store.has_model(params.model):
        known = store.model_names()
        raise LookupError(f"no trained model named {params.model} in {store.root}; "
                          f"known models: {', '.join(known) or 'none (run visemeflow train first)'}")
    missing = [str(p) for p in params.audio if not Path(p).is_file()]
    if missing:
        raise LookupError(f"no such audio file: {', '.join(missing)}")
    digest = model_hash(store, params.model)
    rows = []
    for audio in params.audio:
        uid = prediction_id(audio)
        state = prediction_task_for(store, params.model, uid)(
            str(store.root), params.model, digest, str(audio), file_hash(audio), uid, float(params.fps),
            params.device, return_state=True,
        )
        result = state.result()  # raises the task's error (unreadable audio, ...)
        exports = []
        if params.out is not None:
            track = curve_track(store, uid, SOURCE, params.model)
            exports = [str(write_export(track, path, fmt)) for fmt, path in export_paths(params.out, uid).items()]
        rows.append({**result, "audio": str(audio), "model": params.model, "cached": state.name == "Cached",
                     "exports": exports})
    markdown = _markdown(params.model, rows)
    create_markdown_artifact(key="predictions", markdown=markdown,
                             description=f"curves predicted by {params.model}, with real-time factors")
    get_run_logger().info("predict %s: %d files, %d cached", params.model, len(rows), sum(r["cached"] for r in rows))
    return {"model": params.model, "predictions": rows}
