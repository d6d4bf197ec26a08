"""The 3D segment layer: persistent class-agnostic segments built from source tracks (paper III-D),
with long-term re-identification of revisited segments (III-E) and CLIP galleries (III-F).

Each update takes the marching-cubes mesh of the active window with its per-vertex hypotheses
H = {(tau_k, l_k)} and the latest state of every source track, and

1. gives each track that wins at least ``min_vertices`` vertices and has no segment yet a
   segment: an active segment it overlaps (eq. 7 and the DINOv3 gate) or a new one;
2. re-assigns the window's vertices to segments by their winning track tau*, keeping the
   geometry a segment had outside the current mesh (see ``SegmentLayer`` on archived geometry);
3. refreshes each segment's bounds, aggregated DINOv3 feature and CLIP gallery;
4. merges active segments into matching historical ones (eqs. 8-9).

Decisions the paper leaves open, made here:

- *Track weight in a segment* (``Segment.track_weight``): the hypothesis weight the track holds
  on the latest mesh it appeared in, summed over every slot (not only where it wins), plus its
  ``TrackState.displaced_weight``. III-C says displaced hypotheses are still accumulated into
  segments; the weight a track lost to slot replacement is evidence for it that the bounded
  voxel state could not keep, so it counts as if it were still on the mesh. A track that left
  the window keeps its last mesh weight, so its past support is not forgotten.
- *Aggregated DINOv3 feature*: the unit-normalised, track-weight-weighted mean of the unit
  DINOv3 features of the segment's tracks. Weighting by evidence lets the tracks that explain
  most of the surface, seen most confidently, dominate its appearance.
- *Tracks without a DINOv3 feature yet* (track features arrive asynchronously) are left
  unassigned until one arrives: creating a segment for them would skip the appearance gate and
  leave duplicates that the active-window matching never revisits.
- *Retired tracks* are still assigned: retirement stops propagation in 2D, but the geometry
  already fused for the track still needs a segment.

Deviation (docs/method.md, F6; ``SegmentsConfig.containment``): rho_{q->i} of eq. 7, "the track
lies inside the segment", weighs each vertex of V_q by the hypothesis weights,
sum min(l_q, l_i) / sum l_q, instead of counting every vertex where the segment holds any
hypothesis. Over a surface the segment was fused on before the track appeared the segment's
weight is the larger one, and the two agree up to weighing each vertex by l_q. They part where
the segment holds only stray weight (a mask boundary, a mask that once fused a rug with the
floor) and the new track outweighs it, which is not a re-observation of the segment.
rho_{i->q} counts as the paper does.
"""


from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Annotated

import numpy as np
from scipy.spatial import cKDTree

from services.fusion.corrections.poses import Motion
from services.fusion.layers.gallery import sync_gallery
from services.fusion.layers.overlap import Incidence, MeshCover, Window, match_segment
from services.fusion.layers.reid import ReidMatch, best_match, unit
from services.fusion.layers.segment import Segment, no_vertices
from services.fusion.types import HypothesisMesh, TrackState
from shared.config.fusion import ReidConfig, SegmentsConfig
from shared.messages.graph import SegmentNode

log = logging.getLogger(__name__)

STATE_FORMAT = 1


@dataclass
class SegmentChanges:
    """What one ``SegmentLayer.update`` did, by segment id (each list ascending)."""

    added: list[int] = field(default_factory=list)
    """Created in this update (and not merged away in it)."""
    changed: list[int] = field(default_factory=list)
    """Existing before this update and different in anything ``to_node`` reports."""
    removed: list[int] = field(default_factory=list)
    """Existing before this update and merged into a historical segment by re-identification."""
    merged: dict[int, int] = field(default_factory=dict)
    """query id -> historical id it was merged into (including queries created in this update),
    so the graph can redirect the query's edges."""



