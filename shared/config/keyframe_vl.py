"""FastSAM masks and CLIP features at keyframes (paper section III-B)."""

from __future__ import annotations

from abc import abstractmethod
from typing import Literal

from pydantic import Field

from shared.config.backends import BackendConfig, backend_config, backend_section
from shared.config.base import Device, Precision, StrictModel
from shared.registry import Registry

SEGMENTERS: Registry[type[SegmenterBackend]] = Registry("segmenter backend")
"""Keyframe segmenter backends (``keyframe_vl.segmenter.backend``)."""

VL_ENCODERS: Registry[type[VLEncoderBackend]] = Registry("VL encoder backend")
"""Vision-language encoder backends (``keyframe_vl.vl.backend``)."""


class SegmenterBackend(BackendConfig):
    """What every class-agnostic keyframe segmenter (FastSAM in the paper) shares: the filter
    its masks pass (services/keyframe_vl/segmenters/base.py)."""

    max_masks: int = Field(100, ge=1)
    """Keep at most this many masks per keyframe, highest score first."""
    min_area_px: int = Field(100, ge=0)
    """Drop masks smaller than this (pixels)."""
    max_area_frac: float = Field(0.95, gt=0, le=1)
    """Drop masks covering more than this fraction of the image."""

    @abstractmethod
    def build(self, device: str = "cpu", fp16: bool = False):
        """The :class:`~shared.perception.Segmenter` this config describes. ``device`` and
        ``fp16`` matter to the backends that run a network; missing weights raise
        FileNotFoundError naming the path (nothing is ever downloaded)."""


class VLEncoderBackend(BackendConfig):
    """What every vision-language encoder (CLIP in the paper) is asked for."""

    @abstractmethod
    def build(self, device: str = "cpu", fp16: bool = True, ground_truth=None):
        """The :class:`~shared.perception.VLEncoder` this config describes. ``device`` is
        ``cpu``, ``cuda`` (or ``cuda:N``) or ``auto``; ``fp16`` says whether a ``precision:
        auto`` may be half precision on CUDA (shared/devices.py); ``ground_truth`` (an
        :class:`~shared.datasets.ground_truth.InstanceSource`) stands in for a simulated
        backend's sequence folder (tests)."""


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


class _FastSAMFields(SegmenterBackend):
    """FastSAM's settings, shared by the ultralytics and the ONNX runtime backends."""

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


@SEGMENTERS.register("fastsam")
class FastSAMConfig(_FastSAMFields):
    """FastSAM on ultralytics: the paper's FastSAM-x (III-B)."""

    backend: Literal["fastsam"] = "fastsam"
    """FastSAM on ultralytics (services/keyframe_vl/segmenters/fastsam.py)."""
    precision: Precision = "auto"
    """FastSAM's arithmetic: ``fp32``, ``fp16`` (on CUDA ultralytics' own half-precision
    model; on a CPU torch autocast around predict) or ``bf16`` (torch autocast; the weights
    stay fp32). ``auto`` is fp16 on CUDA
    when ``keyframe_vl.fp16`` (tensor cores run half precision at full rate) and fp32 on a
    CPU, where fp16 is emulated: on this 2-core CPU a random-weight FastSAM-s took 0.55 s a
    320 px keyframe in fp16 against 0.12 s in bf16."""

    def build(self, device: str = "cpu", fp16: bool = False):
        from services.keyframe_vl.segmenters.fastsam import FastSAMSegmenter

        return FastSAMSegmenter(self, device=device, fp16=fp16)


@SEGMENTERS.register("fastsam_onnx")
class FastSAMOnnxConfig(_FastSAMFields):
    """FastSAM exported to ONNX (``trackgraph export-onnx``), run by onnxruntime. It runs in
    the precision it was exported in."""

    backend: Literal["fastsam_onnx"] = "fastsam_onnx"
    """FastSAM's ONNX export on onnxruntime (services/keyframe_vl/segmenters/fastsam_onnx.py)."""
    weights: str = "weights/FastSAM-x.onnx"
    """Local FastSAM ONNX export (``trackgraph export-onnx``); never downloaded."""

    def build(self, device: str = "cpu", fp16: bool = False):
        from services.keyframe_vl.segmenters.fastsam_onnx import FastSAMOnnxSegmenter

        return FastSAMOnnxSegmenter(self, device=device, fp16=fp16)


@SEGMENTERS.register("classical")
class ClassicalSegmenterConfig(SegmenterBackend):
    """Graph-based RGB-D segmentation (no learned weights)."""

    backend: Literal["classical"] = "classical"
    """Graph-based RGB-D segmentation, no weights (services/keyframe_vl/segmenters/classical.py)."""

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

    def build(self, device: str = "cpu", fp16: bool = False):
        from services.keyframe_vl.segmenters.classical import ClassicalSegmenter

        return ClassicalSegmenter(self)


@SEGMENTERS.register("simulated")
class SimulatedSegmenterConfig(SegmenterBackend):
    """Noisy ground-truth masks of a synthetic scene: measures the mapping, not FastSAM."""

    backend: Literal["simulated"] = "simulated"
    """Ground truth with FastSAM-like errors; synthetic scenes only
    (services/keyframe_vl/segmenters/simulated.py)."""
    noise: SimulatedSegmenterNoise = Field(default_factory=SimulatedSegmenterNoise)
    """The errors; all zeros reproduces the ground truth."""
    seed: int = 0
    """Seed of the noise, combined with the frame index."""
    ground_truth: str | None = None
    """The synthetic sequence folder (``SEQ_DIR`` with ``instances/``) whose instance images
    it reads by keyframe index. ``trackgraph map``, ``launch`` and ``serve --sequence`` set it
    to the sequence when unset."""

    def build(self, device: str = "cpu", fp16: bool = False):
        from services.keyframe_vl.segmenters.simulated import SimulatedSegmenter

        return SimulatedSegmenter(self)


