"""visemeflow.tracking.optical_flow: DIS optical flow, the forward-backward check, flow sampling, the per-utterance
FlowField and the optical-flow loss of Eq. 6. Synthetic frames with known motion, and two frames of a real GRID
clip (fails, not skips, when ../shared/data is missing)."""


import cv2
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from factories import SHARED_DATA
from visemeflow.tracking.optical_flow import (
    PRESETS,
    FlowConfig,
    FlowField,
    bidirectional_flow,
    clip_roi,
    consistency_mask,
    dis_flow,
    flow_masks,
    photometric_mask,
    roi_around,
    sample_flow,
    estimate_optical_flow,
    _make_dis,
)
from visemeflow.tracking.losses import flow_loss
from visemeflow.tracking.video import read_video_frames

GRID_CLIP = SHARED_DATA / "grid_s1" / "video" / "bbaf2n.mpg"
GRID_FACE = (87, 99, 139, 139)   # x, y, w, h: the Haar-cascade face box of bbaf2n (the speaker barely moves)

H, W = 160, 200
INNER = (slice(16, H - 16), slice(16, W - 16))   # away from the borders the warp fills by reflection


def texture(h=H, w=W, seed=0, sigma=2.0) -> np.ndarray:
    """Smooth random RGB texture, full 0..255 range: every patch has gradients to track."""
    noise = np.random.default_rng(seed).normal(size=(h, w, 3)).astype(np.float32)
    img = cv2.GaussianBlur(noise, (0, 0), sigma)
    img = (img - img.min()) / (img.max() - img.min()) * 255.0
    return img.astype(np.uint8)


def shifted(img: np.ndarray, tx: float, ty: float) -> np.ndarray:
    """``img`` with its content moved by (tx, ty) pixels: out(x, y) = img(x - tx, y - ty)."""
    m = np.float32([[1, 0, tx], [0, 1, ty]])
    return cv2.warpAffine(img, m, (img.shape[1], img.shape[0]), flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)


# ---------------------------------------------------------------------------------------------------------------
# Config and regions of interest


def test_config_defaults_and_validation():
    cfg = FlowConfig()
    assert (cfg.preset, cfg.fb_threshold_px, cfg.grayscale) == ("balanced", 1.0, True)
    assert cfg.cv_preset == cv2.DISOPTICAL_FLOW_PRESET_MEDIUM
    assert cfg.dis_settings == {"VariationalRefinementIterations": 0, "PatchStride": 4, "GradientDescentIterations": 16}
    assert FlowConfig(preset="medium").dis_settings == {}
    dis = _make_dis(cfg)   # the settings reach OpenCV's DIS; the rest stay medium's
    assert (dis.getVariationalRefinementIterations(), dis.getPatchStride(), dis.getGradientDescentIterations(),
            dis.getFinestScale(), dis.getPatchSize()) == (0, 4, 16, 1, 8)
    medium = _make_dis(FlowConfig(preset="medium"))
    assert (medium.getVariationalRefinementIterations(), medium.getPatchStride(),
            medium.getGradientDescentIterations()) == (5, 3, 25)
    assert FlowConfig(preset="ULTRAFAST").cv_preset == cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST
    assert FlowConfig(preset="fast").cv_preset == cv2.DISOPTICAL_FLOW_PRESET_FAST
    with pytest.raises(ValueError, match="preset"):
        FlowConfig(preset="slow")
    with pytest.raises(ValueError, match="fb_threshold_px"):
        FlowConfig(fb_threshold_px=0.0)
    with pytest.raises(ValueError, match="storage_dtype"):
        FlowConfig(storage_dtype="int8")
    with pytest.raises(ValueError, match="photometric_threshold"):
        FlowConfig(photometric_threshold=-1.0)
    with pytest.raises(ValueError, match="photometric_window"):
        FlowConfig(photometric_window=4)


def test_clip_roi_and_roi_around():
    assert clip_roi(None, 360, 288) == (0, 0, 360, 288)
    assert clip_roi((10, 20, 30, 40), 360, 288) == (10, 20, 30, 40)
    assert clip_roi((-10, -5, 30, 40), 360, 288) == (0, 0, 20, 35)
    assert clip_roi((350, 280, 30, 40), 360, 288) == (350, 280, 10, 8)
    with pytest.raises(ValueError, match="outside"):
        clip_roi((400, 0, 10, 10), 360, 288)
    with pytest.raises(ValueError, match="positive"):
        clip_roi((0, 0, 0, 10), 360, 288)
    pts = np.array([[100.0, 120.0], [140.0, 160.0], [np.nan, np.nan]])
    x0, y0, w, h = roi_around(pts, 360, 288, margin=0.25)
    assert x0 <= 100 - 10 and y0 <= 120 - 10 and x0 + w >= 140 + 10 and y0 + h >= 160 + 10
    assert roi_around(pts, 360, 288, margin=10.0) == (0, 0, 360, 288)


