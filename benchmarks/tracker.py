"""Benchmark: the tracker's propagation mode against the per-frame baseline (paper IV, tracker
ablation: 15.0 Hz against 6.0 Hz, 2.5x, on an A100).

Run from the repository root::

    python benchmarks/tracker.py --quick    # about 2 minutes on a 2-core CPU
    python benchmarks/tracker.py            # about 5 minutes

Real architectures on random weights, nothing downloaded: DINOv3 ViT-S+/16 built by timm
(``vit_small_plus_patch16_dinov3``, the model the ``timm`` loader builds) and FastSAM-x's form,
a YOLOv8x-seg with one class built by ultralytics from its bundled yaml and saved as a
checkpoint the ``fastsam`` segmenter loads. Random weights give the real cost of every layer;
the number of masks the random head returns is capped (``--max-masks``, about what FastSAM-x
gives on an indoor view) so the association cost is realistic too.

Two parts:

1. **Components at the paper's resolution** (a 720 x 1280 frame): DINOv3 forward at short side
   720 (45 x 80 patches), eq. 1 propagation on those features from 8 references (the keyframe
   and 7 recent frames) over ``--slots`` track slots, the upsampling + argmax to 720 x 1280
   (of a keyframe-like distribution: ``slots`` regions, mixed at their borders),
   FastSAM-x at imgsz 1024, and one keyframe correction (eqs. 2-3) on the FastSAM masks.
   "Propagation" is eq. 1 plus the upsampling: everything propagation adds to a frame once
   its features exist. From these, frames/s of the two modes as the paper runs them:
   propagation = 1 / (DINOv3 + propagation + (FastSAM + correction) / K_f), per-frame =
   1 / (DINOv3 + FastSAM + correction).
2. **End to end**: ``TrackerCore`` in ``propagation`` and ``per_frame`` mode with the segmenter
   called for every keyframe request, over the frames of the synthetic ``small`` preset
   (320 x 240; generated once into benchmarks/out), timed per frame after one warm-up frame.
   On a CPU the paper's resolutions would take minutes per mode, so this part runs DINOv3 at
   short side ``--e2e-short`` and FastSAM at ``--e2e-imgsz`` (both printed); CLIP and fusion
   are left out of both modes (CLIP runs asynchronously in the paper and fusion is the same for
   both).

Targets: propagation under 20% of the DINOv3 forward at 720p, and a propagation / per-frame
frame-rate ratio of at least the paper's 2.5x. Results go to benchmarks/out/tracker.json and a
table on stdout.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from services.keyframe_vl.core import keyframe_image  # noqa: E402
from services.models.random_weights import save_random_fastsam  # noqa: E402
from services.tracker.core import TrackerCore  # noqa: E402
from services.tracker.propagation import propagate_labels, upsample_labels  # noqa: E402
from shared.config.tracker import PropagationConfig, TrackerConfig  # noqa: E402
from shared.logs import setup_logging  # noqa: E402
from shared.perception import KeyframeImage, Segmenter  # noqa: E402
from shared.perception.features.dinov3 import Dinov3Features, PatchTokens  # noqa: E402
from shared.perception.segmenters import make_segmenter  # noqa: E402
from shared.perception.segmenters.config import segmenter_config  # noqa: E402

log = logging.getLogger("bench.tracker")

DEFAULT_OUT = ROOT / "benchmarks" / "out" / "tracker.json"
PAPER = {"propagation_hz": 15.0, "per_frame_hz": 6.0, "ratio": 2.5, "gpu": "NVIDIA A100"}
PROPAGATION_SHARE_TARGET = 0.20
KEYFRAME_INTERVAL = 24
HEIGHT, WIDTH = 720, 1280


# ---------------------------------------------------------------------------------------------
# models


def dinov3_vits16plus(short_side: int, device: str = "cpu") -> Dinov3Features:
    """ViT-S+/16 (29M parameters) with timm's random init, wrapped like the timm loader does."""
    import timm

    torch.manual_seed(0)
    model = timm.create_model("vit_small_plus_patch16_dinov3", pretrained=False, num_classes=0).eval()
    tokens = PatchTokens(model, "timm", model.num_prefix_tokens, model.embed_dim, model.patch_embed.patch_size[0])
    return Dinov3Features(tokens, short_side, device)


def fastsam_segmenter(weights: Path, imgsz: int, max_masks: int) -> Segmenter:
    """The ``fastsam`` backend as keyframe_vl builds it, on the CPU in float32."""
    cfg = segmenter_config(backend="fastsam", weights=str(weights), imgsz=imgsz, conf=0.5, max_masks=max_masks)
    return make_segmenter(cfg, device="cpu", fp16=False)