SegmenterSection, _segmenter_default = backend_section(SEGMENTERS, SegmenterBackend, "fastsam")
"""``keyframe_vl.segmenter``: the fields of the backend its ``backend`` key names."""


def segmenter_config(**fields) -> SegmenterBackend:
    """A ``keyframe_vl.segmenter`` section from keyword fields (``backend`` default ``fastsam``)."""
    return backend_config(SEGMENTERS, "fastsam", **fields)


class _ClipFields(VLEncoderBackend):
    """An OpenCLIP model's settings, shared by the torch and the ONNX runtime backends."""

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
    batch_size: int = Field(16, ge=1)
    """Crops per forward pass."""


@VL_ENCODERS.register("openclip")
class OpenClipConfig(_ClipFields):
    """OpenCLIP from a local checkpoint: the paper's ViT-H-14 (IV-A)."""

    backend: Literal["openclip"] = "openclip"
    """OpenCLIP on torch (services/keyframe_vl/encoders/openclip.py)."""
    precision: Precision = "auto"
    """CLIP's arithmetic, under torch autocast (the weights stay fp32): ``fp32``, ``fp16`` or
    ``bf16``. ``auto`` is fp16 on CUDA when ``keyframe_vl.fp16`` (tensor cores run half
    precision at full rate) and fp32 on a CPU, where fp16 is emulated and slower. On random
    ViT-S-32 weights, crop features in bf16 have cosine 0.9999 to fp32's, in fp16 1.0000
    (tests/services/keyframe_vl/encoders/test_enc_precision.py)."""

    def build(self, device: str = "cpu", fp16: bool = True, ground_truth=None):
        from services.keyframe_vl.encoders.openclip import OpenClipEncoder
        from shared.devices import resolve_device, resolve_precision

        device = resolve_device(device)
        return OpenClipEncoder(
            self.model, self.weights, device=device, precision=resolve_precision(self.precision, device, fp16),
            crop_padding=self.crop_padding, batch_size=self.batch_size, crop_mode=self.crop_mode,
        )  # fmt: skip


@VL_ENCODERS.register("clip_onnx")
class ClipOnnxConfig(_ClipFields):
    """OpenCLIP's towers exported to ONNX (``trackgraph export-onnx``), run by onnxruntime in
    the precision they were exported in."""

    backend: Literal["clip_onnx"] = "clip_onnx"
    """OpenCLIP's ONNX export on onnxruntime (services/keyframe_vl/encoders/clip_onnx.py)."""

    def build(self, device: str = "cpu", fp16: bool = True, ground_truth=None):
        from services.keyframe_vl.encoders.clip_onnx import ClipOnnxEncoder
        from shared.devices import resolve_device

        return ClipOnnxEncoder(
            self.weights, arch=self.model, device=resolve_device(device),
            crop_padding=self.crop_padding, batch_size=self.batch_size, crop_mode=self.crop_mode,
        )  # fmt: skip


@VL_ENCODERS.register("simulated")
class SimulatedVLConfig(VLEncoderBackend):
    """Ground-truth label mixtures in MiniLM text space: measures the mapping, not CLIP."""

    backend: Literal["simulated"] = "simulated"
    """Ground-truth labels embedded by a real offline text encoder; synthetic scenes only
    (services/keyframe_vl/encoders/simulated.py)."""
    noise_std: float = Field(0.05, ge=0)
    """Gaussian noise added before normalisation."""
    ground_truth: str | None = None
    """The synthetic sequence folder (``SEQ_DIR``; its ``gt/`` subfolder is accepted too). The
    encoder mixes the labels of ``gt/gt_categories.json`` by the instance images of
    ``instances/``, read by keyframe index for crops and by pixel content for image queries.
    ``trackgraph map``, ``launch`` and ``serve --sequence`` set it to the sequence when
    unset."""

    def build(self, device: str = "cpu", fp16: bool = True, ground_truth=None):
        from services.keyframe_vl.encoders.simulated import SimulatedVLEncoder

        # The text encoder stays on the CPU: its embeddings are cached on disk by text, and
        # a crop costs no network pass at all.
        return SimulatedVLEncoder(self.ground_truth, noise_std=self.noise_std, source=ground_truth)


VLSection, _vl_default = backend_section(VL_ENCODERS, VLEncoderBackend, "openclip")
"""``keyframe_vl.vl``: the fields of the backend its ``backend`` key names."""


def vl_config(**fields) -> VLEncoderBackend:
    """A ``keyframe_vl.vl`` section from keyword fields (``backend`` default ``openclip``)."""
    return backend_config(VL_ENCODERS, "openclip", **fields)


class KeyframeVLConfig(StrictModel):
    """The keyframe_vl service."""

    segmenter: SegmenterSection = _segmenter_default
    """Mask backend: ``backend`` (one of the segmenter registry's: ``fastsam``,
    ``fastsam_onnx``, ``classical``, ``simulated``) and that backend's fields."""
    vl: VLSection = _vl_default
    """CLIP backend: ``backend`` (``openclip``, ``clip_onnx``, ``simulated``) and that
    backend's fields."""
    device: Device = "auto"
    """Torch device of FastSAM and CLIP: ``auto`` (CUDA when present), ``cpu``, ``cuda`` or
    ``cuda:N``."""
    fp16: bool = True
    """What ``precision: auto`` of the segmenter and the CLIP encoder means on a GPU: fp16
    when true, fp32 when false (ignored on CPU)."""
    embed_cache_size: int = Field(256, ge=0)
    """Text embeddings kept for repeated ``vl/embed`` queries."""

