"""Flow parameters as pydantic models, so the Prefect UI shows them as forms and bad values fail first."""

from pathlib import Path
from typing import Annotated, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, field_validator

from visemeflow.animation.package import AnimateConfig
from visemeflow.ingest import IngestConfig
from visemeflow.learning.augment import AugmentConfig
from visemeflow.learning.device import DeviceWord, Precision
from visemeflow.learning.train import TrainConfig
from visemeflow.procedural import ProceduralConfig
from visemeflow.procedural.recognised import RECOGNISED_MODEL
from visemeflow.schemas import normalize_utterance_id, validate_name
from visemeflow.synth.take import SynthConfig
from visemeflow.tracking.facemesh import FaceMeshConfig
from visemeflow.tracking.solver import TrackingConfig

DEFAULT_STORE = Path("visemeflow-out/store")


def _existing(corpus: Path) -> Path:
    if not corpus.exists():
        raise ValueError(f"corpus {corpus} does not exist")
    return corpus


CorpusPath = Annotated[Path, AfterValidator(_existing)]


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

    store: Path = Field(DEFAULT_STORE, description="Folder of the Parquet store.")
    n_shards: int = Field(
        8, ge=1, le=4096,
        description="Cheap stages run one task per shard of utterances (a stable hash of the id).",
    )


class IngestParams(StoreParams):
    corpus: CorpusPath = Field(..., description="Corpus folder (<speaker>/<name>.wav + .TextGrid) or manifest CSV.")
    config: IngestConfig = Field(default_factory=IngestConfig)



class ProceduralParams(StoreParams):
    config: ProceduralConfig = Field(default_factory=ProceduralConfig)
    variant: str | None = Field(None, description="Name of this curve variant; by default derived from the config.")

    @field_validator("variant")
    @classmethod
    def _safe_variant(cls, variant: str | None) -> str | None:
        return None if variant is None else validate_name(variant, "variant")


class PipelineParams(StoreParams):
    corpus: Path = Field(..., description="Corpus folder or manifest CSV.")
    ingest: IngestConfig = Field(default_factory=IngestConfig)
    procedural: ProceduralConfig = Field(default_factory=ProceduralConfig)
    landmarks: FaceMeshConfig = Field(default_factory=FaceMeshConfig)
    tracking: TrackingConfig = Field(default_factory=TrackingConfig)
    rig: Path | None = Field(None, description="Viseme rig for tracking; default: the shipped ICT demo rig.")
    runner: RunnerConfig = RunnerField
    characters: list[Path] = Field([], description="Characters to animate with the tracked curves (procedural when "
                                                   "no utterance has a video); none: no animate stage.")
    animate: AnimateConfig = Field(default_factory=AnimateConfig)


class SynthParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    corpus: CorpusPath = Field(..., description="Source corpus: audio + alignments (folder or manifest CSV).")
    out: Path = Field(Path("visemeflow-out/synth-corpus"), description="Folder of the synthetic corpus written.")
    store: Path = Field(DEFAULT_STORE, description="Store receiving the true curves (source 'ground_truth').")
    rig: Path | None = Field(None, description="Viseme rig (folder, GLB or npz); default: the shipped ICT demo rig.")
    config: SynthConfig = Field(default_factory=SynthConfig)



class TrackParams(StoreParams):
    config: TrackingConfig = Field(default_factory=TrackingConfig)
    rig: Path | None = Field(None, description="Viseme rig (folder, GLB or npz); default: the shipped ICT demo rig.")
    procedural_variant: str | None = Field(
        None, description="Procedural curves that guide tracking; default: those the procedural stage last wrote."
    )
    runner: RunnerConfig = RunnerField


class TrainParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    store: Path = Field(DEFAULT_STORE, description="Folder of the Parquet store.")
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

    store: Path = Field(DEFAULT_STORE, description="Folder of the Parquet store.")
    config: TrainConfig = Field(default_factory=TrainConfig)
    sizes: list[int] = Field([100, 300, 1000, 3000], description="Training-set sizes (nested subsets).")
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
    stage: Literal["ingest", "procedural", "landmarks", "track", "animate"] = Field(
        "procedural", description="The stage to rerun.")
    store: Path = Field(DEFAULT_STORE, description="Folder of the Parquet store.")
    force: bool = Field(True, description="Recompute even when a cached result is valid.")

    @field_validator("utterance_id")
    @classmethod
    def _valid_id(cls, utterance_id: str) -> str:
        return normalize_utterance_id(utterance_id)  # typed by hand: NFD "ü" from a macOS terminal is the same id


class EvaluateParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    store: Path = Field(DEFAULT_STORE, description="Folder of the Parquet store.")
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
