"""The differentiable mouth-crop renderer behind L_rgb (Eq. 3): coverage, z-test, gradients, albedo, fitting."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from visemeflow.rig import evaluate_rig, load_demo_rig
from visemeflow.tracking import diffrender as dr
from visemeflow.render.camera import Intrinsics, project
from visemeflow.visemes import viseme_index

AHH = viseme_index("AHH")


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """The renderer is built for one core per tracked clip; small ops on a busy machine only lose with more."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def grid_pixels(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.mgrid[0:height, 0:width]
    return cols.astype(np.float64), rows.astype(np.float64)


def rasterize_2d(pix, depth, faces, height=16, width=16, **kwargs):
    rasterizer = dr.CropRasterizer(np.asarray(faces), dr.Crop(0, 0, width, height), **kwargs)
    pix = torch.as_tensor(pix, dtype=torch.float64)
    depth = torch.as_tensor(depth, dtype=torch.float64)
    return rasterizer, rasterizer.rasterize(pix, depth), pix


# ------------------------------------------------------------------------------------------ one triangle

# front-facing (counter-clockwise seen from the camera = negative signed area with v pointing down); the
# hypotenuse u + v = 12.3 passes no pixel centre, so coverage has one right answer
TRIANGLE = np.array([[1.5, 1.5], [1.5, 10.8], [10.8, 1.5]])


def expected_triangle_mask(height=16, width=16):
    u, v = grid_pixels(height, width)
    return (u >= 1.5) & (v >= 1.5) & (u + v <= 12.3)


def test_single_triangle_mask_is_exact():
    _, fragments, _ = rasterize_2d(TRIANGLE, [5.0, 5.0, 5.0], [[0, 1, 2]])
    mask = fragments.mask.numpy()
    np.testing.assert_array_equal(mask, expected_triangle_mask())
    assert mask.sum() == 45  # u, v >= 2 and u + v <= 12: 9 + 8 + ... + 1
    assert (fragments.triangle.numpy()[mask] == 0).all() and (fragments.triangle.numpy()[~mask] == -1).all()
    np.testing.assert_allclose(fragments.depth.numpy()[mask], 5.0, rtol=1e-6)
    assert np.isinf(fragments.depth.numpy()[~mask]).all()


def test_back_faces_are_culled_unless_asked():
    flipped = TRIANGLE[[0, 2, 1]]
    _, culled, _ = rasterize_2d(flipped, [5.0, 5.0, 5.0], [[0, 1, 2]])
    assert not culled.mask.any()
    _, both, _ = rasterize_2d(flipped, [5.0, 5.0, 5.0], [[0, 1, 2]], cull_backfaces=False)
    np.testing.assert_array_equal(both.mask.numpy(), expected_triangle_mask())


def test_triangle_partly_outside_the_grid_and_tile_sizes_agree():
    big = np.array([[-20.0, -5.0], [3.0, 40.0], [30.0, -3.0]])
    masks = []
    for tile in (1, 3, 4, 8, 16):
        _, fragments, _ = rasterize_2d(big, [2.0, 2.0, 2.0], [[0, 1, 2]], height=13, width=11, tile=tile, chunk=64)
        masks.append(fragments.mask.numpy())
    for mask in masks[1:]:
        np.testing.assert_array_equal(mask, masks[0])
    u, v = grid_pixels(13, 11)
    a, b, c = big

    def cross(p, q):
        return (q[0] - p[0]) * (v - p[1]) - (q[1] - p[1]) * (u - p[0])

    inside = (cross(a, b) <= 0) & (cross(b, c) <= 0) & (cross(c, a) <= 0)
    np.testing.assert_array_equal(masks[0], inside)


def test_interpolating_a_linear_attribute_reproduces_it_at_pixel_centres():
    rasterizer, fragments, pix = rasterize_2d(TRIANGLE, [5.0, 5.0, 5.0], [[0, 1, 2]])

    def linear(u, v):
        return np.stack([0.3 + 0.05 * u - 0.02 * v, 2.0 * u + 3.0 * v], -1)

    attributes = torch.as_tensor(linear(TRIANGLE[:, 0], TRIANGLE[:, 1]))
    image, mask = rasterizer.interpolate(fragments, pix, attributes)
    u, v = grid_pixels(16, 16)
    want = linear(u, v)
    m = mask.numpy()
    np.testing.assert_allclose(image.detach().numpy()[m], want[m], atol=1e-9)
    assert (image.detach().numpy()[~m] == 0).all()


