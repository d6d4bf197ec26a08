"""``trackgraph synth --drift``: drifting odometry, loop closures and their corrections."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from shared.geometry import is_rigid
from shared.messages.poses import read_corrections
from shared.synth import writer
from shared.synth.drift import (
    ROT_DRIFT_PER_RATE,
    add_drift,
    corrections,
    drift_poses,
    loop_closures,
    position_errors,
)
from shared.synth.trajectory import look_pose
from tests.shared.synth.conftest import shrink_synth

TINY = {"camera": {"frames": 6, "width": 64, "height": 48}, "gt": {"point_spacing": 0.05}}


@pytest.fixture(scope="module")
def revisit() -> np.ndarray:
    """True poses of the ``revisit`` preset, seed 0 (the walk only, nothing rendered: < 1 s)."""
    from shared.synth.config import preset_config
    from shared.synth.trajectory import build_trajectory
    from shared.synth.world import build_world

    cfg = preset_config("revisit")
    return build_trajectory(build_world(cfg, 0), cfg.camera).poses


def out_and_back(step: float = 0.03, n: int = 300) -> np.ndarray:
    """Along +x for ``n`` steps of ``step`` m, then back to the start: 2n + 1 frames."""
    xs = np.concatenate([np.arange(n + 1) * step, (n - np.arange(1, n + 1)) * step])
    yaw = np.where(np.arange(2 * n + 1) <= n, 0.0, math.pi)
    return np.stack([look_pose(np.array([x, 0.0, 1.5]), y, -0.2) for x, y in zip(xs, yaw, strict=True)])


def travelled(poses: np.ndarray) -> np.ndarray:
    """Distance walked up to each frame (m)."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1))])


def yaw_error(true: np.ndarray, odom: np.ndarray) -> np.ndarray:
    rel = odom[:, :3, :3] @ true[:, :3, :3].transpose(0, 2, 1)
    return np.arctan2(rel[:, 1, 0], rel[:, 0, 0])


def load_traj(path: Path) -> np.ndarray:
    return np.array([[float(v) for v in line.split()] for line in path.read_text().splitlines()]).reshape(-1, 4, 4)


# -- drift_poses ---------------------------------------------------------------------------------


def test_drift_is_deterministic_per_seed(revisit):
    a = drift_poses(revisit, 0.02, 3)
    assert np.array_equal(a, drift_poses(revisit, 0.02, 3))
    assert not np.allclose(a, drift_poses(revisit, 0.02, 4)), "another seed drifts another way"
    assert not np.allclose(a, revisit), "rate 0.02 moves the poses"


def test_first_pose_exact_every_pose_rigid_roll_pitch_untouched(revisit):
    odom = drift_poses(revisit, 0.1, 0)
    assert odom.shape == revisit.shape and odom.dtype == np.float64
    assert np.array_equal(odom[0], revisit[0])
    R = odom[:, :3, :3]
    assert np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max() < 1e-12
    assert np.abs(np.linalg.det(R) - 1.0).max() < 1e-12
    assert np.array_equal(odom[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (len(odom), 1)))
    assert all(is_rigid(T) for T in odom)
    # The rotation error is about world z only: it keeps the world's up axis.
    rel = R @ revisit[:, :3, :3].transpose(0, 2, 1)
    assert np.abs(rel[:, :, 2] - [0.0, 0.0, 1.0]).max() < 1e-12


def test_rate_zero_returns_the_true_poses(revisit):
    odom = drift_poses(revisit, 0.0, 7)
    assert np.array_equal(odom, revisit) and odom is not revisit


def test_error_grows_about_rate_per_metre(revisit):
    rate = 0.02
    length = travelled(revisit)
    L = length[-1]
    assert L > 30, "the revisit walk is long enough to measure drift on"
    odom = drift_poses(revisit, rate, 0)
    err = position_errors(revisit, odom)
    assert 0.5 * rate * L < err[-1] < 2.0 * rate * L, (err[-1], rate * L)
    assert err.max() < 2.0 * rate * L
    quarter = int(np.searchsorted(length, L / 4))
    assert err[-1] > 1.5 * err[quarter], "the error compounds along the path"
    # Over seeds the final error stays about rate * L (the heading error adds to or cancels
    # some of the translation drift, depending on the seed).
    finals = [position_errors(revisit, drift_poses(revisit, rate, s))[-1] / (rate * L) for s in range(8)]
    assert 0.5 < float(np.mean(finals)) < 2.0, finals
    # Yaw drifts by about ROT_DRIFT_PER_RATE * rate rad per metre.
    yaw = abs(yaw_error(revisit, odom)[-1])
    assert 0.5 * ROT_DRIFT_PER_RATE * rate * L < yaw < 2.0 * ROT_DRIFT_PER_RATE * rate * L, yaw
    # Twice the rate, twice the error (same seed, same random walk).
    double = position_errors(revisit, drift_poses(revisit, 2 * rate, 0))
    assert 1.8 < double[-1] / err[-1] < 2.2


