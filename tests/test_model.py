"""The PanoLAM network: shapes, gradients, clamps, densification, tri-plane branch, ablations, full sizes."""
from __future__ import annotations

import pytest
import torch

from panolam import model as model_module
from panolam.config import ModelConfig, preset
from panolam.encoder import DinoV2ShapedStub
from panolam.model import PanoLAM, parameter_count, virtual_ray_samples
from panolam.rasterizer import render_views
from tests.conftest import gan_fixture

# A tiny model that still exercises every stage; fast enough for CPU tests.
SMALL = dict(image_size=64, token_dim=64, encoder_width=64, encoder_depth=2, encoder_layers=(1, 2), blocks=2,
             head_hidden=32, dense_points=2000, triplane_resolution=8, triplane_blocks=1, ray_samples=4,
             triplane_aggregate_dim=16, triplane_render_resolution=12, triplane_render_samples=(6, 6))


def small(name="tiny", **kw) -> PanoLAM:
    torch.manual_seed(0)
    return PanoLAM(preset(name, **{**SMALL, **kw}))


def front_cameras(b: int, v: int = 2):
    from datagen.cameras import named_views
    views = named_views(["front", "back"][:v])
    c2w = torch.from_numpy(views.cam2world).float()[None].expand(b, -1, -1, -1)
    K = torch.from_numpy(views.K).float()[None].expand(b, -1, -1, -1)
    return c2w, K


def test_tiny_forward_backward_on_512_image():
    m = small()
    img = torch.rand(2, 3, 512, 512)
    rec = m(img)
    V, M = len(m.template_points), m.dense_count
    assert rec.coarse.means.shape == (2, V, 3) and rec.dense.means.shape == (2, M, 3)
    assert abs(M - 2000) / 2000 < 0.1
    assert rec.planes.shape == (2, 2, 3, 32, 8, 8)
    upm = m.template.units_per_metre
    assert rec.coarse_offsets.abs().max() <= 0.15 * upm + 1e-6
    assert rec.dense_offsets.abs().max() <= 0.056 * upm + 1e-6
    lo, hi = m.cfg.dense_scale_range
    assert rec.dense.scales.min() >= lo and rec.dense.scales.max() <= hi
    assert torch.allclose(rec.dense.quats.norm(dim=-1), torch.ones(2, M), atol=1e-5)
    c2w, K = front_cameras(2)
    rgb, alpha, _ = render_views(rec.dense, c2w, K, 24)
    rgb_c, _, _ = render_views(rec.coarse, c2w, K, 24)
    trgb, talpha = m.render_triplane(rec.planes, c2w, K, torch.full((2, 2), 2.7))
    assert rgb.shape == (2, 2, 24, 24, 3) and trgb.shape == (2, 2, 3, 12, 12) and talpha.shape == (2, 2, 1, 12, 12)
    loss = rgb.mean() + alpha.mean() + rgb_c.mean() + trgb.mean()
    loss.backward()
    for name in ("encoder", "point_embed", "blocks", "coarse_head", "triplane", "aggregate", "dense_head",
                 "triplane_decoder"):
        grads = [p.grad for p in getattr(m, name).parameters() if p.requires_grad]
        assert grads and all(g is not None for g in grads), name
        assert all(torch.isfinite(g).all() for g in grads), name
        assert any(g.abs().sum() > 0 for g in grads), name


def test_untrained_model_renders_the_template_shape():
    """Offsets start at zero: coarse Gaussians sit on the template, dense ones on its barycentric points."""
    m = small()
    with torch.no_grad():
        rec = m(torch.rand(1, 3, 64, 64))
    V = len(m.template_points)
    assert torch.equal(rec.coarse.means[0], m.template_points)
    assert torch.allclose(rec.dense.means[0, :V], m.template_points, atol=1e-6)
    expected = m.densify(m.template_points[None])[0]
    assert torch.allclose(rec.dense.means[0], expected, atol=1e-6)
    c2w, K = front_cameras(1)
    _, alpha, _ = render_views(rec.dense, c2w, K, 32)
    assert alpha[0, 0, 16, 16, 0] > 0.9 and alpha[0, 0, 0, 0, 0] < 0.05  # a head in the middle, empty corner


def test_densify_gradient_reaches_coarse_offsets():
    m = small()
    rec = m(torch.rand(1, 3, 64, 64))
    rec.dense.means.sum().backward()
    g = m.coarse_head.net[-1].weight.grad
    assert g is not None and g[-3:].abs().sum() > 0  # offset rows: dense points move with their coarse anchors


@pytest.mark.parametrize("ablation", ["no_c2f", "single_point", "no_triplane"])
def test_ablations(ablation):
    m = small(f"tiny+{ablation}")
    rec = m(torch.rand(1, 3, 64, 64))
    assert rec.dense.means.shape[1] == m.dense_count
    if ablation == "no_c2f":
        assert rec.coarse is None and rec.coarse_offsets is None and not hasattr(m, "coarse_head")
        assert rec.dense_offsets.abs().max() <= 0.15 * m.template.units_per_metre + 1e-6
    if ablation == "no_triplane":
        assert rec.planes is None and not hasattr(m, "triplane")
    if ablation == "single_point":
        assert m.aggregate[0].in_features == m.cfg.triplane_channels
    rec.dense.colors.mean().backward()