# ---------------------------------------------------------------------------------------------------------------
# DIS flow on synthetic motion


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_subpixel_translation_is_recovered(preset):
    t = np.array([1.3, -0.7], dtype=np.float32)
    a = texture()
    b = shifted(a, *t)
    cfg = FlowConfig(preset=preset)
    fwd, bwd = bidirectional_flow(a, b, cfg)
    assert fwd.shape == bwd.shape == (H, W, 2) and fwd.dtype == np.float32
    err_f = np.linalg.norm(fwd - t, axis=-1)[INNER]
    err_b = np.linalg.norm(bwd + t, axis=-1)[INNER]
    # medium refines variationally; balanced (the default) does not, ultrafast / fast stop at a coarser scale
    bound = 0.2 if preset == "medium" else 0.5
    assert err_f.max() < bound and err_b.max() < bound
    if preset == "medium":
        assert err_f.mean() < 0.08
    np.testing.assert_array_equal(dis_flow(a, b, cfg), fwd)
    mask = consistency_mask(fwd, bwd, cfg.fb_threshold_px)
    assert mask.shape == (H, W) and mask.dtype == bool
    assert mask[INNER].all()
    # right border: where p + f(p) leaves the image the check fails
    assert not mask[:, W - 1].any()


def test_identical_frames_give_zero_flow():
    a = texture(seed=4)
    fwd = dis_flow(a, a)
    assert np.abs(fwd).max() < 0.05


def test_flow_input_validation():
    a = texture()
    with pytest.raises(ValueError, match="differ in size"):
        dis_flow(a, a[:-1])
    with pytest.raises(ValueError, match="uint8"):
        dis_flow(a.astype(np.float32), a.astype(np.float32))
    with pytest.raises(ValueError, match="one channel"):
        dis_flow(a, a, FlowConfig(grayscale=False))
    gray = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY)
    assert dis_flow(gray, gray, FlowConfig(grayscale=False)).shape == (H, W, 2)
    with pytest.raises(ValueError, match="too small"):
        dis_flow(a[:4, :4], a[:4, :4])


def test_roi_flow_is_in_full_image_pixels():
    t = np.array([0.8, 1.1], dtype=np.float32)
    a = texture(seed=2)
    b = shifted(a, *t)
    roi = (40, 30, 100, 90)
    fwd, bwd = bidirectional_flow(a, b, roi=roi)
    assert fwd.shape == bwd.shape == (90, 100, 2)
    assert np.linalg.norm(fwd - t, axis=-1)[8:-8, 8:-8].max() < 0.2


def test_moving_occluder_fails_forward_backward_check():
    """A patch moving (+8, +6) over a background moving (+1, +0.5): background pixels it covers have no
    correspondence in the next frame, and the check rejects them; the open background keeps its flow."""
    bg, patch = texture(seed=1), texture(40, 40, seed=7)
    a = bg.copy()
    a[60:100, 60:100] = patch
    b = shifted(bg, 1.0, 0.5)
    b[66:106, 68:108] = patch
    fwd, bwd = bidirectional_flow(a, b, FlowConfig(preset="medium"))
    mask = consistency_mask(fwd, bwd, 1.0)
    covered = np.zeros((H, W), dtype=bool)   # background of frame a hidden under the patch in frame b
    covered[66:105, 67:107] = True
    covered[60:100, 60:100] = False
    assert covered.sum() > 300
    assert mask[covered].mean() < 0.4
    assert mask[120:150, 20:180].mean() > 0.95


def test_region_turning_dark_fails_forward_backward_check():
    """Content that vanishes (a mouth opening: a textured region turns dark) has no correspondence."""
    a = texture()
    b = shifted(a, 1.3, -0.7)
    b[60:100, 80:130] = 30
    fwd, bwd = bidirectional_flow(a, b)
    mask = consistency_mask(fwd, bwd, 1.0)
    assert mask[64:96, 84:126].mean() < 0.1
    assert mask[16:50, 16:-16].mean() > 0.95


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_arbitrarily_changed_region_fails_with_photometric_check(preset):
    """A region replaced by unrelated texture: DIS propagates smooth flow into it both ways, so the
    forward-backward check alone may pass it; the photometric check rejects it at every preset."""
    a = texture()
    b = shifted(a, 1.3, -0.7)
    b[60:100, 80:130] = texture(40, 50, seed=9)
    cfg = FlowConfig(preset=preset, photometric_threshold=10.0)
    fwd, bwd = bidirectional_flow(a, b, cfg)
    fmask, bmask = flow_masks(a, b, fwd, bwd, cfg)
    core = (slice(64, 96), slice(84, 126))
    assert fmask[core].mean() < 0.2
    assert bmask[core].mean() < 0.2
    assert fmask[16:50, 16:-16].mean() > 0.95
    fb_only, _ = flow_masks(a, b, fwd, bwd, FlowConfig(preset=preset))
    assert not (fmask & ~fb_only).any()   # the photometric check only removes pixels


