"""Device placement of the GAN samplers on a simulated accelerator (tests/simdev.py).

Every hot path (mapping, backbone planes, background, ray march, super-resolution) runs with its
tensors on the simulated device, in float32 and in float16: an op that mixes in a host tensor
fails, and reads back to the host are counted against what the design allows. The values are real,
so each run is also compared with the same work on the CPU.
"""
import copy

import numpy as np
import pytest
import torch

from datagen.cameras import named_views
from datagen.gans.checkpoint import read_checkpoint
from datagen.gans.kinds import KINDS
from datagen.gans.triplane import sample_planes
from datagen.generators import gan as gan_module
from tests.conftest import gan_fixture
from tests.simdev import DeviceMismatch, on_device, simulated_device

VIEWS = ["front", "back"]


@pytest.fixture(scope="module", params=KINDS)
def checkpoint(request):
    return read_checkpoint(gan_fixture(request.param, ".pkl"), request.param)


def _heads(checkpoint, device, precision, clip_rays=False, monkeypatch=None):
    """GANHeads on ``device`` (any torch device, the simulated one included), on a copy of the
    checkpoint (GANHeads moves the generator it is given)."""
    monkeypatch.setattr(gan_module, "resolve_device", lambda _name: torch.device(device))
    config = gan_module.GANConfig(precision=precision, clip_rays=clip_rays, device=str(device))
    return gan_module.GANHeads(checkpoint.kind, copy.deepcopy(checkpoint), config)


def _sample(heads, resolution=32):
    subject = heads.sample_subject(5, 2)
    return subject, heads.render(subject, named_views(VIEWS), resolution)


@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_gan_sampling_stays_on_the_device(checkpoint, precision, monkeypatch):
    """fp32 is compared with the CPU; fp16 (the simulated device computes its convolutions in
    float32) checks that the float16 blocks' dtypes and placement flow through."""
    with simulated_device() as (device, mode):
        heads = _heads(checkpoint, device, precision, monkeypatch=monkeypatch)
        assert all(on_device(p) for p in heads.G.parameters())
        subject, views = _sample(heads)
        ws, planes, background = subject.state
        assert on_device(ws) and on_device(planes)
        assert background is None or on_device(background)
        assert planes.dtype == torch.float32
    # No value is read back inside the per-subject or per-view work; what crosses to the host is the
    # subject's w (once) and the three outputs of each render (rgb, alpha, depth).
    assert mode.syncs == []
    assert len(mode.transfers) == 1 + 3
    if precision == "fp16":
        assert heads.fp16 and all(np.isfinite(getattr(views, n)).all() for n in ("rgb", "alpha", "depth"))
        return
    expected_subject, expected = _sample(_heads(checkpoint, "cpu", precision, monkeypatch=monkeypatch))
    np.testing.assert_array_equal(subject.arrays["w"], expected_subject.arrays["w"])
    for name in ("rgb", "alpha", "depth"):
        np.testing.assert_allclose(getattr(views, name), getattr(expected, name), atol=1e-5, rtol=1e-5, err_msg=name)


def test_clipped_rays_sync_once_per_render(monkeypatch):
    """--clip-rays finds the rays that cross the box with one nonzero (a host sync) per render."""
    checkpoint = read_checkpoint(gan_fixture("spherehead", ".pkl"), "spherehead")
    with simulated_device() as (device, mode):
        heads = _heads(checkpoint, device, "fp32", clip_rays=True, monkeypatch=monkeypatch)
        subject = heads.sample_subject(5, 2)
        before = len(mode.syncs)
        heads.render(subject, named_views(VIEWS), 32)
    assert [op.__name__ for op in mode.syncs[before:]] == ["nonzero.default"]


@pytest.mark.parametrize("kind", KINDS)
def test_plane_sampling_forward_and_backward_on_the_device(kind):
    """sample_planes is also PanoLAM's tri-plane branch: gradients must stay on the device."""
    shapes = {"eg3d": (1, 3, 32, 8, 8), "panohead": (1, 3, 32 * 3, 8, 8), "spherehead": (1, 2, 3, 32, 8, 8)}
    with simulated_device(strict_syncs=True) as (device, _mode):
        planes = torch.randn(shapes[kind], device=device, requires_grad=True)
        points = (torch.rand(1, 50, 3, device=device) - 0.5).requires_grad_()
        feats = sample_planes(kind, planes, points, box_warp=1.0)
        feats.square().sum().backward()
        assert on_device(feats) and on_device(planes.grad) and on_device(points.grad)
        assert feats.shape == (1, 3, 50, 32)


def test_the_harness_catches_a_host_constant():
    """The tier's own check: a host matrix in device math fails (SphereHead's first sample crashed so)."""
    host_rotation = torch.eye(3)
    with simulated_device() as (device, _mode):
        points = torch.rand(10, 3, device=device)
        with pytest.raises(DeviceMismatch, match="host tensor of shape \\(3, 3\\)"):
            points @ host_rotation


@pytest.mark.cuda
@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_gan_sampling_on_cuda_matches_the_cpu(checkpoint, precision, monkeypatch):
    """On a real GPU: the same subject as on the CPU (fp32 to float32 rounding; fp16's images and
    masks on average within 1/255, its depth within 0.01 world units)."""
    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA GPU")
    _, expected = _sample(_heads(checkpoint, "cpu", "fp32", monkeypatch=monkeypatch))
    _, views = _sample(_heads(checkpoint, "cuda", precision, monkeypatch=monkeypatch))
    for name in ("rgb", "alpha", "depth"):
        got, want = getattr(views, name), getattr(expected, name)
        if precision == "fp32":
            np.testing.assert_allclose(got, want, atol=1e-4, rtol=1e-4, err_msg=name)
        else:
            assert np.abs(got - want).mean() < (0.01 if name == "depth" else 1 / 255), name
