"""Image encoders: DINOv2 loading (Hugging Face folder and Meta's checkpoint), layer fusion, errors, small encoder."""
from __future__ import annotations

import os

os.environ["HF_HUB_OFFLINE"] = "1"  # before transformers is imported

import socket

import pytest
import torch
import transformers

from panolam.encoder import (IMAGENET_MEAN, IMAGENET_STD, DinoV2Encoder, EncoderError, SmallEncoder,
                             build_encoder)

# Meta's checkpoints imply 64-dim heads (heads = dim / 64), so the tiny model keeps them.
TINY = dict(hidden_size=128, num_hidden_layers=4, num_attention_heads=2, patch_size=14, image_size=56)
HAS_REGISTERS = hasattr(transformers, "Dinov2WithRegistersModel")


@pytest.fixture(autouse=True)
def no_network(monkeypatch):
    def refuse(*args, **kwargs):
        raise OSError("a test tried to reach the network")
    monkeypatch.setattr(socket.socket, "connect", refuse)


def tiny_dinov2(registers: int = 0):
    """A random tiny DINOv2 with every parameter perturbed (so layer scales and norms matter), in eval mode."""
    torch.manual_seed(0)
    if registers:
        model = transformers.Dinov2WithRegistersModel(transformers.Dinov2WithRegistersConfig(
            num_register_tokens=registers, **TINY))
    else:
        model = transformers.Dinov2Model(transformers.Dinov2Config(**TINY))
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.randn_like(p))
    return model.eval()


def to_meta(model) -> dict:
    """Inverse of the loader's key conversion: a Hugging Face Dinov2 state dict -> Meta's checkpoint layout."""
    sd = model.state_dict()
    new_names = "encoder.layer.0.attention.q_proj.weight" in sd  # transformers >= 5 renamed the attention
    q, k, v, o = (("attention.q_proj", "attention.k_proj", "attention.v_proj", "attention.o_proj") if new_names else
                  ("attention.attention.query", "attention.attention.key", "attention.attention.value",
                   "attention.output.dense"))
    out = {"cls_token": sd["embeddings.cls_token"], "mask_token": sd["embeddings.mask_token"],
           "pos_embed": sd["embeddings.position_embeddings"],
           "patch_embed.proj.weight": sd["embeddings.patch_embeddings.projection.weight"],
           "patch_embed.proj.bias": sd["embeddings.patch_embeddings.projection.bias"],
           "norm.weight": sd["layernorm.weight"], "norm.bias": sd["layernorm.bias"]}
    if "embeddings.register_tokens" in sd:
        out["register_tokens"] = sd["embeddings.register_tokens"]
    for i in range(model.config.num_hidden_layers):
        hf, meta = f"encoder.layer.{i}.", f"blocks.{i}."
        for t in ("weight", "bias"):
            out[f"{meta}attn.qkv.{t}"] = torch.cat([sd[f"{hf}{name}.{t}"] for name in (q, k, v)])
            for a, b in (("norm1", "norm1"), ("norm2", "norm2"), (o, "attn.proj"), ("mlp.fc1", "mlp.fc1"),
                         ("mlp.fc2", "mlp.fc2")):
                out[f"{meta}{b}.{t}"] = sd[f"{hf}{a}.{t}"]
        out[f"{meta}ls1.gamma"] = sd[f"{hf}layer_scale1.lambda1"]
        out[f"{meta}ls2.gamma"] = sd[f"{hf}layer_scale2.lambda1"]
    return {key: value.clone() for key, value in out.items()}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """(model, Hugging Face folder, Meta checkpoint file) of the tiny DINOv2."""
    root = tmp_path_factory.mktemp("dinov2")
    model = tiny_dinov2()
    model.save_pretrained(root / "hf")
    torch.save(to_meta(model), root / "dinov2_tiny_pretrain.pth")
    return model, root / "hf", root / "dinov2_tiny_pretrain.pth"


