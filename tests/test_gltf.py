"""glTF 2.0 characters (visemeflow/animation/gltf.py): exact round trips, the reader's inputs and errors, and the
GLBs we write checked by real clients:

- the Khronos glTF validator (npm `gltf-validator`, through tools/js/validate_gltf.mjs): no error, no warning, on
  GLBs with sparse and with dense morph targets, with vertex colours;
- three.js (npm `three`) in headless chromium: GLTFLoader reads every target name (sparse targets substituted to
  the exact deltas), an AnimationMixer plays the clip, and the morph target influences at frame times and between
  frames are the linear interpolation of the weights we wrote; the material is our PBR one, and COLOR_0 is loaded
  as a colour attribute (vertexColors on) equal to three.js's own sRGB -> linear conversion of our colours.

The JS packages are pinned in tools/js/package-lock.json and installed by `make js-deps` (a prerequisite of
`make test`); without them, node or chromium the tests fail with the command that installs them, never skip.
"""

import json
import math
from pathlib import Path

import numpy as np
import pygltflib as gl
import pytest
from browser import Browser, serve_folder
from factories import NODE_MODULES, glb_arrays, node_or_fail, validate

from visemeflow.rig.character import Character, CharacterError, character_from_rig, make_character
from visemeflow.animation.load import load_character
from visemeflow.animation.gltf import read_character_glb, vertex_normals, write_glb
from visemeflow.rig import load_demo_rig

# ---- inputs ---------------------------------------------------------------------------------------------------
def small_character(n_shapes: int = 3, seed: int = 0, colors: bool = False) -> Character:
    """A 5 x 4 grid (20 vertices, 24 triangles) with `n_shapes` random shapes, names with spaces and non-ASCII;
    with `colors`, random vertex colours that include 0, 1 and both sides of the sRGB curve's linear toe."""
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.arange(5, dtype=np.float32), np.arange(4, dtype=np.float32))
    neutral = np.stack([xs.ravel() * 0.5, ys.ravel() * 0.5, rng.normal(0, 0.05, 20)], axis=1)
    quads = [(r * 5 + c, r * 5 + c + 1, (r + 1) * 5 + c + 1, (r + 1) * 5 + c) for r in range(3) for c in range(4)]
    faces = [tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))]
    names = ["jawOpen", "mouth Smile_L", "Ö-pucker", "MBP", "lèvres", "口"][:n_shapes]
    deltas = rng.normal(0, 0.1, (n_shapes, 20, 3)).astype(np.float32)
    deltas[:, :5] = 0.0                                  # the top row never moves
    deltas[0] = np.abs(deltas[0])                        # the first shape's minimum is the top row's zeros
    rgb = None
    if colors:
        rgb = rng.random((20, 3)).astype(np.float32)
        rgb[:3] = [[0.0, 0.0, 1.0], [0.04045, 0.04, 0.05], [1.0, 0.5, 0.002]]
    return make_character("test face [v1.2]", neutral, faces, names, deltas, vertex_colors=rgb)


def srgb_to_linear_here(c: np.ndarray) -> np.ndarray:
    """The sRGB transfer function inverted (IEC 61966-2-1), written here rather than imported."""
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def random_weights(n_frames: int, n_shapes: int, seed: int = 1) -> np.ndarray:
    """Weights that change a lot from frame to frame, so that a wrong order or interpolation shows."""
    return np.random.default_rng(seed).random((n_frames, n_shapes)).astype(np.float32)


@pytest.fixture(scope="module")
def demo() -> Character:
    return character_from_rig(load_demo_rig())


def expected_weights(times: np.ndarray, weights: np.ndarray, t: float) -> np.ndarray:
    """glTF LINEAR interpolation of the keyframes (`times` as stored: float32) at time t, clamped at the ends."""
    times = times.astype(np.float64)
    if t <= times[0]:
        return weights[0].astype(np.float64)
    if t >= times[-1]:
        return weights[-1].astype(np.float64)
    k = int(np.searchsorted(times, t, side="right")) - 1
    alpha = (t - times[k]) / (times[k + 1] - times[k])
    return weights[k] * (1.0 - alpha) + weights[k + 1] * alpha


class Doc:
    """A glTF document built by hand through pygltflib, for reader inputs our writer never produces."""

    def __init__(self) -> None:
        self.g = gl.GLTF2()
        self.blob = bytearray()

    def view(self, data: bytes, stride: int | None = None, target: int | None = None) -> int:
        self.blob += b"\0" * (-len(self.blob) % 4)
        self.g.bufferViews.append(gl.BufferView(buffer=0, byteOffset=len(self.blob), byteLength=len(data),
                                                byteStride=stride, target=target))
        self.blob += data
        return len(self.g.bufferViews) - 1

    def accessor(self, array=None, kind: str = gl.VEC3, *, view: int | None = None, offset: int = 0,
                 count: int | None = None, component: int | None = None, normalized: bool = False,
                 sparse: gl.Sparse | None = None) -> int:
        if array is not None:
            array = np.ascontiguousarray(array)
            component = {np.dtype("float32"): gl.FLOAT, np.dtype("int16"): gl.SHORT,
                         np.dtype("uint8"): gl.UNSIGNED_BYTE, np.dtype("uint16"): gl.UNSIGNED_SHORT,
                         np.dtype("uint32"): gl.UNSIGNED_INT}[array.dtype]
            view = self.view(array.tobytes())
            count = len(array)
        self.g.accessors.append(gl.Accessor(bufferView=view, byteOffset=offset, componentType=component,
                                            normalized=normalized, count=count, type=kind, sparse=sparse))
        return len(self.g.accessors) - 1

    def mesh(self, primitives: list[gl.Primitive], names: list[str] | None = None, name: str | None = None) -> int:
        extras = {"targetNames": names} if names is not None else {}
        self.g.meshes.append(gl.Mesh(name=name, primitives=primitives, extras=extras))
        return len(self.g.meshes) - 1

    def save(self, path: Path, nodes: list[int] | None = None) -> Path:
        """With `nodes` (mesh indices): one node per mesh, all in scene 0."""
        if nodes is not None:
            self.g.nodes = [gl.Node(mesh=m) for m in nodes]
            self.g.scenes = [gl.Scene(nodes=list(range(len(nodes))))]
            self.g.scene = 0
        self.blob += b"\0" * (-len(self.blob) % 4)
        self.g.buffers = [gl.Buffer(byteLength=len(self.blob))]
        self.g.set_binary_blob(bytes(self.blob))
        self.g.save_binary(str(path))
        return path


