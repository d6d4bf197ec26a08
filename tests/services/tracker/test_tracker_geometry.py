"""The tracker's static-world checks at keyframes (``services.tracker.core``): a label that
drifted onto another object does not take its detection, the best 3D support wins among
candidates, and the pieces of an object cut in two stay one track.

A flat scene 2 m in front of the camera, coloured squares on it; the propagated labels at
the second keyframe are set by hand, so each test states exactly what propagation got wrong.
"""

from __future__ import annotations

import numpy as np

from services.tracker.core import TrackerCore
from services.tracker.footprints import mask_footprint, support
from shared.config.tracker import TrackerConfig
from shared.geometry import Intrinsics
from shared.messages.frames import Frame
from shared.perception import Masks
from shared.perception.features.classical import ClassicalFeatures

H, W = 48, 64
K = Intrinsics(fx=100.0, fy=100.0, cx=31.5, cy=23.5, width=W, height=H)
RED, BLUE, GREY = (200, 30, 30), (30, 40, 200), (128, 128, 128)


def pose(x: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def box(y0: int, x0: int, h: int, w: int) -> np.ndarray:
    m = np.zeros((H, W), bool)
    m[y0 : y0 + h, x0 : x0 + w] = True
    return m


def frame(index: int, x: float, painted: list[tuple[np.ndarray, tuple[int, int, int]]]) -> Frame:
    rgb = np.empty((H, W, 3), np.uint8)
    rgb[:] = GREY
    for m, colour in painted:
        rgb[m] = colour
    depth = np.full((H, W), 2000, np.uint16)  # 2 m at 1000 units per metre
    return Frame(frame_index=index, rgb=rgb, depth=depth, depth_scale=1000.0, intrinsics=K, T_world_cam=pose(x))


def masks(*ms: np.ndarray) -> Masks:
    stack = np.stack(ms)
    boxes = np.zeros((len(ms), 4), np.float32)
    return Masks(stack, boxes, np.ones(len(ms), np.float32))


def core(**association: float) -> TrackerCore:
    cfg = TrackerConfig.model_validate({"keyframe_interval": 1, "association": association, "device": "cpu"})
    return TrackerCore(cfg, ClassicalFeatures(short_side=H, patch_size=4))


def keyframe(c: TrackerCore, f: Frame, m: Masks, predicted: np.ndarray | None = None) -> list[int]:
    """One keyframe through the core; ``predicted`` replaces what propagation predicted."""
    assert c.begin_frame(f) is not None
    if predicted is not None:
        c._predicted_labels = lambda st, h, w: predicted  # what eq. 1 would have given
    assert c.apply_masks(f.frame_index, m)
    c.end_frame()
    return list(c.mask_tracks[f.frame_index])


def labels(*pairs: tuple[np.ndarray, int]) -> np.ndarray:
    out = np.full((H, W), -1, np.int32)
    for m, tid in pairs:
        out[m] = tid
    return out


def test_support_is_the_share_of_points_near_the_footprint():
    depth = np.full((H, W), 2.0, np.float32)
    a = mask_footprint(box(10, 10, 20, 20), depth, K, pose())
    assert support(a, a, 0.05) == 1.0
    # Half of this square lies on a (10 of its 20 columns), one more column is within 1.5
    # sampling steps (2 cm each at 2 m), the rest up to 0.2 m beyond it.
    half = mask_footprint(box(10, 20, 20, 20), depth, K, pose())
    assert support(a, half, 0.01) == 11 / 20
    assert support(a, mask_footprint(box(10, 44, 10, 10), depth, K, pose()), 0.05) == 0.0


def test_a_drifted_label_does_not_take_the_detection_under_it():
    # Keyframe 0: the red square A on the left. The camera then moves 0.9 m right, so A is
    # out of view, and propagation carried A's label onto the blue square B that came in.
    a, b = box(16, 4, 12, 12), box(16, 30, 12, 12)
    first = frame(0, 0.0, [(a, RED)])
    second = frame(1, 0.9, [(b, BLUE)])
    drifted = labels((b, 0))
    gated = core()
    assert keyframe(gated, first, masks(a)) == [0]
    assert keyframe(gated, second, masks(b), drifted) == [1]  # a track of its own
    # The paper's purely 2D eq. 3 (the check off) hands B to A's track.
    plain = core(support_radius_m=0.0)
    keyframe(plain, first, masks(a))
    assert keyframe(plain, second, masks(b), drifted) == [0]


def test_the_track_with_the_best_3d_support_wins():
    # A and B touch and look alike. At the second keyframe propagation moved A's label over
    # most of B and left B's own label on a sliver of it: by IoU alone (0.42 against 0.17)
    # A's track takes B's detection.
    a, b = box(16, 8, 12, 12), box(16, 20, 12, 12)
    view = frame(0, 0.0, [(a, RED), (b, RED)])
    predicted = labels((a, 0), (b, 0), (box(16, 30, 12, 2), 1))
    relative = core()
    assert keyframe(relative, view, masks(a, b)) == [0, 1]
    assert keyframe(relative, frame(1, 0.0, [(a, RED), (b, RED)]), masks(b), predicted) == [1]
    # A's footprint touches B along their shared edge only: above support_min, so without
    # the relative test A's track, with the larger IoU, would win.
    absolute = core(support_relative=0.0)
    keyframe(absolute, view, masks(a, b))
    assert keyframe(absolute, frame(1, 0.0, [(a, RED), (b, RED)]), masks(b), predicted) == [0]


def test_the_pieces_of_a_split_object_stay_one_track():
    whole = box(12, 12, 20, 24)
    left, right = box(12, 12, 20, 12), box(12, 24, 20, 12)
    c = core()
    assert keyframe(c, frame(0, 0.0, [(whole, RED)]), masks(whole)) == [0]
    # The segmenter cuts the object in two at the next keyframe: both pieces keep its id.
    assert keyframe(c, frame(1, 0.0, [(whole, RED)]), masks(left, right), labels((whole, 0))) == [0, 0]
    assert c.book.next_id == 1
    out = c.end_frame()
    assert set(np.unique(out.track_ids[whole])) == {0}


def test_a_different_object_inside_the_prediction_starts_its_own_track():
    red, blue = box(12, 12, 20, 16), box(12, 28, 20, 8)
    c = core()
    assert keyframe(c, frame(0, 0.0, [(red, RED)]), masks(red)) == [0]
    # Propagation spread the red track over the blue object next to it, never seen before:
    # it looks different and lies off the red track's footprint, so it is not a piece.
    scene = frame(1, 0.0, [(red, RED), (blue, BLUE)])
    assert keyframe(c, scene, masks(red, blue), labels((red | blue, 0))) == [0, 1]


def test_fragment_thresholds_come_from_the_config():
    # The scene above with ``tracker.fragments`` loosened to any cosine and any 3D support:
    # the blue object, inside the red track's prediction, now joins it as a piece.
    red, blue = box(12, 12, 20, 16), box(12, 28, 20, 8)
    cfg = TrackerConfig.model_validate({"keyframe_interval": 1, "device": "cpu", "fragments": {"sim": -1.0, "support": 0.0}})
    c = TrackerCore(cfg, ClassicalFeatures(short_side=H, patch_size=4))
    assert keyframe(c, frame(0, 0.0, [(red, RED)]), masks(red)) == [0]
    scene = frame(1, 0.0, [(red, RED), (blue, BLUE)])
    assert keyframe(c, scene, masks(red, blue), labels((red | blue, 0))) == [0, 0]
