"""OpenLex3D evaluation: top-N category frequencies (segmentation) and query retrieval AP.

Follows the public OpenLex3D toolbox at its default settings (``openlex3d/core/{categories,
metric,io,align_masks,average_precision,cosine_similarity}.py``,
``scripts/evaluate_{segmentation,queries}.py``, ``config/eval_{segmentation,query}.yaml``):

**Segmentation.** The prediction is voxel-downsampled (0.05 m) on Open3D's voxel grid: cells
``floor(p / 0.05)`` computed in the precision of the stored positions, float32 for every
cloud this project writes (as Open3D's ``t.geometry.PointCloud.voxel_down_sample`` does; in
float64 a coordinate near a cell boundary can land in the neighbouring cell). Every
downsampled point takes the N prompts of the ground truth's prompt list with the highest
cosine similarity to its feature. Every ground-truth point of a scored object takes its
nearest downsampled point; if that is farther than 0.05 m the point is *missing*, otherwise
its category is the first of synonyms > depictions > vis_sim > clutter > incorrect that any
of the N labels hits (a label hits *clutter* when it is a synonym, a depiction or a
visually-similar label of one of the object's clutter objects, as ``CategoriesHandler.
_check_clutter``). Labels are compared with spaces removed. Per object, each category's share
of its points; each figure is the mean over objects. Objects without synonyms, not in
``gt_categories.json``, or named wall, floor, ceiling, doorframe, ledge or window ledge are not
scored.

**Retrieval.** Predicted instances are aligned to the ground-truth points (``alignment``):
by default ``per_mask``, where a ground-truth point belongs to every instance that has a
point within the threshold, so neighbouring instances may share points; or ``global``, where
it belongs to the instance of its one nearest predicted point. The threshold
(``alignment_threshold``, default 0.001) is compared with the *squared* distance, as
OpenLex3D compares it with FAISS ``IndexFlatL2`` distances: 0.001 m² is a radius of
sqrt(0.001) = 3.16 cm. An instance's size is the number of ground-truth points aligned to it.
Each query scores every predicted instance by cosine similarity, mapped to [0, 1] by
(c + 1) / 2 and min-max normalised over the instances (range floored at 1e-8); of its 10 best
instances, those covering at least one ground-truth point become predictions with that
score. Each (query, object id) pair is one ground-truth instance (as OpenLex3D's
``create_gt_instances``; not the union of the query's objects, which no single instance could
match when a query names several objects); a prediction matches ground truth of its own query
only. AP is ScanNet's greedy class-agnostic AP over all queries pooled (see
:mod:`shared.eval.ap`): ``ap`` averages IoU 0.50:0.05:0.90; ``ap50`` and ``ap25`` are reported
too.

Deliberate differences from OpenLex3D:

1. Downsampling: OpenLex3D gives each voxel centroid the feature of the original point
   nearest to it; here each centroid carries its voxel's majority instance (ties: lowest
   instance number). Centroids are the exact means rounded to float32; Open3D sums in float32
   in its own order, so they may differ from its centroids by a float32 step (about 1e-7 m),
   which matters only for a ground-truth point that close to the 0.05 m association radius.
2. Top-N ties are broken by prompt-list order (OpenLex3D's ``np.argsort`` leaves them to the
   sort algorithm). Top-N labels are computed once per instance, not per point (the same
   result, since all points of an instance share its feature).
3. Mask alignment compares the exact squared distance between the float32-rounded points
   with the threshold; FAISS computes it in float32 (for many queries as
   |x|² + |y|² - 2 x.y), so a point whose squared distance is within float32 rounding of the
   threshold may fall on the other side. Ties between equally near predicted points
   (``global``) go to whichever the k-d tree returns.
4. Duplicate handling, thresholds and curve follow ScanNet/OpenLex3D exactly, but the IoU
   thresholds are the rounded values 0.50, 0.55, ..., 0.90 (``np.arange`` gives
   0.6000000000000001 and the like), which only matters for an IoU exactly on a threshold.
5. Extra outputs OpenLex3D does not have: ``top1_hit_rate`` (share of *synonym queries*, whose
   text is a synonym of at least one of their objects, whose single best-scoring instance
   overlaps one of the query's objects with IoU >= 0.25 on the aligned ground-truth points),
   the ``alignment`` and ``alignment_threshold`` used, counts, and with ``details=True``
   per-object and per-query breakdowns.
6. Undefined figures (no scored object, no query) are None instead of NaN, so the result
   serialises as strict JSON.
7. The labelled ground-truth cloud is ``points.npy``/``labels.npy`` rather than a dataset
   mesh; ``--oracle`` (the ground truth scored as the prediction, one instance per object,
   its feature the normalised mean text embedding of all its synonyms) is ours.
8. Small input conveniences: an object is also excluded when its *category* is one of the
   excluded names (OpenLex3D checks synonyms only); blank and repeated lines of
   ``prompt_list.txt`` are dropped; every negative object id means "no object" (OpenLex3D
   special-cases -100).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any

import numpy as np

from shared.eval.ap import MatchTable, ap_summary
from shared.eval.cloud import (
    Alignment,
    align_instances,
    check_alignment,
    cloud_file_dtype,
    contingency,
    nearest,
    positions_dtype,
    voxel_downsample,
)
from shared.eval.gt import EXCLUDED_LABELS, TIERS, GroundTruth, load_gt, strip_label
from shared.eval.prediction import (
    CLOUD_FILES,
    EMBEDDINGS_FILE,
    Prediction,
    load_prediction,
    oracle_prediction,
)
from shared.eval.text import TextEncoder, check_dimension, cosine, default_encoder, encode_texts

log = logging.getLogger(__name__)

CATEGORIES = ("synonyms", "depictions", "vis_sim", "clutter", "missing", "incorrect")
"""Segmentation categories, in priority order."""
SYNONYMS, DEPICTIONS, VIS_SIM, CLUTTER, MISSING, INCORRECT = range(6)

VOXEL_SIZE = 0.05
"""Prediction downsampling for segmentation (m)."""
ASSOCIATION_RADIUS = 0.05
"""A ground-truth point farther than this from every downsampled predicted point is missing (m)."""
ALIGNMENT: Alignment = "per_mask"
"""Default mask alignment for retrieval (OpenLex3D's ``masks.alignment_mode``)."""
ALIGNMENT_THRESHOLD = 0.001
"""Default alignment threshold (m², compared with the squared distance: a radius of 3.16 cm;
OpenLex3D's ``masks.alignment_threshold``)."""
ALIGN_RADIUS = 0.03
"""Euclidean radius (m) of the one-nearest-point matching that ``trackgraph eval queries``
(``services/query/evaluate.py``) uses through :func:`shared.eval.cloud.transfer_instances`;
the retrieval here aligns with ``ALIGNMENT`` and ``ALIGNMENT_THRESHOLD``."""
TOP_K = 10
"""Predictions per retrieval query."""
TOP1_IOU = 0.25
"""IoU a query's best instance needs with one of its objects to count as a top-1 hit."""


# ---------------------------------------------------------------------------- label tables


def label_tables(
    gt: GroundTruth, object_ids: Annotated[np.ndarray, "(O,) int"]
) -> Annotated[np.ndarray, "(4, O, L) bool: synonyms, depictions, vis_sim, clutter"]:
    """For each scored object and prompt: does the prompt hit each tier (spaces stripped)?"""
    stripped = [strip_label(p) for p in gt.prompts]
    where: dict[str, list[int]] = {}
    for j, s in enumerate(stripped):
        where.setdefault(s, []).append(j)
    out = np.zeros((4, len(object_ids), len(stripped)), bool)

    def mark(tier: int, row: int, labels: Sequence[str]) -> None:
        cols = [j for lab in labels for j in where.get(strip_label(lab), ())]
        out[tier, row, cols] = True

    for row, oid in enumerate(object_ids):
        obj = gt.objects[int(oid)]
        for t, name in enumerate(TIERS):
            mark(t, row, obj.tier(name))
        # OpenLex3D's _check_clutter: any synonym, depiction or visually similar label of
        # a clutter object makes the label clutter (after this object's own tiers).
        for cid in obj.clutter:
            other = gt.objects.get(int(cid))
            if other is not None:
                for name in TIERS:
                    mark(CLUTTER, row, other.tier(name))
    return out


def top_n_prompts(
    features: Annotated[np.ndarray, "(K, D) float"],
    prompt_emb: Annotated[np.ndarray, "(L, D) float"],
    n: int,
) -> Annotated[np.ndarray, "(K, min(n, L)) int prompt indices, best first"]:
    sims = cosine(features, prompt_emb)
    order = np.argsort(-sims, axis=1, kind="stable")
    return order[:, : min(n, prompt_emb.shape[0])]


# ---------------------------------------------------------------------------- segmentation


def segmentation_frequencies(
    pred: Prediction,
    gt: GroundTruth,
    prompt_emb: Annotated[np.ndarray, "(L, D) float"],
    *,
    top_n: int = 5,
    voxel: float = VOXEL_SIZE,
    radius: float = ASSOCIATION_RADIUS,
    excluded: Sequence[str] = EXCLUDED_LABELS,
    positions: np.dtype | None = None,
    details: bool = False,
) -> dict[str, Any]:
    """OpenLex3D's top-N category frequencies (see the module docstring).

    ``positions`` is the precision the prediction's cloud is stored in, which Open3D computes
    its voxel grid in (None: float32 when every coordinate is a float32 value, else float64).
    """
    object_ids = gt.evaluated_object_ids(excluded)
    n_obj = len(object_ids)
    result: dict[str, Any] = {c: None for c in CATEGORIES}
    result["n_objects"] = n_obj
    if n_obj == 0:
        log.warning("no ground-truth object is scored (all excluded or unlabelled)")
        return result

    row = gt.object_rows(object_ids)
    scored = row >= 0
    rows = row[scored]
    gt_pts = gt.points[scored]

    centroids, vox_inst = voxel_downsample(pred.points, pred.index, voxel, dtype=positions_dtype(pred.points, positions))
    dist, nn = nearest(centroids, gt_pts)
    missing = dist > radius
    category = np.full(len(gt_pts), MISSING, np.int64)
    found = ~missing
    if found.any():
        tables = label_tables(gt, object_ids)
        top = top_n_prompts(pred.embeddings, prompt_emb, top_n)[vox_inst[nn[found]]]
        r = rows[found][:, None]
        hits = [tables[t][r, top].any(axis=1) for t in range(4)]
        cat = np.full(int(found.sum()), INCORRECT, np.int64)
        for t in (CLUTTER, VIS_SIM, DEPICTIONS, SYNONYMS):  # highest priority written last
            cat[hits[t]] = t
        category[found] = cat

    counts = np.bincount(rows * len(CATEGORIES) + category, minlength=n_obj * len(CATEGORIES))
    counts = counts.reshape(n_obj, len(CATEGORIES)).astype(np.float64)
    fractions = counts / counts.sum(axis=1, keepdims=True)
    means = fractions.mean(axis=0)
    for c, name in enumerate(CATEGORIES):
        result[name] = float(means[c])
    result["n_points_scored"] = int(len(gt_pts))
    result["n_pred_points_downsampled"] = int(len(centroids))
    if details:
        result["per_object"] = {
            str(int(oid)): {
                "name": gt.objects[int(oid)].name(),
                "points": int(counts[i].sum()),
                **{name: float(fractions[i, c]) for c, name in enumerate(CATEGORIES)},
            }
            for i, oid in enumerate(object_ids)
        }
    return result


# ---------------------------------------------------------------------------- retrieval


def query_scores(
    features: Annotated[np.ndarray, "(K, D) float"], query_emb: Annotated[np.ndarray, "(Q, D) float"]
) -> Annotated[np.ndarray, "(K, Q) float64 in [0, 1]"]:
    """OpenLex3D's per-query normalised similarity: (cos + 1) / 2, min-max over instances."""
    sim = (cosine(features, query_emb).astype(np.float64) + 1.0) / 2.0
    if sim.shape[0] == 0:
        return sim
    lo = sim.min(axis=0, keepdims=True)
    span = np.maximum(sim.max(axis=0, keepdims=True) - lo, 1e-8)
    return (sim - lo) / span


def synonym_query(gt: GroundTruth, text: str, object_ids: Sequence[int]) -> bool:
    s = strip_label(text)
    return any(
        s in {strip_label(x) for x in gt.objects[o].synonyms} for o in object_ids if o in gt.objects
    )


def retrieval(
    pred: Prediction,
    gt: GroundTruth,
    query_emb: Annotated[np.ndarray, "(Q, D) float"],
    *,
    top_k: int = TOP_K,
    alignment: Alignment = ALIGNMENT,
    alignment_threshold: float = ALIGNMENT_THRESHOLD,
    details: bool = False,
) -> dict[str, Any]:
    """Query retrieval AP and top-1 hit rate (see the module docstring). ``alignment`` is
    "per_mask" or "global"; ``alignment_threshold`` is a squared distance (m²)."""
    queries = gt.queries
    point_of, inst_of = align_instances(pred.points, pred.index, gt.points, alignment_threshold, alignment)
    obj_ids, obj_of_point = np.unique(gt.labels, return_inverse=True)
    obj_of_point = np.where(gt.labels >= 0, obj_of_point.reshape(-1), -1)
    obj_size = np.bincount(obj_of_point[obj_of_point >= 0], minlength=len(obj_ids))
    k = pred.n_instances
    # (K, O_all) from the aligned (point, instance) pairs: under per_mask a point may count
    # for several instances, exactly as OpenLex3D intersects the per-instance index lists.
    inter = contingency(inst_of, k, obj_of_point[point_of], len(obj_ids))
    inst_size = np.bincount(inst_of, minlength=k)
    covered = np.zeros(len(gt.points), bool)
    covered[point_of] = True
    scores = query_scores(pred.embeddings, query_emb)  # (K, Q)

    def col(oid: int) -> int:
        j = int(np.searchsorted(obj_ids, oid))
        return j if j < len(obj_ids) and obj_ids[j] == oid and obj_size[j] > 0 else -1

    gt_q, gt_col, pred_q, pred_inst = [], [], [], []
    top1 = []
    per_query = []
    for q, query in enumerate(queries):
        cols = [c for o in query.object_ids if (c := col(o)) >= 0]
        if len(cols) < len(query.object_ids):
            log.debug("query %r: %d of its objects have no ground-truth points", query.text, len(query.object_ids) - len(cols))
        gt_q += [q] * len(cols)
        gt_col += cols
        ranked = np.argsort(-scores[:, q], kind="stable") if k else np.zeros(0, np.int64)
        chosen = [int(i) for i in ranked[:top_k] if inst_size[i] > 0]
        pred_q += [q] * len(chosen)
        pred_inst += chosen
        best_iou = 0.0
        if k and cols:
            b = int(ranked[0])
            i = inter[b, cols].astype(np.float64)
            u = obj_size[cols] + inst_size[b] - i
            best_iou = float(np.max(np.divide(i, u, out=np.zeros_like(i), where=u > 0)))
        is_syn = bool(cols) and synonym_query(gt, query.text, query.object_ids)
        if is_syn:
            top1.append(best_iou >= TOP1_IOU)
        if details:
            per_query.append({
                "query": query.query_id,
                "objects": list(query.object_ids),
                "synonym_query": is_syn,
                "top1_instance": int(ranked[0]) if k else None,
                "top1_iou": best_iou,
            })

    gt_q_a, gt_col_a = np.asarray(gt_q, np.int64), np.asarray(gt_col, np.int64)
    pred_q_a, pred_inst_a = np.asarray(pred_q, np.int64), np.asarray(pred_inst, np.int64)
    # (G, P): points of GT instance g covered by prediction p, zero across queries.
    same_query = gt_q_a[:, None] == pred_q_a[None, :]
    intersection = np.where(same_query, inter[pred_inst_a[None, :], gt_col_a[:, None]], 0)
    table = MatchTable(
        gt_group=gt_q_a,
        gt_size=obj_size[gt_col_a],
        pred_group=pred_q_a,
        pred_size=inst_size[pred_inst_a],
        pred_score=scores[pred_inst_a, pred_q_a] if len(pred_inst_a) else np.zeros(0),
        intersection=intersection,
    )
    out: dict[str, Any] = dict(ap_summary(table))
    out["top1_hit_rate"] = float(np.mean(top1)) if top1 else None
    out["n_queries"] = len(queries)
    out["n_synonym_queries"] = len(top1)
    out["n_gt_instances"] = len(gt_col_a)
    out["n_predictions"] = len(pred_inst_a)
    out["gt_points_aligned"] = float(np.mean(covered)) if len(covered) else 0.0
    out["alignment"] = alignment
    out["alignment_threshold"] = float(alignment_threshold)
    if details:
        out["per_query"] = per_query
    return out


# ---------------------------------------------------------------------------- entry points


def evaluate_openlex3d(
    pred: Prediction,
    gt: GroundTruth,
    encoder: TextEncoder,
    *,
    top_n: int = 5,
    top_k: int = TOP_K,
    alignment: Alignment = ALIGNMENT,
    alignment_threshold: float = ALIGNMENT_THRESHOLD,
    details: bool = False,
) -> dict[str, Any]:
    """Both OpenLex3D tasks on loaded inputs (defaults: OpenLex3D's)."""
    check_alignment(alignment, alignment_threshold)
    if pred.n_instances:
        check_dimension(pred.dim, encoder, pred.file(EMBEDDINGS_FILE))
    prompt_emb = encode_texts(encoder, gt.prompts)
    query_emb = encode_texts(encoder, [q.text for q in gt.queries])
    emb = pred.embeddings if pred.n_instances else np.zeros((0, int(encoder.dim)), np.float32)
    stored = _stored_dtype(pred)
    pred = Prediction(pred.points, pred.index, emb, pred.root)
    seg = segmentation_frequencies(pred, gt, prompt_emb, top_n=top_n, positions=stored, details=details)
    ret = retrieval(
        pred, gt, query_emb, top_k=top_k, alignment=alignment, alignment_threshold=alignment_threshold, details=details
    )
    out = {**seg, **ret}
    out["top_n"] = top_n
    out["n_pred_points"] = len(pred.points)
    out["n_pred_instances"] = pred.n_instances
    return out


def eval_openlex3d(
    pred_dir: str | Path | None,
    gt_dir: str | Path,
    *,
    oracle: bool = False,
    encoder: TextEncoder | None = None,
    top_n: int = 5,
    alignment: Alignment = ALIGNMENT,
    alignment_threshold: float = ALIGNMENT_THRESHOLD,
    details: bool = False,
) -> dict[str, Any]:
    """OpenLex3D scores of the prediction in ``pred_dir`` against the ground truth in ``gt_dir``.

    Returns at least ``synonyms``, ``depictions``, ``vis_sim``, ``clutter``, ``missing``,
    ``incorrect`` (mean per-object shares, summing to 1), ``ap``, ``ap50``, ``ap25``,
    ``top1_hit_rate``, plus ``ap_per_threshold``, ``n_objects``, ``n_queries``,
    ``n_synonym_queries`` and other counts. With ``oracle`` the ground truth itself is scored
    as the prediction (``pred_dir`` is ignored). ``encoder`` defaults to the MiniLM encoder.
    ``alignment`` ("per_mask" or "global") and ``alignment_threshold`` (m², compared with the
    squared distance) choose the retrieval's mask alignment, echoed as the result's
    ``alignment`` and ``alignment_threshold``; the defaults are OpenLex3D's.
    """
    check_alignment(alignment, alignment_threshold)
    t0 = time.perf_counter()
    gt = load_gt(gt_dir)
    enc = encoder if encoder is not None else default_encoder()
    if oracle:
        pred = oracle_prediction(gt, enc)
    else:
        if pred_dir is None:
            raise ValueError("pred_dir is required unless oracle=True")
        pred = load_prediction(pred_dir)
    out = evaluate_openlex3d(
        pred, gt, enc, top_n=top_n, alignment=alignment, alignment_threshold=alignment_threshold, details=details
    )
    out["oracle"] = bool(oracle)
    out["seconds"] = round(time.perf_counter() - t0, 3)
    log.info(
        "OpenLex3D%s: synonyms %.3f, incorrect %.3f, missing %.3f, AP %s, AP50 %s, top-1 %s",
        " (oracle)" if oracle else "",
        out["synonyms"] or 0.0, out["incorrect"] or 0.0, out["missing"] or 0.0,
        _fmt(out["ap"]), _fmt(out["ap50"]), _fmt(out["top1_hit_rate"]),
    )
    return out


def _stored_dtype(pred: Prediction) -> np.dtype | None:
    """The precision of the prediction's cloud file, when it came from one."""
    if pred.root is None:
        return None
    path = next((pred.root / n for n in CLOUD_FILES if (pred.root / n).is_file()), None)
    return cloud_file_dtype(path) if path is not None else None


def _fmt(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.3f}"
