"""Pinhole projection, rigid transforms and quaternions (shared/geometry.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from shared.geometry import (
    OPENGL_TO_OPENCV,
    Intrinsics,
    backproject,
    invert,
    is_rigid,
    pose_from_quat,
    project,
    quat_to_matrix,
    transform,
)

FAST = settings(max_examples=25, deadline=None, derandomize=True)

QUATS = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1)
TRANSLATIONS = st.lists(st.floats(-100, 100), min_size=3, max_size=3)


def rigid(q: list[float], t: list[float]) -> np.ndarray:
    return pose_from_quat(np.array(t), np.array(q))


K = Intrinsics(fx=525.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)


# ---------------------------------------------------------------- projection


@FAST
@given(
    fx=st.floats(10, 2000), fy=st.floats(10, 2000), cx=st.floats(-50, 50), cy=st.floats(-50, 50),
    w=st.integers(1, 16), h=st.integers(1, 16), seed=st.integers(0, 2**32 - 1),
)
def test_project_inverts_backproject(fx: float, fy: float, cx: float, cy: float, w: int, h: int, seed: int) -> None:
    k = Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h)
    depth = np.random.default_rng(seed).uniform(0.1, 10.0, (h, w))
    pts = backproject(k, depth)
    assert pts.shape == (h, w, 3)
    np.testing.assert_array_equal(pts[..., 2], depth)
    uv, z = project(k, pts.reshape(-1, 3))
    vv, uu = np.mgrid[:h, :w]
    np.testing.assert_allclose(uv[:, 0], uu.ravel(), atol=1e-6)
    np.testing.assert_allclose(uv[:, 1], vv.ravel(), atol=1e-6)
    np.testing.assert_array_equal(z, depth.ravel())


def test_backproject_known_pixel() -> None:
    depth = np.zeros((480, 640))
    depth[239, 319] = 2.0  # near the principal point
    depth[0, 0] = 1.0
    pts = backproject(K, depth)
    np.testing.assert_allclose(pts[239, 319], [-0.5 / 525 * 2, -0.5 / 500 * 2, 2.0])
    np.testing.assert_allclose(pts[0, 0], [-319.5 / 525, -239.5 / 500, 1.0])
    assert pts.dtype == np.float64


def test_zero_depth_gives_zero_point() -> None:
    k = Intrinsics(fx=100, fy=100, cx=1.5, cy=1.5, width=4, height=4)
    pts = backproject(k, np.zeros((4, 4), dtype=np.float32))
    assert pts.shape == (4, 4, 3)
    assert not pts.any()


def test_project_known_point_and_behind_camera() -> None:
    pts = np.array([[1.0, -0.5, 2.0], [0.0, 0.0, 1.0], [1.0, 1.0, 0.0], [1.0, 1.0, -3.0]])
    uv, z = project(K, pts)
    np.testing.assert_allclose(uv[0], [525 * 0.5 + 319.5, 500 * -0.25 + 239.5])
    np.testing.assert_allclose(uv[1], [319.5, 239.5])
    assert np.isnan(uv[2:]).all()
    np.testing.assert_array_equal(z, pts[:, 2])


@pytest.mark.parametrize("shape", [(480, 641), (481, 640), (640, 480), (1, 1)])
def test_backproject_size_mismatch_raises(shape: tuple[int, int]) -> None:
    with pytest.raises(ValueError, match="640x480"):
        backproject(K, np.ones(shape))


# ---------------------------------------------------------------- rigid transforms


@FAST
@given(q=QUATS, t=TRANSLATIONS)
def test_invert_is_the_inverse(q: list[float], t: list[float]) -> None:
    T = rigid(q, t)
    Ti = invert(T)
    np.testing.assert_allclose(Ti @ T, np.eye(4), atol=1e-9)
    np.testing.assert_allclose(T @ Ti, np.eye(4), atol=1e-9)
    np.testing.assert_allclose(Ti, np.linalg.inv(T), atol=1e-9)
    assert is_rigid(Ti)


@FAST
@given(q=QUATS, t=TRANSLATIONS, seed=st.integers(0, 2**32 - 1))
def test_transform_matches_homogeneous_product(q: list[float], t: list[float], seed: int) -> None:
    T = rigid(q, t)
    pts = np.random.default_rng(seed).normal(size=(7, 3))
    homo = np.c_[pts, np.ones(7)] @ T.T
    np.testing.assert_allclose(transform(T, pts), homo[:, :3], atol=1e-9)
    np.testing.assert_allclose(transform(invert(T), transform(T, pts)), pts, atol=1e-9)


@FAST
@given(q=QUATS, t=TRANSLATIONS)
def test_random_rigid_transforms_are_rigid(q: list[float], t: list[float]) -> None:
    assert is_rigid(rigid(q, t))


def _with(T: np.ndarray, i: int, j: int, value: float) -> np.ndarray:
    T = T.copy()
    T[i, j] = value
    return T


BAD_POSES = {
    "nan-translation": _with(np.eye(4), 0, 3, math.nan),
    "nan-rotation": _with(np.eye(4), 1, 1, math.nan),
    "inf": _with(np.eye(4), 2, 3, math.inf),
    "scaled": np.diag([2.0, 2.0, 2.0, 1.0]),
    "shrunk": np.diag([0.99, 0.99, 0.99, 1.0]),
    "reflection": np.diag([-1.0, 1.0, 1.0, 1.0]),
    "point-reflection": np.diag([-1.0, -1.0, -1.0, 1.0]),
    "shear": _with(np.eye(4), 0, 1, 0.5),
    "bad-last-row": _with(np.eye(4), 3, 0, 0.5),
    "homogeneous-scale": np.diag([1.0, 1.0, 1.0, 2.0]),
    "zeros": np.zeros((4, 4)),
    "3x3": np.eye(3),
    "3x4": np.eye(4)[:3],
    "5x5": np.eye(5),
}


@pytest.mark.parametrize("name", sorted(BAD_POSES))
def test_is_rigid_rejects(name: str) -> None:
    assert not is_rigid(BAD_POSES[name])


def test_is_rigid_accepts() -> None:
    assert is_rigid(np.eye(4))
    assert is_rigid(rigid([0.3, -0.2, 0.9, 0.1], [1e3, -5.0, 0.25]))
    assert is_rigid(OPENGL_TO_OPENCV)  # 180 degrees about x
    assert is_rigid(np.eye(4).tolist())  # array-likes are accepted


def test_is_rigid_tolerance() -> None:
    assert is_rigid(np.diag([1 + 1e-5, 1.0, 1.0, 1.0]))
    assert not is_rigid(np.diag([1 + 1e-2, 1.0, 1.0, 1.0]))
    assert is_rigid(np.diag([1 + 1e-2, 1.0, 1.0, 1.0]), tol=0.05)


def test_opengl_to_opencv_flips_y_and_z() -> None:
    np.testing.assert_array_equal(OPENGL_TO_OPENCV, np.diag([1.0, -1.0, -1.0, 1.0]))
    gl_pose = rigid([1, 0, 0, 0], [1, 2, 3])
    cv_pose = gl_pose @ OPENGL_TO_OPENCV
    # the OpenCV camera looks down +z, i.e. down -z of the OpenGL camera
    np.testing.assert_allclose(transform(cv_pose, np.array([[0.0, 0.0, 1.0]])), [[1, 2, 2]])
    assert not is_rigid(OPENGL_TO_OPENCV @ np.diag([1.0, 1.0, -1.0, 1.0]))


# ---------------------------------------------------------------- quaternions

S = math.sqrt(0.5)
KNOWN_ROTATIONS = {
    "identity": ([1, 0, 0, 0], np.eye(3)),
    "z90": ([S, 0, 0, S], np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])),
    "x90": ([S, S, 0, 0], np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])),
    "y90": ([S, 0, S, 0], np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]])),
    "x180": ([0, 1, 0, 0], np.diag([1, -1, -1])),
    "z-90": ([S, 0, 0, -S], np.array([[0, 1, 0], [-1, 0, 0], [0, 0, 1]])),
    "axis111-120": ([0.5, 0.5, 0.5, 0.5], np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]])),
}


@pytest.mark.parametrize("name", sorted(KNOWN_ROTATIONS))
def test_quat_to_matrix_known(name: str) -> None:
    q, R = KNOWN_ROTATIONS[name]
    np.testing.assert_allclose(quat_to_matrix(np.array(q, dtype=float)), R, atol=1e-12)
    # not necessarily unit, and q and -q are the same rotation
    np.testing.assert_allclose(quat_to_matrix(3.5 * np.array(q, dtype=float)), R, atol=1e-12)
    np.testing.assert_allclose(quat_to_matrix(-np.array(q, dtype=float)), R, atol=1e-12)


def test_quat_to_matrix_rotates_vectors_right_handed() -> None:
    R = quat_to_matrix([S, 0, 0, S])  # +90 degrees about z
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(R @ [0, 1, 0], [-1, 0, 0], atol=1e-12)


@FAST
@given(q=QUATS)
def test_quat_to_matrix_is_a_rotation(q: list[float]) -> None:
    R = quat_to_matrix(np.array(q))
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert abs(np.linalg.det(R) - 1.0) < 1e-9


@FAST
@given(angle=st.floats(-math.pi, math.pi), axis=st.sampled_from([0, 1, 2]))
def test_quat_to_matrix_matches_axis_angle(angle: float, axis: int) -> None:
    q = np.zeros(4)
    q[0] = math.cos(angle / 2)
    q[1 + axis] = math.sin(angle / 2)
    c, s = math.cos(angle), math.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-12)


@pytest.mark.parametrize("q", [[0, 0, 0, 0], [1e-13, 0, 0, 0], [math.nan, 0, 0, 1], [math.inf, 0, 0, 0]])
def test_quat_to_matrix_refuses_degenerate(q: list[float]) -> None:
    with pytest.raises(ValueError):
        quat_to_matrix(np.array(q))


def test_pose_from_quat() -> None:
    T = pose_from_quat(np.array([1.0, 2.0, 3.0]), np.array([S, 0, 0, S]))
    np.testing.assert_allclose(T[:3, :3], KNOWN_ROTATIONS["z90"][1], atol=1e-12)
    np.testing.assert_array_equal(T[:3, 3], [1, 2, 3])
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])


# ---------------------------------------------------------------- intrinsics


def test_intrinsics_matrix() -> None:
    np.testing.assert_array_equal(K.matrix(), [[525, 0, 319.5], [0, 500, 239.5], [0, 0, 1]])


def test_scaled_halves_with_pixel_centre_convention() -> None:
    half = K.scaled(320, 240)
    assert (half.width, half.height) == (320, 240)
    assert (half.fx, half.fy) == (262.5, 250.0)
    # the image centre stays the image centre: (319.5 + 0.5) / 2 - 0.5
    assert (half.cx, half.cy) == (159.5, 119.5)
    assert K.scaled(640, 480) == K


def test_strided_camera_sees_every_point_at_its_strided_pixel() -> None:
    """``image[::s, ::s]``'s camera: a point at pixel (s u, s v) of the full image is at
    (u, v) of the strided one, for odd sizes too (the last row and column are kept)."""
    from shared.geometry import pixel_stride

    k = Intrinsics(fx=782.0, fy=781.0, cx=599.5, cy=339.5, width=1201, height=681)
    rng = np.random.default_rng(0)
    for step in (1, 2, 3):
        ks = k.strided(step)
        assert (ks.width, ks.height) == (len(range(0, 1201, step)), len(range(0, 681, step)))
        u, v = rng.integers(0, ks.width, 50), rng.integers(0, ks.height, 50)
        z = rng.uniform(0.5, 5.0, 50)
        x, y = (step * u - k.cx) / k.fx * z, (step * v - k.cy) / k.fy * z  # the full camera's point
        np.testing.assert_allclose(ks.fx * x / z + ks.cx, u, atol=1e-9)
        np.testing.assert_allclose(ks.fy * y / z + ks.cy, v, atol=1e-9)
    assert k.strided(1) == k
    assert [pixel_stride("auto", w) for w in (320, 640, 800, 1200, 1280, 1920, 3840)] == [1, 1, 1, 2, 2, 3, 6]
    assert pixel_stride(3, 320) == 3


def test_scaled_anisotropic_and_back() -> None:
    k = Intrinsics(fx=600.0, fy=610.0, cx=300.25, cy=250.75, width=640, height=480)
    s = k.scaled(1280, 360)
    assert s.fx == pytest.approx(1200.0)
    assert s.fy == pytest.approx(610.0 * 0.75)
    assert s.cx == pytest.approx((300.25 + 0.5) * 2 - 0.5)
    assert s.cy == pytest.approx((250.75 + 0.5) * 0.75 - 0.5)
    back = s.scaled(640, 480)
    for name in ("fx", "fy", "cx", "cy"):
        assert getattr(back, name) == pytest.approx(getattr(k, name))
    assert (back.width, back.height) == (640, 480)


def test_scaled_projects_to_the_same_relative_position() -> None:
    """A 3D point lands on the same spot of the image (in pixel-edge coordinates) at any size."""
    pts = np.array([[0.3, -0.2, 2.0], [-1.0, 0.5, 4.0]])
    uv, _ = project(K, pts)
    s = K.scaled(160, 120)
    uv_s, _ = project(s, pts)
    np.testing.assert_allclose((uv_s + 0.5) * 4, uv + 0.5)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"fx": 0.0}, {"fy": -1.0}, {"fx": math.nan}, {"cx": math.nan}, {"cy": math.inf},
        {"width": 0}, {"height": -1}, {"width": 65537}, {"skew": 0.0},
    ],
)
def test_intrinsics_validation(kwargs: dict) -> None:
    base = {"fx": 1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0, "width": 4, "height": 3}
    with pytest.raises(ValidationError):
        Intrinsics(**{**base, **kwargs})


def test_intrinsics_frozen() -> None:
    with pytest.raises(ValidationError):
        K.fx = 1.0  # type: ignore[misc]


def test_matrix_to_quat_inverts_quat_to_matrix_everywhere() -> None:
    from shared.geometry import matrix_to_quat, pose_row, quat_to_matrix

    rng = np.random.default_rng(7)
    qs = rng.standard_normal((500, 4))
    # Half-turns about each axis: the trace is -1 and the scalar part zero.
    qs = np.concatenate([qs, np.eye(4)[1:], [[1e-9, 1.0, 1.0, 0.0]]])
    for q in qs:
        q = q / np.linalg.norm(q)
        got = matrix_to_quat(quat_to_matrix(q))
        assert got[0] >= 0 and np.isclose(np.linalg.norm(got), 1.0)
        np.testing.assert_allclose(got, q if q[0] >= 0 else -q, atol=1e-7)
    # A 90 degree turn about z, scalar last: (0, 0, sin 45, cos 45).
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    T[:3, 3] = [1, 2, 3]
    np.testing.assert_allclose(pose_row(T), [1, 2, 3, 0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)
