"""Room segmentation of a map against the ground-truth rooms.

Inputs:

- the predicted rooms: ``MAP_DIR/rooms.npz`` (:mod:`shared.graph.roomgrid`), a grid of
  RoomNode ids over world xy;
- the ground truth: ``rooms.json`` (in ``GT_DIR`` or ``GT_DIR/gt``, as ``trackgraph synth``
  writes it), each room's name, type and inner-floor polygon; for sequences written before it
  existed, ``scene.json``'s rooms (their ``inner`` rectangles, the kind mapped to a type).

Every ground-truth polygon is rasterised onto the predicted grid's lattice (a cell belongs
to a room when its centre is inside the polygon; the lattice is extended past the grid where
a polygon reaches beyond it, so ground truth the map never reached still counts), and all
areas and IoUs are counted in cells.

- Matching: one-to-one, Hungarian on the IoU matrix (predicted x ground truth), pairs below
  the threshold (0.5) excluded; ``precision`` = matches / predicted rooms, ``recall`` =
  matches / ground-truth rooms (None when there are none), ``f1`` their harmonic mean
  (2 matches / (predicted + ground-truth rooms), so 0 for a map without rooms). Every room of the grid's
  ``room_ids`` is a prediction, with or without cells.
- ``over_segmented``: ground-truth rooms with 2 or more predicted rooms that each have at
  least 20% of their own cells inside it (the room was split among them);
  ``under_segmented``: predicted rooms that each hold at least 20% of the cells of 2 or more
  ground-truth rooms (they were merged). The two rules mirror each other.
- ``per_room``: each ground-truth room's best-overlapping predicted room and IoU, and its
  match; ``mean_iou`` averages the best IoUs over ground-truth rooms (0 for none).
- ``type_accuracy`` (when the grid carries room names): the share of matched ground-truth
  rooms whose predicted room's name is the ground-truth type.
- ``room_type_top1`` (when a room ranker is given: the query service's "which room is the
  X", ``target: rooms``): for each ground-truth type of the scene, its text is asked and the
  top room is a hit when it is matched (IoU >= the threshold) to a ground-truth room of that
  type. ``room_queries`` lists each with its answer.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np

from shared.eval.errors import EvalInputError
from shared.graph.roomgrid import ROOMS_FILE, RoomGrid, RoomGridError, load_room_grid

log = logging.getLogger(__name__)

ROOMS_GT_FILE = "rooms.json"
SCENE_FILE = "scene.json"
MATCH_IOU = 0.5
"""IoU at which a predicted room matches a ground-truth room."""
SPLIT_SHARE = 0.2
"""Share of a room's cells another room must hold for the over/under-segmentation counts."""


@dataclass(frozen=True)
class GTRoom:
    """One ground-truth room."""

    id: int
    name: str
    type: str
    """Natural label ("living room", "hall", ...)."""
    footprint: Annotated[np.ndarray, "(V, 2) float64 world xy, counter-clockwise"]


# ---------------------------------------------------------------- ground truth