# ------------------------------------------------------------------------------------------ z-test


def test_nearer_triangle_wins_whatever_the_order():
    # two overlapping front-facing triangles: id 0 at depth 8, id 1 at depth 3 (nearer)
    pix = np.concatenate([TRIANGLE, TRIANGLE + [2.0, 2.0]])
    depth = [8.0, 8.0, 8.0, 3.0, 3.0, 3.0]
    for faces, near_id in (([[0, 1, 2], [3, 4, 5]], 1), ([[3, 4, 5], [0, 1, 2]], 0)):
        _, fragments, _ = rasterize_2d(pix, depth, faces)
        tri = fragments.triangle.numpy()
        u, v = grid_pixels(16, 16)
        front = (u >= 3.5) & (v >= 3.5) & (u + v <= 16.3)
        back_only = expected_triangle_mask() & ~front
        assert front.any() and back_only.any()
        assert (tri[front] == near_id).all()
        assert (tri[back_only] == 1 - near_id).all()
        np.testing.assert_allclose(fragments.depth.numpy()[front], 3.0, rtol=1e-6)


def test_depth_is_perspective_exact_on_a_slanted_triangle():
    # depth is compared as 1/d, affine in screen space: a pixel sees d = 1 / (sum_k b_k / d_k)
    depth = np.array([2.0, 4.0, 8.0])
    _, fragments, _ = rasterize_2d(TRIANGLE, depth, [[0, 1, 2]])
    u, v = grid_pixels(16, 16)
    # barycentrics of the right triangle: b1 along v, b2 along u
    b1 = (v - 1.5) / 9.3
    b2 = (u - 1.5) / 9.3
    b0 = 1 - b1 - b2
    want = 1.0 / (b0 / 2.0 + b1 / 4.0 + b2 / 8.0)
    m = expected_triangle_mask()
    np.testing.assert_allclose(fragments.depth.numpy()[m], want[m], rtol=1e-5)


# ------------------------------------------------------------------------------------------ gradients


def test_interpolate_gradcheck_positions_and_attributes():
    # a quad of two triangles; all covered pixel centres stay > 0.2 px from every edge, so the fixed fragments
    # stay valid under gradcheck's perturbations
    pix0 = torch.tensor([[1.3, 1.2], [1.4, 8.7], [8.8, 8.6], [8.6, 1.35]], dtype=torch.float64)
    faces = [[0, 1, 2], [0, 2, 3]]
    rasterizer, fragments, _ = rasterize_2d(pix0, [4.0, 4.5, 5.0, 4.2], faces, height=10, width=10)
    assert fragments.mask.sum() == 49 and set(np.unique(fragments.triangle.numpy())) == {-1, 0, 1}
    attributes = torch.rand(4, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))

    def fn(pix, attr):
        return rasterizer.interpolate(fragments, pix, attr)[0]

    assert torch.autograd.gradcheck(fn, (pix0.clone().requires_grad_(), attributes.clone().requires_grad_()))


def test_render_crop_gradcheck_pose_vertices_albedo():
    # a small slanted quad mesh seen by a pinhole camera, Lambert shading on: gradients reach vertices, pose, albedo
    vertices = torch.tensor([[-1.0, -1.0, 0.2], [1.0, -1.0, -0.1], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.3], [0.0, 0.0, 0.6]],
                            dtype=torch.float64)
    faces = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    camera = Intrinsics(20.0, 20.0, 7.5, 7.5, 16, 16)
    crop = dr.Crop(0, 0, 16, 16)
    rotation = torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64)
    translation = torch.tensor([0.1, 0.05, -5.0], dtype=torch.float64)
    albedo = torch.rand(5, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    light = dr.Light((0.3, 0.5, 1.0), 0.3)
    image, mask = dr.render_crop(vertices, rotation, translation, camera, crop, faces, albedo, light)
    assert mask.sum() > 20 and image.dtype == torch.float64

    # pixel centres must keep their triangles under the perturbation: check they are not on an edge
    pix, _ = dr.project_to_crop(vertices, rotation, translation, camera, crop)
    weights = torch.linspace(0.5, 1.5, 16 * 16 * 3, dtype=torch.float64).reshape(16, 16, 3)

    def fn(v, r, t, a):
        return (dr.render_crop(v, r, t, camera, crop, faces, a, light)[0] * weights).sum()

    inputs = tuple(x.clone().requires_grad_() for x in (vertices, rotation, translation, albedo))
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-7, atol=1e-5)
    assert pix.shape == (5, 2)


