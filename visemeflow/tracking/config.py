"""What a tracking run is asked for: the solver's weights and schedule (`TrackingConfig`, paper 4.3) and FaceMesh's
settings (`FaceMeshConfig`), apart from the code that runs them, so that reading a config (the CLI's options, a
flow's parameters) imports no torch or MediaPipe. `tracking.solver` and `tracking.facemesh` run them."""

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from visemeflow.visemes import N_VISEMES


class TrackingConfig(BaseModel):
    """Weights of Eq. 1 (paper defaults), guidance sets, solver schedule; ablation switches."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    w_lmk: float = Field(0.8, ge=0, description="w1, landmark loss (Eq. 2).")
    w_rgb: float = Field(1.0, ge=0, description="w2, RGB photo loss (Eq. 3).")
    w_sup: float = Field(800.0, ge=0, description="w3, phoneme-guided suppression (Eq. 4).")
    w_act: float = Field(150.0, ge=0, description="w4, phoneme-guided activation (Eq. 5).")
    w_flow: float = Field(1.0, ge=0, description="w5, optical-flow loss (Eq. 6).")
    w_diff: float = Field(300.0, ge=0, description="w6, temporal consistency (Eq. 7).")
    w_range: float = Field(100.0, ge=0, description="w7, value range (Eq. 8).")
    m: int = Field(3, ge=1, le=N_VISEMES, description="A viseme outside the top m of every neighbouring frame is suppressed.")
    n: int = Field(2, ge=1, le=N_VISEMES, description="The top n visemes of a frame are activated.")
    guidance_radius: int = Field(1, ge=0, description="Neighbouring frames for I_sup: j-radius..j+radius.")
    guidance: bool = Field(True, description="Phoneme guidance on; off sets w3 = w4 = 0 (paper Fig. 3-4 ablation).")
    use_rgb: bool = Field(False, description="Include L_rgb (needs the video frames).")
    use_flow: bool = Field(True, description="Include L_flow (needs the video frames).")
    flow_preset: Literal["ultrafast", "fast", "balanced", "medium"] = Field(
        "balanced", description="How carefully the optical flow (which helps tracking follow the skin between the "
                                "landmarks, L_flow) is computed: balanced (the default), medium (OpenCV's medium "
                                "preset, the default before; slower for the same curves), fast or ultrafast (faster, "
                                "slightly less accurate). balanced is medium without its variational refinement and "
                                "with fewer iterations: measured (bench/end_to_end.py --joint 5 --compare-flow medium:256, one "
                                "core, two runs) GRID end to end 53.0-58.6 -> 55.8-66.6 frames/s and 700x700 talking "
                                "heads 34.1-42.2 -> 47.2-50.6, the flow step 1.9-2.2x as fast, mouth error 1.409 px "
                                "both and 2.742 -> 2.741 px, MBP 14/14 both; synthetic takes (bench/tracking.py) L1 x 100 to the truth 5.14 -> 5.15, "
                                "mouth 0.464 -> 0.469 px (no flow: 5.62). fast (measured against medium before the "
                                "flow ran on the lower face): GRID 47-54 -> 62-70 frames/s, talking heads 32 -> "
                                "50-51, mouth error 1.410 -> 1.420 px and 2.741 -> 2.762 px, L1 x 100 5.135 -> 5.174 "
                                "(`tracking.optical_flow.FlowConfig.preset`, `PRESET_SETTINGS`).")
    flow_max_roi_px: int | None = Field(
        256, ge=16, description="Largest size in pixels of the face the optical flow works on: a larger face is "
                                "shrunk until its longer side fits (smaller: faster, slightly less accurate; none, null "
                                "in a JSON config: never shrunk). 256 instead of 480: 1.7x the flow's speed on 700x700 "
                                "talking heads, mouth error 2.730 -> 2.733 px; GRID's faces are smaller and unchanged. "
                                "192: talking heads end to end 31.8 -> 40.0 frames/s per core, mouth error 2.741 -> "
                                "2.747 px (bench/end_to_end.py --joint 5 --compare-flow medium:192; "
                                "`FlowConfig.max_roi_px`). 160 is the speed setting for large faces (figures in "
                                "docs/reference.md, 'The face's size for DIS').")
    flow_region: Literal["face", "lower"] = Field(
        "lower", description="Where the optical flow is computed: lower (the default: the chin, the nose's base and "
                             "the mouth, which hold every point the flow term follows, at the whole face's "
                             "resolution) or face (the whole face, as before; slower, the same curves within "
                             "0.001 px of mouth error). Measured (bench/end_to_end.py --compare-config "
                             "'{\"flow_region\": \"face\"}', one core): flow 137 -> 281 frames/s on GRID and 48 -> "
                             "89 on 700x700 talking heads, end to end 46.3 -> 58.5 and 29.3 -> 41.3; mouth error "
                             "1.410 -> 1.409 px and 2.741 -> 2.742 px, MBP 14/14 both; synthetic L1 x 100 5.14 both "
                             "(`tracking.utterance.flow_regions`).")
    speaker_identity: bool = Field(
        False, description="Fit the face (ICT identity modes) and camera focal length of real video once per speaker "
                           "and image size, on neutral frames pooled from `identity_clips` of the speaker's clips, "
                           "rather than to each clip's own neutral frames (paper 4.2). Measured (bench/end_to_end.py "
                           "--compare-config '{\"speaker_identity\": true}', CPU time): GRID identity share 12.9% -> "
                           "3.6% (10 clips; the fit is shared by all of a speaker's clips), mouth error 1.410 -> "
                           "1.411 px, MBP 14/14 both; talking heads 2.741 -> 2.692 px. Off until confirmed: GRID's "
                           "error is not lower and a corpus folder of several people would share one face.")
    identity_clips: int = Field(
        5, ge=1, description="Speaker identity: the first this many of a speaker's clips (by utterance id, with "
                             "landmarks) give neutral frames.")
    identity_frames: int = Field(
        10, ge=1, description="Speaker identity: neutral frames in all, ceil(this / clips) from each chosen clip (10 "
                              "from one clip is the per-clip fit's choice).")
    solver: Literal["fast", "faithful"] = Field("fast", description="Whole-utterance batch, or the paper's per-frame schedule.")
    iterations: int = Field(250, ge=1, description="Faithful: Adam iterations per frame and pass.")
    lr: float = Field(0.1, gt=0, description="Faithful: Adam learning rate.")
    lr_decay: float = Field(0.9, gt=0, le=1, description="Faithful: learning-rate factor applied every 10 iterations.")
    passes: tuple[str, ...] = Field(("forward", "backward"), description="Faithful: passes through the frames.")
    fast_iterations: int = Field(
        200, ge=1, description="Fast: Adam iterations over the whole utterance. 200 rather than 300 (with 50 pose "
                               "iterations rather than 200): solver 1.9x faster, closer to the synthetic truth "
                               "(L1 x 100 5.99 -> 5.58), GRID mouth error 1.387 -> 1.379 px, talking heads 2.733 -> "
                               "2.741 px (bench/end_to_end.py --compare-config).")
    fast_lr: float = Field(0.05, gt=0, description="Fast: peak Adam learning rate (cosine decay).")
    fast_method: Literal["lm", "adam"] = Field(
        "adam", description="Fast: Adam (the default), or Levenberg-Marquardt on the block-tridiagonal least squares "
                            "(faster, lower objective, further from the synthetic truth: module docstring)."
    )
    lm_iterations: int = Field(40, ge=1, description="Fast, LM: most iterations per round (it stops on convergence).")
    lm_pose_iterations: int = Field(20, ge=0, description="Fast, LM: most rigid-pose iterations (0 = PnP only).")
    lm_flow_rounds: int = Field(2, ge=1, description="Fast, LM with L_flow: rounds, the correspondences refreshed at each.")
    rgb_iterations: int = Field(20, ge=0, description="Fast with L_rgb: refinement iterations including the photo term.")
    mouth_weight: float = Field(1.0, ge=0, description="beta_k of the 20 mouth landmarks (48-67).")
    face_weight: float = Field(0.3, ge=0, description="beta_k of brows, eyes and nose (17-47).")
    jaw_weight: float = Field(0.0, ge=0, description="beta_k of the jaw contour (0-16): 2D silhouette points.")
    pose_iterations: int = Field(50, ge=0, description="Rigid pose initialisation iterations (Adam; 200 before).")
    box: Literal["projected", "soft"] = Field(
        "projected",
        description=(
            "How weights are kept in [0, 1]: 'projected' clamps after every optimiser step (L_range is then zero); "
            "'soft' is the paper's L_range penalty and a truncation at the end. With the paper's weights the soft "
            "form is unbounded below once two activated visemes exceed 1 (L_act gives each -150/2 x^2, L_range only "
            "+100/2 (x-1)^2), so only the landmarks hold the weights back."
        ),
    )
    pose_lr_factor: float = Field(
        0.1, gt=0, description="Learning rate of the head pose (rad, cm) relative to the viseme weights' rate."
    )
    reference_face_px: float = Field(
        1000.0, gt=0, description="Face height (brow to chin) at which pixel residuals are measured (see module doc)."
    )

    def effective(self) -> "TrackingConfig":
        """The config with the ablation switches applied to the weights."""
        updates = {}
        if not self.guidance:
            updates.update(w_sup=0.0, w_act=0.0)
        if not self.use_rgb:
            updates["w_rgb"] = 0.0
        if not self.use_flow:
            updates["w_flow"] = 0.0
        return self.model_copy(update=updates)

    @property
    def variant(self) -> str:
        """Name of the curves this configuration produces, e.g. `guided-fast`, `unguided-faithful-rgb`."""
        parts = ["guided" if self.guidance else "unguided", self.solver]
        if self.use_rgb:
            parts.append("rgb")
        if not self.use_flow:
            parts.append("noflow")
        return "-".join(parts)


class FaceMeshConfig(BaseModel):
    """Settings of a FaceMesh run over one clip (part of the landmarks stage's cache key)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    refine_landmarks: bool = Field(True, description="478 points with the iris refinement; off: 468 (faster).")
    max_faces: int = Field(4, ge=2, le=16, description="Faces followed at once when a clip shows more than one.")
    min_detection_confidence: float = Field(0.5, ge=0, le=1)
    min_tracking_confidence: float = Field(0.5, ge=0, le=1)
    min_detected_share: float = Field(
        0.5, ge=0, le=1, description="A clip whose face is found on fewer frames than this share is rejected.")
    probe_every: int = Field(
        10, ge=0, description="Frames between face-detector probes for a second face; 0: always run multi-face.")
