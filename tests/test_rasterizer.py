"""The pure-PyTorch Gaussian rasterizer against its brute-force reference, analytic footprints,
finite differences and degenerate inputs; the 3DGS PLY round trip; parity with gsplat on CUDA
when both are available (tests/test_rasterizer_device.py: the same rasterizer on a device)."""
import math

import numpy as np
import pytest
import torch

from datagen.cameras import camera_position, intrinsics, look_at, pixel_intrinsics
from panolam.gaussians import PLY_PROPERTIES, Gaussians, load_ply, save_ply
from panolam.rasterizer import ALPHA_MIN, EPS2D, project, rasterize
from panolam.rasterizer_reference import rasterize_reference

W, H = 32, 24
OUTPUTS = ("rgb", "alpha", "depth")
INPUTS = ("means", "quats", "scales", "opacities", "colors", "background")


def camera(dtype=torch.float64, yaw=25.0, pitch=15.0, radius=2.5, focal=1.2, width=W, height=H):
    """World-to-camera 4x4 of a look-at camera around the origin, and its pixel K."""
    c2w = torch.from_numpy(look_at(camera_position(yaw, pitch, radius)))
    K = pixel_intrinsics(torch.from_numpy(intrinsics(focal)), width, height)
    return torch.linalg.inv(c2w).to(dtype), K.to(dtype)


def random_scene(n, seed, dtype=torch.float64, opacity=(0.05, 0.95), scale=(0.03, 0.2), spread=0.4):
    """n Gaussians around the origin (random rotations, anisotropic scales) and a background."""
    g = torch.Generator().manual_seed(seed)
    uniform = lambda shape, lo, hi: lo + (hi - lo) * torch.rand(shape, generator=g, dtype=dtype)  # noqa: E731
    return dict(
        means=spread * torch.randn(n, 3, generator=g, dtype=dtype),
        quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=dtype), dim=-1),
        scales=torch.exp(uniform((n, 3), math.log(scale[0]), math.log(scale[1]))),
        opacities=uniform((n,), *opacity),
        colors=torch.rand(n, 3, generator=g, dtype=dtype),
        background=torch.rand(3, generator=g, dtype=dtype),
    )


def render(fn, scene, view, K, width=W, height=H, **options):
    s = scene
    return fn(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], view, K, width, height,
              background=s["background"], **options)


def requiring_grad(scene):
    return {k: v.clone().requires_grad_() for k, v in scene.items()}


def assert_finite(*tensors):
    for t in tensors:
        assert torch.isfinite(t).all()


# --------------------------------------------------------------------------------------------
# Forward pass against the brute-force reference


@pytest.mark.parametrize("n, seed, tile_size", [(30, 0, 8), (100, 1, 8), (200, 2, 16), (150, 3, 12), (120, 4, 4)])
def test_forward_matches_reference_float64(n, seed, tile_size):
    view, K = camera()
    scene = random_scene(n, seed)
    fast = render(rasterize, scene, view, K, tile_size=tile_size)
    ref = render(rasterize_reference, scene, view, K, tile_size=tile_size)
    for name, a, b in zip(OUTPUTS, fast, ref):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-10, msg=name)
    assert ref[1].max() > 0.5  # the scene is visible


def test_forward_matches_reference_float32():
    view, K = camera(torch.float32)
    scene = {k: v.float() for k, v in random_scene(150, 5).items()}
    for name, a, b in zip(OUTPUTS, render(rasterize, scene, view, K, tile_size=8),
                          render(rasterize_reference, scene, view, K, tile_size=8)):
        assert a.dtype == torch.float32
        torch.testing.assert_close(a, b, rtol=0, atol=1e-5, msg=name)


def test_dense_opaque_scene_stops_early_and_matches():
    """Many opaque Gaussians: pixels reach the 1e-4 transmittance stop, lists span several steps."""
    view, K = camera()
    scene = random_scene(300, 6, opacity=(0.5, 0.98), scale=(0.05, 0.25), spread=0.25)
    fast = render(rasterize, scene, view, K, tile_size=8)
    ref = render(rasterize_reference, scene, view, K, tile_size=8)
    assert (1.0 - ref[1]).min() < 1e-3
    for name, a, b in zip(OUTPUTS, fast, ref):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-10, msg=name)


