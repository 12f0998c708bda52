"""Characters in real rigs' naming conventions: loading, detection, the retargeting tables, chunked deformation.

The ARKit path is checked on a real third-party mesh: the ICT Face Model's own ARKit-style shapes
(`../shared/data/ict_facekit`, MIT), driven through the shipped ARKit table, must reproduce the demo rig's visemes.
"""

import subprocess
import sys

import numpy as np
import pytest

from factories import REPO, SHARED_DATA
from visemeflow.animation.apply import CurvesError, check_curves, deform, deform_all, resample, \
    resampled_frame_count
from visemeflow.rig.character import CharacterError, character_from_rig, make_character, save_character_npz
from visemeflow.animation.load import load_character
from visemeflow.shapes.conventions import ARKIT_52, CONVENTIONS, OCULUS_15, arkit_weights, bind, builtin_table, \
    detect_convention, normalize_shape_name
from visemeflow.rig import load_demo_rig, read_obj
from visemeflow.visemes import N_VISEMES, VISEMES, viseme_index

ICT = SHARED_DATA / "ict_facekit"


def tiny(names, n_vertices=4, seed=0, name="tiny"):
    rng = np.random.default_rng(seed)
    neutral = rng.normal(size=(n_vertices, 3))
    deltas = rng.normal(size=(len(names), n_vertices, 3))
    return make_character(name, neutral, [[0, 1, 2], [0, 2, 3]], names, deltas)


@pytest.fixture(scope="module")
def demo():
    return character_from_rig(load_demo_rig())


@pytest.fixture(scope="module")
def ict_arkit():
    """The ICT head (full mesh) with its 35 shapes under ICT's own names (`mouthStretch_L`, ...), as a folder."""
    assert ICT.is_dir(), f"{ICT} missing: the shared data must be present"
    neutral = read_obj(ICT / "generic_neutral_mesh.obj.gz")
    files = sorted((ICT / "shapes_mouth_jaw_cheek_nose").glob("*.obj.gz"))
    names = [p.name.removesuffix(".obj.gz") for p in files]
    deltas = np.stack([read_obj(p).vertices - neutral.vertices for p in files])
    return make_character("ict_arkit", neutral.vertices, neutral.faces, names, deltas, ICT)


def test_our_rig_is_detected_as_our_16_visemes_and_binds_as_the_identity(demo):
    assert detect_convention(demo) == "visemeflow16"
    binding = bind(demo)
    np.testing.assert_array_equal(binding.matrix, np.eye(N_VISEMES, dtype=np.float32))
    curves = np.random.default_rng(1).uniform(size=(7, N_VISEMES)).astype(np.float32)
    np.testing.assert_array_equal(binding.weights(curves), curves)
    assert binding.missing == () and binding.unmapped == ()


def test_ict_shapes_are_detected_as_arkit_and_reproduce_the_demo_visemes(ict_arkit, demo):
    """Curves -> shipped ARKit table -> ICT's ARKit-style shapes gives the demo rig's meshes (same ICT vertices)."""
    assert detect_convention(ict_arkit) == "arkit52"
    binding = bind(ict_arkit)
    assert "mouthStretch_L" in binding.driven and "jawOpen" in binding.driven
    assert binding.unmapped == () and binding.missing == ()
    curves = np.random.default_rng(2).uniform(0, 0.15, size=(5, N_VISEMES)).astype(np.float32)
    assert (binding.weights(curves) < 1).all()  # no clipping, so the two meshes must agree
    ours = deform_all(demo, curves)
    theirs = deform_all(ict_arkit, binding.weights(curves))[:, :9409]  # the face: first vertices of both meshes
    assert np.abs(ours[:, :9409] - theirs).max() < 0.01  # cm: the table is a fit of float16-stored visemes


