"""PSNR, SSIM (against scikit-image), D-SSIM and LPIPS built from random weights saved in the
torchvision / lpips file layouts (the real weights cannot be downloaded here)."""
import math

import pytest
import torch

from panolam.metrics import (ARCHS, LPIPS, PSNR_MAX_DB, TAPS, MetricError, dssim_loss, load_lpips,
                             psnr, ssim)


def images(b=2, c=3, h=40, w=48, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, c, h, w, generator=g, dtype=dtype)


def test_psnr_values_cap_and_mask():
    x = images()
    assert torch.allclose(psnr(torch.zeros(1, 3, 4, 4), torch.full((1, 3, 4, 4), 0.1)), torch.tensor([20.0]))
    same = psnr(x, x)
    assert torch.equal(same, torch.full((2,), PSNR_MAX_DB, dtype=x.dtype))
    y = x.clone()
    y[:, :, :, 24:] = 0.5  # only the right half differs
    mask = torch.zeros(2, 40, 48, dtype=torch.bool)
    mask[:, :, :24] = True
    assert torch.equal(psnr(x, y, mask), same)
    assert torch.allclose(psnr(x, y, mask[:, None].float()), same)
    empty = psnr(x, y, torch.zeros_like(mask))
    assert torch.isnan(empty).all()
    with pytest.raises(ValueError, match="B, C, H, W"):
        psnr(x[0], y[0])
    skm = pytest.importorskip("skimage.metrics", reason="scikit-image is the reference PSNR")
    noisy = (x + 0.05 * torch.randn(x.shape, generator=torch.Generator().manual_seed(3), dtype=x.dtype)).clamp(0, 1)
    expected = [skm.peak_signal_noise_ratio(a.numpy(), b.numpy(), data_range=1) for a, b in zip(x, noisy)]
    torch.testing.assert_close(psnr(noisy, x), torch.tensor(expected, dtype=x.dtype), rtol=1e-6, atol=0)


def test_ssim_matches_skimage_gaussian():
    skm = pytest.importorskip("skimage.metrics", reason="scikit-image is needed for the reference SSIM")
    x = images(seed=1)
    y = (0.7 * x + 0.3 * images(seed=2)).clamp(0, 1)
    ours = ssim(x, y)
    for i in range(2):
        ref = skm.structural_similarity(x[i].permute(1, 2, 0).numpy(), y[i].permute(1, 2, 0).numpy(),
                                        gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                        data_range=1, channel_axis=2)
        assert abs(ours[i].item() - ref) < 1e-4
    # float32 input agrees with the float64 result
    assert torch.allclose(ssim(x.float(), y.float()).double(), ours, atol=1e-4)


def test_masked_ssim_averages_the_map_over_the_mask_only():
    skm = pytest.importorskip("skimage.metrics", reason="scikit-image is needed for the reference SSIM map")
    x = images(seed=4)
    y = x.clone()
    y[:, :, :, 30:] = (0.5 * y[:, :, :, 30:] + 0.25)  # the right part differs, the left part is identical
    mask = torch.zeros(2, 1, 40, 48)
    mask[..., :20] = 1
    assert torch.allclose(ssim(x, y, mask), torch.ones(2, dtype=x.dtype))  # 20 + 5 < 30: windows see x = y only
    assert torch.allclose(ssim(x, y, torch.ones(2, 40, 48)), ssim(x, y))
    mask[..., 25:] = 1
    _, full = skm.structural_similarity(x[0].permute(1, 2, 0).numpy(), y[0].permute(1, 2, 0).numpy(),
                                        gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                        data_range=1, channel_axis=2, full=True)
    keep = mask[0, 0, 5:-5, 5:-5].numpy() > 0
    expected = full[5:-5, 5:-5][keep].mean()
    assert abs(ssim(x, y, mask)[0].item() - expected) < 1e-4 and ssim(x, y, mask)[0] < 0.99
    assert torch.isnan(ssim(x, y, torch.zeros(2, 40, 48))).all()