def test_photometric_mask_on_exact_flow():
    a = cv2.cvtColor(texture(), cv2.COLOR_RGB2GRAY)
    b = np.roll(a, 2, axis=1)   # content moves +2 px in x, exactly
    flow = np.zeros((H, W, 2), np.float32)
    flow[..., 0] = 2.0
    ok = photometric_mask(a, b, flow, threshold=1.0, window=1)
    assert ok[:, : W - 2].all() and not ok[:, W - 2:].any()
    wrong = photometric_mask(a, b, np.zeros_like(flow), threshold=5.0, window=5)
    assert wrong[INNER].mean() < 0.2


# ---------------------------------------------------------------------------------------------------------------
# Forward-backward check and sampling on hand-made fields


def test_consistency_mask_hand_made():
    h, w = 6, 8
    fwd = np.zeros((h, w, 2), np.float32)
    fwd[..., 0] = 2.0
    bwd = np.zeros((h, w, 2), np.float32)
    bwd[..., 0] = -1.5
    m = consistency_mask(fwd, bwd, 1.0)   # |2 - 1.5| = 0.5 < 1
    assert m[:, : w - 2].all() and not m[:, w - 2:].any()   # x + 2 > 7 leaves the image
    assert not consistency_mask(fwd, bwd, 0.4).any()
    # the backward flow is sampled at p + f(p), bilinearly
    fwd[...] = 0.0
    fwd[..., 0] = 0.5
    bwd[...] = 0.0
    bwd[:, :, 0] = -np.arange(w, dtype=np.float32)[None, :]   # b(x) = -x: b(x + 0.5) = -x - 0.5
    m = consistency_mask(fwd, bwd, 0.1)
    assert m[:, 0].all() and not m[:, 1:].any()   # |0.5 - x - 0.5| = x
    fwd[2, 3] = np.nan
    assert not consistency_mask(fwd, bwd, 100.0)[2, 3]
    with pytest.raises(ValueError):
        consistency_mask(fwd, bwd[:-1], 1.0)


