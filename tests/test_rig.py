"""Rig loading (folder of OBJ/PLY/GLB, GLB morph targets, npz), validation errors, evaluation, recipes, the demo rig."""

from __future__ import annotations

import base64
import gzip
import importlib.util
import json
import struct
import weakref
from pathlib import Path

import numpy as np
import pytest
import torch

from visemeflow.rig import (
    RigError,
    VisemeRig,
    combine_shapes,
    demo_rig_path,
    evaluate_rig,
    load_demo_rig,
    load_ict_recipes,
    load_rig,
    load_rig_folder,
    load_rig_glb,
    linear_to_srgb,
    load_rig_npz,
    parse_recipes,
    read_mesh,
    read_obj,
    recipe_shapes,
    rig_tensors,
    save_rig_npz,
    srgb_to_linear,
    validate_rig,
)
from visemeflow.visemes import N_VISEMES, VISEMES, viseme_index

REPO = Path(__file__).resolve().parents[1]
ICT = REPO.parent / "shared" / "data" / "ict_facekit"

# ------------------------------------------------------------------------------------------ tiny rig builders

# a 3x3 grid of vertices in the z = 0 plane, 8 triangles, counter-clockwise seen from +z
GRID = np.array([[x, y, 0.0] for y in range(3) for x in range(3)], np.float64)
QUADS = [[0, 1, 4, 3], [1, 2, 5, 4], [3, 4, 7, 6], [4, 5, 8, 7]]
TRIANGLES = np.array([t for q in QUADS for t in ([q[0], q[1], q[2]], [q[0], q[2], q[3]])], np.int32)


def viseme_offsets(seed: int = 0) -> np.ndarray:
    """(16, 9, 3) distinct small deltas, one set per viseme."""
    return np.random.default_rng(seed).normal(0.0, 0.1, (N_VISEMES, len(GRID), 3))


def write_obj(path: Path, vertices: np.ndarray, polygons, colors: np.ndarray | None = None) -> Path:
    """OBJ text with 1-based `v/vt` face tokens (as exporters write them); gzip when the name ends in .gz."""
    lines = ["# test mesh"]
    for i, v in enumerate(vertices):
        extra = "" if colors is None else " " + " ".join(f"{c:.6f}" for c in colors[i])
        lines.append("v " + " ".join(f"{c:.9g}" for c in v) + extra)
    lines.append("vt 0 0")
    lines += ["f " + " ".join(f"{i + 1}/1" for i in polygon) for polygon in polygons]
    text = "\n".join(lines) + "\n"
    if path.name.endswith(".gz"):
        with gzip.open(path, "wt") as handle:
            handle.write(text)
    else:
        path.write_text(text)
    return path


def write_ply(path: Path, vertices: np.ndarray, triangles: np.ndarray) -> Path:
    lines = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}", "property float x", "property float y",
             "property float z", f"element face {len(triangles)}", "property list uchar int vertex_indices", "end_header"]
    lines += [" ".join(f"{c:.9g}" for c in v) for v in vertices]
    lines += ["3 " + " ".join(str(i) for i in t) for t in triangles]
    path.write_text("\n".join(lines) + "\n")
    return path


def write_glb(path: Path, vertices: np.ndarray, triangles: np.ndarray, targets: dict[str, np.ndarray],
              sparse: tuple[str, ...] = (), extras: dict | None = None, primitives: int = 1,
              colors: np.ndarray | None = None) -> Path:
    """A minimal glTF 2.0 asset: one mesh of `primitives` copies of one primitive (each with its own accessors) with
    morph targets (some stored as sparse accessors) and optional COLOR_0 (float32 (V, 3), or uint8 (V, 4)
    normalized). A `.gltf` name writes JSON with the buffer as a data URI, anything else a binary GLB."""
    blob = bytearray()
    views, accessors = [], []

    def add_view(data: bytes) -> int:
        while len(blob) % 4:
            blob.append(0)
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
        blob.extend(data)
        return len(views) - 1

    def add_accessor(array: np.ndarray, component: int, kind: str) -> int:
        view = add_view(array.tobytes())
        accessors.append({"bufferView": view, "componentType": component, "count": len(array), "type": kind})
        return len(accessors) - 1

    def add_primitive() -> dict:
        position = add_accessor(vertices.astype(np.float32), 5126, "VEC3")
        accessors[position].update(min=vertices.min(0).tolist(), max=vertices.max(0).tolist())
        indices = add_accessor(triangles.astype(np.uint32).reshape(-1), 5125, "SCALAR")
        target_list = []
        for name, delta in targets.items():
            delta = delta.astype(np.float32)
            if name in sparse:
                moved = np.flatnonzero(np.abs(delta).sum(1) > 0).astype(np.uint32)
                accessors.append({
                    "componentType": 5126, "count": len(delta), "type": "VEC3",
                    "sparse": {"count": int(len(moved)),
                               "indices": {"bufferView": add_view(moved.tobytes()), "componentType": 5125},
                               "values": {"bufferView": add_view(delta[moved].tobytes())}},
                })
                target_list.append({"POSITION": len(accessors) - 1})
            else:
                target_list.append({"POSITION": add_accessor(delta, 5126, "VEC3")})
        attributes = {"POSITION": position}
        if colors is not None and colors.dtype == np.float32:
            attributes["COLOR_0"] = add_accessor(colors, 5126, "VEC3")
        elif colors is not None:
            attributes["COLOR_0"] = add_accessor(colors, 5121, "VEC4")
            accessors[-1]["normalized"] = True
        return {"attributes": attributes, "indices": indices, "targets": target_list}

    mesh = {"primitives": [add_primitive() for _ in range(primitives)],
            "extras": {"targetNames": list(targets), **(extras or {})}}
    while len(blob) % 4:
        blob.append(0)
    document = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
                "meshes": [mesh], "accessors": accessors, "bufferViews": views,
                "buffers": [{"byteLength": len(blob)}]}
    if path.suffix == ".gltf":
        document["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
        path.write_text(json.dumps(document))
        return path
    text = json.dumps(document).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(blob), 0x004E4942) + bytes(blob)
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    return path


