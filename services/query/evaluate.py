"""``trackgraph eval queries``: does the query service's top answer land on the right object?

For every *synonym query* of the ground truth (its text is a synonym of one of its objects)
that names an object larger than ``min_size_m`` (the longest side of its ground-truth
points' box), the map is asked through the query core, eq. 10 with the map's own encoder,
exactly as ``trackgraph query MAP_DIR`` answers, and the top segment is a hit when it overlaps
one of the query's objects with IoU >= 0.25 on ground-truth points (each ground-truth point takes
its nearest predicted point within 3 cm: ``shared.eval.openlex3d``'s ``global`` alignment,
not its default ``per_mask``).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np

from services.query.offline import OfflineQueries, map_config
from shared.eval.cloud import contingency, transfer_instances
from shared.eval.errors import EvalInputError
from shared.eval.gt import load_gt
from shared.eval.openlex3d import ALIGN_RADIUS, TOP1_IOU, synonym_query
from shared.eval.prediction import load_prediction
from shared.messages.rpc import QueryRequest

log = logging.getLogger(__name__)


class MapTruth:
    """A saved map's segments on the ground truth's points: which object each segment
    covers, and how well."""

    def __init__(self, map_dir: str | Path, gt_dir: str | Path) -> None:
        from services.mapping import SEGMENT_IDS_FILE

        map_dir, gt_dir = Path(map_dir), Path(gt_dir)
        self.gt = gt = load_gt(gt_dir / "gt" if (gt_dir / "gt").is_dir() else gt_dir)
        pred = load_prediction(map_dir)
        ids_path = map_dir / SEGMENT_IDS_FILE
        if not ids_path.is_file():
            raise EvalInputError(ids_path, "missing: re-export the map with this version (trackgraph map or the fusion service)")
        seg_ids = np.load(ids_path, allow_pickle=False)
        if len(seg_ids) != pred.n_instances:
            raise EvalInputError(ids_path, f"{len(seg_ids)} segment ids for {pred.n_instances} instances")
        self.row_of = {int(s): k for k, s in enumerate(seg_ids)}
        self.obj_ids, obj_of_point = np.unique(gt.labels, return_inverse=True)
        obj_of_point = np.where(gt.labels >= 0, obj_of_point.reshape(-1), -1)
        self.obj_size = np.bincount(obj_of_point[obj_of_point >= 0], minlength=len(self.obj_ids))
        aligned = transfer_instances(pred.points, pred.index, gt.points, ALIGN_RADIUS)
        self.inter = contingency(aligned, pred.n_instances, obj_of_point, len(self.obj_ids))
        self.inst_size = np.bincount(aligned[aligned >= 0], minlength=pred.n_instances)
        self.extent: dict[int, float] = {}
        for c, oid in enumerate(self.obj_ids):
            pts = gt.points[obj_of_point == c]
            self.extent[int(oid)] = float((pts.max(0) - pts.min(0)).max()) if len(pts) else 0.0

    def columns(self, object_ids) -> list[int]:
        """Columns of the objects that have ground-truth points."""
        cols = []
        for o in object_ids:
            c = int(np.searchsorted(self.obj_ids, o))
            if c < len(self.obj_ids) and self.obj_ids[c] == o and self.obj_size[c] > 0:
                cols.append(c)
        return cols

    def iou(self, segment: int, cols: list[int]) -> Annotated[np.ndarray, "(len(cols),) float64"]:
        k = self.row_of.get(int(segment))
        if k is None or not cols:
            return np.zeros(len(cols))
        i = self.inter[k, cols].astype(np.float64)
        u = self.obj_size[cols] + self.inst_size[k] - i
        return np.divide(i, u, out=np.zeros_like(i), where=u > 0)

    def best_object(self, segment: int) -> tuple[int | None, str, float]:
        """(object id, its name, IoU) of the object the segment overlaps most."""
        cols = list(range(len(self.obj_ids)))
        ious = self.iou(segment, cols)
        if not len(ious) or ious.max() <= 0:
            return None, "nothing", 0.0
        c = int(ious.argmax())
        oid = int(self.obj_ids[c])
        labels = self.gt.objects.get(oid)
        name = labels.name() if labels is not None else None
        return oid, name or f"object {oid}", float(ious[c])


def _top1_rows(
    truth: MapTruth, offline: OfflineQueries, map_dir: str | Path, gallery: Literal["max", "mean"] | None, min_size_m: float
) -> list[dict[str, Any]]:
    """The top answer to each synonym query of an object over ``min_size_m``, and whether it hits."""
    gt = truth.gt
    rows = []
    for query in gt.queries:
        cols = truth.columns(query.object_ids)
        if not cols or not synonym_query(gt, query.text, query.object_ids):
            continue
        if max(truth.extent[int(truth.obj_ids[c])] for c in cols) <= min_size_m:
            continue
        reply = offline.ask(QueryRequest(text=query.text, top_k=1, gallery=gallery))
        if reply.error is not None:
            raise EvalInputError(map_dir, f"query {query.text!r} refused: {reply.error}")
        iou, top = 0.0, None
        if reply.hits:
            top = reply.hits[0].segment
            iou = float(truth.iou(top, cols).max())
        rows.append({"query": query.text, "objects": list(query.object_ids), "top_segment": top, "iou": round(iou, 4), "hit": iou >= TOP1_IOU})
    return rows


def top1_hit_rates(
    map_dir: str | Path,
    gt_dir: str | Path,
    galleries: tuple[Literal["max", "mean"], ...] = ("max", "mean"),
    *,
    min_size_m: float = 0.2,
) -> dict[str, float | None]:
    """``eval_queries``' top-1 hit rate for each gallery rule, the map and ground truth read once."""
    truth = MapTruth(map_dir, gt_dir)
    offline = OfflineQueries(map_dir, map_config(map_dir))
    out: dict[str, float | None] = {}
    for g in galleries:
        hits = [r["hit"] for r in _top1_rows(truth, offline, map_dir, g, min_size_m)]
        out[g] = float(np.mean(hits)) if hits else None
    return out


def eval_queries(
    map_dir: str | Path,
    gt_dir: str | Path,
    *,
    min_size_m: float = 0.2,
    gallery: Literal["max", "mean"] | None = None,
    details: bool = False,
) -> dict[str, Any]:
    """Top-1 hit rate of the synonym queries of objects larger than ``min_size_m``, scored
    with the map config's gallery rule or ``gallery``."""
    t0 = time.perf_counter()
    truth = MapTruth(map_dir, gt_dir)
    offline = OfflineQueries(map_dir, map_config(map_dir))
    rows = _top1_rows(truth, offline, map_dir, gallery, min_size_m)
    hits = [r["hit"] for r in rows]
    out: dict[str, Any] = {
        "top1_hit_rate": float(np.mean(hits)) if hits else None,
        "n_queries": len(rows),
        "n_hits": int(sum(hits)),
        "min_size_m": min_size_m,
        "gallery": gallery or offline.cfg.query.gallery,
        "seconds": round(time.perf_counter() - t0, 3),
    }
    if details:
        out["per_query"] = rows
    log.info("queries: %d of %d synonym queries hit (%.3f)", out["n_hits"], len(rows), out["top1_hit_rate"] or 0.0)
    return out
