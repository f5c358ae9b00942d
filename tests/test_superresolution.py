"""Super-resolution variants of the originals: parameter names, in-place image_raw, float16 path."""
import json

import pytest
import torch

from datagen.cameras import rays
from datagen.gans.checkpoint import read_checkpoint
from datagen.gans.networks import SUPERRESOLUTION, Superresolution
from tests.conftest import gan_fixture

# From the originals' constructors (EG3D training/superresolution.py): output resolution,
# (block0, block1) channels and resolutions, and whether the module registers its own filter.
ORIGINALS = {
    "SuperresolutionHybrid2X": (128, (128, 64), (64, 128), True),
    "SuperresolutionHybrid4X": (256, (128, 64), (128, 256), True),
    "SuperresolutionHybrid8X": (512, (128, 64), (256, 512), True),
    "SuperresolutionHybrid8XDC": (512, (256, 128), (256, 512), False),
    "SuperresolutionHybridDeepfp32": (256, (128, 64), (128, 256), True),
}


def original_listing(kind, in_channels=32):
    """(name, shape) in state-dict order as the originals register them."""
    _, (c0, c1), (r0, r1), own_filter = ORIGINALS[kind]
    out = [("resample_filter", [4, 4])] if own_filter else []  # a module's own buffers precede its children's
    for b, (cin, cout, res) in enumerate([(in_channels, c0, r0), (c0, c1, r1)]):
        p = f"block{b}."
        out.append((p + "resample_filter", [4, 4]))
        for conv, ci in (("conv0", cin), ("conv1", cout)):
            out += [(f"{p}{conv}.weight", [cout, ci, 3, 3]), (f"{p}{conv}.noise_strength", []),
                    (f"{p}{conv}.bias", [cout]), (f"{p}{conv}.resample_filter", [4, 4]),
                    (f"{p}{conv}.noise_const", [res, res]), (f"{p}{conv}.affine.weight", [ci, 512]),
                    (f"{p}{conv}.affine.bias", [ci])]
        out += [(p + "torgb.weight", [3, cout, 1, 1]), (p + "torgb.bias", [3]),
                (p + "torgb.affine.weight", [cout, 512]), (p + "torgb.affine.bias", [cout])]
    return out


@pytest.mark.parametrize("kind", sorted(ORIGINALS))
def test_every_variant_has_the_originals_names_and_shapes(kind):
    assert set(SUPERRESOLUTION) == set(ORIGINALS)
    sr = Superresolution(kind, 32, ORIGINALS[kind][0], sr_num_fp16_res=4)
    assert [(k, list(v.shape)) for k, v in sr.state_dict().items()] == original_listing(kind)


@pytest.mark.parametrize("fixture_set,kind", [("gan", "SuperresolutionHybrid2X"), ("gan-sr", "SuperresolutionHybrid8XDC")])
def test_listing_agrees_with_official_checkpoints(fixture_set, kind):
    """The oracle above against the state dicts of official pickles of both classes."""
    keys = json.loads(gan_fixture("eg3d", "-keys.json", fixture_set).read_text())
    assert keys["init_kwargs"]["rendering_kwargs"]["superresolution_module"].endswith(kind)
    official = [(e["name"][len("superresolution."):], e["shape"]) for e in keys["state_dict"]
                if e["name"].startswith("superresolution.")]
    assert official == original_listing(kind)


def _render(G, nrr, fp16_precision="fp32"):
    G.precision = fp16_precision
    ws = G.mapping(torch.randn(1, G.z_dim, generator=torch.Generator().manual_seed(3)), torch.zeros(1, 25), 0.7)
    cam = torch.eye(4)
    cam[2, 3] = 2.7
    cam[:3, 1:3] *= -1  # OpenCV camera at +z looking at the origin
    K = torch.tensor([[4.2647, 0, 0.5], [0, 4.2647, 0.5], [0, 0, 1.0]])
    o, d = rays(cam[None], K[None], nrr)
    return ws, o, d


@torch.no_grad()
def test_no_up_block_changes_image_raw_in_place_as_the_originals_do():
    """2X with a 64 px render: block0 (no upsampling) adds its ToRGB into image_raw in place."""
    G = read_checkpoint(gan_fixture("eg3d", ".pkl"), "eg3d").generator
    ws, o, d = _render(G, 64)
    seen = {}
    sr = G.superresolution
    pre = sr.register_forward_pre_hook(lambda _m, args: seen.update(rgb=args[0].clone(), x=args[1].clone()))
    post = sr.block0.torgb.register_forward_hook(lambda _m, _i, y: seen.update(torgb=y.clone()))
    out = G.synthesis(ws, o, d, 64, deterministic=True)
    pre.remove()
    post.remove()
    assert float((out["image_raw"] - seen["rgb"]).abs().max()) > 1e-3
    torch.testing.assert_close(out["image_raw"], seen["rgb"] + seen["torgb"])
    torch.testing.assert_close(out["feature_image"][:, :3], out["image_raw"])  # EG3D: a view of the feature image
    torch.testing.assert_close(out["feature_image"][:, 3:], seen["x"][:, 3:])
    # the final image is what the SR makes of the untouched inputs
    torch.testing.assert_close(out["image"], sr(seen["rgb"].clone(), seen["x"].clone(), ws))


@torch.no_grad()
def test_resized_input_leaves_image_raw_alone():
    G = read_checkpoint(gan_fixture("eg3d", ".pkl"), "eg3d").generator
    ws, o, d = _render(G, 32)
    seen = {}
    hook = G.superresolution.register_forward_pre_hook(lambda _m, args: seen.update(rgb=args[0].clone()))
    out = G.synthesis(ws, o, d, 32, deterministic=True)
    hook.remove()
    torch.testing.assert_close(out["image_raw"], seen["rgb"], rtol=0, atol=0)


@torch.no_grad()
def test_float16_blocks_stay_close_to_float32_and_finite():
    """The originals' fp16 SR arithmetic (forced here on the CPU) against float32, clamps active."""
    G = read_checkpoint(gan_fixture("eg3d", ".pkl", "gan-sr"), "eg3d").generator
    ws, o, d = _render(G, 128)
    ref = G.synthesis(ws, o, d, 128, deterministic=True)["image"]
    G.precision = "fp16"
    seen = {}
    hook = G.superresolution.block0.register_forward_hook(lambda _m, _i, out: seen.update(x=out[0]))
    half = G.synthesis(ws, o, d, 128, deterministic=True)["image"]
    hook.remove()
    G.precision = "auto"
    assert seen["x"].dtype == torch.float16 and half.dtype == torch.float32
    assert torch.isfinite(half).all()
    err = (half - ref).abs()
    assert 0 < float(err.max()) < 0.05 and float(err.mean()) < 5e-3