def make_rig_folder(root: Path, offsets: np.ndarray | None = None, landmarks: list | None = None) -> Path:
    """neutral.obj (quads) + 16 visemes: most OBJ, a few PLY and one gzipped OBJ, names in mixed case."""
    offsets = viseme_offsets() if offsets is None else offsets
    root.mkdir(parents=True, exist_ok=True)
    write_obj(root / "neutral.obj", GRID, QUADS)
    for i, name in enumerate(VISEMES):
        shape = GRID + offsets[i]
        if name in ("AHH", "UUU"):
            write_ply(root / f"{name}.ply", shape, TRIANGLES)
        elif name == "MBP":
            write_obj(root / "mbp.OBJ", shape, QUADS)
        elif name == "SSS":
            write_obj(root / "SSS.obj.gz", shape, QUADS)
        else:
            write_obj(root / f"{name}.obj", shape, QUADS)
    if landmarks is not None:
        (root / "landmarks.json").write_text(json.dumps(landmarks))
    return root


def tiny_rig(**changes) -> VisemeRig:
    fields = dict(
        name="tiny",
        neutral=GRID.astype(np.float32),
        deltas=viseme_offsets().astype(np.float32),
        faces=TRIANGLES.copy(),
        landmark_ids=np.array([i % len(GRID) for i in range(68)], np.int64),
        vertex_colors=np.full((len(GRID), 3), 0.5, np.float32),
        regions={"mouth_interior": np.array([4], np.int64)},
    )
    fields.update(changes)
    return VisemeRig(**fields)


# ------------------------------------------------------------------------------------------ loading

def test_obj_reader_splits_polygons_into_fans_in_file_order(tmp_path):
    path = write_obj(tmp_path / "m.obj", GRID, [[0, 1, 4], [1, 2, 5, 4], [3, 4, 8, 7, 6]])
    mesh = read_obj(path)
    assert mesh.faces.tolist() == [[0, 1, 4], [1, 2, 5], [1, 5, 4], [3, 4, 8], [3, 8, 7], [3, 7, 6]]
    assert mesh.faces.dtype == np.int32 and mesh.colors is None
    np.testing.assert_allclose(mesh.vertices, GRID)


def test_obj_reader_reads_vertex_colours_and_negative_indices(tmp_path):
    colors = np.linspace(0, 1, 27).reshape(9, 3)
    path = tmp_path / "c.obj"
    write_obj(path, GRID, [])
    path.write_text(path.read_text().replace("f ", "") + "f -9 -8 -5\n")
    write_obj(tmp_path / "c2.obj", GRID, [[0, 1, 4]], colors)
    assert read_obj(path).faces.tolist() == [[0, 1, 4]]
    np.testing.assert_allclose(read_obj(tmp_path / "c2.obj").colors, colors, atol=1e-6)


