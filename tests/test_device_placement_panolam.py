"""PanoLAM's device placement, checked without a GPU on the simulated accelerator of :mod:`tests.simdev`.

With the model there, an op that mixes its tensors with a host tensor fails as on CUDA, and reads
from the device are counted. Covered: the encoders, point attention, densification, the tri-plane
branch and the Gaussian heads, forward and backward through the training losses; a training run
(one read from the device per step); checkpoints moving between the CPU and a device; the devices
and process group of data-parallel processes; inference and evaluation. Tests that render with
:func:`flat_render` check PanoLAM's own code apart from the rasterizer, which has device tests of its
own; the tests through the rasterizer run it too.
"""
from __future__ import annotations

import copy
import math
import shutil
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import torch.distributed as dist

from datagen.errors import UserError
from datagen.dataset.manifests import read_manifest
from labeling_tool.compiler import compile_manifest, write_manifest
from panolam import evaluate as evaluate_module
from panolam import infer, launch
from panolam import train as train_module
from panolam.checkpoints import model_from_checkpoint, read_checkpoint
from panolam.config import TrainConfig, preset
from panolam.data import Views
from panolam.launch import process_device
from panolam.metrics import LPIPS
from panolam.train import Perceptual, bf16_autocast, compute_losses, train
from tests.simdev import on_device, simulated_device
from tests.test_model import SMALL, front_cameras, small

MODEL = preset("tiny", **SMALL)
LOSSES = TrainConfig(views_per_sample=3, render_resolution=16)
RUN = TrainConfig(steps=3, batch_size=1, views_per_sample=3, render_resolution=16, warmup_steps=1,
                  checkpoint_every=100, log_every=1, image_every=3)
STAGES = ("encoder", "point_embed", "blocks", "coarse_head", "triplane", "aggregate", "dense_head", "triplane_decoder")


@pytest.fixture
def sim():
    """(device, mode): the simulated accelerator, active for the test."""
    with simulated_device() as (dev, mode):
        yield dev, mode


@pytest.fixture(scope="module")
def cpu_model():
    return small()


def moved(model, device):
    return copy.deepcopy(model).to(device)


def batch_of_views(b: int = 1, res: int = 16) -> Views:
    """b samples of 3 views (input front; targets front and back) with SphereHead planes, on the CPU."""
    c2w, K = front_cameras(b, 2)
    c2w, K = torch.cat([c2w[:, :1], c2w], 1), torch.cat([K[:, :1], K], 1)
    g = torch.Generator().manual_seed(0)
    r, size = MODEL.triplane_resolution, MODEL.image_size
    planes = torch.randn(b, 2, 3, MODEL.triplane_channels, r, r, generator=g)
    return Views("s", torch.rand(b, 3, 3, res, res, generator=g), torch.rand(b, 3, 1, res, res, generator=g), c2w, K,
                 torch.zeros(b, 3), torch.full((b, 3), 2.7), planes, torch.rand(b, 3, size, size, generator=g))


def flat_render(g, cam2world, K_norm, resolution, background=None, backend="auto"):
    """A stand-in for :func:`panolam.rasterizer.render_views` that runs on any device: every pixel of
    a view is the set's mean colour over ``background`` by its mean opacity (the alpha); depth 1. The
    cameras take part, so they must be on the Gaussians' device."""
    b, v = cam2world.shape[:2]
    alpha = (g.opacities.mean(1)[:, None] * cam2world[..., 3, 3] * K_norm[..., 2, 2])[..., None]  # (B, V, 1)
    rgb = alpha * g.colors.mean(1)[:, None] + (1 - alpha) * (0 if background is None else background)
    image = lambda t: t[:, :, None, None].expand(b, v, resolution, resolution, t.shape[-1])  # noqa: E731
    return image(rgb), image(alpha), image(torch.ones_like(alpha))


def host_sums(tensors) -> torch.Tensor:
    """The absolute sum of each tensor, copied to the host in one transfer."""
    return torch.stack([t.detach().abs().sum() for t in tensors]).cpu()


def assert_trained_on_the_device(model):
    """Every stage has gradients, all of them on the device, finite and not all zero."""
    for name in STAGES:
        grads = [p.grad for p in getattr(model, name).parameters() if p.requires_grad]
        assert grads and all(g is not None and on_device(g) for g in grads), name
        sums = host_sums(grads)
        assert torch.isfinite(sums).all() and sums.sum() > 0, name


