"""A user's head without landmarks gets its inner lips found in its geometry (visemeflow/animation/lipfinder.py), so
its closures are measured in millimetres on the mesh as the demo head's are. Checked on the ICT head under ARKit names
(examples/build_arkit_character.py, written to a GLB as a user would have it), whose true landmarks are the demo
rig's: the middle pair found is the landmark pair itself, and the found gap calls closures as the landmark gap does.
"""

import sys
from dataclasses import replace

import numpy as np
import pytest
from factories import REPO

from visemeflow.animation.gltf import write_glb
from visemeflow.animation.lipfinder import find_inner_lips, found_inner_lips
from visemeflow.animation.lips import CLOSED_MM, closure_report, inner_lip_pairs, pair_gap_mm
from visemeflow.animation.load import load_character
from visemeflow.rig import load_demo_rig
from visemeflow.shapes.conventions import bind
from visemeflow.visemes import N_VISEMES, viseme_index

sys.path.insert(0, str(REPO / "examples"))
from build_arkit_character import build_character  # noqa: E402


@pytest.fixture(scope="module")
def arkit(tmp_path_factory):
    character = build_character()
    path = tmp_path_factory.mktemp("characters") / "ict_arkit.glb"
    write_glb(path, character, np.zeros((1, character.n_shapes), np.float32), 30.0, name="rest")
    loaded = load_character(path)
    assert loaded.landmark_ids is None                     # a GLB carries no landmarks: the finder's case
    return loaded


def landmark_pairs() -> np.ndarray:
    ids = load_demo_rig().landmark_ids
    return np.asarray([[ids[a], ids[b]] for a, b in ((61, 67), (62, 66), (63, 65))], np.int64)


def gaps(character, pairs, weights) -> np.ndarray:
    ids = pairs.ravel()
    at = character.neutral[ids][None] + np.tensordot(weights, character.deltas[:, ids], axes=1)
    return pair_gap_mm(at.reshape(len(at), 3, 2, 3), character.mm_per_unit)


def test_the_lips_found_on_the_arkit_head_measure_what_its_landmarks_measure(arkit):
    found = inner_lip_pairs(arkit)
    truth = landmark_pairs()
    assert found is not None and found[1].tolist() == truth[1].tolist()        # the middle: landmarks 62-66
    binding = bind(arkit)
    rng = np.random.default_rng(0)
    curves = np.concatenate([rng.random((200, N_VISEMES)) ** 3, np.eye(N_VISEMES)]).astype(np.float32)
    weights = binding.weights(curves)
    ours, theirs = gaps(arkit, found, weights), gaps(arkit, truth, weights)
    print(f"\nfound {found.tolist()}; r {np.corrcoef(ours, theirs)[0, 1]:.4f}, worst {np.abs(ours - theirs).max():.2f} mm")
    assert np.corrcoef(ours, theirs)[0, 1] > 0.99
    assert np.abs(ours - theirs).max() < 3.0
    assert ((ours < CLOSED_MM) == (theirs < CLOSED_MM)).all()
    mbp, ahh = -N_VISEMES + viseme_index("MBP"), -N_VISEMES + viseme_index("AHH")
    assert ours[mbp] < CLOSED_MM and ours[ahh] > 20                              # shut at b/p/m, 2-3 cm open


def test_the_finder_follows_the_head_turned_and_in_metres(arkit):
    """Orientation and unit are the file's: the head turned 30 degrees and tilted, in centimetres (the GLB's are
    metres), gives the same pairs."""
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    turn = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ np.array([[1, 0, 0], [0, 0.985, -0.174], [0, 0.174, 0.985]])
    one = np.zeros((1, N_VISEMES), np.float32)
    one[0, viseme_index("AHH")] = 1
    opening = np.tensordot(bind(arkit).weights(one)[0], arkit.deltas, axes=1)
    assert arkit.mm_per_unit == 1000.0
    pairs = find_inner_lips((arkit.neutral @ turn.T) * 100, arkit.faces, (opening @ turn.T) * 100, 10.0)
    assert pairs is not None and pairs.tolist() == inner_lip_pairs(arkit).tolist()


