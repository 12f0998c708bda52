"""Deformation transfer of the 16 visemes onto new faces (visemeflow/authoring/transfer.py), checked by meaning:

- onto its own neutral the template comes back (vertex error near 0);
- without markers, FaceMesh on renders of both meshes finds marker pairs near the true correspondence;
- onto ICT identities (same topology: the shipped identity modes, and identity OBJs from shared data) and onto a
  face of another topology (the ICT face cut to the narrow face, Loop-subdivided by trimesh so no triangle is
  the template's, moved, turned and scaled, landmarks found by nearest point), the demo rig's landmark checks pass
  on the transferred visemes: MBP closes the lips, AHH opens the jaw most, UUU is the narrowest mouth and IEE the
  widest;
- bad input: a non-manifold target, degenerate triangles (repaired with a note), markers naming missing vertices,
  too few markers, another topology without markers where none can be found automatically (no face on
  its render), an ICP that does not converge;
- the command writes a GLB the Khronos validator accepts, read back as a 16-viseme rig with its landmarks.

Tests that read ../shared/data fail, never skip, when it is missing.
"""

import gzip

import numpy as np
import pytest
import trimesh
from factories import REMESHED_IDENTITY, ROTATION, SHARED_DATA, identity_face, placed, remeshed_face, validate

from visemeflow.rig.character import make_character
from visemeflow.authoring.transfer import TransferError, read_markers_csv, transfer_command, transfer_visemes
from visemeflow.rig import load_demo_rig, load_rig, read_obj, rig_data_path
from visemeflow.visemes import VISEMES

SHARED_ICT = SHARED_DATA / "ict_facekit"


def viseme_index(name: str) -> int:
    return VISEMES.index(name)


@pytest.fixture(scope="module")
def demo():
    return load_demo_rig()


@pytest.fixture(scope="module")
def modes():
    return np.load(rig_data_path("ict_identities.npz"))["modes"].astype(np.float64)


def landmark_tracks(character, landmark_ids, rotation=np.eye(3)):
    """(17, 68, 3) landmarks of the neutral then each viseme at full weight, in the face's own (unturned) axes."""
    meshes = np.concatenate([character.neutral[None], character.neutral[None] + character.deltas])
    return meshes[:, landmark_ids] @ rotation


def check_visemes(lm):
    """The demo rig's landmark tests (tests/test_rig.py), relative to this face's own mouth width."""
    gap = np.linalg.norm(lm[:, 62] - lm[:, 66], axis=1)
    width = np.linalg.norm(lm[:, 48] - lm[:, 54], axis=1)
    chin = lm[:, 8, 1]
    mbp, ahh, uuu, iee = (1 + viseme_index(v) for v in ("MBP", "AHH", "UUU", "IEE"))
    assert gap[mbp] < 0.025 * width[0], gap           # MBP: lips closed (the template: 1% of the mouth's width)
    assert gap[1:].argmin() == mbp - 1
    assert gap[1:].argmax() == ahh - 1 and chin[1:].argmin() == ahh - 1
    assert gap[ahh] > 0.45 * width[0]                 # the template: 3.3 cm on a 5.1 cm mouth
    assert width[1:].argmin() == uuu - 1 and width[uuu] < width[0] - 0.15 * width[0]
    assert width[1:].argmax() == iee - 1 and width[iee] > width[0] + 0.12 * width[0]


def test_the_template_onto_its_own_neutral_comes_back(demo):
    result = transfer_visemes(demo, demo.neutral, demo.faces, name="self")
    report = result.report
    print("\n" + str(report))
    assert report.mode == "same topology"
    error = np.abs(result.character.deltas - demo.deltas).max()
    assert error < 1e-3, error                        # cm; the template moves up to 3 cm
    assert max(report.gradient_residual.values()) < 2e-3
    np.testing.assert_array_equal(result.landmark_ids, demo.landmark_ids)
    assert result.character.shape_names == tuple(VISEMES)
    check_visemes(landmark_tracks(result.character, result.landmark_ids))