def test_ssim_identity_gradient_and_small_images():
    x = images(b=1)
    assert torch.allclose(ssim(x, x), torch.ones(1, dtype=x.dtype))
    y = images(b=1, seed=3).requires_grad_(True)
    loss = dssim_loss(y, x)
    loss.backward()
    assert 0 < loss.item() < 1 and torch.isfinite(y.grad).all() and y.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="11x11"):
        ssim(x[..., :10, :], x[..., :10, :])


def save_random_weights(tmp_path, net, seed=0):
    """Random backbone and lin weights, saved with torchvision's and lpips' key names."""
    g = torch.Generator().manual_seed(seed)
    backbone, cin = {}, None
    for i, spec in enumerate(ARCHS[net]):
        if spec != "relu" and spec[0] == "conv":
            _, cin, cout, k, _, _ = spec
            backbone[f"features.{i}.weight"] = torch.randn(cout, cin, k, k, generator=g) * math.sqrt(2 / (cin * k * k))
            backbone[f"features.{i}.bias"] = 0.01 * torch.randn(cout, generator=g)
    backbone["classifier.1.weight"] = torch.randn(4, 4, generator=g)  # present in torchvision's files, unused
    lin = {f"lin{j}.model.1.weight": torch.rand(1, ARCHS[net][t - 1][2], 1, 1, generator=g)
           for j, t in enumerate(TAPS[net])}
    bpath, lpath = tmp_path / f"{net}-backbone.pth", tmp_path / f"{net}-lin.pth"
    torch.save(backbone, bpath)
    torch.save(lin, lpath)
    return bpath, lpath


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_properties(tmp_path, net):
    model = load_lpips(*save_random_weights(tmp_path, net), net=net)
    x, y = images(b=2, h=64, w=64, seed=4, dtype=torch.float32), images(b=2, h=64, w=64, seed=5, dtype=torch.float32)
    assert torch.equal(model(x, x), torch.zeros(2))
    d = model(x, y)
    assert d.shape == (2,) and (d > 0).all()
    assert torch.allclose(d, model(y, x))
    assert (model(x, (x + 0.02).clamp(0, 1)) < d).all()
    y.requires_grad_(True)
    model(x, y).sum().backward()
    assert torch.isfinite(y.grad).all() and y.grad.abs().sum() > 0
    assert not any(p.requires_grad for p in model.parameters())


def test_lpips_loads_exact_weights(tmp_path):
    bpath, lpath = save_random_weights(tmp_path, "alex", seed=7)
    model = load_lpips(bpath, lpath, net="alex")
    assert torch.equal(model.features[3].weight, torch.load(bpath)["features.3.weight"])
    assert torch.equal(model.lins[4].weight, torch.load(lpath)["lin4.model.1.weight"])


def test_lpips_missing_and_mismatched_files(tmp_path):
    a_back, a_lin = save_random_weights(tmp_path, "alex")
    v_back, v_lin = save_random_weights(tmp_path, "vgg")
    with pytest.raises(MetricError, match="not found.*alexnet-owt-7be5be79.pth.*alex.pth"):
        load_lpips(tmp_path / "nope.pth", a_lin)
    with pytest.raises(MetricError, match="needs lin weights too"):
        load_lpips(a_back, None)
    with pytest.raises(MetricError, match="not the alex weights"):
        load_lpips(v_back, a_lin, net="alex")
    with pytest.raises(MetricError, match="not the vgg weights"):
        load_lpips(v_back, a_lin, net="vgg")
    with pytest.raises(MetricError, match="no 'features.0.weight'"):
        load_lpips(a_lin, a_lin)
    bad = tmp_path / "truncated.pth"
    bad.write_bytes(a_back.read_bytes()[:100])
    with pytest.raises(MetricError, match="cannot read LPIPS backbone"):
        load_lpips(bad, a_lin)
    with pytest.raises(ValueError, match="must be one of"):
        load_lpips(a_back, a_lin, net="squeeze")
    assert load_lpips(v_back, v_lin, net="vgg").net == "vgg"


def test_lpips_rejects_non_rgb():
    with pytest.raises(ValueError, match="RGB"):
        LPIPS()(torch.rand(1, 1, 64, 64), torch.rand(1, 1, 64, 64))

