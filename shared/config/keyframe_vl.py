"""FastSAM masks and CLIP features at keyframes (paper section III-B)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from shared.config.base import Device, Precision, StrictModel


class SimulatedSegmenterNoise(StrictModel):
    """Noise model applied to ground-truth masks by the ``simulated`` segmenter."""

    boundary_jitter_px: float = Field(1.5, ge=0)
    """Std of the random morphological boundary shift (pixels)."""
    split_prob: float = Field(0.05, ge=0, le=1)
    """Chance a mask is split in two along its principal axis."""
    merge_prob: float = Field(0.03, ge=0, le=1)
    """Chance a mask is merged with a touching neighbour."""
    miss_below_frac: float = Field(150 / (640 * 480), ge=0, le=1)
    """Objects covering less than this share of the image are dropped, as FastSAM misses small
    objects. A share, not a pixel count, because FastSAM resizes every image to its own input
    size (1024 on the long side) before it detects anything, so what it misses depends on the
    object's size relative to the frame. The default is 150 pixels at 640x480 (about a
    12 x 12 pixel object), 38 at the 320x240 presets."""
    miss_below_px: int | None = Field(None, ge=0)
    """An absolute threshold in pixels instead of ``miss_below_frac``, when set (0 misses
    nothing)."""
    spurious_per_frame: float = Field(0.5, ge=0)
    """Mean number of spurious blob masks added per keyframe."""


class ClassicalSegmenterConfig(StrictModel):
    """Graph-based RGB-D segmentation of the ``classical`` segmenter (no learned weights)."""

    graph_width: int = Field(320, ge=16, le=4096)
    """Least width (pixels) of the pixel graph: the image is reduced by the largest integer
    factor that keeps this many pixels across (640 -> 320, 320 -> 320, 1280 -> 320), and the
    region labels are copied back to full resolution. 160 is about four times faster and a
    little coarser."""
    connectivity: Literal[4, 8] = 8
    """Pixel neighbourhood of the graph."""
    smooth_sigma: float = Field(0.8, ge=0)
    """Gaussian blur (graph pixels) of the colour image before edge weights are taken."""
    colour_weight: float = Field(1.0, ge=0)
    """Weight of the CIE Lab colour distance (per 100 Lab units) in an edge."""
    lightness_weight: float = Field(0.75, ge=0, le=1)
    """Scale of L* against a* and b* in the colour distance: below 1 forgives shading."""
    depth_weight: float = Field(16.0, ge=0)
    """Weight of the depth step not explained by the neighbouring steps, relative to depth."""
    normal_weight: float = Field(0.5, ge=0)
    """Weight of the angle (radians) between the normals of two pixels at a concave crease
    (where an object meets the floor or a wall)."""
    convex_factor: float = Field(0.2, ge=0, le=1)
    """Scale of the normal term at convex creases (the edges of one box-like object)."""
    k: float = Field(1.2, gt=0)
    """Felzenszwalb scale: a region covering a thousandth of the image accepts an edge this much
    heavier than the heaviest one inside it; larger values give larger regions."""
    min_region_frac: float = Field(0.0005, ge=0, le=0.5)
    """Regions smaller than this share of the image merge into their most similar neighbour."""
    min_region_width: float = Field(2.5, ge=0)
    """Regions thinner than this (graph pixels) merge into their most similar neighbour: the
    slivers of mixed pixels along silhouettes."""


class SegmenterConfig(StrictModel):
    """Class-agnostic keyframe segmenter (FastSAM in the paper)."""

    backend: Literal["fastsam", "fastsam_onnx", "classical", "simulated"] = "fastsam"
    """Which implementation; ``simulated`` works only on synthetic scenes."""
    weights: str = "weights/FastSAM-x.pt"
    """Local FastSAM checkpoint (.pt) or ONNX export; never downloaded."""
    imgsz: int = Field(1024, ge=32)
    """FastSAM inference size (long side, pixels)."""
    conf: float = Field(0.4, ge=0, le=1)
    """FastSAM confidence threshold."""
    iou: float = Field(0.9, ge=0, le=1)
    """FastSAM NMS IoU threshold."""
    retina_masks: bool = True
    """Upsample masks to full image resolution before thresholding."""
    max_masks: int = Field(100, ge=1)
    """Keep at most this many masks per keyframe, highest score first."""
    min_area_px: int = Field(100, ge=0)
    """Drop masks smaller than this (pixels)."""
    max_area_frac: float = Field(0.95, gt=0, le=1)
    """Drop masks covering more than this fraction of the image."""
    precision: Precision = "auto"
    """FastSAM's arithmetic: ``fp32``, ``fp16`` (on CUDA ultralytics' own half-precision
    model; on a CPU torch autocast around predict) or ``bf16`` (torch autocast; the weights
    stay fp32). ``auto`` is fp16 on CUDA
    when ``keyframe_vl.fp16`` (tensor cores run half precision at full rate) and fp32 on a
    CPU, where fp16 is emulated: on this 2-core CPU a random-weight FastSAM-s took 0.55 s a
    320 px keyframe in fp16 against 0.12 s in bf16."""
    noise: SimulatedSegmenterNoise = Field(default_factory=SimulatedSegmenterNoise)
    """Noise of the ``simulated`` backend; all zeros reproduces the ground truth."""
    seed: int = 0
    """Seed of the ``simulated`` backend's noise, combined with the frame index."""
    ground_truth: str | None = None
    """``simulated`` backend only: the synthetic sequence folder (``SEQ_DIR`` with
    ``instances/``) whose instance images it reads by keyframe index. ``trackgraph map``,
    ``launch`` and ``serve --sequence`` set it to the sequence when unset."""
    classical: ClassicalSegmenterConfig = Field(default_factory=ClassicalSegmenterConfig)
    """Knobs of the ``classical`` backend."""