def test_an_ict_identity_gets_the_visemes_of_its_own_shape(demo, modes):
    coefficients = np.zeros(len(modes))
    coefficients[:5] = [1.0, -1.0, 1.0, -0.5, 0.5]    # a narrower, smaller face than the template
    target = demo.neutral + np.tensordot(coefficients, modes, axes=1)
    result = transfer_visemes(demo, target, demo.faces, name="identity")
    print("\n" + str(result.report))
    check_visemes(landmark_tracks(result.character, result.landmark_ids))
    # a real transfer, not the template's offsets copied: the motion follows the new face's surface
    assert np.abs(result.character.deltas - demo.deltas).max() > 0.05
    assert np.mean(list(result.report.gradient_residual.values())) < 0.1


def test_ict_identity_files_from_shared_data(demo):
    folder = SHARED_ICT / "identities"
    assert folder.is_dir(), f"{folder} is missing: the ICT identity OBJs are shared data (see shared/data)"
    ids = np.load(rig_data_path("ict_identities.npz"))["ict_vertex_ids"]
    generic = read_obj(SHARED_ICT / "generic_neutral_mesh.obj.gz").vertices[ids]
    np.testing.assert_allclose(generic, demo.neutral, atol=1e-4)       # the rig's vertices are the ICT mesh's
    for name in ("identity000", "identity003"):
        target = read_obj(folder / f"{name}.obj.gz").vertices[ids]
        result = transfer_visemes(demo, target, demo.faces, name=name)
        check_visemes(landmark_tracks(result.character, result.landmark_ids))


# ---- another topology -------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def remeshed(demo, modes):
    vertices, faces, landmarks = remeshed_face(demo, modes)
    return vertices, faces, landmarks, transfer_visemes(demo, vertices, faces, target_landmarks=landmarks,
                                                        name="remeshed")


def test_another_topology_gets_the_visemes(demo, remeshed):
    vertices, faces, landmarks, result = remeshed
    report = result.report
    print("\n" + str(report))
    assert len(vertices) != demo.n_vertices and report.mode == "different topology"
    assert report.icp_residual_relative < 0.005 and report.n_markers == 68
    character = result.character
    # the target's own vertices come first and unchanged; the template's mouth and eyes are carried after them
    np.testing.assert_allclose(character.neutral[: len(vertices)], vertices, atol=1e-5)
    assert report.carried_vertices == len(np.union1d(demo.regions["mouth_interior"], demo.regions["eyes"]))
    np.testing.assert_array_equal(result.landmark_ids, landmarks)
    check_visemes(landmark_tracks(character, result.landmark_ids, ROTATION))
    # the carried lower teeth follow the jaw: AHH moves them down (in the face's axes) by about the chin's drop
    lm = landmark_tracks(character, result.landmark_ids, ROTATION)
    teeth = len(vertices) + np.flatnonzero(np.isin(np.flatnonzero(np.isin(
        np.arange(demo.n_vertices), np.union1d(demo.regions["mouth_interior"], demo.regions["eyes"]))),
        demo.regions["teeth"]))
    drop = (character.deltas[viseme_index("AHH"), teeth] @ ROTATION)[:, 1].min()
    assert drop < -0.5 * (lm[0, 8, 1] - lm[1 + viseme_index("AHH"), 8, 1])


def test_markers_are_found_automatically_on_another_topology(demo, modes):
    """No markers: FaceMesh on renders of both meshes pairs their points (automarkers); the pairs lie near the true
    correspondence, the registration converges as with the 68 true landmarks, and the visemes pass the checks."""
    from visemeflow.authoring.automarkers import automatic_markers

    vertices, faces, landmarks = remeshed_face(demo, modes)
    size = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    carried = np.union1d(demo.regions["mouth_interior"], demo.regions["eyes"])
    auto = automatic_markers(demo.neutral, demo.faces, vertices, faces, exclude=carried)
    assert len(auto.pairs) >= 100 and not np.isin(auto.pairs[:, 0], carried).any()
    truth = placed(identity_face(demo, modes, REMESHED_IDENTITY)[auto.pairs[:, 0]])
    error = np.linalg.norm(vertices[auto.pairs[:, 1]] - truth, axis=1)
    assert np.median(error) < 0.02 * size and np.percentile(error, 90) < 0.05 * size
    result = transfer_visemes(demo, vertices, faces, name="remeshed")
    assert any(note.startswith("markers found automatically") for note in result.report.notes)
    assert result.report.icp_residual_relative < 0.005
    found = np.linalg.norm(vertices[result.landmark_ids] - vertices[landmarks], axis=1)
    assert np.median(found) < 0.01 * size
    check_visemes(landmark_tracks(result.character, landmarks, ROTATION))