def _find(gt_dir: Path, name: str) -> Path | None:
    for cand in (gt_dir / name, gt_dir / "gt" / name):
        if cand.is_file():
            return cand
    return None


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise EvalInputError(path, f"not valid JSON ({exc})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise EvalInputError(path, f"cannot read ({exc})") from None


def _polygon(value: Any, path: Path, where: str) -> np.ndarray:
    try:
        poly = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        poly = np.zeros((0,))
    if poly.ndim != 2 or poly.shape[0] < 3 or poly.shape[1] != 2 or not np.isfinite(poly).all():
        raise EvalInputError(path, f"{where}: expected a polygon of 3 or more finite [x, y] vertices")
    return poly


def _field(room: Any, key: str, kind: type, path: Path, where: str) -> Any:
    if not isinstance(room, dict) or key not in room:
        raise EvalInputError(path, f"{where}: missing field {key!r}")
    value = room[key]
    if not isinstance(value, kind) or isinstance(value, bool):
        raise EvalInputError(path, f"{where}.{key}: expected {kind.__name__}, got {type(value).__name__}")
    return value


def _rooms_list(data: Any, path: Path) -> list:
    if not isinstance(data, dict) or not isinstance(data.get("rooms"), list):
        raise EvalInputError(path, "missing field 'rooms' (a list of rooms)")
    return data["rooms"]


def load_gt_rooms(gt_dir: str | Path) -> list[GTRoom]:
    """The ground-truth rooms of ``gt_dir`` (the sequence folder or its ``gt/``): from
    ``rooms.json``, else from ``scene.json``'s rooms (inner rectangles) for sequences written
    before rooms.json existed. Errors name the file and the field."""
    from shared.synth.layout import ROOM_TYPES

    gt_dir = Path(gt_dir)
    if not gt_dir.is_dir():
        raise EvalInputError(gt_dir, "ground-truth folder does not exist")
    path = _find(gt_dir, ROOMS_GT_FILE)
    rooms: list[GTRoom] = []
    if path is not None:
        for i, r in enumerate(_rooms_list(_read_json(path), path)):
            where = f"rooms[{i}]"
            rooms.append(GTRoom(
                id=_field(r, "id", int, path, where), name=_field(r, "name", str, path, where),
                type=_field(r, "type", str, path, where),
                footprint=_polygon(_field(r, "footprint", list, path, where), path, f"{where}.footprint"),
            ))  # fmt: skip
    else:
        path = _find(gt_dir, SCENE_FILE)
        if path is None:
            raise EvalInputError(
                gt_dir / "gt" / ROOMS_GT_FILE,
                f"no room ground truth: neither {ROOMS_GT_FILE} nor {SCENE_FILE} in {gt_dir} or {gt_dir / 'gt'}",
            )
        log.info("%s: no %s beside it (an older sequence); rooms from its inner rectangles", path, ROOMS_GT_FILE)
        for i, r in enumerate(_rooms_list(_read_json(path), path)):
            where = f"rooms[{i}]"
            kind = _field(r, "kind", str, path, where)
            if kind not in ROOM_TYPES:
                raise EvalInputError(path, f"{where}.kind: {kind!r} is not a known room kind ({sorted(ROOM_TYPES)})")
            inner = _field(r, "inner", list, path, where)
            if len(inner) != 4:
                raise EvalInputError(path, f"{where}.inner: expected [x0, y0, x1, y1]")
            x0, y0, x1, y1 = inner
            poly = _polygon([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], path, f"{where}.inner")
            rooms.append(GTRoom(id=i, name=_field(r, "name", str, path, where), type=ROOM_TYPES[kind], footprint=poly))
    if not rooms:
        raise EvalInputError(path, "lists no rooms")
    return rooms


# ---------------------------------------------------------------- geometry


def points_in_polygon(
    points: Annotated[np.ndarray, "(N, 2) float"], polygon: Annotated[np.ndarray, "(V, 2) float"]
) -> Annotated[np.ndarray, "(N,) bool"]:
    """Even-odd rule: a horizontal ray from each point crosses the boundary an odd number of
    times. Either orientation works; a point exactly on an edge may fall either way."""
    pts = np.asarray(points, np.float64)
    poly = np.asarray(polygon, np.float64)
    x, y = pts[:, 0:1], pts[:, 1:2]
    ax, ay = poly[:, 0], poly[:, 1]
    bx, by = np.roll(ax, -1), np.roll(ay, -1)
    straddles = (ay > y) != (by > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        cross_x = ax + (y - ay) * (bx - ax) / (by - ay)
    return ((straddles & (x < cross_x)).sum(axis=1) % 2).astype(bool)


def rasterise(
    polygon: Annotated[np.ndarray, "(V, 2) float"], origin: Annotated[np.ndarray, "(2,) float"], resolution: float
) -> Annotated[np.ndarray, "(K, 2) int64 lattice cells whose centre is inside"]:
    """Cells ``(i, j)`` of the lattice ``origin + (i, j) * resolution`` (any sign) whose centre
    lies inside ``polygon``."""
    lo = np.floor((polygon.min(axis=0) - origin) / resolution).astype(np.int64)
    hi = np.ceil((polygon.max(axis=0) - origin) / resolution).astype(np.int64)
    i, j = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij")
    cells = np.stack([i.ravel(), j.ravel()], axis=1)
    return cells[points_in_polygon(origin + (cells + 0.5) * resolution, polygon)]


@dataclass
class Overlap:
    """Cell counts of predicted against ground-truth rooms."""

    inter: Annotated[np.ndarray, "(P, G) int64 shared cells"]
    pred_cells: Annotated[np.ndarray, "(P,) int64"]
    gt_cells: Annotated[np.ndarray, "(G,) int64"]

    def iou(self) -> Annotated[np.ndarray, "(P, G) float64"]:
        union = self.pred_cells[:, None] + self.gt_cells[None, :] - self.inter
        return np.divide(self.inter, union, out=np.zeros(self.inter.shape), where=union > 0)


def overlap(grid: RoomGrid, gt_rooms: list[GTRoom]) -> Overlap:
    """Rasterise the ground truth onto ``grid``'s lattice and count shared cells."""
    ids = grid.room_ids
    order = np.argsort(ids)
    h, w = grid.shape
    inter = np.zeros((len(ids), len(gt_rooms)), np.int64)
    gt_cells = np.zeros(len(gt_rooms), np.int64)
    for g, room in enumerate(gt_rooms):
        cells = rasterise(room.footprint, grid.origin, grid.resolution)
        gt_cells[g] = len(cells)
        on = (cells[:, 0] >= 0) & (cells[:, 0] < h) & (cells[:, 1] >= 0) & (cells[:, 1] < w)
        lab = grid.labels[cells[on, 0], cells[on, 1]]
        lab = lab[lab >= 0]
        inter[:, g] = np.bincount(order[np.searchsorted(ids[order], lab)], minlength=len(ids))
        if gt_cells[g] == 0:
            log.warning("ground-truth room %s covers no cell centre at %.3f m resolution", room.name, grid.resolution)
    return Overlap(inter, grid.cell_counts(), gt_cells)


def match(iou: Annotated[np.ndarray, "(P, G) float"], threshold: float) -> list[tuple[int, int]]:
    """One-to-one (predicted, ground-truth) pairs maximising the summed IoU over the pairs at
    or above ``threshold``; pairs below it never enter the assignment."""
    from scipy.optimize import linear_sum_assignment

    if iou.size == 0:
        return []
    ok = (iou >= threshold) & (iou > 0)
    rows, cols = linear_sum_assignment(np.where(ok, iou, 0.0), maximize=True)
    return [(int(p), int(g)) for p, g in zip(rows, cols, strict=True) if ok[p, g]]


def _ratio(a: float, b: float) -> float | None:
    return a / b if b else None


def _norm(label: str) -> str:
    return " ".join(str(label).lower().split())


# ---------------------------------------------------------------- the metric


RoomRanker = Callable[[str], list[int]]
"""A room-type text -> the map's room ids, best first (the query service's room ranking)."""


def evaluate_rooms(
    grid: RoomGrid, gt_rooms: list[GTRoom], *, iou: float = MATCH_IOU, rank_rooms: RoomRanker | None = None
) -> dict[str, Any]:
    """Room scores of a loaded grid against loaded ground truth (see the module docstring)."""
    if not 0 < iou <= 1:
        raise ValueError(f"iou threshold must be in (0, 1], got {iou}")
    ov = overlap(grid, gt_rooms)
    ious = ov.iou()
    pairs = match(ious, iou)
    n_pred, n_gt, tp = len(grid.room_ids), len(gt_rooms), len(pairs)
    precision, recall = _ratio(tp, n_pred), _ratio(tp, n_gt)
    # 2 TP / (2 TP + FP + FN): the harmonic mean of the two, and 0 (not undefined) for a map
    # with no rooms at all against ground truth that has some.
    f1 = _ratio(2 * tp, n_pred + n_gt)

    share_of_pred = np.divide(ov.inter, ov.pred_cells[:, None], out=np.zeros(ov.inter.shape), where=ov.pred_cells[:, None] > 0)
    share_of_gt = np.divide(ov.inter, ov.gt_cells[None, :], out=np.zeros(ov.inter.shape), where=ov.gt_cells[None, :] > 0)
    over = np.flatnonzero((share_of_pred >= SPLIT_SHARE).sum(axis=0) >= 2)
    under = np.flatnonzero((share_of_gt >= SPLIT_SHARE).sum(axis=1) >= 2)

    partner = {g: p for p, g in pairs}
    per_room = []
    best_ious = []
    for g, room in enumerate(gt_rooms):
        best = int(ious[:, g].argmax()) if n_pred and ious[:, g].max() > 0 else None
        best_iou = float(ious[best, g]) if best is not None else 0.0
        best_ious.append(best_iou)
        p = partner.get(g)
        per_room.append({
            "gt_id": room.id, "gt_name": room.name, "gt_type": room.type, "gt_cells": int(ov.gt_cells[g]),
            "best_pred_id": None if best is None else int(grid.room_ids[best]),
            "best_pred_name": None if best is None else grid.name_of(int(grid.room_ids[best])),
            "iou": round(best_iou, 6),
            "matched_pred_id": None if p is None else int(grid.room_ids[p]),
            "matched_iou": None if p is None else round(float(ious[p, g]), 6),
        })  # fmt: skip

    type_accuracy = None
    named = any(n.strip() for n in grid.names)
    if named and pairs:
        hits = sum(_norm(grid.name_of(int(grid.room_ids[p]))) == _norm(gt_rooms[g].type) for p, g in pairs)
        type_accuracy = hits / len(pairs)
    room_queries, room_type_top1 = None, None
    if rank_rooms is not None:
        room_queries = _room_type_queries(grid, gt_rooms, pairs, rank_rooms)
        room_type_top1 = _ratio(sum(q["hit"] for q in room_queries), len(room_queries))
    return {
        "iou_threshold": iou,
        "precision": precision,
        "recall": recall,
        "f1": f1,
        "n_pred": n_pred,
        "n_gt": n_gt,
        "n_matched": tp,
        "over_segmented": int(len(over)),
        "over_segmented_rooms": [gt_rooms[g].name for g in over],
        "under_segmented": int(len(under)),
        "under_segmented_rooms": [int(grid.room_ids[p]) for p in under],
        "mean_iou": float(np.mean(best_ious)) if best_ious else None,
        "type_accuracy": type_accuracy,
        "named_rooms": named,
        "room_type_top1": room_type_top1,
        "room_queries": room_queries,
        "resolution": grid.resolution,
        "per_room": per_room,
    }


def _room_type_queries(grid: RoomGrid, gt_rooms: list[GTRoom], pairs: list[tuple[int, int]], rank_rooms: RoomRanker) -> list[dict[str, Any]]:
    """Each ground-truth type asked once; the top room hits when matched to a room of that type."""
    gt_of = {int(grid.room_ids[p]): g for p, g in pairs}
    rows = []
    for text in sorted({r.type for r in gt_rooms}):
        ranked = list(rank_rooms(text))
        top = int(ranked[0]) if ranked else None
        g = gt_of.get(top) if top is not None else None
        rows.append({
            "query": text, "top_room": top, "top_name": None if top is None else grid.name_of(top),
            "gt_room": None if g is None else gt_rooms[g].name, "gt_type": None if g is None else gt_rooms[g].type,
            "hit": g is not None and _norm(gt_rooms[g].type) == _norm(text),
        })  # fmt: skip
    return rows


def load_pred_grid(pred_dir: str | Path) -> RoomGrid:
    """``MAP_DIR/rooms.npz``; a missing one says the map predates room footprints."""
    pred_dir = Path(pred_dir)
    if not pred_dir.is_dir():
        raise EvalInputError(pred_dir, "map folder does not exist")
    path = pred_dir / ROOMS_FILE
    if not path.is_file():
        raise EvalInputError(path, "missing: the map was written before room footprints were saved; map again")
    try:
        return load_room_grid(path)
    except RoomGridError as exc:
        raise EvalInputError(exc.path, exc.reason) from None


def eval_rooms(
    pred_dir: str | Path, gt_dir: str | Path, *, iou: float = MATCH_IOU, rank_rooms: RoomRanker | None = None
) -> dict[str, Any]:
    """Room precision, recall and F1 at ``iou``, over/under-segmentation, per-room IoU and
    ``mean_iou`` of the map in ``pred_dir`` (its ``rooms.npz``) against ``gt_dir``; with
    ``rank_rooms``, the room-type top-1 of "which room is X"."""
    t0 = time.perf_counter()
    gt_rooms = load_gt_rooms(gt_dir)
    grid = load_pred_grid(pred_dir)
    out = evaluate_rooms(grid, gt_rooms, iou=iou, rank_rooms=rank_rooms)
    out["seconds"] = round(time.perf_counter() - t0, 3)
    log.info(
        "rooms: %d predicted, %d ground truth, P %s R %s F1 %s at IoU %.2f, mean IoU %s",
        out["n_pred"], out["n_gt"], *(("n/a" if out[k] is None else f"{out[k]:.3f}") for k in ("precision", "recall", "f1")),
        iou, "n/a" if out["mean_iou"] is None else f"{out['mean_iou']:.3f}",
    )  # fmt: skip
    return out


__all__ = [
    "GTRoom",
    "RoomRanker",
    "evaluate_rooms",
    "eval_rooms",
    "load_gt_rooms",
    "load_pred_grid",
    "points_in_polygon",
    "rasterise",
]