def test_project_to_crop_matches_camera_project_through_the_crop():
    camera = Intrinsics.from_fov(360, 288)
    crop = dr.Crop(100, 90, 81, 77, 64, 60)
    points = torch.tensor([[0.5, -1.0, 2.0], [-3.0, 2.0, 1.0], [0.0, 0.0, 0.0]])
    rotation, translation = torch.tensor([0.05, 0.1, -0.02]), torch.tensor([0.3, 1.0, -60.0])
    pix, depth = dr.project_to_crop(points, rotation, translation, camera, crop)
    full = project(points[None], rotation[None], translation[None], camera)[0]
    np.testing.assert_allclose(pix.numpy(), crop.to_crop(full).numpy(), atol=1e-4)
    np.testing.assert_allclose(crop.to_image(pix).numpy(), full.numpy(), atol=1e-4)
    assert (depth > 55).all()


# ------------------------------------------------------------------------------------------ crops


def test_mouth_crop_square_around_the_lips_and_inside_the_image():
    landmarks = np.zeros((68, 2))
    landmarks[48:68] = np.column_stack([np.linspace(150, 190, 20), np.linspace(200, 215, 20)])
    crop = dr.mouth_crop(landmarks, size=64, margin=0.6, image_size=(360, 288))
    assert crop.width == crop.height == 64  # 40 px wide * 1.6
    assert (crop.out_width, crop.out_height) == (64, 64)
    assert crop.x0 <= 150 and crop.x0 + crop.width - 1 >= 190 and crop.y0 <= 200 and crop.y0 + crop.height > 215
    # near the border the window is shifted in, not cut; over a small image it is cut and keeps its scale
    corner = dr.mouth_crop(landmarks + [165.0, 70.0], size=64, margin=0.6, image_size=(360, 288))
    assert (corner.x0, corner.y0, corner.width, corner.height) == (360 - 64, 288 - 64, 64, 64)
    # several frames: the union of their mouths
    both = dr.mouth_crop(np.stack([landmarks, landmarks + [20.0, 10.0]]), size=64, margin=0.6)
    assert both.width == both.height == 96 and both.out_width == 64 and both.scale == (64 / 96, 64 / 96)
    assert both.x0 <= 150 and both.x0 + both.width - 1 >= 210 and both.y0 <= 200 and both.y0 + both.height > 225
    small = dr.mouth_crop(landmarks - [140.0, 150.0], size=32, margin=1.0, image_size=(60, 70))
    assert (small.x0, small.y0, small.width, small.height) == (0, 0, 60, 70)
    assert small.scale[0] == pytest.approx(small.scale[1], rel=0.03) and small.out_width == 24
    with pytest.raises(ValueError):
        dr.mouth_crop(np.full((68, 2), np.nan))


def test_crop_image_and_crop_grid_render_agree():
    # render a scene on the whole image, cut and resample it with crop_image; render the same scene straight on
    # the crop's grid through the scaled camera: the two must match up to resampling
    rig, camera, rotation, translation = demo_scene()
    vertices = torch.as_tensor(rig.neutral)
    albedo = torch.as_tensor(rig.vertex_colors)
    full = dr.Crop(0, 0, camera.width, camera.height)
    faces = rig.faces[dr.triangles_in_crop(rig.faces, dr.project_to_crop(vertices, rotation, translation, camera,
                                                                             full)[0], full, margin=-40.0)]
    frame, _ = dr.render_crop(vertices, rotation, translation, camera, full, faces, albedo, dr.Light())
    frame = (frame.detach().numpy() * 255).round().astype(np.uint8)
    landmarks = project(vertices[None, rig.landmark_ids], rotation[None], translation[None], camera)[0].numpy()
    crop = dr.mouth_crop(landmarks, size=48, margin=0.5, image_size=(camera.width, camera.height))
    assert crop.width > 48  # a real down-sampling
    cut = dr.crop_image(frame, crop)
    direct, mask = dr.render_crop(vertices, rotation, translation, camera, crop, faces, albedo, dr.Light())
    assert cut.shape == direct.shape == (48, 48, 3) and mask.all()
    error = (cut - direct.detach()).abs().mean().item()
    assert error < 0.02, error