def test_markers_from_a_csv_and_their_errors(tmp_path, demo, remeshed):
    vertices, faces, landmarks, _ = remeshed
    csv = tmp_path / "markers.csv"
    csv.write_text("template_vertex,target_vertex\n" + "".join(f"{a},{b}\n" for a, b in
                                                               zip(demo.landmark_ids, landmarks)))
    np.testing.assert_array_equal(read_markers_csv(csv), np.stack([demo.landmark_ids, landmarks], axis=1))
    (tmp_path / "bad.csv").write_text("template_vertex,target_vertex\n1,x\n")
    with pytest.raises(TransferError, match=r"bad\.csv line 2: vertex ids must be integers"):
        read_markers_csv(tmp_path / "bad.csv")
    pairs = np.stack([demo.landmark_ids, landmarks], axis=1)
    pairs[3, 1] = len(vertices) + 7
    with pytest.raises(TransferError, match=rf"marker 3: target vertex {len(vertices) + 7} does not exist"):
        transfer_visemes(demo, vertices, faces, pairs)
    pairs[3] = (demo.n_vertices, 0)
    with pytest.raises(TransferError, match=rf"marker 3: template vertex {demo.n_vertices} does not exist"):
        transfer_visemes(demo, vertices, faces, pairs)
    with pytest.raises(TransferError, match="give at least 5"):
        transfer_visemes(demo, vertices, faces, pairs[:3])
    ball = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    with pytest.raises(TransferError, match=r"topology differs from the template's .* no markers could be found "
                                            r"automatically \(ball: the [0-9]+ automatic marker pairs do not fit "
                                            r"one similarity transform \(median residual [0-9.]+, [0-9.]+% of the "
                                            r"mesh's size; limit 2.0%\)"):
        transfer_visemes(demo, ball.vertices, ball.faces, name="ball")   # FaceMesh sees a "face" on a ball
    with pytest.raises(TransferError, match=r"no markers could be found automatically \(flat: MediaPipe FaceMesh "
                                            r"found no face on a frontal render"):
        flat = trimesh.creation.box(extents=(30.0, 30.0, 1.0))
        transfer_visemes(demo, flat.vertices, flat.faces, name="flat")
    with pytest.raises(TransferError, match="neither marker pairs nor 'auto'"):
        transfer_visemes(demo, vertices, faces, "automatic")
    with pytest.raises(TransferError, match="is not on the template's skin"):
        good = np.stack([demo.landmark_ids, landmarks], axis=1)[:6]
        transfer_visemes(demo, vertices, faces, np.concatenate([[[demo.regions["teeth"][0], 0]], good]))


# ---- bad meshes and a registration that fails --------------------------------------------------------------------
def grid_character(n=12):
    """A small curved sheet with two shapes (a bump and a sideways shear): a template for quick tests."""
    xs, ys = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n))
    neutral = np.stack([xs.ravel(), ys.ravel(), 0.3 * (1 - xs.ravel() ** 2)], axis=1)
    faces = [(r * n + c, r * n + c + 1, (r + 1) * n + c + 1) for r in range(n - 1) for c in range(n - 1)]
    faces += [(r * n + c, (r + 1) * n + c + 1, (r + 1) * n + c) for r in range(n - 1) for c in range(n - 1)]
    bump = np.zeros_like(neutral)
    bump[:, 2] = 0.2 * np.exp(-4 * (xs.ravel() ** 2 + ys.ravel() ** 2))
    shear = np.zeros_like(neutral)
    shear[:, 0] = 0.1 * np.clip(ys.ravel(), 0, None)
    return make_character("sheet", neutral, faces, ["bump", "shear"], np.stack([bump, shear]))


