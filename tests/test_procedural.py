import numpy as np
import pytest
import torch

from datagen.cameras import ViewSet, named_views, sample_views
from datagen.generators.base import STREAM_CAMERAS, STREAM_LATENT, subject_rng
from datagen.generators.procedural import (DEFECT_TYPES, HAIR_STYLES, ProceduralConfig, ProceduralHeads,
                                           laplace_density, sample_defects, sample_params)

GEN = ProceduralHeads(ProceduralConfig(grid_resolution=64, defect_rate=0.0))
WHITE = np.array([1.0, 1.0, 1.0])


def views(yaw, pitch=0.0, radius=2.7, fov=18.83, pivot=(0.0, 0.0, 0.0)):
    n = len(yaw)
    return ViewSet("test", np.array(yaw, float), np.full(n, float(pitch)), np.full(n, float(radius)),
                   np.full(n, float(fov)), pivot)


@pytest.fixture(scope="module")
def subject():
    return GEN.sample_subject(0, 1)


def assert_clean(out):
    for a in (out.rgb, out.alpha, out.depth):
        assert np.isfinite(a).all()
    assert out.alpha.min() >= 0 and out.alpha.max() <= 1
    assert out.rgb.min() >= 0 and out.rgb.max() <= 1
    assert out.depth.min() >= 0


def test_subjects_are_reproducible_from_seed_and_index():
    a, b = GEN.sample_subject(3, 11), GEN.sample_subject(3, 11)
    assert a.latent == b.latent
    assert torch.equal(a.state.field, b.state.field)
    c = GEN.sample_subject(3, 12)
    assert c.latent != a.latent
    v = named_views(["front", "left"])
    assert np.array_equal(GEN.render(a, v, 32).rgb, GEN.render(b, v, 32).rgb)


def test_subjects_are_diverse():
    params = [sample_params(subject_rng(0, i, STREAM_LATENT)) for i in range(200)]
    styles = {p["hair_style"] for p in params}
    assert styles == set(HAIR_STYLES)
    tones = np.array([np.mean(p["skin_rgb"]) for p in params])
    assert tones.max() - tones.min() > 0.35
    assert 0.08 < np.mean([p["glasses"] for p in params]) < 0.35
    assert 0.04 < np.mean([p["cap"] for p in params]) < 0.25
    assert len({p["hair_colour"] for p in params}) >= 6
    assert any(p["hair_style"] == "long" and p["hair_length"] > 0.3 for p in params)


def test_defect_rate_and_types():
    rng = np.random.default_rng(0)
    p = sample_params(rng)
    hits = sum(bool(sample_defects(rng, 0.04, p)) for _ in range(2000))
    assert 50 <= hits <= 110  # 4 % of 2000 = 80
    kinds = {sample_defects(rng, 1.0, p)[0]["type"] for _ in range(200)}
    assert kinds == set(DEFECT_TYPES)
    assert not any(sample_defects(rng, 0.0, p) for _ in range(200))


def test_truth_is_recorded_apart_from_the_latent():
    gen = ProceduralHeads(ProceduralConfig(grid_resolution=48, defect_rate=1.0))
    s = gen.sample_subject(0, 2)
    assert s.truth["defects"] and s.truth["defects"][0]["type"] in DEFECT_TYPES
    assert "defect" not in repr(s.latent)


def test_head_is_framed_with_background_around(subject):
    out = GEN.render(subject, views([0, 90, 180, 270]), 64)
    assert_clean(out)
    c = 32
    assert (out.alpha[:, c - 4:c + 4, c - 4:c + 4] > 0.99).all()  # the head fills the centre of every view
    corners = out.alpha[:, [0, 0, -1], [0, -1, 0]]
    assert (corners < 1e-3).all()
    np.testing.assert_allclose(out.rgb[:, 0, 0], np.tile(WHITE, (4, 1)), atol=1e-6)
    assert 0.25 < out.alpha.mean() < 0.85
    # The front of the head is between 0.1 and 0.45 units in front of the origin.
    d = out.depth[0, c - 2:c + 2, c - 2:c + 2]
    assert (d > 2.7 - 0.45).all() and (d < 2.7 - 0.1).all()
    assert (out.depth[out.alpha == 0] == 0).all()