def test_sample_flow_bilinear_by_hand():
    flow = np.zeros((2, 3, 2), np.float32)
    flow[..., 0] = [[0.0, 1.0, 2.0], [4.0, 5.0, 6.0]]
    flow[..., 1] = [[1.0, -1.0, 0.0], [3.0, 3.0, 3.0]]
    pts = np.array([[0.25, 0.5], [1.0, 0.0], [2.0, 1.0], [1.5, 0.75]])
    disp, ok = sample_flow(flow, None, pts)
    assert ok.all() and disp.dtype == np.float32 and disp.shape == (4, 2)
    # (0.25, 0.5): x: 0.5 * (0.75*0 + 0.25*1) + 0.5 * (0.75*4 + 0.25*5) = 2.25;
    #              y: 0.5 * (0.75*1 + 0.25*-1) + 0.5 * 3 = 1.75
    np.testing.assert_allclose(disp[0], [2.25, 1.75], atol=1e-6)
    np.testing.assert_allclose(disp[1], [1.0, -1.0], atol=1e-6)
    np.testing.assert_allclose(disp[2], [6.0, 3.0], atol=1e-6)   # the last pixel, clamped neighbours
    # (1.5, 0.75): x: 0.25 * 1.5 + 0.75 * 5.5 = 4.5; y: 0.25 * -0.5 + 0.75 * 3 = 2.125
    np.testing.assert_allclose(disp[3], [4.5, 2.125], atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(coef=st.lists(st.floats(-3, 3), min_size=8, max_size=8),
       pts=st.lists(st.tuples(st.floats(0, 9), st.floats(0, 6)), min_size=1, max_size=20))
def test_sample_flow_reproduces_bilinear_fields(coef, pts):
    """Bilinear interpolation is exact on any field a + b x + c y + d x y."""
    h, w = 7, 10
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    c = np.asarray(coef)
    fx = c[0] + c[1] * xs + c[2] * ys + c[3] * xs * ys
    fy = c[4] + c[5] * xs + c[6] * ys + c[7] * xs * ys
    flow = np.stack([fx, fy], axis=-1)
    p = np.asarray(pts, dtype=np.float64)
    disp, ok = sample_flow(flow, np.ones((h, w), bool), p)
    assert ok.all()
    x, y = p[:, 0], p[:, 1]
    want = np.stack([c[0] + c[1] * x + c[2] * y + c[3] * x * y, c[4] + c[5] * x + c[6] * y + c[7] * x * y], axis=1)
    np.testing.assert_allclose(disp, want, atol=1e-4)


def test_sample_flow_validity():
    h, w = 5, 6
    flow = np.ones((h, w, 2), np.float32)
    valid = np.ones((h, w), bool)
    valid[2, 3] = False
    pts = np.array([
        [3.0, 2.0],      # on the invalid pixel
        [2.5, 1.5],      # its cell touches (3, 2)
        [3.9, 2.9],      # so does this one
        [1.2, 1.2],      # far from it
        [4.0, 3.0],      # the cell right-below: (4, 3), (5, 3), (4, 4), (5, 4): fine
        [-0.01, 1.0],    # outside, left
        [5.01, 1.0],     # outside, right
        [1.0, 4.5],      # outside, bottom
        [5.0, 4.0],      # the last pixel: inside
        [np.nan, 1.0],   # not a point
    ])
    disp, ok = sample_flow(flow, valid, pts)
    np.testing.assert_array_equal(ok, [False, False, False, True, True, False, False, False, True, False])
    np.testing.assert_array_equal(disp[~ok], 0.0)
    np.testing.assert_array_equal(disp[ok], 1.0)
    flow[1, 1] = np.nan
    _, ok = sample_flow(flow, None, np.array([[1.5, 1.5], [3.5, 3.5]]))
    np.testing.assert_array_equal(ok, [False, True])
    empty_disp, empty_ok = sample_flow(flow, valid, np.zeros((0, 2)))
    assert empty_disp.shape == (0, 2) and empty_ok.shape == (0,)
    with pytest.raises(ValueError):
        sample_flow(flow, valid, np.zeros((3, 3)))
    with pytest.raises(ValueError):
        sample_flow(flow, valid[:-1], pts)


# ---------------------------------------------------------------------------------------------------------------
# Per-utterance flow


POSITIONS = np.array([[0.0, 0.0], [1.25, -0.5], [2.0, 1.0], [0.5, 1.75], [-0.75, 0.25]])   # content offset per frame


def moving_frames(seed=3) -> np.ndarray:
    base = texture(seed=seed)
    return np.stack([shifted(base, *pos) for pos in POSITIONS])


@pytest.fixture(scope="module")
def field() -> FlowField:
    return estimate_optical_flow(moving_frames())


def _grid_points(lo=30.0, hi_x=W - 30.0, hi_y=H - 30.0, n=7):
    xs, ys = np.meshgrid(np.linspace(lo, hi_x, n) + 0.37, np.linspace(lo, hi_y, n) + 0.61)
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def test_track_flow_layout(field):
    assert field.n_frames == 5 and field.n_pairs == 4
    assert field.forward.shape == field.backward.shape == (4, H, W, 2)
    assert field.forward.dtype == np.float16
    assert field.forward_valid.shape == (4, H, W) and field.forward_valid.dtype == bool
    assert (field.roi, field.width, field.height) == ((0, 0, W, H), W, H)
    assert field.forward_flow(1).dtype == np.float32
    assert 0.9 < field.valid_fraction(1) <= 1.0
    for bad in (0, 5):
        with pytest.raises(IndexError):
            field.correspondences(bad, _grid_points())
    for bad in (-1, 4):
        with pytest.raises(IndexError):
            field.backward_correspondences(bad, _grid_points())


def test_track_flow_correspondences_per_pair(field):
    pts = _grid_points()
    for j in range(1, 5):
        disp, ok = field.correspondences(j, pts)
        assert ok.all()
        np.testing.assert_allclose(disp, np.broadcast_to(POSITIONS[j] - POSITIONS[j - 1], disp.shape), atol=0.2)
    for j in range(0, 4):
        disp, ok = field.backward_correspondences(j, pts)
        assert ok.all()
        np.testing.assert_allclose(disp, np.broadcast_to(POSITIONS[j] - POSITIONS[j + 1], disp.shape), atol=0.2)


@pytest.mark.parametrize("preset, bound", [("medium", 0.3), ("balanced", 0.35)])
def test_track_flow_correspondences_chain(preset, bound):
    """Following the flow frame to frame carries points along the pattern, and the backward flows bring them
    back: the forward and the backward pass of the tracker see the same motion. Without medium's variational
    refinement, balanced (the default) drifts further over the eight chained steps: 0.32 px at worst here, medium
    0.23 (one step, what L_flow uses: 0.07 px both)."""
    field = estimate_optical_flow(moving_frames(), FlowConfig(preset=preset))
    start = _grid_points()
    pts = start.copy()
    for j in range(1, 5):
        disp, ok = field.correspondences(j, pts)
        assert ok.all()
        pts = pts + disp
        np.testing.assert_allclose(pts, start + (POSITIONS[j] - POSITIONS[0]), atol=bound)
    for j in range(3, -1, -1):
        disp, ok = field.backward_correspondences(j, pts)
        assert ok.all()
        pts = pts + disp
    np.testing.assert_allclose(pts, start, atol=bound)


def test_track_flow_roi_matches_full_frame(field):
    frames = moving_frames()
    roi = (50, 40, 110, 80)
    cropped = estimate_optical_flow(list(frames), FlowConfig(storage_dtype="float32"), roi=roi)
    assert cropped.roi == roi and cropped.forward.shape == (4, 80, 110, 2)
    assert cropped.forward.dtype == np.float32
    assert cropped.nbytes < field.nbytes
    pts = _grid_points(lo=62.0, hi_x=145.0, hi_y=105.0, n=5)   # inside the ROI, away from its border
    outside = np.array([[20.0, 20.0], [49.5, 60.0], [170.0, 60.0], [100.0, 130.0]])
    for j in range(1, 5):
        disp, ok = cropped.correspondences(j, pts)
        full, full_ok = field.correspondences(j, pts)
        assert ok.all() and full_ok.all()
        np.testing.assert_allclose(disp, np.broadcast_to(POSITIONS[j] - POSITIONS[j - 1], disp.shape), atol=0.2)
        np.testing.assert_allclose(disp, full, atol=0.2)
        d_out, ok_out = cropped.correspondences(j, outside)
        assert not ok_out.any() and not d_out.any()


def test_track_flow_edge_cases():
    one = estimate_optical_flow(moving_frames()[:1])
    assert one.n_frames == 1 and one.n_pairs == 0
    with pytest.raises(ValueError, match="at least one frame"):
        estimate_optical_flow(np.zeros((0, H, W, 3), np.uint8))
    frames = list(moving_frames()[:2])
    frames[1] = frames[1][:-2]
    with pytest.raises(ValueError, match="frame 1"):
        estimate_optical_flow(frames)
    pts = torch.tensor(_grid_points(), requires_grad=True)   # torch points are accepted (detached)
    disp, ok = estimate_optical_flow(moving_frames()[:2]).correspondences(1, pts)
    assert ok.all() and disp.shape == (49, 2)


# ---------------------------------------------------------------------------------------------------------------
# Eq. 6


def test_flow_loss_by_hand():
    cur = torch.tensor([[1.0, 2.0], [3.0, 4.0], [0.0, 0.0]], requires_grad=True)
    prev = torch.tensor([[0.0, 0.0], [1.0, 1.0], [5.0, 5.0]])
    u = np.array([[0.5, 1.0], [1.0, 1.0], [np.nan, np.nan]], dtype=np.float32)   # the invalid one holds NaN
    valid = np.array([True, True, False])
    loss = flow_loss(cur, prev, u, valid)
    # k=0: (1 - 0.5)^2 + (2 - 1)^2 = 1.25; k=1: (3 - 2)^2 + (4 - 2)^2 = 5; mean over the 2 valid = 3.125
    assert loss.shape == ()
    assert loss.item() == pytest.approx(3.125)
    loss.backward()
    # d/dcur_k = 2 (cur_k - prev_k - u_k) / |K|
    np.testing.assert_allclose(cur.grad.numpy(), [[0.5, 1.0], [1.0, 2.0], [0.0, 0.0]], atol=1e-6)


def test_flow_loss_zero_at_exact_correspondence():
    g = torch.Generator().manual_seed(0)
    prev = torch.rand(50, 2, generator=g) * 300
    u = torch.randn(50, 2, generator=g)
    cur = (prev + u).clone().requires_grad_(True)
    loss = flow_loss(cur, prev, u, torch.ones(50, dtype=torch.bool))
    assert loss.item() == 0.0
    loss.backward()
    assert torch.count_nonzero(cur.grad) == 0


def test_flow_loss_masks_invalid_points():
    g = torch.Generator().manual_seed(1)
    cur, prev, u = (torch.randn(20, 2, generator=g) for _ in range(3))
    valid = torch.rand(20, generator=g) > 0.4
    base = flow_loss(cur, prev, u, valid)
    u2 = u.clone()
    u2[~valid] = 1e6   # whatever the invalid entries hold
    assert flow_loss(cur, prev, u2, valid).item() == pytest.approx(base.item())
    want = ((cur - prev - u)[valid] ** 2).sum(dim=1).mean()
    assert base.item() == pytest.approx(want.item(), rel=1e-6)


def test_flow_loss_nothing_valid_is_zero_with_gradient():
    cur = torch.randn(6, 2, requires_grad=True)
    loss = flow_loss(cur, torch.zeros(6, 2), torch.full((6, 2), float("nan")), torch.zeros(6, dtype=torch.bool))
    assert loss.item() == 0.0 and loss.requires_grad
    loss.backward()
    assert torch.equal(cur.grad, torch.zeros(6, 2))


def test_flow_loss_gradcheck():
    g = torch.Generator().manual_seed(2)
    cur = torch.randn(4, 2, dtype=torch.float64, generator=g, requires_grad=True)
    prev = torch.randn(4, 2, dtype=torch.float64, generator=g, requires_grad=True)
    u = torch.randn(4, 2, dtype=torch.float64, generator=g)
    valid = torch.tensor([True, False, True, True])
    assert torch.autograd.gradcheck(lambda c, p: flow_loss(c, p, u, valid), (cur, prev))
    batched_cur = torch.randn(3, 4, 2, dtype=torch.float64, generator=g, requires_grad=True)
    bvalid = torch.tensor([[True, False, True, True], [False] * 4, [True] * 4])
    assert torch.autograd.gradcheck(lambda c: flow_loss(c, prev.detach().expand(3, 4, 2),
                                                        u.expand(3, 4, 2), bvalid), (batched_cur,))


def test_flow_loss_batched_matches_per_frame():
    g = torch.Generator().manual_seed(3)
    cur, prev, u = (torch.randn(5, 30, 2, generator=g) for _ in range(3))
    valid = torch.rand(5, 30, generator=g) > 0.3
    valid[2] = False
    losses = flow_loss(cur, prev, u, valid)
    assert losses.shape == (5,)
    for t in range(5):
        assert losses[t].item() == pytest.approx(flow_loss(cur[t], prev[t], u[t], valid[t]).item(), rel=1e-6)
    assert losses[2].item() == 0.0


def test_flow_loss_shape_errors():
    cur = torch.zeros(4, 2)
    with pytest.raises(ValueError, match="proj_prev"):
        flow_loss(cur, torch.zeros(3, 2), torch.zeros(4, 2), torch.ones(4, dtype=torch.bool))
    with pytest.raises(ValueError, match="displacement"):
        flow_loss(cur, torch.zeros(4, 2), torch.zeros(4, 3), torch.ones(4, dtype=torch.bool))
    with pytest.raises(ValueError, match="valid"):
        flow_loss(cur, torch.zeros(4, 2), torch.zeros(4, 2), torch.ones(5, dtype=torch.bool))
    with pytest.raises(TypeError):
        flow_loss(np.zeros((4, 2)), np.zeros((4, 2)), np.zeros((4, 2)), np.ones(4, bool))


def test_flow_loss_drives_projections_to_flow_targets(field):
    """End to end: correspondences from the tracked flow, then minimising Eq. 6 moves the current projections to
    where the flow carries the previous ones."""
    prev = _grid_points()
    disp, ok = field.correspondences(2, prev)
    cur = torch.tensor(prev, dtype=torch.float32, requires_grad=True)
    opt = torch.optim.Adam([cur], lr=0.1)
    for _ in range(200):
        opt.zero_grad()
        loss = flow_loss(cur, prev, disp, ok)
        loss.backward()
        opt.step()
    moved = cur.detach().numpy() - prev
    np.testing.assert_allclose(moved, np.broadcast_to(POSITIONS[2] - POSITIONS[1], moved.shape), atol=0.25)


# ---------------------------------------------------------------------------------------------------------------
# A real GRID clip


@pytest.fixture(scope="module")
def grid_pair() -> np.ndarray:
    assert GRID_CLIP.is_file(), f"shared test data missing: {GRID_CLIP}"
    frames = read_video_frames(GRID_CLIP, start=30, count=2)
    assert frames.shape == (2, 288, 360, 3)
    return frames


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_grid_consecutive_frames(grid_pair, preset):
    cfg = FlowConfig(preset=preset)
    fwd, bwd = bidirectional_flow(grid_pair[0], grid_pair[1], cfg)
    mask = consistency_mask(fwd, bwd, cfg.fb_threshold_px)
    x0, y0, w, h = GRID_FACE
    face = (slice(y0, y0 + h), slice(x0, x0 + w))
    assert mask[face].mean() > 0.5
    assert np.median(np.linalg.norm(fwd[face], axis=-1)) < 2.0
    # the same on the face region only
    ff = estimate_optical_flow(grid_pair, cfg, roi=GRID_FACE)
    assert ff.valid_fraction(1) > 0.5
    assert np.median(np.linalg.norm(ff.forward_flow(1), axis=-1)) < 2.0
    # landmarks-like points on the face mostly find a correspondence
    ys, xs = np.mgrid[y0 + 20:y0 + h - 20:10, x0 + 20:x0 + w - 20:10]
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64) + 0.5
    disp, ok = ff.correspondences(1, pts)
    assert ok.mean() > 0.5
    assert np.median(np.linalg.norm(disp[ok], axis=1)) < 2.0
    photo = estimate_optical_flow(grid_pair, FlowConfig(preset=preset, photometric_threshold=10.0), roi=GRID_FACE)
    assert photo.valid_fraction(1) > 0.5


