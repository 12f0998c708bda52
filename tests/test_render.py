"""The ground-truth renderer: projection, z-buffer, culling, shading, fast path against the per-triangle reference."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from visemeflow.rig import evaluate_rig, load_demo_rig
from visemeflow.render.raster import (
    DEFAULT_BACKGROUND,
    Camera,
    MeshTexture,
    Pose,
    frontal_pose,
    project,
    rasterize,
    rasterize_fragments,
    rasterize_reference,
    render_backdrop,
    render_mesh,
    vertex_normals,
)
from visemeflow.visemes import viseme_index


def quad(x0: float, x1: float, y0: float, y1: float, z: float) -> tuple[np.ndarray, np.ndarray]:
    """A rectangle in the plane z, two triangles counter-clockwise seen from +z (the camera side)."""
    vertices = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float64)
    return vertices, np.array([[0, 1, 2], [0, 2, 3]], np.int64)


def scene(*quads) -> tuple[np.ndarray, np.ndarray]:
    vertices, faces = [], []
    for v, f in quads:
        faces.append(f + sum(len(x) for x in vertices))
        vertices.append(v)
    return np.concatenate(vertices), np.concatenate(faces)


CAMERA = Camera.default(64, 48, fov_deg=40.0)
FRONT = Pose((0.0, 0.0, 0.0), (0.0, 0.0, -20.0))


@pytest.fixture(scope="module")
def demo():
    return load_demo_rig()


def demo_view(rig, width=360, height=288):
    camera = Camera.default(width, height)
    return camera, frontal_pose(rig.neutral[rig.landmark_ids], camera, fill=0.45)


# ------------------------------------------------------------------------------------------ projection

def test_camera_default_intrinsics():
    camera = Camera.default(360, 288, fov_deg=25.0)
    assert (camera.width, camera.height) == (360, 288)
    assert camera.fx == camera.fy == pytest.approx(144 / np.tan(np.radians(12.5)))
    assert (camera.cx, camera.cy) == (179.5, 143.5)


def test_project_matches_opencv():
    rng = np.random.default_rng(0)
    points = rng.uniform(-5, 5, (50, 3))
    pose = Pose((0.1, -0.3, 0.05), (1.0, -2.0, -60.0))
    camera = Camera.default(640, 480)
    rvec, tvec = pose.opencv_extrinsics()
    expected, _ = cv2.projectPoints(points, rvec, tvec, camera.matrix, None)
    np.testing.assert_allclose(project(points, camera, pose), expected.reshape(-1, 2), atol=1e-6)


def test_frontal_view_is_upright_and_unmirrored(demo):
    camera, pose = demo_view(demo)
    uv = project(demo.neutral[demo.landmark_ids], camera, pose)
    assert uv[8, 1] > uv[27, 1]  # chin below the nose bridge
    assert uv[36, 0] < uv[45, 0]  # subject's right eye corner on the image left (Multi-PIE)
    height = uv[:, 1].max() - uv[:, 1].min()
    assert height == pytest.approx(0.45 * 288, rel=0.05)
    assert abs(uv[:, 0].mean() - camera.cx) < 10


# ------------------------------------------------------------------------------------------ rendering the demo rig

@pytest.mark.parametrize(("width", "height"), [(360, 288), (640, 480)])
def test_render_shape_dtype_and_coverage(demo, width, height):
    camera, pose = demo_view(demo, width, height)
    image = render_mesh(demo.neutral, demo.faces, demo.vertex_colors, camera, pose)
    assert image.shape == (height, width, 3) and image.dtype == np.uint8
    face = (image != np.array(DEFAULT_BACKGROUND, np.uint8)).any(axis=2)
    assert 0.15 < face.mean() < 0.7
    assert image[face].std() > 10  # shaded, not a flat silhouette


def test_landmarks_project_inside_the_rendered_face(demo):
    camera, pose = demo_view(demo)
    for weights in (np.zeros(16), np.eye(16)[viseme_index("AHH")]):
        mesh = evaluate_rig(demo, weights.astype(np.float32)).numpy()
        raster = rasterize(mesh, demo.faces, camera, pose)
        uv = np.round(project(mesh[demo.landmark_ids], camera, pose)).astype(int)
        assert ((uv >= 0) & (uv < [camera.width, camera.height])).all()
        assert (raster.triangle_id[uv[:, 1], uv[:, 0]] >= 0).all()


def test_open_mouth_shows_a_dark_interior(demo):
    camera, pose = demo_view(demo)
    mesh = evaluate_rig(demo, np.eye(16, dtype=np.float32)[viseme_index("AHH")]).numpy()
    image = render_mesh(mesh, demo.faces, demo.vertex_colors, camera, pose)
    lm = project(mesh[demo.landmark_ids], camera, pose)
    centre = np.round((lm[62] + lm[66]) / 2).astype(int)
    cheek = np.round(lm[3] * 0.6 + lm[30] * 0.4).astype(int)
    assert image[centre[1], centre[0]].astype(int).sum() < 0.5 * image[cheek[1], cheek[0]].astype(int).sum()


def test_fast_path_equals_reference_on_the_demo_rig(demo):
    camera, pose = demo_view(demo, 180, 144)
    mesh = evaluate_rig(demo, np.eye(16, dtype=np.float32)[viseme_index("OHH")]).numpy()
    fast = rasterize(mesh, demo.faces, camera, pose)
    slow = rasterize_fragments_dense(rasterize_reference(mesh, demo.faces, camera, pose), camera)
    np.testing.assert_array_equal(fast.triangle_id >= 0, slow[0] >= 0)
    assert (fast.triangle_id == slow[0]).mean() > 0.999  # ties on shared edges may go either way
    covered = slow[0] >= 0
    np.testing.assert_allclose(fast.depth[covered], slow[1][covered], rtol=1e-5)
    image_fast = render_mesh(mesh, demo.faces, demo.vertex_colors, camera, pose)
    image_slow = render_mesh(mesh, demo.faces, demo.vertex_colors, camera, pose, reference=True)
    assert np.abs(image_fast.astype(int) - image_slow).max() <= 2


def rasterize_fragments_dense(fragments, camera):
    ids = np.full(camera.width * camera.height, -1)
    depth = np.full(camera.width * camera.height, np.inf)
    ids[fragments.pixel] = fragments.triangle
    depth[fragments.pixel] = fragments.depth
    return ids.reshape(camera.height, camera.width), depth.reshape(camera.height, camera.width)


# ------------------------------------------------------------------------------------------ z-buffer, culling

@pytest.mark.parametrize("front_first", [True, False])
def test_zbuffer_hides_a_small_quad_behind_a_big_one(front_first):
    big = quad(-4, 4, -3, 3, 0.0)
    small = quad(-1, 1, -1, 1, -2.0)  # further from the camera
    vertices, faces = scene(big, small) if front_first else scene(small, big)
    raster = rasterize(vertices, faces, CAMERA, FRONT)
    visible = set(np.unique(raster.triangle_id)) - {-1}
    assert visible == ({0, 1} if front_first else {2, 3})


def test_zbuffer_shows_a_small_quad_in_front():
    vertices, faces = scene(quad(-4, 4, -3, 3, 0.0), quad(-1, 1, -1, 1, 2.0))
    raster = rasterize(vertices, faces, CAMERA, FRONT)
    centre = raster.triangle_id[CAMERA.height // 2, CAMERA.width // 2]
    assert centre in (2, 3)
    assert raster.depth[CAMERA.height // 2, CAMERA.width // 2] == pytest.approx(18.0, rel=1e-6)
    u, v = np.round(project(np.array([[3.0, 2.0, 0.0]]), CAMERA, FRONT)[0]).astype(int)
    assert raster.triangle_id[v, u] in (0, 1)


def test_intersecting_planes_split_at_the_intersection():
    # a plane tilted about y crossing z = 0 at x = 0: in front on the right, behind on the left
    flat = quad(-4, 4, -3, 3, 0.0)
    tilted = (np.array([[-4, -3, -2], [4, -3, 2], [4, 3, 2], [-4, 3, -2]], np.float64), flat[1])
    vertices, faces = scene(flat, tilted)
    raster = rasterize(vertices, faces, CAMERA, FRONT)
    row = raster.triangle_id[CAMERA.height // 2]
    cx = int(CAMERA.cx)
    assert set(row[cx - 12 : cx - 2]) <= {0, 1}
    assert set(row[cx + 3 : cx + 13]) <= {2, 3}


def test_backfaces_are_culled_unless_asked():
    vertices, faces = quad(-2, 2, -2, 2, 0.0)
    flipped = faces[:, ::-1].copy()
    assert (rasterize(vertices, flipped, CAMERA, FRONT).triangle_id == -1).all()
    assert (rasterize(vertices, flipped, CAMERA, FRONT, cull_backfaces=False).triangle_id >= 0).any()
    assert (rasterize(vertices, faces, CAMERA, FRONT).triangle_id >= 0).any()


def test_behind_the_camera_renders_nothing():
    vertices, faces = quad(-2, 2, -2, 2, 0.0)
    image = render_mesh(vertices, faces, None, CAMERA, Pose((0, 0, 0), (0, 0, 5.0)))
    assert (image == np.array(DEFAULT_BACKGROUND, np.uint8)).all()


def test_shared_edges_leave_no_cracks():
    # a finely tessellated plane covering the view: every pixel must be covered exactly by the plane
    n = 40
    xs, ys = np.meshgrid(np.linspace(-8, 8, n + 1), np.linspace(-6, 6, n + 1))
    vertices = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    vertices[:, :2] += np.random.default_rng(0).uniform(-0.05, 0.05, (len(vertices), 2))
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    pose = Pose((0, 0, 0), (0, 0, -16.0))
    raster = rasterize(vertices, faces, CAMERA, pose)
    assert (raster.triangle_id[4:-4, 4:-4] >= 0).all()


# ------------------------------------------------------------------------------------------ shading

def test_lambert_plus_ambient():
    vertices, faces = quad(-4, 4, -3, 3, 0.0)
    colors = np.full((4, 3), 0.8)
    lit = render_mesh(vertices, faces, colors, CAMERA, FRONT, light_dir=(0, 0, 1), ambient=0.25)
    dark = render_mesh(vertices, faces, colors, CAMERA, FRONT, light_dir=(0, 0, -1), ambient=0.25)
    grazing = render_mesh(vertices, faces, colors, CAMERA, FRONT, light_dir=(1, 0, 1), ambient=0.25)
    centre = (CAMERA.height // 2, CAMERA.width // 2)
    assert lit[centre].tolist() == [204, 204, 204]  # 0.8 * 255
    assert dark[centre].tolist() == [51, 51, 51]  # ambient only
    expected = round(255 * 0.8 * (0.25 + 0.75 * np.sqrt(0.5)))
    assert abs(int(grazing[centre][0]) - expected) <= 1


def test_vertex_colours_are_interpolated():
    vertices, faces = quad(-4, 4, -3, 3, 0.0)
    colors = np.array([[1, 0, 0], [1, 0, 0], [0, 0, 1], [0, 0, 1]], np.float64)  # red bottom, blue top
    image = render_mesh(vertices, faces, colors, CAMERA, FRONT, light_dir=(0, 0, 1), ambient=1.0)
    column = image[:, CAMERA.width // 2]
    covered = (column != np.array(DEFAULT_BACKGROUND, np.uint8)).any(axis=1)
    reds = column[covered, 0].astype(int)
    assert reds[0] < 40 and reds[-1] > 215  # image top is blue, bottom red
    assert (np.diff(reds) >= 0).all()


def test_a_texture_colours_each_fragment_by_its_texel_times_the_face_colour_and_the_light():
    """A quad with UVs 0..1 (glTF's origin at the image's top left) over a 2x2 image: each quarter of the quad shows
    its texel (bilinear, exact at texel centres), the second triangle's base colour halves green, and the light
    scales it all; a face without an image shows its base colour."""
    vertices, faces = quad(-4, 4, -3, 3, 0.0)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)     # bottom left vertex: the image's bottom left
    texels = np.array([[[250, 0, 0], [0, 250, 0]], [[0, 0, 250], [250, 250, 250]]], np.uint8)   # top: red green
    texture = MeshTexture(uv=uv, face_image=np.array([0, 0]), face_color=np.ones((2, 3)), images=(texels,))
    image = render_mesh(vertices, faces, None, CAMERA, FRONT, light_dir=(0, 0, 1), ambient=1.0, texture=texture)
    at = project(np.array([[-2, 1.5, 0], [2, 1.5, 0], [-2, -1.5, 0], [2, -1.5, 0]], np.float64), CAMERA, FRONT)
    quarters = np.array([image[int(round(y)), int(round(x))] for x, y in at], np.float64)
    # top left red, top right green, bottom left blue, bottom right white (the nearest pixel centre is within a
    # fraction of a texel of the texel's centre: bilinear blends a little of the neighbours)
    np.testing.assert_allclose(quarters, texels.reshape(4, 3), atol=25)
    halved = MeshTexture(uv=uv, face_image=np.array([0, -1]), face_color=np.array([[1, 1, 1], [0.2, 0.4, 0.6]]),
                         images=(texels,))
    dim = render_mesh(vertices, faces, None, CAMERA, FRONT, light_dir=(0, 0, 1), ambient=0.5, texture=halved)
    # the top left quarter lies on face 1 (vertices 0, 2, 3): its base colour alone, at ambient 0.5 + 0.5 lit
    top_left, bottom_right = dim[int(round(at[0][1])), int(round(at[0][0]))], dim[int(round(at[3][1])),
                                                                                   int(round(at[3][0]))]
    assert top_left.tolist() == [51, 102, 153]
    np.testing.assert_allclose(bottom_right, [250, 250, 250], atol=25)
    grey = render_mesh(vertices, faces, None, CAMERA, FRONT, light_dir=(0, 0, 1), ambient=1.0)
    assert grey[int(round(at[0][1])), int(round(at[0][0]))].tolist() == [191, 191, 191]   # untextured: as before


def test_vertex_normals_of_a_sphere_point_outward():
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2)
    normals = vertex_normals(sphere.vertices, sphere.faces)
    np.testing.assert_allclose((normals * sphere.vertices).sum(1), 1.0, atol=0.02)


# ------------------------------------------------------------------------------------------ properties

triangle_soup = st.integers(0, 2**32 - 1).map(lambda seed: np.random.default_rng(seed))


@settings(max_examples=30, deadline=None)
@given(rng=triangle_soup, n=st.integers(1, 12), yaw=st.floats(-0.6, 0.6))
def test_fast_path_equals_reference_on_random_triangles(rng, n, yaw):
    vertices = rng.uniform(-6, 6, (3 * n, 3))
    faces = np.arange(3 * n).reshape(n, 3)
    pose = Pose((0.0, yaw, 0.0), (0.0, 0.0, -25.0))
    for cull in (True, False):
        fast = rasterize(vertices, faces, CAMERA, pose, cull_backfaces=cull)
        ids, depth = rasterize_fragments_dense(rasterize_reference(vertices, faces, CAMERA, pose, cull), CAMERA)
        np.testing.assert_array_equal(fast.triangle_id >= 0, ids >= 0)
        covered = ids >= 0
        np.testing.assert_allclose(fast.depth[covered], depth[covered], rtol=1e-5)
        # where depths differ the nearer triangle won in both
        agree = (fast.triangle_id == ids) | np.isclose(fast.depth, depth, rtol=1e-9)
        assert agree.all()


def test_fragments_hold_one_winner_per_pixel(demo):
    camera, pose = demo_view(demo)
    fragments = rasterize_fragments(demo.neutral, demo.faces, camera, pose)
    assert np.unique(fragments.pixel).size == fragments.pixel.size
    np.testing.assert_allclose(fragments.barycentric.sum(axis=1), 1.0, atol=1e-9)
    assert (fragments.barycentric > -1e-6).all()


def test_batched_rasterisation_equals_one_batch(demo, monkeypatch):
    import visemeflow.render.raster as render

    camera, pose = demo_view(demo, 180, 144)
    mesh = evaluate_rig(demo, np.eye(16, dtype=np.float32)[viseme_index("AHH")]).numpy()
    whole = rasterize(mesh, demo.faces, camera, pose)
    monkeypatch.setattr(render, "_BATCH_PIXELS", 5000)
    batched = rasterize(mesh, demo.faces, camera, pose)
    np.testing.assert_array_equal(batched.triangle_id, whole.triangle_id)
    np.testing.assert_array_equal(batched.depth, whole.depth)
    np.testing.assert_allclose(batched.barycentric, whole.barycentric, atol=1e-6)


@pytest.mark.parametrize("textured", [False, True])
def test_a_mesh_over_a_backdrop_equals_both_drawn_as_one(demo, textured):
    """Previews draw a scene's static meshes once (`render_backdrop`) and the moving ones over them each frame. That
    must be the image of both drawn as one mesh, the moving faces first: here the demo head over a plane that cuts
    through it (the plane in front of the jaw, behind the nose), and the same plane in front of everything."""
    camera, pose = demo_view(demo, 180, 144)
    head = evaluate_rig(demo, np.eye(16, dtype=np.float32)[viseme_index("AHH")]).numpy().astype(np.float64)
    low, high = head.min(axis=0), head.max(axis=0)
    for z in (0.5 * (low[2] + high[2]) + 0.3 * (high[2] - low[2]), high[2] + 1.0):
        plane = quad(low[0] - 1, high[0] + 1, low[1] - 1, 0.5 * (low[1] + high[1]), z)
        vertices, faces = scene((head, demo.faces), plane)
        colors = np.concatenate([demo.vertex_colors, np.full((4, 3), 0.3)])
        texture = None
        if textured:
            rng = np.random.default_rng(0)
            uv = rng.random((len(vertices), 2)).astype(np.float32)
            texture = MeshTexture(uv=uv, face_image=np.where(np.arange(len(faces)) % 3 == 0, 0, -1),
                                  face_color=rng.random((len(faces), 3)),
                                  images=(rng.integers(0, 255, (8, 8, 3), dtype=np.uint8),))
        whole = render_mesh(vertices, faces, colors, camera, pose, texture=texture)
        n, f = len(head), len(demo.faces)
        backdrop = render_backdrop(plane[0], plane[1], colors[n:], camera, pose, texture=None if texture is None else
                                   MeshTexture(texture.uv[n:], texture.face_image[f:], texture.face_color[f:],
                                               texture.images))
        front = render_mesh(head, demo.faces, colors[:n], camera, pose, backdrop=backdrop, texture=None
                            if texture is None else MeshTexture(texture.uv[:n], texture.face_image[:f],
                                                                texture.face_color[:f], texture.images))
        np.testing.assert_array_equal(front, whole)
        assert (backdrop.depth < np.inf).any() and not np.array_equal(whole, render_mesh(head, demo.faces, colors[:n],
                                                                                        camera, pose))