def assert_same_character(a: Character, b: Character) -> None:
    """Same names, bit-equal arrays; vertex colours equal to float32 rounding (they are stored linear, read back as
    sRGB) or both absent."""
    assert a.shape_names == b.shape_names
    for field in ("neutral", "faces", "deltas"):
        x, y = getattr(a, field), getattr(b, field)
        assert x.dtype == y.dtype and x.shape == y.shape, field
        assert np.array_equal(x, y), field
    assert (a.vertex_colors is None) == (b.vertex_colors is None)
    if a.vertex_colors is not None:
        assert a.vertex_colors.dtype == b.vertex_colors.dtype == np.float32
        np.testing.assert_allclose(a.vertex_colors, b.vertex_colors, rtol=0, atol=1e-6)


# ---- writing and reading back -----------------------------------------------------------------------------------
def test_small_character_round_trips_exactly_with_its_animation(tmp_path):
    c = small_character()
    w = random_weights(7, c.n_shapes)
    path = write_glb(tmp_path / "face.glb", c, w, 25.0)
    assert path == tmp_path / "face.glb" and [p.name for p in tmp_path.iterdir()] == ["face.glb"]
    back = read_character_glb(path)
    assert_same_character(back, c)
    assert back.name == c.name and back.source == str(path)

    g, read = glb_arrays(path)
    assert g.asset.version == "2.0" and g.scene == 0 and g.scenes[0].nodes == [0] and g.nodes[0].mesh == 0
    mesh = g.meshes[0]
    (prim,) = mesh.primitives
    assert mesh.extras["targetNames"] == prim.extras["targetNames"] == list(c.shape_names)
    assert mesh.weights == [0.0] * c.n_shapes and prim.mode == gl.TRIANGLES
    assert g.accessors[prim.indices].componentType == gl.UNSIGNED_SHORT        # 20 vertices: uint16 suffices
    position = g.accessors[prim.attributes.POSITION]
    assert position.min == c.neutral.min(axis=0).tolist() and position.max == c.neutral.max(axis=0).tolist()
    normals = read(prim.attributes.NORMAL)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    assert np.array_equal(normals, vertex_normals(c.neutral, c.faces))
    for s, target in enumerate(prim.targets):
        acc = g.accessors[target["POSITION"]]
        assert acc.min == c.deltas[s].min(axis=0).tolist() and acc.max == c.deltas[s].max(axis=0).tolist()
        assert set(target) == {"POSITION"}
        # the top row never moves: 15 of 20 vertices in 15 x (1 + 12) bytes beat 20 x 12 dense, so sparse
        assert acc.bufferView is None and acc.sparse.count == 15 and acc.componentType == gl.FLOAT
        assert acc.sparse.indices.componentType == gl.UNSIGNED_BYTE
        assert read(target["POSITION"]).tolist() == c.deltas[s].tolist()
        for view in (acc.sparse.indices.bufferView, acc.sparse.values.bufferView):
            assert g.bufferViews[view].target is None      # sparse views may not target ARRAY_BUFFER
    assert prim.attributes.COLOR_0 is None                   # no colours, none written
    (material,) = g.materials
    assert prim.material == 0 and material.pbrMetallicRoughness.metallicFactor == 0.0
    assert material.pbrMetallicRoughness.roughnessFactor == 0.6
    assert material.pbrMetallicRoughness.baseColorFactor == [1.0, 1.0, 1.0, 1.0]
    views = g.bufferViews
    assert views[g.accessors[prim.attributes.POSITION].bufferView].target == gl.ARRAY_BUFFER
    assert views[g.accessors[prim.indices].bufferView].target == gl.ELEMENT_ARRAY_BUFFER
    assert all(v.byteOffset % 4 == 0 for v in views)

    (animation,) = g.animations
    assert animation.name == c.name
    (channel,) = animation.channels
    assert channel.target.node == 0 and channel.target.path == "weights"
    sampler = animation.samplers[channel.sampler]
    assert sampler.interpolation == "LINEAR"
    times, values = read(sampler.input)[:, 0], read(sampler.output)[:, 0]
    assert np.array_equal(times, (np.arange(7) / 25.0).astype(np.float32))
    assert g.accessors[sampler.input].min == [0.0] and g.accessors[sampler.input].max == [float(times[-1])]
    assert np.array_equal(values.reshape(7, c.n_shapes), w)                  # frame by frame, shapes in order
    for view_index in (g.accessors[sampler.input].bufferView, g.accessors[sampler.output].bufferView):
        assert views[view_index].target is None


