"""Benchmark: keyframe latency of the keyframe_vl core per backend, and message sizes.

    python benchmarks/keyframe_vl.py --quick          # weightless backends + small learned ones
    python benchmarks/keyframe_vl.py                   # adds FastSAM-x + ViT-B-32 on this CPU
    python benchmarks/keyframe_vl.py --paper --device cuda   # FastSAM-x + ViT-H-14 at 1200x680

Learned models are the real architectures with random weights (same FLOPs as the real ones;
see services/models/random_weights.py). Frames come from the synthetic ``small`` scene,
resized to the case's resolution. Segmentation is timed on the backend's own masks; CLIP is
timed on the crops of the frame's ground-truth objects, so every backend embeds the same,
realistic number of crops, and the mask message is sized on those masks too: random FastSAM
weights give no realistic mask count (at its default confidence they give none, so its time
is the network plus an empty post-processing).
Writes benchmarks/out/keyframe_vl.json and prints a table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shared.codec import encode  # noqa: E402
from shared.config import CodecConfig  # noqa: E402
from shared.datasets.ground_truth import StaticGroundTruth  # noqa: E402
from shared.messages import KeyframeMasks, MaskFeatures  # noqa: E402
from shared.perception import KeyframeImage, Masks  # noqa: E402
from shared.perception.encoders.config import VLEncoderBackend, vl_config  # noqa: E402
from shared.perception.segmenters.config import SegmenterBackend, segmenter_config  # noqa: E402

log = logging.getLogger("bench.keyframe_vl")
OUT = Path(__file__).resolve().parent / "out"


@dataclasses.dataclass(frozen=True)
class Keyframe(KeyframeImage):
    """A resized keyframe with its resized ground truth, which the simulated backends get
    through a :class:`StaticGroundTruth` (no message or KeyframeImage carries it)."""

    instances: np.ndarray | None = None


def ground_truth(imgs: list[Keyframe]) -> StaticGroundTruth:
    return StaticGroundTruth({img.frame_index: img.instances for img in imgs})


def frames(seq: Path, n: int, size: tuple[int, int]) -> list[Keyframe]:
    from PIL import Image

    from shared.datasets import open_sequence

    reader = open_sequence(seq)
    w, h = size
    out = []
    for i in np.linspace(0, len(reader) - 1, n).astype(int):
        f = reader.frame(int(i))
        rgb = np.asarray(Image.fromarray(f.rgb).resize((w, h), Image.BILINEAR))
        inst = np.asarray(Image.fromarray(reader.instances(int(i)).astype(np.int32)).resize((w, h), Image.NEAREST)).astype(np.int32)
        depth = np.asarray(Image.fromarray(f.depth_m()).resize((w, h), Image.NEAREST)).astype(np.float32)
        out.append(Keyframe(frame_index=int(i), rgb=rgb, depth_m=depth, intrinsics=f.intrinsics.scaled(w, h), instances=inst))
    return out


def gt_masks(img: Keyframe, min_px: int) -> Masks:
    ids, counts = np.unique(img.instances[img.instances >= 0], return_counts=True)
    ids = ids[counts >= min_px]
    m = img.instances[None] == ids[:, None, None]
    boxes = np.array([[np.nonzero(k)[1].min(), np.nonzero(k)[0].min(), np.nonzero(k)[1].max() + 1, np.nonzero(k)[0].max() + 1] for k in m], np.float32).reshape(-1, 4)
    return Masks(m, boxes, np.ones(len(ids), np.float32))


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        import torch

        torch.cuda.synchronize()


def run_case(name: str, seg_cfg: SegmenterBackend, vl_cfg: VLEncoderBackend, imgs: list[Keyframe], device: str, fp16: bool, warmup: int) -> dict:
    from shared.perception.encoders import make_vl_encoder
    from shared.perception.segmenters import make_segmenter
    from shared.perception.segmenters.simulated import SimulatedSegmenter

    truth = ground_truth(imgs)
    seg = SimulatedSegmenter(seg_cfg, truth) if seg_cfg.backend == "simulated" else make_segmenter(seg_cfg, device=device, fp16=fp16)
    enc = make_vl_encoder(vl_cfg, device=device, fp16=fp16, ground_truth=truth)
    t_seg, t_clip, n_masks, n_crops, mask_bits, mask_rle, feat_bytes = [], [], [], [], [], [], []
    for k, img in enumerate(imgs):
        _sync(device)
        t0 = time.perf_counter()
        masks = seg.segment(img)
        _sync(device)
        t1 = time.perf_counter()
        crops = gt_masks(img, 100)
        feats = enc.encode_crops(img, crops)
        _sync(device)
        t2 = time.perf_counter()
        if k >= warmup:
            t_seg.append(1000 * (t1 - t0))
            t_clip.append(1000 * (t2 - t1))
        n_masks.append(len(masks))
        n_crops.append(len(crops))
        # Sized on the ground-truth masks: random FastSAM weights give no realistic mask count.
        msg = KeyframeMasks(frame_index=img.frame_index, masks=crops.masks, boxes=crops.boxes, scores=crops.scores)
        mask_bits.append(len(encode(msg, robot_id="r", seq=0, stamp=0.0, cfg=CodecConfig(masks="bits"))))
        mask_rle.append(len(encode(msg, robot_id="r", seq=0, stamp=0.0, cfg=CodecConfig(masks="rle"))))
        fmsg = MaskFeatures(frame_index=img.frame_index, features=np.asarray(feats, np.float32), model=enc.name)
        feat_bytes.append(len(encode(fmsg, robot_id="r", seq=0, stamp=0.0)))
    seg_ms, clip_ms = statistics.median(t_seg), statistics.median(t_clip)
    h, w = imgs[0].rgb.shape[:2]
    return {
        "case": name, "segmenter": seg_cfg.backend, "vl": f"{vl_cfg.backend}:{vl_cfg.model}" if vl_cfg.backend != "simulated" else "simulated",
        "resolution": f"{w}x{h}", "device": device, "fp16": fp16, "keyframes": len(t_seg),
        "seg_ms": round(seg_ms, 1), "clip_ms": round(clip_ms, 1), "total_ms": round(seg_ms + clip_ms, 1),
        "masks_per_keyframe": round(float(np.mean(n_masks)), 1), "crops_per_keyframe": round(float(np.mean(n_crops)), 1),
        "masks_msg_kb_bits": round(float(np.mean(mask_bits)) / 1024, 1), "masks_msg_kb_rle": round(float(np.mean(mask_rle)) / 1024, 1),
        "features_msg_kb": round(float(np.mean(feat_bytes)) / 1024, 1),
    }  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="weightless backends and small learned models only")
    ap.add_argument("--paper", action="store_true", help="FastSAM-x + ViT-H-14 at 1200x680 (use a GPU)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--keyframes", type=int, default=None)
    ap.add_argument("--seq", type=Path, help="a synthetic sequence (default: generate small seed 0)")
    ap.add_argument("--out", type=Path, default=OUT / "keyframe_vl.json")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    from services.models.random_weights import save_random_fastsam, save_random_openclip

    tmp = Path(tempfile.mkdtemp(prefix="bench_kvl_"))
    seq = args.seq
    if seq is None:
        from shared.synth import run_synth

        seq = tmp / "small"
        run_synth("small", 0, seq)
    gt = str(seq / "gt")
    fp16 = args.device.startswith("cuda")
    n = args.keyframes or (3 if args.quick else 6)
    warm = 1
    cases = []
    if not args.paper:
        small = frames(seq, n + warm, (320, 240))
        cases.append(("classical", segmenter_config(backend="classical"), vl_config(backend="simulated", ground_truth=gt), small))
        cases.append(("simulated", segmenter_config(backend="simulated"), vl_config(backend="simulated", ground_truth=gt), small))
        vga = frames(seq, n + warm, (640, 480))
        fastsam = save_random_fastsam(tmp / "FastSAM-s.pt", "s")
        b32 = save_random_openclip(tmp / "vit_b32.bin", "ViT-B-32")
        cases.append(("fastsam-s + ViT-B-32 @640x480", segmenter_config(backend="fastsam", weights=str(fastsam), imgsz=640), vl_config(backend="openclip", model="ViT-B-32", weights=str(b32)), vga))
        if not args.quick:
            fx = save_random_fastsam(tmp / "FastSAM-x.pt", "x")
            cases.append(("fastsam-x + ViT-B-32 @640x480", segmenter_config(backend="fastsam", weights=str(fx), imgsz=1024), vl_config(backend="openclip", model="ViT-B-32", weights=str(b32)), vga))
    else:
        replica = frames(seq, n + warm, (1200, 680))
        fx = save_random_fastsam(tmp / "FastSAM-x.pt", "x")
        h14 = save_random_openclip(tmp / "vit_h14.bin", "ViT-H-14")
        cases.append(("paper: fastsam-x + ViT-H-14 @1200x680", segmenter_config(backend="fastsam", weights=str(fx), imgsz=1024), vl_config(backend="openclip", model="ViT-H-14", weights=str(h14)), replica))
    rows = []
    for name, seg_cfg, vl_cfg, imgs in cases:
        log.info("case %s", name)
        rows.append(run_case(name, seg_cfg, vl_cfg, imgs, args.device, fp16, warm))
    gpu = None
    if args.device.startswith("cuda"):
        import torch

        gpu = {"name": torch.cuda.get_device_name(0), "peak_mb": round(torch.cuda.max_memory_allocated() / 2**20, 1)}
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=Path(__file__).parent).stdout.strip() or None
    report = {"rows": rows, "gpu": gpu, "machine": {"platform": platform.platform(), "python": platform.python_version(), "cpus": __import__("os").cpu_count()}, "commit": commit, "time": time.strftime("%Y-%m-%dT%H:%M:%S")}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2))
    cols = ["case", "resolution", "seg_ms", "clip_ms", "total_ms", "masks_per_keyframe", "crops_per_keyframe", "masks_msg_kb_bits", "masks_msg_kb_rle", "features_msg_kb"]
    print(" | ".join(cols))
    for r in rows:
        print(" | ".join(str(r[c]) for c in cols))
    if gpu:
        print(f"GPU {gpu['name']}: peak {gpu['peak_mb']} MB")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
