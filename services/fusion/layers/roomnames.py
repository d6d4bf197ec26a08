"""Open-vocabulary room features and names (not in the paper; docs/method.md, F7).

A room's feature pools two descriptions of it, both in the VL encoder's space:

- **what it holds**: the unit mean of each of its segments' CLIP galleries (every segment
  weighs the same, so a room is not described by its largest surface), averaged;
- **what it looks like**: the whole-keyframe embeddings (``TrackFeatures.view``). A view
  shows parts of one or more rooms: fusion keeps a sparse sample of each keyframe's
  back-projected depth (:data:`VIEW_SAMPLE_STRIDE`), and a seen point lies in the room of its
  free-space cell or of the nearest room cell within :data:`VIEW_ROOM_REACH_M` (walls and
  doorways stand on no room's floor). Its shares s_kr over the rooms make the view a mix,
  v_k ~ sum_r s_kr f_r, and the rooms' view features F are that mix undone by ridge least
  squares, (S^T S + lambda I) F = S^T V with lambda = :data:`VIEW_RIDGE`. A room the robot only
  looked into from a doorway, never the main thing in any view, still gets its own look, not
  its neighbour's. A view that sees no room counts for the room the camera stands in.

``GraphConfig.room_view_weight`` mixes the two unit means; a room with only one source takes
it alone. The name is the label of ``GraphConfig.room_labels`` whose text embedding is
nearest the feature, and ``name_score`` that cosine. Without the labels' embeddings yet
(keyframe_vl not up), a room keeps the name it had: after a restart, the saved names stay
until the labels are fetched again.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from scipy import ndimage

from shared.messages.graph import RoomNode, SegmentNode

log = logging.getLogger(__name__)

VIEW_ROOM_REACH_M = 0.3
"""How far from a room's cells a seen point (or the camera) still counts as in it: past the
wall band's half width, so the points on a room's walls are its own."""
VIEW_RIDGE = 0.1
"""lambda of the views' unmixing, in views: a room seen in full by one view is shrunk by
1/1.1, one seen at a share of 0.1 in a single view mostly left without a view feature."""
VIEW_SAMPLE_STRIDE = 16
"""Pixel stride of the depth sample kept per keyframe (300 points of a 320 x 240 frame)."""


def _unit(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float64)
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return x / np.maximum(n, 1e-12)


@dataclass(frozen=True)
class RoomVocabulary:
    """The room labels and their text embeddings, row k for ``labels[k]``."""

    labels: tuple[str, ...]
    embeddings: Annotated[np.ndarray, "(L, D) float32 unit rows"]

    def __post_init__(self) -> None:
        emb = np.asarray(self.embeddings)
        if emb.ndim != 2 or emb.shape[0] != len(self.labels):
            raise ValueError(f"room vocabulary: {len(self.labels)} labels but embeddings of shape {emb.shape}")
        if not np.isfinite(emb).all():
            raise ValueError("room vocabulary: the label embeddings are not finite")

    @property
    def dim(self) -> int:
        return int(self.embeddings.shape[1])


def segment_feature(s: SegmentNode) -> Annotated[np.ndarray, "(D,) float64 unit"] | None:
    """The unit mean of a segment's unit gallery rows, or None without a gallery."""
    if not len(s.gallery_tracks) or s.gallery.size == 0:
        return None
    return _unit(_unit(s.gallery).sum(axis=0))


def unmix_views(
    shares: Annotated[np.ndarray, "(K, R) float share of each view's seen points in each room"],
    views: Annotated[np.ndarray, "(K, D) float"],
    ridge: float = VIEW_RIDGE,
) -> Annotated[np.ndarray, "(R, D) float64 unit rows, zero for a room no view shows"]:
    """The rooms' own view features: ridge least squares of ``views ~ shares @ F``."""
    shares = np.asarray(shares, np.float64)
    r = shares.shape[1]
    if shares.shape[0] == 0 or r == 0:
        return np.zeros((r, views.shape[1] if views.ndim == 2 else 0))
    # The views as they come (an encoder's are unit already): the mix is linear in them.
    v = np.asarray(views, np.float64)
    f = np.linalg.solve(shares.T @ shares + ridge * np.eye(r), shares.T @ v)
    seen = shares.sum(axis=0) > 0
    return np.where(seen[:, None], _unit(f), 0.0)