# ---------------------------------------------------------------------------------------------------------------
# Large frames: the ROI shrunk to FlowConfig.max_roi_px, frames taken one at a time


def test_large_roi_is_shrunk_and_queries_stay_in_image_pixels():
    """A 960 x 800 texture moving by whole and fractional pixels: with the ROI shrunk to 240 px the flows take
    1/16 of the memory and the correspondences still give the motion in image pixels."""
    big = texture(800, 960, seed=5, sigma=8.0)
    moves = np.array([[0.0, 0.0], [4.0, -2.5], [9.5, 1.0]])
    frames = [shifted(big, *m) for m in moves]
    full = estimate_optical_flow(frames, FlowConfig(max_roi_px=None))
    small = estimate_optical_flow(frames, FlowConfig(max_roi_px=240))
    assert full.scale == 1.0 and small.scale == pytest.approx(0.25)
    assert small.forward.shape == (2, 200, 240, 2) and small.nbytes * 16 == full.nbytes
    pts = np.stack(np.meshgrid(np.linspace(150, 800, 6) + 0.3, np.linspace(150, 650, 5) + 0.7), -1).reshape(-1, 2)
    for j in (1, 2):
        want = moves[j] - moves[j - 1]
        u, ok = small.correspondences(j, pts)
        assert ok.mean() > 0.9
        assert np.abs(u[ok] - want).max() < 0.5
        b, okb = small.backward_correspondences(j - 1, pts)
        assert np.abs(b[okb] + want).max() < 0.5


