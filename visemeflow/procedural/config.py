"""Constants of the JALI-like procedural viseme rules (paper 4.1), as one frozen, validated config."""

from typing import Self

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    field_serializer,
    field_validator,
    model_validator,
)

from visemeflow.visemes import VISEMES


# The model name of curves from phones recognised in the audio (`procedural.recognised`): reserved, no trained
# model may take it.
RECOGNISED_MODEL = "phones"

class ProceduralConfig(BaseModel):
    """Every timing, amplitude and viseme class the procedural rules use; times in seconds."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    fps: float | None = Field(
        None, gt=0.0,
        description=(
            "Frame rate of the curves; default: each utterance's own (its video's, else ingest's --fps)."
        ),
    )
    merge_max_gap_s: float = Field(
        0.05, ge=0.0,
        description="Consecutive segments of the same viseme at most this far apart merge into one key.",
    )
    onset_s: float = Field(
        0.12, ge=0.0,
        description="Onset ramp length: the curve starts rising this long before the segment start (apex).",
    )
    sustain_fraction: float = Field(
        0.75, ge=0.0, le=1.0,
        description="The peak is held from the segment start until start + this fraction of its duration.",
    )
    decay_s: float = Field(
        0.12, ge=0.0,
        description="Decay ramp length: after the sustain the curve falls to 0 over this long.",
    )
    closure_onset_s: float | None = Field(
        None, ge=0.0,
        description="Onset length for closure visemes (MBP, FFF); None: onset_s. Shorter ramps keep a closure's "
                    "rise out of the neighbouring phones.",
    )
    closure_decay_s: float | None = Field(
        None, ge=0.0,
        description="Decay length for closure visemes (MBP, FFF); None: decay_s.",
    )
    lip_onset_s: float = Field(
        0.15, ge=0.0,
        description="Onset length for lip-heavy visemes (earlier start: lip protrusion takes longer).",
    )
    lip_sustain_fraction: float = Field(
        0.9, ge=0.0, le=1.0,
        description="Sustain fraction of the duration for lip-heavy visemes.",
    )
    lip_decay_s: float = Field(
        0.15, ge=0.0,
        description="Decay length for lip-heavy visemes (the lips release late).",
    )
    min_peak: float = Field(
        0.5, ge=0.0, le=1.0,
        description="Lowest peak amplitude of a non-closure, non-tongue viseme, however short.",
    )
    full_peak_duration_s: float = Field(
        0.08, gt=0.0,
        description="Non-closure visemes at least this long reach amplitude 1; shorter ones scale down linearly.",
    )
    tongue_peak: float = Field(
        0.6, ge=0.0, le=1.0,
        description="Peak amplitude of tongue-only visemes, which barely move the lips.",
    )
    max_bridge_s: float = Field(
        0.3, ge=0.0,
        description="Longest run of tongue-only segments through which the preceding lip shape is held.",
    )
    max_lookahead_s: float = Field(
        0.3, ge=0.0,
        description="A lip-heavy viseme anticipating from its word start begins at most this long before its apex.",
    )
    lip_heavy: frozenset[str] = Field(
        frozenset({"UUU", "OHH", "WWW", "SSH", "SSS"}),
        description="Visemes with strong lip protrusion/rounding: longer onset, sustain and decay, word look-ahead.",
    )
    closure_visemes: frozenset[str] = Field(
        frozenset({"MBP", "FFF"}),
        description="Lip closures: always full amplitude, peak held for at least one frame.",
    )
    tongue_only: frozenset[str] = Field(
        frozenset({"LNTD", "GK"}),
        description="Visemes made with the tongue: reduced peak, and the lips keep the neighbouring shape.",
    )
    lookahead_blockers: frozenset[str] = Field(
        frozenset({"MBP", "FFF"}),
        description=(
            "Visemes that stop a lip-heavy viseme anticipating from its word start when they precede it in the "
            "word (the lips must close for them); other lip-heavy visemes co-articulate, as in 'stew'."
        ),
    )
    closure_rule: bool = Field(
        True,
        description=(
            "Apply the lip rules of visemeflow.articulation to the curves: other visemes yield during MBP and FFF, "
            "so bilabials close and labiodentals touch the teeth on the mesh, and no blend opens wider than AHH."
        ),
    )

    @field_validator("lip_heavy", "closure_visemes", "tongue_only", "lookahead_blockers")
    @classmethod
    def _known_visemes(cls, names: frozenset[str]) -> frozenset[str]:
        """Reject names that are not among the 16 visemes."""
        unknown = sorted(set(names) - set(VISEMES))
        if unknown:
            raise ValueError(f"unknown viseme(s) {unknown}; expected names from {', '.join(VISEMES)}")
        return names

    @field_serializer("lip_heavy", "closure_visemes", "tongue_only", "lookahead_blockers")
    def _sorted(self, names: frozenset[str]) -> list[str]:
        """Sets dump sorted, so config hashes (cache keys, variant names) are the same in every process."""
        return sorted(names)

    @model_validator(mode="after")
    def _closure_not_tongue(self) -> Self:
        """A viseme cannot be both a full lip closure and tongue-only."""
        both = sorted(self.closure_visemes & self.tongue_only)
        if both:
            raise ValueError(f"viseme(s) {both} are in both closure_visemes and tongue_only")
        return self