# ------------------------------------------------------------------------------------------ demo rig


def demo_scene(width=360, height=288, distance=60.0, rotation=(0.05, -0.1, 0.0)):
    rig = load_demo_rig()
    camera = Intrinsics.from_fov(width, height)
    mouth = rig.neutral[rig.landmark_ids[48:68]].mean(axis=0)
    translation = torch.tensor([-mouth[0], -mouth[1], -(mouth[2] + distance)], dtype=torch.float32)
    return rig, camera, torch.tensor(rotation, dtype=torch.float32), translation


@pytest.fixture(scope="module")
def demo():
    rig, camera, rotation, translation = demo_scene()
    open_mouth = torch.zeros(16)
    open_mouth[AHH] = 1.0
    landmarks = project(evaluate_rig(rig, torch.stack([torch.zeros(16), open_mouth]))[:, rig.landmark_ids],
                        rotation.expand(2, 3), translation.expand(2, 3), camera).numpy()
    crop = dr.mouth_crop(landmarks, size=64, margin=0.6, image_size=(camera.width, camera.height))
    meshes = evaluate_rig(rig, torch.stack([torch.zeros(16), open_mouth]))
    pix = torch.stack([dr.project_to_crop(m, rotation, translation, camera, crop)[0] for m in meshes])
    regions = np.concatenate([rig.regions["face"], rig.regions["mouth_interior"]])
    ids = np.intersect1d(dr.triangles_in_crop(rig.faces, pix, crop), dr.select_triangles(rig.faces, regions))
    rasterizer = dr.CropRasterizer(rig.faces[ids], crop)
    albedo = torch.as_tensor(rig.vertex_colors)[torch.as_tensor(rasterizer.vertex_ids)]
    return {"rig": rig, "camera": camera, "rotation": rotation, "translation": translation, "crop": crop,
            "rasterizer": rasterizer, "albedo": albedo}


LIGHT = dr.Light()


def render_weights(demo, weights, rotation=None, translation=None, light=LIGHT, albedo=None):
    vertices = evaluate_rig(demo["rig"], weights, demo["rasterizer"].vertex_ids)
    return dr.render_crop(vertices, demo["rotation"] if rotation is None else rotation,
                          demo["translation"] if translation is None else translation, demo["camera"], demo["crop"],
                          None, demo["albedo"] if albedo is None else albedo, light, rasterizer=demo["rasterizer"])


def ahh(value: float) -> torch.Tensor:
    weights = torch.zeros(16)
    weights[AHH] = value
    return weights


def test_compact_and_full_mesh_inputs_render_the_same(demo):
    rig = demo["rig"]
    compact, mask_c = render_weights(demo, ahh(0.4))
    full, mask_f = dr.render_crop(evaluate_rig(rig, ahh(0.4)), demo["rotation"], demo["translation"], demo["camera"],
                                  demo["crop"], demo["rasterizer"].faces, torch.as_tensor(rig.vertex_colors),
                                  dr.Light())
    assert torch.equal(mask_c, mask_f)
    np.testing.assert_allclose(compact.detach().numpy(), full.detach().numpy(), atol=1e-5)
    with pytest.raises(ValueError):
        demo["rasterizer"].faces_for(len(demo["rasterizer"].vertex_ids) + 1)


def test_open_jaw_shows_more_dark_mouth_interior(demo):
    rig, rasterizer = demo["rig"], demo["rasterizer"]
    interior = np.isin(rasterizer.faces, rig.regions["mouth_interior"]).all(axis=1)

    def dark_interior_pixels(weight):
        vertices = evaluate_rig(rig, ahh(weight), rasterizer.vertex_ids)
        image, mask, fragments = dr.render_crop(vertices, demo["rotation"], demo["translation"], demo["camera"],
                                                demo["crop"], None, demo["albedo"], dr.Light(),
                                                rasterizer=rasterizer, return_fragments=True)
        assert mask.float().mean() > 0.95  # the crop is nearly all face
        triangle = fragments.triangle.numpy()
        inside = triangle >= 0
        inside[inside] = interior[triangle[inside]]
        luminance = image.detach().numpy().mean(axis=-1)
        return int((inside & (luminance < 0.3)).sum()), luminance[mask.numpy() & ~inside].mean()

    (closed, _), (half, skin), (wide, _) = (dark_interior_pixels(w) for w in (0.0, 0.5, 1.0))
    assert closed < 20 < half < wide, (closed, half, wide)
    assert wide > 1.5 * half and wide > 250 and skin > 0.4


