"""Padded bounding-box crops: padding, rounding and clipping on hand-made masks."""

from __future__ import annotations

import numpy as np
import pytest

from shared.perception.encoders.crops import batched, mask_box, pad_box, padded_boxes, padded_crops


def _rect(h: int, w: int, y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
    m = np.zeros((h, w), bool)
    m[y0:y1, x0:x1] = True
    return m


def _image(h: int = 80, w: int = 100) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    return np.stack([yy, xx, (yy + xx) % 256], axis=-1).astype(np.uint8)


def test_mask_box_is_half_open_and_tight():
    m = _rect(80, 100, 10, 30, 20, 50)
    m[15, 20] = False  # a hole inside does not change the box
    assert mask_box(m) == (20, 10, 50, 30)
    assert mask_box(np.zeros((4, 4), bool)) is None


def test_padding_is_a_fraction_of_the_box_size_on_each_side():
    # 30 wide, 20 high: 0.1 pads 3 px left and right, 2 px top and bottom.
    assert pad_box((20, 10, 50, 30), 0.1, 100, 80) == (17, 8, 53, 32)
    assert pad_box((20, 10, 50, 30), 0.0, 100, 80) == (20, 10, 50, 30)


def test_fractional_padding_rounds_outwards():
    # 7 x 7 box: 0.1 pads 0.7 px, which becomes a whole pixel on each side.
    assert pad_box((10, 10, 17, 17), 0.1, 100, 80) == (9, 9, 18, 18)


def test_padding_is_clipped_to_the_image():
    # A 10 x 10 box in the bottom-left corner padded by half its size.
    assert pad_box((0, 70, 10, 80), 0.5, 100, 80) == (0, 65, 15, 80)
    assert pad_box((90, 0, 100, 10), 1.0, 100, 80) == (80, 0, 100, 20)


def test_degenerate_box_still_gives_one_pixel():
    assert pad_box((100, 80, 100, 80), 0.1, 100, 80) == (99, 79, 100, 80)


def test_crops_are_the_padded_pixels():
    rgb = _image()
    masks = np.stack([_rect(80, 100, 10, 30, 20, 50), _rect(80, 100, 70, 80, 0, 10)])
    crops = padded_crops(rgb, masks, 0.1)
    # The second, in the corner, loses its padding on the left and bottom.
    assert [c.shape for c in crops] == [(24, 36, 3), (11, 11, 3)]
    np.testing.assert_array_equal(crops[0], rgb[8:32, 17:53])
    np.testing.assert_array_equal(crops[1], rgb[69:80, 0:11])
    assert all(c.dtype == np.uint8 and c.flags.c_contiguous for c in crops)
    crops[0][:] = 0  # copies, not views of the image
    assert rgb[8:32, 17:53].any()


def test_empty_mask_falls_back_to_the_segmenter_box():
    masks = np.zeros((1, 80, 100), bool)
    boxes = padded_boxes(masks, np.array([[20.0, 10.0, 50.0, 30.0]], np.float32), 0.1)
    np.testing.assert_array_equal(boxes, [[17, 8, 53, 32]])
    with pytest.raises(ValueError, match="empty"):
        padded_boxes(masks, None, 0.1)


def test_crops_check_shapes():
    with pytest.raises(ValueError, match="uint8"):
        padded_crops(np.zeros((8, 8, 3), np.float32), np.zeros((0, 8, 8), bool), 0.1)
    with pytest.raises(ValueError, match="do not match"):
        padded_crops(np.zeros((8, 8, 3), np.uint8), np.zeros((1, 8, 9), bool), 0.1)


def test_batched():
    assert [list(b) for b in batched(list(range(7)), 3)] == [[0, 1, 2], [3, 4, 5], [6]]
    assert list(batched([], 4)) == []
    with pytest.raises(ValueError):
        list(batched([1], 0))
