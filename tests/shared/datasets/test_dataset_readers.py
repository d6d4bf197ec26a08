"""Every reader gives back the same poses, intrinsics and 3D points from the same content."""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import write_rosbag
from dataset_fixtures import (
    H,
    N,
    Scene,
    W,
    backprojected_world,
    write_hm3d,
    write_replica,
    write_scannetpp,
    write_tum,
)
from rosbags.rosbag2 import StoragePlugin

from shared.config.source import SourceConfig
from shared.datasets import DATASETS, open_sequence
from shared.datasets.hm3d import HM3D_INTRINSICS
from shared.datasets.replica import REPLICA_DEPTH_SCALE, REPLICA_INTRINSICS, ReplicaReader
from shared.datasets.scannetpp import ScanNetppReader
from shared.datasets.tum import TUM_FR1_INTRINSICS

# name -> (dataset, depth units per metre, lossless colour, writer)
CASES = {
    "scannetpp": ("scannetpp", 1000.0, False, lambda s, p: write_scannetpp(s, p)),
    "hm3d": ("hm3d", 1000.0, True, lambda s, p: write_hm3d(s, p)),
    "tum": ("tum", 5000.0, True, lambda s, p: write_tum(s, p)),
    "bag-odom-rgb8-16u": ("rosbag", 1000.0, True, lambda s, p: write_rosbag(s, p)),
    "bag-posestamped-bgr8-32f": (
        "rosbag", 1000.0, True, lambda s, p: write_rosbag(s, p, pose="posestamped", rgb="bgr8", depth="32FC1"),
    ),
    "bag-tf-jpeg-32f": ("rosbag", 1000.0, False, lambda s, p: write_rosbag(s, p, pose="tf", rgb="jpeg", depth="32FC1")),
    "bag-tf-png-mcap": (
        "rosbag", 1000.0, True, lambda s, p: write_rosbag(s, p, pose="tf", rgb="png", storage=StoragePlugin.MCAP),
    ),
}  # fmt: skip
JPEG_TOL = 8


def ray_factor(s: Scene) -> float:
    """Largest |point| / depth over the image: how much a depth error grows into a point error."""
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    return float(np.sqrt(1 + ((u - s.K.cx) / s.K.fx) ** 2 + ((v - s.K.cy) / s.K.fy) ** 2).max())


@pytest.fixture(scope="module")
def written(scene: Scene, tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, SourceConfig]]:
    root = tmp_path_factory.mktemp("formats")
    out = {"replica": (write_replica(scene, root / "replica"), SourceConfig())}
    for name, (_, _, _, write) in CASES.items():
        result = write(scene, root / name)
        cfg = SourceConfig(rosbag=result) if not isinstance(result, Path) else SourceConfig()
        out[name] = (root / name, cfg)
    return out


@pytest.fixture(scope="module")
def replica_frames(written):
    return list(ReplicaReader(written["replica"][0]))


def test_replica_reads_the_scene(scene: Scene, replica_frames) -> None:
    assert len(replica_frames) == N
    for i, f in enumerate(replica_frames):
        np.testing.assert_allclose(f.T_world_cam, scene.poses[i], atol=1e-12)
        assert f.intrinsics == scene.K and f.depth_scale == REPLICA_DEPTH_SCALE
        step = 0.5 / REPLICA_DEPTH_SCALE
        np.testing.assert_allclose(f.depth_m(), scene.depth_m[i], atol=step + 1e-7)
        assert np.abs(f.rgb.astype(int) - scene.rgb[i]).max() <= JPEG_TOL
        assert f.frame_index == i and "instances" not in type(f).model_fields


@pytest.mark.parametrize("name", list(CASES))
def test_same_content_as_replica(name: str, scene: Scene, written, replica_frames) -> None:
    dataset, scale, lossless, _ = CASES[name]
    path, cfg = written[name]
    with open_sequence(path, dataset, cfg) as reader:
        assert len(reader) == N
        np.testing.assert_allclose(reader.poses(), scene.poses, atol=1e-6)
        K = reader.intrinsics
        np.testing.assert_allclose([K.fx, K.fy, K.cx, K.cy], [scene.K.fx, scene.K.fy, scene.K.cx, scene.K.cy], atol=1e-9)
        tol = ray_factor(scene) * (0.5 / REPLICA_DEPTH_SCALE + 0.5 / scale) + 1e-9
        for i, f in enumerate(reader):
            ref = replica_frames[i]
            assert f.rgb.shape == (H, W, 3) and f.depth.shape == (H, W)
            assert f.depth_scale == scale and f.depth[0, 0] == 0  # holes stay holes
            np.testing.assert_allclose(f.T_world_cam, ref.T_world_cam, atol=1e-6)
            np.testing.assert_allclose(backprojected_world(f), backprojected_world(ref), atol=tol)
            diff = np.abs(f.rgb.astype(int) - scene.rgb[i]).max()
            assert diff == 0 if lossless else diff <= JPEG_TOL
            assert f.frame_index == i