# -- the network and its losses ----------------------------------------------------------------------------
def test_losses_forward_and_backward_stay_on_the_device_without_a_host_read(sim, cpu_model, monkeypatch):
    """Encoder, point attention, densification, tri-plane branch and its render, Gaussian heads, the
    losses (D-SSIM, masks, SphereHead planes) and their backward, under autocast as on CUDA."""
    dev, mode = sim
    monkeypatch.setattr(train_module, "render_views", flat_render)
    model, batch = moved(cpu_model, dev), batch_of_views().to(dev)
    mode.strict_syncs = True  # a read raises where it happens
    loss, parts, renders = compute_losses(model, batch, LOSSES, Perceptual(LOSSES, dev), autocast=True)
    loss.backward()
    mode.strict_syncs = False
    assert {"l1_dense", "mask_coarse", "l1_triplane", "perceptual_triplane", "planes", "psnr_dense"} <= set(parts)
    assert on_device(loss) and all(on_device(v) for v in (*parts.values(), *renders.values()))
    assert_trained_on_the_device(model)


@pytest.mark.parametrize("ablation", ["no_c2f", "single_point", "no_triplane"])
def test_the_ablations_run_on_the_device(sim, ablation):
    dev, mode = sim
    model = small(f"tiny+{ablation}").to(dev)
    mode.strict_syncs = True
    rec = model(torch.rand(1, 3, 64, 64).to(dev))
    assert on_device(rec.dense.means) and (rec.planes is None) == (ablation == "no_triplane")


def test_lpips_runs_on_the_device(sim):
    dev, mode = sim
    lpips = LPIPS("alex").to(dev)
    pred = torch.rand(2, 3, 64, 64).to(dev).requires_grad_()
    mode.strict_syncs = True
    lpips(pred, torch.rand(2, 3, 64, 64).to(dev)).sum().backward()
    assert on_device(pred.grad)


def test_losses_through_the_rasterizer_on_the_device(sim, cpu_model):
    """The rasterizer reads the device by design (sizes of its per-tile work), so reads are not counted here."""
    dev, mode = sim
    model, batch = moved(cpu_model, dev), batch_of_views().to(dev)
    loss, parts, _ = compute_losses(model, batch, LOSSES, Perceptual(LOSSES, dev))
    loss.backward()
    assert on_device(loss) and all(on_device(v) for v in parts.values())
    assert_trained_on_the_device(model)


def test_bf16_autocast_runs_the_network_in_bf16_with_losses_and_gradients_near_float32(cpu_model):
    """On the CPU, where torch's autocast is real (the simulated device's casts nothing)."""
    assert bf16_autocast("cuda") and bf16_autocast("cuda:1") and bf16_autocast(torch.device("cuda", 0))
    assert not bf16_autocast("cpu") and not bf16_autocast(torch.device("cpu"))
    batch = batch_of_views()
    results = {}
    for autocast in (False, True):
        model = copy.deepcopy(cpu_model)
        seen = []
        model.blocks[0].register_forward_hook(lambda module, args, out: seen.append(out.dtype))
        loss, parts, _ = compute_losses(model, batch, LOSSES, Perceptual(LOSSES, "cpu"), autocast=autocast)
        loss.backward()
        assert seen == [torch.bfloat16 if autocast else torch.float32]
        assert all(v.dtype == torch.float32 for v in parts.values())  # renders and losses stay float32
        grads = [p.grad for p in model.parameters() if p.grad is not None]
        results[autocast] = (float(loss.detach()), float(torch.nn.utils.get_total_norm(grads)))
        assert all(math.isfinite(v) for v in results[autocast])
    (loss32, norm32), (loss16, norm16) = results[False], results[True]
    assert loss16 == pytest.approx(loss32, rel=0.02) and norm16 == pytest.approx(norm32, rel=0.2)


# -- training runs ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def data(tmp_path_factory, tiny_dataset):
    """(dataset, manifest): the shared tiny dataset, one subject held out."""
    root = tmp_path_factory.mktemp("device-data")
    (root / "labels").mkdir()
    manifest = compile_manifest(tiny_dataset, root / "labels", test_count=1)
    return tiny_dataset, write_manifest(manifest, root / "m-v1.json")


@pytest.fixture(scope="module")
def cpu_run(data, tmp_path_factory):
    """A run of ``RUN`` stopped after its first step, trained on the CPU."""
    run = tmp_path_factory.mktemp("device-run") / "run"
    train(*data, MODEL, RUN, run, progress=False, until=1)
    return run


