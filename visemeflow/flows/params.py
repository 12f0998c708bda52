"""Flow parameters as pydantic models, so the Prefect UI shows them as forms and bad values fail first."""

from pathlib import Path
from typing import Annotated, Literal

from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, field_validator, model_validator

from visemeflow.animation.config import AnimateConfig
from visemeflow.learning.default_model import DEFAULT_MODEL
from visemeflow.timebase import DEFAULT_FPS
from visemeflow.ingest.config import CaptureConfig, IngestConfig

from visemeflow.learning.device import DeviceWord, Precision
from visemeflow.flows.stages import RERUNNABLE
from visemeflow.learning.config import AugmentConfig, TrainConfig
from visemeflow.procedural.config import RECOGNISED_MODEL, ProceduralConfig
from visemeflow.schemas.ids import normalize_utterance_id, validate_name
from visemeflow.schemas.sources import CurveSource
from visemeflow.location import parse_root
from visemeflow.synth.config import SynthConfig
from visemeflow.tracking.config import FaceMeshConfig, TrackingConfig

DEFAULT_STORE = Path("visemeflow-out/store")
StoreLocation = Annotated[Path | str, BeforeValidator(parse_root)]
"""A store folder, or a URL of a store on object storage (`s3://bucket/prefix`, kept as text)."""
# the curve sources `animate` puts on characters
SOURCES = (CurveSource.TRACKED, CurveSource.PROCEDURAL, CurveSource.GROUND_TRUTH, CurveSource.PREDICTED)


def _demo_character() -> Path:
    from visemeflow.rig import demo_rig_path   # on first use: the rig package reads glTF (pygltflib)

    return demo_rig_path()


def _demo_characters() -> list[Path]:
    return [_demo_character()]


def _existing(corpus: Path | str) -> Path | str:
    if isinstance(corpus, Path) and not corpus.exists():
        raise ValueError(f"corpus {corpus} does not exist")
    return corpus


CorpusLocation = Annotated[Path | str, BeforeValidator(parse_root)]
"""A corpus folder, manifest or file, or its URL on object storage (`s3://bucket/corpus`, kept as text): the tasks
read its files through local copies (`location.local_input`), so no machine needs it on a shared disk."""
CorpusPath = Annotated[CorpusLocation, AfterValidator(_existing)]
"""A `CorpusLocation` whose folder or file exists (a URL is checked when it is read)."""
# a model's name as a file name in the store (no path, no dot-dot)
ModelName = Annotated[str, AfterValidator(lambda name: validate_name(name, "model name"))]


