"""The pure-PyTorch rasterizer on an accelerator, simulated (tests/simdev.py): every tensor stays on
the inputs' device, forward and backward, with the host reads the design allows (per camera one
scalar read and one copy of the per-block list lengths, both in binning, none in the backward
pass: the docstring of :mod:`panolam.rasterizer`); the gsplat fallback; autocast."""
import sys
import warnings
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from datagen.cameras import camera_position, intrinsics, look_at
from panolam import rasterizer
from panolam.gaussians import Gaussians
from panolam.rasterizer import rasterize, render_views
from tests.simdev import on_device, simulated_device
from tests.test_rasterizer import INPUTS, OUTPUTS, camera, random_scene, render, requiring_grad

W, H = 16, 12


def dense_scene(n):
    """Opaque enough that some pixels reach the transmittance stop (the CPU walk drops their blocks
    early, the device walk does not: both must agree)."""
    return random_scene(n, 70, opacity=(0.6, 0.98), scale=(0.05, 0.2), spread=0.15)


def forward_backward(scene, views, Ks):
    """-> (outputs, gradients of INPUTS) of a weighted sum of all outputs."""
    leaves = requiring_grad(scene)
    outputs = render(rasterize, leaves, views, Ks, W, H, tile_size=8, backend="torch")
    loss = sum((o * (i + 1)).sum() for i, o in enumerate(outputs))
    return outputs, torch.autograd.grad(loss, [leaves[k] for k in INPUTS])


@pytest.mark.parametrize("n", [0, 30])
def test_forward_and_backward_stay_on_the_device(n):
    scene = dense_scene(n)
    scene["background"] = torch.stack([scene["background"], 1 - scene["background"]])
    views, Ks = (torch.stack(t) for t in zip(camera(yaw=10.0, width=W, height=H), camera(yaw=-50.0, width=W, height=H)))
    cpu_outputs, cpu_grads = forward_backward(scene, views, Ks)
    if n:
        assert (1 - cpu_outputs[1]).min() < 1e-3  # the stop is reached
    with simulated_device() as (dev, mode):
        leaves = requiring_grad({k: v.to(dev) for k, v in scene.items()})
        outputs = render(rasterize, leaves, views.to(dev), Ks.to(dev), W, H, tile_size=8, backend="torch")
        forward_reads = len(mode.syncs), len(mode.transfers)
        loss = sum((o * (i + 1)).sum() for i, o in enumerate(outputs))
        grads = torch.autograd.grad(loss, [leaves[k] for k in INPUTS])
        assert (len(mode.syncs), len(mode.transfers)) == forward_reads  # the backward pass reads nothing
        assert all(on_device(t) for t in (*outputs, *grads))
        outputs, grads = [t.cpu() for t in outputs], [t.cpu() for t in grads]
    n_cameras = len(views)
    assert forward_reads[0] <= n_cameras and forward_reads[1] <= n_cameras, forward_reads
    for name, a, b in zip(OUTPUTS + INPUTS, [*outputs, *grads], [*cpu_outputs, *cpu_grads]):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12, msg=name)


def test_render_views_on_the_device_with_auto_backend():
    """The training path: a batch of Gaussian sets through ``render_views`` ("auto": no gsplat off CUDA)."""
    scene = {k: v.float() for k, v in random_scene(20, 71).items() if k != "background"}
    g = Gaussians(**{k: v[None] for k, v in scene.items()})
    c2w = torch.from_numpy(look_at(camera_position(np.array([0.0, 120.0]), np.zeros(2), np.full(2, 2.5)))).float()
    K_norm = torch.from_numpy(intrinsics(1.2)).float().expand(1, 2, 3, 3)
    expected = render_views(g, c2w[None], K_norm, W, background=torch.ones(3))
    with simulated_device() as (dev, mode):
        on_dev = Gaussians(**{k: v.to(dev) for k, v in vars(g).items()})
        outputs = render_views(on_dev, c2w[None].to(dev), K_norm.to(dev), W, background=torch.ones(3, device=dev))
        assert all(on_device(o) for o in outputs) and len(mode.syncs) <= 2 and len(mode.transfers) <= 2
        outputs = [o.cpu() for o in outputs]
    for name, a, b in zip(OUTPUTS, outputs, expected):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-6, msg=name)


@pytest.mark.parametrize("gsplat", ["absent", "no kernels", "usable"])
def test_auto_on_cuda_takes_gsplat_only_when_its_kernels_load_and_says_so_once(monkeypatch, gsplat):
    """gsplat absent, or installed where it found no CUDA toolkit to build its kernels (it then
    imports, but every call fails): the pure-PyTorch path, with one warning per process."""
    modules = {"absent": None, "no kernels": SimpleNamespace(_C=None), "usable": SimpleNamespace(_C=object())}
    monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", modules[gsplat])
    if gsplat == "absent":
        monkeypatch.setitem(sys.modules, "gsplat", None)
    rasterizer._say_torch_on_cuda.cache_clear()
    cuda = torch.device("cuda")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert [rasterizer._use_gsplat("auto", cuda) for _ in range(3)] == [gsplat == "usable"] * 3
        assert not rasterizer._use_gsplat("torch", cuda) and not rasterizer._use_gsplat("auto", torch.device("cpu"))
    assert len(caught) == (gsplat != "usable")
    assert all("pure-PyTorch rasterizer" in str(w.message) for w in caught)
    if gsplat == "absent":
        view, K = camera()
        with pytest.raises(ImportError):
            render(rasterize, random_scene(3, 0), view, K, backend="gsplat")


def test_autocast_leaves_the_rasterizer_in_the_inputs_dtype():
    """bf16 autocast (as training uses on CUDA; here the CPU's) must not reach the compositing sums."""
    view, K = camera(torch.float32)
    scene = {k: v.float() for k, v in random_scene(60, 72).items()}
    plain = render(rasterize, scene, view, K, tile_size=8)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        cast = render(rasterize, scene, view, K, tile_size=8)
    for name, a, b in zip(OUTPUTS, cast, plain):
        assert a.dtype == torch.float32
        torch.testing.assert_close(a, b, rtol=0, atol=0, msg=name)
