"""``trackgraph eval segmenter``: per-keyframe mask quality against ground-truth instances."""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from shared.config.root import TrackGraphConfig
from shared.datasets import open_sequence
from shared.eval import mean_best_iou

log = logging.getLogger(__name__)


def eval_segmenter(seq_dir: Path, cfg: TrackGraphConfig, *, every: int | None = None) -> dict[str, Any]:
    """Segment every K_f-th frame (the keyframes) and match each ground-truth object larger
    than 0.5% of the image to its best mask. ``mean_best_iou`` averages over all such
    (keyframe, object) pairs; ``objects`` counts them."""
    from services.mapping import prepare_config
    from shared.perception import KeyframeImage
    from shared.perception.segmenters import make_segmenter

    cfg = prepare_config(cfg, Path(seq_dir))
    reader = open_sequence(seq_dir, cfg.source.dataset, cfg.source)
    step = every or cfg.tracker.keyframe_interval
    segmenter = make_segmenter(cfg.keyframe_vl.segmenter, device=cfg.keyframe_vl.device, fp16=cfg.keyframe_vl.fp16)
    ious: list[float] = []
    per_frame = []
    seconds = []
    for i in range(0, len(reader), step):
        frame, instances = reader.frame(i), reader.instances(i)
        if instances is None:
            raise ValueError(f"{seq_dir}: frame {i} has no ground-truth instances (instances/ folder)")
        image = KeyframeImage(frame.frame_index, frame.rgb, frame.depth_m(), frame.intrinsics)
        t0 = time.perf_counter()
        masks = segmenter.segment(image)
        seconds.append(time.perf_counter() - t0)
        mean, per_obj = mean_best_iou(masks.masks, instances)
        ious.extend(per_obj.values())
        per_frame.append({"frame": i, "masks": len(masks), "objects": len(per_obj), "mean_best_iou": None if math.isnan(mean) else mean})
    result = {
        "mean_best_iou": float(np.mean(ious)) if ious else None,
        "objects": len(ious),
        "keyframes": len(per_frame),
        "segmenter": cfg.keyframe_vl.segmenter.backend,
        "ms_per_keyframe": round(1000 * float(np.mean(seconds)), 1) if seconds else None,
        "per_keyframe": per_frame,
    }
    log.info("segmenter %s: mean best IoU %.3f over %d objects in %d keyframes", result["segmenter"], result["mean_best_iou"] or 0, len(ious), len(per_frame))
    return result
