"""Classical dense features: grid and norm contract, discrimination, speed, and propagation
keeping object identity on a synthetic indoor scene seen by a moving camera."""

from __future__ import annotations

import time

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from services.tracker.propagation import LabelPropagator, masks_to_soft, upsample_labels  # noqa: E402
from shared.config.tracker import PropagationConfig  # noqa: E402
from shared.perception.features import make_dense_features  # noqa: E402
from shared.perception.features.config import dense_features_config  # noqa: E402

FOCAL = 300.0

# (centre x, centre y, width, height) in pixels at camera x = 0, depth m, RGB, texture.
OBJECTS = [
    (70, 100, 80, 90, 1.6, (200, 40, 40), "flat"),
    (170, 90, 70, 110, 2.6, (200, 50, 45), "stripes"),  # same red as the first, farther, striped
    (250, 170, 90, 60, 2.0, (40, 90, 190), "checker"),
    (150, 190, 110, 40, 1.4, (220, 200, 60), "noise"),
    (270, 60, 60, 60, 3.0, (60, 150, 70), "flat"),
]
WALL = (4.0, (190, 180, 160))
FLOOR_ROW = 200


def render(cam_x: float, height: int = 240, width: int = 320, seed: int = 0):
    """RGB, depth (m) and instance slots (0 = background, i + 1 = object i) for a camera moved
    cam_x metres to the right: each object shifts by FOCAL * cam_x / depth pixels."""
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:height, 0:width]
    rgb = np.empty((height, width, 3), np.float32)
    rgb[:] = WALL[1]
    depth = np.full((height, width), WALL[0], np.float32)
    floor = ys >= FLOOR_ROW
    rgb[floor] = (120, 100, 80)
    depth[floor] = (2.0 + 2.0 * (height - ys[floor]) / (height - FLOOR_ROW)).astype(np.float32)
    slots = np.zeros((height, width), np.int32)
    tex = np.random.default_rng(99).random((256, 256)).astype(np.float32)
    order = sorted(range(len(OBJECTS)), key=lambda i: -OBJECTS[i][4])  # far to near
    for i in order:
        cx, cy, w, h, d, colour, texture = OBJECTS[i]
        cx = cx - FOCAL * cam_x / d
        inside = (np.abs(xs - cx) <= w / 2) & (np.abs(ys - cy) <= h / 2)
        u = (xs - (cx - w / 2)).astype(np.int64)
        v = (ys - (cy - h / 2)).astype(np.int64)
        shade = np.ones((height, width), np.float32)
        if texture == "stripes":
            shade = 0.75 + 0.25 * np.sign(np.sin(u * np.pi / 6))
        elif texture == "checker":
            shade = np.where(((u // 10) + (v // 10)) % 2 == 0, 1.0, 0.55)
        elif texture == "noise":
            shade = 0.7 + 0.5 * tex[v % 256, u % 256]
        rgb[inside] = np.asarray(colour, np.float32) * shade[inside, None]
        depth[inside] = d
        slots[inside] = i + 1
    rgb += rng.normal(0, 3, rgb.shape)
    return np.clip(rgb, 0, 255).astype(np.uint8), depth, slots


@pytest.fixture(scope="module")
def classical():
    return make_dense_features(dense_features_config(backend="classical", short_side=240))


def test_contract(classical):
    rgb, depth, _ = render(0.0)
    out = classical(rgb, depth)
    assert classical.name == "classical" and classical.patch_size == 16
    assert tuple(out.shape) == (15, 20, classical.dim) == (*classical.grid_shape(240, 320), classical.dim)
    assert out.dtype == torch.float32
    assert torch.allclose(out.norm(dim=-1), torch.ones(15, 20), atol=1e-5)
    no_depth = classical(rgb)
    assert tuple(no_depth.shape) == tuple(out.shape) and torch.isfinite(no_depth).all()
    # Resizing follows the shared rule: 480x640 at short side 240 -> the same 15x20 grid.
    big = np.repeat(np.repeat(rgb, 2, 0), 2, 1)
    assert tuple(classical(big, np.repeat(np.repeat(depth, 2, 0), 2, 1)).shape) == tuple(out.shape)


def test_bad_frames_raise(classical):
    with pytest.raises(ValueError, match="uint8"):
        classical(np.zeros((32, 32, 3), np.float32))
    with pytest.raises(ValueError, match="depth_m"):
        classical(np.zeros((32, 32, 3), np.uint8), np.zeros((16, 16), np.float32))


def test_same_object_patches_are_more_similar(classical):
    rgb, depth, slots = render(0.0)
    feats = classical(rgb, depth).reshape(-1, classical.dim)
    cells = masks_to_soft(slots, 15, 20).reshape(-1, len(OBJECTS) + 1)
    pure = cells.max(-1).values > 0.99  # patches wholly inside one object (or background)
    owner = cells.argmax(-1)
    sim = feats @ feats.T
    for i in range(1, len(OBJECTS) + 1):
        mine = pure & (owner == i)
        assert mine.sum() >= 2
        within = sim[mine][:, mine].mean()
        for j in range(len(OBJECTS) + 1):
            other = pure & (owner == j)
            if j == i or other.sum() == 0:
                continue
            between = sim[mine][:, other].mean()
            assert within > between + 0.1, (i, j, float(within), float(between))


def test_depth_separates_same_colour_flat_surfaces(classical):
    rgb = np.full((64, 64, 3), 128, np.uint8)
    depth = np.full((64, 64), 1.0, np.float32)
    depth[:, 32:] = 3.0
    f = classical(rgb, depth)
    assert f.shape[:2] == (15, 15)
    assert (f[:, 0] * f[:, -1]).sum(-1).max() < 0.5  # near half vs far half
    assert (f[:, 0] * f[:, 1]).sum(-1).min() > 0.999  # same surface


def test_fast_enough():
    """Budget from the design: < 30 ms at 320x240 (short side 240), < 150 ms at 640x480 (480)."""
    rng = np.random.default_rng(0)
    for (height, width, short), budget in [((240, 320, 240), 0.030), ((480, 640, 480), 0.150)]:
        feats = make_dense_features(dense_features_config(backend="classical", short_side=short))
        rgb = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
        depth = rng.uniform(0.5, 5.0, (height, width)).astype(np.float32)
        feats(rgb, depth)
        best = float("inf")
        for _ in range(7):
            t0 = time.perf_counter()
            feats(rgb, depth)
            best = min(best, time.perf_counter() - t0)
        assert best < budget, (height, width, best)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def test_propagation_keeps_identity_on_a_moving_camera(classical):
    """Keyframe labels from ground truth, then 12 frames propagated with eq. 1 as the camera
    slides 0.6 m (objects move 40-110 px, with parallax and occlusion changes)."""
    rgb, depth, slots = render(0.0)
    prop = LabelPropagator(PropagationConfig())
    prop.reset(classical(rgb, depth), masks_to_soft(slots, 15, 20, num_slots=len(OBJECTS) + 1))
    for step in range(1, 13):
        rgb, depth, slots = render(0.05 * step, seed=step)
        y = prop.step(classical(rgb, depth))
    pred = upsample_labels(y, 240, 320).numpy()
    ious = [iou(pred == i, slots == i) for i in range(1, len(OBJECTS) + 1)]
    assert min(ious) > 0.5, ious
    assert np.mean(ious) > 0.65, ious


def test_appearance_channels_do_not_depend_on_depth():
    """Mask prototypes (eq. 2) use the first ``appearance_dims`` channels only: the same
    colours seen at another distance or slant give the same appearance, not the same depth
    block."""
    from services.tracker.core import appearance

    feats = make_dense_features(dense_features_config(backend="classical", short_side=240, patch_size=8))
    rgb, depth, _ = render(0.0)
    near = feats(rgb, depth).numpy()
    slanted = depth * np.linspace(0.6, 1.4, depth.shape[1], dtype=np.float32)[None, :]
    far = feats(rgb, slanted).numpy()
    assert feats.appearance_dims < feats.dim
    assert np.abs(near - far).max() > 0.05  # the full descriptor sees the change
    a, b = appearance(near, feats.appearance_dims), appearance(far, feats.appearance_dims)
    assert a.shape[-1] == feats.appearance_dims
    np.testing.assert_allclose(np.linalg.norm(a, axis=-1), 1.0, atol=1e-5)
    np.testing.assert_allclose(a, b, atol=1e-5)


@pytest.mark.parametrize("size", [(240, 320), (680, 1200), (123, 77)])
def test_the_numba_passes_give_the_numpy_features_bit_for_bit(size):
    """``use_numba``: the per-pixel passes in kernels, the per-patch formulas shared; every sum
    in numpy's order and precision, so the features are the same to the bit (missing, NaN and
    infinite depth, an edge-on depth step, a frame without depth and flat colour included)."""
    from shared.perception.features import classical_numba
    from shared.perception.features.classical import ClassicalFeatures

    if not classical_numba.available():
        pytest.skip("numba is not installed")
    height, width = size
    rgb, depth, _ = render(0.1, 240, 320, seed=3)
    if (height, width) != (240, 320):  # the scene at another size, as a camera of that size sees it
        ys = np.arange(height) * 240 // height
        xs = np.arange(width) * 320 // width
        rgb, depth = np.ascontiguousarray(rgb[ys[:, None], xs[None, :]]), np.ascontiguousarray(depth[ys[:, None], xs[None, :]])
    depth = depth.copy()
    depth[:20, :30] = 0.0
    depth[30:40, 50:60] = np.nan
    depth[45, 70:90] = np.inf
    rgb[-25:, -25:] = 128
    fast, slow = ClassicalFeatures(240, 5, use_numba=True), ClassicalFeatures(240, 5, use_numba=False)
    for d in (depth, None, np.zeros_like(depth)):
        a, b = fast(rgb, d).numpy(), slow(rgb, d).numpy()
        assert a.shape == b.shape and a.dtype == b.dtype == np.float32
        assert np.array_equal(a, b)
