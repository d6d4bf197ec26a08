"""YOLOv8-seg pre- and post-processing in numpy, step for step as ultralytics does it, so an
ONNX export run by onnxruntime gives the masks the ultralytics path gives, without torch.

Shapes: ``output0`` is (1, 4 + nc + nm, A) with boxes as centre x, centre y, width, height at
the network input's scale, then nc class scores, then nm mask coefficients per anchor;
``output1`` is (1, nm, H/4, W/4) mask prototypes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated

import numpy as np

PAD_VALUE = 114
"""Grey of ultralytics' letterbox border."""
MAX_NMS = 30000
"""Most candidates NMS considers, best first (ultralytics' ``max_nms``)."""
CLASS_OFFSET = 7680
"""Box offset per class that keeps class-aware NMS from suppressing across classes."""


@dataclass(frozen=True)
class Letterbox:
    """Where the image sits in the network input."""

    input_hw: tuple[int, int]
    """Network input (height, width)."""
    image_hw: tuple[int, int]
    """Original image (height, width)."""
    resized_wh: tuple[int, int]
    """The image's size inside the input, (width, height)."""
    top: int
    left: int


def input_size(imgsz: int, stride: int) -> int:
    """``imgsz`` rounded up to a multiple of the stride (ultralytics' ``check_imgsz``)."""
    return max(math.ceil(imgsz / stride) * stride, stride)


def plan_letterbox(image_hw: tuple[int, int], new_hw: tuple[int, int], auto: bool, stride: int) -> Letterbox:
    """Scale to fit ``new_hw`` keeping the aspect ratio, then pad around it evenly; with ``auto``
    pad only up to the next multiple of ``stride`` (ultralytics' ``LetterBox.get_params``)."""
    h, w = image_hw
    r = min(new_hw[0] / h, new_hw[1] / w)
    new_w, new_h = max(round(w * r), 1), max(round(h * r), 1)
    dw, dh = new_hw[1] - new_w, new_hw[0] - new_h
    if auto:
        dw, dh = dw % stride, dh % stride
    dw, dh = dw / 2, dh / 2
    top, bottom = round(dh - 0.1), round(dh + 0.1)
    left, right = round(dw - 0.1), round(dw + 0.1)
    return Letterbox((new_h + top + bottom, new_w + left + right), (h, w), (new_w, new_h), top, left)


def _resize_rgb(rgb: np.ndarray, wh: tuple[int, int]) -> np.ndarray:
    try:
        import cv2
    except ImportError:  # pragma: no cover - onnxruntime-only installs
        from PIL import Image

        # PIL's bilinear filter antialiases when shrinking, unlike cv2: masks may differ slightly.
        return np.asarray(Image.fromarray(rgb).resize(wh, Image.BILINEAR))
    return cv2.resize(rgb, wh, interpolation=cv2.INTER_LINEAR)


def letterbox_image(
    rgb: Annotated[np.ndarray, "(H, W, 3) uint8"], lb: Letterbox
) -> Annotated[np.ndarray, "(1, 3, h, w) float32 in [0, 1]"]:
    """The network input: resized with cv2 bilinear (as ultralytics), padded with grey."""
    h, w = lb.image_hw
    resized = rgb if (w, h) == lb.resized_wh else _resize_rgb(rgb, lb.resized_wh)
    out = np.full((*lb.input_hw, 3), PAD_VALUE, np.uint8)
    out[lb.top : lb.top + resized.shape[0], lb.left : lb.left + resized.shape[1]] = resized
    return (out.transpose(2, 0, 1)[None].astype(np.float32)) / 255.0


