"""Image encoders: images (B, 3, H, W) RGB in [0, 1] -> image tokens (B, N, out_dim).

Both encoders resize the images to ``image_size`` (bilinear, antialiased; the aspect ratio is not
kept), normalize them with the ImageNet mean and std, take the outputs of several transformer
blocks (1-based indices) with a final LayerNorm applied to each and without class or register
tokens, concatenate them per patch and fuse them with a per-token MLP (:class:`TokenFusion`).

* :class:`DinoV2Encoder`: the paper's frozen DINOv2 (layers 5, 12, 18, 24 of ViT-L/14, as the
  official ``get_intermediate_layers(norm=True)``), from a Hugging Face folder or Meta's checkpoint.
* :class:`SmallEncoder`: a CPU-sized ViT trained from scratch.
"""
from __future__ import annotations

import math
from contextlib import contextmanager
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

from datagen.device import constant
from datagen.errors import UserError, optional_import

# transformers is imported where DINOv2 is loaded: importing it takes seconds and the small encoder does not need it.

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
WEIGHTS_HINT = ("official DINOv2 weights: dinov2_vitl14_pretrain.pth from https://github.com/facebookresearch/dinov2 "
                "or the folder of https://huggingface.co/facebook/dinov2-large")
# Meta's checkpoint keys inside blocks.N -> the Hugging Face checkpoint names (the fused qkv is split apart).
_BLOCK_RENAMES = (("attn.proj.", "attention.output.dense."), ("ls1.gamma", "layer_scale1.lambda1"),
                  ("ls2.gamma", "layer_scale2.lambda1"))
_META_REQUIRED = ("cls_token", "pos_embed", "patch_embed.proj.weight", "blocks.0.attn.qkv.weight",
                  "blocks.0.mlp.fc1.weight", "norm.weight")


class EncoderError(UserError, ValueError):
    """An encoder that cannot be built: bad weights or settings (a one-line message)."""


class DinoV2ShapedStub(nn.Module):
    """Tokens of DINOv2 ViT-L/14's shape at 518 px (37 x 37 of ``out_dim``) from a linear map of the
    area-averaged image: a stand-in for timing the rest of the model, and for tests, without weights."""

    def __init__(self, out_dim: int):
        super().__init__()
        self.out_dim, self.num_tokens, self.image_size = out_dim, 37 * 37, 518
        self.proj = nn.Linear(3, out_dim)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.proj(F.interpolate(images, size=(37, 37), mode="area").flatten(2).transpose(1, 2))


class TokenFusion(nn.Sequential):
    """Per-token MLP (B, N, in_dim) -> (B, N, out_dim): Linear, GELU, Linear."""

    def __init__(self, in_dim: int, out_dim: int):
        super().__init__(nn.Linear(in_dim, out_dim), nn.GELU(), nn.Linear(out_dim, out_dim))