def _counted(mode, fn, counts: dict):
    """``fn`` with the reads from the device it makes added to ``counts`` (syncs, transfers)."""
    def wrapper(*args, **kwargs):
        before = len(mode.syncs), len(mode.transfers)
        try:
            return fn(*args, **kwargs)
        finally:
            counts["syncs"] += len(mode.syncs) - before[0]
            counts["transfers"] += len(mode.transfers) - before[1]
    return wrapper


def test_a_cpu_run_resumes_on_the_device_reading_it_once_per_step_and_comes_back(sim, data, cpu_run, tmp_path,
                                                                                   monkeypatch):
    """Adam's state follows the parameters onto the device; a step reads the device once (its values
    and checks in one transfer), the checkpoint and the TensorBoard image apart; the checkpoint it
    writes holds host tensors."""
    dev, mode = sim
    run = tmp_path / "run"
    shutil.copytree(cpu_run, run)
    monkeypatch.setattr(train_module, "render_views", flat_render)
    saved, apart = [], {"syncs": 0, "transfers": 0}
    real_save = train_module.save_checkpoint

    def save(out, model, optimizer, *args, **kwargs):
        saved.append(list(optimizer.state.values()))
        return real_save(out, model, optimizer, *args, **kwargs)
    monkeypatch.setattr(train_module, "save_checkpoint", _counted(mode, save, apart))
    monkeypatch.setattr(train_module, "_grid", _counted(mode, train_module._grid, apart))
    mode.strict_syncs = True
    entry = train(*data, MODEL, RUN, run, resume=True, device=dev, progress=False)
    mode.strict_syncs = False
    assert entry["step"] == 3 and math.isfinite(entry["loss"])
    (state,) = saved  # the last step's checkpoint
    assert state and all(on_device(s["exp_avg"]) and on_device(s["exp_avg_sq"]) for s in state)
    assert not mode.syncs and apart["transfers"] > 0  # the step-3 image and the checkpoint were copied
    assert len(mode.transfers) - apart["transfers"] == 2  # steps 2 and 3
    ckpt = read_checkpoint(run)
    tensors = [*ckpt["model"].values(), *(t for s in ckpt["optimizer"]["state"].values() for t in s.values())]
    assert all(type(t) is torch.Tensor and t.device.type == "cpu" for t in tensors)
    assert ckpt["step"] == 3 and [h["step"] for h in ckpt["history"]] == [1, 2, 3]


def test_a_checkpoint_written_from_a_gpu_resumes_on_a_machine_without_one(data, cpu_run, tmp_path, monkeypatch):
    """Tensors saved from CUDA are tagged with their device (checkpoints of earlier versions were);
    they are read onto the CPU and the run goes on there."""
    run = tmp_path / "run"
    shutil.copytree(cpu_run, run)
    state = read_checkpoint(run)
    monkeypatch.setattr(torch.serialization, "_package_registry", list(torch.serialization._package_registry))
    torch.serialization.register_package(0, lambda storage: "cuda:0", lambda storage, location: None)
    torch.save(state, run / "checkpoint.pt")
    monkeypatch.undo()
    if not torch.cuda.is_available():
        with pytest.raises(RuntimeError, match="CUDA"):
            torch.load(run / "checkpoint.pt", weights_only=True)  # as written: on the GPU
    assert read_checkpoint(run)["model"]["template_points"].device.type == "cpu"
    model_from_checkpoint(read_checkpoint(run), run)
    assert train(*data, MODEL, RUN, run, resume=True, progress=False, until=2)["step"] == 2


# -- processes -------------------------------------------------------------------------------------------------
def test_each_process_takes_the_gpu_of_its_local_rank():
    assert process_device("cuda", 1, gpus=2) == "cuda:1" and process_device("cpu", 3, gpus=0) == "cpu"
    with pytest.raises(UserError, match="give device cuda"):  # the command line words it --device
        process_device("cuda:1", 0, gpus=2)
    with pytest.raises(UserError, match="needs GPU 2, and it has 2"):
        process_device("cuda", 2, gpus=2)