def box_iou_one(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """IoU of one xyxy box with each of ``boxes`` (as torchvision's ``box_iou``)."""
    x0 = np.maximum(box[0], boxes[:, 0])
    y0 = np.maximum(box[1], boxes[:, 1])
    x1 = np.minimum(box[2], boxes[:, 2])
    y1 = np.minimum(box[3], boxes[:, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    area = (box[2] - box[0]) * (box[3] - box[1])
    areas = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    union = area + areas - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)


def nms(
    boxes: Annotated[np.ndarray, "(N, 4) xyxy"],
    scores: Annotated[np.ndarray, "(N,)"],
    iou_thres: float,
    max_keep: int | None = None,
) -> Annotated[np.ndarray, "(K,) int64 kept indices, best first"]:
    """Greedy non-maximum suppression: a box goes when its IoU with a better kept one exceeds
    ``iou_thres`` (torchvision's ``nms``), then the first ``max_keep`` (ultralytics' ``max_det``).

    Stopping once ``max_keep`` are kept gives the same result, since a box is kept or dropped
    by the better ones alone; it keeps a low ``conf`` (thousands of candidates) from costing one
    numpy pass per candidate."""
    order = np.argsort(-scores, kind="stable")
    keep = []
    alive = np.ones(len(order), bool)
    for rank, i in enumerate(order):
        if max_keep is not None and len(keep) >= max_keep:
            break
        if not alive[rank]:
            continue
        keep.append(i)
        rest = order[rank + 1 :]
        alive[rank + 1 :] &= box_iou_one(boxes[i], boxes[rest]) <= iou_thres
    return np.asarray(keep, np.int64)


@dataclass(frozen=True)
class Detections:
    """Detections after NMS, at the network input's scale."""

    boxes: Annotated[np.ndarray, "(N, 4) float32 xyxy"]
    scores: Annotated[np.ndarray, "(N,) float32"]
    coeffs: Annotated[np.ndarray, "(N, nm) float32 mask coefficients"]


def decode(
    output0: Annotated[np.ndarray, "(1, 4 + nc + nm, A)"],
    n_masks: int,
    conf: float,
    iou: float,
    max_det: int,
) -> Detections:
    """Confidence filter, best class, NMS (ultralytics' ``non_max_suppression``, one image)."""
    pred = np.asarray(output0[0], np.float32).T
    nc = pred.shape[1] - 4 - n_masks
    cls = pred[:, 4 : 4 + nc]
    best = cls.max(axis=1)
    pred, cls, best = pred[best > conf], cls[best > conf], best[best > conf]
    if len(pred) > MAX_NMS:
        top = np.argsort(-best, kind="stable")[:MAX_NMS]
        pred, cls, best = pred[top], cls[top], best[top]
    xywh = pred[:, :4]
    boxes = np.concatenate([xywh[:, :2] - xywh[:, 2:] / 2, xywh[:, :2] + xywh[:, 2:] / 2], axis=1)
    label = cls.argmax(axis=1)
    offset = (label[:, None] * CLASS_OFFSET).astype(np.float32)
    keep = nms(boxes + offset, best, iou, max_det)
    return Detections(boxes[keep], best[keep], pred[keep, 4 + nc :])


def resize_matrix(n_out: int, n_in: int, scale: float | None = None) -> Annotated[np.ndarray, "(n_out, n_in) float32"]:
    """Linear map of torch's bilinear resize along one axis (``align_corners=False``): source
    coordinate ``(i + 0.5) * scale - 0.5`` clamped at 0, ``scale = n_in / n_out`` unless given.
    Coordinates are float32 like torch's CPU kernel, so the weights match it to the last bit."""
    s = np.float32(n_in / n_out if scale is None else scale)
    src = np.maximum((np.arange(n_out, dtype=np.float32) + np.float32(0.5)) * s - np.float32(0.5), np.float32(0))
    i0 = np.minimum(np.floor(src).astype(np.int64), n_in - 1)
    i1 = np.minimum(i0 + 1, n_in - 1)
    lam = src - i0.astype(np.float32)
    m = np.zeros((n_out, n_in), np.float32)
    rows = np.arange(n_out)
    np.add.at(m, (rows, i0), np.float32(1) - lam)
    np.add.at(m, (rows, i1), lam)
    return m


def scale_boxes_to_image(boxes: np.ndarray, lb: Letterbox) -> np.ndarray:
    """Input-scale xyxy boxes to the original image, clipped (ultralytics' ``scale_boxes``)."""
    h, w = lb.image_hw
    ih, iw = lb.input_hw
    gain = min(ih / h, iw / w)
    new_h, new_w = max(round(h * gain), 1), max(round(w * gain), 1)
    gy, gx = new_h / h, new_w / w
    px, py = round((iw - new_w) / 2 - 0.1), round((ih - new_h) / 2 - 0.1)
    out = boxes.astype(np.float32).copy()
    out[:, [0, 2]] = ((out[:, [0, 2]] - px) / gx).clip(0, w)
    out[:, [1, 3]] = ((out[:, [1, 3]] - py) / gy).clip(0, h)
    return out


def _content_crop(src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> tuple[int, int, int, int]:
    """Rows and columns of the image content inside a letterboxed map (``scale_masks``)."""
    sh, sw = src_hw
    dh, dw = dst_hw
    gain = min(sh / dh, sw / dw)
    pad_w, pad_h = (sw - max(round(dw * gain), 1)) / 2, (sh - max(round(dh * gain), 1)) / 2
    top, left = round(pad_h - 0.1), round(pad_w - 0.1)
    return top, top + max(round(dh * gain), 1), left, left + max(round(dw * gain), 1)


def _box_span(lo: float, hi: float, n: int) -> tuple[int, int]:
    """Pixel indices ``i`` with ``lo <= i < hi`` (ultralytics' ``crop_mask``)."""
    return max(int(math.ceil(lo)), 0), min(int(math.ceil(hi)), n)


def masks_native(
    protos: Annotated[np.ndarray, "(nm, mh, mw)"],
    coeffs: Annotated[np.ndarray, "(N, nm)"],
    boxes: Annotated[np.ndarray, "(N, 4) xyxy at image scale"],
    image_hw: tuple[int, int],
) -> Annotated[np.ndarray, "(N, H, W) bool"]:
    """Retina masks (ultralytics' ``process_mask_native``): prototype logits upsampled by 1, 2
    or 4, the letterbox padding cropped, bilinear to the image, and kept where positive (the
    mask probability sigmoid(coeffs @ protos) above 0.5) inside the box.

    Both resizes are linear, so they are folded into one matrix per axis, and only each box's
    rows and columns are computed: everything outside is cropped to zero anyway.
    """
    nm, mh, mw = protos.shape
    h, w = image_hw
    gain = min(4 * mh / h, 4 * mw / w)
    pad = (4 * mh - max(round(h * gain), 1)) | (4 * mw - max(round(w * gain), 1))
    f = 4 // math.gcd(4, pad | pad // 2)
    top, bottom, left, right = _content_crop((f * mh, f * mw), (h, w))
    ry = resize_matrix(h, bottom - top) @ resize_matrix(f * mh, mh, 1.0 / f)[top:bottom]
    rx = resize_matrix(w, right - left) @ resize_matrix(f * mw, mw, 1.0 / f)[left:right]
    flat = protos.reshape(nm, -1).astype(np.float32)
    out = np.zeros((len(coeffs), h, w), bool)
    for i, (c, box) in enumerate(zip(coeffs.astype(np.float32), boxes, strict=True)):
        y0, y1 = _box_span(box[1], box[3], h)
        x0, x1 = _box_span(box[0], box[2], w)
        if y1 <= y0 or x1 <= x0:
            continue
        logits = (c @ flat).reshape(mh, mw)
        out[i, y0:y1, x0:x1] = (ry[y0:y1] @ logits @ rx[x0:x1].T) > 0
    return out


def masks_input_scale(
    protos: Annotated[np.ndarray, "(nm, mh, mw)"],
    coeffs: Annotated[np.ndarray, "(N, nm)"],
    boxes: Annotated[np.ndarray, "(N, 4) xyxy at input scale"],
    lb: Letterbox,
) -> Annotated[np.ndarray, "(N, H, W) bool"]:
    """Masks without retina upsampling (ultralytics' ``process_mask`` with ``upsample``):
    thresholded at the network input's size and cropped to the box there, then the padding is
    dropped and the rest resized to the image and thresholded at 0.5 (``scale_masks``)."""
    nm, mh, mw = protos.shape
    ih, iw = lb.input_hw
    h, w = lb.image_hw
    up_y, up_x = resize_matrix(ih, mh), resize_matrix(iw, mw)
    top, bottom, left, right = _content_crop((ih, iw), (h, w))
    down_y, down_x = resize_matrix(h, bottom - top), resize_matrix(w, right - left)
    flat = protos.reshape(nm, -1).astype(np.float32)
    out = np.zeros((len(coeffs), h, w), bool)
    for i, (c, box) in enumerate(zip(coeffs.astype(np.float32), boxes, strict=True)):
        y0, y1 = _box_span(box[1], box[3], ih)
        x0, x1 = _box_span(box[0], box[2], iw)
        y0, y1, x0, x1 = max(y0, top), min(y1, bottom), max(x0, left), min(x1, right)
        if y1 <= y0 or x1 <= x0:
            continue
        logits = (c @ flat).reshape(mh, mw)
        small = ((up_y[y0:y1] @ logits @ up_x[x0:x1].T) > 0).astype(np.float32)
        cy = down_y[:, y0 - top : y1 - top]
        cx = down_x[:, x0 - left : x1 - left]
        rows = np.flatnonzero(cy.any(axis=1))
        cols = np.flatnonzero(cx.any(axis=1))
        if len(rows) == 0 or len(cols) == 0:
            continue
        r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
        out[i, r0:r1, c0:c1] = (cy[r0:r1] @ small @ cx[c0:c1].T) > 0.5
    return out