def room_features(
    room_ids: list[int],
    segments: Mapping[int, SegmentNode],
    view_shares: Annotated[np.ndarray, "(K, R) float shares of each view in room_ids' rooms"],
    views: Annotated[np.ndarray, "(K, D) float view embeddings"],
    view_weight: float,
) -> dict[int, Annotated[np.ndarray, "(D,) float32 unit"]]:
    """Each room's feature (module docstring); rooms with neither source are left out."""
    if not room_ids:
        return {}
    wanted = set(room_ids)
    content: dict[int, list[np.ndarray]] = {}
    for s in segments.values():
        if s.room is None or s.room not in wanted:
            continue
        f = segment_feature(s)
        if f is not None:
            content.setdefault(int(s.room), []).append(f)
    view_shares = np.asarray(view_shares, np.float64).reshape(-1, len(room_ids))
    looks = unmix_views(view_shares, np.asarray(views, np.float64).reshape(len(view_shares), -1)) if len(view_shares) else None
    out: dict[int, np.ndarray] = {}
    for k, rid in enumerate(room_ids):
        parts: list[tuple[float, np.ndarray]] = []
        if content.get(rid):
            parts.append((1.0 - view_weight, _unit(np.sum(content[rid], axis=0))))
        if looks is not None and np.any(looks[k]):
            parts.append((view_weight, looks[k]))
        if not parts:
            continue
        if len({p.shape for _, p in parts}) > 1:
            log.warning("room %d: its views are %d-d but its galleries %d-d; the views are left out", rid, parts[1][1].shape[0], parts[0][1].shape[0])
            parts = parts[:1]
        total = sum(w for w, _ in parts)
        # One source alone, or both weighted 0 against each other: an even mix.
        mix = sum(p for _, p in parts) if total <= 0 or len(parts) == 1 else sum(w * p for w, p in parts)
        out[rid] = _unit(mix).astype(np.float32)
    return out


def describe_rooms(
    rooms: Mapping[int, RoomNode],
    segments: Mapping[int, SegmentNode],
    view_shares: Annotated[np.ndarray, "(K, R) float shares of each view in the rooms, sorted by id"],
    views: Annotated[np.ndarray, "(K, D) float"],
    vocabulary: RoomVocabulary | None,
    view_weight: float,
    previous: Mapping[int, RoomNode] | None = None,
) -> dict[int, RoomNode]:
    """``rooms`` with their ``feature``, ``name`` and ``name_score`` filled in; without a
    ``vocabulary`` each keeps the name of the ``previous`` room of its id."""
    feats = room_features(sorted(rooms), segments, view_shares, views, view_weight)
    previous = previous or {}
    out: dict[int, RoomNode] = {}
    for rid, r in rooms.items():
        f = feats.get(rid)
        update: dict = {"feature": f}
        if vocabulary is None:
            old = previous.get(rid)
            if old is not None:
                update.update(name=old.name, name_score=old.name_score)
        elif f is None:
            update.update(name="", name_score=None)
        elif vocabulary is not None and len(vocabulary.labels) and vocabulary.dim == f.shape[0]:
            cos = vocabulary.embeddings.astype(np.float64) @ f.astype(np.float64)
            k = int(np.argmax(cos))
            update.update(name=vocabulary.labels[k], name_score=float(cos[k]))
        elif vocabulary is not None and len(vocabulary.labels):
            log.warning("room %d: its feature is %d-d but the room labels' embeddings %d-d; not named", rid, f.shape[0], vocabulary.dim)
            update.update(name="", name_score=None)
        out[rid] = r.model_copy(update=update)
    return out