def test_load_rig_folder_mixed_formats_and_case(tmp_path):
    offsets = viseme_offsets()
    folder = make_rig_folder(tmp_path / "rig", offsets, landmarks=list(range(9)) * 7 + [None] * 5)
    (folder / "README.txt").write_text("not a mesh: ignored")
    rig = load_rig(folder)
    assert rig.name == "rig"
    assert rig.neutral.dtype == np.float32 and rig.deltas.dtype == np.float32 and rig.faces.dtype == np.int32
    assert rig.deltas.shape == (16, 9, 3)
    np.testing.assert_allclose(rig.deltas, offsets, atol=1e-6)
    assert rig.faces.tolist() == TRIANGLES.tolist()
    assert rig.landmark_ids.tolist() == list(range(9)) * 7 + [-1] * 5
    assert rig.valid_landmarks.sum() == 63
    np.testing.assert_allclose(rig.viseme_shape("MBP"), GRID + offsets[viseme_index("MBP")], atol=1e-6)


def test_load_rig_folder_without_landmarks_has_none(tmp_path):
    rig = load_rig_folder(make_rig_folder(tmp_path / "rig"))
    assert (rig.landmark_ids == -1).all() and rig.landmark_ids.shape == (68,)


def test_load_rig_folder_with_glb_neutral(tmp_path):
    folder = make_rig_folder(tmp_path / "rig")
    (folder / "neutral.obj").unlink()
    write_glb(folder / "Neutral.glb", GRID, TRIANGLES, {})
    rig = load_rig_folder(folder)
    np.testing.assert_allclose(rig.neutral, GRID)


def test_load_rig_glb_with_morph_targets(tmp_path):
    offsets = viseme_offsets(3)
    offsets[viseme_index("MBP"), 1:] = 0.0  # a sparse target moves few vertices
    # file order differs from VISEMES order, names in mixed case, two targets stored as sparse accessors
    names = [name.lower() if i % 2 else name for i, name in enumerate(reversed(VISEMES))]
    targets = {name: offsets[viseme_index(name.upper())] for name in names}
    sparse = tuple(n for n in names if n.upper() in ("MBP", "AHH"))
    path = write_glb(tmp_path / "face.glb", GRID, TRIANGLES, targets, sparse=sparse, extras={"landmark_ids": [4] * 68})
    rig = load_rig(path)
    assert rig.name == "face"
    np.testing.assert_allclose(rig.neutral, GRID)
    np.testing.assert_allclose(rig.deltas, offsets, atol=1e-6)
    assert rig.faces.tolist() == TRIANGLES.tolist()
    assert (rig.landmark_ids == 4).all()


def test_load_rig_gltf_with_data_uri_and_two_primitives(tmp_path):
    offsets = viseme_offsets(4)
    path = write_glb(tmp_path / "face.gltf", GRID, TRIANGLES, {v: offsets[i] for i, v in enumerate(VISEMES)},
                     primitives=2)
    rig = load_rig(path)
    np.testing.assert_allclose(rig.neutral, np.concatenate([GRID, GRID]))
    assert rig.faces.tolist() == np.concatenate([TRIANGLES, TRIANGLES + 9]).tolist()
    np.testing.assert_allclose(rig.deltas, np.concatenate([offsets, offsets], axis=1), atol=1e-6)


def test_load_rig_glb_landmark_sidecar_wins(tmp_path):
    path = write_glb(tmp_path / "face.glb", GRID, TRIANGLES, {v: viseme_offsets()[i] for i, v in enumerate(VISEMES)})
    (tmp_path / "face.landmarks.json").write_text(json.dumps({"landmark_ids": [2] * 68}))
    assert (load_rig_glb(path).landmark_ids == 2).all()


def test_npz_round_trip(tmp_path):
    rig = tiny_rig()
    path = save_rig_npz(rig, tmp_path / "tiny.npz")
    with np.load(path) as raw:
        assert raw["deltas"].dtype == np.float16 and raw["neutral"].dtype == np.float32
        assert raw["faces"].dtype == np.int32
    back = load_rig(path)
    assert back.name == "tiny"
    np.testing.assert_array_equal(back.neutral, rig.neutral)
    np.testing.assert_allclose(back.deltas, rig.deltas, atol=1e-3)
    assert back.deltas.dtype == np.float32
    np.testing.assert_array_equal(back.faces, rig.faces)
    np.testing.assert_array_equal(back.landmark_ids, rig.landmark_ids)
    np.testing.assert_allclose(back.vertex_colors, rig.vertex_colors, atol=1 / 255)
    assert list(back.regions) == ["mouth_interior"] and back.regions["mouth_interior"].tolist() == [4]


def test_npz_round_trip_without_colours_keeps_name_suffix(tmp_path):
    path = save_rig_npz(tiny_rig(vertex_colors=None, regions={}), tmp_path / "plain.rig")
    assert path.exists() and not (tmp_path / "plain.rig.npz").exists()
    back = load_rig_npz(path)
    assert back.vertex_colors is None and back.regions == {}


# ------------------------------------------------------------------------------------------ loading errors