@pytest.mark.parametrize("seed", [8, 9])
def test_output_does_not_depend_on_tile_size(seed):
    """gsplat's opacity-aware tile box holds the whole alpha >= 1/255 ellipse of every Gaussian of
    opacity <= 1 (the former 3-sigma box cut opaque ones at tile borders); opacities up to 1."""
    view, K = camera()
    scene = random_scene(150, seed, opacity=(0.05, 1.0), scale=(0.05, 0.4))
    outputs = [render(rasterize, scene, view, K, tile_size=t) for t in (2, 4, 12, 16, 64)]
    for other in outputs[1:]:
        for name, a, b in zip(OUTPUTS, outputs[0], other):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-12, msg=name)


def test_batch_of_cameras_equals_one_by_one():
    views, Ks = zip(camera(yaw=0.0), camera(yaw=70.0, focal=1.5))
    scene = random_scene(60, 7)
    batch = scene | {"background": torch.stack([scene["background"], 1.0 - scene["background"]])}
    together = render(rasterize, batch, torch.stack(views), torch.stack(Ks), tile_size=8)
    for i in range(2):
        alone = render(rasterize, scene | {"background": batch["background"][i]}, views[i], Ks[i], tile_size=8)
        for a, b in zip(together, alone):
            assert a.shape[0] == 2
            torch.testing.assert_close(a[i], b, rtol=0, atol=0)


# --------------------------------------------------------------------------------------------
# Gradients


def loss_weights(outputs, seed=0):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(o.shape, generator=g, dtype=o.dtype) for o in outputs]


def gradients(fn, scene, view, K, weights, **options):
    leaves = requiring_grad(scene)
    outputs = render(fn, leaves, view, K, **options)
    loss = sum((o * w).sum() for o, w in zip(outputs, weights))
    return dict(zip(INPUTS, torch.autograd.grad(loss, [leaves[k] for k in INPUTS])))


@pytest.mark.parametrize("n, seed, tile_size, dense", [(40, 10, 8, False), (150, 11, 16, False), (200, 12, 8, True)])
def test_gradients_match_reference_autograd(n, seed, tile_size, dense):
    """dense: opaque enough for the transmittance stop, several steps per block."""
    view, K = camera()
    scene = random_scene(n, seed, opacity=(0.5, 0.98) if dense else (0.05, 0.95), spread=0.25 if dense else 0.4)
    weights = loss_weights(render(rasterize_reference, scene, view, K, tile_size=tile_size))
    fast = gradients(rasterize, scene, view, K, weights, tile_size=tile_size)
    ref = gradients(rasterize_reference, scene, view, K, weights, tile_size=tile_size)
    for name in INPUTS:
        assert ref[name].abs().max() > 0, name
        torch.testing.assert_close(fast[name], ref[name], rtol=1e-7, atol=1e-9, msg=name)


def test_gradients_float32_close_to_float64():
    view, K = camera()
    scene = random_scene(100, 13)
    weights = loss_weights(render(rasterize, scene, view, K, tile_size=8))
    exact = gradients(rasterize, scene, view, K, weights, tile_size=8)
    single = gradients(rasterize, {k: v.float() for k, v in scene.items()}, view.float(), K.float(),
                       [w.float() for w in weights], tile_size=8)
    for name in INPUTS:
        scale = exact[name].abs().max()
        torch.testing.assert_close(single[name].double(), exact[name], rtol=0, atol=1e-4 * scale, msg=name)


def test_gradcheck_tiny_scene():
    """Finite differences in float64, every input coordinate against three random projections of the
    outputs (one per image; a full Jacobian would need a backward pass per pixel). Opacities stay
    below the 0.999 clamp and well above 1/255, and the scene is too thin for the transmittance stop, so the
    function is smooth at this point."""
    view, K = camera(width=12, height=10, focal=0.9)
    scene = random_scene(4, 21, opacity=(0.3, 0.8), scale=(0.1, 0.3), spread=0.2)
    leaves = requiring_grad(scene)
    weights = loss_weights(render(rasterize, scene, view, K, 12, 10, tile_size=4), seed=1)

    def fn(means, quats, scales, opacities, colors, background):
        outputs = rasterize(means, quats, scales, opacities, colors, view, K, 12, 10, background=background,
                            tile_size=4)
        return tuple((o * w).sum() for o, w in zip(outputs, weights))

    assert torch.autograd.gradcheck(fn, tuple(leaves[k] for k in INPUTS), eps=1e-6, atol=1e-7, rtol=1e-5)


