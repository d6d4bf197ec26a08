"""One 3D segment node of the scene graph (III-A): its tracks, stored geometry, aggregated
DINOv3 feature and CLIP gallery, its wire form and its saved form. The layer that creates,
updates and merges segments is :mod:`services.fusion.layers.segments`."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Annotated

import numpy as np

from services.fusion.layers.gallery import (
    Gallery,
    gallery_from_state,
    gallery_rows,
    gallery_state,
)
from services.fusion.layers.reid import unit
from shared.messages.graph import SegmentNode


def _no_positions() -> np.ndarray:
    return np.zeros((0, 3), np.float32)


def no_vertices() -> np.ndarray:
    return np.zeros(0, np.int32)


@dataclass
class Segment:
    """A 3D segment node N_S = {B, p_S, T, f^dino, F^ov, s} (III-A)."""

    id: int
    tracks: set[int]
    """T, the source tracks assigned to the segment."""
    dino: Annotated[np.ndarray, "(D,) float32 unit"]
    """f^dino, aggregated as :mod:`services.fusion.layers.segments` describes."""
    positions: Annotated[np.ndarray, "(P, 3) float32 world metres"] = field(
        default_factory=_no_positions
    )
    """Every vertex connected to the segment: its latest-mesh vertices (``vertex_ids``) and those
    kept from earlier meshes that the latest mesh no longer covers (they left the window).
    Historical segments keep theirs: it is what re-identification compares a revisit against."""
    anchors: Annotated[np.ndarray, "(P,) int32 frame index per position, -1 = unknown"] = field(
        default_factory=no_vertices
    )
    """The frame each position was last fused from: a pose correction moves the position with
    that frame's correction (:meth:`SegmentLayer.move`)."""
    vertex_ids: Annotated[np.ndarray, "(n,) int32 indices into the latest mesh"] = field(
        default_factory=no_vertices
    )
    """Latest-mesh vertices whose winning track belongs to the segment; empty when historical."""
    active: bool = True
    """s: True while at least one of its vertices is on the latest mesh (the active window)."""
    gallery: Gallery = field(default_factory=dict)
    """F^ov: track id -> that track's running-mean CLIP feature (eq. 4), kept in sync."""
    track_dino: dict[int, np.ndarray] = field(default_factory=dict)
    """Last known unit DINOv3 feature of each track, so forgotten tracks still count."""
    track_mesh_weight: dict[int, float] = field(default_factory=dict)
    """Hypothesis weight of each track on the latest mesh it appeared in."""
    track_displaced: dict[int, float] = field(default_factory=dict)
    """Last reported ``TrackState.displaced_weight`` of each track."""
    bbox_min: Annotated[np.ndarray, "(3,) float64"] = field(default_factory=lambda: np.zeros(3))
    bbox_max: Annotated[np.ndarray, "(3,) float64"] = field(default_factory=lambda: np.zeros(3))
    centroid: Annotated[np.ndarray, "(3,) float64"] = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        if len(self.anchors) != len(self.positions):
            # built from positions alone (no grid behind them): frames unknown, never moved
            self.anchors = np.full(len(self.positions), -1, np.int32)

    @property
    def num_vertices(self) -> int:
        return int(self.positions.shape[0])

    def track_weight(self, tid: int) -> float:
        """Weight of track ``tid`` in the segment's statistics: mesh weight + displaced weight."""
        return self.track_mesh_weight.get(tid, 0.0) + self.track_displaced.get(tid, 0.0)

    def refresh_bounds(self) -> None:
        if self.num_vertices == 0:
            return
        p = self.positions.astype(np.float64)
        self.bbox_min = p.min(axis=0)
        self.bbox_max = p.max(axis=0)
        self.centroid = p.mean(axis=0)

    def summary(self) -> tuple:
        """What ``to_node`` reports of the geometry and state: equal summaries, same node."""
        return (
            self.active, self.num_vertices,
            self.bbox_min.tobytes(), self.bbox_max.tobytes(), self.centroid.tobytes(),
        )  # fmt: skip

    def refresh_dino(self) -> bool:
        """Recompute the aggregated DINOv3 feature; True if it changed."""
        tids = sorted(t for t in self.tracks if t in self.track_dino)
        if not tids:
            return False
        feats = np.stack([self.track_dino[t] for t in tids]).astype(np.float64)
        w = np.array([max(self.track_weight(t), 0.0) for t in tids])
        if w.sum() <= 0:
            # No evidence yet (e.g. only zero-weight hypotheses): every view counts the same.
            w = np.ones(len(tids))
        agg = unit(w @ feats)
        if not np.any(agg):
            # Opposite features cancelled out; the best-supported track is the least arbitrary.
            agg = unit(feats[int(np.argmax(w))])
        new = agg.astype(np.float32)
        if self.dino.shape == new.shape and np.array_equal(self.dino, new):
            return False
        self.dino = new
        return True

    def to_node(self, room: int | None = None) -> SegmentNode:
        """The wire form (``graph/delta`` and snapshots)."""
        rows, ids = gallery_rows(self.gallery)
        total = sum(max(self.track_weight(t), 0.0) for t in self.tracks)
        # Three decimals: a share only meets a threshold, and finer values would change the
        # node (and resend it) at every update.
        shares = [round(max(self.track_weight(t), 0.0) / total, 3) if total > 0 else round(1.0 / len(self.tracks), 3) for t in ids]
        return SegmentNode(
            id=self.id,
            centroid=np.asarray(self.centroid, np.float64),
            bbox_min=np.asarray(self.bbox_min, np.float64),
            bbox_max=np.asarray(self.bbox_max, np.float64),
            tracks=sorted(self.tracks),
            dino=np.asarray(self.dino, np.float32),
            gallery=rows,
            gallery_tracks=ids,
            gallery_weights=shares,
            active=self.active,
            room=room,
            num_vertices=self.num_vertices,
        )

    def state(self) -> dict:
        return {
            "id": self.id,
            "tracks": sorted(self.tracks),
            "dino": self.dino.copy(),
            "positions": self.positions.copy(),
            "anchors": self.anchors.copy(),
            "vertex_ids": self.vertex_ids.copy(),
            "active": self.active,
            "gallery": gallery_state(self.gallery),
            "track_dino": gallery_state(self.track_dino),
            "track_mesh_weight": _weights_state(self.track_mesh_weight),
            "track_displaced": _weights_state(self.track_displaced),
            "bbox_min": self.bbox_min.copy(),
            "bbox_max": self.bbox_max.copy(),
            "centroid": self.centroid.copy(),
        }

    @staticmethod
    def from_state(s: Mapping) -> Segment:
        return Segment(
            id=int(s["id"]),
            tracks={int(t) for t in s["tracks"]},
            dino=np.array(s["dino"], np.float32),
            positions=np.array(s["positions"], np.float32).reshape(-1, 3),
            # saved before pose corrections: every position's frame unknown
            anchors=np.array(s["anchors"], np.int32).reshape(-1) if "anchors" in s else np.full(len(np.asarray(s["positions"]).reshape(-1, 3)), -1, np.int32),
            vertex_ids=np.array(s["vertex_ids"], np.int32),
            active=bool(s["active"]),
            gallery=gallery_from_state(s["gallery"]),
            track_dino=gallery_from_state(s["track_dino"]),
            track_mesh_weight=_weights_from_state(s["track_mesh_weight"]),
            track_displaced=_weights_from_state(s["track_displaced"]),
            bbox_min=np.array(s["bbox_min"], np.float64),
            bbox_max=np.array(s["bbox_max"], np.float64),
            centroid=np.array(s["centroid"], np.float64),
        )


def _weights_state(w: Mapping[int, float]) -> dict:
    ids = sorted(w)
    return {"tracks": ids, "values": [float(w[t]) for t in ids]}


def _weights_from_state(s: Mapping) -> dict[int, float]:
    return {int(t): float(v) for t, v in zip(s["tracks"], s["values"], strict=True)}
