"""TSDF with hypotheses on an analytic scene: mesh accuracy, vertex winners, backends agreeing,
the active window and the state round trip."""

from __future__ import annotations

import numpy as np
import pytest

from shared.config.fusion import TSDFConfig
from shared.geometry import Intrinsics
from shared.o3d import import_open3d

try:
    import_open3d()
except ImportError:
    pytest.skip("open3d is not installed (fusion extra)", allow_module_level=True)

from services.fusion.types import HypothesisMesh  # noqa: E402
from services.fusion.volume.hypotheses import numba_available  # noqa: E402
from services.fusion.volume.tsdf import HypothesisTSDF  # noqa: E402
from services.fusion.volume.window import pack_keys  # noqa: E402

K = Intrinsics(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)

# Axis-aligned boxes (min corner, max corner, object id, colour), OpenCV world axes (y down):
# a wall behind, a box standing in front of it, and the floor.
BOXES = [
    ((-3.0, -2.0, 3.0), (3.0, 2.0, 3.3), 1, (200, 180, 160)),
    ((-0.4, -0.3, 1.6), (0.4, 0.5, 2.2), 2, (40, 90, 220)),
    ((-3.0, 0.9, 0.0), (3.0, 1.1, 3.0), 3, (90, 160, 70)),
]
GAMMA = {1: 1.0, 2: 1.0, 3: 0.25}


def render(T_world_cam: np.ndarray, k: Intrinsics = K):
    """Exact z-depth, colour and object id per pixel by ray/box slab intersection."""
    u, v = np.meshgrid(np.arange(k.width), np.arange(k.height))
    d_cam = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones(u.shape)], -1).reshape(-1, 3)
    d = d_cam @ T_world_cam[:3, :3].T  # camera z = 1, so the ray parameter is the z-depth
    o = T_world_cam[:3, 3]
    best = np.full(len(d), np.inf)
    ids = np.full(len(d), -1, np.int32)
    rgb = np.zeros((len(d), 3), np.uint8)
    with np.errstate(divide="ignore", invalid="ignore"):
        for lo, hi, oid, colour in BOXES:
            t1, t2 = (np.array(lo) - o) / d, (np.array(hi) - o) / d
            t_near = np.nanmax(np.minimum(t1, t2), 1)
            t_far = np.nanmin(np.maximum(t1, t2), 1)
            hit = (t_near <= t_far) & (t_near > 0) & (t_near < best)
            best[hit], ids[hit], rgb[hit] = t_near[hit], oid, colour
    depth = np.where(np.isfinite(best), best, 0).astype(np.float32)
    return (
        depth.reshape(k.height, k.width),
        rgb.reshape(k.height, k.width, 3),
        ids.reshape(k.height, k.width),
    )


def surface_distances(points: np.ndarray) -> np.ndarray:
    """(N, boxes) unsigned distance from each point to each box surface."""
    out = []
    for lo, hi, _, _ in BOXES:
        c, h = (np.array(lo) + hi) / 2, (np.array(hi) - lo) / 2
        q = np.abs(points - c) - h
        out.append(np.abs(np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)))
    return np.stack(out, 1)


def look_at(eye, target) -> np.ndarray:
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, (0.0, -1.0, 0.0))
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, eye
    return T


POSES = [look_at(np.array([x, -0.3, 0.0]), (0.0, 0.2, 2.5)) for x in np.linspace(-0.5, 0.5, 5)]
FRAMES = [(T, *render(T)) for T in POSES]


def fused(cfg: TSDFConfig | None = None, backend: str = "auto", frames=FRAMES) -> HypothesisTSDF:
    cfg = (cfg or TSDFConfig()).model_copy(update={"vote_backend": backend})
    tsdf = HypothesisTSDF(cfg, device="cpu")
    for T, depth, rgb, ids in frames:
        tsdf.integrate(depth, rgb, K, T, ids, GAMMA)
    return tsdf


@pytest.fixture(scope="module")
def scene() -> HypothesisTSDF:
    return fused()


