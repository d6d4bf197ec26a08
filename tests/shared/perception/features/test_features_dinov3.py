"""DINOv3 ViT-S+/16 backends with random weights, saved in all three layouts and loaded
through the same code path real weights take (loading, preprocessing, shapes, ONNX parity;
not accuracy)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
timm = pytest.importorskip("timm")
transformers = pytest.importorskip("transformers")

from shared.perception.features import export_dinov3_onnx, make_dense_features  # noqa: E402
from shared.perception.features.config import DenseFeaturesBackend, dense_features_config  # noqa: E402

SHORT = 64  # tiny inputs keep the 12-layer ViT fast on CPU
DEPTH = 12


def vits16plus_hf_config():
    """The transformers config of facebook/dinov3-vits16plus-pretrain-lvd1689m."""
    return transformers.DINOv3ViTConfig(
        patch_size=16,
        hidden_size=384,
        intermediate_size=1536,  # ffn_ratio 6 -> SwiGLU hidden int(2304 * 2 / 3), aligned to 8
        num_hidden_layers=12,
        num_attention_heads=6,
        hidden_act="silu",
        use_gated_mlp=True,
        num_register_tokens=4,
        layerscale_value=1.0,
        layer_norm_eps=1e-5,
        rope_theta=100.0,
        query_bias=True,
        key_bias=False,
        value_bias=True,
        proj_bias=True,
        mlp_bias=True,
    )


def timm_to_hub(sd: dict) -> dict:
    """timm keys -> the official facebookresearch/dinov3 checkpoint keys (inverse of the
    mapping the hub loader relies on)."""
    out = {
        "cls_token": sd["cls_token"],
        "storage_tokens": sd["reg_token"],
        "mask_token": torch.zeros(1, 384),
        "rope_embed.periods": torch.arange(16, dtype=torch.float32),
        "patch_embed.proj.weight": sd["patch_embed.proj.weight"],
        "patch_embed.proj.bias": sd["patch_embed.proj.bias"],
        "norm.weight": sd["norm.weight"],
        "norm.bias": sd["norm.bias"],
    }
    for i in range(DEPTH):
        b = f"blocks.{i}."
        for n in ("norm1", "norm2"):
            out[b + n + ".weight"], out[b + n + ".bias"] = sd[b + n + ".weight"], sd[b + n + ".bias"]
        out[b + "attn.qkv.weight"] = sd[b + "attn.qkv.weight"]
        zeros = torch.zeros(384)
        out[b + "attn.qkv.bias"] = torch.cat([sd[b + "attn.q_bias"], zeros, sd[b + "attn.v_bias"]])
        out[b + "attn.qkv.bias_mask"] = torch.cat([torch.ones(384), zeros, torch.ones(384)])
        out[b + "attn.proj.weight"], out[b + "attn.proj.bias"] = sd[b + "attn.proj.weight"], sd[b + "attn.proj.bias"]
        out[b + "ls1.gamma"], out[b + "ls2.gamma"] = sd[b + "gamma_1"], sd[b + "gamma_2"]
        for src, dst in (("fc1_g", "w1"), ("fc1_x", "w2"), ("fc2", "w3")):
            out[b + f"mlp.{dst}.weight"] = sd[b + f"mlp.{src}.weight"]
            out[b + f"mlp.{dst}.bias"] = sd[b + f"mlp.{src}.bias"]
    return out


def timm_to_hf(sd: dict) -> dict:
    out = {
        "embeddings.cls_token": sd["cls_token"],
        "embeddings.register_tokens": sd["reg_token"],
        "embeddings.mask_token": torch.zeros(1, 1, 384),
        "embeddings.patch_embeddings.weight": sd["patch_embed.proj.weight"],
        "embeddings.patch_embeddings.bias": sd["patch_embed.proj.bias"],
        "norm.weight": sd["norm.weight"],
        "norm.bias": sd["norm.bias"],
    }
    for i in range(DEPTH):
        b, layer = f"blocks.{i}.", f"model.layer.{i}."
        q, k, v = sd[b + "attn.qkv.weight"].chunk(3, 0)
        out[layer + "attention.q_proj.weight"], out[layer + "attention.k_proj.weight"] = q, k
        out[layer + "attention.v_proj.weight"] = v
        out[layer + "attention.q_proj.bias"] = sd[b + "attn.q_bias"]
        out[layer + "attention.v_proj.bias"] = sd[b + "attn.v_bias"]
        out[layer + "attention.o_proj.weight"] = sd[b + "attn.proj.weight"]
        out[layer + "attention.o_proj.bias"] = sd[b + "attn.proj.bias"]
        out[layer + "layer_scale1.lambda1"], out[layer + "layer_scale2.lambda1"] = sd[b + "gamma_1"], sd[b + "gamma_2"]
        for n in ("norm1", "norm2"):
            out[layer + n + ".weight"], out[layer + n + ".bias"] = sd[b + n + ".weight"], sd[b + n + ".bias"]
        for src, dst in (("fc1_g", "gate_proj"), ("fc1_x", "up_proj"), ("fc2", "down_proj")):
            out[layer + f"mlp.{dst}.weight"] = sd[b + f"mlp.{src}.weight"]
            out[layer + f"mlp.{dst}.bias"] = sd[b + f"mlp.{src}.bias"]
    return out


def random_vits16plus_state() -> dict:
    """Random ViT-S+/16 weights in timm's layout (q/v biases included), drawn directly: a
    real init of 29M parameters costs seconds per model on a small CPU."""
    with torch.device("meta"):
        shapes = timm.create_model("vit_small_plus_patch16_dinov3_qkvb", pretrained=False).state_dict()
    gen = torch.Generator().manual_seed(0)
    sd = {}
    for key, meta in shapes.items():
        if "k_bias" in key:
            continue
        shape = tuple(meta.shape)
        noise = torch.randn(shape, generator=gen)
        if "gamma" in key:
            # Layer scale is 1e-5 at init, which would leave the blocks (and RoPE) untested.
            sd[key] = 0.5 + 0.2 * noise
        elif key.startswith("norm") or ".norm" in key:
            sd[key] = (1.0 + 0.1 * noise) if key.endswith("weight") else 0.05 * noise
        elif key.endswith(("bias", "q_bias", "v_bias")) or key in ("cls_token", "reg_token"):
            sd[key] = 0.05 * noise
        else:
            fan_in = int(np.prod(shape[1:]))
            sd[key] = noise / fan_in**0.5
    return sd


@pytest.fixture(scope="module")
def weights(tmp_path_factory) -> dict[str, Path]:
    """One random ViT-S+/16 saved as a transformers folder, a timm file and a hub .pth."""
    from safetensors.torch import save_file

    root = tmp_path_factory.mktemp("dinov3")
    sd = random_vits16plus_state()
    save_file(sd, str(root / "timm.safetensors"))
    torch.save(timm_to_hub(sd), root / "dinov3_vits16plus_pretrain_lvd1689m-test.pth")
    with torch.device("meta"):
        hf = transformers.DINOv3ViTModel(vits16plus_hf_config())
    missing, unexpected = hf.load_state_dict(timm_to_hf(sd), strict=False, assign=True)
    assert not missing and not unexpected
    hf.save_pretrained(root / "hf")
    return {
        "transformers": root / "hf",
        "timm": root / "timm.safetensors",
        "hub": root / "dinov3_vits16plus_pretrain_lvd1689m-test.pth",
        "state": sd,
    }


@pytest.fixture(scope="module")
def loaded(weights) -> dict:
    return {loader: make_dense_features(cfg_for(loader, weights[loader])) for loader in ("transformers", "timm", "hub")}


@pytest.fixture(scope="module")
def frame() -> np.ndarray:
    rng = np.random.default_rng(1)
    return rng.integers(0, 256, (48, 80, 3), dtype=np.uint8)


def cfg_for(loader: str, path: Path, backend: str = "dinov3") -> DenseFeaturesBackend:
    return dense_features_config(backend=backend, loader=loader, weights=str(path), short_side=SHORT)


def test_hf_config_is_vit_small_plus():
    """The real S+ hyperparameters: 29M parameters (paper IV-A), as timm's definition."""
    with torch.device("meta"):
        hf = transformers.DINOv3ViTModel(vits16plus_hf_config())
        tm = timm.create_model("vit_small_plus_patch16_dinov3", pretrained=False)
    n_hf = sum(p.numel() for p in hf.parameters())
    n_timm = sum(p.numel() for p in tm.parameters())
    assert abs(n_hf - 28.69e6) < 0.05e6
    assert abs(n_hf - n_timm) <= 384 * 26  # mask token and q/v biases
    assert tm.blocks[0].mlp.fc1_g.out_features == hf.config.intermediate_size == 1536
    assert tm.num_prefix_tokens == 1 + hf.config.num_register_tokens == 5