def test_no_mouth_no_pairs(arkit):
    """A head whose shapes open nothing, a mesh without a slit (a flat grid whose middle moves), and a character
    whose names no convention binds have no lip measure: None, and the report stays empty."""
    still = replace(arkit, deltas=np.zeros_like(arkit.deltas))
    assert find_inner_lips(still.neutral, still.faces, np.zeros_like(still.neutral), 10.0) is None
    xs, ys = np.meshgrid(np.linspace(-3, 3, 13), np.linspace(-2, 2, 9))
    grid = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1)
    faces = [(r * 13 + k, r * 13 + k + 1, (r + 1) * 13 + k + 1) for r in range(8) for k in range(12)] + \
        [(r * 13 + k, (r + 1) * 13 + k + 1, (r + 1) * 13 + k) for r in range(8) for k in range(12)]
    bump = np.zeros_like(grid)
    bump[:, 1] = -3.0 * np.exp(-(grid[:, 0] ** 2 + grid[:, 1] ** 2))     # a sealed "mouth" that stretches open
    assert find_inner_lips(grid, np.asarray(faces), bump, 10.0) is None
    unnamed = replace(arkit, shape_names=tuple(f"shape{k}" for k in range(arkit.n_shapes)))
    assert found_inner_lips(unnamed) is None and inner_lip_pairs(unnamed) is None


def test_the_package_report_counts_the_closures_of_a_users_head(arkit):
    """`animate`/`speak` report b/p/m closed on the mesh for a head without landmarks now: a b at a closure and a b
    the curves leave open."""
    binding = bind(arkit)
    curves = np.zeros((6, N_VISEMES), np.float32)
    curves[1, viseme_index("MBP")] = 1.0
    curves[4, viseme_index("AHH")] = 1.0
    report = closure_report(arkit, binding, binding.weights(curves), 30.0,
                            [(0.02, 0.06, "b"), (0.12, 0.16, "p")])
    assert report["bilabials"] == 2 and report["closed"] == 1 and "warning" not in report, report
    assert report["mbp_shape_gap_mm"] < CLOSED_MM


def test_a_mesh_packed_into_millimetres_costs_bounded_work():
    """30,000 vertices within 3 mm of each other (a head in the wrong unit, or a hostile file) whose half moves 10 mm:
    every vertex is within the search radius of every other, yet each looks at its nearest 48 only, and the answer
    comes back (there is no lip slit in a random cloud)."""
    import time

    rng = np.random.default_rng(1)
    points = rng.uniform(0, 0.3, (30_000, 3))                  # centimetres: a 3-mm cube
    faces = rng.integers(0, len(points), (60_000, 3))
    opening = np.zeros_like(points)
    opening[points[:, 1] < 0.15, 1] = -1.0                     # 10 mm down
    started = time.process_time()
    found = find_inner_lips(points, faces, opening, 10.0)
    print(f"\n{time.process_time() - started:.1f} s CPU")
    assert found is None or found.shape == (3, 2)


def test_a_flat_shaded_export_with_every_triangle_its_own_vertices_finds_the_same_lips(arkit):
    """Blender's glTF exporter splits every vertex of a flat-shaded mesh per triangle (no two triangles share one):
    the copies are welded first, and the pairs found sit where the smooth head's are."""
    one = np.zeros((1, N_VISEMES), np.float32)
    one[0, viseme_index("AHH")] = 1
    opening = np.tensordot(bind(arkit).weights(one)[0], arkit.deltas, axes=1)
    corners = arkit.faces.ravel()
    split = find_inner_lips(arkit.neutral[corners], np.arange(len(corners)).reshape(-1, 3), opening[corners],
                            arkit.mm_per_unit)
    assert split is not None
    np.testing.assert_array_equal(arkit.neutral[corners][split], arkit.neutral[inner_lip_pairs(arkit)])