def assert_same_mesh(a: HypothesisMesh, b: HypothesisMesh) -> None:
    for name in ("vertices", "colors", "faces", "hyp_ids", "hyp_weights"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def all_blocks(state: dict) -> dict[str, np.ndarray]:
    """Active and archived blocks of a state dict together, sorted by key."""
    keys = np.concatenate([state["keys"], state["archive_keys"]])
    order = np.argsort(pack_keys(keys))
    out = {"keys": keys[order]}
    for name in ("tsdf", "weight", "color", "hyp_id", "hyp_w"):
        out[name] = np.concatenate([state[name], state[f"archive_{name}"]])[order]
    return out


def test_mesh_lies_on_the_true_surfaces(scene):
    mesh = scene.extract_mesh()
    assert len(mesh) > 3000 and mesh.faces.shape[1] == 3
    assert mesh.faces.max() < len(mesh) and mesh.faces.dtype == np.int32
    dist = surface_distances(mesh.vertices.astype(np.float64)).min(1)
    vs = scene.cfg.voxel_size
    assert np.median(dist) < 0.1 * vs
    assert np.percentile(dist, 95) < 0.5 * vs
    assert dist.max() < 2.5 * vs  # the worst are TSDF corners seen at grazing angles


def test_vertex_winners_are_the_true_objects(scene):
    mesh = scene.extract_mesh()
    d = surface_distances(mesh.vertices.astype(np.float64))
    true_id = np.array([b[2] for b in BOXES])[d.argmin(1)]
    srt = np.sort(d, 1)
    clear = srt[:, 1] - srt[:, 0] > 1.5 * scene.cfg.voxel_size  # away from object contacts
    win = mesh.winners()
    assert clear.mean() > 0.9
    has = clear & (win >= 0)
    assert has.sum() > 0.95 * clear.sum()
    assert (win[has] == true_id[has]).mean() > 0.995
    # every object is represented, and vertex colours come from the object's colour
    for _, _, oid, colour in BOXES:
        sel = has & (true_id == oid)
        assert sel.sum() > 100
        assert np.abs(np.median(mesh.colors[sel].astype(int), axis=0) - colour).max() <= 2


@pytest.mark.skipif(not numba_available(), reason="numba not installed")
def test_numba_and_torch_agree_bit_for_bit():
    import torch

    a = fused(backend="numba", frames=FRAMES[:3]).state_dict()
    # one torch thread: its OpenMP pool and Open3D's spin against each other on a small CPU
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        b = fused(backend="torch", frames=FRAMES[:3]).state_dict()
    finally:
        torch.set_num_threads(threads)
    for name in ("keys", "tsdf", "weight", "color", "hyp_id", "hyp_w"):
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert (a["hyp_id"] > 0).sum() > 1000


def test_window_archives_and_restores_without_loss():
    tsdf = fused(TSDFConfig(active_window_m=8.0, restore_archived=True))
    before_mesh = tsdf.extract_mesh()
    before = all_blocks(tsdf.state_dict())
    n = tsdf.active_blocks

    st = tsdf.update_window(np.array([100.0, 0.0, 0.0]))
    assert (st.archived, st.restored, st.active_blocks, st.archived_blocks) == (n, 0, 0, n)
    assert len(tsdf.extract_mesh()) == 0
    assert tsdf.hypotheses_at(np.array([[0.0, 0.0, 1.6]]))[0].max() == -1

    st = tsdf.update_window(np.array([0.0, 0.0, 1.5]))
    assert (st.archived, st.restored, st.active_blocks, st.archived_blocks) == (0, n, n, 0)
    assert_same_mesh(before_mesh, tsdf.extract_mesh())
    after = all_blocks(tsdf.state_dict())
    for name, arr in before.items():
        np.testing.assert_array_equal(arr, after[name], err_msg=name)


def test_archived_mesh_completes_the_window_mesh():
    """A whole-map export: the archive's mesh plus the window's is the mesh before archiving."""
    tsdf = fused(TSDFConfig(active_window_m=8.0))
    whole = tsdf.extract_mesh()
    assert len(tsdf.extract_archived_mesh()) == 0
    tsdf.update_window(np.array([100.0, 0.0, 0.0]))  # everything leaves
    assert len(tsdf.extract_mesh()) == 0
    assert_same_mesh(whole, tsdf.extract_archived_mesh())
    np.testing.assert_array_equal(whole.winners(), tsdf.extract_archived_mesh().winners())


def test_window_partial_and_frustum_restore():
    tsdf = fused(TSDFConfig(active_window_m=2.0, restore_archived=True))
    total = tsdf.active_blocks
    before = all_blocks(tsdf.state_dict())
    st = tsdf.update_window(np.array([0.0, 0.0, 0.0]))  # the wall (z >= 3 m) leaves
    assert 0 < st.archived < total and st.active_blocks + st.archived_blocks == total
    mesh = tsdf.extract_mesh()
    assert np.linalg.norm(mesh.vertices, axis=1).max() < 2.0 + tsdf.res * tsdf.cfg.voxel_size
    # a frame that sees the wall brings its archived blocks back before integrating
    T, depth, rgb, ids = FRAMES[2]
    st = tsdf.integrate(depth, rgb, K, T, ids, GAMMA)
    assert st.restored_blocks > 0
    keys = np.concatenate([tsdf.state_dict()["keys"], tsdf.state_dict()["archive_keys"]])
    assert len(np.unique(pack_keys(keys))) == len(keys)  # no block twice
    # nothing was lost: the archived blocks that were not restored are unchanged
    state = tsdf.state_dict()
    rows = np.searchsorted(pack_keys(before["keys"]), pack_keys(state["archive_keys"]))
    np.testing.assert_array_equal(before["hyp_w"][rows], state["archive_hyp_w"])
    np.testing.assert_array_equal(before["tsdf"][rows], state["archive_tsdf"])


def test_revisit_rebuilds_afresh_by_default():
    """The paper's window: a revisit reconstructs with new hypotheses and leaves the archive
    alone; archiving the rebuilt blocks again replaces their older copies (no key twice)."""
    tsdf = fused(TSDFConfig(active_window_m=8.0))
    n = tsdf.active_blocks
    old = all_blocks(tsdf.state_dict())
    st = tsdf.update_window(np.array([100.0, 0.0, 0.0]))
    assert (st.archived, st.active_blocks, st.archived_blocks) == (n, 0, n)
    st = tsdf.update_window(np.array([0.0, 0.0, 1.5]))
    assert (st.restored, st.active_blocks, st.archived_blocks) == (0, 0, n)
    T, depth, rgb, ids = FRAMES[0]
    rebuilt = tsdf.integrate(depth, rgb, K, T, np.where(ids >= 0, ids + 100, -1).astype(np.int32), {t + 100: g for t, g in GAMMA.items()})
    assert rebuilt.restored_blocks == 0 and tsdf.active_blocks > 0
    fresh = tsdf.hypotheses_at(np.array([[0.0, 0.0, 3.0]]))[0]
    assert set(fresh[fresh >= 0].tolist()) <= {t + 100 for t in GAMMA}, "old hypotheses must not come back"
    new_keys = tsdf.state_dict()["keys"]
    st = tsdf.update_window(np.array([100.0, 0.0, 0.0]))
    keys = tsdf.state_dict()["archive_keys"]
    assert len(np.unique(pack_keys(keys))) == len(keys) == st.archived_blocks
    # every block, old or rebuilt, is archived exactly once
    assert st.archived_blocks == len(np.union1d(pack_keys(old["keys"]), pack_keys(new_keys)))


def test_state_round_trip_is_identical(tmp_path):
    tsdf = fused(TSDFConfig(active_window_m=2.5), frames=FRAMES[:4])
    tsdf.update_window(np.array([0.0, 0.0, 0.5]))
    assert tsdf.archived_blocks > 0
    path = tmp_path / "tsdf.npz"
    np.savez(path, **tsdf.state_dict())
    loaded = HypothesisTSDF(TSDFConfig(active_window_m=2.5), device="cpu")
    with np.load(path) as z:
        loaded.load_state_dict(dict(z))
    assert (loaded.active_blocks, loaded.archived_blocks) == (
        tsdf.active_blocks,
        tsdf.archived_blocks,
    )
    assert_same_mesh(tsdf.extract_mesh(), loaded.extract_mesh())
    # and fusion resumes identically from the reloaded state
    T, depth, rgb, ids = FRAMES[4]
    for t in (tsdf, loaded):
        t.update_window(T[:3, 3])
        t.integrate(depth, rgb, K, T, ids, GAMMA)
    assert_same_mesh(tsdf.extract_mesh(), loaded.extract_mesh())
    a, b = tsdf.state_dict(), loaded.state_dict()
    assert a.keys() == b.keys()
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)

    with pytest.raises(ValueError, match="voxel_size"):
        HypothesisTSDF(TSDFConfig(voxel_size=0.05), device="cpu").load_state_dict(a)