# ---------------------------------------------------------------------------------------------
# timing


def timed(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> tuple[float, Any]:
    """Median seconds of ``fn`` over ``repeats`` calls after ``warmup`` untimed ones."""
    out = None
    for _ in range(warmup):
        out = fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def smooth_image(height: int, width: int, seed: int = 0) -> np.ndarray:
    """A frame with regions and edges (blurred noise, quantised), not white noise."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    small = rng.random((height // 40 + 2, width // 40 + 2, 3))
    big = ndimage.zoom(small, (40, 40, 1), order=1)[:height, :width]
    return (np.floor(big * 6) / 6 * 255).astype(np.uint8)


def region_labels(h: int, w: int, slots: int, seed: int) -> torch.Tensor:
    """Track distributions shaped like a keyframe's: ``slots`` regions (nearest of random
    seeds), one-hot inside and mixed over the patch at their borders, as ``masks_to_soft``
    gives them. The upsampling cost depends on how much of the frame is border."""
    rng = np.random.default_rng(seed)
    centres = rng.random((slots, 2)) * (h, w)
    yy, xx = np.mgrid[0:h, 0:w]
    owner = ((yy[..., None] - centres[:, 0]) ** 2 + (xx[..., None] - centres[:, 1]) ** 2).argmin(-1)
    one_hot = np.eye(slots, dtype=np.float32)[owner]
    padded = np.pad(one_hot, ((1, 1), (1, 1), (0, 0)), mode="edge")
    mixed = sum(padded[dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3)) / 9.0
    return torch.from_numpy(np.ascontiguousarray(mixed, np.float32))


def components(args: argparse.Namespace, fastsam_pt: Path) -> dict[str, Any]:
    """Part 1: each piece once at the paper's resolution."""
    repeats = 1 if args.quick else 2
    rgb = smooth_image(HEIGHT, WIDTH)
    dino = dinov3_vits16plus(720)
    t_dino, feats = timed(lambda: dino(rgb), repeats)
    h, w, dim = feats.shape
    log.info("DINOv3 ViT-S+ at %dx%d -> %dx%d patches: %.2f s", HEIGHT, WIDTH, h, w, t_dino)

    gen = torch.Generator().manual_seed(0)
    cfg = PropagationConfig()
    refs = []
    for r in range(1 + cfg.context_frames):
        noisy = torch.nn.functional.normalize(feats + 0.1 * torch.randn(feats.shape, generator=gen), dim=-1)
        refs.append((noisy, region_labels(h, w, args.slots, seed=r)))

    def prop() -> torch.Tensor:
        return propagate_labels(feats, refs, window_radius=cfg.window_radius, topk=cfg.topk, temperature=cfg.temperature)

    t_prop, _ = timed(prop, repeats + 1)
    # Random weights make the propagated distributions incoherent from patch to patch, which
    # real features do not: the upsampling, whose cost grows with the share of label borders,
    # is timed on a keyframe-like distribution instead.
    t_up, _ = timed(lambda: upsample_labels(refs[0][1], HEIGHT, WIDTH), repeats + 1)
    log.info("propagation %.3f s + upsampling %.3f s", t_prop, t_up)

    segmenter = fastsam_segmenter(fastsam_pt, 1024, args.max_masks)
    image = KeyframeImage(frame_index=0, rgb=rgb)
    t_seg, masks = timed(lambda: segmenter.segment(image), repeats)
    log.info("FastSAM-x at imgsz 1024: %.2f s, %d masks", t_seg, len(masks))

    # One keyframe correction (eqs. 2-3) with as many active tracks as masks.
    from services.tracker.association import associate_iou, label_mask_iou, mask_prototypes

    feats_np = feats.numpy()

    # The active tracks' predicted masks: the detections moved by 8 pixels, as one slot image.
    predicted = np.zeros(masks.masks.shape[1:], np.int64)
    for j in np.argsort(-masks.masks.reshape(len(masks), -1).sum(1)):
        predicted[np.roll(masks.masks[j], 8, axis=1)] = j + 1

    def correct() -> None:
        det = mask_prototypes(feats_np, masks.masks)
        iou = label_mask_iou(predicted, len(masks), masks.masks)
        associate_iou(iou, det, det, TrackerConfig().association)

    t_assoc, _ = timed(correct, repeats)
    log.info("keyframe correction on %d masks: %.3f s", len(masks), t_assoc)

    prop_total = t_prop + t_up
    k = KEYFRAME_INTERVAL
    hz_prop = 1.0 / (t_dino + prop_total + (t_seg + t_assoc) / k)
    hz_pf = 1.0 / (t_dino + t_seg + t_assoc)
    # With propagation free, the ratio is set by what FastSAM costs against DINOv3 alone.
    bound = (t_dino + t_seg + t_assoc) / (t_dino + (t_seg + t_assoc) / k)
    return {
        "frame": [HEIGHT, WIDTH],
        "grid": [h, w],
        "feature_dim": dim,
        "references": len(refs),
        "slots": args.slots,
        "masks": len(masks),
        "dinov3_s": t_dino,
        "propagation_s": t_prop,
        "upsample_s": t_up,
        "propagation_total_s": prop_total,
        "propagation_share_of_dinov3": prop_total / t_dino,
        "fastsam_s": t_seg,
        "correction_s": t_assoc,
        "keyframe_interval": k,
        "model_hz": {"propagation": hz_prop, "per_frame": hz_pf, "ratio": hz_prop / hz_pf, "ratio_if_propagation_were_free": bound},
    }