@pytest.mark.parametrize("loader", ["transformers", "timm", "hub"])
def test_loader_grid_and_norm(loaded, frame, loader):
    feats = loaded[loader]
    out = feats(frame)
    # 48x80 at short side 64: 64x107 -> 64x112, a 4x7 grid of 384-d unit features.
    assert tuple(out.shape) == (4, 7, 384) == (*feats.grid_shape(48, 80), feats.dim)
    assert feats.appearance_dims == feats.dim  # DINOv3 patch features describe appearance whole
    assert out.dtype == torch.float32 and feats.patch_size == 16 and feats.name == "dinov3"
    assert torch.allclose(out.norm(dim=-1), torch.ones(4, 7), atol=1e-5)


def test_three_loaders_give_the_same_features(loaded, frame):
    """Same weights, three layouts: the key mappings and RoPE conventions agree."""
    outs = {loader: feats(frame) for loader, feats in loaded.items()}
    assert torch.allclose(outs["transformers"], outs["timm"], atol=1e-4)
    assert torch.allclose(outs["hub"], outs["timm"], atol=1e-4)
    # Not a degenerate map: patches differ from each other.
    flat = outs["timm"].reshape(-1, 384)
    assert (flat @ flat.T).min() < 0.99


def test_patch_tokens_exclude_cls_and_registers(loaded, frame):
    from shared.perception.features.dinov3 import preprocess

    model = loaded["transformers"].model
    x = preprocess(frame, (64, 112))
    with torch.no_grad():
        full = model.backbone(pixel_values=x).last_hidden_state
        ours = model(x)
    assert full.shape[1] == 1 + 4 + 28 and ours.shape[1] == 28
    assert torch.equal(ours, full[:, 5:])