def test_demo_rig_round_trips_exactly(tmp_path, demo):
    """A minute of animation on the demo rig; its write time is bench/animation.py's (section 1, glb)."""
    w = random_weights(1800, demo.n_shapes)                      # one minute at 30 fps
    path = write_glb(tmp_path / "demo.glb", demo, w, 30.0, name="minute")
    size = path.stat().st_size
    dense = write_glb(tmp_path / "dense.glb", demo, w, 30.0, name="minute", sparse=False)
    print(f"\ndemo rig, 1 min at 30 fps: {size / 1e6:.3f} MB (targets dense: {dense.stat().st_size / 1e6:.3f} MB)")
    back = read_character_glb(path)
    # glTF's unit is the metre: the demo rig's centimetres are written scaled, so a tool shows a head 18 cm wide
    # (it was 18 m), and reading the file back gives the same character in metres, bit for bit
    assert_same_character(back, demo.in_metres())
    assert back.name == demo.name and back.mm_per_unit == 1000.0 and demo.mm_per_unit == 10.0
    width, height, _ = np.ptp(back.neutral, axis=0)
    assert 0.15 < width < 0.25 and 0.2 < height < 0.4, (width, height)
    assert_same_character(read_character_glb(dense), demo.in_metres())
    g, read = glb_arrays(path)
    assert g.animations[0].name == "minute"
    assert g.accessors[g.meshes[0].primitives[0].indices].componentType == gl.UNSIGNED_SHORT   # 21,984 vertices
    # every demo viseme moves about 72% of the vertices: sparse (uint16 id + 3 float32 = 14 bytes a vertex) is
    # smaller than dense (12 bytes a vertex) below 6/7 of them
    moved = (demo.deltas != 0).any(axis=2).sum(axis=1)
    assert ((moved > 0.6 * demo.n_vertices) & (moved < demo.n_vertices * 6 / 7)).all(), moved
    assert all(g.accessors[t["POSITION"]].sparse.count == n for t, n in zip(g.meshes[0].primitives[0].targets, moved))
    pad4 = lambda n: -(-n // 4) * 4                                            # noqa: E731
    sparse_bytes = sum(pad4(2 * int(n)) + 12 * int(n) for n in moved)
    # positions, normals, colours (float32 VEC3), uint16 indices, the targets, 1800 x (1 + 16) float32 of animation
    fixed = 4 * demo.n_vertices * 3 * 3 + pad4(2 * demo.faces.size) + 4 * 1800 * 17
    assert fixed + sparse_bytes <= size < fixed + sparse_bytes + 16_000
    dense_bytes = 12 * demo.n_vertices * demo.n_shapes
    assert fixed + dense_bytes <= dense.stat().st_size < fixed + dense_bytes + 16_000
    assert load_character(path).shape_names == demo.shape_names                 # the generic loader reads it too


def test_vertex_colours_are_written_linear_and_read_back(tmp_path):
    c = small_character(colors=True)
    path = write_glb(tmp_path / "coloured.glb", c, random_weights(3, c.n_shapes), 30.0)
    g, read = glb_arrays(path)
    prim = g.meshes[0].primitives[0]
    acc = g.accessors[prim.attributes.COLOR_0]
    assert (acc.type, acc.componentType, acc.count) == ("VEC3", gl.FLOAT, 20)
    assert g.bufferViews[acc.bufferView].target == gl.ARRAY_BUFFER
    stored = read(prim.attributes.COLOR_0)
    np.testing.assert_allclose(stored, srgb_to_linear_here(c.vertex_colors), rtol=0, atol=1e-7)
    assert stored.min() >= 0.0 and stored.max() <= 1.0 and stored[0].tolist() == [0.0, 0.0, 1.0]
    back = read_character_glb(path)
    assert_same_character(back, c)
    assert_same_character(load_character(path), c)
    # a COLOR_0 of normalized unsigned shorts with alpha, as other tools write it, is read too
    d = Doc()
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    rgba = np.array([[0, 65535, 32768, 65535], [65535, 0, 0, 0], [1000, 2000, 3000, 4000]], np.uint16)
    d.mesh([gl.Primitive(attributes=gl.Attributes(POSITION=d.accessor(tri),
                                                  COLOR_0=d.accessor(rgba, gl.VEC4, normalized=True)),
                         targets=[{"POSITION": d.accessor(tri)}])], names=["up"])
    quantized = read_character_glb(d.save(tmp_path / "rgba16.glb", nodes=[0]))
    linear = rgba[:, :3] / 65535.0
    expected = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)
    np.testing.assert_allclose(quantized.vertex_colors, expected, rtol=0, atol=1e-6)


def test_large_meshes_get_uint32_indices(tmp_path):
    n = 70_000                                                  # over 65,535: uint16 cannot index it
    neutral = np.zeros((n, 3), np.float32)
    neutral[:, 0] = np.arange(n)
    neutral[1::2, 1] = 1.0
    faces = np.stack([np.arange(n - 2), np.arange(1, n - 1), np.arange(2, n)], axis=1)
    deltas = np.zeros((1, n, 3), np.float32)
    deltas[0, -1] = (0.0, 0.0, 2.5)
    c = make_character("strip", neutral, faces, ["lift"], deltas)
    path = write_glb(tmp_path / "strip.glb", c, np.array([[0.0], [1.0]], np.float32), 30.0)
    g, _ = glb_arrays(path)
    assert g.accessors[g.meshes[0].primitives[0].indices].componentType == gl.UNSIGNED_INT
    assert_same_character(read_character_glb(path), c)