# --------------------------------------------------------------------------------------------
# Analytic footprint


@pytest.mark.parametrize("quat", [(1.0, 0.0, 0.0, 0.0), (0.3, -0.5, 0.7, 0.2)])
def test_isotropic_gaussian_renders_its_analytic_footprint(quat):
    """On the optical axis J = diag(f/z): sigma_px^2 = (f s / z)^2 + 0.3 in every direction."""
    f, z, s, o, size = 100.0, 2.0, 0.06, 0.8, 64
    f64 = lambda x: torch.tensor(x, dtype=torch.float64)  # noqa: E731
    color, bg = f64([0.9, 0.4, 0.1]), f64([0.0, 0.2, 1.0])
    K = f64([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])
    rgb, alpha, depth = rasterize(f64([[0.0, 0.0, z]]), f64([quat]), f64([[s, s, s]]), f64([o]), color[None],
                                  torch.eye(4, dtype=torch.float64), K, size, size, background=bg)
    sigma2 = (f * s / z) ** 2 + EPS2D
    centres = torch.arange(size, dtype=torch.float64) + 0.5 - size / 2
    r2 = centres[:, None] ** 2 + centres[None, :] ** 2
    expected = o * torch.exp(-r2 / (2 * sigma2))
    expected = torch.where(expected >= ALPHA_MIN, expected, 0.0)  # every such pixel lies in its tiles
    torch.testing.assert_close(alpha[..., 0], expected, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(rgb, expected[..., None] * color + (1 - expected[..., None]) * bg)
    torch.testing.assert_close(depth[..., 0], (expected > 0).double() * z)


# --------------------------------------------------------------------------------------------
# Degenerate inputs


def degenerate_scene(dtype=torch.float32):
    """Zero/huge scales, zero quaternion, opacity 0 and 1, behind the camera, at and before the near plane."""
    means = torch.tensor([[0.0, 0.0, 2.0], [0.1, 0.0, 2.0], [0.0, 0.1, 2.0], [-0.1, 0.0, 2.0], [0.0, 0.0, -1.0],
                          [0.0, 0.0, 0.01], [0.0, 0.0, 0.0], [0.05, 0.05, 0.005], [0.0, -0.1, 2.0], [0.0, 0.0, 1e12]],
                         dtype=dtype)
    n = len(means)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n, dtype=dtype)
    quats[2] = 0.0
    scales = torch.full((n, 3), 0.05, dtype=dtype)
    scales[0], scales[1], scales[8] = 0.0, 1e20, torch.tensor([1e-30, 1e6, 0.0])
    opacities = torch.tensor([1.0, 0.3, 0.7, 0.0, 1.0, 0.9, 0.9, 0.9, 0.5, 0.9], dtype=dtype)
    return dict(means=means, quats=quats, scales=scales, opacities=opacities,
                colors=torch.rand(n, 3, generator=torch.Generator().manual_seed(0), dtype=dtype),
                background=torch.tensor([0.1, 0.2, 0.3], dtype=dtype))


def test_degenerate_inputs_give_finite_outputs_and_gradients():
    scene = requiring_grad(degenerate_scene())
    view, K = torch.eye(4), torch.tensor([[40.0, 0.0, 16.0], [0.0, 40.0, 12.0], [0.0, 0.0, 1.0]])
    outputs = render(rasterize, scene, view, K)
    assert_finite(*outputs)
    sum(o.sum() for o in outputs).backward()
    assert_finite(*(scene[k].grad for k in INPUTS))
    # The 1e20-scale Gaussian (opacity 0.3) covers the whole image with alpha 0.3 at least.
    assert outputs[1].min() >= 0.3 - 1e-6


def test_near_plane_is_inclusive_and_behind_is_culled():
    view, K = torch.eye(4, dtype=torch.float64), torch.tensor([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]],
                                                              dtype=torch.float64)
    one = lambda z: dict(means=torch.tensor([[0.0, 0.0, z]], dtype=torch.float64),  # noqa: E731
                         quats=torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
                         scales=torch.full((1, 3), 1e-4, dtype=torch.float64),
                         opacities=torch.tensor([0.5], dtype=torch.float64),
                         colors=torch.ones(1, 3, dtype=torch.float64), background=torch.zeros(3, dtype=torch.float64))
    assert render(rasterize, one(0.01), view, K)[1].max() > 0.1              # z == near_plane: kept
    for z in (0.0099, 0.0, -1.0, 2e10):                                       # before near, behind, beyond far
        rgb, alpha, depth = render(rasterize, one(z), view, K)
        assert alpha.max() == 0 and rgb.max() == 0 and depth.max() == 0, z