def test_all_correspondences_at_once_equal_the_per_frame_queries(field):
    """The fast solver refreshes its correspondences with one `all_correspondences` call per clip; it is exactly
    `correspondences(j, points[j - 1])` for every j, inside the ROI and out, NaN points, masked pixels, on a field
    shrunk to max_roi_px and one at native size, and refuses points of another number of pairs."""
    rng = np.random.default_rng(4)
    big = texture(400, 480, seed=6, sigma=8.0)
    frames = [shifted(big, *m) for m in ((0.0, 0.0), (3.0, -1.5), (5.5, 0.5), (4.0, 2.0))]
    shrunk = estimate_optical_flow(frames, FlowConfig(max_roi_px=120), roi=(40, 30, 380, 300))
    assert shrunk.scale < 1.0
    for flow in (field, shrunk):
        pts = np.stack([rng.uniform(-20, flow.width + 20, (flow.n_pairs, 60)),
                        rng.uniform(-20, flow.height + 20, (flow.n_pairs, 60))], axis=-1)
        pts[0, 3] = np.nan
        disp, ok = flow.all_correspondences(pts)
        assert disp.dtype == np.float32 and ok.shape == (flow.n_pairs, 60)
        assert 0 < ok.sum() < ok.size                  # some outside the ROI or masked
        for j in range(1, flow.n_frames):
            one, one_ok = flow.correspondences(j, pts[j - 1])
            np.testing.assert_array_equal(disp[j - 1], one)
            np.testing.assert_array_equal(ok[j - 1], one_ok)
        with pytest.raises(ValueError, match="one row of points per frame pair"):
            flow.all_correspondences(pts[:-1])


