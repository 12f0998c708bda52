"""Identity modes and the subject's neutral face (paper Sec. 4.2): the shipped modes file, applying modes to a rig,
picking neutral frames, and fitting identity + pose (+ focal) to 2D landmarks, synthetic and on GRID.
Tests on ../shared/data fail (not skip) when it is missing."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import torch

from factories import REPO, SHARED_DATA
from visemeflow.rig import RigError, evaluate_rig, load_demo_rig
from visemeflow.render.camera import Intrinsics, project
from visemeflow.tracking.identity import (
    IdentityModes,
    SpeakerIdentity,
    apply_identity,
    demo_identity_path,
    fit_identity,
    fit_speaker_identity,
    load_identity_modes,
    mouth_opening,
    neutral_frames,
)
from visemeflow.tracking.landmarks import LandmarkTrack, read_landmarks
from visemeflow.visemes import N_VISEMES, viseme_index

ICT = SHARED_DATA / "ict_facekit"
GRID = SHARED_DATA / "grid_s1"
NON_JAW = np.arange(17, 68)
CAMERA = Intrinsics.from_fov(360, 288, 25)


def shared(path: Path) -> Path:
    assert path.exists(), f"shared test data missing: {path}"
    return path


@pytest.fixture(scope="module")
def rig():
    return load_demo_rig()


@pytest.fixture(scope="module")
def modes():
    return load_identity_modes(demo_identity_path())


def similarity_rms(points: np.ndarray, target: np.ndarray) -> float:
    """RMS distance of (N, 3) points to target after the best rotation, translation and scale (Umeyama)."""
    p, q = points - points.mean(axis=0), target - target.mean(axis=0)
    u, s, vt = np.linalg.svd(p.T @ q)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ d @ vt
    scale = np.sum(s * np.diag(d)) / np.sum(p**2)
    return float(np.sqrt(np.mean(np.sum((scale * p @ rotation - q) ** 2, axis=1))))


def track_of(points: np.ndarray, valid: np.ndarray | None = None) -> LandmarkTrack:
    if valid is None:
        valid = np.ones(points.shape[:2], bool)
    return LandmarkTrack(points=points.astype(np.float32), valid=valid, fps=25.0, source="generic68")


def project_landmarks(vertices: np.ndarray, rotation: np.ndarray, translation: np.ndarray, camera=CAMERA) -> np.ndarray:
    """(N, 3) or (T, N, 3) landmark vertices seen in T poses -> (T, N, 2) pixels."""
    points = torch.as_tensor(vertices, dtype=torch.float64)
    if points.ndim == 2:
        points = points.expand(len(rotation), -1, -1)
    return project(points, torch.as_tensor(rotation), torch.as_tensor(translation), camera).numpy()


# ------------------------------------------------------------------------------------------ the shipped modes


def test_shipped_modes_match_the_demo_rig(rig, modes):
    assert modes.names == tuple(f"identity{k:03d}" for k in range(20))
    assert modes.modes.shape == (20, rig.n_vertices, 3) and modes.modes.dtype == np.float32
    size = np.sqrt(np.mean(np.sum(modes.modes**2, axis=2), axis=1))
    assert size[0] > size[-1] * 3  # sigma-scaled PCA modes shrink with k
    assert demo_identity_path().stat().st_size < 3e6


def test_shipped_modes_match_a_rebuild_from_the_ict_face_model(rig, modes):
    shared(ICT / "identities")
    spec = importlib.util.spec_from_file_location("build_demo_identities", REPO / "examples" / "build_demo_identities.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    names, rebuilt = module.build_identity_modes(ICT)
    assert tuple(names) == modes.names
    np.testing.assert_array_equal(rebuilt.astype(np.float16).astype(np.float32), modes.modes)
    # the crop is the demo rig's: the ICT neutral at the kept ids is the rig's neutral, vertex for vertex
    from visemeflow.rig import read_obj

    neutral = read_obj(ICT / "generic_neutral_mesh.obj.gz").vertices
    with np.load(demo_identity_path()) as archive:
        kept = archive["ict_vertex_ids"]
    np.testing.assert_array_equal(neutral[kept].astype(np.float32), rig.neutral)


def test_load_identity_modes_names_the_file_when_it_is_not_a_modes_file(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, something=np.zeros(3))
    with pytest.raises(RigError, match="other.npz.*missing names, modes"):
        load_identity_modes(path)


# ------------------------------------------------------------------------------------------ applying identity


def test_apply_identity_moves_the_neutral_and_scales_the_visemes(rig, modes):
    c = np.zeros(modes.n_modes)
    c[[0, 3]] = [1.0, -0.5]
    subject = apply_identity(rig, modes, c, scale=1.1)
    expected = 1.1 * (rig.neutral + modes.modes[0] - 0.5 * modes.modes[3])
    np.testing.assert_allclose(subject.neutral, expected, atol=1e-5)
    np.testing.assert_allclose(subject.deltas, 1.1 * rig.deltas, atol=1e-6)
    np.testing.assert_array_equal(subject.faces, rig.faces)
    weights = np.zeros(N_VISEMES, np.float32)
    weights[viseme_index("AAA")] = 1.0
    np.testing.assert_allclose(evaluate_rig(subject, weights).numpy(), expected + 1.1 * rig.deltas[viseme_index("AAA")],
                               atol=1e-4)
    same = apply_identity(rig, modes, np.zeros(modes.n_modes))
    np.testing.assert_array_equal(same.neutral, rig.neutral)


def test_apply_identity_refuses_modes_of_another_mesh(rig, modes):
    other = IdentityModes(names=("a",), modes=np.zeros((1, 5, 3), np.float32))
    with pytest.raises(RigError, match="5 vertices"):
        apply_identity(rig, other, [0.0])
    with pytest.raises(ValueError, match="coefficients must have shape"):
        apply_identity(rig, modes, np.zeros(3))


# ------------------------------------------------------------------------------------------ neutral frames


def test_neutral_frames_picks_closed_mouths_and_prefers_silence(rig):
    rng = np.random.default_rng(1)
    n_frames = 30
    weights = np.zeros((n_frames, N_VISEMES), np.float32)
    open_frames = rng.choice(n_frames, 18, replace=False)
    weights[open_frames, viseme_index("AAA")] = rng.uniform(0.3, 1.0, len(open_frames))
    meshes = evaluate_rig(rig, weights, vertex_ids=rig.landmark_ids).numpy()
    rotation = np.column_stack([np.zeros(n_frames), rng.uniform(-0.2, 0.2, n_frames), np.zeros(n_frames)])
    translation = np.column_stack([rng.uniform(-2, 2, (n_frames, 2)), np.full(n_frames, -90.0)])
    points = project_landmarks(meshes, rotation, translation) + rng.normal(0.0, 0.3, (n_frames, 68, 2))
    closed = np.setdiff1d(np.arange(n_frames), open_frames)

    opening = mouth_opening(points)
    assert opening[closed].max() < 0.05
    assert opening[open_frames].min() > 0.1
    np.testing.assert_array_equal(neutral_frames(track_of(points), n=len(closed)), closed)
    picked = neutral_frames(track_of(points), n=5)
    assert len(picked) == 5 and set(picked) <= set(closed)
    assert len(neutral_frames(track_of(points), n=100)) == n_frames  # never more frames than there are

    valid = np.ones((n_frames, 68), bool)
    valid[closed[0], 62] = False  # an invalid inner-lip point disqualifies the frame; a jaw point does not
    valid[closed[1], 3] = False
    picked = neutral_frames(track_of(points, valid), n=len(closed))
    assert closed[0] not in picked and closed[1] in picked

    silence = np.zeros(n_frames, bool)
    silence[closed[-3:]] = True
    silence[open_frames[:2]] = True  # a silent frame with the mouth well open still loses to closed speech frames
    np.testing.assert_array_equal(neutral_frames(track_of(points), n=3, silence=silence), closed[-3:])
    assert set(neutral_frames(track_of(points), n=5, silence=silence)) <= set(closed)


# ------------------------------------------------------------------------------------------ fitting, synthetic


@pytest.fixture(scope="module")
def synthetic(rig, modes):
    """A face with 5 known identity coefficients at scale 1.1, seen in 10 poses by CAMERA, 0.5 px landmark noise."""
    rng = np.random.default_rng(7)
    c = np.zeros(modes.n_modes)
    c[[0, 1, 2, 4, 7]] = [0.4, -0.7, -1.4, -1.45, 0.95]
    truth = 1.1 * (rig.neutral + np.tensordot(c, modes.modes, axes=1))[rig.landmark_ids]
    n_frames = 10
    rotation = np.column_stack([rng.uniform(-0.1, 0.1, n_frames), rng.uniform(-0.3, 0.3, n_frames),
                                rng.uniform(-0.1, 0.1, n_frames)])
    translation = np.column_stack([rng.uniform(-3, 3, (n_frames, 2)), rng.uniform(-100, -80, n_frames)])
    points = project_landmarks(truth, rotation, translation) + rng.normal(0.0, 0.5, (n_frames, 68, 2))
    return truth, rotation, track_of(points)


def fitted_landmarks(fit, rig, modes) -> np.ndarray:
    return apply_identity(rig, modes, fit.coefficients, fit.scale).neutral[rig.landmark_ids]


def test_fit_identity_recovers_a_known_face_with_the_camera_known(rig, modes, synthetic):
    truth, rotation, track = synthetic
    fit = fit_identity(rig, modes, track, np.arange(10), camera=CAMERA)
    assert fit.rms_px < 1.0
    assert fit.camera == CAMERA
    np.testing.assert_array_equal(fit.frames, np.arange(10))
    assert np.abs(fit.rotation - rotation).max() < 0.03
    # the landmarks fix shape and pose but not absolute size (a larger face further away projects the same), so the
    # 3D comparison is up to a similarity; the scale stays at its prior mean and the head moves nearer instead
    error = similarity_rms(fitted_landmarks(fit, rig, modes), truth)
    untouched = similarity_rms(rig.neutral[rig.landmark_ids], truth)
    assert error < 0.5 * untouched, (error, untouched)
    assert fit.scale == pytest.approx(1.0, abs=1e-3)
    assert np.all(np.abs(fit.coefficients) < 2.0)
    assert np.isnan(fit.residuals_px).sum() == 0 and fit.residuals_px.shape == (10, 68)


def test_fit_identity_with_an_unknown_camera_fits_the_focal_length(rig, modes, synthetic):
    truth, _, track = synthetic
    with pytest.raises(ValueError, match="image_size"):
        fit_identity(rig, modes, track, np.arange(10))
    fit = fit_identity(rig, modes, track, np.arange(10), image_size=(360, 288))
    assert fit.rms_px < 1.0
    assert fit.camera.fx == fit.camera.fy and 0.7 * CAMERA.fx < fit.camera.fx < 1.3 * CAMERA.fx
    assert (fit.camera.cx, fit.camera.cy, fit.camera.width, fit.camera.height) == (CAMERA.cx, CAMERA.cy, 360, 288)
    error = similarity_rms(fitted_landmarks(fit, rig, modes), truth)
    assert error < 0.5 * similarity_rms(rig.neutral[rig.landmark_ids], truth)


def test_fit_identity_leaves_out_missing_landmarks(rig, modes, synthetic):
    track = synthetic[2]
    points, valid = track.points.copy(), track.valid.copy()
    points[:, 30] += 40.0  # a wild nose tip, flagged missing, must not pull the fit
    valid[:, 30] = False
    fit = fit_identity(rig, modes, track_of(points, valid), np.arange(10), camera=CAMERA)
    assert fit.rms_px < 1.0 and np.isnan(fit.residuals_px[:, 30]).all()


# ------------------------------------------------------------------------------------------ fitting, GRID


def grid_silence(clip: str, track: LandmarkTrack) -> np.ndarray:
    """(T,) True for frames inside the `sil` spans of a GRID .align file (times in 1/25000 s)."""
    times = track.times()
    silence = np.zeros(track.n_frames, bool)
    for line in shared(GRID / "align" / f"{clip}.align").read_text().splitlines():
        if line.strip():
            start, end, word = line.split()
            if word == "sil":
                silence |= (times >= int(start) / 25000) & (times < int(end) / 25000)
    return silence


def test_fit_identity_on_a_grid_clip(rig, modes):
    track = read_landmarks(shared(GRID / "landmarks" / "bbaf2n.mediapipe478.csv"))
    frames = neutral_frames(track, n=10, silence=grid_silence("bbaf2n", track))
    assert len(frames) == 10 and mouth_opening(track.points[frames]).max() < 0.1
    fit = fit_identity(rig, modes, track, frames, image_size=(360, 288))
    # measured: 1.76 px on the non-jaw landmarks (1.63-1.85 over the 10 clips), 6.3 px on the jaw contour
    assert fit.rms_over(NON_JAW) < 2.2
    assert fit.scale == pytest.approx(1.0, abs=0.01)
    assert np.linalg.norm(fit.coefficients) < 2.0 * np.sqrt(modes.n_modes)  # a plausible face under the prior
    fov = np.degrees(2 * np.arctan(144.0 / fit.camera.fy))
    assert 10.0 < fov < 60.0  # measured 42 degrees, focal 369 px
    depth = -fit.translation[:, 2]
    assert np.all((30.0 < depth) & (depth < 200.0))  # centimetres to the head origin


# ------------------------------------------------------------------------------------------ one identity per speaker


def speaker_clips(synthetic) -> list[tuple[str, LandmarkTrack]]:
    """The synthetic face's 10 poses as three clips of one speaker (frames 0-2, 3-5, 6-9)."""
    track = synthetic[2]
    return [(f"spk/{name}", track_of(track.points[part], track.valid[part]))
            for name, part in (("a", slice(0, 3)), ("b", slice(3, 6)), ("c", slice(6, 10)))]


