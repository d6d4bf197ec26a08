"""The pose book: corrections are absolute, checked before anything changes, and say what moved."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.fusion.corrections.poses import CorrectionError, Motion, PoseBook
from shared.messages.poses import PoseCorrection


def _pose(x: float, yaw: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[0, 3] = x
    return T


def _book(n: int = 10) -> PoseBook:
    book = PoseBook()
    for f in range(n):
        book.add(2 * f, _pose(0.1 * f))  # frames 0, 2, 4, ...: the map skipped the odd ones
    return book


def _shift(T: np.ndarray, dx: float, dy: float = 0.0) -> np.ndarray:
    out = T.copy()
    out[0, 3] += dx
    out[1, 3] += dy
    return out


def _correction(cid: int, frames: list[int], poses: list[np.ndarray], upto: int | None = None) -> PoseCorrection:
    return PoseCorrection(correction_id=cid, frame_index=upto if upto is not None else frames[-1], frames=np.asarray(frames, np.int64), poses=np.stack(poses))


def test_before_any_correction_the_estimate_is_the_raw_pose():
    book = _book(3)
    assert np.array_equal(book.estimate(4), _pose(0.2))
    assert book.estimate(3) is None


def test_listed_frames_take_their_pose_and_the_others_follow_the_nearest_listed_one():
    book = _book(10)  # frames 0..18 even, raw x = 0.1 * f/2
    # frames 4 and 8 corrected by +1 m and +2 m in y
    c = _correction(1, [4, 8], [_shift(_pose(0.2), 0, 1.0), _shift(_pose(0.4), 0, 2.0)], upto=9)
    motion = book.correct(c)
    ys = [book.estimate(f)[1, 3] for f in range(0, 20, 2)]
    # 0, 2 -> nearest 4 (+1); 6 is as near to 4 as to 8 (the earlier wins); 10.. -> 8 (+2)
    assert ys == pytest.approx([1, 1, 1, 1, 2, 2, 2, 2, 2, 2])
    assert len(motion) == 10 and motion.max_shift_m == pytest.approx(2.0)
    # a new frame is placed by the fix of the last listed frame (map -> odom)
    assert book.add(20, _pose(1.0))[1, 3] == pytest.approx(2.0)


def test_the_same_correction_again_moves_nothing_and_an_older_one_is_refused():
    book = _book(5)
    c1 = _correction(1, [0, 2, 4], [_shift(book.raw[k], 0.3) for k in range(3)])
    c2 = _correction(2, [0, 2, 4, 6], [_shift(book.raw[k], 0.5) for k in range(4)])
    assert len(book.correct(c1)) == 5
    assert len(book.correct(c1)) == 0  # sent again
    assert len(book.correct(c2)) == 5
    est = [T.copy() for T in book.est]
    with pytest.raises(CorrectionError, match="not after the newest applied correction 2"):
        book.correct(c1)
    # the same poses under a newer id: absolute, so nothing moves (and no rounding creeps in)
    assert len(book.correct(c2.model_copy(update={"correction_id": 3}))) == 0
    assert all(np.array_equal(a, b) for a, b in zip(est, book.est, strict=True))
    assert book.last_id == 3


def test_corrections_do_not_compound():
    """Two corrections with the same poses for the past give the same estimates as the second alone."""
    a, b = _book(6), _book(6)
    first = _correction(1, [0, 4], [_shift(a.raw[0], 0.2), _shift(a.raw[2], 0.4)])
    second = _correction(2, [0, 4, 8], [_shift(a.raw[0], 0.1), _shift(a.raw[2], 0.3), _shift(a.raw[4], 0.6)])
    a.correct(first)
    a.correct(second)
    b.correct(second.model_copy(update={"correction_id": 1}))
    for x, y in zip(a.est, b.est, strict=True):
        np.testing.assert_allclose(x, y, atol=1e-12)


@pytest.mark.parametrize(
    ("frames", "why"),
    [([0, 30], "frame 30 is unknown"), ([1, 3], "none of its 2 frames is in the map")],
)
def test_unknown_frames_are_refused_with_nothing_changed(frames, why):
    book = _book(5)  # frames 0..8
    before = [T.copy() for T in book.est]
    with pytest.raises(CorrectionError, match=why):
        book.correct(_correction(1, frames, [np.eye(4)] * len(frames)))
    assert book.last_id == -1 and book.epoch == 0
    assert all(np.array_equal(a, b) for a, b in zip(before, book.est, strict=True))


def test_epoch_motion_goes_from_an_old_epoch_to_now():
    book = _book(4)
    book.correct(_correction(1, [0, 6], [_shift(book.raw[0], 1.0), _shift(book.raw[3], 1.0)]))
    book.add(8, _pose(0.4))
    book.correct(_correction(2, [0, 8], [_shift(book.raw[0], 3.0), _shift(book.raw[4], 3.0)]))
    m0, m1, m2 = book.epoch_motion(0), book.epoch_motion(1), book.epoch_motion(2)
    assert len(m2) == 0
    # frames fused by epoch 1 moved 2 m since; from the raw poses, 3 m
    assert m1.frames.tolist() == [0, 2, 4, 6] and np.allclose(m1.deltas[:, 0, 3], 2.0)
    assert np.allclose(m0.deltas[:, 0, 3], 3.0) and m0.frames.tolist() == [0, 2, 4, 6]


def test_motion_moves_points_by_their_anchor_only():
    d = np.eye(4)
    d[:3, 3] = [1.0, 0.0, 0.0]
    m = Motion(np.array([3, 7]), np.stack([d, np.eye(4)]))
    pts = np.zeros((3, 3), np.float32)
    out, hit = m.apply(pts, np.array([3, 5, -1]))
    assert hit.tolist() == [True, False, False]
    assert out.dtype == np.float32 and out[:, 0].tolist() == [1.0, 0.0, 0.0]


def test_state_round_trip():
    book = _book(4)
    book.correct(_correction(4, [0, 6], [_shift(book.raw[0], 0.5), _shift(book.raw[3], 0.7)]))
    again = PoseBook()
    again.load_state_dict(book.state_dict())
    assert again.frames == book.frames and again.last_id == 4 and again.last_digest == book.last_digest
    assert all(np.array_equal(a, b) for a, b in zip(again.est, book.est, strict=True))
    assert len(again.correct(_correction(4, [0, 6], [_shift(book.raw[0], 0.5), _shift(book.raw[3], 0.7)]))) == 0
    assert np.array_equal(again.epoch_motion(0).deltas, book.epoch_motion(0).deltas)


@pytest.mark.parametrize(
    ("change", "msg"),
    [
        ({"poses": np.full((2, 4, 4), np.nan)}, "not finite"),
        ({"poses": np.stack([np.eye(4), np.diag([2.0, 1, 1, 1])])}, "not a rigid transform"),
        ({"frames": np.array([3, 1])}, "strictly increasing"),
        ({"frame_index": 0}, "past frame_index"),
        ({"poses": np.stack([np.eye(4)])}, "2 frames but 1 poses"),
    ],
)
def test_bad_corrections_fail_validation(change, msg):
    data = {"correction_id": 1, "frame_index": 5, "frames": np.array([1, 3]), "poses": np.stack([np.eye(4)] * 2), **change}
    with pytest.raises(ValueError, match=msg):
        PoseCorrection.model_validate(data)


@pytest.mark.parametrize(("pose", "msg"), [(np.full((4, 4), np.nan), "not finite"), (np.diag([1.0, 1.0, 3.0, 1.0]), "not a rigid")])
def test_a_hostile_correction_on_the_wire_is_refused_by_the_codec(pose, msg):
    """The wire carries arrays as they are: a NaN or a scaled pose gets past no receiver."""
    import msgpack

    from shared.codec import CodecError, decode, encode

    good = _correction(1, [0, 2], [np.eye(4), np.eye(4)])
    raw = msgpack.unpackb(encode(good, robot_id="robot0", seq=0, stamp=0.0), raw=False)
    raw["body"]["poses"]["data"] = np.stack([np.eye(4), pose]).astype(np.float64).tobytes()
    with pytest.raises(CodecError, match=msg):
        decode(msgpack.packb(raw, use_bin_type=True), PoseCorrection)
    assert decode(encode(good, robot_id="robot0", seq=0, stamp=0.0), PoseCorrection).body.correction_id == 1