def synth_small(n: int):
    from shared.datasets import open_sequence
    from shared.synth import run_synth

    folder = ROOT / "benchmarks" / "out" / "tracker_synth_small"
    if not (folder / "traj.txt").is_file():
        log.info("generating the synth small preset into %s", folder)
        run_synth("small", 0, folder, overwrite=True)
    reader = open_sequence(folder, "replica")
    return [reader.frame(i) for i in range(min(n, len(reader)))]


def end_to_end(args: argparse.Namespace, fastsam_pt: Path) -> dict[str, Any]:
    """Part 2: TrackerCore in both modes, segmenter on every keyframe request."""
    frames = synth_small(args.frames + 1)
    dino = dinov3_vits16plus(args.e2e_short)
    segmenter = fastsam_segmenter(fastsam_pt, args.e2e_imgsz, args.max_masks)
    out: dict[str, Any] = {
        "frames": len(frames) - 1,
        "frame_size": list(frames[0].rgb.shape[:2]),
        "dinov3_short_side": args.e2e_short,
        "fastsam_imgsz": args.e2e_imgsz,
        "keyframe_interval": KEYFRAME_INTERVAL,
    }
    for mode in ("propagation", "per_frame"):
        cfg = TrackerConfig(mode=mode, keyframe_interval=KEYFRAME_INTERVAL, device="cpu")
        core = TrackerCore(cfg, dino)
        times, seg_times, n_key = [], [], 0
        for i, fr in enumerate(frames):
            t0 = time.perf_counter()
            req = core.begin_frame(fr)
            if req is not None:
                t1 = time.perf_counter()
                masks = segmenter.segment(keyframe_image(req))
                seg_times.append(time.perf_counter() - t1)
                core.apply_masks(fr.frame_index, masks)
                n_key += 1
            tracked = core.end_frame()
            dt_ = time.perf_counter() - t0
            if i > 0:  # the first frame pays for lazy initialisation in both modes
                times.append(dt_)
            assert tracked.track_ids.shape == fr.rgb.shape[:2]
        total = sum(times)
        out[mode] = {
            "seconds": total,
            "hz": len(times) / total,
            "ms_per_frame": 1e3 * total / len(times),
            "keyframes": n_key,
            "segmenter_ms_mean": 1e3 * statistics.mean(seg_times) if seg_times else None,
            "tracks": core.book.next_id,
        }
        log.info("%s: %.2f frames/s over %d frames", mode, out[mode]["hz"], len(times))
    out["ratio"] = out["propagation"]["hz"] / out["per_frame"]["hz"]
    return out