def test_speaker_identity_is_the_same_whatever_order_its_clips_come_in(rig, modes, synthetic):
    clips = speaker_clips(synthetic)
    first = fit_speaker_identity(rig, modes, clips, (360, 288), total_frames=6)
    again = fit_speaker_identity(rig, modes, clips[::-1], (360, 288), total_frames=6)
    assert first == again and first.digest == again.digest
    assert first.clips == ("spk/a", "spk/b", "spk/c") and first.frames == 6 and first.rms_px < 1.0
    assert SpeakerIdentity.from_dict(first.to_dict()) == first   # as a cached task result and back
    assert 0.7 * CAMERA.fx < first.focal < 1.3 * CAMERA.fx and first.camera().cx == CAMERA.cx
    # one changed clip: another identity, another digest (the per-clip tasks' cache keys change with it)
    a, b, c = clips
    moved = (a[0], track_of(a[1].points + np.float32(2.0), a[1].valid))
    changed = fit_speaker_identity(rig, modes, [moved, b, c], (360, 288), total_frames=6)
    assert changed.digest != first.digest


def test_speaker_identity_of_one_clip_is_the_per_clip_fit(rig, modes, synthetic):
    track = synthetic[2]
    one = fit_speaker_identity(rig, modes, [("spk/a", track)], (360, 288), total_frames=10)
    fit = fit_identity(rig, modes, track, neutral_frames(track, n=10), image_size=(360, 288))
    np.testing.assert_array_equal(np.asarray(one.coefficients, np.float32), fit.coefficients)
    assert (one.scale, one.focal, one.rms_px) == (fit.scale, fit.camera.fx, fit.rms_px)


