"""Our non-rigid ICP (visemeflow.authoring.nricp): it lands a template on another surface of another triangulation as
closely as trimesh's `nricp_amberg` (the implementation it replaced, the peer here), with its markers where they are
sent, and its preconditioned conjugate-gradient iterations solve the same systems as factorising each one."""

import numpy as np
import pytest
import scipy.sparse as sp

from visemeflow.authoring import nricp as nr


def grid(n: int, size: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """An n x n vertex grid over [-size/2, size/2]^2 on a shallow bowl (a flat template would leave each vertex's
    z column undetermined), two triangles a cell."""
    u = np.linspace(-size / 2, size / 2, n)
    xs, ys = np.meshgrid(u, u)
    vertices = np.c_[xs.ravel(), ys.ravel(), 0.1 * (xs.ravel() ** 2 + ys.ravel() ** 2)]
    ids = np.arange(n * n).reshape(n, n)
    a, b, c, d = ids[:-1, :-1].ravel(), ids[:-1, 1:].ravel(), ids[1:, :-1].ravel(), ids[1:, 1:].ravel()
    return vertices, np.r_[np.c_[a, b, d], np.c_[a, d, c]]


def bend(points: np.ndarray) -> np.ndarray:
    """A smooth bump and a tilt added: the target surface the template must take."""
    x, y = points[:, 0], points[:, 1]
    return np.c_[x, y, points[:, 2] + 0.35 * np.exp(-(x**2 + y**2) / 0.4) + 0.1 * x]


def surface_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    from visemeflow.authoring.transfer import _closest

    return _closest(vertices, faces, points)[1]


@pytest.fixture(scope="module")
def case():
    source_v, source_f = grid(25)
    target_v, target_f = grid(41, size=2.3)              # another triangulation, a little larger than the template
    target_v = bend(target_v)
    markers = np.array([0, 24, 12 * 25 + 12, 600, 624, 6 * 25 + 18])
    goals = bend(source_v[markers])                      # each marker's own point on the bent surface
    steps = [[0.01, 10, 0.5, 3], [0.02, 5, 0.5, 3], [0.03, 2.5, 0.5, 3], [0.01, 1, 0.0, 3]]
    return source_v, source_f, target_v, target_f, markers, goals, steps


def test_the_template_lands_on_the_target_as_closely_as_trimeshs_and_keeps_its_markers(case):
    import trimesh
    from trimesh.registration import nricp_amberg

    source_v, source_f, target_v, target_f, markers, goals, steps = case
    ours = nr.nricp(source_v, source_f, target_v, target_f, markers, goals, steps, distance_threshold=0.05)
    peer = nricp_amberg(trimesh.Trimesh(source_v, source_f, process=False),
                        trimesh.Trimesh(target_v, target_f, process=False), source_landmarks=markers,
                        target_positions=goals, steps=steps, distance_threshold=0.05, use_faces=False)
    flat = surface_distance(source_v, target_v, target_f)
    got, want = surface_distance(ours, target_v, target_f), surface_distance(peer, target_v, target_f)
    rms = lambda d: float(np.sqrt(np.mean(d**2)))  # noqa: E731
    print(f"\nsurface RMS: unregistered {rms(flat):.4f}, ours {rms(got):.5f}, trimesh {rms(want):.5f}")
    assert rms(flat) > 0.1                                # the template was far from the bump
    assert rms(got) < 0.01 and rms(got) <= 1.2 * rms(want) + 1e-4
    assert np.linalg.norm(ours[markers] - goals, axis=1).max() < 0.03
    assert np.sqrt(np.mean(np.sum((ours - peer) ** 2, axis=1))) < 0.02   # the same registration, not another fit


def test_preconditioned_iterations_solve_what_a_new_factorisation_solves(case):
    source_v, source_f, *_ = case
    n = len(source_v)
    edges = source_f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    order = nr._block_order(n, edges)
    rng = np.random.default_rng(0)
    laplacian = sp.csgraph.laplacian(sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])),
                                                    shape=(n, n)).tocsr(), symmetrized=True)
    stiffness = sp.kron(laplacian, sp.identity(4))

    def system(weights):
        return 0.02**2 * stiffness + nr._blocks(source_v, weights, np.arange(n), n)

    right = rng.normal(size=(4 * n, 3))
    first, factor = nr._solve(system(np.ones(n)), right, order, np.zeros_like(right))
    weights = np.where(rng.random(n) < 0.005, 0.0, rng.uniform(0.9, 1.0, n))  # a later iteration's: a few lost
    fresh, _ = nr._solve(system(weights), right, order, first)
    warm, used = nr._solve(system(weights), right, order, first, factor)
    assert used is factor                                 # no new factorisation was needed
    np.testing.assert_allclose(system(weights) @ fresh, right, atol=1e-6)
    np.testing.assert_allclose(warm, fresh, rtol=0, atol=1e-6 * np.abs(fresh).max())


def test_a_template_without_extent_is_refused():
    vertices = np.zeros((3, 3))
    with pytest.raises(ValueError, match="no extent"):
        nr.nricp(vertices, np.array([[0, 1, 2]]), vertices, np.array([[0, 1, 2]]))