def test_gltf_json_with_external_or_data_uri_buffers_reads_the_same(tmp_path):
    c = small_character()
    glb = write_glb(tmp_path / "face.glb", c, random_weights(3, c.n_shapes), 30.0)
    g = gl.GLTF2.load(str(glb))
    g.save_json(str(tmp_path / "external.gltf"))               # the binary chunk becomes external.bin beside it
    assert json.loads((tmp_path / "external.gltf").read_text())["buffers"][0]["uri"] == "external.bin"
    assert_same_character(load_character(tmp_path / "external.gltf"), c)
    g = gl.GLTF2.load(str(glb))
    g.convert_buffers(gl.BufferFormat.DATAURI)
    g.save_json(str(tmp_path / "embedded.gltf"))
    assert_same_character(load_character(tmp_path / "embedded.gltf"), c)
    (tmp_path / "external.bin").unlink()
    with pytest.raises(CharacterError, match=r"external\.gltf: buffer 0 \(external\.bin\) is missing"):
        read_character_glb(tmp_path / "external.gltf")


def test_write_rejects_bad_weights_and_keeps_the_previous_file(tmp_path):
    c = small_character()
    path = write_glb(tmp_path / "face.glb", c, random_weights(4, c.n_shapes), 30.0)
    before = path.read_bytes()
    bad = {"frames x wrong shapes": (np.zeros((4, c.n_shapes + 1), np.float32), 30.0),
           "no frames": (np.zeros((0, c.n_shapes), np.float32), 30.0),
           "one dimension": (np.zeros(c.n_shapes, np.float32), 30.0),
           "above 1": (np.full((4, c.n_shapes), 1.5, np.float32), 30.0),
           "negative": (np.full((4, c.n_shapes), -0.25, np.float32), 30.0),
           "NaN": (np.full((4, c.n_shapes), np.nan, np.float32), 30.0),
           "zero fps": (np.zeros((4, c.n_shapes), np.float32), 0.0),
           "NaN fps": (np.zeros((4, c.n_shapes), np.float32), math.nan)}
    for label, (weights, fps) in bad.items():
        with pytest.raises(ValueError):
            write_glb(path, c, weights, fps)
        assert path.read_bytes() == before, label
    assert [p.name for p in tmp_path.iterdir()] == ["face.glb"]
    with pytest.raises(ValueError, match="no triangles"):
        write_glb(path, make_character("points", c.neutral, np.zeros((0, 3), np.int32), c.shape_names, c.deltas),
                  np.zeros((2, c.n_shapes), np.float32), 30.0)
    one = write_glb(tmp_path / "one.glb", c, np.full((1, c.n_shapes), 0.5, np.float32), 30.0)
    g, read = glb_arrays(one)
    assert read(g.animations[0].samplers[0].input)[:, 0].tolist() == [0.0]


# ---- what the reader takes --------------------------------------------------------------------------------------
def test_reader_joins_primitives_shares_vertices_and_reads_sparse_strided_and_quantized_data(tmp_path):
    """Three primitives: a strided one (positions interleaved with normals) whose second target is sparse, a
    non-indexed one whose targets are normalized int16, and one that reuses the first's vertices."""
    d = Doc()
    p0 = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    interleaved = np.concatenate([p0, np.tile([[0, 0, 1]], (4, 1)).astype(np.float32)], axis=1)
    stride_view = d.view(interleaved.tobytes(), stride=24, target=gl.ARRAY_BUFFER)
    pos0 = d.accessor(view=stride_view, count=4, component=gl.FLOAT)
    nrm0 = d.accessor(view=stride_view, offset=12, count=4, component=gl.FLOAT)
    t00 = np.arange(12, dtype=np.float32).reshape(4, 3) / 10
    sparse = gl.Sparse(count=2,
                       indices=gl.AccessorSparseIndices(bufferView=d.view(np.array([1, 3], np.uint16).tobytes()),
                                                        componentType=gl.UNSIGNED_SHORT),
                       values=gl.AccessorSparseValues(bufferView=d.view(np.array([[0, 0, 0.5], [0, -0.5, 0]],
                                                                                 np.float32).tobytes())))
    t01 = d.accessor(count=4, component=gl.FLOAT, sparse=sparse)                 # no buffer view: zeros + sparse
    idx0 = d.accessor(np.array([0, 1, 2, 0, 2, 3], np.uint8), gl.SCALAR)
    p1 = np.array([[5, 0, 0], [6, 0, 0], [5, 1, 0]], np.float32)
    q = np.array([[32767, 0, -32767], [-32768, 16384, 0], [0, 0, 1]], np.int16)
    q2 = q[::-1].copy()
    prims = [
        gl.Primitive(attributes=gl.Attributes(POSITION=pos0, NORMAL=nrm0), indices=idx0,
                     targets=[{"POSITION": d.accessor(t00)}, {"POSITION": t01}]),
        gl.Primitive(attributes=gl.Attributes(POSITION=d.accessor(p1)),
                     targets=[{"POSITION": d.accessor(q, normalized=True)},
                              {"POSITION": d.accessor(q2, normalized=True)}]),
    ]
    reversed_ids = d.accessor(np.array([3, 2, 1], np.uint32), gl.SCALAR)
    prims.append(gl.Primitive(attributes=gl.Attributes(POSITION=pos0), indices=reversed_ids, targets=prims[0].targets))
    d.mesh(prims, names=["open", "wide"], name="joined")
    c = read_character_glb(d.save(tmp_path / "joined.glb", nodes=[0]))
    assert c.name == "joined" and c.shape_names == ("open", "wide")
    assert np.array_equal(c.neutral, np.concatenate([p0, p1]))                 # the third primitive adds no vertex
    assert c.faces.tolist() == [[0, 1, 2], [0, 2, 3], [4, 5, 6], [3, 2, 1]]
    q_float = np.maximum(q / 32767.0, -1.0).astype(np.float32)
    sparse_dense = np.zeros((4, 3), np.float32)
    sparse_dense[1], sparse_dense[3] = (0, 0, 0.5), (0, -0.5, 0)
    assert np.array_equal(c.deltas[0], np.concatenate([t00, q_float]))
    assert np.array_equal(c.deltas[1], np.concatenate([sparse_dense, np.maximum(q2 / 32767.0, -1).astype(np.float32)]))