def test_unsure_propagated_pixels_do_not_vote():
    """``tsdf.min_label_confidence``: where eq. 1 gave a pixel's track a low probability, the
    pixel adds no hypothesis; the TSDF itself still integrates its depth."""
    from services.fusion.core import FusionCore
    from shared.config.fusion import FusionConfig
    from shared.messages.frames import Frame, TrackedFrame, TrackObservation

    def tracked(i, T, depth, rgb, ids) -> TrackedFrame:
        wrong = np.where(ids == 2, 9, ids).astype(np.int32)  # propagation named the neighbour
        conf = np.where(ids == 2, 60, 255).astype(np.uint8)  # ... and was unsure of it
        frame = Frame(frame_index=i, rgb=rgb, depth=np.round(depth * 1000).astype(np.uint16),
                      depth_scale=1000.0, intrinsics=K, T_world_cam=T)
        obs = [TrackObservation(track_id=int(t), keyframe=False, frames_since_keyframe=1) for t in np.unique(wrong) if t >= 0]
        return TrackedFrame(frame=frame, track_ids=wrong, tracks=obs, confidence=conf)

    def winners(min_conf: float) -> set[int]:
        cfg = FusionConfig.model_validate({"tsdf": {"min_label_confidence": min_conf}, "mesh_every_n_frames": 1000})
        fusion = FusionCore(cfg, device="cpu")
        for i, f in enumerate(FRAMES):
            fusion.add_frame(tracked(i, *f))
        mesh = fusion.tsdf.extract_mesh()
        d = surface_distances(mesh.vertices.astype(np.float64))
        on_box = (d.argmin(1) == 1) & (np.sort(d, 1)[:, 1] > 0.05)
        assert on_box.sum() > 100  # the box is reconstructed either way
        return {int(w) for w in np.unique(mesh.winners()[on_box])}

    assert 9 not in winners(0.8)
    assert 9 in winners(0.0)  # the paper fuses every propagated pixel