def test_frames_may_come_one_at_a_time():
    frames = moving_frames()
    whole = estimate_optical_flow(frames)
    streamed = estimate_optical_flow(f for f in frames)
    np.testing.assert_array_equal(streamed.forward, whole.forward)
    np.testing.assert_array_equal(streamed.backward_valid, whole.backward_valid)
    with pytest.raises(ValueError, match="at least one frame"):
        estimate_optical_flow(iter(()))


def test_a_crop_of_a_region_keeps_the_region_s_resolution():
    """`scale_roi`: the flow of a part of a face is sampled at the shrink that fits the whole face into max_roi_px,
    not the larger one the part alone would get, and still finds the motion there."""
    big = texture(400, 480, seed=8, sigma=8.0)
    frames = [shifted(big, *m) for m in ((0.0, 0.0), (4.0, -2.0))]
    face, part = (40, 30, 380, 300), (100, 150, 200, 120)
    config = FlowConfig(max_roi_px=190)
    whole = estimate_optical_flow(frames, config, roi=face)
    crop = estimate_optical_flow(frames, config, roi=part, scale_roi=face)
    alone = estimate_optical_flow(frames, config, roi=part)
    assert crop.scale == whole.scale == pytest.approx(0.5) and alone.scale == pytest.approx(190 / 200)
    assert crop.forward.shape[1:3] == (60, 100)
    pts = np.array([[150.0, 180.0], [250.0, 220.0]])
    disp, ok = crop.correspondences(1, pts)
    assert ok.all() and np.abs(disp - [4.0, -2.0]).max() < 0.5


