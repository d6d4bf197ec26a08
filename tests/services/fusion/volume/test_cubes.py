"""The numba marching cubes of the map path (services/fusion/volume/cubes.py): its case table
closes every surface, a sphere comes out watertight and outward-wound across blocks, and on
a fused scene it gives Open3D's vertices, colours, anchors and hypotheses to the bit."""

from __future__ import annotations

import numpy as np
import pytest

from services.fusion.volume import cubes
from services.fusion.volume.cubes import (
    CORNERS,
    EDGES,
    BlockCopy,
    case_table,
    hypothesis_mesh,
    march,
)

if not cubes.available():
    pytest.skip("numba is not installed (fusion extra)", allow_module_level=True)


def test_the_table_puts_a_vertex_on_every_sign_change_and_closes_each_case():
    tris, bits = case_table()
    for case in range(256):
        inside = [(case >> k) & 1 for k in range(8)]
        crossing = {e for e, (a, b) in enumerate(EDGES.tolist()) if inside[a] != inside[b]}
        assert {e for e in range(12) if (bits[case] >> e) & 1} == crossing, case
        row = tris[case][tris[case] >= 0].reshape(-1, 3)
        assert set(row.reshape(-1).tolist()) == crossing, case
        # inside the cube the surface is a set of closed polygons: every edge between two of
        # its vertices is used once each way, except polygon rims on the cube's faces
        directed = {(int(a), int(b)) for t in row for a, b in zip(t, np.roll(t, -1), strict=True)}
        assert len(directed) == 3 * len(row), case  # no triangle edge repeated in one direction


def _sphere_blocks(radius: float, centre: np.ndarray, res: int = 8, voxel: float = 0.1) -> BlockCopy:
    """Every block within reach of a sphere's signed distance (positive outside, so the
    outside is TSDF > 0), all voxels with weight 5; hypotheses by octant."""
    span = int(np.ceil((radius + 2 * voxel) / (res * voxel))) + 1
    keys = np.array([[x, y, z] for x in range(-span, span) for y in range(-span, span) for z in range(-span, span)], np.int32)
    g = np.arange(res)
    zz, yy, xx = np.meshgrid(g, g, g, indexing="ij")
    pts = (keys[:, None, None, None, :] * res + np.stack([xx, yy, zz], -1)[None]) * voxel  # (B, r, r, r, 3) [z, y, x]
    sdf = (np.linalg.norm(pts - centre, axis=-1) - radius).astype(np.float32)
    n = len(keys)
    octant = ((pts[..., 0] > centre[0]) * 1 + (pts[..., 1] > centre[1]) * 2 + 1).astype(np.int32)
    hyp_id = np.zeros((n, res, res, res, 2), np.int32)
    hyp_id[..., 0] = octant
    hyp_w = np.zeros((n, res, res, res, 2), np.float32)
    hyp_w[..., 0] = 3.0
    return BlockCopy(
        keys=keys, tsdf=sdf, weight=np.full(sdf.shape, 5.0, np.float32),
        color=np.broadcast_to(np.array([10.0, 120.0, 250.0], np.float32), (*sdf.shape, 3)).copy(),
        hyp_id=hyp_id, hyp_w=hyp_w, anchor=np.full(sdf.shape, 7, np.int32),
    )  # fmt: skip


def test_a_sphere_across_blocks_is_closed_and_wound_outwards():
    centre = np.array([0.03, -0.02, 0.05])
    pos, col, faces, (ids_a, w_a, _, _), anc = march(_sphere_blocks(0.55, centre), 0.1, 1.0)
    assert len(faces) > 500
    # closed and consistently wound: every directed edge once, its reverse once
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    directed = set(map(tuple, e.tolist()))
    assert len(directed) == len(e) and all((b, a) in directed for a, b in directed)
    # on the sphere (linear interpolation of the distance is exact up to its curvature)
    r = np.linalg.norm(pos - centre, axis=1)
    assert np.abs(r - 0.55).max() < 0.01
    # each face's normal points out of the sphere, to TSDF > 0
    p = pos[faces]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert (np.einsum("ij,ij->i", normal, p.mean(axis=1) - centre) > 0).all()
    assert (col == [10, 120, 250]).all() and (anc == 7).all()
    assert set(np.unique(ids_a[:, 0])) <= {0, 1, 2, 3} and (w_a[:, 0] > 0).all()


def test_a_missing_neighbour_block_or_a_light_voxel_leaves_the_cube_out():
    blocks = _sphere_blocks(0.55, np.zeros(3))
    full = march(blocks, 0.1, 1.0)[0]
    blocks.weight[0] = 0.5  # below the threshold: that block's cubes are left out
    assert 0 < len(march(blocks, 0.1, 1.0)[0]) <= len(full)
    heavy = _sphere_blocks(0.55, np.zeros(3))
    assert len(march(heavy, 0.1, 5.0)[0]) == 0  # weight 5 is not above 5


def test_an_empty_copy_is_an_empty_mesh():
    empty = BlockCopy(keys=np.zeros((0, 3), np.int32), tsdf=np.zeros((0, 8, 8, 8), np.float32), weight=np.zeros((0, 8, 8, 8), np.float32),
                      color=np.zeros((0, 8, 8, 8, 3), np.float32), hyp_id=np.zeros((0, 8, 8, 8, 3), np.int32),
                      hyp_w=np.zeros((0, 8, 8, 8, 3), np.float32), anchor=np.zeros((0, 8, 8, 8), np.int32))  # fmt: skip
    assert len(hypothesis_mesh(empty, 0.05, 3, 1.0)) == 0


def test_it_gives_open3ds_vertices_colours_and_hypotheses_on_a_fused_scene():
    from services.fusion.volume.mesh import extract_hypothesis_mesh
    from tests.services.fusion.volume.test_tsdf_scene import fused

    tsdf = fused()
    ours = tsdf.mesh_of(tsdf.copy_active())
    theirs = extract_hypothesis_mesh(tsdf.vbg, tsdf.cfg.voxel_size, tsdf.res, tsdf.K, tsdf.mesh_weight_threshold)
    assert len(ours) > 1000
    np.testing.assert_array_equal(ours.vertices, theirs.vertices)
    np.testing.assert_array_equal(ours.colors, theirs.colors)
    np.testing.assert_array_equal(ours.anchors, theirs.anchors)
    np.testing.assert_array_equal(ours.hyp_ids, theirs.hyp_ids)
    # Open3D's path reads each end's share back off the float32 vertex (a 1e-5 voxel error);
    # the kernel keeps the interpolation ratio itself
    np.testing.assert_allclose(ours.hyp_weights, theirs.hyp_weights, rtol=1e-3)
    assert len(ours.faces) == len(theirs.faces)  # the same surface, possibly other diagonals

    def vector_area(m):
        p = m.vertices[m.faces].astype(np.float64)
        return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]).sum(axis=0) / 2

    # wound the same way: the surface's vector area is the same (up to the diagonals' share)
    a, b = vector_area(ours), vector_area(theirs)
    assert np.linalg.norm(a - b) < 0.02 * np.linalg.norm(b), (a, b)
    assert CORNERS.shape == (8, 3)