def test_times(written, scene: Scene) -> None:
    tum = open_sequence(written["tum"][0], "tum")
    np.testing.assert_allclose([tum.frame(i).time_s for i in range(N)], scene.times, atol=1e-6)
    path, cfg = written["bag-odom-rgb8-16u"]
    bag = open_sequence(path, "rosbag", cfg)
    np.testing.assert_allclose([bag.frame(i).time_s for i in range(N)], scene.times, atol=1e-6)
    snpp = open_sequence(written["scannetpp"][0], "scannetpp")
    assert [snpp.frame(i).time_s for i in range(N)] == pytest.approx([10 * i / 60 for i in range(N)])


def test_scannetpp_full_resolution_option(written, scene: Scene) -> None:
    reader = ScanNetppReader(written["scannetpp"][0], resize_to="rgb")
    K = reader.intrinsics
    assert (K.width, K.height) == (2 * W, 2 * H)
    f = reader.frame(2)
    assert f.rgb.shape == (2 * H, 2 * W, 3)
    np.testing.assert_array_equal(f.depth, np.repeat(np.repeat(np.rint(scene.depth_m[2] * 1000), 2, 0), 2, 1))
    assert K.scaled(W, H).cx == pytest.approx(scene.K.cx)


def test_scannetpp_accepts_the_iphone_folder(written) -> None:
    assert len(ScanNetppReader(written["scannetpp"][0] / "iphone")) == N


def test_tum_skips_unmatched_frames(written, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="shared.datasets.tum"):
        reader = open_sequence(written["tum"][0], "tum")
    assert len(reader) == N  # the 6th colour frame has no depth
    assert "skipped 1 of 6" in caplog.text


def test_tum_stricter_association_skips_more(written) -> None:
    cfg = SourceConfig(tum={"max_time_diff_s": 0.0055})
    assert len(open_sequence(written["tum"][0], "tum", cfg)) == 3  # jitters of 6 and 8 ms fail


def test_replica_instances(scene: Scene, tmp_path: Path) -> None:
    ids = np.full((N, H, W), -1, np.int64)
    ids[:, 6:15, 10:21] = 7
    ids[:, 20:, :5] = 0
    reader = ReplicaReader(write_replica(scene, tmp_path, instances=ids))
    got = reader.instances(1)
    assert reader.has_instances and got is not None and got.dtype == np.int32
    np.testing.assert_array_equal(got, ids[1])
    assert ReplicaReader(write_replica(scene, tmp_path / "plain")).instances(1) is None


def test_default_intrinsics_when_no_json(scene: Scene, tmp_path: Path) -> None:
    assert ReplicaReader(write_replica(scene, tmp_path / "r", with_intrinsics=False)).intrinsics == REPLICA_INTRINSICS
    assert open_sequence(write_hm3d(scene, tmp_path / "h", with_intrinsics=False), "hm3d").intrinsics == HM3D_INTRINSICS
    tum = open_sequence(write_tum(scene, tmp_path / "t", with_intrinsics=False), "tum")
    assert tum.intrinsics == TUM_FR1_INTRINSICS and tum.depth_scale == 5000.0
    assert (HM3D_INTRINSICS.cx, HM3D_INTRINSICS.cy) == (539.5, 359.5)


def test_strided_access_and_bounds(written) -> None:
    reader = open_sequence(written["replica"][0])
    assert [f.frame_index for f in (reader.frame(i) for i in range(0, N, 2))] == [0, 2, 4]
    with pytest.raises(IndexError):
        reader.frame(N)
    with pytest.raises(IndexError):
        reader.pose(-1)


def test_unknown_dataset_lists_choices(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="choose one of: " + ", ".join(DATASETS)):
        open_sequence(tmp_path, "kitti")


def test_rosbags_imported_only_for_bags(written) -> None:
    code = (
        "import sys; from shared.datasets import open_sequence; "
        f"open_sequence({str(written['replica'][0])!r}).frame(0); "
        "assert not any(m.startswith('rosbags') for m in sys.modules), 'rosbags imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(__file__).resolve().parents[3])