class RoomLookup:
    """The room of any free-space cell: its own, or the nearest room cell's within a reach.

    One distance transform of the room grid serves every lookup: an update gives every
    keyframe view to a room, and a transform per view made that cost grow with the views
    times the building's grid (hundreds of keyframes over a building)."""

    def __init__(
        self,
        labels: Annotated[np.ndarray, "(H, W) int room index per cell, -1 none"],
        room_ids: Annotated[np.ndarray, "(R,) int64 id of each room index"],
        resolution: float,
    ) -> None:
        self.labels = labels
        self.room_ids = np.asarray(room_ids, np.int64)
        self.resolution = resolution
        self._nearest: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    @property
    def empty(self) -> bool:
        return self.labels.size == 0 or not len(self.room_ids) or self.labels.max() < 0

    def rooms_of(
        self, cells: Annotated[np.ndarray, "(K, 2) int64 grid cells, may lie outside"], reach_m: float = VIEW_ROOM_REACH_M
    ) -> Annotated[np.ndarray, "(K,) int64 room id, -1 none"]:
        cells = np.asarray(cells, np.int64).reshape(-1, 2)
        out = np.full(len(cells), -1, np.int64)
        if not len(cells) or self.empty:
            return out
        if self._nearest is None:  # computed on the first lookup that needs it
            dist, (ni, nj) = ndimage.distance_transform_edt(self.labels < 0, return_indices=True)
            self._nearest = dist, ni, nj
        dist, ni, nj = self._nearest
        h, w = self.labels.shape
        inside = (cells[:, 0] >= 0) & (cells[:, 1] >= 0) & (cells[:, 0] < h) & (cells[:, 1] < w)
        c = cells[inside]
        near = (dist[c[:, 0], c[:, 1]] * self.resolution) <= reach_m
        lab = self.labels[ni[c[:, 0], c[:, 1]], nj[c[:, 0], c[:, 1]]]
        out[inside] = np.where(near & (lab >= 0), self.room_ids[np.maximum(lab, 0)], -1)
        return out


def rooms_of_positions(
    labels: Annotated[np.ndarray, "(H, W) int room index per cell, -1 none"],
    room_ids: Annotated[np.ndarray, "(R,) int64 id of each room index"],
    cells: Annotated[np.ndarray, "(K, 2) int64 grid cells, may lie outside"],
    resolution: float,
    reach_m: float = VIEW_ROOM_REACH_M,
) -> Annotated[np.ndarray, "(K,) int64 room id, -1 none"]:
    """The room of each cell: its own, or the nearest room cell's within ``reach_m``."""
    return RoomLookup(labels, room_ids, resolution).rooms_of(cells, reach_m)


def view_shares(
    labels: Annotated[np.ndarray, "(H, W) int room index per cell, -1 none"],
    room_ids: Annotated[np.ndarray, "(R,) int64 id of each room index"],
    order: list[int],
    seen_cells: Annotated[np.ndarray, "(N, 2) int64 cells of the view's points"],
    camera_cell: Annotated[np.ndarray, "(2,) int64"],
    resolution: float,
    lookup: RoomLookup | None = None,
) -> Annotated[np.ndarray, "(len(order),) float64"]:
    """The share of a view's in-room points in each room of ``order`` (ids); one-hot on the
    camera's room for a view that sees none; all zero when the camera is in none either.
    ``lookup``: the same grid's :class:`RoomLookup`, shared by the views of one update."""
    lookup = lookup or RoomLookup(labels, room_ids, resolution)
    col = {rid: k for k, rid in enumerate(order)}
    out = np.zeros(len(order))
    rooms = lookup.rooms_of(seen_cells)
    rooms = rooms[rooms >= 0]
    if not len(rooms):
        rooms = lookup.rooms_of(np.asarray(camera_cell).reshape(1, 2))
        rooms = rooms[rooms >= 0]
    for rid in rooms.tolist():
        if rid in col:
            out[col[rid]] += 1.0
    return out / out.sum() if out.sum() > 0 else out