def test_plain_timm_layout_loads(weights, tmp_path, frame):
    """timm's released S+ file has no q/v biases: the loader picks the matching variant."""
    from safetensors.torch import save_file

    (tmp_path / "plain").mkdir()
    plain = {k: v for k, v in weights["state"].items() if not k.endswith(("q_bias", "v_bias"))}
    save_file(plain, str(tmp_path / "plain" / "model.safetensors"))
    out = make_dense_features(cfg_for("timm", tmp_path / "plain"))(frame)
    assert tuple(out.shape) == (4, 7, 384)


@pytest.mark.parametrize("loader", ["transformers", "timm", "hub"])
def test_missing_weights_name_the_path(tmp_path, loader):
    where = tmp_path / "nowhere"
    with pytest.raises(FileNotFoundError) as err:
        make_dense_features(cfg_for(loader, where))
    assert str(where) in str(err.value) and "never downloaded" in str(err.value)


def test_missing_onnx_names_the_path(tmp_path):
    with pytest.raises(FileNotFoundError, match="model.onnx"):
        make_dense_features(cfg_for("timm", tmp_path, backend="dinov3_onnx"))


def test_wrong_checkpoint_is_rejected(weights, tmp_path):
    from safetensors.torch import save_file

    # A ViT-S/16 (plain 4x MLP) where the S+ SwiGLU is expected.
    wrong = dict(weights["state"])
    wrong["blocks.0.mlp.fc1_g.weight"] = torch.zeros(1536 * 2 // 3, 384)
    save_file(wrong, str(tmp_path / "s.safetensors"))
    with pytest.raises(ValueError, match="not a DINOv3 ViT-S\\+/16"):
        make_dense_features(cfg_for("timm", tmp_path / "s.safetensors"))
    torch.save({"foo": torch.zeros(1)}, tmp_path / "dinov3_vits16plus_x.pth")
    with pytest.raises(ValueError, match="storage_tokens"):
        make_dense_features(cfg_for("hub", tmp_path / "dinov3_vits16plus_x.pth"))


@pytest.mark.slow
def test_onnx_export_matches_torch(weights, loaded, tmp_path):
    """Dynamic H, W: one export serves several input sizes; fp32 relative error < 1e-3."""
    path = export_dinov3_onnx(cfg_for("transformers", weights["transformers"]), tmp_path / "dinov3.onnx")
    torch_feats = loaded["transformers"]
    onnx_feats = make_dense_features(cfg_for("timm", path, backend="dinov3_onnx"))
    assert onnx_feats.name == "dinov3_onnx" and onnx_feats.dim == onnx_feats.appearance_dims == 384 and onnx_feats.patch_size == 16
    rng = np.random.default_rng(2)
    for shape in [(48, 80, 3), (80, 64, 3), (64, 64, 3)]:
        rgb = rng.integers(0, 256, shape, dtype=np.uint8)
        a, b = torch_feats(rgb), onnx_feats(rgb)
        assert a.shape == b.shape
        rel = (a - b).norm() / a.norm()
        assert rel < 1e-3, rel


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_fp16_on_cuda(weights, loaded, frame):
    a = loaded["timm"](frame)
    b = make_dense_features(cfg_for("timm", weights["timm"]), device="cuda", fp16=True)(frame)
    assert b.dtype == torch.float32 and b.device.type == "cuda"
    assert (a - b.cpu()).norm() / a.norm() < 2e-2
