"""Every model loader refuses weights that are not its model (issue 20, "Real models without
surprises"): DINOv3 in its three layouts, OpenCLIP and FastSAM, each given a file of another
model and checked to raise ValueError naming the file, the model and what does not fit,
where the libraries underneath would load random init in its place or fail later, obscurely.

All weights are built here, small and deterministic (zeros or seeded), in the official file
layouts; nothing is downloaded.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")


def needs_ultralytics():
    """ultralytics through the project's one import of it, which leaves ``PIL.Image.open`` as
    it was; skips the test where it is not installed."""
    if importlib.util.find_spec("ultralytics") is None:
        pytest.skip("needs ultralytics")
    from shared.perception.segmenters.fastsam import import_ultralytics

    return import_ultralytics()


@pytest.fixture
def cli_logging():
    """``main`` points the root logger at the stream pytest captures for this test; put the
    handlers back, so later tests' log records do not go to a closed stream."""
    import logging

    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


# --- DINOv3 ----------------------------------------------------------------------------------


def vits16plus_config():
    """The transformers config of facebook/dinov3-vits16plus-pretrain-lvd1689m."""
    transformers = pytest.importorskip("transformers")
    return transformers.DINOv3ViTConfig(
        patch_size=16, hidden_size=384, intermediate_size=1536, num_hidden_layers=12, num_attention_heads=6,
        hidden_act="silu", use_gated_mlp=True, num_register_tokens=4, layerscale_value=1.0, layer_norm_eps=1e-5,
        rope_theta=100.0, query_bias=True, key_bias=False, value_bias=True, proj_bias=True, mlp_bias=True,
    )