def test_rgb_loss_zero_on_itself_and_growing_with_motion(demo):
    target, mask = render_weights(demo, ahh(0.3))
    target = target.detach()
    assert dr.rgb_loss(target, target, mask).item() == 0.0
    losses = []
    for shift in (0.0, 0.05, 0.15, 0.4):  # centimetres across the image, ~0.1 .. 1 grid pixel
        moved = demo["translation"] + torch.tensor([shift, 0.5 * shift, 0.0])
        image, moved_mask = render_weights(demo, ahh(0.3), translation=moved)
        losses.append(dr.rgb_loss(image, target, moved_mask).item())
    assert losses[0] == pytest.approx(0.0, abs=1e-10)
    assert losses[1] < losses[2] < losses[3], losses
    # Eq. 3 by hand: the mean over the mask of the squared RGB distance
    other, _ = render_weights(demo, ahh(0.5))
    by_hand = ((other.detach() - target) ** 2).sum(dim=-1)[mask].mean()
    assert dr.rgb_loss(other, target, mask).item() == pytest.approx(by_hand.item(), rel=1e-5)


def test_gradients_reach_viseme_weights_and_pose(demo):
    target, _ = render_weights(demo, ahh(0.6))
    weights = ahh(0.3).requires_grad_()
    rotation = demo["rotation"].clone().requires_grad_()
    translation = demo["translation"].clone().requires_grad_()
    image, mask = render_weights(demo, weights, rotation, translation)
    dr.rgb_loss(image, target.detach(), mask).backward()
    assert weights.grad[AHH] < 0  # opening further lowers the loss
    assert torch.isfinite(rotation.grad).all() and rotation.grad.abs().sum() > 0
    assert torch.isfinite(translation.grad).all() and translation.grad.abs().sum() > 0


def test_albedo_estimated_from_own_renders_recovers_it(demo):
    rig, rasterizer, crop, camera = demo["rig"], demo["rasterizer"], demo["crop"], demo["camera"]
    ids = torch.as_tensor(rasterizer.vertex_ids)
    neutral = torch.as_tensor(rig.neutral)[ids]
    # a smooth albedo (linear in the rest position): sampling an image of it at a vertex gives the vertex's value
    lo, hi = neutral.min(dim=0).values, neutral.max(dim=0).values
    unit = (neutral - lo) / (hi - lo)
    known = (0.15 + 0.7 * torch.stack([unit[:, 0], unit[:, 1], 1 - 0.5 * (unit[:, 0] + unit[:, 1])], 1)).clamp(0, 1)
    frames, pixels, visible = [], [], []
    for k, weight in enumerate((0.0, 0.4, 0.8)):
        rotation = demo["rotation"] + torch.tensor([0.0, 0.04 * (k - 1), 0.0])
        vertices = evaluate_rig(rig, ahh(weight), rasterizer.vertex_ids)
        image, _, fragments = dr.render_crop(vertices, rotation, demo["translation"], camera, crop, None, known,
                                             None, rasterizer=rasterizer, return_fragments=True)
        pix, depth = dr.project_to_crop(vertices, rotation, demo["translation"], camera, crop)
        frames.append((image.detach().numpy() * 255).round().astype(np.uint8))
        pixels.append(pix.detach().numpy())
        visible.append(dr.visible_vertices(fragments, pix, depth))
    seen = np.any(visible, axis=0)
    assert 0.1 < seen.mean() < 0.9  # the hidden mouth interior is not seen
    estimate = dr.estimate_albedo(frames, pixels, visible, faces=rasterizer.faces_for(len(ids)))
    error = np.abs(estimate - known.numpy())
    assert error[seen].mean() < 0.01, error[seen].mean()
    assert np.percentile(error[seen], 95) < 0.03
    assert estimate.shape == (len(ids), 3) and estimate.min() >= 0 and estimate.max() <= 1
    # unseen vertices take their neighbours' colours: closer than a flat default would be
    assert error[~seen].mean() < np.abs(known.numpy()[~seen] - 0.5).mean()