def test_missing_viseme_is_named(tmp_path):
    folder = make_rig_folder(tmp_path / "rig")
    (folder / "UUU.ply").unlink()
    with pytest.raises(RigError, match=r"missing viseme mesh\(es\) UUU"):
        load_rig_folder(folder)


def test_missing_neutral(tmp_path):
    folder = make_rig_folder(tmp_path / "rig")
    (folder / "neutral.obj").unlink()
    with pytest.raises(RigError, match="no neutral mesh"):
        load_rig_folder(folder)


def test_vertex_count_mismatch_names_file_and_counts(tmp_path):
    folder = make_rig_folder(tmp_path / "rig")
    write_obj(folder / "EH.obj", GRID[:8], [[0, 1, 4]])
    with pytest.raises(RigError, match=r"EH\.obj: 8 vertices, but neutral\.obj has 9"):
        load_rig_folder(folder)


def test_topology_mismatch_names_file(tmp_path):
    folder = make_rig_folder(tmp_path / "rig")
    write_obj(folder / "GK.obj", GRID, QUADS[:3])
    with pytest.raises(RigError, match=r"GK\.obj: topology differs from neutral\.obj \(6 vs 8 triangles"):
        load_rig_folder(folder)


def test_unknown_mesh_name(tmp_path):
    folder = make_rig_folder(tmp_path / "rig")
    write_obj(folder / "AAHH.obj", GRID, QUADS)
    with pytest.raises(RigError, match=r"AAHH\.obj: unknown mesh name 'AAHH'"):
        load_rig_folder(folder)


def test_duplicate_viseme_mesh(tmp_path):
    folder = make_rig_folder(tmp_path / "rig")
    write_obj(folder / "aaa.obj.gz", GRID, QUADS)
    with pytest.raises(RigError, match="a second mesh for 'aaa'"):
        load_rig_folder(folder)


def test_non_finite_vertex_names_file(tmp_path):
    folder = make_rig_folder(tmp_path / "rig")
    bad = GRID.copy()
    bad[5, 1] = np.nan
    write_obj(folder / "TTH.obj", bad, QUADS)
    with pytest.raises(RigError, match=r"TTH\.obj: non-finite vertex coordinates \(first at vertex 5\)"):
        load_rig_folder(folder)


def test_bad_face_id_in_obj(tmp_path):
    folder = make_rig_folder(tmp_path / "rig")
    write_obj(folder / "neutral.obj", GRID, QUADS + [[0, 1, 12]])
    with pytest.raises(RigError, match=r"neutral\.obj: OBJ face refers to a vertex outside 1\.\.9"):
        load_rig_folder(folder)


def test_wrong_landmark_count(tmp_path):
    folder = make_rig_folder(tmp_path / "rig", landmarks=list(range(9)) * 7)
    with pytest.raises(RigError, match=r"landmarks\.json: expected 68 landmark vertex ids .*got 63"):
        load_rig_folder(folder)


def test_landmark_out_of_range(tmp_path):
    folder = make_rig_folder(tmp_path / "rig", landmarks=[9] * 68)
    with pytest.raises(RigError, match=r"landmarks\.json: landmark ids must lie in \[0, 9\)"):
        load_rig_folder(folder)


def test_glb_unknown_and_missing_targets(tmp_path):
    targets = {v: viseme_offsets()[i] for i, v in enumerate(VISEMES)}
    with pytest.raises(RigError, match=r"face\.glb: unknown morph target name 'jawOpen'"):
        load_rig_glb(write_glb(tmp_path / "face.glb", GRID, TRIANGLES, {**targets, "jawOpen": targets["AHH"]}))
    del targets["WWW"]
    with pytest.raises(RigError, match=r"missing viseme morph target\(s\) WWW"):
        load_rig_glb(write_glb(tmp_path / "face.glb", GRID, TRIANGLES, targets))
    with pytest.raises(RigError, match="no mesh with morph targets"):
        load_rig_glb(write_glb(tmp_path / "face.glb", GRID, TRIANGLES, {}))


def test_glb_problems_are_rig_errors_that_name_the_file(tmp_path):
    targets = {v: viseme_offsets()[i] for i, v in enumerate(VISEMES)}
    (tmp_path / "text.glb").write_text("not a model")
    no_names = write_glb(tmp_path / "no-names.glb", GRID, TRIANGLES, targets)
    document = json.loads(no_names.read_bytes()[20:20 + struct.unpack_from("<I", no_names.read_bytes(), 12)[0]])
    assert document["meshes"][0]["extras"]["targetNames"] == list(targets)    # the helper's layout, as read here
    blob = no_names.read_bytes()
    no_names.write_bytes(blob.replace(b'"targetNames"', b'"targetNamez"'))   # same length: the GLB stays whole
    cases = {"text.glb": "not a glTF 2.0 / GLB file", "no-names.glb": "16 morph targets but no names",
             "gone.glb": "cannot be read"}
    for name, expected in cases.items():
        with pytest.raises(RigError) as info:
            load_rig_glb(tmp_path / name)
        assert str(tmp_path / name) in str(info.value) and expected in str(info.value), str(info.value)
    with pytest.raises(RigError, match=r"neutral\.glb: no mesh in this glTF file"):
        (tmp_path / "neutral.glb").write_bytes(no_names.read_bytes().replace(b'"meshes"', b'"meshez"'))
        read_mesh(tmp_path / "neutral.glb")