@pytest.mark.parametrize("n", [0, 25])
def test_empty_or_transparent_scene_shows_the_background(n):
    scene = random_scene(n, 30, dtype=torch.float32)
    scene["opacities"] = torch.rand(n) * ALPHA_MIN * 0.99                     # below 1/255: never visible
    leaves = requiring_grad(scene)
    view, K = camera(torch.float32)
    rgb, alpha, depth = render(rasterize, leaves, view, K)
    assert rgb.shape == (H, W, 3) and alpha.shape == depth.shape == (H, W, 1)
    assert torch.equal(rgb, leaves["background"].detach().expand(H, W, 3))
    assert alpha.abs().max() == 0 and depth.abs().max() == 0
    (rgb.sum() + alpha.sum() + depth.sum()).backward()
    assert torch.equal(leaves["background"].grad, torch.full((3,), float(H * W)))
    assert all(leaves[k].grad is None or torch.count_nonzero(leaves[k].grad) == 0 for k in INPUTS[:-1])


def test_projection_culls_and_stays_finite():
    scene = degenerate_scene(torch.float64)
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]], dtype=torch.float64)
    proj = project(*(scene[k] for k in ("means", "quats", "scales", "opacities")), torch.eye(4, dtype=torch.float64),
                   K, W, H)
    assert proj.valid.tolist() == [True, True, True, False, False, True, False, False, True, False]
    assert_finite(proj.means2d, proj.conics, proj.depths, proj.log_opacities, proj.radii)


# --------------------------------------------------------------------------------------------
# Numerical stability: needles, non-finite parameters


def needle(length_px, width_px, angle_deg, f=100.0, z=2.0, dtype=torch.float64):
    """One Gaussian on the optical axis whose projected axes are length_px and width_px standard
    deviations, the long one at angle_deg in the image; the third axis is 0 (a flat ellipse)."""
    half = math.radians(angle_deg) / 2
    quats = torch.tensor([[math.cos(half), 0.0, 0.0, math.sin(half)]], dtype=dtype)
    scales = torch.tensor([[length_px * z / f, width_px * z / f, 0.0]], dtype=dtype)
    return torch.tensor([[0.0, 0.0, z]], dtype=dtype), quats, scales


@pytest.mark.parametrize("length", [1e4, 1e6, 1e8, 1e10, 1e12])
def test_covariance_determinant_has_no_cancellation(length):
    """a c - b^2 of a 45 deg needle loses every digit beyond ~1e7 px (and culls it beyond ~1e9)."""
    means, quats, scales = needle(length, 1.5, 45.0)
    K = torch.tensor([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]], dtype=torch.float64)
    proj = project(means, quats, scales, torch.tensor([0.8], dtype=torch.float64), torch.eye(4, dtype=torch.float64),
                   K, 64, 64)
    exact = (length * 1.5) ** 2 + EPS2D * (length ** 2 + 1.5 ** 2) + EPS2D ** 2
    assert proj.valid.item() and float(proj.det2d[0]) == pytest.approx(exact, rel=1e-12)


@pytest.mark.parametrize("length, angle, dtype, atol", [(1e6, 30.0, torch.float64, 1e-9), (1e8, 45.0, torch.float64, 1e-9),
                                                        (1e6, 120.0, torch.float32, 1e-4)])