def test_reader_takes_names_from_the_primitive_and_the_mesh_asked_for(tmp_path):
    c = small_character()
    path = write_glb(tmp_path / "face.glb", c, random_weights(2, c.n_shapes), 30.0)
    g = gl.GLTF2.load(str(path))
    g.meshes[0].extras = {}                                      # names only on the primitive
    g.save_binary(str(tmp_path / "prim-names.glb"))
    assert read_character_glb(tmp_path / "prim-names.glb", name="given").shape_names == c.shape_names

    d = Doc()
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    plain = d.mesh([gl.Primitive(attributes=gl.Attributes(POSITION=d.accessor(tri)))], name="no targets")
    first = d.mesh([gl.Primitive(attributes=gl.Attributes(POSITION=d.accessor(tri)),
                                 targets=[{"POSITION": d.accessor(tri)}])], names=["first"], name="first")
    second = d.mesh([gl.Primitive(attributes=gl.Attributes(POSITION=d.accessor(tri)),
                                  targets=[{"POSITION": d.accessor(tri * 2)}])], names=["second"], name="second")
    d.save(tmp_path / "loose.glb")                               # no node: every mesh is still a candidate
    # two meshes with targets of no known convention: which is the face is not guessed (tests/test_multimesh.py)
    with pytest.raises(CharacterError, match=r"no targets \(3 v, no targets\); first \(3 v, 1 targets: first\)"):
        read_character_glb(tmp_path / "loose.glb")
    assert read_character_glb(tmp_path / "loose.glb", meshes=["first"]).shape_names == ("first",)
    d.save(tmp_path / "scene.glb", nodes=[plain, second, first])
    c2 = read_character_glb(tmp_path / "scene.glb", meshes=["second"])
    assert c2.name == "second" and c2.shape_names == ("second",) and np.array_equal(c2.deltas[0], tri * 2)


def _glb_with(tmp_path: Path, name: str, change, c: Character | None = None) -> Path:
    """Our GLB of `c` (the small character), changed by `change(gltf, blob: bytearray)` and saved as `name`."""
    c = c or small_character()
    g = gl.GLTF2.load(str(write_glb(tmp_path / "good.glb", c, random_weights(3, c.n_shapes), 30.0)))
    for accessor in g.accessors:      # pygltflib reads a missing byteOffset as 0; a sparse one may not have it
        if accessor.bufferView is None:
            accessor.byteOffset = None
    blob = bytearray(g.binary_blob())
    change(g, blob)
    g.set_binary_blob(bytes(blob))
    g.save_binary(str(tmp_path / name))
    return tmp_path / name


def _nan_vertex(g: gl.GLTF2, blob: bytearray) -> None:
    view = g.bufferViews[g.accessors[g.meshes[0].primitives[0].attributes.POSITION].bufferView]
    blob[view.byteOffset + 12: view.byteOffset + 16] = np.float32(np.nan).tobytes()      # vertex 1, x


def _set_names(names):
    def change(g: gl.GLTF2, blob: bytearray) -> None:
        g.meshes[0].extras = {"targetNames": names} if names is not None else {}
        g.meshes[0].primitives[0].extras = {}
    return change