def test_speaker_without_a_neutral_frame_has_no_speaker_identity(rig, modes, synthetic):
    clips = speaker_clips(synthetic)
    blind = [(uid, track_of(t.points, np.zeros_like(t.valid))) for uid, t in clips]   # no usable frame
    assert fit_speaker_identity(rig, modes, blind, (360, 288)) is None
    # a clip without one is left out, the others still give the identity
    mixed = fit_speaker_identity(rig, modes, [blind[0], *clips[1:]], (360, 288), total_frames=6)
    assert mixed is not None and mixed.clips == ("spk/b", "spk/c")


@pytest.mark.parametrize("fit_focal", [False, True])
def test_the_written_out_jacobian_equals_forward_mode_autodiff(fit_focal):
    """fit_identity's Levenberg-Marquardt uses `_Problem.jacobian`, written out block by block; forward-mode AD
    through `residuals` is the reference (it was the solver's Jacobian until it was a quarter of tracking's time),
    at zero rotation (fit_identity's start), small and large angles, with and without the identity prior."""
    import math

    from visemeflow.tracking.identity import _Problem

    gen = torch.Generator().manual_seed(0)
    frames, points, modes = 4, 30, 5

    def rand(*shape):
        return torch.randn(*shape, generator=gen, dtype=torch.float64)

    problem = _Problem(rand(points, 3), 0.1 * rand(modes, points, 3), 300 * torch.rand(frames, points, 2, generator=gen,
                       dtype=torch.float64), (torch.rand(frames, points, generator=gen) > 0.2).double(),
                       torch.rand(points, generator=gen, dtype=torch.float64), CAMERA, CAMERA.fx, fit_focal,
                       (2.0, 0.1, 0.5))
    for angle in (0.0, 0.05, 0.6):
        theta = problem.pack(0.3 * rand(modes), torch.tensor(0.05, dtype=torch.float64), angle * rand(frames, 3),
                             torch.tensor([[0.0, 0.0, -40.0]], dtype=torch.float64) + rand(frames, 3),
                             torch.tensor(math.log(CAMERA.fx * 1.01), dtype=torch.float64))
        for with_identity in (True, False):
            written = problem.jacobian(theta, with_identity)
            reference = torch.func.jacfwd(lambda th: problem.residuals(th, with_identity))(theta)
            assert written.shape == reference.shape
            assert float((written - reference).abs().max()) < 1e-9 * float(reference.abs().max())


def test_right_jacobian_gives_the_derivative_of_a_rotated_point():
    """d(R(r) p)/dr = -R [p]_x J_r(r) against autograd through `rotation_matrices`, in float64 at zero, small
    and large angles, and in float32 at the small angles where the series replaces t - sin t."""
    from visemeflow.render.camera import cross_matrices, right_jacobian, rotation_matrices

    gen = torch.Generator().manual_seed(1)
    point = torch.randn(3, generator=gen, dtype=torch.float64)
    for angle in (0.0, 1e-4, 0.02, 0.09, 0.11, 0.7, 2.5):
        for dtype, tol in ((torch.float64, 1e-9), (torch.float32, 2e-6)):
            r = torch.randn(3, generator=gen, dtype=torch.float64)
            r = (angle * r / r.norm()).to(dtype)
            reference = torch.autograd.functional.jacobian(
                lambda v: rotation_matrices(v[None])[0] @ point.to(dtype), r)
            written = -(rotation_matrices(r[None])[0] @ cross_matrices(point.to(dtype)) @ right_jacobian(r[None])[0])
            assert float((written - reference).abs().max()) < tol, (angle, dtype)