def test_needle_renders_its_analytic_footprint(length, angle, dtype, atol):
    width, o, size = 1.5, 0.8, 64
    means, quats, scales = needle(length, width, angle, dtype=dtype)
    K = torch.tensor([[100.0, 0, size / 2], [0, 100.0, size / 2], [0, 0, 1]], dtype=dtype)
    _, alpha, _ = rasterize(means, quats, scales, torch.tensor([o], dtype=dtype), torch.ones(1, 3, dtype=dtype),
                            torch.eye(4, dtype=dtype), K, size, size)
    c = torch.arange(size, dtype=torch.float64) + 0.5 - size / 2
    dx, dy = c[None, :], c[:, None]
    t = math.radians(angle)
    along, across = dx * math.cos(t) + dy * math.sin(t), -dx * math.sin(t) + dy * math.cos(t)
    expected = o * torch.exp(-0.5 * (along ** 2 / (length ** 2 + EPS2D) + across ** 2 / (width ** 2 + EPS2D)))
    expected = torch.where(expected >= ALPHA_MIN, expected, 0.0)
    assert expected.max() > 0.79 and (expected == 0).float().mean() > 0.5  # a thin line across the image
    torch.testing.assert_close(alpha[..., 0].double(), expected, rtol=0, atol=atol)


def test_non_finite_gaussians_are_culled_with_zero_gradients():
    """NaN in a mean, a quaternion, an opacity or a colour, an infinite scale: those Gaussians vanish
    and the image and every gradient are those of the others (no NaN through a masked branch)."""
    view, K = camera()
    scene = random_scene(40, 60)
    broken = {k: v.clone() for k, v in scene.items()}
    broken["means"][3, 1] = math.nan
    broken["quats"][7, 0] = math.nan
    broken["scales"][11, 2] = math.inf
    broken["opacities"][13] = math.nan
    broken["colors"][17, 2] = math.nan
    bad = [3, 7, 11, 13, 17]
    good = [i for i in range(40) if i not in bad]
    weights = loss_weights(render(rasterize, scene, view, K, tile_size=8))
    leaves = requiring_grad(broken)
    outputs = render(rasterize, leaves, view, K, tile_size=8)
    sum((o * w).sum() for o, w in zip(outputs, weights)).backward()
    only_good = {k: (v[good] if k != "background" else v) for k, v in scene.items()}
    for a, b in zip(outputs, render(rasterize, only_good, view, K, tile_size=8)):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    for name in INPUTS:
        grad = leaves[name].grad
        assert torch.isfinite(grad).all(), name
        if name != "background":
            assert grad[bad].abs().max() == 0 and grad[good].abs().max() > 0, name


# --------------------------------------------------------------------------------------------
# PLY export