def images(batch=2, size=56):
    return torch.rand(batch, 3, size, size, generator=torch.Generator().manual_seed(1))


def test_dinov2_folder_shapes_and_frozen_backbone(tiny):
    _, folder, _ = tiny
    enc = DinoV2Encoder(folder, layers=(1, 2, 3, 4), out_dim=32, image_size=56).train()
    assert (enc.out_dim, enc.num_tokens, enc.image_size) == (32, 16, 56)
    assert not enc.backbone.training and enc.fusion.training
    out = enc(images(size=70))  # resized to 56 inside
    assert out.shape == (2, 16, 32)
    out.square().mean().backward()
    assert all(not p.requires_grad and p.grad is None for p in enc.backbone.parameters())
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in enc.fusion.parameters())


@pytest.mark.parametrize("layers", [(1, 2, 3, 4), (3, 1)])
def test_dinov2_layers_are_normalized_hidden_states(tiny, layers):
    model, folder, _ = tiny
    enc = DinoV2Encoder(folder, layers=layers, out_dim=8, image_size=56)
    img = images()
    x = (img - torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)) / torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    with torch.no_grad():
        ref = model(pixel_values=x, output_hidden_states=True)
        expected = [model.layernorm(ref.hidden_states[i])[:, 1:] for i in layers]
    got = enc.features(img)
    assert len(got) == len(layers)
    for g, e in zip(got, expected):
        torch.testing.assert_close(g, e, rtol=1e-5, atol=1e-5)
    if layers[0] == 1:  # the last block's normalized output is the model's own last_hidden_state
        torch.testing.assert_close(got[-1], ref.last_hidden_state[:, 1:], rtol=1e-5, atol=1e-5)


def assert_same_encoders(a: DinoV2Encoder, b: DinoV2Encoder, tokens: int):
    b.fusion.load_state_dict(a.fusion.state_dict())
    img = images()
    with torch.no_grad():
        fa, fb = a.features(img), b.features(img)
        assert fa[0].shape[1] == tokens
        for x, y in zip(fa, fb):
            torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(a(img), b(img), rtol=1e-5, atol=1e-5)


def test_meta_checkpoint_matches_folder(tiny):
    _, folder, meta = tiny
    a = DinoV2Encoder(folder, layers=(1, 2, 3, 4), out_dim=16, image_size=56)
    b = DinoV2Encoder(meta, layers=(1, 2, 3, 4), out_dim=16, image_size=56)
    assert type(b.backbone).__name__ == "Dinov2Model"
    assert (b.backbone.config.hidden_size, b.backbone.config.num_hidden_layers) == (128, 4)
    assert_same_encoders(a, b, tokens=16)


@pytest.mark.skipif(not HAS_REGISTERS, reason="this transformers has no Dinov2WithRegistersModel")
def test_meta_register_checkpoint_matches_folder(tmp_path):
    model = tiny_dinov2(registers=2)
    model.save_pretrained(tmp_path / "hf")
    torch.save(to_meta(model), tmp_path / "dinov2_tiny_reg2_pretrain.pth")
    a = DinoV2Encoder(tmp_path / "hf", layers=(2, 4), out_dim=16, image_size=56)
    b = DinoV2Encoder(tmp_path / "dinov2_tiny_reg2_pretrain.pth", layers=(2, 4), out_dim=16, image_size=56)
    assert b.backbone.config.num_register_tokens == 2
    assert_same_encoders(a, b, tokens=16)  # class and register tokens dropped
    with torch.no_grad():
        x = (images() - torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)) / torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
        last = model(pixel_values=x).last_hidden_state[:, 3:]
        torch.testing.assert_close(b.features(images())[-1], last, rtol=1e-5, atol=1e-5)


