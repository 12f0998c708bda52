"""One synthetic take: true curves, rendered frames and noisy detected landmarks of one utterance.

The true curves come from `synth.dynamics` (a model of another family than the procedural rules), the
frames from the rig driven by them through `render.raster` (a numpy rasteriser, not the tracker's
differentiable renderer), with small head motion and lighting changes from `synth.motion`. Landmarks
are the rig's landmark vertices projected by the same camera, plus detector-like noise and occasional
missed frames.
"""

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from visemeflow.phonetics.types import VisemeSegment
from visemeflow.rig import VisemeRig, evaluate_rig
from visemeflow.synth.config import SynthConfig
from visemeflow.synth.dynamics import generate_ground_truth
from visemeflow.synth.motion import SceneTrack, scene_track
from visemeflow.render.raster import Camera, Pose, frontal_pose, project, render_mesh
from visemeflow.tracking.landmarks import LandmarkTrack

RENDER_CHUNK = 64


@dataclass(frozen=True)
class SyntheticTake:
    """Everything known about one synthetic utterance except its pixels (rendered lazily)."""

    curves: np.ndarray        # (frames, 16) true viseme weights
    camera: Camera
    poses: tuple[Pose, ...]   # per frame
    scene: SceneTrack
    landmarks: LandmarkTrack  # noisy detections, (frames, 68, 2)
    true_landmarks: np.ndarray  # (frames, 68, 2) exact projections (NaN for landmarks the rig lacks)


def _rng(*keys: object) -> np.random.Generator:
    import zlib

    return np.random.default_rng([zlib.crc32(str(k).encode()) for k in keys])


def frame_poses(base: Pose, scene: SceneTrack) -> tuple[Pose, ...]:
    """The base pose moved by the scene's per-frame head rotation and translation."""
    t0 = np.asarray(base.translation)
    return tuple(
        Pose(tuple(float(v) for v in r), tuple(float(v) for v in t0 + t))
        for r, t in zip(scene.rotations, scene.translations)
    )


def project_landmarks(rig: VisemeRig, curves: np.ndarray, camera: Camera, poses: Sequence[Pose]) -> np.ndarray:
    """(frames, 68, 2) exact pixel positions of the rig's landmark vertices; NaN where the rig has none."""
    ids = np.asarray(rig.landmark_ids)
    valid = ids >= 0
    points = evaluate_rig(rig, curves, ids[valid]).numpy()
    out = np.full((len(curves), len(ids), 2), np.nan, np.float32)
    for k, pose in enumerate(poses):
        out[k, valid] = project(points[k], camera, pose)
    return out


def detect_like(exact: np.ndarray, rng: np.random.Generator, noise_px: float, miss_rate: float, fps: float) -> LandmarkTrack:
    """What a landmark detector would report: exact points plus Gaussian noise, whole frames missed at random."""
    noisy = exact + rng.normal(0.0, noise_px, exact.shape).astype(np.float32)
    valid = np.isfinite(noisy).all(axis=2)
    missed = rng.random(len(exact)) < miss_rate
    valid[missed] = False
    noisy[~valid] = np.nan
    return LandmarkTrack(noisy.astype(np.float32), valid, fps, "generic68")


def make_take(
    rig: VisemeRig, segments: Sequence[VisemeSegment], n_frames: int, speaker: str, utterance_id: str,
    config: SynthConfig = SynthConfig(),
) -> SyntheticTake:
    """True curves, camera path and landmarks of one utterance; reproducible from the config's seed."""
    curves = generate_ground_truth(segments, n_frames, config.fps, speaker, utterance_id, config.truth)
    camera = config.camera()
    base = frontal_pose(rig.neutral, camera, config.fill)
    scene = scene_track(n_frames, config.fps, _rng("scene", utterance_id, config.truth.seed), config.scene)
    poses = frame_poses(base, scene)
    exact = project_landmarks(rig, curves, camera, poses)
    rng = _rng("landmarks", utterance_id, config.truth.seed)
    track = detect_like(exact, rng, config.landmark_noise_px, config.landmark_miss_rate, config.fps)
    return SyntheticTake(curves, camera, poses, scene, track, exact)


def render_take(rig: VisemeRig, take: SyntheticTake) -> Iterator[np.ndarray]:
    """The take's frames, (H, W, 3) uint8 RGB each, rendered a chunk of frames at a time."""
    colors = rig.vertex_colors
    faces = rig.faces
    for start in range(0, len(take.curves), RENDER_CHUNK):
        meshes = evaluate_rig(rig, take.curves[start:start + RENDER_CHUNK]).numpy()
        for offset, vertices in enumerate(meshes):
            k = start + offset
            tint = None if colors is None else np.clip(colors * take.scene.intensities[k], 0.0, 1.0)
            yield render_mesh(vertices, faces, tint, take.camera, take.poses[k], light_dir=take.scene.light_dirs[k])


def camera_record(take: SyntheticTake) -> dict[str, object]:
    """Intrinsics and per-frame head poses as JSON-able data (written beside the video)."""
    cam = take.camera
    return {
        "width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
        "convention": "x right, y up, camera looks down -z; pixels u right, v down; poses map mesh to camera (cm)",
        "rotations_axis_angle": [list(p.rotation) for p in take.poses],
        "translations": [list(p.translation) for p in take.poses],
    }