def test_flows_are_stored_with_numpy_s_float16_values_and_a_crop_s_gray_is_the_gray_s_crop():
    """The stored field equals one computed the plain way (whole frames to gray, then cropped, shrunk, DIS both
    ways, NumPy's float16): the vectorised float16 conversion rounds as NumPy does, down to the last bit, also at
    the edges of float16's range."""
    from visemeflow.tracking import optical_flow

    edges = np.array([0.0, -0.0, 1e-8, 6e-8, -3e-5, 6.1e-5, 0.33333334, 2047.5, 65504.0, 65520.0, -1e6, 1e6],
                     np.float32)
    flow = np.concatenate([edges, np.random.default_rng(0).normal(0, 20, 10 * 12 * 2 - len(edges))
                           .astype(np.float32)]).reshape(10, 12, 2)
    np.testing.assert_array_equal(optical_flow.as_storage(flow, np.float16).view(np.uint16),
                                  flow.astype(np.float16).view(np.uint16))
    assert optical_flow.as_storage(flow, np.float32) is flow

    rgb = [shifted(texture(120, 160, seed=3), 1.5 * k, -0.5 * k) for k in range(3)]   # colour: gray matters
    roi, scale_roi = (30, 20, 90, 70), (10, 5, 140, 110)
    config = FlowConfig(preset="medium", max_roi_px=100)   # an OpenCV preset as it comes (balanced: test_config_...)
    field = estimate_optical_flow(rgb, config, roi=roi, scale_roi=scale_roi)
    x0, y0, w, h = roi
    s = 100 / 140
    crops = [cv2.resize(cv2.cvtColor(f, cv2.COLOR_RGB2GRAY)[y0:y0 + h, x0:x0 + w], (round(w * s), round(h * s)),
                        interpolation=cv2.INTER_AREA) for f in rgb]
    dis = cv2.DISOpticalFlow_create(config.cv_preset)
    for i in range(2):
        np.testing.assert_array_equal(field.forward[i], dis.calc(crops[i], crops[i + 1], None).astype(np.float16))
        np.testing.assert_array_equal(field.backward[i], dis.calc(crops[i + 1], crops[i], None).astype(np.float16))


def test_the_backward_masks_are_made_on_first_use_from_the_stored_flows():
    """Without the photometric check the backward masks wait for a solver that asks (the fast solver never does):
    made then by the forward-backward check on the stored float16 flows, they are the eager masks of the float32
    flows but for pixels within float16's rounding of the threshold."""
    frames = moving_frames()
    field = estimate_optical_flow(frames)
    assert field.backward_mask is None
    assert field.nbytes == 4 * H * W * (2 * 2 * 2 + 1)
    lazy = field.backward_valid
    assert field.backward_mask is lazy and field.nbytes == 4 * H * W * (2 * 2 * 2 + 2)
    assert lazy.shape == (4, H, W) and lazy.dtype == bool
    differ = 0
    for i in range(4):
        fwd, bwd = bidirectional_flow(frames[i], frames[i + 1])
        np.testing.assert_array_equal(field.forward_valid[i], consistency_mask(fwd, bwd, 1.0))
        eager = consistency_mask(bwd, fwd, 1.0)
        differ += int((eager != lazy[i]).sum())
    assert differ <= 0.001 * lazy.size
    # with the photometric check both masks are made at once, from the frames
    photo = estimate_optical_flow(frames, FlowConfig(photometric_threshold=10.0))
    assert photo.backward_mask is not None and photo.backward_valid is photo.backward_mask


def test_many_flows_sampled_at_once_equal_each_point_sampled_by_hand():
    """`FlowField.all_correspondences`' sampler (neighbours read by flat index) against bilinear interpolation
    written out point by point: the same values and validity, at the last row and column, outside, at NaN."""
    from visemeflow.tracking.optical_flow import _sample_flows

    rng = np.random.default_rng(5)
    p, h, w, n = 3, 7, 9, 40
    flows = rng.normal(0, 3, (p, h, w, 2)).astype(np.float16)
    flows[1, 2, 3, 0] = np.nan
    valid = rng.random((p, h, w)) > 0.2
    pts = np.stack([rng.uniform(-1, w, (p, n)), rng.uniform(-1, h, (p, n))], axis=2)
    pts[0, :4] = [(w - 1, h - 1), (w - 1, 2.5), (3.5, h - 1), (0, 0)]
    pts[2, 0] = (np.nan, 1.0)
    pts[2, 1] = (3.2, 2.6)                               # next to the NaN flow of pair 1's neighbour, not pair 2's
    out, ok = _sample_flows(flows, valid, pts)
    for i in range(p):
        for k in range(n):
            x, y = pts[i, k]
            if not (0 <= x <= w - 1 and 0 <= y <= h - 1):
                assert not ok[i, k] and (out[i, k] == 0).all()
                continue
            x0, y0 = int(np.floor(x)), int(np.floor(y))
            x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
            ax, ay = x - x0, y - y0
            c = [flows[i, yy, xx].astype(np.float64) for yy, xx in ((y0, x0), (y0, x1), (y1, x0), (y1, x1))]
            value = (1 - ay) * ((1 - ax) * c[0] + ax * c[1]) + ay * ((1 - ax) * c[2] + ax * c[3])
            good = bool(np.isfinite(value).all() and valid[i, y0, x0] and valid[i, y0, x1]
                        and valid[i, y1, x0] and valid[i, y1, x1])
            assert ok[i, k] == good
            np.testing.assert_array_equal(out[i, k], value.astype(np.float32) if good else np.zeros(2, np.float32))
    assert ok.any() and not ok.all()
