"""The released 512 checkpoints' architecture: official generators with SuperresolutionHybrid8XDC.

The fixtures (../shared/fixtures/gan-sr) are ORIGINAL EG3D / PanoHead / SphereHead generators with
the production super-resolution at full size (128 px neural render -> 512 px, conv_clamp 256 active
in some channels), random weights, in the official pickle format, with recorded stage outputs.
Everything is loaded through ``read_checkpoint``, the loader ``datagen sample`` uses. Every float
array in a fixture is reproduced to 1e-4 max abs (per-channel statistics included); a fixture
array this test does not know fails it, so nothing is skipped silently.
"""
import json

import numpy as np
import pytest
import torch

from datagen.cameras import rays
from datagen.gans.checkpoint import read_checkpoint
from tests.conftest import gan_fixture

ATOL = 1e-4
MODELS = ["eg3d", "panohead", "spherehead"]
INPUTS = {"z", "c", "cams", "cam_yaw_pitch", "cam_pivot", "points", "truncation_psi", "truncation_cutoff",
          "neural_rendering_resolution"}


@pytest.fixture(scope="module", params=MODELS)
def reproduced(request):
    """(model, fixture arrays, our full-size tensors for every recorded stage)."""
    m = request.param
    F = np.load(gan_fixture(m, "-fixture.npz", "gan-sr"))
    G = read_checkpoint(gan_fixture(m, ".pkl", "gan-sr"), m).generator
    nrr = int(F["neural_rendering_resolution"])
    assert G.neural_rendering_resolution == nrr
    z, c = torch.tensor(F["z"]), torch.tensor(F["c"])
    psi, cutoff = float(F["truncation_psi"]), int(F["truncation_cutoff"])
    ours = {}
    sr = G.superresolution
    hooks = [sr.block0.register_forward_hook(lambda _m, _i, out: ours.update(sr_block0_x=out[0], sr_block0_img=out[1])),
             sr.block1.register_forward_hook(lambda _m, _i, out: ours.update(sr_block1_x=out[0]))]
    with torch.no_grad():
        ours["ws_notrunc"] = G.mapping(z, c, 1.0)
        ws = ours["ws"] = G.mapping(z, c, psi, cutoff)
        ours["planes"] = G.backbone.synthesis(ws, noise_mode="const")
        planes = G.planes(ws)
        if m == "spherehead":
            ours["planes_ab"] = planes
        if m != "eg3d":
            ours["delta_c"] = G.delta_c(z, c, psi, cutoff)
            ours["bcg_image"] = G.background(ws)
        cams = torch.tensor(F["cams"])
        o, d = rays(cams[:, :16].view(-1, 4, 4), cams[:, 16:].view(-1, 3, 3), nrr)
        out = G.synthesis(ws, o, d, nrr, planes=planes, noise_mode="const", deterministic=True)
        ours.update({k: out[k] for k in ("feature_image", "image_raw", "image_depth", "weights_sum", "image")})
        if "image_mask" in out:
            ours["image_mask"] = out["image_mask"]
        pts = torch.tensor(F["points"])[None].repeat(2, 1, 1)
        ours["point_plane_features"] = G.plane_features(planes, pts)
        ours["point_rgb"], ours["point_sigma"] = G.decode(planes, pts)
    for h in hooks:
        h.remove()
    return m, F, ours


def _expected_vs_ours(F, ours):
    """Yield (fixture name, fixture array, our array) for every recorded float array."""
    for name in F.files:
        ref = F[name]
        if name in INPUTS or name.endswith(("_stride", "_crop_origin", "_shape")):
            continue
        for suffix in ("_sub", "_crop", "_chan_mean", "_chan_std", ""):
            base = name[: len(name) - len(suffix)] if suffix else name
            if name.endswith(suffix) and base in ours:
                break
        else:
            raise AssertionError(f"fixture array {name} is not reproduced by this test")
        t = ours[base].double()
        if base + "_shape" in F.files:
            assert list(t.shape) == list(F[base + "_shape"]), f"{base}: shape {list(t.shape)}"
        if suffix == "_sub":
            s = int(F[base + "_stride"])
            t = t[..., ::s, ::s]
        elif suffix == "_crop":
            (r0, c0), (h, w) = F[base + "_crop_origin"], ref.shape[-2:]
            t = t[..., r0:r0 + h, c0:c0 + w]
        elif suffix == "_chan_mean":
            t = t.mean((-2, -1))
        elif suffix == "_chan_std":
            t = t.std((-2, -1))
        yield name, ref, t.numpy()


def test_every_recorded_stage_reproduces(reproduced):
    m, F, ours = reproduced
    errors = {}
    for name, ref, got in _expected_vs_ours(F, ours):
        assert got.shape == ref.shape, f"{m} {name}: shape {got.shape} != {ref.shape}"
        errors[name] = float(np.abs(got - ref.astype(np.float64)).max())
    print(m, "worst:", sorted(errors.items(), key=lambda kv: -kv[1])[:3])
    bad = {k: v for k, v in errors.items() if not v <= ATOL}
    assert not bad, f"{m}: max abs error above {ATOL}: {bad}"
    assert {"image", "sr_block0_img_sub", "sr_block1_x_chan_std", "image_depth"} <= set(errors)


def test_clamped_channels_are_active(reproduced):
    """The fixture puts SR channels across conv_clamp=256; ours clamps exactly there."""
    _, _, ours = reproduced
    x0 = ours["sr_block0_x"]
    assert float(x0.abs().max()) == 256.0
    assert float((x0.abs() == 256).float().mean()) > 1e-3


@pytest.mark.parametrize("model", MODELS)
def test_state_dict_names_shapes_and_bytes_match_the_originals(model):
    import hashlib
    keys = json.loads(gan_fixture(model, "-keys.json", "gan-sr").read_text())
    G = read_checkpoint(gan_fixture(model, ".pkl", "gan-sr"), model).generator
    ours = G.state_dict()
    listed = keys["state_dict"]
    assert list(ours) == [e["name"] for e in listed]  # same names, same order
    for e in listed:
        t = ours[e["name"]]
        assert list(t.shape) == e["shape"], e["name"]
        assert hashlib.sha256(t.contiguous().numpy().tobytes()).hexdigest() == e["sha256"], e["name"]
