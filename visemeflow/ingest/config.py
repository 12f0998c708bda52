"""Ingestion settings, validated before any work starts."""

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from visemeflow.timebase import DEFAULT_FPS


class IngestConfig(BaseModel):
    """How alignments and audio are read and checked."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    phone_tiers: tuple[str, ...] = Field(
        ("phones", "phone", "phons", "phonemes", "MAU", "PhonAlign"),
        description="Names of the TextGrid or XRA tier holding phones, tried in order (case-insensitive): MFA, "
                    "P2FA and praatio name it phones/phone/phons, WebMAUS MAU, SPPAS PhonAlign.",
    )
    word_tiers: tuple[str, ...] = Field(
        ("words", "word", "ORT-MAU", "ORT", "TokensAlign"),
        description="Names of the TextGrid or XRA tier holding words, tried in order (WebMAUS ORT-MAU, SPPAS "
                    "TokensAlign).",
    )
    inventory: Literal["auto", "arpabet", "ipa", "xsampa", "pinyin"] = Field(
        "auto", description="Phoneme inventory of the labels; 'auto' detects it per utterance."
    )
    language: str | None = Field(
        None, description="Language of the corpus (e.g. 'en', 'zh'); by default taken from the manifest or inferred."
    )
    alignment_tolerance_s: float = Field(
        0.1, ge=0, description="Largest allowed difference between the alignment's end and the audio duration "
                               "(label files without a file end, HTK/MLF/XRA, may end earlier but not run past it)."
    )
    fps: float = Field(DEFAULT_FPS, gt=0, description="Curve frame rate for utterances without video.")
    val_fraction: float = Field(
        0.1, ge=0, le=1, description="Share of utterances (by a stable hash of the id) put in the 'val' split."
    )
    vowel_weight: float = Field(
        2.0, gt=0, description="Share of a vowel relative to a consonant when word spans are split into phones."
    )
    align_transcripts: bool = Field(
        True, description="Forced-align a transcript beside audio that has no alignment (`NAME.lab` without times, "
                          "`NAME.txt`) with pocketsphinx's English model; off: such utterances are rejects "
                          "(MissingAlignment). English only: a word its dictionary lacks is a reject naming it.",
    )
    grid_time_unit_s: float = Field(
        1.0 / 25000.0, gt=0, description="Time unit of word alignment files (`start end word`); GRID uses 1/25000 s."
    )


class CaptureConfig(BaseModel):
    """How captured takes become curves."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    variant: str = Field("arkit-nnls", pattern=r"^[A-Za-z0-9_\-][A-Za-z0-9_.\-]*$",
                         description="Variant name of the `captured` curves written.")
    fps: float | None = Field(None, gt=0, le=1000, description="Capture frame rate of takes whose file has no clock "
                                                               "(NPY, CSV without a time column), unless the manifest "
                                                               "gives one; Live Link takes read theirs from timecodes.")
    max_drift_frames_per_s: float = Field(
        1.0, ge=0, description="Largest allowed difference between the capture's frame count and the audio's "
                               "duration x fps, in frames per second of audio (at least one frame).")
    val_fraction: float = Field(0.1, ge=0, le=1, description="Share of takes (by a stable hash of the id) put in "
                                                             "the 'val' split when the manifest gives none.")
