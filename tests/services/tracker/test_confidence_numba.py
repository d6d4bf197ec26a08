"""The numba kernel of ``upsample_confidence`` (services/tracker/upsample_numba.py) against
torch's bilinear interpolation, byte for byte."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("numba")

from services.tracker.propagation import upsample_confidence  # noqa: E402


@pytest.mark.parametrize(
    ("h", "w", "H", "W"),
    [
        (48, 85, 680, 1200),  # the classical config at 1200x680
        (45, 79, 680, 1200),
        (48, 64, 240, 320),
        (4, 7, 64, 112),
        (5, 3, 17, 23),  # scales that are not integers
        (8, 8, 4, 4),  # downsampling
        (1, 1, 3, 5),
    ],
)
def test_confidence_kernel_equals_torch(h, w, H, W):
    gen = torch.Generator().manual_seed(h * 100 + w)
    soft = torch.softmax(4 * torch.randn(h, w, 6, generator=gen), -1)
    fast = upsample_confidence(soft, H, W)
    slow = upsample_confidence(soft, H, W, use_numba=False)
    assert fast.dtype == slow.dtype == np.uint8 and fast.shape == slow.shape == (H, W)
    assert np.array_equal(fast, slow)


def test_confidence_kernel_clamps_like_torch():
    """Values outside [0, 1] (not distributions, but the function takes any map) clamp."""
    gen = torch.Generator().manual_seed(5)
    labels = (torch.rand(9, 11, 2, generator=gen) * 1.6 - 0.3)
    fast = upsample_confidence(labels, 50, 70)
    slow = upsample_confidence(labels, 50, 70, use_numba=False)
    assert np.array_equal(fast, slow)
    assert fast.min() == 0 and fast.max() == 255
