"""Our EG3D / PanoHead / SphereHead reproduce the original generators' recorded outputs.

The fixtures are randomly initialised ORIGINAL generators in tiny configurations, pickled in the
official format, with stage-by-stage outputs in deterministic rendering mode (../shared/fixtures/gan).
Tolerance: 1e-4 max abs on every array (we measure <= 1e-5).
"""
import numpy as np
import pytest
import torch

from datagen.cameras import rays
from datagen.gans.checkpoint import read_checkpoint
from tests.conftest import gan_fixture

ATOL = 1e-4
MODELS = ["eg3d", "panohead", "spherehead"]


def close(ours, ref, name):
    ours = ours.detach().numpy() if torch.is_tensor(ours) else ours
    err = np.abs(ours.astype(np.float64) - ref.astype(np.float64)).max()
    assert ours.shape == ref.shape, f"{name}: shape {ours.shape} != {ref.shape}"
    assert err <= ATOL, f"{name}: max abs error {err:.2e} > {ATOL}"


@pytest.fixture(scope="module", params=MODELS)
def model(request):
    m = request.param
    fixture = np.load(gan_fixture(m, "-fixture.npz"))
    ck = read_checkpoint(gan_fixture(m, ".pkl"), m)
    return m, ck.generator, fixture


@torch.no_grad()
def test_mapping_and_truncation(model):
    _, G, F = model
    z, c = torch.tensor(F["z"]), torch.tensor(F["c"])
    close(G.mapping(z, c, 1.0), F["ws_notrunc"], "ws_notrunc")
    close(G.mapping(z, c, float(F["truncation_psi"]), int(F["truncation_cutoff"])), F["ws"], "ws")
    if "delta_c" in F.files:
        close(G.delta_c(z, c, float(F["truncation_psi"]), int(F["truncation_cutoff"])), F["delta_c"], "delta_c")


@torch.no_grad()
def test_backbone_planes(model):
    m, G, F = model
    ws = torch.tensor(F["ws"])
    raw = G.backbone.synthesis(ws, noise_mode="const")
    assert list(raw.shape) == list(F["planes_shape"])
    s = int(F["planes_stride"])
    r0, c0 = F["planes_crop_origin"]
    close(raw[..., ::s, ::s], F["planes_sub"], "planes_sub")
    close(raw[..., r0:r0 + 8, c0:c0 + 8], F["planes_crop"], "planes_crop")
    np.testing.assert_allclose(raw.double().mean((2, 3)).numpy(), F["planes_chan_mean"], atol=1e-5)
    np.testing.assert_allclose(raw.double().std((2, 3)).numpy(), F["planes_chan_std"], atol=1e-5)
    if m == "spherehead":
        ab = G.planes(ws)
        s, (r0, c0) = int(F["planes_ab_stride"]), F["planes_ab_crop_origin"]
        close(ab[..., ::s, ::s], F["planes_ab_sub"], "planes_ab_sub")
        close(ab[..., r0:r0 + 8, c0:c0 + 8], F["planes_ab_crop"], "planes_ab_crop")
    if "bcg_image" in F.files:
        close(G.background(ws), F["bcg_image"], "bcg_image")


@torch.no_grad()
def test_plane_sampling_and_decoder(model):
    _, G, F = model
    planes = G.planes(torch.tensor(F["ws"]))
    pts = torch.tensor(F["points"])[None].repeat(2, 1, 1)
    close(G.plane_features(planes, pts), F["point_plane_features"], "point_plane_features")
    rgb, sigma = G.decode(planes, pts)
    close(rgb, F["point_rgb"], "point_rgb")
    close(sigma, F["point_sigma"], "point_sigma")


@torch.no_grad()
def test_rendered_images(model):
    m, G, F = model
    ws = torch.tensor(F["ws"])
    planes = G.planes(ws)
    nrr = int(F["neural_rendering_resolution"])
    assert G.neural_rendering_resolution == nrr
    for k, cam in enumerate(torch.tensor(F["cams"])):
        cam = cam[None].repeat(2, 1)
        o, d = rays(cam[:, :16].view(-1, 4, 4), cam[:, 16:].view(-1, 3, 3), nrr)
        out = G.synthesis(ws, o, d, nrr, planes=planes, noise_mode="const", deterministic=True)
        if k == 0:
            close(out["feature_image"], F["feature_image_cam0"], "feature_image_cam0")
        for name in ("image_raw", "image_depth", "weights_sum", "image_mask", "image"):
            if name in F.files:
                close(out[name], F[name][k], f"{name}[cam {k}]")