class RunnerConfig(BaseModel):
    """Where a stage's per-utterance (or per-model) tasks run."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["threads", "dask"] = Field(
        "threads", description="threads: Prefect's thread pool in the flow's process; dask: a Dask cluster (prefect-dask).",
    )
    threads: int | None = Field(
        None, ge=1, le=1024,
        description="threads: tasks at once (default: Prefect's thread_pool_max_workers setting, else the CPUs).",
    )
    dask_workers: int = Field(
        2, ge=1, le=1024, description="Worker processes of the local Dask cluster, one thread each (not with an address).",
    )
    dask_address: str | None = Field(
        None, description="Scheduler of an existing Dask cluster (tcp://host:8786); default: a local cluster.",
    )


    @model_validator(mode="before")
    @classmethod
    def _address_means_dask(cls, data):
        # a scheduler's address names a Dask cluster: `--dask-address` alone is enough
        if isinstance(data, dict) and data.get("dask_address"):
            data = {**data, "kind": "dask"}
        return data

RunnerField = Field(default_factory=RunnerConfig, description="Where the per-utterance or per-model tasks run.")

# Where and in what precision models run: not part of any cache key or model name (a result computed on the CPU
# stays valid for a GPU run and the other way round); a CUDA request on a machine without CUDA fails in one line.
DeviceField = Field("auto", description="Where models run: auto (a CUDA GPU when there is one, else the CPU), cpu, "
                                        "cuda or cuda:N.")
PrecisionField = Field("auto", description="Training precision on CUDA: auto (bf16 where the GPU has it), fp32, bf16 "
                                           "or fp16 (with loss scaling); the CPU always trains in float32.")
EncoderCacheField = Field(None, description="wav2vec2 presets: folder keeping the frozen CNN encoder's outputs as "
                                            "files (by audio content hash), shared by runs; none: in memory for a run.")


class StoreParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    store: StoreLocation = Field(DEFAULT_STORE, description="Folder of the Parquet store, or its URL on object "
                                                            "storage (s3://bucket/prefix).")
    n_shards: int = Field(
        8, ge=1, le=4096,
        description="Cheap stages run one task per shard of utterances (a stable hash of the id).",
    )


ReplaceField = Field(False, description="Let this corpus replace the one the store was last ingested from, dropping "
                                        "the utterances it lacks (without it such an ingest stops and says so).")


class IngestParams(StoreParams):
    corpus: CorpusPath = Field(..., description="Corpus folder (<speaker>/<name>.wav + .TextGrid) or manifest CSV, "
                                                "or its URL (s3://bucket/corpus).")
    config: IngestConfig = Field(default_factory=IngestConfig)
    replace: bool = ReplaceField



class ProceduralParams(StoreParams):
    config: ProceduralConfig = Field(default_factory=ProceduralConfig)
    variant: str | None = Field(None, description="Name of this curve variant; by default derived from the config.")

    @field_validator("variant")
    @classmethod
    def _safe_variant(cls, variant: str | None) -> str | None:
        return None if variant is None else validate_name(variant, "variant")


class PipelineParams(StoreParams):
    corpus: CorpusLocation = Field(..., description="Corpus folder or manifest CSV, or its URL (s3://bucket/corpus).")
    ingest: IngestConfig = Field(default_factory=IngestConfig)
    replace: bool = ReplaceField
    procedural: ProceduralConfig = Field(default_factory=ProceduralConfig)
    landmarks: FaceMeshConfig = Field(default_factory=FaceMeshConfig)
    tracking: TrackingConfig = Field(default_factory=TrackingConfig)
    rig: Path | None = Field(None, description="Viseme rig for tracking; default: the shipped ICT demo rig.")
    joint_frames: int = Field(
        400, ge=0, le=100_000,
        description="Utterances to track are solved together in groups of about this many frames (as `track "
                    "--joint-frames`); 0: one utterance per task.")
    device: DeviceWord = Field("cpu", description="Where tracking's joint solves run (as `track --device`).")
    runner: RunnerConfig = RunnerField
    characters: list[Path] = Field([], description="Characters to animate with the tracked curves (procedural when "
                                                   "no utterance has a video); none: no animate stage.")
    animate: AnimateConfig = Field(default_factory=AnimateConfig)


class SynthParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    corpus: CorpusPath = Field(..., description="Source corpus: audio + alignments (folder or manifest CSV).")
    out: StoreLocation = Field(Path("visemeflow-out/synth-corpus"),
                               description="Folder of the synthetic corpus written, or its URL on object storage "
                                           "(s3://bucket/prefix: each file uploaded whole).")
    store: StoreLocation = Field(DEFAULT_STORE, description="Store receiving the true curves (source 'ground_truth'): "
                                                           "a folder, or its URL on object storage.")
    rig: Path | None = Field(None, description="Viseme rig (folder, GLB or npz); default: the shipped ICT demo rig.")
    config: SynthConfig = Field(default_factory=SynthConfig)



class TrackParams(StoreParams):
    config: TrackingConfig = Field(default_factory=TrackingConfig)
    rig: Path | None = Field(None, description="Viseme rig (folder, GLB or npz); default: the shipped ICT demo rig.")
    procedural_variant: str | None = Field(
        None, description="Procedural curves that guide tracking; default: those the procedural stage last wrote."
    )
    joint_frames: int = Field(
        400, ge=0, le=100_000,
        description="Utterances to track are solved together in groups of about this many frames (the same curves "
                    "as one by one, less solver time; memory grows with it); 0: one utterance per task.")
    device: DeviceWord = Field(
        "cpu", description="Where the joint solves run: cpu, cuda, cuda:N or auto (a CUDA GPU when there is one); "
                           "larger --joint-frames pay on a GPU. One utterance in its own task runs on the CPU.")
    runner: RunnerConfig = RunnerField


class TrainParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    store: StoreLocation = Field(DEFAULT_STORE, description="The Parquet store: a folder, or s3://bucket/prefix.")
    config: TrainConfig = Field(default_factory=TrainConfig)
    source: Literal["tracked", "ground_truth", "procedural", "captured"] = Field("tracked", description="Curves to learn.")
    variant: str | None = Field(None, description="Variant of those curves; may be omitted when only one exists.")
    model_name: str | None = Field(None, description="Name of the model in the store; default: preset + a hash.")
    device: DeviceWord = DeviceField
    precision: Precision = PrecisionField
    encoder_cache_dir: Path | None = EncoderCacheField

    @field_validator("model_name")
    @classmethod
    def _safe_model(cls, name: str | None) -> str | None:
        if name == RECOGNISED_MODEL:
            raise ValueError(f"the model name {RECOGNISED_MODEL!r} is reserved for curves from recognised phones "
                             "(`visemeflow predict --model phones`); choose another")
        return None if name is None else validate_name(name, "model name")


class SweepParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    store: StoreLocation = Field(DEFAULT_STORE, description="The Parquet store: a folder, or s3://bucket/prefix.")
    config: TrainConfig = Field(default_factory=TrainConfig)
    sizes: list[Annotated[int, Field(ge=1)]] = Field([100, 300, 1000, 3000], min_length=1,
                                                     description="Training-set sizes (nested subsets), each at least 1.")
    steps: int = Field(10000, ge=1, description="Training steps (utterances) per size: the equal budget.")
    source: Literal["tracked", "ground_truth", "procedural", "captured"] = Field("tracked", description="Curves to learn.")
    variant: str | None = Field(None, description="Variant of those curves; may be omitted when only one exists.")
    runner: RunnerConfig = RunnerField
    device: DeviceWord = DeviceField
    precision: Precision = PrecisionField
    encoder_cache_dir: Path | None = EncoderCacheField


class RerunParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    utterance_id: str = Field(..., description="The utterance to rerun, '<speaker>/<name>'.")
    stage: Literal[RERUNNABLE] = Field(  # type: ignore[valid-type] (the stages table's rerunnable rows)
        "procedural", description="The stage to rerun.")
    store: StoreLocation = Field(DEFAULT_STORE, description="Folder of the Parquet store.")
    force: bool = Field(True, description="Recompute even when a cached result is valid.")

    @field_validator("utterance_id")
    @classmethod
    def _valid_id(cls, utterance_id: str) -> str:
        return normalize_utterance_id(utterance_id)  # typed by hand: NFD "ü" from a macOS terminal is the same id


class EvaluateParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    store: StoreLocation = Field(DEFAULT_STORE, description="The Parquet store: a folder, or s3://bucket/prefix.")
    models: list[str] = Field(..., min_length=1, description="Names of trained models in the store; `phones`: the "
                                                             "curves of phones recognised in the audio (no training).")
    conditions: list[Literal["volume", "pitch", "speed", "noise"]] = Field(
        ["volume", "pitch", "speed", "noise"], description="Augmented copies of the validation set to judge on."
    )
    seed: int = Field(0, description="Seed of the augmentations: the same seed gives the same augmented audio.")
    augment: AugmentConfig = Field(default_factory=AugmentConfig, description="Ranges (the paper's by default).")
    source: Literal["tracked", "ground_truth", "procedural", "captured"] | None = Field(
        None, description="Target curves; default: those the first model was trained on.")
    variant: str | None = Field(None, description="Variant of those curves; default: the first model's.")
    device: DeviceWord = Field("auto", description="Where the models run: auto, cpu, cuda or cuda:N (float32 "
                                                   "everywhere; not part of the cache key).")

    @field_validator("models")
    @classmethod
    def _safe_models(cls, models: list[str]) -> list[str]:
        return [validate_name(m, "model name") for m in models]


class AnimateParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    store: StoreLocation = Field(DEFAULT_STORE, description="Folder of the Parquet store, or its URL on object "
                                                            "storage (s3://bucket/prefix).")
    characters: list[Path] = Field(default_factory=_demo_characters, min_length=1,
                                   description="Character files (.glb/.gltf with morph targets, .npz) or mesh "
                                               "folders; default: the shipped ICT demo character.")
    source: str = Field("tracked", description=f"Curves to animate: {', '.join(SOURCES)}.")
    variant: str | None = Field(None, description="Variant of those curves (a model's name for predicted), or several, "
                                                  "comma-separated, in order of preference; none: every stored "
                                                  "variant, each utterance from its own (tracked: guided and "
                                                  "unguided), the one the stage last wrote first.")
    utterances: list[str] | None = Field(None, description="Utterance ids; none: every utterance with such curves.")
    audio: dict[str, Path] = Field(default_factory=dict, description="Audio per utterance id where the utterances "
                                                                     "table has none (predictions).")
    mapping: Path | None = Field(None, description="CSV viseme,shape,weight for characters of any other naming.")
    config: AnimateConfig = Field(default_factory=AnimateConfig)
    out: Path | None = Field(None, description="Folder for the files; none: the store's animations folder.")
    n_shards: int = Field(8, ge=1, le=4096, description="Shards of the rejects table.")

    @field_validator("source")
    @classmethod
    def _safe_source(cls, source: str) -> str:
        return validate_name(source, "curve source")

    @field_validator("utterances")
    @classmethod
    def _valid_ids(cls, ids: list[str] | None) -> list[str] | None:
        return None if ids is None else [normalize_utterance_id(u) for u in ids]


class SpeakParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    store: StoreLocation = Field(DEFAULT_STORE, description="Folder of the Parquet store, or its URL on object "
                                                            "storage (s3://bucket/prefix).")
    model: ModelName = Field("default", description="Name of a trained model in the store; `default`: the model shipped "
                                              "with the package; `phones`: no model, phones recognised in the audio "
                                              "(English).")
    audio: list[Path] = Field(..., min_length=1, description="Audio files (any rate, any channel count) or videos.")
    characters: list[Path] = Field(default_factory=_demo_characters, min_length=1,
                                   description="Character files or folders; default: the shipped ICT demo character.")
    mapping: Path | None = Field(None, description="CSV viseme,shape,weight for characters of any other naming.")
    fps: float = Field(DEFAULT_FPS, gt=0, le=1000, description="Frame rate of the predicted curves and the exports.")
    config: AnimateConfig = Field(default_factory=AnimateConfig)
    out: Path | None = Field(None, description="Folder for the files; none: the store's animations folder.")


class PreviewParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    store: StoreLocation = Field(DEFAULT_STORE, description="Folder of the Parquet store, or its URL on object storage.")
    utterance_id: str = Field(..., description="The utterance, '<speaker>/<name>'.")
    character: Path = Field(default_factory=_demo_character, description="Character file or folder.")
    mapping: Path | None = Field(None, description="CSV viseme,shape,weight for characters of any other naming.")
    sources: list[str] = Field(["procedural", "tracked", "predicted", "ground_truth"],
                               description="Curve sources side by side, each `source` or `source:variant`; sources "
                                           "the utterance lacks are left out (at least one must exist).")
    size: int = Field(360, ge=64, le=2048, description="Panel size in pixels.")
    out: Path | None = Field(None, description="MP4 file; none: <store>/animations/<character>/.../<name>.preview.mp4")
    mode: Literal["blendshape", "bones", "both"] = Field(
        "blendshape", description="blendshape: the character's shapes; bones: its SSDR bones blended by the curves "
                                  "(what the bone exports play); both: each source's blendshape and bone panels side "
                                  "by side.")
    bones: int = Field(32, ge=1, le=512, description="Bone count of the SSDR solve (modes bones and both).")
    meshes: list[str] = Field([], description="Meshes of a .glb/.gltf character to drive (mesh names); none: every "
                                              "mesh whose morph targets match.")
    closure_rule: bool = Field(True, description="Apply the lip rules (visemeflow.articulation) as the exports do: "
                                                 "lips close at b/p/m and touch the teeth at f/v, bounded opening.")
    force: bool = Field(False, description="Render again even when the MP4 there was made from the same inputs.")

    @field_validator("utterance_id")
    @classmethod
    def _valid_id(cls, utterance_id: str) -> str:
        return normalize_utterance_id(utterance_id)


class PredictParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    store: StoreLocation = Field(DEFAULT_STORE, description="The Parquet store: a folder, or s3://bucket/prefix.")
    model: ModelName = Field(DEFAULT_MODEL, description="Name of a trained model in the store; `default`: the model shipped "
                                                   "with the package (installed into the store on first use); "
                                                   "`phones`: no model, phones recognised in the audio (English).")
    audio: list[Path] = Field(..., min_length=1, description="Audio files (any rate, any channel count) or videos.")
    fps: float = Field(DEFAULT_FPS, gt=0, le=1000, description="Frame rate of the curves.")
    out: Path | None = Field(None, description="Folder for CSV and JSON copies of the curves (none: store only).")
    device: DeviceWord = Field("auto", description="Where the model runs: auto (a CUDA GPU when there is one), cpu, "
                                                   "cuda or cuda:N (float32; not part of the cache key).")


class ImportCurvesParams(BaseModel):
    """Where the takes are, where the store is, and how captured channels become curves."""

    model_config = ConfigDict(extra="forbid")

    takes: Path = Field(..., description="Manifest CSV of takes (utterance_id,audio,capture,format,channels,names,"
                                         "fps,language,split), a folder holding takes.csv, or a folder "
                                         "<speaker>/<name>.wav + <name>.livelink.csv|.capture.csv|.capture.npy.")
    store: StoreLocation = Field(DEFAULT_STORE, description="Folder of the Parquet store, or its URL on object storage.")
    n_shards: int = Field(8, ge=1, le=4096, description="Shards of the utterances table the rows go to (as ingest).")
    channel_table: Path | None = Field(None, description="Channel -> ARKit table (CSV arkit,expression[,status] or "
                                                         "channel,arkit,weight, or .xlsx) for takes that give none.")
    names: Path | None = Field(None, description="Channel names (.npy of strings or text) for NPY takes that give none.")
    config: CaptureConfig = Field(default_factory=CaptureConfig)

    @field_validator("takes")
    @classmethod
    def _exists(cls, path: Path) -> Path:
        if not path.exists():
            raise ValueError(f"takes {path} do not exist")
        return path

    @field_validator("channel_table", "names")
    @classmethod
    def _file(cls, path: Path | None) -> Path | None:
        if path is not None and not path.is_file():
            raise ValueError(f"{path} is not a file")
        return path


class LandmarksParams(StoreParams):
    config: FaceMeshConfig = Field(default_factory=FaceMeshConfig)
    runner: RunnerConfig = RunnerField


# ---- what a stage last ran with ---------------------------------------------------------------------------------


class StageSettings(BaseModel):
    """What a stage last ran with, kept in the store (`configs/<stage>.json`): `rerun` repeats it for one utterance.
    Keys another version wrote and this one lacks are ignored; a stage that never ran has none (`last_settings`)."""

    model_config = ConfigDict(extra="ignore")

    n_shards: int = Field(8, ge=1, le=4096)


class IngestSettings(StageSettings):
    corpus: str
    config: IngestConfig = Field(default_factory=IngestConfig)


class ProceduralSettings(StageSettings):
    variant: str | None = None
    config: ProceduralConfig = Field(default_factory=ProceduralConfig)


class LandmarksSettings(StageSettings):
    config: FaceMeshConfig = Field(default_factory=FaceMeshConfig)


class TrackSettings(StageSettings):
    rig: str | None = None
    procedural_variant: str | None = None
    config: TrackingConfig = Field(default_factory=TrackingConfig)


class AnimateSettings(StageSettings):
    characters: list[str]
    source: str
    variant: str
    # every variant the run animated, `variant` first (tracked: the guided one and `unguided-...`); `rerun` takes
    # each utterance's own
    variants: list[str] = Field(default_factory=list)
    mapping: str | None = None
    out: str | None = None
    config: AnimateConfig = Field(default_factory=AnimateConfig)


class ImportCurvesSettings(StageSettings):
    takes: str
    channel_table: str | None = None
    names: str | None = None
    config: CaptureConfig = Field(default_factory=CaptureConfig)


SETTINGS: dict[str, type[StageSettings]] = {
    "ingest": IngestSettings, "procedural": ProceduralSettings, "landmarks": LandmarksSettings,
    "track": TrackSettings, "animate": AnimateSettings, "import_curves": ImportCurvesSettings,
}
"""Each stage that records its settings, and their type."""