def test_degenerate_triangles_are_removed_with_a_note_and_non_manifold_is_an_error():
    sheet = grid_character()
    faces = np.concatenate([sheet.faces, [[0, 0, 5], [3, 4, 5]]])     # a repeated vertex; a zero-area sliver row
    vertices = sheet.neutral.astype(np.float64).copy()
    result = transfer_visemes(sheet, vertices, faces, markers=np.stack([np.arange(0, 144, 7)] * 2, axis=1))
    notes = " ".join(result.report.notes)
    assert "removed 1 degenerate triangle" in notes
    assert len(result.character.faces) == len(sheet.faces) + 1          # the sliver (3, 4, 5) has area: kept
    # the same sheet, registered onto itself: the shapes come back
    np.testing.assert_allclose(result.character.deltas, sheet.deltas, atol=0.02)
    extra = np.concatenate([sheet.faces, [[0, 13, 140]]])          # a third triangle on the diagonal 0-13
    with pytest.raises(TransferError, match="not manifold: .* shared by more than two triangles"):
        transfer_visemes(sheet, vertices, extra, markers=np.stack([np.arange(0, 144, 7)] * 2, axis=1))


def test_an_icp_that_does_not_converge_is_rejected_with_its_residual():
    sheet = grid_character()
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    markers = np.stack([np.arange(0, 143, 13), np.arange(0, 11 * 13, 13) % len(ball.vertices)], axis=1)
    with pytest.raises(TransferError, match=r"did not converge: the registered template lies [0-9.]+ \(RMS, "
                                            r"[0-9.]+% of the target's size; limit 1.00%\)"):
        transfer_visemes(sheet, ball.vertices, ball.faces, markers)


# ---- the command ------------------------------------------------------------------------------------------------
def test_the_command_writes_a_valid_glb_that_reads_back_as_a_rig(tmp_path, demo, modes):
    coefficients = np.zeros(len(modes))
    coefficients[1] = 1.5
    target = tmp_path / "newface.obj.gz"
    vertices = demo.neutral + np.tensordot(coefficients, modes, axes=1)
    with gzip.open(target, "wt") as handle:
        handle.writelines(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in vertices)
        handle.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in demo.faces)
    out = tmp_path / "newface.glb"
    report = transfer_command(rig_data_path("ict_visemes.npz"), target, None, out)
    assert report.mode == "same topology"
    rig = load_rig(out)                                # reads newface.landmarks.json beside it
    np.testing.assert_array_equal(rig.landmark_ids, demo.landmark_ids)
    np.testing.assert_allclose(rig.neutral, vertices, atol=1e-4)
    lm = np.concatenate([rig.neutral[None], rig.neutral[None] + rig.deltas])[:, rig.landmark_ids]
    check_visemes(lm)
    issues = validate(out)["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]
    with pytest.raises(TransferError, match="the output must be a .glb"):
        transfer_command(rig_data_path("ict_visemes.npz"), target, None, tmp_path / "x.usd")


def test_transfer_command_line_names_the_bad_file_and_exits_2(tmp_path):
    """`visemeflow transfer` with a target that cannot be read: one line naming the file, exit status 2, no GLB."""
    from typer.testing import CliRunner

    from visemeflow.cli import app

    missing = tmp_path / "nobody.obj"
    out = tmp_path / "out.glb"
    result = CliRunner().invoke(app, ["transfer", "--template", str(rig_data_path("ict_visemes.npz")), "--target", str(missing),
                                      "--out", str(out)])
    assert result.exit_code == 2
    # refused by the command's path check, before any mesh is read
    assert result.output.splitlines() == [f"error: path {missing} does not exist"]
    assert not out.exists()
