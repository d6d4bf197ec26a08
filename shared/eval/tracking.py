"""2D source-track quality: predicted per-frame track maps against ground-truth instance maps.

Frames evaluated: every frame index with a track map in ``RUN_DIR/tracks`` (a strided run is
scored on the frames it processed); each needs ``SEQ_DIR/instances/instanceNNNNNN.png``. A
track map of another size is resized to the ground truth's (nearest neighbour). Masks
smaller than ``min_area_frac`` of the image are ignored, on both sides.

Per frame, predicted track masks and ground-truth object masks are matched one-to-one twice
with the Hungarian algorithm on IoU:

- **mean_iou**: over all pairs of the max-IoU assignment with IoU > 0 on *non-keyframes*
  (frames not in ``keyframes.json``, i.e. the frames where tracks are propagated rather than
  re-segmented), the mean IoU. Unmatched masks do not enter it (``gt_coverage`` and the
  identity metrics account for them).
- **identity metrics**: pairs of the max-IoU assignment restricted to IoU >= 0.5 are the
  frame's *matches* (a ground-truth object detected by a track), on all frames.

From the matches, over the whole sequence:

- **idf1** (Ristani et al. 2016): ground-truth object ids and track ids are matched globally,
  one-to-one, maximising the identity true positives IDTP (frames in which the pair is
  matched); IDF1 = 2 IDTP / (ground-truth detections + predicted detections), where a
  detection is one (frame, id) mask. ``idp``, ``idr`` likewise.
- **id_switches**: times a ground-truth object's matched track differs from the track it was
  last matched to (gaps do not reset it); ``id_switches_per_100_frames_per_object`` =
  100 x switches / ground-truth detections, i.e. per 100 frames in which an object is visible.
- **fragmentations**: times a ground-truth object's matching is interrupted (visible but
  unmatched) and later resumed, counted over the frames in which it is visible.
- **mota** = 1 - (misses + false tracks + switches) / ground-truth detections.
- **gt_coverage**: share of ground-truth detections that some track overlaps at IoU >= 0.5.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from PIL import Image
from scipy.optimize import linear_sum_assignment

from shared.eval.errors import EvalInputError
from shared.eval.track_io import (
    IdMap,
    instance_path,
    list_track_frames,
    read_id_png,
    read_keyframes,
    track_path,
    tracks_dir,
)

log = logging.getLogger(__name__)

IDENTITY_IOU = 0.5
"""IoU at which a track detects a ground-truth object, for the identity metrics."""
MIN_AREA_FRAC = 0.001
"""Masks smaller than this share of the image are ignored on both sides."""


def _compact(ids: np.ndarray, min_area: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(kept ids, their areas, per-pixel compact index or -1) without sorting: ids are small."""
    flat = ids.reshape(-1).astype(np.int64) + 1  # 0 = none
    area = np.bincount(flat)
    area[0] = 0
    keep = np.flatnonzero(area >= max(min_area, 1))
    lut = np.full(len(area), -1, np.int64)
    lut[keep] = np.arange(len(keep))
    return keep - 1, area[keep], lut[flat]


def mask_ious(
    pred: IdMap, gt: IdMap, min_area: int = 0
) -> tuple[Annotated[np.ndarray, "(P,) track ids"], Annotated[np.ndarray, "(G,) object ids"], Annotated[np.ndarray, "(G, P) IoU"]]:
    """Ids of the masks of at least ``min_area`` pixels on each side, and their IoUs."""
    p_ids, p_area, pc = _compact(pred, min_area)
    g_ids, g_area, gr = _compact(gt, min_area)
    n_p, n_g = len(p_ids), len(g_ids)
    ok = (pc >= 0) & (gr >= 0)
    inter = np.bincount(gr[ok] * n_p + pc[ok], minlength=n_g * n_p).reshape(n_g, n_p).astype(np.float64)
    union = g_area[:, None] + p_area[None, :] - inter
    iou = np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)
    return p_ids, g_ids, iou


def assign(iou: Annotated[np.ndarray, "(G, P)"], min_iou: float, strict: bool = False) -> list[tuple[int, int, float]]:
    """Max-IoU one-to-one pairs (row, col, IoU) with IoU >= ``min_iou`` (> when ``strict``),
    pairs below it being excluded before the assignment."""
    if iou.size == 0:
        return []
    allowed = iou > min_iou if strict else iou >= min_iou
    weights = np.where(allowed, iou, 0.0)
    rows, cols = linear_sum_assignment(weights, maximize=True)
    return [(int(r), int(c), float(iou[r, c])) for r, c in zip(rows, cols, strict=True) if allowed[r, c]]


def _resize_nearest(ids: IdMap, shape: tuple[int, int]) -> IdMap:
    img = Image.fromarray(ids.astype(np.int32))
    return np.asarray(img.resize((shape[1], shape[0]), Image.NEAREST), dtype=np.int32)