class SegmentLayer:
    """The segment layer N_S of the scene graph, updated from each active-window mesh.

    Re-identification queries every active segment on every update: a segment that was small
    or far from any historical one at creation may grow onto a revisited surface later. This
    stays cheap because the centroid k-d tree limits each query to H_q, the cosine gate runs
    before the vertex overlap, and a historical segment's vertex k-d tree is built once and
    kept while it stays historical (its geometry is frozen).

    On a merge (III-E) the query's tracks, gallery rows, per-track features and vertices move
    into the historical segment, which becomes active; the historical segment's own stored
    vertices that the current mesh re-observes are replaced by the query's, as the paper's
    "becomes active again with the newly reconstructed geometry". Several queries may merge
    into one historical segment in the same update: each picks its best candidate among the
    segments historical before the update's merges, so the outcome does not depend on order.

    Geometry outside the window: ``positions`` keeps a segment's vertices that the latest mesh
    does not cover (``MeshCover``), so a segment straddling or leaving the window keeps its full
    extent for its box, centroid and re-identification. Coverage uses ``ReidConfig.r_nn``, the
    paper's own radius for "the same surface" (eq. 8).
    """

    def __init__(self, seg_cfg: SegmentsConfig, reid_cfg: ReidConfig) -> None:
        self.seg_cfg = seg_cfg
        self.reid_cfg = reid_cfg
        self.segments: dict[int, Segment] = {}
        self._track_segment: dict[int, int] = {}
        self._next_id = 0
        self._vertex_segments = np.zeros(0, np.int32)
        self._hist_trees: dict[int, cKDTree] = {}

    # -- queries ------------------------------------------------------------------------------

    def segment_of_track(self, track_id: int) -> int | None:
        """The segment a track is assigned to, if any."""
        return self._track_segment.get(int(track_id))

    def vertex_segments(
        self,
    ) -> Annotated[np.ndarray, "(V,) int32 segment id per latest-mesh vertex, -1 = none"]:
        """Segment of each vertex of the latest mesh (``MeshChunk.segment_ids``)."""
        return self._vertex_segments.copy()

    def nodes(self, ids: list[int] | None = None) -> list[SegmentNode]:
        """Wire form of the given segments (all when None), in ascending id order."""
        keys = sorted(self.segments) if ids is None else sorted(ids)
        return [self.segments[i].to_node() for i in keys]

    # -- update -------------------------------------------------------------------------------

    def update(
        self,
        mesh: HypothesisMesh,
        tracks: Mapping[int, TrackState],
        *,
        window: Window | None = None,
    ) -> SegmentChanges:
        """Fold the latest active-window mesh and track states into the layer (III-D, III-E).

        ``window``, when given, lets stored geometry inside the window that the mesh no longer
        has be dropped (a carved-away surface); without it such geometry is kept.
        """
        inc = Incidence(mesh)
        cover = MeshCover(mesh, self.reid_cfg.r_nn, window)
        added: list[int] = []
        dirty: set[int] = set()
        self._assign_new_tracks(inc, tracks, added, dirty)
        self._refresh_geometry(mesh, inc, cover, dirty)
        self._refresh_features(inc, tracks, dirty)
        changes = SegmentChanges()
        if self.reid_cfg.enabled:
            for m in self._reidentify(cover, dirty):
                changes.merged[m.query] = m.target
        gone = set(changes.merged)
        changes.added = sorted(set(added) - gone)
        changes.removed = sorted(gone - set(added))
        changes.changed = sorted(dirty - set(added) - gone)
        if changes.added or changes.removed or changes.merged:
            log.debug(
                "segments: %d added, %d changed, %d merged by re-identification (%d total)",
                len(changes.added), len(changes.changed), len(changes.merged), len(self.segments),
            )  # fmt: skip
        return changes

    def _assign_new_tracks(
        self, inc: Incidence, tracks: Mapping[int, TrackState], added: list[int], dirty: set[int]
    ) -> None:
        """III-D: attach each unassigned track with enough winning vertices to a segment."""
        seg_of = np.array([self._track_segment.get(int(t), -1) for t in inc.track_ids], np.int64)
        # Active = some track of the segment still wins a vertex of this mesh (the window).
        active_now = {int(s) for s in np.unique(seg_of[(inc.wins > 0) & (seg_of >= 0)])}
        sizes: dict[int, int] = {}
        pending = np.nonzero((seg_of < 0) & (inc.wins >= self.seg_cfg.min_vertices))[0]
        # Best-supported tracks first, so a fragment is matched to the segment of the bulk
        # rather than seeding its own.
        for c in sorted(pending.tolist(), key=lambda c: (-int(inc.wins[c]), int(inc.track_ids[c]))):
            tid = int(inc.track_ids[c])
            state = tracks.get(tid)
            if state is None or state.dino is None:
                log.debug("track %d has %d vertices but no DINOv3 feature yet", tid, inc.wins[c])
                continue
            dino = unit(state.dino).astype(np.float32)
            sid = match_segment(c, dino, inc, seg_of, active_now, sizes, self.segments, self.seg_cfg)
            if sid is None:
                sid = self._next_id
                self._next_id += 1
                self.segments[sid] = Segment(id=sid, tracks={tid}, dino=dino)
                added.append(sid)
                active_now.add(sid)
                log.debug("track %d starts segment %d", tid, sid)
            else:
                self.segments[sid].tracks.add(tid)
                dirty.add(sid)
                log.debug("track %d joins segment %d", tid, sid)
            sizes.pop(sid, None)
            seg_of[c] = sid
            self._track_segment[tid] = sid
            # Later tracks of this update are compared with the grown segment's appearance.
            self._refresh_segment_features(self.segments[sid], inc, tracks)

    def _refresh_geometry(
        self, mesh: HypothesisMesh, inc: Incidence, cover: MeshCover, dirty: set[int]
    ) -> None:
        """Re-assign the mesh's vertices by winning track; set active/historical."""
        seg_of = np.array([self._track_segment.get(int(t), -1) for t in inc.track_ids], np.int64)
        # Group vertices by segment through compact segment keys, so the sort is a radix sort.
        seg_ids, seg_key = np.unique(seg_of[seg_of >= 0], return_inverse=True)
        key_of = np.full(len(seg_of), len(seg_ids), np.int64)
        key_of[seg_of >= 0] = seg_key
        vkey = np.where(
            inc.winner >= 0, key_of[np.maximum(inc.winner, 0)] if len(key_of) else 0, len(seg_ids)
        )
        self._vertex_segments = np.append(seg_ids, -1).astype(np.int32)[vkey]
        order = np.argsort(vkey.astype(np.uint16) if len(seg_ids) < 65536 else vkey, kind="stable")
        bounds_v = np.searchsorted(vkey[order], np.arange(len(seg_ids) + 1))
        current = {
            # A stable sort leaves each group's vertex indices ascending.
            int(sid): order[bounds_v[k] : bounds_v[k + 1]].astype(np.int32)
            for k, sid in enumerate(seg_ids)
            if bounds_v[k + 1] > bounds_v[k]
        }
        anchors = mesh.vertex_anchors()
        # One coverage query for all stored geometry of the segments seen on this mesh.
        seen = sorted(current)
        stored = [self.segments[s].positions for s in seen]
        keep_all = cover.keep(np.concatenate(stored)) if seen else np.zeros(0, bool)
        bounds = np.cumsum([0] + [len(p) for p in stored])
        for k, sid in enumerate(seen):
            seg = self.segments[sid]
            keep = keep_all[bounds[k] : bounds[k + 1]]
            before = seg.summary()
            seg.positions = np.concatenate([seg.positions[keep], mesh.vertices[current[sid]].astype(np.float32)])
            seg.anchors = np.concatenate([seg.anchors[keep], anchors[current[sid]]]).astype(np.int32)
            seg.vertex_ids = current[sid]
            seg.active = True
            seg.refresh_bounds()
            if seg.summary() != before:
                dirty.add(sid)
            self._hist_trees.pop(sid, None)
        for sid, seg in self.segments.items():
            if sid not in current and seg.active:
                # Its stored geometry stays as it was last seen: that is what a revisit is
                # compared against.
                seg.active = False
                seg.vertex_ids = no_vertices()
                dirty.add(sid)
                log.debug("segment %d is historical", sid)

    def _refresh_features(
        self, inc: Incidence, tracks: Mapping[int, TrackState], dirty: set[int]
    ) -> None:
        for sid, seg in self.segments.items():
            if self._refresh_segment_features(seg, inc, tracks):
                dirty.add(sid)

    @staticmethod
    def _refresh_segment_features(
        seg: Segment, inc: Incidence, tracks: Mapping[int, TrackState]
    ) -> bool:
        """Per-track weights and features, the aggregated DINOv3 feature and the gallery."""
        for tid in seg.tracks:
            c = inc.index.get(tid)
            if c is not None:
                seg.track_mesh_weight[tid] = float(inc.weight[c])
            state = tracks.get(tid)
            if state is None:
                continue
            seg.track_displaced[tid] = float(state.displaced_weight)
            if state.dino is not None:
                seg.track_dino[tid] = unit(state.dino).astype(np.float32)
        dino_changed = seg.refresh_dino()
        gallery_changed = sync_gallery(seg.gallery, seg.tracks, tracks)
        return dino_changed or gallery_changed

    # -- re-identification (III-E) ------------------------------------------------------------

    def _hist_tree(self, sid: int) -> cKDTree:
        tree = self._hist_trees.get(sid)
        if tree is None:
            tree = cKDTree(self.segments[sid].positions.astype(np.float64))
            self._hist_trees[sid] = tree
        return tree

    def _reidentify(self, cover: MeshCover, dirty: set[int]) -> list[ReidMatch]:
        hist = sorted(s for s, seg in self.segments.items() if not seg.active and seg.num_vertices)
        if not hist:
            return []
        centroids = cKDTree(np.stack([self.segments[h].centroid for h in hist]))
        matches: list[ReidMatch] = []
        for q in sorted(s for s, seg in self.segments.items() if seg.active):
            seg = self.segments[q]
            near = centroids.query_ball_point(seg.centroid, r=self.reid_cfg.search_radius_m)
            if not near:
                continue
            m = best_match(
                q, seg.positions, seg.dino, [hist[i] for i in near],
                lambda h: self.segments[h].dino, self._hist_tree, self.reid_cfg,
            )  # fmt: skip
            if m is not None:
                matches.append(m)
        by_target: dict[int, list[ReidMatch]] = {}
        for m in matches:
            by_target.setdefault(m.target, []).append(m)
        for target, ms in sorted(by_target.items()):
            self._merge(target, [m.query for m in ms], cover)
            dirty.add(target)
            for m in ms:
                dirty.discard(m.query)
                log.info(
                    "re-identified segment %d as historical segment %d (o=%.2f cos=%.2f J=%.2f)",
                    m.query, m.target, m.overlap, m.cosine, m.score,
                )  # fmt: skip
        return matches

    def _merge(self, target: int, queries: list[int], cover: MeshCover) -> None:
        """Move the queries' tracks, features and vertices into historical segment ``target``."""
        h = self.segments[target]
        keep = cover.keep(h.positions)
        parts, anchors = [h.positions[keep]], [h.anchors[keep]]
        vids = [h.vertex_ids]
        for q in queries:
            seg = self.segments.pop(q)
            self._hist_trees.pop(q, None)
            h.tracks |= seg.tracks
            h.gallery.update(seg.gallery)
            h.track_dino.update(seg.track_dino)
            h.track_mesh_weight.update(seg.track_mesh_weight)
            h.track_displaced.update(seg.track_displaced)
            for t in seg.tracks:
                self._track_segment[t] = target
            parts.append(seg.positions)
            anchors.append(seg.anchors)
            vids.append(seg.vertex_ids)
            self._vertex_segments[self._vertex_segments == q] = target
        h.positions = np.concatenate(parts)
        h.anchors = np.concatenate(anchors).astype(np.int32)
        h.vertex_ids = np.sort(np.concatenate(vids)).astype(np.int32)
        h.active = True
        h.refresh_bounds()
        h.refresh_dino()
        self._hist_trees.pop(target, None)

    # -- pose corrections ---------------------------------------------------------------------

    def move(self, motion: Motion) -> list[int]:
        """Move every stored position with its anchor frame's correction; returns the ids of
        the segments that moved (their bounds and centroid are refreshed). A segment keeps its
        id, tracks and gallery: only where it is changes. Historical k-d trees are rebuilt on
        their next use."""
        segs = [s for _, s in sorted(self.segments.items()) if s.num_vertices]
        if not segs:
            return []
        # one lookup for every position of the map
        sizes = [s.num_vertices for s in segs]
        pos, hit = motion.apply(np.concatenate([s.positions for s in segs]), np.concatenate([s.anchors for s in segs]))
        bounds = np.cumsum([0, *sizes])
        moved = []
        for k, seg in enumerate(segs):
            if hit[bounds[k] : bounds[k + 1]].any():
                seg.positions = pos[bounds[k] : bounds[k + 1]].astype(np.float32)
                seg.refresh_bounds()
                self._hist_trees.pop(seg.id, None)
                moved.append(seg.id)
        return moved

    def replace_geometry(self, mesh: HypothesisMesh) -> list[int]:
        """Every segment's stored geometry replaced by the vertices of ``mesh`` (the whole map,
        re-fused) whose winning track is one of its tracks; returns the ids that got geometry.
        A segment the mesh has no vertex of keeps its own. Ids, tracks and galleries stay;
        the next :meth:`update` marks which segments the active window holds."""
        win = mesh.winners()
        seg_of_track = {int(t): s for t, s in self._track_segment.items()}
        tracks, inverse = np.unique(win, return_inverse=True)
        seg = np.array([seg_of_track.get(int(t), -1) if t >= 0 else -1 for t in tracks], np.int64)[inverse] if len(win) else np.zeros(0, np.int64)
        anchors = mesh.vertex_anchors()
        order = np.argsort(seg, kind="stable")
        ids, starts = np.unique(seg[order], return_index=True)
        ends = np.append(starts[1:], len(order))
        done = []
        for sid, a, b in zip(ids.tolist(), starts.tolist(), ends.tolist(), strict=True):
            if sid < 0 or sid not in self.segments:
                continue
            rows = order[a:b]
            sg = self.segments[sid]
            sg.positions = mesh.vertices[rows].astype(np.float32)
            sg.anchors = anchors[rows].astype(np.int32)
            sg.vertex_ids = no_vertices()
            sg.active = False
            sg.refresh_bounds()
            self._hist_trees.pop(sid, None)
            done.append(int(sid))
        return done

    # -- save / resume ------------------------------------------------------------------------

    def state_dict(self) -> dict:
        """Plain python + numpy; ``load_state_dict`` restores the layer exactly."""
        return {
            "format": STATE_FORMAT,
            "next_id": self._next_id,
            "segments": [self.segments[s].state() for s in sorted(self.segments)],
            "vertex_segments": self._vertex_segments.copy(),
        }

    def load_state_dict(self, state: Mapping) -> None:
        if state.get("format") != STATE_FORMAT:
            raise ValueError(
                f"segment layer state format {state.get('format')!r}, expected {STATE_FORMAT}"
            )
        segments = [Segment.from_state(s) for s in state["segments"]]
        self.segments = {s.id: s for s in segments}
        self._track_segment = {t: s.id for s in segments for t in s.tracks}
        self._next_id = int(state["next_id"])
        self._vertex_segments = np.array(state["vertex_segments"], np.int32)
        self._hist_trees = {}