def test_bad_files_raise_character_errors_that_name_the_file(tmp_path):
    good = write_glb(tmp_path / "good.glb", small_character(), random_weights(3, 3), 30.0)
    (tmp_path / "text.glb").write_text("hello, not a model\n")
    (tmp_path / "empty.glb").write_bytes(b"")
    (tmp_path / "page.glb").write_text("\n<!DOCTYPE html>\n<html><head><title>avatar.glb at main</title>")
    (tmp_path / "truncated.glb").write_bytes(good.read_bytes()[:400])
    (tmp_path / "no-asset.gltf").write_text('{"meshes": []}')
    (tmp_path / "version1.gltf").write_text('{"asset": {"version": "1.0"}}')
    no_mesh = gl.GLTF2(scenes=[gl.Scene(nodes=[])], scene=0)
    no_mesh.save_binary(str(tmp_path / "no-mesh.glb"))
    d = Doc()
    d.mesh([gl.Primitive(attributes=gl.Attributes(POSITION=d.accessor(np.eye(3, dtype=np.float32))))])
    d.save(tmp_path / "no-targets.glb", nodes=[0])
    cases = {
        "text.glb": "not a glTF 2.0 / GLB file",
        "empty.glb": "not a glTF 2.0 / GLB file",
        "page.glb": "not a glTF 2.0 / GLB file (it is an HTML page: a web page saved instead of the file?",
        "truncated.glb": "truncated",
        "no-asset.gltf": "not a glTF 2.0 / GLB file",
        "version1.gltf": "only glTF 2.0",
        "no-mesh.glb": "no mesh",
        "no-targets.glb": "no mesh has morph targets",
        _glb_with(tmp_path, "no-names.glb", _set_names(None)).name: "no names",
        _glb_with(tmp_path, "short-names.glb", _set_names(["a", "b"])).name: "must be 3 strings",
        _glb_with(tmp_path, "number-names.glb", _set_names(["a", "b", 3])).name: "must be 3 strings",
        _glb_with(tmp_path, "duplicate-names.glb", _set_names(["a", "b", "a"])).name: "used twice",
        _glb_with(tmp_path, "empty-name.glb", _set_names(["a", " ", "c"])).name: "has no name",
        _glb_with(tmp_path, "nan.glb", _nan_vertex).name: "NaN",
        _glb_with(tmp_path, "lines.glb", lambda g, b: setattr(g.meshes[0].primitives[0], "mode", gl.LINES)).name:
            "draws LINES; only triangles (TRIANGLES, TRIANGLE_STRIP, TRIANGLE_FAN) are read",
        _glb_with(tmp_path, "bad-index.glb",
                  lambda g, b: setattr(g.meshes[0].primitives[0], "indices", 99)).name: "accessor 99 does not exist",
    }
    for name, expected in cases.items():
        path = tmp_path / name
        with pytest.raises(CharacterError) as info:
            read_character_glb(path)
        message = str(info.value)
        assert str(path) in message and expected in message, (name, message)
    with pytest.raises(CharacterError, match="gone.glb"):
        read_character_glb(tmp_path / "gone.glb")


# ---- real clients -----------------------------------------------------------------------------------------------
def test_the_validator_finds_no_error_or_warning_in_what_we_write(tmp_path, demo):
    small = small_character(n_shapes=6, colors=True)
    curves = (0.5 + 0.5 * np.sin(2 * np.pi * (np.arange(120)[:, None] / 30.0) * (0.5 + np.arange(16) / 8)))
    files = {
        write_glb(tmp_path / "small.glb", small, random_weights(50, 6), 24.0): small,
        write_glb(tmp_path / "single-frame.glb", small, np.full((1, 6), 0.25, np.float32), 30.0): small,
        # the demo rig (vertex colours, sparse targets) with 4 s of smooth viseme curves at 30 fps, and dense
        write_glb(tmp_path / "demo.glb", demo, curves.astype(np.float32), 30.0): demo,
        write_glb(tmp_path / "demo-dense.glb", demo, curves.astype(np.float32), 30.0, sparse=False): demo,
    }
    # what the validator is shown: sparse targets (uint8 ids for 20 vertices, uint16 for the demo), and dense ones
    sparse_ids = {}
    for path in files:
        g, _ = glb_arrays(path)
        targets = [g.accessors[t["POSITION"]] for t in g.meshes[0].primitives[0].targets]
        sparse_ids[path.name] = {a.sparse.indices.componentType if a.sparse else None for a in targets}
        assert g.meshes[0].primitives[0].attributes.COLOR_0 is not None and len(g.materials) == 1
    assert sparse_ids == {"small.glb": {gl.UNSIGNED_BYTE}, "single-frame.glb": {gl.UNSIGNED_BYTE},
                          "demo.glb": {gl.UNSIGNED_SHORT}, "demo-dense.glb": {None}}
    for path, character in files.items():
        report = validate(path)
        issues = report["issues"]
        assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]
        info = report["info"]
        assert info["hasMorphTargets"] and info["animationCount"] == 1 and info["hasDefaultScene"]
        assert info["totalVertexCount"] == character.n_vertices
        assert info["totalTriangleCount"] == len(character.faces)


def test_the_validator_check_can_fail(tmp_path):
    """A wrong accessor.min, frame times out of order, a wrong max on a sparse target, sparse ids out of order and a
    colour above 1 are errors the check above would see."""
    def corrupt(g: gl.GLTF2, blob: bytearray) -> None:
        prim = g.meshes[0].primitives[0]
        g.accessors[prim.attributes.POSITION].min[0] -= 1.0
        times = g.bufferViews[g.accessors[g.animations[0].samplers[0].input].bufferView]
        blob[times.byteOffset: times.byteOffset + 8] = np.array([0.5, 0.25], np.float32).tobytes()
        first, second = (g.accessors[t["POSITION"]] for t in prim.targets[:2])
        first.max[1] += 0.5
        ids = g.bufferViews[second.sparse.indices.bufferView]
        blob[ids.byteOffset: ids.byteOffset + 2] = blob[ids.byteOffset: ids.byteOffset + 2][::-1]
        colors = g.bufferViews[g.accessors[prim.attributes.COLOR_0].bufferView]
        blob[colors.byteOffset: colors.byteOffset + 4] = np.float32(1.5).tobytes()

    report = validate(_glb_with(tmp_path, "bad.glb", corrupt, small_character(colors=True)))
    codes = {m["code"] for m in report["issues"]["messages"] if m["severity"] == 0}
    assert "ACCESSOR_MIN_MISMATCH" in codes and "ACCESSOR_MAX_MISMATCH" in codes
    assert "ACCESSOR_SPARSE_INDICES_NON_INCREASING" in codes and "ACCESSOR_NON_CLAMPED" in codes
    assert any("ANIMATION_INPUT" in code for code in codes), codes
    pointers = {m["pointer"] for m in report["issues"]["messages"] if m["code"] == "ACCESSOR_MAX_MISMATCH"}
    first_target = glb_arrays(tmp_path / "bad.glb")[0].meshes[0].primitives[0].targets[0]["POSITION"]
    assert f"/accessors/{first_target}/max/1" in pointers, pointers


PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>glb check</title><link rel="icon" href="data:,">
<script type="importmap">
{"imports": {"three": "/node_modules/three/build/three.module.js",
             "three/addons/": "/node_modules/three/examples/jsm/"}}
</script>
<script type="module">
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';

// Load `url`, play its first clip with an AnimationMixer and read the morph target influences at `times`; the
// vertex data, colours and material as three.js holds them, and `srgb` (colours) converted by three.js's own
// colour management into its linear working space.
window.playGlb = async (url, times, vertexIds, srgb) => {
  const gltf = await new GLTFLoader().loadAsync(url);
  const meshes = [];
  gltf.scene.traverse((o) => { if (o.isMesh) meshes.push(o); });
  const mesh = meshes[0];
  const clip = gltf.animations[0];
  const mixer = new THREE.AnimationMixer(gltf.scene);
  const action = mixer.clipAction(clip);
  action.setLoop(THREE.LoopOnce, 1);
  action.clampWhenFinished = true;          // the last frame holds instead of wrapping to the first
  const influences = [];
  for (const t of times) {
    action.reset().play();
    mixer.setTime(t);                          // advances the mixer from 0 by t seconds
    influences.push(Array.from(mesh.morphTargetInfluences));
  }
  const geometry = mesh.geometry;
  const position = geometry.attributes.position;
  const xyz = (a) => vertexIds.map((i) => [a.getX(i), a.getY(i), a.getZ(i)]);
  const color = geometry.attributes.color;
  const material = mesh.material;
  return {
    meshes: meshes.length, dictionary: mesh.morphTargetDictionary, clips: gltf.animations.map((c) => c.name),
    duration: clip.duration, tracks: clip.tracks.map((t) => [t.name, t.times.length, t.values.length]),
    vertexCount: position.count, triangles: geometry.index.count / 3, relative: geometry.morphTargetsRelative,
    neutral: xyz(position), deltas: geometry.morphAttributes.position.map(xyz), influences,
    colors: color ? xyz(color) : null, colorItemSize: color ? color.itemSize : null,
    material: { type: material.type, vertexColors: material.vertexColors, metalness: material.metalness,
                roughness: material.roughness, color: material.color.toArray() },
    workingColorSpace: THREE.ColorManagement.workingColorSpace,
    threeLinear: srgb ? srgb.map(([r, g, b]) => new THREE.Color().setRGB(r, g, b, THREE.SRGBColorSpace).toArray())
                      : null,
  };
};
window.pageReady = true;
</script></head><body></body></html>
"""


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """(root folder, base address): a page, the node_modules and the GLBs we put in root, served on 127.0.0.1."""
    node_or_fail()
    root = tmp_path_factory.mktemp("served")
    with serve_folder(root, PAGE, NODE_MODULES) as address:
        yield root, address


def play_in_three(browser: Browser, served, path: Path, times: list[float], vertex_ids: list[int],
                  srgb: list | None = None) -> dict:
    root, base = served
    (root / path.name).write_bytes(path.read_bytes())
    state = browser.load(f"{base}/index.html")
    assert state["errors"] == [], state
    assert all(u.startswith(base) for u in state["requests"]), state["requests"]
    call = (f"window.playGlb({json.dumps('/' + path.name)}, {json.dumps(times)}, {json.dumps(vertex_ids)}, "
            f"{json.dumps(srgb)})")
    result = browser.send("Runtime.evaluate", {"expression": call, "awaitPromise": True, "returnByValue": True})
    assert "exceptionDetails" not in result, result["exceptionDetails"]
    browser.send("Runtime.evaluate", {"expression": "0"})       # flush: console events of the run are in
    problems = [e for e in browser.events if e["method"] == "Runtime.exceptionThrown"
                or (e["method"] == "Log.entryAdded" and e["params"]["entry"]["level"] in ("error", "warning"))
                or (e["method"] == "Runtime.consoleAPICalled" and e["params"]["type"] in ("error", "warning"))]
    assert problems == [], problems
    return result["result"]["value"]


@pytest.mark.parametrize("which", ["small", "demo"])
def test_three_js_plays_the_animation_we_wrote(tmp_path, served, browser, demo, which):
    """Both GLBs have sparse targets; the demo rig has vertex colours, the small character none."""
    character = small_character(n_shapes=6) if which == "small" else demo
    fps, n = (24.0, 30) if which == "small" else (30.0, 60)
    w = random_weights(n, character.n_shapes, seed=7)
    path = write_glb(tmp_path / f"{which}.glb", character, w, fps, name=f"clip {which}")
    character = character.in_metres()   # what the file holds: glTF's metres (the demo rig is in centimetres)
    frame_times = (np.arange(n) / fps).astype(np.float32)
    times = sorted({0.0, float(frame_times[1]), float(frame_times[-1]), float(frame_times[-2]),
                    *[(k + 0.5) / fps for k in range(0, n - 1, 3)], *[(k + 0.25) / fps for k in (1, n // 2, n - 2)],
                    *[float(frame_times[k]) for k in range(0, n, 7)]})
    moves = (character.deltas[0] != 0).any(axis=1)             # a vertex the first shape's sparse target lists,
    vertex_ids = [0, 7, character.n_vertices // 2, character.n_vertices - 1,    # and one it leaves at zero
                  int(np.flatnonzero(moves)[0]), int(np.flatnonzero(~moves)[0])]
    g, _ = glb_arrays(path)
    assert all(g.accessors[t["POSITION"]].sparse is not None for t in g.meshes[0].primitives[0].targets)
    srgb = None if character.vertex_colors is None else character.vertex_colors[vertex_ids].tolist()
    got = play_in_three(browser, served, path, times, vertex_ids, srgb)

    assert got["meshes"] == 1 and got["clips"] == [f"clip {which}"]
    assert got["dictionary"] == {name: i for i, name in enumerate(character.shape_names)}
    assert got["duration"] == pytest.approx(float(frame_times[-1]), abs=1e-6)
    ((track, n_times, n_values),) = got["tracks"]
    assert track.endswith(".morphTargetInfluences") and n_times == n and n_values == n * character.n_shapes
    assert got["vertexCount"] == character.n_vertices and got["triangles"] == len(character.faces)
    assert got["relative"] is True
    assert np.array_equal(np.array(got["neutral"], np.float32), character.neutral[vertex_ids])
    assert np.array_equal(np.array(got["deltas"], np.float32), character.deltas[:, vertex_ids])
    # the material: our PBR values, not glTF's default metal; vertex colours on exactly when we wrote COLOR_0
    material = got["material"]
    assert material["type"] == "MeshStandardMaterial" and material["color"] == [1, 1, 1]
    assert material["metalness"] == 0 and material["roughness"] == pytest.approx(0.6)
    if character.vertex_colors is None:
        assert got["colors"] is None and material["vertexColors"] is False
    else:
        assert got["colorItemSize"] == 3 and material["vertexColors"] is True
        assert got["workingColorSpace"] == "srgb-linear"
        # what three.js holds is what three.js itself makes of our sRGB colours: the preview's colours on screen
        assert np.allclose(got["colors"], got["threeLinear"], rtol=0, atol=1e-6)
        assert np.allclose(got["colors"], srgb_to_linear_here(character.vertex_colors[vertex_ids]), rtol=0,
                           atol=1e-6)
        assert np.abs(np.array(got["colors"]) - character.vertex_colors[vertex_ids]).max() > 0.05   # not copied
    influences = np.array(got["influences"])
    assert influences.shape == (len(times), character.n_shapes)
    expected = np.array([expected_weights(frame_times, w, t) for t in times])
    worst = np.abs(influences - expected).max()
    print(f"\nthree.js {which}: {len(times)} times, worst influence error {worst:.2e}")
    assert np.allclose(influences, expected, rtol=0, atol=1e-3), worst
    # between frames the influences are blends, not the previous keyframe held (STEP) or the next one
    mid = [i for i, t in enumerate(times) if abs(t * fps - round(t * fps)) > 0.2]
    before = w[[int(np.floor(times[i] * fps)) for i in mid]]
    assert len(mid) >= 10 and np.abs(influences[mid] - before).max() > 0.1
    assert np.abs(influences[mid] - w[[int(np.floor(times[i] * fps)) + 1 for i in mid]]).max() > 0.1


@pytest.mark.parametrize("mode", ["strip", "fan", "strip-unindexed"])
def test_triangle_strips_and_fans_are_read_as_their_triangles(tmp_path, mode):
    """glTF allows TRIANGLE_STRIP and TRIANGLE_FAN (3.7.2.1); they were refused ("only TRIANGLES are read"), and a
    scene mesh drawn so was left out of the USD and the preview. They are read as the triangles they draw, in the
    specification's winding; a strip's degenerate joining triangles are dropped."""
    d = Doc()
    from visemeflow.rig.gltf import read_gltf_mesh

    fifth = [0, 2, 0] if mode == "strip-unindexed" else [2, 0, 0]      # the strip zigzags on, or joins back
    quad = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], fifth], np.float32)
    deltas = np.zeros_like(quad)
    deltas[3, 2] = 0.5
    if mode == "fan":
        indices, expected = [0, 1, 3, 2], [(1, 3, 0), (3, 2, 0)]
    elif mode == "strip":      # two triangles, then a degenerate pair joining a third
        indices, expected = [0, 1, 2, 3, 3, 1, 1, 4, 3], [(0, 1, 2), (1, 3, 2), (1, 4, 3)]
    else:                      # the vertices in order: 0 1 2 3 4
        indices, expected = None, [(0, 1, 2), (1, 3, 2), (2, 3, 4)]
    primitive = gl.Primitive(attributes=gl.Attributes(POSITION=d.accessor(quad)),
                             indices=None if indices is None else d.accessor(np.array(indices, np.uint16),
                                                                             gl.SCALAR),
                             mode=gl.TRIANGLE_FAN if mode == "fan" else gl.TRIANGLE_STRIP,
                             targets=[{"POSITION": d.accessor(deltas)}])
    d.mesh([primitive], names=["jawOpen"])
    path = d.save(tmp_path / f"{mode}.glb", nodes=[0])
    mesh = read_gltf_mesh(path)
    assert [tuple(f) for f in mesh.faces] == expected
    assert mesh.surfaces == ((None, len(expected)),)
    normals = np.cross(quad[mesh.faces[:, 1]] - quad[mesh.faces[:, 0]], quad[mesh.faces[:, 2]] - quad[mesh.faces[:, 0]])
    assert (normals[:, 2] > 0).all()       # every triangle faces +z, as a strip's alternating winding intends
