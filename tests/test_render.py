import math

import pytest
import torch

from datagen.render import RenderSettings, march, render_rays, render_rays_chunked, sample_pdf, sample_stratified

RADIUS = 0.5


def sphere_field(density=200.0):
    """A solid sphere of radius 0.5 at the origin; colour = position-independent red."""
    def field(pts, dirs):
        inside = pts.norm(dim=-1, keepdim=True) < RADIUS
        rgb = torch.tensor([1.0, 0.0, 0.0]).expand(*pts.shape[:-1], 3)
        return rgb, torch.where(inside, torch.tensor(density), torch.tensor(0.0))
    return field


def empty_field(pts, dirs):
    return torch.zeros(*pts.shape[:-1], 3), torch.zeros(*pts.shape[:-1], 1)


def frontal_rays(n=64, offset_max=0.8):
    """Parallel rays from z=2 toward -z, with x offsets from 0 to offset_max."""
    x = torch.linspace(0.0, offset_max, n)
    origins = torch.stack([x, torch.zeros(n), torch.full((n,), 2.0)], -1)[None]
    dirs = torch.tensor([0.0, 0.0, -1.0]).expand(1, n, 3).contiguous()
    return origins, dirs, x


DET = RenderSettings(64, 64, "none", deterministic=True)


def test_sphere_alpha_and_depth_are_exact():
    origins, dirs, x = frontal_rays()
    rgb, depth, alpha = render_rays(sphere_field(), origins, dirs, 1.0, 3.0, DET)
    inside = x < RADIUS - 0.02
    outside = x > RADIUS + 0.02
    assert torch.all(alpha[0, inside, 0] > 0.999)
    assert torch.all(alpha[0, outside, 0] < 1e-6)
    true_depth = 2.0 - torch.sqrt((RADIUS ** 2 - x[inside] ** 2).clamp(min=0))
    assert torch.allclose(depth[0, inside, 0], true_depth, atol=0.02)
    assert torch.allclose(rgb[0, inside], torch.tensor([1.0, 0.0, 0.0]), atol=1e-3)


def test_midpoint_features_converge_to_the_field_features_and_beat_them_at_few_samples():
    """A colour ramp along z through a soft slab: features looked up at interval midpoints agree
    with the field's own at many samples, and are closer to that reference at few."""
    def ramp(pts):
        return torch.stack([pts[..., 2], 1 - pts[..., 2], torch.ones_like(pts[..., 2])], -1)

    def field(pts, dirs):
        return ramp(pts), 30.0 * torch.sigmoid((0.3 - pts[..., 2:3].abs()) * 40.0)

    def no_features(pts, dirs):
        return pts.new_zeros(*pts.shape[:-1], 0), field(pts, dirs)[1]

    origins, dirs, _ = frontal_rays(8)
    ref = render_rays(field, origins, dirs, 1.0, 3.0, RenderSettings(256, 0, "none", deterministic=True))[0]
    many = RenderSettings(256, 0, "none", deterministic=True)
    mid = render_rays(no_features, origins, dirs, 1.0, 3.0, many, features=ramp)[0]
    assert torch.allclose(mid, ref, atol=1e-3)
    few = RenderSettings(4, 4, "none", deterministic=True)
    err_ends = (render_rays(field, origins, dirs, 1.0, 3.0, few)[0] - ref).abs().max()
    out, depth, alpha = render_rays(no_features, origins, dirs, 1.0, 3.0, few, features=ramp)
    assert out.shape == (1, 8, 3) and torch.isfinite(out).all()
    assert (out - ref).abs().max() < err_ends
    chunked = RenderSettings(4, 4, "none", deterministic=True, chunk_rays=3)
    f, _, _ = render_rays_chunked(no_features, origins[0], dirs[0], 1.0, 3.0, chunked, features=ramp, box=1.0)
    assert torch.allclose(f, out[0], atol=1e-6)
    away = origins[0] + torch.tensor([5.0, 0.0, 0.0])  # every ray misses the box
    f, _, a = render_rays_chunked(no_features, away, dirs[0], 1.0, 3.0, chunked, features=ramp, box=1.0)
    assert f.shape == (8, 3) and not f.any() and not a.any()


def test_importance_samples_concentrate_at_the_surface():
    origins, dirs, _ = frontal_rays(1, 0.0)
    settings = RenderSettings(32, 32, "none", deterministic=True)
    depths = sample_stratified(1.0, 3.0, 32, (1, 1), True)
    feats, dens = sphere_field()(origins[:, :, None] + depths * dirs[:, :, None], None)
    _, _, w = march(feats, dens.reshape(1, 1, 32, 1), depths, "none")
    from datagen.render import sample_importance

    fine = sample_importance(depths, w, 32, True)
    near_surface = ((fine - 1.5).abs() < 0.15).float().mean()
    assert near_surface > 0.5, settings


def test_deterministic_mode_ignores_global_rng():
    origins, dirs, _ = frontal_rays()
    torch.manual_seed(0)
    a = render_rays(sphere_field(), origins, dirs, 1.0, 3.0, RenderSettings(16, 16, "none", deterministic=True))
    torch.manual_seed(123)
    b = render_rays(sphere_field(), origins, dirs, 1.0, 3.0, RenderSettings(16, 16, "none", deterministic=True))
    for x, y in zip(a, b):
        assert torch.equal(x, y)