def error_of(fn, *args, **kwargs) -> str:
    with pytest.raises(EncoderError) as info:
        fn(*args, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    return message


def test_dinov2_errors(tiny, tmp_path):
    _, folder, _ = tiny
    missing = tmp_path / "nowhere.pth"
    msg = error_of(DinoV2Encoder, missing)
    assert str(missing) in msg and "no such file" in msg and "github.com/facebookresearch/dinov2" in msg

    not_dino = tmp_path / "other.pth"
    torch.save({"conv.weight": torch.randn(4, 3, 3, 3), "fc.bias": torch.randn(4)}, not_dino)
    msg = error_of(DinoV2Encoder, not_dino)
    assert str(not_dino) in msg and "not a DINOv2 checkpoint" in msg and "huggingface.co/facebook/dinov2-large" in msg

    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"not a checkpoint at all")
    msg = error_of(DinoV2Encoder, garbage)
    assert str(garbage) in msg and "cannot load DINOv2 weights" in msg

    partial = tmp_path / "partial.pth"
    state = to_meta(tiny[0])
    del state["blocks.1.ls1.gamma"]
    torch.save(state, partial)
    msg = error_of(DinoV2Encoder, partial, layers=(1,), image_size=56)
    assert str(partial) in msg and "lacks DINOv2 tensors (1, e.g. encoder.layer.1.layer_scale1" in msg

    msg = error_of(DinoV2Encoder, folder, layers=(2, 5), image_size=56)
    assert str(folder) in msg and "4 layers" in msg and "1..4" in msg and "facebookresearch/dinov2" in msg

    msg = error_of(DinoV2Encoder, folder, layers=(1,), image_size=50)
    assert "patch size 14" in msg

    no_weights = tmp_path / "config_only"
    transformers.Dinov2Config(**TINY).save_pretrained(no_weights)
    msg = error_of(DinoV2Encoder, no_weights)
    assert str(no_weights) in msg and "cannot load DINOv2 weights" in msg

    vit = tmp_path / "vit"
    transformers.ViTConfig().save_pretrained(vit)
    assert "'vit' model, not DINOv2" in error_of(DinoV2Encoder, vit)


def test_build_encoder():
    msg = error_of(build_encoder, "dinov2", None, 512)
    assert "'full' config needs DINOv2 weights" in msg and "facebookresearch/dinov2" in msg
    assert "unknown encoder" in error_of(build_encoder, "resnet", None, 512)
    enc = build_encoder("small", None, 64, image_size=32, patch_size=8, width=32, depth=2, heads=2, layers=(1, 2))
    assert isinstance(enc, SmallEncoder) and enc.out_dim == 64 and enc(images(1, 32)).shape == (1, 16, 64)


def test_small_encoder_shapes_backward_and_determinism():
    torch.manual_seed(0)
    enc = SmallEncoder()
    assert (enc.out_dim, enc.num_tokens, enc.image_size, len(enc.blocks)) == (256, 256, 128, 4)
    img = images(2, 512)  # resized to 128 inside
    out = enc(img)
    assert out.shape == (2, 256, 256) and torch.isfinite(out).all()
    out.square().mean().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in enc.parameters())

    torch.manual_seed(0)
    again = SmallEncoder()
    torch.manual_seed(1)
    other = SmallEncoder()
    with torch.no_grad():
        assert torch.equal(again(img), out.detach())
        assert not torch.allclose(other(img), out.detach())


def test_small_encoder_layers():
    enc = SmallEncoder(image_size=32, patch_size=8, width=32, depth=4, heads=2, layers=(3, 1), out_dim=16)
    assert len(enc.blocks) == 3  # nothing after the last fused block
    feats = enc.features(images(1, 32))
    assert [f.shape for f in feats] == [(1, 16, 32)] * 2
    torch.testing.assert_close(feats[0].mean(-1), torch.zeros(1, 16), atol=1e-5, rtol=0)  # through the LayerNorm
    assert "1..4" in error_of(SmallEncoder, depth=4, layers=(2, 5))
    assert "patch_size" in error_of(SmallEncoder, image_size=100, patch_size=8)