@pytest.mark.parametrize("torchrun", [False, True])
def test_a_process_binds_its_gpu_before_it_joins_the_nccl_group(torchrun, monkeypatch):
    calls = []
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.setattr(torch.cuda, "set_device", lambda device: calls.append(("set_device", device)))
    monkeypatch.setattr(torch, "set_num_threads", lambda n: None)
    monkeypatch.setattr(dist, "init_process_group", lambda backend, **kw: calls.append(("init", backend, kw)))
    monkeypatch.setattr(dist, "destroy_process_group", lambda: calls.append(("destroy",)))
    monkeypatch.setattr(dist, "get_rank", lambda: 1)
    monkeypatch.setattr(launch.Job, "run", lambda job, device: calls.append(("run", device)))
    for name in ("MASTER_ADDR", "MASTER_PORT", "RANK"):
        monkeypatch.setenv(name, "")
    monkeypatch.setenv("WORLD_SIZE", "2" if torchrun else "1")
    monkeypatch.setenv("LOCAL_RANK", "1")
    job = launch.Job("data", "manifest", "out", False, "cuda", MODEL, RUN)
    if torchrun:
        assert launch.run(job) is None  # rank 1 reports nothing
    else:
        launch._child(1, 2, 29500, job)
    group = {"device_id": torch.device("cuda:1")} if torchrun else {"device_id": torch.device("cuda:1"), "rank": 1,
                                                                     "world_size": 2}
    assert calls == [("set_device", "cuda:1"), ("init", "nccl", group), ("run", "cuda:1"), ("destroy",)]


def test_processes_agree_with_an_all_reduce_on_their_device(sim, monkeypatch):
    dev, mode = sim
    reduced = []
    monkeypatch.setattr(dist, "all_reduce", lambda t, op: reduced.append(t.device))
    assert train_module._agreed(2, dev, True, False) == [True, False] and reduced == [dev]
    assert train_module._agreed(1, dev, False, True) == [False, True] and reduced == [dev]


# -- inference ------------------------------------------------------------------------------------------------
def test_inference_runs_on_the_device_and_copies_each_output_once(sim, cpu_model, tmp_path, monkeypatch):
    dev, mode = sim
    monkeypatch.setattr(infer, "render_views", flat_render)
    model = moved(cpu_model, dev).eval()
    image = np.random.default_rng(0).random((48, 48, 3))
    gaussians, _ = infer.reconstruct(model, image)
    assert on_device(gaussians.means) and not mode.syncs and not mode.transfers
    report = infer.run(model, image, tmp_path / "head.ply", tmp_path / "turn.gif", tmp_path / "views", resolution=16,
                       frames=3)
    assert len(report.written) == 6 and all(p.exists() for p in report.written)
    # One read (the pruning's PSNR); the Gaussians' 5 attributes, the turntable's and the views' frames copied.
    assert len(mode.syncs) == 1 and len(mode.transfers) == 5 + 1 + 1


def test_inference_through_the_rasterizer_on_the_device(sim, cpu_model, tmp_path):
    dev, mode = sim
    model = moved(cpu_model, dev).eval()
    report = infer.run(model, np.random.default_rng(0).random((48, 48, 3)), tmp_path / "head.ply",
                       resolution=16, frames=2)
    assert report.written == [tmp_path / "head.ply"]


def test_evaluation_runs_on_the_device_reading_it_once_per_subject(sim, cpu_model, data, monkeypatch):
    """Metrics in one transfer; the renders and targets for the face tools in another."""
    dev, mode = sim
    monkeypatch.setattr(evaluate_module, "render_views", flat_render)
    monkeypatch.setattr(evaluate_module, "YAW_TOLERANCE", 180.0)  # the tiny dataset has no back view
    faces = SimpleNamespace(csim=lambda a, b, box_from_b: 0.5, apd=lambda a, b, focal: 1.0,
                            csim_between_subjects=lambda images: (0.1, len(images)))
    mode.strict_syncs = True
    result = evaluate_module.evaluate(moved(cpu_model, dev).eval(), data[0], read_manifest(data[1]), faces=faces)
    assert result["subjects"] == 1 and len(result["rows"]) == 4 and len(mode.transfers) == 2


def test_the_dinov2_encoder_runs_on_the_device(sim, tmp_path):
    """The 'full' config's encoder (a frozen DINOv2 and a trained fusion), a tiny one with random weights."""
    import transformers
    from panolam.encoder import DinoV2Encoder
    dev, mode = sim
    config = transformers.Dinov2Config(hidden_size=32, num_hidden_layers=2, num_attention_heads=2,
                                       intermediate_size=64, patch_size=14, image_size=28)
    transformers.Dinov2Model(config).save_pretrained(tmp_path / "dinov2")
    encoder = DinoV2Encoder(tmp_path / "dinov2", layers=(1, 2), out_dim=16, image_size=28).to(dev)
    mode.strict_syncs = True
    tokens = encoder(torch.rand(2, 3, 40, 40).to(dev))
    tokens.square().mean().backward()
    mode.strict_syncs = False
    assert on_device(tokens) and tokens.shape == (2, 4, 16)
    grads = [p.grad for p in encoder.fusion.parameters()]
    assert all(on_device(g) for g in grads) and all(p.grad is None for p in encoder.backbone.parameters())