def test_ray_aggregation_samples_lie_on_camera_rays():
    pts = torch.tensor([[[0.1, 0.2, 0.05], [-0.2, 0.0, -0.1]]])
    s = virtual_ray_samples(pts, radius=2.7, half_length=0.05, k=5)
    assert s.shape == (1, 4, 2, 5, 3)
    assert torch.allclose(s[:, :, :, 2], pts[:, None].expand(1, 4, 2, 3), atol=1e-6)  # the middle sample is the point
    cams = torch.tensor(model_module.VIRTUAL_CAMERAS) * 2.7
    for c in range(4):
        d = s[0, c] - cams[c]  # (2, 5, 3): collinear with the camera centre
        cross = torch.linalg.cross(d[:, 0:1].expand_as(d), d)
        assert cross.abs().max() < 1e-5
        assert torch.allclose((s[0, c, :, -1] - s[0, c, :, 0]).norm(dim=-1), torch.full((2,), 0.1), atol=1e-5)


def test_nan_and_extreme_inputs_give_finite_gaussians():
    m = small()
    img = torch.rand(3, 3, 64, 64)
    img[0] = float("nan")
    img[1] = 0.0
    img[2, :, :8] = 1e6
    with torch.no_grad():
        rec = m(img)
    for t in (rec.dense.means, rec.dense.scales, rec.dense.opacities, rec.dense.colors, rec.dense.quats, rec.planes):
        assert torch.isfinite(t).all()


def test_spherical_triplane_query_has_finite_gradients_on_its_poles_and_centre():
    from datagen.gans.triplane import SPHERE_ROTATIONS, sample_planes
    planes = torch.randn(1, 2, 3, 4, 8, 8, requires_grad=True)
    # the centre, and points on the polar axes of both spheres (where the angles are undefined)
    axes = torch.tensor(SPHERE_ROTATIONS) @ torch.tensor([0.0, 0.0, 1.0])
    points = torch.cat([torch.zeros(1, 3), 0.3 * axes, -0.2 * axes, torch.rand(4, 3) - 0.5])[None].requires_grad_()
    feats = sample_planes("spherehead", planes, points, box_warp=1.0)
    assert torch.isfinite(feats).all()
    feats.square().sum().backward()
    assert torch.isfinite(points.grad).all() and torch.isfinite(planes.grad).all()


def test_spherehead_decoder_is_frozen_and_sets_box():
    path = gan_fixture("spherehead", ".pkl")
    m = small(spherehead_checkpoint=str(path))
    assert all(not p.requires_grad for p in m.triplane_decoder.parameters())
    assert m.box_warp == 1.0
    rec = m(torch.rand(1, 3, 64, 64))
    c2w, K = front_cameras(1)
    rgb, _ = m.render_triplane(rec.planes, c2w, K, torch.full(c2w.shape[:2], 2.7))
    rgb.mean().backward()
    assert m.triplane.queries.grad is not None and m.triplane.queries.grad.abs().sum() > 0


def test_full_config_builds_with_paper_sizes(monkeypatch):
    cfg = preset("full")
    assert (cfg.encoder, cfg.encoder_layers, cfg.token_dim, cfg.blocks, cfg.heads) == ("dinov2", (5, 12, 18, 24), 512, 8, 16)
    assert (cfg.template_vertices, cfg.triplane_resolution, cfg.ray_samples, cfg.dense_points) == (5023, 64, 32, 10000)
    assert (cfg.coarse_offset_m, cfg.dense_offset_m) == (0.15, 0.056)
    monkeypatch.setattr(model_module, "build_encoder", lambda kind, weights, out_dim, **kw: DinoV2ShapedStub(out_dim))
    m = PanoLAM(cfg)
    assert len(m.template_points) == 5023 and abs(m.dense_count - 10000) / 10000 < 0.05
    assert m.triplane.queries.shape == (6 * 64 * 64, 512)
    assert m.aggregate[0].in_features == 4 * 32 * 32
    assert parameter_count(m) > 20e6


def test_full_config_without_dinov2_weights_is_a_clear_error():
    from panolam.encoder import EncoderError
    with pytest.raises(EncoderError, match="DINOv2"):
        PanoLAM(preset("full"))


def test_config_round_trip_and_errors():
    cfg = preset("tiny+no_c2f+single_point", dense_points=3000)
    assert ModelConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="unknown config"):
        preset("huge")
    with pytest.raises(ValueError, match="unknown ablation"):
        preset("tiny+fast")
    with pytest.raises(ValueError, match="unknown settings"):
        ModelConfig.from_dict({**cfg.to_dict(), "bogus": 1})


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_forward_and_renders_on_cuda_match_the_cpu():
    """The whole forward, the tri-plane render and the splats run on the GPU with no host round trip."""
    m = small()
    img = torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(1))
    c2w, K = front_cameras(1)
    with torch.no_grad():
        rec = m(img)
        ref = m.render_triplane(rec.planes, c2w, K, torch.full((1, 2), 2.7))[0]
        g = m.cuda()
        rec_g = g(img.cuda())
        out = g.render_triplane(rec_g.planes, c2w.cuda(), K.cuda(), torch.full((1, 2), 2.7, device="cuda"))[0]
        rgb, _, _ = render_views(rec_g.dense, c2w.cuda(), K.cuda(), 24)
    assert out.is_cuda and rgb.is_cuda and torch.isfinite(rgb).all()
    assert torch.allclose(out.cpu(), ref, atol=1e-3)
    assert torch.allclose(rec_g.dense.means.cpu(), rec.dense.means, atol=1e-4)