def test_ply_round_trip(tmp_path):
    g = Gaussians(**{k: v.float() for k, v in random_scene(50, 40).items() if k != "background"})
    path = save_ply(tmp_path / "head.ply", g)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["head.ply"]        # no temporary file left
    header = path.read_bytes().split(b"end_header\n")[0].decode().splitlines()
    assert header[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 50"]
    assert header[3:] == [f"property float {p}" for p in PLY_PROPERTIES]
    assert path.stat().st_size == len("\n".join(header)) + len("\nend_header\n") + 50 * 17 * 4
    back = load_ply(path)
    torch.testing.assert_close(back.means, g.means, rtol=0, atol=0)
    torch.testing.assert_close(back.quats, g.quats, rtol=0, atol=1e-6)
    torch.testing.assert_close(back.scales, g.scales, rtol=1e-6, atol=0)
    torch.testing.assert_close(back.opacities, g.opacities, rtol=0, atol=1e-6)
    torch.testing.assert_close(back.colors, g.colors, rtol=0, atol=1e-6)


def test_ply_stores_the_3dgs_raw_values_and_stays_finite_at_extremes(tmp_path):
    g = Gaussians(means=torch.zeros(3, 3), quats=torch.tensor([[2.0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 3.0]]),
                  scales=torch.tensor([[1.0, 0.0, 1e-3]] * 3), opacities=torch.tensor([0.0, 0.5, 1.0]),
                  colors=torch.tensor([[0.5, 0.0, 1.0]] * 3))
    path = save_ply(tmp_path / "x.ply", g)
    raw = np.frombuffer(path.read_bytes().split(b"end_header\n", 1)[1], dtype="<f4").reshape(3, 17)
    assert np.isfinite(raw).all()
    col = {p: raw[:, i] for i, p in enumerate(PLY_PROPERTIES)}
    np.testing.assert_allclose(col["f_dc_0"], 0.0, atol=1e-7)
    np.testing.assert_allclose(col["f_dc_2"], 0.5 / 0.28209479177387814, rtol=1e-6)
    np.testing.assert_allclose(col["opacity"][1], 0.0, atol=1e-7)
    assert col["opacity"][0] < -10 and col["opacity"][2] > 10
    np.testing.assert_allclose(col["scale_2"], math.log(1e-3), rtol=1e-6)
    np.testing.assert_allclose(raw[:, 13:17], [[1, 0, 0, 0], [1, 0, 0, 0], [0, 0, 0, 1]])
    back = load_ply(path)
    assert torch.isfinite(back.scales).all() and back.scales[:, 1].max() < 1e-6
    torch.testing.assert_close(back.opacities, torch.tensor([0.0, 0.5, 1.0]), rtol=0, atol=1e-5)


def test_ply_loader_ignores_extra_properties(tmp_path):
    """Files from other 3DGS tools carry f_rest_* (degree > 0 SH) between f_dc and opacity."""
    g = Gaussians(**{k: v.float() for k, v in random_scene(5, 41).items() if k != "background"})
    path = save_ply(tmp_path / "a.ply", g)
    table = np.frombuffer(path.read_bytes().split(b"end_header\n", 1)[1], dtype="<f4").reshape(5, 17)
    names = list(PLY_PROPERTIES[:9]) + [f"f_rest_{i}" for i in range(9)] + list(PLY_PROPERTIES[9:])
    extended = np.concatenate([table[:, :9], np.ones((5, 9), "<f4"), table[:, 9:]], axis=1)
    header = "ply\nformat binary_little_endian 1.0\ncomment other tool\nelement vertex 5\n"
    header += "".join(f"property float {p}\n" for p in names) + "end_header\n"
    (tmp_path / "b.ply").write_bytes(header.encode() + extended.tobytes())
    a, b = load_ply(path), load_ply(tmp_path / "b.ply")
    for name in ("means", "quats", "scales", "opacities", "colors"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


@pytest.mark.parametrize("text, byte_order", [(True, "="), (False, ">")])
def test_ply_loader_reads_other_encodings_and_elements(tmp_path, text, byte_order):
    """ASCII and big-endian files, a double-precision position and a face element with a list property."""
    from plyfile import PlyData, PlyElement
    g = Gaussians(**{k: v.float() for k, v in random_scene(6, 42).items() if k != "background"})
    ours = save_ply(tmp_path / "ours.ply", g)
    table = np.frombuffer(ours.read_bytes().split(b"end_header\n", 1)[1], dtype="<f4").reshape(6, 17)
    vertex = np.empty(6, dtype=[(p, "f8" if p in "xyz" else "f4") for p in PLY_PROPERTIES])
    for i, p in enumerate(PLY_PROPERTIES):
        vertex[p] = table[:, i]
    face = np.array([([0, 1, 2],), ([3, 4, 5],)], dtype=[("vertex_indices", "i4", (3,))])
    PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(face, "face")], text=text,
            byte_order=byte_order).write(str(tmp_path / "other.ply"))
    a, b = load_ply(ours), load_ply(tmp_path / "other.ply")
    for name in ("means", "quats", "scales", "opacities", "colors"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=0, atol=1e-6, msg=name)
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 5\n")
    with pytest.raises(ValueError, match="not a readable PLY file"):
        load_ply(tmp_path / "bad.ply")


# --------------------------------------------------------------------------------------------
# gsplat


class FakeGsplat:
    """Stands in for the ``gsplat`` module where CUDA is missing: ``rasterization`` as gsplat defines it
    (all cameras at once, ``backgrounds`` composited inside, "RGB+ED" appends the expected depth),
    computed by the pure-PyTorch rasterizer; it records each call's arguments."""

    def __init__(self):
        self.calls = []

    def rasterization(self, means, quats, scales, opacities, colors, viewmats, Ks, width, height, backgrounds=None,
                      render_mode="RGB", **options):
        self.calls.append(dict(cameras=viewmats.shape, backgrounds=None if backgrounds is None else backgrounds.shape,
                               render_mode=render_mode, **options))
        rgb, alpha, depth = rasterize(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                                      backend="torch")
        if backgrounds is not None:
            rgb = rgb + (1 - alpha) * backgrounds[:, None, None, :]
        return torch.cat([rgb, depth], -1), alpha, {}


