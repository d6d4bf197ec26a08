"""FastSAM (the paper's segmenter) through ultralytics, from a local checkpoint only."""

from __future__ import annotations

import functools
import logging
import os
from pathlib import Path

import numpy as np

from shared.perception import KeyframeImage, Masks
from shared.perception.segmenters.base import check_image, finalize, require_file
from shared.perception.segmenters.fastsam_config import FastSAMConfig

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


EXPECTED = (
    "a FastSAM checkpoint: an ultralytics YOLOv8-seg segmentation model (task 'segment', "
    "SegmentationModel) such as FastSAM-x.pt or FastSAM-s.pt"
)


def describe_checkpoint(path: Path) -> str | None:
    """What a .pt that ultralytics cannot use holds, for the refusal; None when torch's
    weights-only loader (which runs no code from the file) cannot read it either."""
    import torch

    try:
        obj = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception:  # noqa: BLE001 - unreadable for any reason: ultralytics' own words say why
        return None
    if isinstance(obj, dict):
        keys = [str(k) for k in obj]
        if keys and all(isinstance(v, torch.Tensor) for v in obj.values()):
            return f"a bare state dict of {len(keys)} tensors (first keys: {', '.join(keys[:5])}), not a pickled ultralytics model"
        return f"a dict with keys {keys[:8]}, but no pickled ultralytics model under 'model' or 'ema'"
    return f"a {type(obj).__name__}, not an ultralytics checkpoint"


def load_fastsam(path: Path):
    """``ultralytics.FastSAM`` on an existing local checkpoint (never a bare name, which
    ultralytics would try to download). Anything but a YOLOv8-seg checkpoint is refused with
    ValueError naming the file, what it holds and what was expected: ultralytics itself loads
    a detection or classification model without complaint and only fails at the first
    prediction, and words a bare state dict as "types outside the supported format"."""
    path = require_file(path, "FastSAM checkpoint", WEIGHTS_HINT).resolve()  # errors name the absolute path
    if path.suffix.lower() != ".pt":
        # ultralytics treats any other suffix as an exported model and picks a runtime by it.
        raise ValueError(f"{path} is not a .pt file; expected {EXPECTED} (ONNX exports go to the fastsam_onnx backend)")
    ultralytics = import_ultralytics()
    from ultralytics.nn.tasks import SegmentationModel

    try:
        model = ultralytics.FastSAM(str(path))
    except TypeError as exc:  # ultralytics' word for "no pickled model in there" and "unreadable"
        found = describe_checkpoint(path)
        if found is None:
            reason = (str(exc).replace("ERROR ❌️", "").replace(str(path), "the file").strip().splitlines() or [""])[0]
            found = f"nothing torch or ultralytics can read; ultralytics says: {reason}"
        else:
            found = f"it holds {found}"
        raise ValueError(f"{path} is not an ultralytics checkpoint: {found}. Expected {EXPECTED}; {WEIGHTS_HINT}") from exc
    net = model.model
    names = getattr(net, "names", None) or {}
    if model.task != "segment" or not isinstance(net, SegmentationModel):
        raise ValueError(
            f"{path} holds an ultralytics {type(net).__name__} for task {model.task!r} with {len(names)} classes, "
            f"not a FastSAM. Expected {EXPECTED}; {WEIGHTS_HINT}"
        )
    if len(names) != 1:
        # Runs, but segments only the classes it was trained on, not "anything".
        log.warning("%s is a segmentation model with %d classes; FastSAM has one (segment anything)", path, len(names))
    return model


@functools.cache
def _precision_arg() -> str:
    """The name of ultralytics' half-precision setting in the installed version, read from
    its default config once: ``quantize`` (16 or None) where it has replaced ``half`` (a
    bool). ``ultralytics>=8.3`` spans both; the older ones reject ``quantize=`` as an unknown
    argument, the newer ones accept ``half=`` only with a deprecation warning."""
    import_ultralytics()
    from ultralytics.cfg import DEFAULT_CFG_DICT

    return "quantize" if "quantize" in DEFAULT_CFG_DICT else "half"


def precision_kwargs(fp16: bool) -> dict:
    """``predict`` / ``export`` keyword for fp16 (or fp32) in the installed ultralytics."""
    if _precision_arg() == "quantize":
        return {"quantize": 16 if fp16 else None}
    return {"half": bool(fp16)}


class FastSAMSegmenter:
    """FastSAM-x (YOLOv8-seg, one class) via ultralytics, in ``cfg.precision``.

    fp16 on CUDA is ultralytics' own half-precision model; bf16, and fp16 on a CPU (where
    ultralytics runs fp32 whatever it is asked), run under torch autocast around predict.
    ``fp16`` says whether ``precision: auto`` may be half precision on CUDA."""

    name = "fastsam"

    def __init__(self, cfg: FastSAMConfig, device: str = "cpu", fp16: bool = True) -> None:
        from shared.devices import resolve_device, resolve_precision

        self.cfg = cfg
        self.model = load_fastsam(Path(cfg.weights))
        self.device = resolve_device(device, "keyframe_vl.device")
        self.precision = resolve_precision(cfg.precision, self.device, fp16)
        self.fp16 = self.precision == "fp16" and self.device.startswith("cuda")
        log.info("FastSAM %s on %s in %s", cfg.weights, self.device, self.precision)

    def _autocast(self):
        from shared.devices import autocast

        return autocast(self.device, "fp32" if self.fp16 else self.precision)

    def segment(self, image: KeyframeImage) -> Masks:
        h, w = check_image(image.rgb)
        # ultralytics reads numpy images as OpenCV BGR.
        bgr = np.ascontiguousarray(image.rgb[:, :, ::-1])
        with self._autocast():
            result = self._predict(bgr)
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

    def _predict(self, bgr: np.ndarray):
        return self.model.predict(
            bgr,
            imgsz=self.cfg.imgsz,
            conf=self.cfg.conf,
            iou=self.cfg.iou,
            retina_masks=self.cfg.retina_masks,
            max_det=max(MAX_DETECTIONS, self.cfg.max_masks),
            device=self.device,
            **precision_kwargs(self.fp16),
            verbose=False,
        )[0]