def zeros_state(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """Zero tensors of ``model``'s state-dict shapes (a model built on the meta device)."""
    return {k: torch.zeros(tuple(v.shape), dtype=v.dtype) for k, v in model.state_dict().items()}


def save_safetensors(state: dict[str, torch.Tensor], path: Path) -> Path:
    from safetensors.torch import save_file

    path.parent.mkdir(parents=True, exist_ok=True)
    save_file({k: v.contiguous() for k, v in state.items()}, str(path))
    return path


@pytest.fixture(scope="module")
def foreign_dinov3_folder(tmp_path_factory) -> Path:
    """The ViT-S+/16 config.json beside the weights of another model: a tiny transformers ViT."""
    transformers = pytest.importorskip("transformers")
    folder = tmp_path_factory.mktemp("dinov3_foreign") / "dinov3_vits16plus"
    vits16plus_config().save_pretrained(folder)
    with torch.device("meta"):
        vit = transformers.ViTModel(
            transformers.ViTConfig(hidden_size=32, num_hidden_layers=1, num_attention_heads=2, intermediate_size=64, image_size=32, patch_size=16)
        )
    save_safetensors(zeros_state(vit), folder / "model.safetensors")
    return folder


@pytest.mark.slow
def test_transformers_folder_with_foreign_weights_is_refused(foreign_dinov3_folder):
    from shared.perception.features.dinov3 import load_patch_tokens

    with pytest.raises(ValueError) as err:
        load_patch_tokens("transformers", foreign_dinov3_folder)
    msg = str(err.value)
    assert str(foreign_dinov3_folder) in msg and "not a DINOv3 ViT-S+/16 checkpoint (transformers layout)" in msg
    assert "missing keys (first: embeddings.mask_token, embeddings.patch_embeddings.bias" in msg
    assert "unexpected keys (first: embeddings.patch_embeddings.projection.bias" in msg
    assert "embeddings.cls_token (file (1, 1, 32), model (1, 1, 384))" in msg
    assert "huggingface.co/facebook/dinov3-vits16plus-pretrain-lvd1689m" in msg


@pytest.mark.slow
def test_transformers_folder_with_a_smaller_dinov3_is_refused(tmp_path):
    """Same key names, other shapes: transformers would re-initialise them (or raise an error
    that only points at its log)."""
    transformers = pytest.importorskip("transformers")
    from shared.perception.features.dinov3 import load_patch_tokens

    folder = tmp_path / "small"
    vits16plus_config().save_pretrained(folder)
    small = transformers.DINOv3ViTConfig(hidden_size=64, num_hidden_layers=2, num_attention_heads=2, intermediate_size=128, num_register_tokens=4)
    with torch.device("meta"):
        model = transformers.DINOv3ViTModel(small)
    save_safetensors(zeros_state(model), folder / "model.safetensors")
    with pytest.raises(ValueError) as err:
        load_patch_tokens("transformers", folder)
    msg = str(err.value)
    assert str(folder) in msg and "keys of the wrong shape (first: embeddings.cls_token (file (1, 1, 64), model (1, 1, 384))" in msg
    assert "missing keys (first: model.layer.0.mlp.gate_proj.bias" in msg  # ViT-S has no gate: 2 of 12 layers


def test_transformers_config_of_another_size_is_refused(tmp_path):
    """A whole DINOv3 of another size (its own config and weights) is refused by its config,
    before any weight is read."""
    transformers = pytest.importorskip("transformers")
    from shared.perception.features.dinov3 import load_patch_tokens

    cfg = transformers.DINOv3ViTConfig(hidden_size=64, num_hidden_layers=2, num_attention_heads=2, intermediate_size=128, num_register_tokens=0, patch_size=14)
    cfg.save_pretrained(tmp_path)
    (tmp_path / "model.safetensors").write_bytes(b"never read")
    with pytest.raises(ValueError) as err:
        load_patch_tokens("transformers", tmp_path)
    msg = str(err.value)
    assert str(tmp_path / "config.json") in msg and "DINOv3 ViT other than ViT-S+/16" in msg
    assert "hidden_size 64 (expected 384)" in msg and "patch_size 14 (expected 16)" in msg
    assert "num_register_tokens 0 (expected 4)" in msg and "use_gated_mlp False (expected True)" in msg


def test_transformers_config_of_another_model_is_refused(tmp_path):
    (tmp_path / "config.json").write_text(json.dumps({"model_type": "vit", "hidden_size": 768}))
    (tmp_path / "model.safetensors").write_bytes(b"never read")
    from shared.perception.features.dinov3 import load_patch_tokens

    with pytest.raises(ValueError, match=r"describes a 'vit' model, not DINOv3 ViT-S\+/16"):
        load_patch_tokens("transformers", tmp_path)


def test_transformers_folder_without_weights_is_missing(tmp_path):
    vits16plus_config().save_pretrained(tmp_path)
    from shared.perception.features.dinov3 import load_patch_tokens

    with pytest.raises(FileNotFoundError, match="no model.safetensors / pytorch_model.bin"):
        load_patch_tokens("transformers", tmp_path)


@pytest.mark.slow
def test_models_check_fails_on_foreign_dinov3_weights(foreign_dinov3_folder, tmp_path, capsys, monkeypatch, cli_logging):
    from services.cli import main
    from shared.perception.features.dinov3 import WHERE

    cfg = tmp_path / "cfg.yaml"
    # A relative path, so the report's absolute one is checked too.
    monkeypatch.chdir(foreign_dinov3_folder.parent)
    cfg.write_text(
        "keyframe_vl:\n  segmenter:\n    backend: simulated\n  vl:\n    backend: simulated\n"
        f"tracker:\n  features:\n    backend: dinov3\n    loader: transformers\n    weights: {foreign_dinov3_folder.name}\n"
    )
    assert main(["models", "check", "--config", str(cfg)]) == 1
    out = capsys.readouterr().out
    assert "FAILS" in out and f"{foreign_dinov3_folder.resolve()}\n" in out
    assert f"ValueError: {foreign_dinov3_folder.resolve()} is not a DINOv3 ViT-S+/16 checkpoint" in out
    assert "missing keys (first: embeddings.mask_token" in out
    assert f"get it: DINOv3 ViT-S+/16 for tracker.features.loader transformers: {WHERE['transformers']}" in out

    assert main(["models", "check", "--config", str(cfg), "--json"]) == 1
    result = json.loads(capsys.readouterr().out)
    (entry,) = result["models"]
    assert result["ok"] is False and result["missing"] == []
    assert entry["present"] is True and entry["loads"] is False
    assert entry["error"].startswith("ValueError: ") and "embeddings.patch_embeddings.weight" in entry["error"]
    assert entry["path"] == foreign_dinov3_folder.name and entry["resolved"] == str(foreign_dinov3_folder.resolve())
    assert entry["loader"] == "transformers" and WHERE["transformers"] in entry["source"]


def test_models_check_source_follows_the_dinov3_loader(tmp_path, capsys, cli_logging):
    from services.cli import main
    from shared.perception.features.dinov3 import WHERE

    for loader in ("timm", "hub"):
        cfg = tmp_path / f"{loader}.yaml"
        cfg.write_text(
            "keyframe_vl:\n  segmenter:\n    backend: simulated\n  vl:\n    backend: simulated\n"
            f"tracker:\n  features:\n    backend: dinov3\n    loader: {loader}\n    weights: {tmp_path / 'absent'}\n"
        )
        assert main(["models", "check", "--config", str(cfg), "--json"]) == 1
        (entry,) = json.loads(capsys.readouterr().out)["models"]
        assert entry["loader"] == loader and WHERE[loader] in entry["source"]
        assert entry["error"] == f"{(tmp_path / 'absent').resolve()} not found"


def tiny_dinov3_timm_state() -> dict[str, torch.Tensor]:
    """timm's ViT-Ti/16 DINOv3 (192 wide, plain MLP): a DINOv3 of the wrong size, 5M zeros."""
    timm = pytest.importorskip("timm")
    with torch.device("meta"):
        model = timm.create_model("vit_tiny_patch16_dinov3_qkvb", pretrained=False, num_classes=0)
    return zeros_state(model)


def timm_to_hub(sd: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """timm keys -> the official facebookresearch/dinov3 checkpoint's (plain-MLP ViTs)."""
    width = sd["cls_token"].shape[-1]
    out = {"mask_token": torch.zeros(1, width), "rope_embed.periods": torch.arange(16, dtype=torch.float32)}
    for key, value in sd.items():
        if key.endswith("attn.q_bias"):
            v_bias = sd[key.replace("q_bias", "v_bias")]
            out[key.replace("q_bias", "qkv.bias")] = torch.cat([value, torch.zeros_like(value), v_bias])
        elif key.endswith("attn.v_bias"):
            continue
        else:
            key = key.replace("reg_token", "storage_tokens").replace("gamma_1", "ls1.gamma").replace("gamma_2", "ls2.gamma")
            out[key] = value
    return out


def test_timm_file_of_the_wrong_size_is_refused(tmp_path):
    from shared.perception.features.dinov3 import load_patch_tokens

    file = save_safetensors(tiny_dinov3_timm_state(), tmp_path / "vit_tiny.safetensors")
    with pytest.raises(ValueError) as err:
        load_patch_tokens("timm", file)
    msg = str(err.value)
    assert msg.startswith(f"{file} is not a DINOv3 ViT-S+/16 checkpoint (timm layout): ")
    assert "keys of the wrong shape (first: cls_token (file (1, 1, 192), model (1, 1, 384)), reg_token" in msg
    assert "missing keys (first: blocks.0.mlp.fc1_g.weight" in msg and "unexpected keys (first: blocks.0.mlp.fc1.bias" in msg
    assert "timm/vit_small_plus_patch16_dinov3.lvd1689m" in msg


def test_hub_file_of_the_wrong_size_is_refused(tmp_path):
    from shared.perception.features.dinov3 import load_patch_tokens

    file = tmp_path / "dinov3_vits16plus_pretrain_lvd1689m-wrong.pth"
    torch.save(timm_to_hub(tiny_dinov3_timm_state()), file)
    with pytest.raises(ValueError) as err:
        load_patch_tokens("hub", tmp_path)  # the folder: the file is found by its name
    msg = str(err.value)
    assert msg.startswith(f"{file} is not a DINOv3 ViT-S+/16 checkpoint (hub layout): ")
    assert "cls_token (file (1, 1, 192), model (1, 1, 384))" in msg
    assert "dinov3_vits16plus_pretrain_lvd1689m-4057cbaa.pth" in msg


def test_timm_patch_embedding_of_another_patch_size_is_refused_not_resampled():
    """timm's filter would resample a 14x14 patch embedding to 16x16 and load it."""
    timm = pytest.importorskip("timm")
    from shared.perception.features.dinov3 import TIMM_VARIANT, timm_from_state_dict

    with torch.device("meta"):
        state = zeros_state(timm.create_model(TIMM_VARIANT, pretrained=False, num_classes=0))
    state["patch_embed.proj.weight"] = torch.zeros(384, 3, 14, 14)
    with pytest.raises(ValueError) as err:
        timm_from_state_dict(state, "vits14.safetensors")
    msg = str(err.value)
    assert msg.startswith("vits14.safetensors is not a DINOv3 ViT-S+/16 checkpoint (timm layout): 1 key of the wrong shape")
    assert "patch_embed.proj.weight (file (384, 3, 14, 14), model (384, 3, 16, 16))" in msg


# --- OpenCLIP --------------------------------------------------------------------------------

ARCH = "ViT-S-32"
"""The architecture the loader is asked for: OpenCLIP's smallest ViT."""


def openclip_zeros(arch: str, path: Path) -> Path:
    """An OpenCLIP state dict of ``arch``, zeros, saved as open_clip_pytorch_model.bin is."""
    open_clip = pytest.importorskip("open_clip")
    model = open_clip.create_model(arch, pretrained=None, device="meta")
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(zeros_state(model), path)
    return path


@pytest.mark.slow
def test_openclip_checkpoint_of_another_architecture_is_refused(tmp_path):
    """ViT-S-32-alt (text 256 wide, 10 layers) weights for ViT-S-32 (384 wide, 12 layers)."""
    from shared.perception.encoders.openclip import load_openclip

    file = openclip_zeros("ViT-S-32-alt", tmp_path / "open_clip_pytorch_model.bin")
    with pytest.raises(ValueError) as err:
        load_openclip(ARCH, file)
    msg = str(err.value)
    assert msg.startswith(f"{file.resolve()} is not an OpenCLIP {ARCH} checkpoint: ")
    assert "missing keys (first: transformer.resblocks.10.ln_1.weight" in msg
    assert "keys of the wrong shape (first: positional_embedding (file (77, 256), model (77, 384)), text_projection (file (256, 256), model (384, 384))" in msg
    assert "Give keyframe_vl.vl.model the architecture the file was trained as" in msg


@pytest.fixture(scope="module")
def transformers_clip_state() -> dict[str, torch.Tensor]:
    """A tiny transformers CLIPModel's state dict: the key layout of model.safetensors and
    pytorch_model.bin in the LAION repositories."""
    transformers = pytest.importorskip("transformers")
    cfg = transformers.CLIPConfig(
        text_config={"hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 1, "num_attention_heads": 2, "vocab_size": 99, "max_position_embeddings": 16},
        vision_config={"hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 1, "num_attention_heads": 2, "image_size": 32, "patch_size": 16},
        projection_dim=16,
    )
    with torch.device("meta"):
        model = transformers.CLIPModel(cfg)
    state = zeros_state(model)
    assert any(k.startswith("vision_model.embeddings.") for k in state)
    return state


@pytest.mark.parametrize("name", ["model.safetensors", "pytorch_model.bin"])
def test_transformers_format_clip_weights_get_the_open_clip_hint(transformers_clip_state, tmp_path, name):
    """A repository folder holding only the transformers conversion: the loader picks that file
    (OpenCLIP's own fallback order) and says which file of the repository to take instead."""
    from shared.perception.encoders.openclip import load_openclip

    if name.endswith(".safetensors"):
        save_safetensors(transformers_clip_state, tmp_path / name)
    else:
        torch.save(transformers_clip_state, tmp_path / name)
    with pytest.raises(ValueError) as err:
        load_openclip(ARCH, tmp_path)
    msg = str(err.value)
    assert msg.startswith(f"{(tmp_path / name).resolve()} is not an OpenCLIP checkpoint for {ARCH}: ")
    assert "Hugging Face transformers CLIPModel weights" in msg
    assert "open_clip cannot load: it needs open_clip_pytorch_model.bin or open_clip_model.safetensors from the same Hugging Face repository" in msg


def test_transformers_clip_hint_names_the_repository():
    from shared.perception.encoders.weights import is_transformers_clip, transformers_clip_hint

    assert "(laion/CLIP-ViT-B-32-laion2B-s34B-b79K)" in transformers_clip_hint("ViT-B-32")
    assert is_transformers_clip(["logit_scale", "text_model.embeddings.token_embedding.weight"])
    assert not is_transformers_clip(["logit_scale", "visual.conv1.weight", "transformer.resblocks.0.ln_1.weight"])


def test_unreadable_clip_file_is_refused(tmp_path):
    pytest.importorskip("open_clip")
    from shared.perception.encoders.openclip import load_openclip

    for name in ("garbage.bin", "garbage.safetensors"):
        (tmp_path / name).write_bytes(b"not a checkpoint at all")
        with pytest.raises(ValueError) as err:
            load_openclip(ARCH, tmp_path / name)
        msg = str(err.value)
        assert msg.startswith(f"{(tmp_path / name).resolve()} is not a readable checkpoint for OpenCLIP {ARCH} (")
        assert "weights_only" not in msg  # torch's advice to unpickle anyway is left out


# --- FastSAM ---------------------------------------------------------------------------------


def save_ultralytics(kind: str, path: Path) -> Path:
    """A random YOLOv8n of ``kind`` saved the way ultralytics saves its checkpoints."""
    needs_ultralytics()
    from ultralytics.nn.tasks import ClassificationModel, DetectionModel, yaml_model_load

    torch.manual_seed(0)
    if kind == "detect":
        model = DetectionModel(yaml_model_load("yolov8n.yaml"), ch=3, nc=80, verbose=False)
    else:
        model = ClassificationModel(yaml_model_load("yolov8n-cls.yaml"), ch=3, nc=10, verbose=False)
    model.task = kind
    torch.save({"model": model.half(), "ema": None, "train_args": {"task": kind}}, path)
    return path


@pytest.mark.parametrize(
    ("kind", "found"),
    [("detect", "an ultralytics DetectionModel for task 'detect' with 80 classes"), ("classify", "an ultralytics ClassificationModel for task 'classify' with 10 classes")],
)
def test_fastsam_refuses_another_yolo_task(tmp_path, kind, found):
    from shared.perception.segmenters.fastsam import load_fastsam

    file = save_ultralytics(kind, tmp_path / f"yolov8n-{kind}.pt")
    with pytest.raises(ValueError) as err:
        load_fastsam(file)
    msg = str(err.value)
    assert msg.startswith(f"{file} holds {found}, not a FastSAM. ")
    assert "expected a FastSAM checkpoint: an ultralytics YOLOv8-seg segmentation model (task 'segment', SegmentationModel) such as FastSAM-x.pt or FastSAM-s.pt" in msg.replace("Expected", "expected")


def test_fastsam_refuses_a_bare_state_dict(tmp_path):
    needs_ultralytics()
    from ultralytics.nn.tasks import SegmentationModel, yaml_model_load

    from shared.perception.segmenters.fastsam import load_fastsam

    torch.manual_seed(0)
    model = SegmentationModel(yaml_model_load("yolov8n-seg.yaml"), ch=3, nc=1, verbose=False)
    file = tmp_path / "FastSAM-s.pt"
    torch.save(model.state_dict(), file)
    with pytest.raises(ValueError) as err:
        load_fastsam(file)
    msg = str(err.value)
    assert msg.startswith(f"{file} is not an ultralytics checkpoint: it holds a bare state dict of ")
    assert "(first keys: model.0.conv.weight" in msg and "FastSAM-x.pt or FastSAM-s.pt" in msg


def test_fastsam_refuses_an_unreadable_file_and_another_suffix(tmp_path):
    needs_ultralytics()
    from shared.perception.segmenters.fastsam import load_fastsam

    broken = tmp_path / "FastSAM-x.pt"
    broken.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match=r"FastSAM-x.pt is not an ultralytics checkpoint: nothing torch or ultralytics can read; ultralytics says: "):
        load_fastsam(broken)
    other = tmp_path / "FastSAM-x.pth"
    other.write_bytes(b"")
    with pytest.raises(ValueError, match=r"FastSAM-x.pth is not a .pt file; expected a FastSAM checkpoint"):
        load_fastsam(other)


def test_fastsam_precision_argument_follows_ultralytics(monkeypatch):
    needs_ultralytics()
    from shared.perception.segmenters import fastsam

    fastsam.import_ultralytics()
    from ultralytics.cfg import DEFAULT_CFG_DICT

    name = "quantize" if "quantize" in DEFAULT_CFG_DICT else "half"
    assert set(fastsam.precision_kwargs(True)) == {name}
    assert set(fastsam.precision_kwargs(False)) <= set(DEFAULT_CFG_DICT)
    monkeypatch.setattr(fastsam, "_precision_arg", lambda: "half")  # an ultralytics before quantize=
    assert fastsam.precision_kwargs(True) == {"half": True} and fastsam.precision_kwargs(False) == {"half": False}
    monkeypatch.setattr(fastsam, "_precision_arg", lambda: "quantize")
    assert fastsam.precision_kwargs(True) == {"quantize": 16} and fastsam.precision_kwargs(False) == {"quantize": None}


# --- models check on every kind of foreign file ----------------------------------------------


def foreign_file(kind: str, folder: Path) -> tuple[str, Path, str]:
    """(config YAML, the file, a phrase of its refusal) for a wrong-model file of ``kind``."""
    simulated = "keyframe_vl:\n  segmenter:\n    backend: simulated\n  vl:\n    backend: simulated\n"
    if kind in ("timm", "hub"):
        name = "vit_tiny.safetensors" if kind == "timm" else "dinov3_vits16plus_pretrain_lvd1689m-wrong.pth"
        file = folder / name
        if kind == "timm":
            save_safetensors(tiny_dinov3_timm_state(), file)
        else:
            torch.save(timm_to_hub(tiny_dinov3_timm_state()), file)
        yaml = simulated + f"tracker:\n  features:\n    backend: dinov3\n    loader: {kind}\n    weights: {file}\n"
        return yaml, file, f"is not a DINOv3 ViT-S+/16 checkpoint ({kind} layout)"
    if kind == "fastsam":
        file = save_ultralytics("detect", folder / "FastSAM-x.pt")
        yaml = (
            f"keyframe_vl:\n  segmenter:\n    backend: fastsam\n    weights: {file}\n  vl:\n    backend: simulated\n"
            "tracker:\n  mode: ground_truth\n"
        )
        return yaml, file, "not a FastSAM"
    file = openclip_zeros("ViT-S-32-alt", folder / "open_clip_pytorch_model.bin")
    yaml = (
        f"keyframe_vl:\n  segmenter:\n    backend: simulated\n  vl:\n    backend: openclip\n    model: {ARCH}\n    weights: {file}\n"
        "tracker:\n  mode: ground_truth\n"
    )
    return yaml, file, f"is not an OpenCLIP {ARCH} checkpoint"


@pytest.mark.parametrize("kind", ["timm", "hub", "fastsam", pytest.param("openclip", marks=pytest.mark.slow)])
def test_models_check_fails_on_every_kind_of_foreign_file(kind, tmp_path, capsys, cli_logging):
    from services.cli import main

    yaml, file, phrase = foreign_file(kind, tmp_path)
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(yaml)
    assert main(["models", "check", "--config", str(cfg)]) == 1
    out = capsys.readouterr().out
    assert "FAILS" in out and phrase in out and "get it: " in out
    assert main(["models", "check", "--config", str(cfg), "--json"]) == 1
    result = json.loads(capsys.readouterr().out)
    (entry,) = result["models"]
    assert result["ok"] is False and entry["present"] is True and entry["loads"] is False
    assert phrase in entry["error"] and entry["resolved"] == str(file.resolve())
