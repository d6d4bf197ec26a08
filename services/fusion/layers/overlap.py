"""What one mesh says about tracks and segments: the (vertex, track) hypothesis incidence, which
stored vertices the mesh re-observes, and the overlap rule of eq. 7 that attaches a new track to
an active segment (III-D). Used by :class:`services.fusion.layers.segments.SegmentLayer`."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated

import numpy as np
from scipy.spatial import cKDTree

from services.fusion.layers.reid import unit, within
from services.fusion.layers.segment import Segment
from services.fusion.types import HypothesisMesh
from shared.config.fusion import SegmentsConfig

Window = tuple[Annotated[np.ndarray, "(3,) float world metres, centre"], float]
"""The active window as (centre, radius in metres)."""


class Incidence:
    """The (vertex, track) hypothesis incidence of one mesh, in compact track indices.

    Tracks are numbered 0..T-1 in ascending id order; pairs are sorted by (track, vertex), so
    each track's vertices are one contiguous, ascending slice (a CSR of track -> vertices).
    """

    def __init__(self, mesh: HypothesisMesh) -> None:
        hyp = mesh.hyp_ids
        rows, cols = np.nonzero(hyp >= 0)
        ids = hyp[rows, cols].astype(np.int64)
        weights = mesh.hyp_weights[rows, cols].astype(np.float64)
        self._lut: np.ndarray | None = None
        if ids.size and int(ids.max()) < 4 * ids.size + 65536:
            # Track ids are small counters: a lookup table compacts them without sorting.
            present = np.zeros(int(ids.max()) + 1, bool)
            present[ids] = True
            self.track_ids = np.flatnonzero(present)
            self._lut = np.where(present, np.cumsum(present, dtype=np.int64) - 1, -1)
            tc = self._lut[ids]
        else:
            self.track_ids, tc = np.unique(ids, return_inverse=True)
            tc = tc.reshape(-1)
        t = len(self.track_ids)
        # np.nonzero yields rows ascending, so a stable sort by track leaves each track's
        # vertices ascending; 16-bit keys get numpy's linear-time radix sort.
        order = np.argsort(tc.astype(np.uint16) if t <= 65536 else tc, kind="stable")
        pt, pv, pw = tc[order], rows[order], weights[order]
        dup = (pt[1:] == pt[:-1]) & (pv[1:] == pv[:-1])
        if dup.any():
            # A voxel listed a track twice: one pair, with the weights added.
            first = np.concatenate([[True], ~dup])
            pw = np.bincount(np.cumsum(first) - 1, pw)
            pt, pv = pt[first], pv[first]
        self.pair_vertex = pv
        self.starts = np.searchsorted(pt, np.arange(t + 1))
        self.weight = np.bincount(pt, pw, t)
        self.hyp_c = self.compact(hyp).astype(np.int32)
        self.hyp_w = mesh.hyp_weights
        """(V, K) weight of each slot of ``hyp_c`` (eq. 7's evidence overlap reads it)."""
        self.winner = self.compact(mesh.winners())
        self.wins = np.bincount(self.winner[self.winner >= 0], minlength=t)
        self.index = {int(tid): i for i, tid in enumerate(self.track_ids)}

    def compact(self, ids: np.ndarray) -> np.ndarray:
        """Track ids (any shape, -1 = none) to compact indices (-1 = none or not on this mesh)."""
        ids = np.asarray(ids, np.int64)
        if len(self.track_ids) == 0:
            return np.full(ids.shape, -1, np.int64)
        if self._lut is not None:
            inside = (ids >= 0) & (ids < len(self._lut))
            return np.where(inside, self._lut[np.clip(ids, 0, len(self._lut) - 1)], -1)
        c = np.minimum(np.searchsorted(self.track_ids, ids), len(self.track_ids) - 1)
        return np.where((ids >= 0) & (self.track_ids[c] == ids), c, -1)

    def vertices_of(self, c: int) -> Annotated[np.ndarray, "(n,) int64 ascending"]:
        return self.pair_vertex[self.starts[c] : self.starts[c + 1]]


class MeshCover:
    """Which stored vertices the latest mesh has re-observed, and so replaces.

    A stored vertex within ``radius`` of a vertex of the latest mesh lies on a surface the mesh
    reconstructs again, where the latest winners are authoritative; one farther away is
    archived geometry (it left the window) and is kept. When the caller names the window, a
    stored vertex inside it that the mesh no longer covers was carved away, and is dropped too.
    """

    def __init__(self, mesh: HypothesisMesh, radius: float, window: Window | None) -> None:
        self.vertices = mesh.vertices
        self.radius = radius
        self.window = window
        self._tree: cKDTree | None = None

    def keep(
        self, points: Annotated[np.ndarray, "(N, 3) float"]
    ) -> Annotated[np.ndarray, "(N,) bool"]:
        if len(points) == 0 or len(self.vertices) == 0:
            keep = np.ones(len(points), bool)
        else:
            if self._tree is None:
                # Built once per update and thrown away: a cheap, unbalanced build pays off.
                self._tree = cKDTree(
                    np.asarray(self.vertices, np.float64), balanced_tree=False, compact_nodes=False
                )
            keep = ~within(points, self._tree, self.radius)
        if self.window is not None and len(points):
            centre, radius = self.window
            d = np.linalg.norm(points - np.asarray(centre, np.float64)[None, :], axis=1)
            keep &= d > radius
        return keep


def match_segment(
    c: int,
    dino: Annotated[np.ndarray, "(D,) float32 unit DINOv3 feature of track c"],
    inc: Incidence,
    seg_of: Annotated[np.ndarray, "(T,) int64 segment of each compact track, -1 none"],
    active_now: set[int],
    sizes: dict[int, int],
    segments: Mapping[int, Segment],
    cfg: SegmentsConfig,
) -> int | None:
    """The active segment track ``c`` belongs to under eq. 7 and the DINOv3 gate, or None.
    ``sizes`` caches |V_i| per segment across the calls of one update."""
    vq = inc.vertices_of(c)
    cq = inc.hyp_c[vq]
    slot_seg = np.where(cq >= 0, seg_of[np.maximum(cq, 0)], -1)
    # A vertex counts once per segment even if several of the segment's tracks are on it.
    segs = np.sort(slot_seg, axis=1)
    segs[:, 1:][segs[:, 1:] == segs[:, :-1]] = -1
    ids, shared = np.unique(segs[segs >= 0], return_counts=True)
    theta = cfg.theta_rho
    evidence = cfg.containment == "evidence"
    if evidence:
        wq = inc.hyp_w[vq]
        lq = np.where(cq == c, wq, 0.0).sum(axis=1, dtype=np.float64)
        lq_total = float(lq.sum())
    best_key: tuple | None = None
    best: int | None = None
    for sid, n in zip(ids.tolist(), shared.tolist(), strict=True):
        if n < cfg.min_shared or sid not in active_now:
            continue
        if sid not in sizes:
            sizes[sid] = hypothesis_support(segments[sid].tracks, inc)
        rho_q, rho_i = n / len(vq), n / sizes[sid]
        if evidence and lq_total > 0:
            # The share of the track's evidence that the segment's matches (SegmentsConfig.
            # containment): stray hypotheses of the segment do not make the track its part.
            li = np.where(slot_seg == sid, wq, 0.0).sum(axis=1, dtype=np.float64)
            rho_q = float(np.minimum(lq, li).sum()) / lq_total
        if rho_q < theta and rho_i < theta:
            continue
        sim = float(unit(dino) @ unit(segments[sid].dino))
        if sim < cfg.theta_sim:
            continue
        # Mutual overlap (a near-duplicate) beats containment (over-segmentation), then the
        # shared vertex count, then appearance; the smaller id settles exact ties.
        key = (rho_q >= theta and rho_i >= theta, n, sim, -sid)
        if best_key is None or key > best_key:
            best_key, best = key, sid
    return best

def hypothesis_support(tracks: set[int], inc: Incidence) -> int:
    """|V_i|: vertices of this mesh holding a hypothesis of any of a segment's ``tracks``."""
    cs = [inc.index[t] for t in tracks if t in inc.index]
    if len(cs) == 1:
        return len(inc.vertices_of(cs[0]))
    return int(np.unique(np.concatenate([inc.vertices_of(c) for c in cs])).size) if cs else 0