def test_translation_drift_without_the_heading_part_is_rate_per_metre(revisit):
    """Walking the true steps with the odometry's own heading leaves the translation drift:
    about ``rate`` m per m, whatever the heading did."""
    rate = 0.05
    odom = drift_poses(revisit, rate, 1)
    psi = yaw_error(revisit, odom)
    steps = np.diff(revisit[:, :3, 3], axis=0)
    c, s = np.cos(psi[:-1]), np.sin(psi[:-1])
    turned = np.stack([c * steps[:, 0] - s * steps[:, 1], s * steps[:, 0] + c * steps[:, 1], steps[:, 2]], axis=1)
    headed = revisit[0, :3, 3] + np.concatenate([np.zeros((1, 3)), np.cumsum(turned, axis=0)])
    residual = np.linalg.norm(odom[:, :3, 3] - headed, axis=1)
    L = travelled(revisit)[-1]
    assert 0.7 * rate * L < residual[-1] < 1.4 * rate * L, (residual[-1], rate * L)


def test_odometry_motion_stays_locally_right_late_in_the_path(revisit):
    """What odometry measures, the motion over a few metres in the camera's own frame, is as
    good late in the walk as early on: the heading error turns the steps in the world, not in
    the camera frame. So after a correction at frame t, odometry from t drifts only from t on
    (a map -> odom fix, as fusion applies it). A heading error that only rotated the cameras
    would put the accumulated yaw into every later relative motion."""
    rate, w = 0.1, 40  # 40 frames: about 3 m of walk
    length = travelled(revisit)
    idx = np.arange(len(revisit) - w)
    late = idx[-len(idx) // 4 :]
    for seed in range(4):
        odom = drift_poses(revisit, rate, seed)
        rel_odom = np.linalg.inv(odom[late]) @ odom[late + w]
        rel_true = np.linalg.inv(revisit[late]) @ revisit[late + w]
        err = np.linalg.norm(rel_odom[:, :3, 3] - rel_true[:, :3, 3], axis=1)
        per_metre = err / (rate * (length[late + w] - length[late]))
        assert np.median(per_metre) < 2.0, (seed, float(np.median(per_metre)))


def test_a_standing_camera_does_not_drift():
    still = np.stack([look_pose(np.array([1.0, 2.0, 1.5]), 0.01 * i, 0.0) for i in range(50)])
    odom = drift_poses(still, 0.3, 0)
    assert np.abs(odom - still).max() < 1e-12


# -- loop closures and corrections ---------------------------------------------------------------


def test_loop_closures_on_an_out_and_back_walk():
    poses = out_and_back()  # 601 frames, 3 cm apart: frame 300 + k is where frame 300 - k was
    # Frame 359 (x = 7.23) is the first within 1 m (0.99) of a frame at least 150 earlier
    # (frame 208, x = 6.24); then every later frame qualifies, so one per 30 frames.
    assert loop_closures(poses) == [359, 389, 419, 449, 479, 509, 539, 569, 599]
    assert loop_closures(poses, min_spacing=1000) == [359]
    assert loop_closures(poses, radius=0.5) == [367, 397, 427, 457, 487, 517, 547, 577]
    assert loop_closures(poses[:301]) == [], "a walk that never comes back closes no loop"
    assert loop_closures(poses[:100]) == []


def test_revisit_closes_loops(revisit):
    closures = loop_closures(revisit)
    assert len(closures) >= 1
    pos = revisit[:, :3, 3]
    for t in closures:
        assert np.linalg.norm(pos[: t - 150 + 1] - pos[t], axis=1).min() <= 1.0
    assert all(b - a >= 30 for a, b in zip(closures, closures[1:], strict=False))


def test_corrections_round_trip(tmp_path):
    poses = out_and_back()
    closures = loop_closures(poses)
    fixes = corrections(poses, closures)
    assert [c.correction_id for c in fixes] == list(range(1, len(closures) + 1))
    path = tmp_path / "corrections.jsonl"
    path.write_text("".join(c.to_json() + "\n" for c in fixes))
    back = read_corrections(path)
    assert len(back) == len(closures)
    for c, t in zip(back, closures, strict=True):
        assert c.frame_index == t and c.apply_after_frame is None
        assert np.array_equal(c.frames, np.arange(t + 1))
        assert np.array_equal(c.poses, poses[: t + 1]), "corrections carry the true poses exactly"


# -- add_drift, generate, CLI --------------------------------------------------------------------


def fake_sequence(root: Path, poses: np.ndarray) -> Path:
    """Just what add_drift reads: traj.txt and a gt/scene.json."""
    writer.write_bytes(root / "traj.txt", writer.traj_text(poses).encode("ascii"))
    writer.write_json(root / "gt" / "scene.json", {"name": "walk", "seed": 5, "rooms": [{"name": "a"}]})
    return root


def test_add_drift_writes_its_files_and_refuses_a_second_time(tmp_path):
    from PIL import Image

    poses = out_and_back()
    seq = fake_sequence(tmp_path / "walk", poses)
    original = (seq / "traj.txt").read_bytes()
    summary = add_drift(seq, 0.05, 5)
    assert summary["rate"] == 0.05 and summary["closures"] == [359, 389, 419, 449, 479, 509, 539, 569, 599]
    assert summary["corrections"] == 9
    err = position_errors(poses, drift_poses(poses, 0.05, 5))
    assert summary["final_error_m"] == pytest.approx(err[-1], abs=1e-4) and summary["final_error_m"] > 0
    assert summary["max_error_m"] == pytest.approx(err.max(), abs=1e-4)

    assert (seq / "traj_gt.txt").read_bytes() == original
    assert np.array_equal(load_traj(seq / "traj.txt"), drift_poses(poses, 0.05, 5))
    fixes = read_corrections(seq / "corrections.jsonl")
    assert [c.frame_index for c in fixes] == summary["closures"]
    assert np.array_equal(fixes[-1].poses, poses[:600])
    assert Image.open(seq / "drift.png").size[0] > 500
    scene = json.loads((seq / "gt" / "scene.json").read_text())
    assert scene["rooms"] == [{"name": "a"}] and scene["seed"] == 5, "the rest of scene.json is kept"
    assert scene["drift"]["closures"] == summary["closures"] and scene["drift"]["corrections"] == 9
    assert scene["drift"]["rate"] == 0.05 and scene["drift"]["final_error_m"] == summary["final_error_m"]
    assert not [p.name for p in seq.rglob(".*")], "no temporary file left behind"

    drifted = (seq / "traj.txt").read_bytes()
    with pytest.raises(ValueError, match=f"{seq}.*already has drift"):
        add_drift(seq, 0.05, 5)
    assert (seq / "traj.txt").read_bytes() == drifted


@pytest.mark.parametrize("rate", [0.0, -0.1, 0.6, float("nan"), float("inf")])
def test_add_drift_refuses_a_bad_rate(tmp_path, rate):
    seq = fake_sequence(tmp_path / "walk", out_and_back(n=20))
    with pytest.raises(ValueError, match="drift rate"):
        add_drift(seq, rate, 0)
    assert not (seq / "traj_gt.txt").exists()


def test_run_synth_with_drift(tmp_path):
    from shared.synth import run_synth

    out = tmp_path / "seq"
    result = run_synth("small", 0, out, TINY, progress=False, drift=0.05)
    assert result["drift"] == 0.05 and result["corrections"] == 0 and result["frames"] == 6
    true, odom = load_traj(out / "traj_gt.txt"), load_traj(out / "traj.txt")
    assert len(true) == len(odom) == 6
    assert np.array_equal(odom, drift_poses(true, 0.05, 0))
    assert (out / "corrections.jsonl").read_text() == ""
    assert json.loads((out / "gt" / "scene.json").read_text())["drift"]["seed"] == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"], "no staging folder left behind"
    again = tmp_path / "again"
    run_synth("small", 0, again, TINY, progress=False, drift=0.05)
    for name in ("traj.txt", "traj_gt.txt", "corrections.jsonl", "drift.png", "gt/scene.json"):
        assert (again / name).read_bytes() == (out / name).read_bytes(), f"{name} differs between two runs"
    with pytest.raises(ValueError, match="drift rate"):
        run_synth("small", 0, tmp_path / "bad", TINY, progress=False, drift=0.0)
    assert not (tmp_path / "bad").exists()


@pytest.fixture
def tiny_synth(monkeypatch):
    """``trackgraph synth`` renders a tiny sequence instead of the whole preset."""
    shrink_synth(monkeypatch, TINY)


def test_cli_drift_json(tmp_path, capsys, tiny_synth):
    from services.cli import main

    out = tmp_path / "seq"
    assert main(["synth", "--preset", "small", "--seed", "0", "--out", str(out), "--drift", "0.05", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert {"frames", "objects", "out"} <= set(result)
    assert result["drift"] == 0.05 and result["corrections"] == 0 and result["out"] == str(out)
    assert (out / "traj_gt.txt").is_file() and (out / "drift.png").is_file()

    plain = tmp_path / "plain"
    assert main(["synth", "--preset", "small", "--seed", "0", "--out", str(plain), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert "drift" not in result and "corrections" not in result
    assert not (plain / "traj_gt.txt").exists()


@pytest.mark.parametrize("rate", ["0", "-0.1", "0.6", "nan", "inf"])
def test_cli_refuses_a_bad_drift_rate(tmp_path, capsys, tiny_synth, rate):
    from services.cli import main

    out = tmp_path / "seq"
    assert main(["synth", "--out", str(out), f"--drift={rate}", "--json"]) != 0
    captured = capsys.readouterr()
    assert captured.out == ""
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and "--drift" in err[0] and "(0, 0.5]" in err[0], err
    assert not out.exists()