def test_srgb_and_linear_are_inverse_and_match_the_standard():
    assert srgb_to_linear([0.0, 0.04045, 0.5, 1.0]).tolist() == pytest.approx([0.0, 0.04045 / 12.92, 0.214041, 1.0],
                                                                              abs=1e-6)
    assert linear_to_srgb([0.0, 0.0031308, 0.5, 1.0]).tolist() == pytest.approx([0.0, 0.0031308 * 12.92, 0.735357,
                                                                                 1.0], abs=1e-6)
    values = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(values)), values, atol=2e-6)
    assert linear_to_srgb([-0.5, 2.0]).tolist() == [0.0, 1.0]                   # clipped


@pytest.mark.parametrize("stored", ["float", "uint8"])
def test_glb_vertex_colours_come_back_as_srgb(tmp_path, stored):
    """COLOR_0 is linear (glTF 2.0); rigs hold sRGB display colours, so the reader converts."""
    linear = np.linspace(0.0, 1.0, 27).reshape(9, 3).astype(np.float32)
    colors = linear if stored == "float" else np.concatenate(
        [np.round(linear * 255).astype(np.uint8), np.full((9, 1), 128, np.uint8)], axis=1)     # alpha ignored
    expected = linear_to_srgb(linear if stored == "float" else np.round(linear * 255) / 255)
    targets = {v: viseme_offsets()[i] for i, v in enumerate(VISEMES)}
    rig = load_rig_glb(write_glb(tmp_path / "face.glb", GRID, TRIANGLES, targets, colors=colors, primitives=2))
    assert rig.vertex_colors.dtype == np.float32 and rig.vertex_colors.shape == (18, 3)
    np.testing.assert_allclose(rig.vertex_colors, np.concatenate([expected, expected]), atol=1e-6)
    assert rig.vertex_colors[4].tolist() != linear[4].tolist()                   # converted, not copied
    mesh = read_mesh(write_glb(tmp_path / "neutral.glb", GRID, TRIANGLES, {}, colors=colors))
    np.testing.assert_allclose(mesh.colors, expected, atol=1e-6)
    assert read_mesh(write_glb(tmp_path / "plain.glb", GRID, TRIANGLES, {})).colors is None


def test_load_rig_unknown_format_and_missing_path(tmp_path):
    (tmp_path / "rig.fbx").write_bytes(b"x")
    with pytest.raises(RigError, match="unknown rig format .fbx"):
        load_rig(tmp_path / "rig.fbx")
    with pytest.raises(RigError, match="no such rig"):
        load_rig(tmp_path / "nothing.npz")


def test_npz_that_is_not_a_rig(tmp_path):
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(RigError, match=r"other\.npz: not a visemeflow rig npz \(missing neutral, deltas"):
        load_rig_npz(tmp_path / "other.npz")


# ------------------------------------------------------------------------------------------ validate_rig

@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"neutral": GRID[:, :2].astype(np.float32)}, r"neutral must have shape \(V, 3\)"),
        ({"neutral": GRID.astype(np.float64)}, "neutral must be float32"),
        ({"neutral": np.where(GRID == 2, np.inf, GRID).astype(np.float32)}, "neutral has non-finite coordinates"),
        ({"deltas": viseme_offsets()[:15].astype(np.float32)}, r"deltas must have shape \(16, V, 3\), one per viseme"),
        ({"deltas": viseme_offsets()[:, :8].astype(np.float32)}, "deltas have 8 vertices per viseme, the neutral has 9"),
        ({"deltas": np.where(np.arange(16)[:, None, None] == 7, np.nan, viseme_offsets()).astype(np.float32)},
         "viseme MBP has non-finite coordinates"),
        ({"faces": TRIANGLES[:, :2]}, r"faces must have shape \(F, 3\)"),
        ({"faces": TRIANGLES.astype(np.float32)}, "faces must be integer vertex ids"),
        ({"faces": TRIANGLES + 1}, r"face vertex ids must lie in \[0, 9\), got 1\.\.9"),
        ({"landmark_ids": np.zeros(67, np.int64)}, "landmark_ids must hold 68 ids"),
        ({"landmark_ids": np.full(68, 9, np.int64)}, r"landmark_ids must lie in \[0, 9\) or be -1"),
        ({"vertex_colors": np.full((9, 3), 1.5, np.float32)}, r"vertex_colors must be finite RGB in \[0, 1\]"),
        ({"vertex_colors": np.full((8, 3), 0.5, np.float32)}, r"vertex_colors must have shape \(9, 3\)"),
        ({"regions": {"lips": np.array([42])}}, r"region 'lips' has vertex ids outside \[0, 9\)"),
    ],
)
def test_validate_rig_names_the_problem(changes, message):
    with pytest.raises(RigError, match=message):
        validate_rig(tiny_rig(**changes))