def print_table(res: dict[str, Any]) -> None:
    c, e = res["components"], res["end_to_end"]
    print(f"\nTracker benchmark on {res['machine']['cpu']} ({res['machine']['torch_threads']} torch threads), CPU")
    print(f"\n1. Components at {c['frame'][0]}x{c['frame'][1]} ({c['grid'][0]}x{c['grid'][1]} patches, {c['references']} references, {c['slots']} slots)")
    print("| step | time per call | note |")
    print("|---|---|---|")
    print(f"| DINOv3 ViT-S+ forward (short side 720) | {c['dinov3_s'] * 1e3:.0f} ms | every frame, both modes |")
    print(f"| eq. 1 propagation | {c['propagation_s'] * 1e3:.0f} ms | every frame, propagation mode |")
    print(f"| upsampling + argmax to {c['frame'][0]}x{c['frame'][1]} | {c['upsample_s'] * 1e3:.0f} ms | every frame, propagation mode |")
    print(f"| propagation total / DINOv3 | {100 * c['propagation_share_of_dinov3']:.1f}% | target < {100 * PROPAGATION_SHARE_TARGET:.0f}% |")
    print(f"| FastSAM-x (imgsz 1024) | {c['fastsam_s'] * 1e3:.0f} ms | every K_f = {c['keyframe_interval']} frames / every frame |")
    print(f"| keyframe correction ({c['masks']} masks) | {c['correction_s'] * 1e3:.0f} ms | same |")
    mh = c["model_hz"]
    print(f"| => propagation mode | {mh['propagation']:.3f} frames/s | |")
    print(f"| => per-frame mode | {mh['per_frame']:.3f} frames/s | |")
    print(f"| => ratio | {mh['ratio']:.2f}x | paper {PAPER['ratio']}x ({PAPER['propagation_hz']} vs {PAPER['per_frame_hz']} Hz, {PAPER['gpu']}) |")
    print(
        f"| => ratio with propagation free | {mh['ratio_if_propagation_were_free']:.2f}x | the ceiling FastSAM / DINOv3 "
        f"= {c['fastsam_s'] / c['dinov3_s']:.2f} sets on this machine |"
    )
    print(
        f"\n2. End to end: TrackerCore + segmenter, synth small frames {e['frame_size'][0]}x{e['frame_size'][1]}, "
        f"{e['frames']} timed frames, DINOv3 short side {e['dinov3_short_side']}, FastSAM-x imgsz {e['fastsam_imgsz']}, K_f {e['keyframe_interval']}"
    )
    print("| mode | frames/s | ms per frame | keyframes | segmenter ms |")
    print("|---|---|---|---|---|")
    for mode in ("propagation", "per_frame"):
        m = e[mode]
        print(f"| {mode} | {m['hz']:.2f} | {m['ms_per_frame']:.0f} | {m['keyframes']} | {m['segmenter_ms_mean']:.0f} |")
    print(f"| ratio | {e['ratio']:.2f}x | | | |")
    t = res["targets"]
    word = {True: "pass", False: "FAIL"}
    print(
        f"\ntargets: propagation < 20% of DINOv3 at 720p: {word[t['propagation_share_below_20pct']]}; "
        f"ratio >= 2.5x end to end: {word[t['end_to_end_ratio_at_least_paper']]}, "
        f"from the 720p components: {word[t['model_ratio_at_least_paper']]}"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="one repeat per component, 24 end-to-end frames")
    ap.add_argument("--frames", type=int, default=None, help="end-to-end frames per mode (default 48, quick 24)")
    ap.add_argument("--slots", type=int, default=40, help="track slots for the propagation timing")
    ap.add_argument("--max-masks", type=int, default=48, help="cap on FastSAM masks per keyframe")
    ap.add_argument("--e2e-short", type=int, default=240, help="DINOv3 short side in the end-to-end part")
    ap.add_argument("--e2e-imgsz", type=int, default=320, help="FastSAM imgsz in the end-to-end part")
    ap.add_argument(
        "--threads", type=int, default=1,
        help="torch threads for everything timed (default 1: on a shared 2-core machine two "
        "threads gave a 10x run-to-run spread on the same call; 0 keeps torch's default)",
    )
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args(argv)
    if args.frames is None:
        args.frames = 24 if args.quick else 48
    setup_logging(1 if args.verbose else 0)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    fastsam_pt = ROOT / "benchmarks" / "out" / "fastsam-x-random.pt"
    if not fastsam_pt.is_file():  # deterministic (seeded): built once, then reused
        save_random_fastsam(fastsam_pt, "x", alive=True)
    res: dict[str, Any] = {
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "quick": args.quick,
        "paper": PAPER,
        "machine": {
            "platform": platform.platform(),
            "cpu": platform.processor() or platform.machine(),
            "cores": os.cpu_count(),
            "torch": torch.__version__,
            "torch_threads": torch.get_num_threads(),
        },
        "weights": "random (timm vit_small_plus_patch16_dinov3; ultralytics yolov8x-seg.yaml, nc=1)",
    }
    res["components"] = components(args, fastsam_pt)
    res["end_to_end"] = end_to_end(args, fastsam_pt)
    res["targets"] = {
        "propagation_share_below_20pct": res["components"]["propagation_share_of_dinov3"] < PROPAGATION_SHARE_TARGET,
        "model_ratio_at_least_paper": res["components"]["model_hz"]["ratio"] >= PAPER["ratio"],
        "end_to_end_ratio_at_least_paper": res["end_to_end"]["ratio"] >= PAPER["ratio"],
    }
    res["seconds"] = time.perf_counter() - t0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=2))
    print_table(res)
    print(f"wrote {args.out} ({res['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
