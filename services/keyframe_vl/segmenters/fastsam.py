"""FastSAM (the paper's segmenter) through ultralytics, from a local checkpoint only."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from services.keyframe_vl.segmenters.base import check_image, finalize, require_file
from shared.config.keyframe_vl import SegmenterConfig
from shared.perception import KeyframeImage, Masks

log = logging.getLogger(__name__)

WEIGHTS_HINT = (
    "download FastSAM-x.pt (github.com/ultralytics/assets/releases, or the FastSAM authors' "
    "release) on a machine with internet access and copy it there, or point "
    "keyframe_vl.segmenter.weights at your copy; trackgraph never downloads weights"
)

MAX_DETECTIONS = 300
"""Detections kept by NMS before the area filter (ultralytics' own default)."""


def import_ultralytics():
    """``import ultralytics`` without the process-wide side effects it has on import.

    - ``YOLO_OFFLINE=1`` first: ultralytics decides at import whether it is online, and offline
      it neither phones home nor tries to pip-install anything.
    - torch before it: ultralytics sets ``OMP_NUM_THREADS=1`` when unset, which would leave a
      torch imported after it on one CPU thread; the variable is removed again afterwards.
    - ``PIL.Image.open`` restored: ultralytics swaps in a wrapper that pip-installs a HEIF
      plugin whenever PIL cannot identify a file, which changes every other reader's errors.
    - numpy print options restored.
    """
    os.environ.setdefault("YOLO_OFFLINE", "1")
    had_omp = "OMP_NUM_THREADS" in os.environ
    print_options = np.get_printoptions()
    import torch  # noqa: F401  (see above: before ultralytics)
    import ultralytics
    from PIL import Image
    from ultralytics.utils import patches

    if Image.open is getattr(patches, "image_open", None):
        Image.open = patches._image_open
    if not had_omp:
        os.environ.pop("OMP_NUM_THREADS", None)
    np.set_printoptions(**print_options)
    return ultralytics


def load_fastsam(path: Path):
    """``ultralytics.FastSAM`` on an existing local checkpoint (never a bare name, which
    ultralytics would try to download)."""
    require_file(path, "FastSAM checkpoint", WEIGHTS_HINT)
    return import_ultralytics().FastSAM(str(path))


class FastSAMSegmenter:
    """FastSAM-x (YOLOv8-seg, one class) via ultralytics; CUDA and fp16 when asked for."""

    name = "fastsam"

    def __init__(self, cfg: SegmenterConfig, device: str = "cpu", fp16: bool = False) -> None:
        self.cfg = cfg
        self.model = load_fastsam(Path(cfg.weights))
        if device == "auto":
            import torch

            device = "cuda" if torch.cuda.is_available() else "cpu"
        self.device = device
        self.fp16 = bool(fp16) and device.startswith("cuda")
        log.info("FastSAM %s on %s%s", cfg.weights, device, " fp16" if self.fp16 else "")

    def segment(self, image: KeyframeImage) -> Masks:
        h, w = check_image(image.rgb)
        # ultralytics reads numpy images as OpenCV BGR.
        bgr = np.ascontiguousarray(image.rgb[:, :, ::-1])
        result = self.model.predict(
            bgr,
            imgsz=self.cfg.imgsz,
            conf=self.cfg.conf,
            iou=self.cfg.iou,
            retina_masks=self.cfg.retina_masks,
            max_det=max(MAX_DETECTIONS, self.cfg.max_masks),
            device=self.device,
            quantize=16 if self.fp16 else None,
            verbose=False,
        )[0]
        if result.masks is None or len(result.masks) == 0:
            return Masks.empty(h, w)
        data = result.masks.data
        if tuple(data.shape[1:]) != (h, w):
            # Without retina masks they come at the letterboxed input size: drop the padding
            # and resize, as ultralytics does for its own prompts.
            from ultralytics.utils.ops import scale_masks

            data = scale_masks(data[None].float(), (h, w))[0] > 0.5
        masks = data.bool().cpu().numpy()
        scores = result.boxes.conf.float().cpu().numpy()
        return finalize(masks, scores, self.cfg)