def test_estimate_albedo_defaults_without_faces():
    frame = np.full((4, 4, 3), 200, np.uint8)
    pix = np.array([[1.0, 1.0], [2.5, 2.5], [0.0, 0.0]])
    estimate = dr.estimate_albedo([frame], [pix], [np.array([True, True, False])])
    np.testing.assert_allclose(estimate, 200 / 255, atol=1e-6)  # the unseen one gets the median of the seen ones


def test_fitting_ahh_by_gradient_descent_on_rgb_loss_recovers_it(demo):
    """The property the tracker needs: L_rgb alone pulls a viseme weight from the neutral to the target's."""
    with torch.no_grad():
        target, _ = render_weights(demo, ahh(0.6))
    value = torch.zeros((), requires_grad=True)
    optimiser = torch.optim.Adam([value], lr=0.05)
    for _ in range(80):
        weights = torch.zeros(16).index_put((torch.tensor([AHH]),), value.reshape(1))
        image, mask = render_weights(demo, weights)
        loss = dr.rgb_loss(image, target, mask)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    assert value.item() == pytest.approx(0.6, abs=0.03)


def test_select_triangles_and_mouth_triangles():
    faces = np.array([[0, 1, 2], [1, 2, 3], [3, 4, 5], [0, 2, 5]])
    np.testing.assert_array_equal(dr.select_triangles(faces, [0, 1, 2, 3]), [0, 1])
    np.testing.assert_array_equal(dr.select_triangles(faces, np.array([5, 3, 4])), [2])
    assert dr.select_triangles(faces, []).size == 0
    rig = load_demo_rig()
    ids = dr.mouth_triangles(rig)
    assert 0 < len(ids) < len(rig.faces)
    corners = rig.faces[ids]
    lips = np.isin(corners, rig.regions["lips"]).all(axis=1)
    assert lips.sum() > 0.9 * len(dr.select_triangles(rig.faces, rig.regions["lips"]))
    assert not np.isin(corners, rig.regions["eyes"]).any()


def test_triangles_in_crop_keeps_what_the_grid_can_show():
    faces = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    pix = np.array([[1.0, 1.0], [5.0, 1.0], [1.0, 5.0],  # inside
                    [30.0, 30.0], [35.0, 30.0], [30.0, 35.0],  # far outside
                    [-8.0, 2.0], [-1.0, 2.0], [-1.0, 6.0]])  # just left of the grid: kept by the margin only
    crop = dr.Crop(0, 0, 10, 10)
    np.testing.assert_array_equal(dr.triangles_in_crop(faces, pix, crop, margin=2.0), [0, 2])
    np.testing.assert_array_equal(dr.triangles_in_crop(faces, pix, crop, margin=0.5), [0])
    moved = pix.copy()
    moved[3:6] -= 25.0  # in a second frame the far triangle comes in
    np.testing.assert_array_equal(dr.triangles_in_crop(faces, np.stack([pix, moved]), crop, margin=0.5), [0, 1])


def test_reused_fragments_and_nothing_in_view(demo):
    image, mask, fragments = dr.render_crop(evaluate_rig(demo["rig"], ahh(0.2), demo["rasterizer"].vertex_ids),
                                            demo["rotation"], demo["translation"], demo["camera"], demo["crop"],
                                            None, demo["albedo"], LIGHT, rasterizer=demo["rasterizer"],
                                            return_fragments=True)
    again, again_mask = dr.render_crop(evaluate_rig(demo["rig"], ahh(0.2), demo["rasterizer"].vertex_ids),
                                       demo["rotation"], demo["translation"], demo["camera"], demo["crop"], None,
                                       demo["albedo"], LIGHT, rasterizer=demo["rasterizer"], fragments=fragments)
    assert torch.equal(image, again) and torch.equal(mask, again_mask)
    # the head behind the camera: nothing drawn, a zero loss, no error
    behind = demo["translation"] * torch.tensor([1.0, 1.0, -1.0])
    empty, empty_mask = render_weights(demo, ahh(0.2), translation=behind)
    assert not empty_mask.any() and (empty == 0).all()
    assert dr.rgb_loss(empty, image.detach(), empty_mask).item() == 0.0