def test_a_pixel_stride_fuses_the_same_surfaces_and_winners():
    """``tsdf.pixel_stride: 2`` on 640x480 frames fuses a quarter of the pixels (320x240) with
    the matching intrinsics: the mesh is as large and as accurate as at every pixel, and its
    winners are still the true objects (the vote is a share of each voxel's pixels, eq. 5 as
    fusion applies it)."""
    from services.fusion.core import FusionCore
    from shared.config.fusion import FusionConfig
    from shared.messages.frames import Frame, TrackedFrame, TrackObservation

    k2 = K.scaled(640, 480)

    def tracked(i, T, depth, rgb, ids) -> TrackedFrame:
        frame = Frame(frame_index=i, rgb=rgb, depth=np.round(depth * 1000).astype(np.uint16),
                      depth_scale=1000.0, intrinsics=k2, T_world_cam=T)  # fmt: skip
        obs = [TrackObservation(track_id=int(t), keyframe=True, frames_since_keyframe=0) for t in np.unique(ids) if t >= 0]
        return TrackedFrame(frame=frame, track_ids=ids, tracks=obs)

    meshes = {}
    for step in (1, 2):
        cfg = FusionConfig.model_validate({"tsdf": {"pixel_stride": step}, "mesh_every_n_frames": 1000})
        fusion = FusionCore(cfg, device="cpu")
        for i, T in enumerate(POSES):
            fusion.add_frame(tracked(i, T, *render(T, k2)))
        meshes[step] = fusion.tsdf.extract_mesh()
    full, strided = meshes[1], meshes[2]
    assert abs(len(strided) - len(full)) < 0.05 * len(full)
    d = surface_distances(strided.vertices.astype(np.float64))
    vs = TSDFConfig().voxel_size
    assert np.median(d.min(1)) < 0.1 * vs and np.percentile(d.min(1), 95) < 0.5 * vs
    true_id = np.array([b[2] for b in BOXES])[d.argmin(1)]
    clear = np.sort(d, 1)[:, 1] - np.sort(d, 1)[:, 0] > 1.5 * vs
    win = strided.winners()
    has = clear & (win >= 0)
    assert has.sum() > 0.95 * clear.sum() and (win[has] == true_id[has]).mean() > 0.995