@pytest.mark.parametrize(
    "changes",
    [
        {},
        {"landmark_ids": np.full(68, -1, np.int64)},                    # a rig with no landmark vertices
        {"vertex_colors": None, "regions": {}},                        # colours and regions are optional
        {"vertex_colors": np.tile(np.float32([0, 1, 1]), (9, 1))},     # the ends of [0, 1]
        {"faces": TRIANGLES.astype(np.int64)},                         # any integer dtype
        {"regions": {"lips": np.array([0, 8])}},                       # ids at both ends of [0, 9)
    ],
)
def test_validate_rig_accepts_rigs_at_the_edges_of_the_rules(changes):
    rig = tiny_rig(**changes)
    assert validate_rig(rig) is None  # raises RigError otherwise


def test_save_refuses_an_invalid_rig(tmp_path):
    with pytest.raises(RigError, match="faces must have shape"):
        save_rig_npz(tiny_rig(faces=TRIANGLES[:, :2]), tmp_path / "x.npz")


# ------------------------------------------------------------------------------------------ evaluation

def test_evaluate_rig_equals_numpy_sum_full_and_subset():
    rig = tiny_rig()
    weights = np.random.default_rng(1).uniform(0, 1, (7, 16)).astype(np.float32)
    expected = rig.neutral[None] + np.einsum("ti,ivc->tvc", weights, rig.deltas)
    full = evaluate_rig(rig, weights)
    assert full.dtype == torch.float32 and full.shape == (7, 9, 3)
    np.testing.assert_allclose(full.numpy(), expected, atol=1e-5)
    subset = evaluate_rig(rig, torch.from_numpy(weights), rig.landmark_ids)
    assert subset.shape == (7, 68, 3)
    np.testing.assert_allclose(subset.numpy(), expected[:, rig.landmark_ids], atol=1e-5)
    single = evaluate_rig(rig, weights[3].astype(np.float64), [8, 0])
    np.testing.assert_allclose(single.numpy(), expected[3, [8, 0]], atol=1e-5)


def test_evaluate_rig_gradient_is_the_delta_contraction():
    rig = tiny_rig()
    weights = torch.rand(4, 16, requires_grad=True)
    out = evaluate_rig(rig, weights, rig.landmark_ids[:5])
    out.sum().backward()
    expected = rig.deltas[:, rig.landmark_ids[:5]].sum(axis=(1, 2))
    np.testing.assert_allclose(weights.grad.numpy(), np.tile(expected, (4, 1)), rtol=1e-5, atol=1e-6)


def test_evaluate_rig_rejects_bad_shapes_and_ids():
    rig = tiny_rig()
    with pytest.raises(ValueError, match=r"weights must have shape \(T, 16\)"):
        evaluate_rig(rig, np.zeros((3, 15)))
    with pytest.raises(RigError, match="drop them before evaluating"):
        evaluate_rig(rig, np.zeros((1, 16)), [-1, 2])


def test_rig_tensors_are_cached_per_rig_and_dropped_with_it():
    rig = tiny_rig()
    assert rig_tensors(rig) is rig_tensors(rig)
    first = rig_tensors(rig).basis(np.array([1, 2]))
    assert rig_tensors(rig).basis(np.array([1, 2]))[0] is first[0]
    tensors = weakref.ref(rig_tensors(rig))
    del rig, first
    import gc

    gc.collect()
    assert tensors() is None


# ------------------------------------------------------------------------------------------ recipes