def test_gsplat_backend_renders_all_cameras_in_one_call_with_its_backgrounds(monkeypatch):
    import sys
    fake = FakeGsplat()
    monkeypatch.setitem(sys.modules, "gsplat", fake)
    views, Ks = zip(camera(yaw=0.0), camera(yaw=70.0, focal=1.5), camera(yaw=-40.0))
    scene = random_scene(60, 7)
    scene["background"] = torch.rand(3, 3, dtype=torch.float64)
    ours = render(rasterize, scene, torch.stack(views), torch.stack(Ks), backend="torch")
    theirs = render(rasterize, scene, torch.stack(views), torch.stack(Ks), backend="gsplat")
    assert len(fake.calls) == 1 and fake.calls[0]["cameras"] == (3, 4, 4) and fake.calls[0]["backgrounds"] == (3, 3)
    assert fake.calls[0]["render_mode"] == "RGB+ED" and fake.calls[0]["eps2d"] == EPS2D
    for a, b in zip(ours, theirs):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    one = render(rasterize, scene | {"background": scene["background"][1]}, views[1], Ks[1], backend="gsplat")
    assert [t.shape for t in one] == [(H, W, 3), (H, W, 1), (H, W, 1)]
    torch.testing.assert_close(one[0], ours[0][1], rtol=0, atol=1e-12)
    from panolam.gaussians import Gaussians
    from panolam.rasterizer import render_views
    fake.calls.clear()
    g = Gaussians(*(torch.stack([scene[k]] * 2).float() for k in ("means", "quats", "scales", "opacities", "colors")))
    c2w = torch.from_numpy(look_at(camera_position(np.array([0.0, 90.0, 180.0, 270.0]), np.zeros(4), np.full(4, 2.5)))).float()
    rgb, _, _ = render_views(g, c2w.expand(2, 4, 4, 4), torch.from_numpy(intrinsics(1.2)).float().expand(2, 4, 3, 3),
                             16, background=torch.ones(3), backend="gsplat")
    assert rgb.shape == (2, 4, 16, 16, 3) and [c["cameras"] for c in fake.calls] == [(4, 4, 4)] * 2


def psnr(a, b) -> float:
    """dB, peak 1."""
    return float(-10.0 * torch.log10((a - b).detach().square().mean()))


@pytest.mark.cuda
def test_torch_backend_matches_gsplat_on_cuda():
    """Both backends on one CUDA scene, opacities up to 1 (so the 0.999 clamp and the full tile box
    matter). The constants are gsplat's, so what differs is float32 rounding (the projection here is
    float64), gsplat's fast exp, and pixels where alpha or the transmittance stop lands on either side
    of its threshold: images at 40 dB PSNR or better, expected depth within 1 % where alpha > 0.5,
    gradients of an RGB + alpha loss at cosine similarity 0.99 or better."""
    if not torch.cuda.is_available():
        pytest.skip("needs CUDA: gsplat rasterizes on CUDA only, so the parity check runs there")
    pytest.importorskip("gsplat", reason="gsplat is not installed (pip install -e '.[cuda]')")
    view, K = camera(torch.float32, width=64, height=48)
    scene = {k: v.float().cuda() for k, v in random_scene(300, 50, opacity=(0.05, 1.0)).items()}
    view, K = view.cuda(), K.cuda()
    weights = [w.cuda() for w in loss_weights([torch.zeros(48, 64, 3), torch.zeros(48, 64, 1)])]
    results = {}
    for backend in ("torch", "gsplat"):
        leaves = requiring_grad(scene)
        rgb, alpha, depth = render(rasterize, leaves, view, K, 64, 48, backend=backend)
        loss = (rgb * weights[0]).sum() + (alpha * weights[1]).sum()
        grads = torch.autograd.grad(loss, [leaves[k] for k in INPUTS[:-1]])
        results[backend] = (rgb, alpha, depth, grads)
    (rgb, alpha, depth, ours), (rgb_g, alpha_g, depth_g, theirs) = results["torch"], results["gsplat"]
    assert alpha_g.max() > 0.9
    assert psnr(rgb, rgb_g) >= 40.0 and psnr(alpha, alpha_g) >= 40.0
    covered = alpha_g > 0.5
    assert ((depth - depth_g).abs() <= 0.01 * depth_g.abs())[covered].all()
    for name, a, b in zip(INPUTS, ours, theirs):
        cosine = torch.nn.functional.cosine_similarity(a.flatten(), b.flatten(), dim=0)
        assert cosine >= 0.99, (name, float(cosine))
