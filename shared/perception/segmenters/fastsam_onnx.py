"""FastSAM exported to ONNX and run by onnxruntime, with numpy post-processing (no torch at
run time), and the export itself.

The export is dynamic-shape by default. ultralytics' predictor letterboxes a frame for .pt
weights to the smallest stride-multiple rectangle (``LetterBox(auto=True)``: 480x640 at imgsz
1024 becomes 768x1024, no padding), and the network's output depends on the input's shape and
its grey border, so only an export that accepts that rectangle gives the .pt path's masks. A
static square export still works on any frame, letterboxed to its fixed size like
ultralytics' own predictor does for static exports, but its masks differ (the network sees a
different input).
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from pathlib import Path
from typing import Annotated

import numpy as np

from shared.perception import KeyframeImage, Masks
from shared.perception.segmenters import yolo_post
from shared.perception.segmenters.base import check_image, finalize, require_file
from shared.perception.segmenters.fastsam import (
    MAX_DETECTIONS,
    WEIGHTS_HINT,
    load_fastsam,
    precision_kwargs,
)
from shared.perception.segmenters.fastsam_config import FastSAMOnnxConfig

log = logging.getLogger(__name__)

ONNX_HINT = (
    "export it from a local FastSAM checkpoint with "
    "`trackgraph export-onnx --config FILE --out DIR` or "
    "`python -m shared.perception.segmenters.fastsam_onnx FastSAM-x.pt FastSAM-x.onnx --imgsz 1024` "
    "(export_fastsam_onnx), or point keyframe_vl.segmenter.weights at your export"
)


def export_fastsam_onnx(
    pt_path: str | Path,
    onnx_path: str | Path,
    imgsz: int = 1024,
    dynamic: bool = True,
    fp16: bool = False,
    device: str = "cpu",
) -> Path:
    """Export a local FastSAM checkpoint to ONNX with ultralytics' exporter (not simplified, so
    no extra packages are needed). ``dynamic`` (the default) accepts any input size; the
    ``fastsam_onnx`` backend then letterboxes each frame to the rectangle the .pt path uses at
    its configured ``imgsz``, and the masks are the .pt path's. ``dynamic=False`` fixes the
    input at ``imgsz`` x ``imgsz`` (for runtimes without dynamic shapes): frames of any other
    aspect are padded to that square and their masks differ from the .pt path's. ``fp16``
    writes a half-precision model, which ultralytics exports on a CUDA ``device`` only."""
    pt_path = require_file(pt_path, "FastSAM checkpoint", WEIGHTS_HINT)
    onnx_path = Path(onnx_path)
    with tempfile.TemporaryDirectory() as tmp:
        # The exporter writes next to its source file; a private copy keeps the user's folder clean.
        src = Path(tmp) / pt_path.name
        shutil.copyfile(pt_path, src)
        made = load_fastsam(src).export(
            format="onnx",
            imgsz=imgsz,
            dynamic=dynamic,
            simplify=False,
            **precision_kwargs(fp16),  # quantize= or half=, whichever this ultralytics knows
            device=device,
            verbose=False,
        )
        onnx_path.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(str(made), onnx_path)
    log.info("exported %s to %s (imgsz %d%s%s)", pt_path, onnx_path, imgsz, ", dynamic" if dynamic else "", ", fp16" if fp16 else "")
    return onnx_path


class FastSAMOnnxSegmenter:
    """A FastSAM ONNX export on onnxruntime; masks decoded in numpy as ultralytics does."""

    name = "fastsam_onnx"

    def __init__(self, cfg: FastSAMOnnxConfig, device: str = "cpu", fp16: bool = False) -> None:
        path = require_file(cfg.weights, "FastSAM ONNX export", ONNX_HINT)
        import onnxruntime as ort

        from shared.devices import onnx_providers

        self.cfg = cfg
        self.session = ort.InferenceSession(str(path), providers=onnx_providers(device, "keyframe_vl.device"))
        inp = self.session.get_inputs()[0]
        self.input_name = inp.name
        self.input_dtype = np.float16 if inp.type == "tensor(float16)" else np.float32
        meta = self.session.get_modelmeta().custom_metadata_map
        self.stride = int(meta.get("stride", 32))
        dims = inp.shape[2:]
        self.dynamic = not all(isinstance(d, int) for d in dims)
        side = yolo_post.input_size(cfg.imgsz, self.stride)
        # What ultralytics' predictor letterboxes to for .pt weights at this imgsz: the square
        # of check_imgsz, shrunk to the smallest stride-multiple rectangle (LetterBox auto=True).
        self.pt_hw = (side, side)
        if self.dynamic:
            self.new_hw = self.pt_hw
        else:
            self.new_hw = (int(dims[0]), int(dims[1]))
            if cfg.imgsz != max(self.new_hw):
                log.warning("%s has a fixed %s input; imgsz %d is ignored", path, self.new_hw, cfg.imgsz)
        self._warned_shapes: set[tuple[int, int]] = set()
        self.path = path
        if fp16 and self.input_dtype != np.float16:
            log.info("%s is an fp32 export; export_fastsam_onnx(..., fp16=True) on CUDA makes an fp16 one", path)
        log.info(
            "FastSAM ONNX %s on %s, input %s%s",
            path, self.session.get_providers()[0], self.new_hw, " (dynamic)" if self.dynamic else "",
        )

    def raw(
        self, rgb: Annotated[np.ndarray, "(H, W, 3) uint8"]
    ) -> tuple[
        yolo_post.Letterbox,
        Annotated[np.ndarray, "(1, 4 + nc + nm, A) float32 detections"],
        Annotated[np.ndarray, "(1, nm, h/4, w/4) float32 mask prototypes"],
    ]:
        """Letterbox plan and the two raw outputs (detections, prototypes) for one image."""
        h, w = check_image(rgb)
        lb = yolo_post.plan_letterbox((h, w), self.new_hw, auto=self.dynamic, stride=self.stride)
        if not self.dynamic:
            self._warn_if_unlike_pt(lb)
        x = yolo_post.letterbox_image(rgb, lb).astype(self.input_dtype)
        out0, out1 = self.session.run(None, {self.input_name: x})[:2]
        return lb, np.asarray(out0, np.float32), np.asarray(out1, np.float32)

    def _warn_if_unlike_pt(self, lb: yolo_post.Letterbox) -> None:
        """Once per frame size: a static export that letterboxes otherwise than the .pt path
        feeds the network another input (other size, more grey border), so its masks differ."""
        if lb.image_hw in self._warned_shapes:
            return
        self._warned_shapes.add(lb.image_hw)
        pt = yolo_post.plan_letterbox(lb.image_hw, self.pt_hw, auto=True, stride=self.stride)
        if (pt.input_hw, pt.resized_wh) != (lb.input_hw, lb.resized_wh):
            log.warning(
                "%s has a fixed %dx%d (height x width) input: %dx%d frames are letterboxed to it, while "
                "the .pt path letterboxes them to %dx%d, so the masks will differ from the .pt path's; export a "
                "dynamic-shape model (trackgraph export-onnx, or export_fastsam_onnx(..., dynamic=True)) "
                "to get the same masks",
                self.path, *lb.input_hw, *lb.image_hw, *pt.input_hw,
            )

    def segment(self, image: KeyframeImage) -> Masks:
        lb, out0, out1 = self.raw(image.rgb)
        protos = out1[0]
        det = yolo_post.decode(out0, protos.shape[0], self.cfg.conf, self.cfg.iou, max(MAX_DETECTIONS, self.cfg.max_masks))
        h, w = lb.image_hw
        if len(det.scores) == 0:
            return Masks.empty(h, w)
        if self.cfg.retina_masks:
            boxes = yolo_post.scale_boxes_to_image(det.boxes, lb)
            masks = yolo_post.masks_native(protos, det.coeffs, boxes, (h, w))
        else:
            masks = yolo_post.masks_input_scale(protos, det.coeffs, det.boxes, lb)
        return finalize(masks, det.scores, self.cfg)


def main(argv: list[str] | None = None) -> None:
    import argparse

    parser = argparse.ArgumentParser(description="Export a local FastSAM checkpoint to ONNX.")
    parser.add_argument("pt", help="FastSAM .pt checkpoint (never downloaded)")
    parser.add_argument("onnx", help="where to write the .onnx file")
    parser.add_argument("--imgsz", type=int, default=1024)
    shape = parser.add_mutually_exclusive_group()
    shape.add_argument(
        "--dynamic", dest="dynamic", action="store_true", default=True,
        help="accept any input size, letterboxed as the .pt path does (the default)",
    )
    shape.add_argument(
        "--static", dest="dynamic", action="store_false",
        help="fixed imgsz x imgsz input; masks of non-square frames then differ from the .pt path's",
    )
    parser.add_argument("--fp16", action="store_true", help="half precision (needs --device cuda)")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    print(export_fastsam_onnx(args.pt, args.onnx, args.imgsz, args.dynamic, args.fp16, args.device))


if __name__ == "__main__":
    main()