def evaluate_track_maps(
    frames: Iterable[tuple[int, IdMap, IdMap]],
    keyframes: set[int],
    *,
    min_area_frac: float = MIN_AREA_FRAC,
) -> dict[str, Any]:
    """The tracking metrics of (frame index, track map, ground-truth map) triples, streamed in
    frame order (see the module docstring)."""
    ious_nonkey: list[float] = []
    match_rows: list[tuple[int, int, int]] = []  # (frame position, gt id, track id)
    det_rows: list[tuple[int, int]] = []  # (frame position, gt id) of every GT detection
    pred_dets = 0
    gt_covered = 0
    n_frames = n_key = 0
    track_ids: set[int] = set()
    for f, (frame, pm, gm) in enumerate(frames):
        if pm.shape != gm.shape:
            raise ValueError(f"frame {frame}: track map {pm.shape} and ground truth {gm.shape} differ in size")
        n_frames += 1
        n_key += int(frame in keyframes)
        min_area = int(np.ceil(min_area_frac * gm.size))
        p_ids, g_ids, iou = mask_ious(pm, gm, min_area)
        pred_dets += len(p_ids)
        track_ids.update(int(t) for t in p_ids)
        det_rows += [(f, int(g)) for g in g_ids]
        if frame not in keyframes:
            ious_nonkey += [v for _, _, v in assign(iou, 0.0, strict=True)]
        for r, c, _ in assign(iou, IDENTITY_IOU):
            match_rows.append((f, int(g_ids[r]), int(p_ids[c])))
        gt_covered += int((iou.max(axis=1) >= IDENTITY_IOU).sum()) if iou.size else 0

    gt_dets = len(det_rows)
    matches = np.asarray(match_rows, np.int64).reshape(-1, 3)
    dets = np.asarray(det_rows, np.int64).reshape(-1, 2)
    n_match = len(matches)

    # IDF1: global one-to-one id matching maximising co-matched frames.
    idtp = 0
    if n_match:
        g_u, g_i = np.unique(matches[:, 1], return_inverse=True)
        t_u, t_i = np.unique(matches[:, 2], return_inverse=True)
        counts = np.zeros((len(g_u), len(t_u)), np.int64)
        np.add.at(counts, (g_i.reshape(-1), t_i.reshape(-1)), 1)
        r, c = linear_sum_assignment(counts, maximize=True)
        idtp = int(counts[r, c].sum())

    # Switches: matched track differs from the object's previous matched track.
    switches = 0
    if n_match:
        m = matches[np.lexsort((matches[:, 0], matches[:, 1]))]
        same_obj = m[1:, 1] == m[:-1, 1]
        switches = int((same_obj & (m[1:, 2] != m[:-1, 2])).sum())

    # Fragmentations: over each object's visible frames, unmatched -> matched after a match.
    fragments = 0
    if gt_dets:
        order = np.lexsort((dets[:, 0], dets[:, 1]))
        d = dets[order]
        span = int(max(d[:, 1].max(), matches[:, 1].max() if n_match else 0)) + 1
        hit = np.isin(d[:, 0] * span + d[:, 1], matches[:, 0] * span + matches[:, 1])
        start = np.ones(len(d), bool)
        start[1:] = d[1:, 1] != d[:-1, 1]
        group = np.cumsum(start) - 1
        csum = np.cumsum(hit)
        before = csum - hit - (csum - hit)[np.flatnonzero(start)][group]  # matches earlier in the object's run
        prev_hit = np.concatenate([[False], hit[:-1]])
        fragments = int((hit & ~prev_hit & ~start & (before > 0)).sum())

    n_objects = len(np.unique(dets[:, 1])) if gt_dets else 0
    misses, false_tracks = gt_dets - n_match, pred_dets - n_match
    denom = gt_dets + pred_dets
    return {
        "mean_iou": float(np.mean(ious_nonkey)) if ious_nonkey else None,
        "idf1": 2.0 * idtp / denom if denom else None,
        "idp": idtp / pred_dets if pred_dets else None,
        "idr": idtp / gt_dets if gt_dets else None,
        "id_switches": switches,
        "id_switches_per_100_frames_per_object": 100.0 * switches / gt_dets if gt_dets else None,
        "fragmentations": fragments,
        "mota": 1.0 - (misses + false_tracks + switches) / gt_dets if gt_dets else None,
        "gt_coverage": gt_covered / gt_dets if gt_dets else None,
        "n_frames": n_frames,
        "n_keyframes": n_key,
        "n_iou_pairs": len(ious_nonkey),
        "n_gt_objects": n_objects,
        "n_tracks": len(track_ids),
        "gt_detections": gt_dets,
        "pred_detections": pred_dets,
        "matches": n_match,
        "idtp": idtp,
    }


def eval_tracking(run_dir: str | Path, seq_dir: str | Path, *, min_area_frac: float = MIN_AREA_FRAC) -> dict[str, Any]:
    """Tracking scores of the track maps saved in ``run_dir`` (``trackgraph map
    --save-tracks``) against the instance maps of ``seq_dir``: ``mean_iou``, ``idf1``,
    ``id_switches_per_100_frames_per_object``, ``fragmentations``, ``mota`` and counts."""
    t0 = time.perf_counter()
    frames = list_track_frames(run_dir)
    if not frames:
        raise EvalInputError(tracks_dir(run_dir), "no track maps (trackNNNNNN.png) found")
    keyframes = set(read_keyframes(run_dir))

    def load() -> Iterator[tuple[int, IdMap, IdMap]]:
        for frame in frames:
            gm = read_id_png(instance_path(seq_dir, frame))
            pm = read_id_png(track_path(run_dir, frame))
            if pm.shape != gm.shape:
                log.debug("resizing track map %d from %s to %s", frame, pm.shape, gm.shape)
                pm = _resize_nearest(pm, gm.shape)
            yield frame, pm, gm

    out = evaluate_track_maps(load(), keyframes, min_area_frac=min_area_frac)
    out["seconds"] = round(time.perf_counter() - t0, 3)
    log.info(
        "tracking: %d frames, mean IoU %s, IDF1 %s, %d switches, %d fragmentations",
        out["n_frames"], _fmt(out["mean_iou"]), _fmt(out["idf1"]), out["id_switches"], out["fragmentations"],
    )
    return out


def _fmt(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.3f}"