def prepare_images(images: torch.Tensor, size: int) -> torch.Tensor:
    """(B, 3, H, W) RGB in [0, 1] -> (B, 3, size, size) resized and ImageNet-normalized."""
    if images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"images must be (B, 3, H, W), got {tuple(images.shape)}")
    if images.shape[-2:] != (size, size):
        images = F.interpolate(images, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
    mean = constant(IMAGENET_MEAN, images.device).to(images.dtype).view(1, 3, 1, 1)
    std = constant(IMAGENET_STD, images.device).to(images.dtype).view(1, 3, 1, 1)
    return (images - mean) / std


def _layers_error(layers: tuple, depth: int) -> str | None:
    """Why ``layers`` are not 1-based block indices of a ``depth``-block model; None when they are."""
    if not layers or any(not isinstance(i, int) or not 1 <= i <= depth for i in layers):
        return f"it has {depth} layers, so the fused layers {layers} must be 1-based indices in 1..{depth}"
    return None


def _one_line(text) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= 300 else text[:297] + "..."


def _weights_error(path: Path, why: str) -> EncoderError:
    return EncoderError(f"{path}: {why}; {WEIGHTS_HINT}")


@contextmanager
def _reading(path: Path):
    """Turns any failure of a third-party loader into an EncoderError naming ``path``."""
    try:
        yield
    except EncoderError:
        raise
    except Exception as e:  # torch.load, safetensors and transformers raise many unrelated types
        raise _weights_error(path, f"cannot load DINOv2 weights ({type(e).__name__}: {_one_line(e)})") from e


def _meta_to_hf(state: dict) -> dict:
    """Meta's DINOv2 state dict -> the Hugging Face Dinov2 / Dinov2WithRegisters checkpoint names."""
    out = {}
    for key, value in state.items():
        if key.startswith("blocks."):
            _, index, rest = key.split(".", 2)
            prefix = f"encoder.layer.{index}."
            if rest.startswith("attn.qkv."):
                for name, part in zip(("query", "key", "value"), value.chunk(3)):
                    out[f"{prefix}attention.attention.{name}.{rest[9:]}"] = part
                continue
            for old, new in _BLOCK_RENAMES:
                rest = rest.replace(old, new)
            out[prefix + rest] = value
        elif key.startswith("norm."):
            out["layernorm." + key[5:]] = value
        elif key.startswith("patch_embed.proj."):
            out["embeddings.patch_embeddings.projection." + key[17:]] = value
        else:  # cls_token, mask_token, register_tokens, pos_embed
            out["embeddings." + ("position_embeddings" if key == "pos_embed" else key)] = value
    return out


def _meta_checkpoint(path: Path):
    """(config, Hugging Face state dict) from Meta's checkpoint; the architecture comes from the shapes."""
    import transformers

    with _reading(path):
        state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or any(k not in state for k in _META_REQUIRED):
        raise _weights_error(path, "not a DINOv2 checkpoint (ViT-S/B/L/14, with or without registers): "
                                   f"it lacks Meta's keys {', '.join(_META_REQUIRED)}")
    with _reading(path):
        dim = state["cls_token"].shape[-1]
        patch = state["patch_embed.proj.weight"].shape[-1]
        grid = math.isqrt(state["pos_embed"].shape[1] - 1)
        registers = state["register_tokens"].shape[1] if "register_tokens" in state else 0
        depth = 1 + max(int(k.split(".")[1]) for k in state if k.startswith("blocks."))
        sizes = dict(hidden_size=dim, num_hidden_layers=depth,
                     num_attention_heads=dim // 64, mlp_ratio=state["blocks.0.mlp.fc1.weight"].shape[0] // dim,
                     patch_size=patch, image_size=grid * patch, qkv_bias="blocks.0.attn.qkv.bias" in state,
                     layer_norm_eps=1e-6)
        config = (transformers.Dinov2WithRegistersConfig(num_register_tokens=registers, **sizes) if registers
                  else transformers.Dinov2Config(**sizes))
        return config, _meta_to_hf(state)


def load_dinov2(weights: str | Path) -> nn.Module:
    """A frozen float32 Dinov2Model / Dinov2WithRegistersModel in eval mode from a Hugging Face folder
    (config.json + weights, local files only) or Meta's checkpoint file."""
    transformers = optional_import("transformers", "model", "the DINOv2 encoder")

    path = Path(weights)
    if not path.exists():
        raise _weights_error(path, "no such file or folder")
    if path.is_dir():
        with _reading(path):
            config = transformers.AutoConfig.from_pretrained(path, local_files_only=True)
        source, state = path, None
    else:
        config, state = _meta_checkpoint(path)
        source = None
    model_class = {"dinov2": transformers.Dinov2Model,
                   "dinov2_with_registers": transformers.Dinov2WithRegistersModel}.get(config.model_type)
    if model_class is None:
        raise _weights_error(path, f"a {config.model_type!r} model, not DINOv2")
    with _reading(path):
        model, info = model_class.from_pretrained(source, config=config, state_dict=state, local_files_only=True,
                                                  output_loading_info=True)
    if info["missing_keys"]:
        missing = sorted(info["missing_keys"])
        raise _weights_error(path, f"it lacks DINOv2 tensors ({len(missing)}, e.g. {missing[0]})")
    return model.float().eval().requires_grad_(False)


class DinoV2Encoder(nn.Module):
    """Frozen DINOv2 backbone (transformers' Dinov2Model) + trainable fusion MLP -> (B, N_patches, out_dim).

    weights: a Hugging Face folder (e.g. facebook/dinov2-large) or Meta's dinov2_vit*14[_reg4]_pretrain.pth.
    layers: 1-based blocks whose normalized patch tokens are fused. image_size: input side, px, a
    multiple of the patch size (transformers interpolates the position embeddings to it).
    """

    def __init__(self, weights: str | Path, layers=(5, 12, 18, 24), out_dim: int = 512, image_size: int = 518):
        super().__init__()
        self.backbone = load_dinov2(weights)
        config = self.backbone.config
        self.layers = tuple(layers)
        if why := _layers_error(self.layers, config.num_hidden_layers):
            raise _weights_error(Path(weights), why)
        if image_size % config.patch_size:
            raise EncoderError(f"image_size {image_size} is not a multiple of DINOv2's patch size {config.patch_size}")
        self.image_size, self.out_dim = image_size, out_dim
        self.num_tokens = (image_size // config.patch_size) ** 2
        self.skip = 1 + getattr(config, "num_register_tokens", 0)  # class token, then the registers
        self.fusion = TokenFusion(len(self.layers) * config.hidden_size, out_dim)

    def train(self, mode: bool = True):
        """Trains the fusion only; the backbone stays in eval mode."""
        super().train(mode)
        self.backbone.eval()
        return self

    @torch.no_grad()
    def features(self, images: torch.Tensor) -> list:
        """images (B, 3, H, W) in [0, 1] -> per fused layer, normalized patch tokens (B, N, hidden)."""
        x = prepare_images(images, self.image_size)
        hidden = self.backbone(pixel_values=x, output_hidden_states=True).hidden_states  # [0] is the embedding
        return [self.backbone.layernorm(hidden[i])[:, self.skip:] for i in self.layers]

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """images (B, 3, H, W) in [0, 1] -> tokens (B, num_tokens, out_dim)."""
        return self.fusion(torch.cat(self.features(images), dim=-1))


class _Block(nn.Module):
    """Pre-LN transformer block (B, N, width) -> (B, N, width): x + attn(LN x), then x + MLP(LN x)."""

    def __init__(self, width: int, heads: int):
        super().__init__()
        self.heads = heads
        self.norm1, self.norm2 = nn.LayerNorm(width), nn.LayerNorm(width)
        self.qkv, self.proj = nn.Linear(width, 3 * width), nn.Linear(width, width)
        self.mlp = nn.Sequential(nn.Linear(width, 4 * width), nn.GELU(), nn.Linear(4 * width, width))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, c = x.shape
        q, k, v = self.qkv(self.norm1(x)).view(b, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        x = x + self.proj(F.scaled_dot_product_attention(q, k, v).transpose(1, 2).reshape(b, n, c))
        return x + self.mlp(self.norm2(x))


class SmallEncoder(nn.Module):
    """CPU-sized encoder trained from scratch: conv patch embedding + learnable position embedding + pre-LN
    transformer blocks; the outputs of ``layers`` (1-based, each through a shared final LayerNorm, like
    DINOv2's intermediate layers) are concatenated and fused -> (B, (image_size/patch_size)^2, out_dim).
    Blocks after the last fused one would not change the output, so they are not built."""

    def __init__(self, image_size: int = 128, patch_size: int = 8, width: int = 192, depth: int = 4, heads: int = 4,
                 layers=(2, 4), out_dim: int = 256):
        super().__init__()
        self.layers = tuple(layers)
        if why := _layers_error(self.layers, depth):
            raise EncoderError(f"SmallEncoder: {why}")
        if image_size % patch_size:
            raise EncoderError(f"image_size {image_size} is not a multiple of patch_size {patch_size}")
        if width % heads:
            raise EncoderError(f"width {width} is not a multiple of heads {heads}")
        self.image_size, self.out_dim = image_size, out_dim
        self.num_tokens = (image_size // patch_size) ** 2
        self.patch_embed = nn.Conv2d(3, width, patch_size, stride=patch_size)
        self.pos_embed = nn.Parameter(0.02 * torch.randn(1, self.num_tokens, width))
        self.blocks = nn.ModuleList(_Block(width, heads) for _ in range(max(self.layers)))
        self.norm = nn.LayerNorm(width)
        self.fusion = TokenFusion(len(self.layers) * width, out_dim)

    def features(self, images: torch.Tensor) -> list:
        """images (B, 3, H, W) in [0, 1] -> per fused layer, normalized tokens (B, N, width)."""
        x = self.patch_embed(prepare_images(images, self.image_size)).flatten(2).transpose(1, 2) + self.pos_embed
        outputs = []
        for block in self.blocks:
            x = block(x)
            outputs.append(x)
        return [self.norm(outputs[i - 1]) for i in self.layers]

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """images (B, 3, H, W) in [0, 1] -> tokens (B, num_tokens, out_dim)."""
        return self.fusion(torch.cat(self.features(images), dim=-1))


def build_encoder(kind: str, weights: str | None, out_dim: int, **kwargs) -> nn.Module:
    """``"dinov2"`` (frozen, ``weights`` required) or ``"small"`` (from scratch, no weights); kwargs go to the class."""
    if kind == "dinov2":
        if weights is None:
            raise EncoderError(f"the 'full' config needs DINOv2 weights (encoder_weights); {WEIGHTS_HINT}")
        return DinoV2Encoder(weights, out_dim=out_dim, **kwargs)
    if kind == "small":
        if weights is not None:
            raise EncoderError(f"the small encoder is trained from scratch and takes no weights (got {weights})")
        return SmallEncoder(out_dim=out_dim, **kwargs)
    raise EncoderError(f"unknown encoder {kind!r}; choose 'dinov2' or 'small'")