def test_the_shipped_arkit_table_matches_a_new_least_squares_solve():
    run = subprocess.run([sys.executable, "examples/build_arkit_table.py", "--check"], cwd=REPO,
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "shipped table matches" in run.stdout
    residuals = [line for line in (REPO / "visemeflow/shapes/data/arkit_visemes.csv").read_text().splitlines()
                 if "relative" in line]
    assert len(residuals) == N_VISEMES


def test_every_builtin_table_covers_every_viseme_with_real_names():
    arkit, oculus = builtin_table("arkit52"), builtin_table("oculus15")
    assert set(arkit) == set(oculus) == set(VISEMES)
    assert {s for row in arkit.values() for s in row} <= set(ARKIT_52)
    assert {s for row in oculus.values() for s in row} <= set(OCULUS_15)
    assert oculus["MBP"] == {"viseme_PP": 1.0} and oculus["FFF"] == {"viseme_FF": 1.0}
    weights = arkit_weights(np.eye(N_VISEMES, dtype=np.float32))
    assert weights.shape == (N_VISEMES, 52)
    assert weights[viseme_index("MBP"), ARKIT_52.index("mouthPressLeft")] > 0.5
    assert weights[viseme_index("AHH"), ARKIT_52.index("jawOpen")] > 0.5


def test_oculus_names_are_detected_and_mbp_closes_pp():
    character = tiny(list(OCULUS_15) + ["eyeBlink"])
    assert detect_convention(character) == "oculus15"
    binding = bind(character)
    curves = np.zeros((2, N_VISEMES), np.float32)
    curves[1, viseme_index("MBP")] = 0.7
    weights = binding.weights(curves)
    assert weights[1, character.shape_index("viseme_PP")] == pytest.approx(0.7)
    assert weights[0].sum() == 0 and "eyeBlink" not in binding.driven
    assert binding.unmapped == ()


def test_ovrlipsync_and_vrm_names_are_detected_and_drive_their_shapes():
    """OVRLipSync's own names (sil, PP .. ih, oh, ou: Ready Player Me writes viseme_PP .. viseme_I, O, U), VRoid's
    Fcl_MTH_A .. O and VRM 1.0's aa ih ou ee oh were "no known convention" (a new user's report)."""
    plain = ["sil", "PP", "FF", "TH", "DD", "kk", "CH", "SS", "nn", "RR", "aa", "E", "ih", "oh", "ou", "blink"]
    binding = bind(tiny(plain))
    assert binding.convention == "oculus15" and binding.unmapped == () and binding.warnings() == []
    curves = np.zeros((1, N_VISEMES), np.float32)
    curves[0, viseme_index("MBP")], curves[0, viseme_index("UUU")] = 0.7, 0.4
    weights = dict(zip(plain, binding.weights(curves)[0]))
    assert weights["PP"] == pytest.approx(0.7) and weights["ou"] == pytest.approx(0.4) and weights["blink"] == 0
    vroid = ["Fcl_ALL_Joy", "Fcl_MTH_Close", "Fcl_MTH_A", "Fcl_MTH_I", "Fcl_MTH_U", "Fcl_MTH_E", "Fcl_MTH_O",
             "Fcl_EYE_Close"]
    for names in (vroid, ["aa", "ih", "ou", "ee", "oh", "blink", "happy"], ["A", "I", "U", "E", "O"]):
        character = tiny(names)
        binding = bind(character)
        assert binding.convention == "vrm5" and binding.warnings() == [], names
        curves = np.zeros((3, N_VISEMES), np.float32)
        curves[0, viseme_index("AAA")], curves[1, viseme_index("IEE")], curves[2, viseme_index("MBP")] = 1, 1, 1
        w = binding.weights(curves)
        assert w[0, character.shape_index(names[0] if names[0] != "Fcl_ALL_Joy" else "Fcl_MTH_A")] == 1.0
        assert w[2].sum() == 0      # b/p/m: a VRM avatar's rest mouth is closed
    assert "vrm5" in CONVENTIONS and set(builtin_table("vrm5")) == set(VISEMES)


def test_a_rig_lacking_the_shapes_that_close_the_lips_is_warned_about():
    """A partial ARKit rig without mouthPress (which carries 1.2 of MBP's 1.47 in the table): its b/p/m would open
    the jaw a little instead of closing the lips; the binding says so and what to do. A full rig says nothing."""
    few = ["jawOpen", "mouthClose", "mouthFunnel", "mouthPucker", "mouthSmileLeft", "mouthSmileRight",
           "mouthRollLower", "mouthUpperUpLeft", "mouthUpperUpRight", "eyeBlinkLeft"]
    (warning,) = bind(tiny(few)).warnings()
    assert "the lips will not close at b/p/m" in warning and "mouthPressLeft, mouthPressRight" in warning
    assert "82%" in warning and "--mapping" in warning
    assert bind(tiny(list(ARKIT_52))).warnings() == []
    (mbp, fff) = bind(tiny(["jawOpen", "mouthClose", "mouthFunnel", "mouthPucker", "mouthSmileLeft",
                            "mouthSmileRight", "mouthStretchLeft", "mouthStretchRight"])).warnings()
    assert "b/p/m" in mbp and "f/v" in fff and "mouthRollLower" in fff
    # a rig without the shapes that open the mouth (a user's probe: the mouth barely moved and nothing said why)
    (ahh,) = bind(tiny(["mouthClose", "mouthFunnel", "mouthPucker", "mouthSmileLeft", "mouthSmileRight",
                        "mouthPressLeft", "mouthPressRight", "mouthRollLower", "mouthStretchLeft",
                        "mouthStretchRight"])).warnings()
    assert "the mouth will hardly open at open vowels" in ahh and "jawOpen" in ahh and "AHH,YOUR_SHAPE" in ahh


def test_names_match_across_case_namespaces_and_side_suffixes():
    assert normalize_shape_name("blendShape1.JawOpen") == normalize_shape_name("jawOpen")
    assert normalize_shape_name("mouthSmile_L") == normalize_shape_name("mouthSmileLeft")
    assert normalize_shape_name("Head:mouthPress_R") == normalize_shape_name("mouthPressRight")
    names = ["blendShape1." + n[0].upper() + n[1:] for n in ARKIT_52[14:41]]
    assert detect_convention(tiny(names)) == "arkit52"


def test_a_character_with_unknown_names_is_an_error_listing_names_and_conventions():
    with pytest.raises(CharacterError) as err:
        detect_convention(tiny(["smile", "frown", "blink"]))
    message = str(err.value)
    assert "smile, frown, blink" in message
    for known in ("visemeflow16", "arkit52", "oculus15", "mapping CSV"):
        assert known in message


def test_a_mapping_csv_drives_any_names_and_rejects_unknown_shapes(tmp_path):
    character = tiny(["LipsTogether", "Open", "Round"])
    mapping = tmp_path / "map.csv"
    mapping.write_text("viseme,shape,weight\nMBP,LipsTogether,1\nAHH,Open,0.8\nUUU,Round,1\nOHH,Round,0.5\n"
                       "OHH,Open,0.3\n")
    binding = bind(character, mapping=mapping)
    assert binding.convention == "mapping"
    curves = np.zeros((1, N_VISEMES), np.float32)
    curves[0, viseme_index("OHH")] = 1.0
    np.testing.assert_allclose(binding.weights(curves)[0], [0, 0.3, 0.5])
    assert "MBP" not in binding.unmapped and "AAA" in binding.unmapped
    mapping.write_text("viseme,shape,weight\nMBP,Lips,1\n")
    with pytest.raises(CharacterError, match=r"map\.csv.*'Lips'.*LipsTogether"):
        bind(character, mapping=mapping)
    mapping.write_text("viseme,shape,weight\nXYZ,Open,1\n")
    with pytest.raises(CharacterError, match=r"map\.csv line 2: unknown viseme 'XYZ'"):
        bind(character, mapping=mapping)


def test_bad_characters_are_errors_naming_the_problem(tmp_path):
    with pytest.raises(CharacterError, match="used twice"):
        tiny(["jawOpen", "jawOpen"])
    with pytest.raises(CharacterError, match="no blendshapes"):
        tiny([])
    neutral = np.zeros((4, 3))
    neutral[2, 1] = np.nan
    with pytest.raises(CharacterError, match="NaN.*vertex 2"):
        make_character("nan", neutral, [[0, 1, 2]], ["a"], np.zeros((1, 4, 3)), source=tmp_path / "nan.glb")
    deltas = np.zeros((2, 4, 3))
    deltas[1, 0, 0] = np.inf
    with pytest.raises(CharacterError, match="'b' has NaN or infinite"):
        make_character("inf", np.zeros((4, 3)), [[0, 1, 2]], ["a", "b"], deltas)
    with pytest.raises(CharacterError, match="no such character"):
        load_character(tmp_path / "missing.glb")
    (tmp_path / "c.fbx").write_text("x")
    with pytest.raises(CharacterError, match="unknown character format"):
        load_character(tmp_path / "c.fbx")


def test_characters_load_from_npz_and_mesh_folders(tmp_path, demo):
    character = tiny(list(OCULUS_15), n_vertices=4)
    back = load_character(save_character_npz(character, tmp_path / "c.npz"))
    assert back.shape_names == character.shape_names
    np.testing.assert_array_equal(back.deltas, character.deltas)
    rig = load_character(REPO / "visemeflow/rig/data/ict_visemes.npz")
    assert rig.shape_names == VISEMES and rig.n_vertices == demo.n_vertices
    assert rig.vertex_colors is not None and rig.vertex_colors.shape == (demo.n_vertices, 3)
    again = load_character(save_character_npz(rig, tmp_path / "rig.npz"))
    np.testing.assert_array_equal(again.vertex_colors, rig.vertex_colors)
    folder = tmp_path / "folder"
    folder.mkdir()
    verts = "v 0 0 0\nv 1 0 0\nv 0 1 0\n"
    (folder / "neutral.obj").write_text(verts + "f 1 2 3\n")
    (folder / "jawOpen.obj").write_text("v 0 -1 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    loaded = load_character(folder)
    assert loaded.shape_names == ("jawOpen",)
    np.testing.assert_allclose(loaded.deltas[0, 0], [0, -1, 0])
    (folder / "mouthClose.obj").write_text("v 0 0 0\nv 1 0 0\nf 1 2 2\n")
    with pytest.raises(CharacterError, match="mouthClose.obj: 2 vertices"):
        load_character(folder)


def test_curve_checks_name_the_utterance_frame_and_viseme():
    curves = np.full((4, N_VISEMES), 0.5, np.float32)
    curves[2, viseme_index("OHH")] = np.nan
    with pytest.raises(CurvesError, match=r"spk/u1.*OHH is nan at frame 2"):
        check_curves(curves, "spk/u1")
    curves[2, viseme_index("OHH")] = 1.3
    with pytest.raises(CurvesError, match=r"OHH is 1.3000 at frame 2, outside \[0, 1\]"):
        check_curves(curves, "spk/u1")
    curves[2, viseme_index("OHH")] = 1.0004
    assert check_curves(curves, "spk/u1").max() == 1.0


def test_resampling_keeps_the_duration_and_interpolates_linearly():
    t = np.arange(31) / 30.0
    curves = np.tile(t[:, None], (1, N_VISEMES)).astype(np.float32) / t[-1]
    out = resample(curves, 30.0, 25.0)
    assert len(out) == resampled_frame_count(31, 30, 25) == 26
    np.testing.assert_allclose(out[:, 0], (np.arange(26) / 25.0) / t[-1], atol=1e-6)
    assert resample(curves, 30, 60).shape[0] == 61
    assert resample(curves, 30, 30) is not None and len(resample(curves, 30, 30)) == 31


def test_chunked_deformation_equals_one_matmul_and_bounds_memory(demo):
    weights = np.random.default_rng(3).uniform(size=(50, N_VISEMES)).astype(np.float32)
    chunks = list(deform(demo, weights, chunk_frames=16))
    assert [start for start, _ in chunks] == [0, 16, 32, 48]
    assert max(len(block) for _, block in chunks) == 16
    full = demo.neutral[None] + np.einsum("ts,svc->tvc", weights, demo.deltas)
    np.testing.assert_allclose(np.concatenate([b for _, b in chunks]), full, atol=1e-4)
    with pytest.raises(ValueError, match="weights must be"):
        next(deform(demo, weights[:, :3]))