def test_alpha_is_binary_inside_and_outside(subject):
    out = GEN.render(subject, views([30]), 64)
    a = out.alpha.ravel()
    assert np.mean((a > 0.01) & (a < 0.99)) < 0.08  # only silhouette pixels are fractional


def test_janus_puts_a_face_on_the_back():
    base = ProceduralHeads(ProceduralConfig(grid_resolution=64, defect_rate=0.0))
    s = base.sample_subject(0, 4)
    janus = base.sample_subject(0, 4)
    from datagen.generators.procedural import bake_head

    janus.state = bake_head(janus.latent["params"], [{"type": "janus"}], 64)
    v = views([0, 180])
    a, b = base.render(s, v, 64), base.render(janus, v, 64)
    front_diff = np.abs(a.rgb[0] - b.rgb[0]).mean()
    back_diff = np.abs(a.rgb[1] - b.rgb[1]).mean()
    assert back_diff > 5 * max(front_diff, 1e-3)


@pytest.mark.parametrize("case", [
    dict(yaw=[0], pitch=90.0), dict(yaw=[0], pitch=-90.0),          # poles
    dict(yaw=[0, 180], radius=0.05), dict(yaw=[45], radius=0.3),    # camera inside the head / the bound
    dict(yaw=[10], radius=1.2), dict(yaw=[10], radius=50.0),        # extreme radius draws
    dict(yaw=[0], fov=0.5), dict(yaw=[0], fov=150.0),               # extreme FOV draws
])
def test_hard_cameras_stay_finite(subject, case):
    out = GEN.render(subject, views(**case), 24)
    assert_clean(out)


def test_grazing_rays_and_camera_looking_away(subject):
    from datagen.cameras import rays
    from datagen.generators import procedural as P

    # Parallel-ish rays skimming the side of the head (camera beside it, looking along -z).
    c2w = np.eye(4)
    c2w[:3, :3] = np.diag([1.0, -1.0, -1.0])
    c2w[:3, 3] = [0.2, 0.0, 2.0]
    K = views([0]).K
    o, d = rays(torch.tensor(c2w[None]), torch.tensor(K), 32)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    t0, t1 = P.box_interval(o, d)
    t, hit = P.sphere_trace(subject.state.sdf, o, d, t0, t1, 0.012)
    assert torch.isfinite(t).all() and 0 < hit.float().mean() < 1
    # Looking away from the head (forward = +z from in front of it): no ray enters the box.
    c2w[:3, :3] = np.diag([-1.0, -1.0, 1.0])
    c2w[:3, 3] = [0.0, 0.0, 2.7]
    o, d = rays(torch.tensor(c2w[None]), torch.tensor(K), 16)
    t0, t1 = P.box_interval(o.reshape(-1, 3), d.reshape(-1, 3))
    assert (t0 >= t1).all()


def test_empty_render_is_background(subject):
    out = GEN.render(subject, views([0], radius=2.7, pivot=(0.0, 3.0, 0.0)), 16)  # looking far above the head
    assert_clean(out)
    assert out.alpha.max() < 1e-6
    np.testing.assert_allclose(out.rgb.reshape(-1, 3), np.tile(WHITE, (256, 1)))


def test_laplace_density_is_finite_for_extreme_distances():
    sdf = torch.tensor([-1e30, -1.0, -1e-9, 0.0, 1e-9, 1.0, 1e30, float("inf"), float("-inf")])
    d = laplace_density(sdf, 0.003)
    assert torch.isfinite(d).all() and (d >= 0).all()
    assert d[0] == pytest.approx(1 / 0.003, rel=1e-6) and d[6] < 1e-20


def test_protocol_views_render(subject):
    v = sample_views("frontal", subject_rng(0, 1, STREAM_CAMERAS), 4)
    out = GEN.render(subject, v, 32)
    assert_clean(out)
    assert out.rgb.shape == (4, 32, 32, 3) and out.alpha.shape == (4, 32, 32)
