"""DINOv3 ViT-S+/16 as an ONNX graph run by onnxruntime, and the export that writes it.

The graph maps ImageNet-normalised pixels ``(1, 3, 16*h, 16*w)`` float32 to the final-norm
patch tokens ``(1, h*w, 384)`` (CLS and registers already dropped); H and W are dynamic,
multiples of the patch size. Resizing, normalisation and the per-patch L2 norm stay in Python,
shared with the torch backend, so both see identical inputs.

Export from local weights (any of the three loaders)::

    python -m shared.perception.features.onnx_backend --loader transformers \\
        --weights weights/dinov3_vits16plus --out weights/dinov3_vits16plus.onnx
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
import torch

from shared.perception.features.base import PatchGridMixin
from shared.perception.features.dinov3 import Loader, load_patch_tokens, preprocess, tokens_to_grid

log = logging.getLogger(__name__)

INPUT_NAME = "pixels"
OUTPUT_NAME = "patch_tokens"
META_PATCH = "trackgraph.patch_size"
META_DIM = "trackgraph.dim"
ONNX_FILE = "model.onnx"


def export_onnx(
    loader: Loader,
    weights: str | Path,
    out_path: str | Path,
    *,
    opset: int = 18,
    example_hw: tuple[int, int] = (224, 320),
    max_side: int = 4096,
) -> Path:
    """Exports the locally stored ViT-S+/16 to one self-contained ``.onnx`` file.

    ``example_hw`` only traces the graph: height and width stay symbolic (multiples of the
    patch size, up to ``max_side`` pixels). Returns the written path.
    """
    model = load_patch_tokens(loader, weights).eval()
    patch = model.patch_size
    if example_hw[0] % patch or example_hw[1] % patch:
        raise ValueError(f"example_hw {example_hw} must be multiples of the patch size {patch}")
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    dim_h = torch.export.Dim("grid_h", min=1, max=max_side // patch)
    dim_w = torch.export.Dim("grid_w", min=1, max=max_side // patch)
    example = torch.zeros(1, 3, *example_hw)
    with torch.no_grad():
        program = torch.onnx.export(
            model,
            (example,),
            None,
            dynamo=True,
            input_names=[INPUT_NAME],
            output_names=[OUTPUT_NAME],
            opset_version=opset,
            dynamic_shapes={"pixels": {2: patch * dim_h, 3: patch * dim_w}},
        )
    # The runtime backend reads these instead of trusting the config to match the file.
    program.model.metadata_props[META_PATCH] = str(patch)
    program.model.metadata_props[META_DIM] = str(model.dim)
    program.save(str(out), external_data=False)
    log.info("DINOv3 exported to %s (%.1f MB)", out, out.stat().st_size / 1e6)
    return out


def resolve_onnx_path(weights: str | Path) -> Path:
    path = Path(weights).expanduser()
    if path.is_dir():
        path = path / ONNX_FILE
    if not path.is_file():
        raise FileNotFoundError(
            f"DINOv3 ONNX model not found at {path}. Create it from local weights with "
            f"`python -m shared.perception.features.onnx_backend --loader transformers "
            f"--weights <ViT-S+/16 folder> --out {path}` (shared.perception.features.export_dinov3_onnx); "
            f"weights are never downloaded."
        )
    return path


class Dinov3OnnxFeatures(PatchGridMixin):
    """DINOv3 patch features from an exported graph (CUDA provider when asked and present).

    The graph is float32; ``fp16`` is accepted for a uniform factory but has no effect here.
    """

    name = "dinov3_onnx"

    def __init__(self, path: str | Path, short_side: int, patch_size: int, device: str = "cpu"):
        import onnxruntime as ort

        from shared.devices import onnx_providers

        self.path = resolve_onnx_path(path)
        self.short_side = short_side
        self.device = torch.device(device)
        providers = onnx_providers(device, "tracker.device")
        options = ort.SessionOptions()
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        self.session = ort.InferenceSession(str(self.path), options, providers=providers)
        meta = self.session.get_modelmeta().custom_metadata_map
        self.patch_size = int(meta.get(META_PATCH, patch_size))
        out_shape = self.session.get_outputs()[0].shape
        self.dim = int(meta.get(META_DIM, out_shape[-1]))
        self.appearance_dims = self.dim
        if self.patch_size != patch_size:
            raise ValueError(f"{self.path} was exported with patch size {self.patch_size}, config says {patch_size}")
        self.input_name = self.session.get_inputs()[0].name
        log.info("DINOv3 ONNX loaded from %s with %s", self.path, self.session.get_providers()[0])

    def features(self, rgb: np.ndarray, depth_m: np.ndarray | None, size: tuple[int, int]) -> torch.Tensor:
        with torch.no_grad():
            pixels = preprocess(rgb, size, "cpu").numpy()
        tokens = self.session.run(None, {self.input_name: pixels})[0]
        grid = tokens_to_grid(torch.from_numpy(tokens[0]), size[0] // self.patch_size, size[1] // self.patch_size)
        return grid.to(self.device)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Export local DINOv3 ViT-S+/16 weights to ONNX.")
    parser.add_argument("--loader", choices=["transformers", "timm", "hub"], default="transformers")
    parser.add_argument("--weights", required=True, help="local weights (folder or file, per loader)")
    parser.add_argument("--out", required=True, help="output .onnx file")
    parser.add_argument("--opset", type=int, default=18)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    print(export_onnx(args.loader, args.weights, args.out, opset=args.opset))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