def test_parse_recipes_errors():
    rows = "".join(f"{v},jawOpen,0.1\n" for v in VISEMES)
    assert parse_recipes("viseme,shape,weight\n" + rows)["MBP"] == {"jawOpen": 0.1}
    with pytest.raises(RigError, match="expected the header"):
        parse_recipes("a,b,c\n" + rows)
    with pytest.raises(RigError, match="line 2: unknown viseme 'ZZZ'"):
        parse_recipes("viseme,shape,weight\nZZZ,jawOpen,1\n" + rows)
    with pytest.raises(RigError, match=r"no recipe row for viseme\(s\) WWW"):
        parse_recipes("viseme,shape,weight\n" + rows.replace("WWW,jawOpen,0.1\n", ""))
    with pytest.raises(RigError, match="weight 'x' is not a number"):
        parse_recipes("viseme,shape,weight\nAAA,jawOpen,x\n" + rows)
    with pytest.raises(RigError, match="lists 'jawOpen' twice"):
        parse_recipes("viseme,shape,weight\n" + rows + "AAA,jawOpen,0.2\n")


def test_combine_shapes_is_the_weighted_sum():
    rng = np.random.default_rng(2)
    shapes = {"a": rng.normal(size=(5, 3)), "b": rng.normal(size=(5, 3))}
    recipes = {v: {"a": 0.5} for v in VISEMES}
    recipes["IEE"] = {"a": 0.25, "b": 1.0}
    deltas = combine_shapes(shapes, recipes)
    np.testing.assert_allclose(deltas[viseme_index("IEE")], 0.25 * shapes["a"] + shapes["b"], rtol=1e-6)
    np.testing.assert_allclose(deltas[viseme_index("AAA")], 0.5 * shapes["a"], rtol=1e-6)
    with pytest.raises(RigError, match="shape\\(s\\) not provided: b"):
        combine_shapes({"a": shapes["a"]}, recipes)


def test_ict_recipes_cover_every_viseme_with_ict_shapes():
    recipes = load_ict_recipes()
    assert list(recipes) == list(VISEMES) and all(recipes.values())
    if ICT.is_dir():
        available = {p.name[: -len(".obj.gz")] for p in (ICT / "shapes_mouth_jaw_cheek_nose").glob("*.obj.gz")}
        assert set(recipe_shapes(recipes)) <= available


# ------------------------------------------------------------------------------------------ the demo rig

@pytest.fixture(scope="module")
def demo():
    return load_demo_rig()


@pytest.fixture(scope="module")
def demo_landmarks(demo):
    """(17, 68, 3): the neutral, then each viseme at weight 1."""
    weights = np.vstack([np.zeros(16), np.eye(16)]).astype(np.float32)
    return evaluate_rig(demo, weights, demo.landmark_ids).numpy()


def test_demo_rig_is_shipped_small_and_valid(demo):
    assert demo_rig_path().stat().st_size < 3_000_000
    validate_rig(demo)
    assert (demo.landmark_ids >= 0).all()
    assert demo.vertex_colors is not None
    assert {"face", "lips", "mouth_interior", "teeth", "eyes"} <= set(demo.regions)
    soft_tissue = np.setdiff1d(demo.regions["mouth_interior"], demo.regions["teeth"])
    interior = demo.vertex_colors[soft_tissue].mean(axis=0)
    face = demo.vertex_colors[demo.regions["face"]].mean(axis=0)
    assert interior.sum() < 0.4 * face.sum()  # a dark mouth
    for name in ("LICENSE", "SOURCE.txt", "README.md"):
        assert (demo_rig_path().parent / name).is_file()


def _inner_gap(lm):
    return np.linalg.norm(lm[..., 62, :] - lm[..., 66, :], axis=-1)


def _width(lm):
    return np.linalg.norm(lm[..., 48, :] - lm[..., 54, :], axis=-1)


def test_demo_mbp_closes_the_lips(demo_landmarks):
    gaps = _inner_gap(demo_landmarks)
    mbp = gaps[1 + viseme_index("MBP")]
    assert mbp < 0.1  # centimetres
    assert mbp <= gaps[0] + 0.02
    assert mbp == gaps[1:].min()


def test_demo_ahh_opens_the_jaw_most(demo_landmarks):
    gaps = _inner_gap(demo_landmarks)[1:]
    chin = demo_landmarks[1:, 8, 1]
    assert gaps.argmax() == viseme_index("AHH")
    assert chin.argmin() == viseme_index("AHH")
    assert gaps[viseme_index("AHH")] > 2.5


def test_demo_uuu_is_narrowest_and_iee_wider_than_neutral(demo_landmarks):
    widths = _width(demo_landmarks)
    assert widths[1:].argmin() == viseme_index("UUU")
    assert widths[1 + viseme_index("UUU")] < widths[0] - 1.0
    assert widths[1 + viseme_index("IEE")] > widths[0] + 0.8
    assert widths[1:].argmax() == viseme_index("IEE")


