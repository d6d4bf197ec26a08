"""Keyframe masks onto the patch grid (masks_to_soft) and back to pixels (upsample_labels)."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from services.tracker.propagation import masks_to_soft, upsample_ids, upsample_labels  # noqa: E402


def test_area_fractions_hand_case():
    # 4x4 image, 2x2 grid: mask 0 fills the top-left cell and one pixel of the top-right one.
    m = np.zeros((1, 4, 4), bool)
    m[0, :2, :2] = True
    m[0, 0, 2] = True
    y = masks_to_soft(m, 2, 2)
    assert y.shape == (2, 2, 2) and y.dtype == torch.float32
    np.testing.assert_allclose(y[0, 0].numpy(), [0.0, 1.0])
    np.testing.assert_allclose(y[0, 1].numpy(), [0.75, 0.25])
    np.testing.assert_allclose(y[1].numpy(), [[1.0, 0.0], [1.0, 0.0]])


def test_earlier_masks_win_overlaps_and_slots_follow_order():
    m = np.zeros((2, 4, 4), bool)
    m[0, :, :2] = True
    m[1, :, 1:3] = True  # overlaps mask 0 in column 1
    y = masks_to_soft(m, 1, 4)
    np.testing.assert_allclose(y[0].numpy(), [[0, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 0]])
    as_list = masks_to_soft([m[0], m[1]], 1, 4)
    assert torch.equal(as_list, y)


def test_label_image_and_slot_count():
    labels = np.array([[0, 0, 2, 2], [-1, 1, 2, 2]], np.int32)
    y = masks_to_soft(labels, 1, 2, num_slots=5)
    assert y.shape == (1, 2, 5)
    np.testing.assert_allclose(y[0, 0].numpy(), [0.75, 0.25, 0, 0, 0])
    np.testing.assert_allclose(y[0, 1].numpy(), [0, 0, 1, 0, 0])
    hard = masks_to_soft(labels, 1, 2, hard=True)
    np.testing.assert_allclose(hard[0].numpy(), [[1, 0, 0], [0, 0, 1]])
    with pytest.raises(ValueError, match="num_slots"):
        masks_to_soft(labels, 1, 2, num_slots=2)
    with pytest.raises(ValueError):
        masks_to_soft(np.zeros((4, 4), np.float32), 1, 1)


def test_no_masks_is_all_background():
    y = masks_to_soft(np.zeros((0, 8, 8), bool), 2, 2)
    assert torch.equal(y, torch.ones(2, 2, 1))


def test_cells_partition_uneven_sizes():
    """Patch cells tile the image as floor(y * h / H): fractions sum to 1 per cell."""
    rng = np.random.default_rng(0)
    m = rng.random((3, 37, 53)) > 0.6
    y = masks_to_soft(torch.from_numpy(m), 5, 7)
    assert torch.allclose(y.sum(-1), torch.ones(5, 7))


@pytest.mark.parametrize(("h", "w", "H", "W"), [(4, 7, 64, 112), (45, 79, 680, 1200), (5, 3, 17, 23), (8, 8, 4, 4)])
def test_upsample_matches_torch_bilinear(h, w, H, W):
    gen = torch.Generator().manual_seed(h * w)
    y = torch.softmax(3 * torch.randn(h, w, 6, generator=gen), -1)
    ours = upsample_labels(y, H, W, chunk_rows=7)
    ref = torch.nn.functional.interpolate(y.permute(2, 0, 1)[None], size=(H, W), mode="bilinear", align_corners=False)
    expected = ref[0].argmax(0).to(torch.int32)
    assert ours.dtype == torch.int32 and ours.shape == (H, W)
    # Identical up to float ties between channels.
    assert (ours != expected).float().mean() < 1e-3


def _sparse_labels(h: int, w: int, n_slots: int, gen: torch.Generator) -> torch.Tensor:
    """Distributions as propagation leaves them: a few slots per patch, the others exactly 0,
    plus patches with no mass at all (a softmax over nothing, zeroed) and exact ties."""
    y = torch.softmax(3 * torch.randn(h, w, n_slots, generator=gen), -1)
    keep = torch.rand(h, w, n_slots, generator=gen) < 0.1
    keep[..., 0] |= torch.rand(h, w, generator=gen) < 0.5
    y = y * keep
    y = y / y.sum(-1, keepdim=True).clamp_min(1e-12)
    y[0, 0] = 0.0
    y[h // 2, w // 2] = 0.0
    y[h - 1, w - 1, :2] = 0.5
    y[h - 1, w - 1, 2:] = 0.0
    return y


@pytest.mark.parametrize(("h", "w", "H", "W", "n_slots"), [
    (48, 84, 680, 1200, 40), (48, 64, 240, 320, 30), (4, 7, 64, 112, 6), (5, 3, 17, 23, 3), (8, 8, 4, 4, 5), (45, 79, 97, 131, 12), (1, 1, 9, 9, 2),
])  # fmt: skip
@pytest.mark.parametrize("kind", ["dense", "sparse"])
def test_numba_upsample_equals_the_torch_path_bit_for_bit(h, w, H, W, n_slots, kind):
    """The CPU kernel (cells, slots with mass only) and the torch path give the same slots,
    ties and empty patches included."""
    from services.tracker import upsample_numba

    if upsample_numba.numba is None:
        pytest.skip("numba is not installed")
    gen = torch.Generator().manual_seed(h * w + n_slots)
    if kind == "dense":
        y = torch.softmax(3 * torch.randn(h, w, n_slots, generator=gen), -1)
    else:
        y = _sparse_labels(h, w, n_slots, gen)
    fast = upsample_labels(y, H, W)
    slow = upsample_labels(y, H, W, use_numba=False)
    assert fast.dtype == slow.dtype == torch.int32 and fast.shape == slow.shape == (H, W)
    assert torch.equal(fast, slow)


@pytest.mark.parametrize(("h", "w", "H", "W", "n_slots"), [(48, 85, 680, 1200, 30), (5, 3, 17, 23, 3), (8, 8, 4, 4, 5)])
@pytest.mark.parametrize("kernel", [True, False])
def test_track_ids_and_the_ids_present_come_from_the_kernel_as_from_the_slots(h, w, H, W, n_slots, kernel, monkeypatch):
    """``upsample_ids``: the slot image through the slot -> track table, and the ids in it,
    on both paths (the kernel marks the slots it writes; the torch path counts)."""
    from services.tracker import upsample_numba

    if not kernel:
        monkeypatch.setattr(upsample_numba, "numba", None)
    gen = torch.Generator().manual_seed(h + w + n_slots)
    y = _sparse_labels(h, w, n_slots, gen)
    y[..., n_slots - 1] = 0.0  # a track no pixel takes
    tracks = [int(t) for t in 3 * torch.randperm(50, generator=gen)[: n_slots - 1] + 7]
    slots = upsample_labels(y, H, W, use_numba=False).numpy()
    want = np.asarray([-1, *tracks], np.int32)[slots]
    ids, present = upsample_ids(y, H, W, tracks)
    assert ids.dtype == np.int32 and np.array_equal(ids, want)
    assert present == sorted(t for t in np.unique(want).tolist() if t >= 0)
    assert tracks[-1] not in present
    with pytest.raises(ValueError, match="label slots"):
        upsample_ids(y, H, W, tracks[:1])


def test_upsample_of_one_hot_blocks_is_exact_inside_blocks():
    slots = torch.zeros(6, 8, dtype=torch.long)
    slots[1:5, 2:6] = 3
    y = torch.nn.functional.one_hot(slots, 4).float()
    out = upsample_labels(y, 96, 128)
    assert out[16 * 1 + 8 : 16 * 5 - 8, 16 * 2 + 8 : 16 * 6 - 8].eq(3).all()
    assert out[:8].eq(0).all() and out[:, :24].eq(0).all()


def test_confidence_is_the_upsampled_peak_probability():
    from services.tracker.propagation import upsample_confidence

    soft = torch.zeros(2, 2, 3)
    soft[0, 0] = torch.tensor([0.0, 1.0, 0.0])
    soft[0, 1] = torch.tensor([0.0, 1.0, 0.0])
    soft[1] = torch.tensor([0.2, 0.4, 0.4])  # a bottom row where two tracks tie
    conf = upsample_confidence(soft, 8, 8)
    assert conf.shape == (8, 8) and conf.dtype == np.uint8
    assert (conf[:2] == 255).all() and (conf[-2:] == round(0.4 * 255)).all()
    assert (np.diff(conf[:, 0].astype(int)) <= 0).all()  # falls off across the border