class VLEncoderConfig(StrictModel):
    """Vision-language encoder for keyframe crops and queries (CLIP in the paper)."""

    backend: Literal["openclip", "clip_onnx", "simulated"] = "openclip"
    """Which implementation; ``simulated`` works only on synthetic scenes."""
    model: str = "ViT-H-14"
    """OpenCLIP architecture; ViT-H-14 in the paper (IV-A), ViT-B-32 onboard."""
    weights: str = "weights/open_clip_vit_h14.bin"
    """Local OpenCLIP checkpoint or ONNX folder; never downloaded."""
    crop_padding: float = Field(0.1, ge=0, le=1)
    """Padding of each mask's bounding-box crop, as a fraction of its size (III-B)."""
    crop_mode: Literal["pad_square", "center_crop"] = "pad_square"
    """How the padded box becomes CLIP's square input. ``pad_square``: the crop is centred on
    a square of CLIP's mean colour (zero after normalisation) and resized whole, so every
    pixel of the object is seen. ``center_crop``: OpenCLIP's own transform, which resizes the
    short side and cuts the middle square; an elongated crop loses its ends (a 165x6 box keeps
    4% of its width). Image queries always use OpenCLIP's own transform."""
    precision: Precision = "auto"
    """CLIP's arithmetic, under torch autocast (the weights stay fp32): ``fp32``, ``fp16`` or
    ``bf16``. ``auto`` is fp16 on CUDA when ``keyframe_vl.fp16`` (tensor cores run half
    precision at full rate) and fp32 on a CPU, where fp16 is emulated and slower. On random
    ViT-S-32 weights, crop features in bf16 have cosine 0.9999 to fp32's, in fp16 1.0000
    (tests/services/keyframe_vl/encoders/test_enc_precision.py). ONNX exports run in the
    precision they were written in."""
    batch_size: int = Field(16, ge=1)
    """Crops per forward pass."""
    noise_std: float = Field(0.05, ge=0)
    """Gaussian noise added by the ``simulated`` encoder before normalisation."""
    ground_truth: str | None = None
    """``simulated`` backend only: the synthetic sequence folder (``SEQ_DIR``; its ``gt/``
    subfolder is accepted too). The encoder mixes the labels of ``gt/gt_categories.json`` by
    the instance images of ``instances/``, read by keyframe index for crops and by pixel
    content for image queries. ``trackgraph map``, ``launch`` and ``serve --sequence`` set it
    to the sequence when unset."""


class KeyframeVLConfig(StrictModel):
    """The keyframe_vl service."""

    segmenter: SegmenterConfig = Field(default_factory=SegmenterConfig)
    """Mask backend."""
    vl: VLEncoderConfig = Field(default_factory=VLEncoderConfig)
    """CLIP backend."""
    device: Device = "auto"
    """Torch device of FastSAM and CLIP: ``auto`` (CUDA when present), ``cpu``, ``cuda`` or
    ``cuda:N``."""
    fp16: bool = True
    """What ``precision: auto`` of the segmenter and the CLIP encoder means on a GPU: fp16
    when true, fp32 when false (ignored on CPU)."""
    embed_cache_size: int = Field(256, ge=0)
    """Text embeddings kept for repeated ``vl/embed`` queries."""