def test_demo_rounded_visemes_protrude_and_fff_raises_the_lower_lip(demo_landmarks):
    neutral = demo_landmarks[0]
    for name in ("UUU", "WWW", "OHH", "SSH"):
        lips = demo_landmarks[1 + viseme_index(name)]
        assert lips[[51, 57], 2].mean() > neutral[[51, 57], 2].mean(), name
    fff = demo_landmarks[1 + viseme_index("FFF")]
    assert fff[57, 1] > neutral[57, 1] + 0.1  # lower lip up toward the upper teeth
    assert fff[57, 2] < neutral[57, 2] - 0.2  # and tucked back
    assert abs(fff[8, 1] - neutral[8, 1]) < 0.3  # with the jaw nearly closed


def test_shipped_demo_rig_matches_a_rebuild_from_the_recipes(demo):
    spec = importlib.util.spec_from_file_location("build_demo_rig", REPO / "examples" / "build_demo_rig.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    rebuilt = module.build_rig(ICT)
    np.testing.assert_array_equal(rebuilt.neutral, demo.neutral)
    np.testing.assert_array_equal(rebuilt.faces, demo.faces)
    np.testing.assert_array_equal(rebuilt.landmark_ids, demo.landmark_ids)
    np.testing.assert_allclose(rebuilt.deltas, demo.deltas, atol=4e-3)  # float16 storage


def test_a_failed_rig_save_keeps_the_previous_file_whole(tmp_path, monkeypatch):
    import visemeflow.rig.io as rig_io

    path = save_rig_npz(tiny_rig(), tmp_path / "tiny.npz")
    before = path.read_bytes()

    def half_then_fail(target, arrays):
        Path(target).write_bytes(before[:100])
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(rig_io, "_write_npz", half_then_fail)
    with pytest.raises(OSError, match="No space left"):
        save_rig_npz(tiny_rig(name="other"), path)
    assert path.read_bytes() == before and load_rig(path).name == "tiny"
    assert [p.name for p in tmp_path.iterdir()] == ["tiny.npz"]  # no temporary file left


def test_obj_reader_names_the_bad_line_and_reads_tabs_crlf_and_mixed_vertex_widths(tmp_path):
    path = tmp_path / "m.obj"
    path.write_bytes(b"v 0 0 0\r\nv 1\t0 0 1.0\r\nv 0 1 0 0.5 0.5 0.5\r\nvt 0 0\r\nf 1/1/1 2//2  3\r\n")
    mesh = read_obj(path)
    np.testing.assert_array_equal(mesh.vertices, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    assert mesh.faces.tolist() == [[0, 1, 2]] and mesh.colors is None
    for text, said in (("v 0 0 0\nv 1 0 0\nv 0 1 zero\nf 1 2 3\n", r"malformed OBJ vertex line: '0 1 zero'"),
                       ("v 0 0 0\nv 1 0 0\nv 0 1\nf 1 2 3\n", r"malformed OBJ vertex line: '0 1'"),
                       ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3.5\n", r"malformed OBJ face line: '1 2 3.5'"),
                       ("v 0 0 0\nv 1 0 0\nf 1 2\n", r"OBJ face with 2 vertices \(need at least 3\)")):
        path.write_text(text)
        with pytest.raises(RigError, match=r"m\.obj: " + said):
            read_obj(path)


def test_an_obj_gz_that_unpacks_far_beyond_its_size_is_refused_before_it_is_unpacked(tmp_path, monkeypatch):
    """Two 400 KB .obj.gz of a character unpacked to 400 MB each (47 s, 845 MiB); OBJ text packs 3-5 times."""
    import visemeflow.rig.io as rig_io

    bomb = tmp_path / "neutral.obj.gz"
    bomb.write_bytes(gzip.compress(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n" + b"#" * (40 << 20), 9))
    assert bomb.stat().st_size < 100_000
    with pytest.raises(RigError, match=r"neutral\.obj\.gz: unpacks to more than 16777216 bytes of OBJ \(from \d+ "
                                       r"packed\): more than 100 times its size"):
        read_obj(bomb)
    fine = tmp_path / "fine.obj.gz"          # packs 1000 times but unpacks to less than 16 MiB: read
    fine.write_bytes(gzip.compress(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n" + b"#" * (4 << 20), 9))
    assert read_obj(fine).faces.tolist() == [[0, 1, 2]]
    monkeypatch.setattr(rig_io, "MAX_OBJ_BYTES", 1000)
    plain = tmp_path / "big.obj"
    plain.write_bytes(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n" + b"#" * 1000)
    with pytest.raises(RigError, match=r"big\.obj: 1032 bytes of OBJ, more than the 1000 an OBJ may have"):
        read_obj(plain)
    with pytest.raises(RigError, match=r"fine\.obj\.gz: unpacks to more than 1000 bytes of OBJ \(from \d+ packed\): "
                                       r"more than the 1000 an OBJ may have"):
        read_obj(fine)