def test_jitter_comes_only_from_the_given_generator():
    origins, dirs, _ = frontal_rays()
    s = RenderSettings(16, 16, "none", deterministic=False)
    a = render_rays(sphere_field(), origins, dirs, 1.0, 3.0, s, torch.Generator().manual_seed(1))
    torch.manual_seed(99)
    b = render_rays(sphere_field(), origins, dirs, 1.0, 3.0, s, torch.Generator().manual_seed(1))
    c = render_rays(sphere_field(), origins, dirs, 1.0, 3.0, s, torch.Generator().manual_seed(2))
    assert torch.equal(a[1], b[1])
    assert not torch.equal(a[1], c[1])


def test_deterministic_stratified_samples_are_bin_starts():
    d = sample_stratified(2.25, 3.3, 12, (1, 2), True)
    assert torch.allclose(d[0, 0, :, 0], torch.linspace(2.25, 3.3, 12))
    assert d[0, 1, -1, 0] == pytest.approx(3.3)
    per_ray = sample_stratified(torch.tensor([[1.0], [2.0]]), torch.tensor([[2.0], [4.0]]), 5, (1, 2), True)
    assert torch.allclose(per_ray[0, 1, :, 0], torch.linspace(2.0, 4.0, 5))


def test_sample_pdf_uniform_weights_give_even_samples():
    bins = torch.linspace(0, 1, 11)[None]
    s = sample_pdf(bins, torch.ones(1, 10), 5, deterministic=True)
    assert torch.allclose(s, torch.linspace(0, 1, 5)[None], atol=1e-4)
    r = sample_pdf(bins, torch.rand(4, 10).expand(1, 4, 10)[0][:1], 50, deterministic=False,
                   generator=torch.Generator().manual_seed(0))
    assert r.min() >= 0 and r.max() <= 1


def test_empty_space_renders_transparent_without_nan():
    origins, dirs, _ = frontal_rays()
    for activation in ("none", "softplus"):
        rgb, depth, alpha = render_rays(empty_field, origins, dirs, 1.0, 3.0,
                                        RenderSettings(8, 8, activation, deterministic=True))
        assert torch.isfinite(rgb).all() and torch.isfinite(depth).all() and torch.isfinite(alpha).all()
        if activation == "none":
            assert alpha.abs().max() == 0 and rgb.abs().max() == 0
        assert depth.min() >= 1.0 and depth.max() <= 3.0


@pytest.mark.parametrize("density", [1e-30, 1e6, 1e30, float("inf")])
def test_extreme_densities_stay_finite(density):
    origins, dirs, _ = frontal_rays(16)
    rgb, depth, alpha = render_rays(sphere_field(density), origins, dirs, 1.0, 3.0,
                                    RenderSettings(8, 8, "none", deterministic=True))
    assert torch.isfinite(rgb).all() and torch.isfinite(depth).all() and torch.isfinite(alpha).all()
    assert alpha.min() >= 0 and alpha.max() <= 1.0 + 1e-6


@pytest.mark.parametrize("density", [200.0, float("inf")])
def test_zero_length_ray_range_is_finite(density):
    origins, dirs, _ = frontal_rays(8)
    out = render_rays(sphere_field(density), origins, dirs, 1.5, 1.5, RenderSettings(8, 8, "none", deterministic=True))
    assert all(torch.isfinite(t).all() for t in out)


def test_nan_density_from_a_field_does_not_reach_the_output():
    def bad(pts, dirs):
        return torch.zeros(*pts.shape[:-1], 3), torch.full((*pts.shape[:-1], 1), float("nan"))
    origins, dirs, _ = frontal_rays(8)
    out = render_rays(bad, origins, dirs, 1.0, 3.0, RenderSettings(8, 8, "none", deterministic=True))
    assert all(torch.isfinite(t).all() for t in out)


def test_chunked_equals_unchunked():
    origins, dirs, _ = frontal_rays(100)
    s_full = RenderSettings(16, 16, "softplus", deterministic=True, chunk_rays=1000)
    s_chunk = RenderSettings(16, 16, "softplus", deterministic=True, chunk_rays=7)
    start = torch.full((100,), 1.0)
    end = torch.linspace(2.5, 3.0, 100)
    a = render_rays_chunked(sphere_field(5.0), origins[0], dirs[0], start, end, s_full)
    b = render_rays_chunked(sphere_field(5.0), origins[0], dirs[0], start, end, s_chunk)
    for x, y in zip(a, b):
        assert torch.allclose(x, y, atol=1e-6)


def test_softplus_activation_matches_eg3d():
    depths = torch.tensor([0.0, 1.0]).reshape(1, 1, 2, 1)
    dens = torch.full((1, 1, 2, 1), 2.0)
    feats = torch.ones(1, 1, 2, 1)
    _, _, w = march(feats, dens, depths, "softplus")
    assert w.item() == pytest.approx(1 - math.exp(-math.log1p(math.e)), rel=1e-5)
