"""What to export for each (utterance, character) (`AnimateConfig`), apart from the exporters, so that reading it
(the CLI's options, the animate flow's parameters) imports no exporter; its checks read the table of formats
(`animation.formats.EXPORTERS`), which imports no writer."""

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from visemeflow.animation.formats import EXPORTERS, bone_only_formats

DEFAULT_FORMATS: tuple[str, ...] = ("glb", "usd", "livelink", "json")
FORMATS_HELP = (f"Export formats, any of {', '.join(n for n in EXPORTERS if n not in bone_only_formats())}; in bone "
                f"mode also {', '.join(bone_only_formats())}.")


class AnimateConfig(BaseModel):
    """What to export for each (utterance, character)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    formats: tuple[str, ...] = Field(DEFAULT_FORMATS, min_length=1, description=FORMATS_HELP)
    fps: float | None = Field(None, gt=0, le=1000, description="Frame rate of the exports; none: the curves' own "
                                                                 "(other rates are resampled, never stretched).")
    convention: str | None = Field(None, description="arkit52, oculus15, vrm5 or visemeflow16; none: detected from the "
                                                      "character's shape names.")
    audio: bool = Field(True, description="Write the utterance's audio beside the exports as <stem>.wav.")
    preview: bool = Field(False, description="Also render <stem>.mp4: the character driven by these curves, with "
                                             "the audio and the current phone (H.264 + AAC).")
    mode: Literal["blendshape", "bones"] = Field(
        "blendshape", description="blendshape: the character's shapes are animated; bones: its visemes become SSDR "
                                  "bones and glb/usd are skinned bone animation (pose-csv/pose-json: the poses).")
    bones: int = Field(32, ge=1, le=512, description="Bone count of the SSDR solve in bone mode.")
    closure_rule: bool = Field(
        True, description="Lip rules before the curves drive the character: lips close at b/p/m and touch the teeth "
                          "at f/v whatever else is active, and no blend opens wider than the widest viseme (AHH).")
    meshes: tuple[str, ...] = Field((), description="Meshes of a .glb/.gltf character to drive (mesh names); default: "
                                                    "every mesh whose morph targets match.")

    @model_validator(mode="after")
    def _pose_tables_need_bones(self):
        poses = [f for f in self.formats if EXPORTERS[f].write is None]
        if poses and self.mode != "bones":
            raise ValueError(f"{', '.join(poses)} are bone-mode formats: add --mode bones")
        return self

    @field_validator("formats", mode="before")
    @classmethod
    def _known_formats(cls, value):
        if isinstance(value, str):
            value = value.split(",")
        value = [f.strip().lower() for f in value if f.strip()]   # GLB as glb
        unknown = [f for f in value if f not in EXPORTERS]
        if unknown:
            raise ValueError(f"unknown export format(s) {', '.join(unknown)}; known: {', '.join(EXPORTERS)}")
        return tuple(dict.fromkeys(value))

    @field_validator("convention")
    @classmethod
    def _known_convention(cls, value: str | None) -> str | None:
        from visemeflow.shapes.conventions import CONVENTIONS

        if value is not None and value not in CONVENTIONS:
            raise ValueError(f"unknown convention {value!r}; known: {', '.join(CONVENTIONS)} (or give a mapping CSV)")
        return value
