"""Training on a curated manifest: losses of the paper, exact resume, data parallel over processes.

Per sample, N_v views of one subject: the first is the input (drawn from the frontal views or from
any, ``input_views``), and the renders are supervised on all N_v views or on the others
(``targets``; :mod:`panolam.data`). Loss (paper Eq. 9): ``lambda_3 L_rgb(G) + lambda_4 L_rgb(ST) + lambda_5 L_mask
+ lambda_6 L_st`` with ``L_rgb = lambda_1 L1 + lambda_2 L_perceptual`` on the coarse and dense
Gaussian renders (G) and on the tri-plane branch's own render (ST, over black at its resolution,
of the first ``triplane_render_views`` targets: the views are drawn at random, so any few are a fair
sample, and this volume render costs more than all the Gaussian renders together),
``L_mask`` the L1 of coarse and dense alpha against the masks, ``L_st`` the L1 between the
predicted planes and the GAN's planes when the dataset stores them (``--save-planes``). The
perceptual term is LPIPS when its weights are given, otherwise D-SSIM ``(1 - SSIM) / 2`` (the log
says which).

Optimizer: Adam, linear warm-up then cosine decay to ``lr_floor`` of the peak (over the steps, or
fitted to ``--time-limit``: :class:`Schedule`), gradient-norm clipping; bf16 autocast of the
network on CUDA (:func:`bf16_autocast`; renders and losses stay float32). A step reads from the
device once, after the update: the loss, its parts, the gradient norm and the largest parameter (a
non-finite loss, gradient or parameter stops the run before anything is saved); several processes
then agree on stopping in one small all-reduce. A checkpoint (:mod:`panolam.checkpoints`) holds
model, optimizer, scheduler, RNG states, step, both configs and what the run trains on (manifest
and dataset hashes, the training subjects); since the data order is a pure function of (seed,
sample index), resuming continues exactly, also on another kind of device, and a resume with
another manifest is refused. Several processes (:mod:`panolam.launch`) average gradients with
torch.distributed (gloo on CPU, nccl on CUDA); each takes its own slice of every global batch.
"""
from __future__ import annotations

import contextlib
import math
import time
from pathlib import Path
from typing import Optional

import torch
import torch.distributed as dist
import torch.nn.functional as F

from datagen.command_line import progress_bar
from datagen.device import constant
from datagen.errors import SettingError, UserError
from datagen.files import sha256_file
from datagen.dataset.manifests import read_manifest

from .checkpoints import CHECKPOINT, read_checkpoint, same_model_config, save_checkpoint
from .config import ModelConfig, TrainConfig
from .data import BACKGROUND, TrainingSamples, Views, collate, resized
from .metrics import dssim_loss, psnr
from .model import PanoLAM, Reconstruction
from .rasterizer import render_views

STEP_TIMES_KEPT = 5  # the time limit predicts the next step from the slowest of this many recent ones


class TrainingError(UserError, RuntimeError):
    """Training cannot go on (non-finite loss, incompatible checkpoint)."""


# -- losses ---------------------------------------------------------------------------------------------
class Perceptual:
    """LPIPS when its weights are given, else D-SSIM; called on (N, 3, H, W) in [0, 1]."""

    def __init__(self, cfg: TrainConfig, device):
        self.lpips = None
        if cfg.lpips_backbone or cfg.lpips_lin:
            from .metrics import load_lpips
            self.lpips = load_lpips(cfg.lpips_backbone, cfg.lpips_lin, net=cfg.lpips_net).to(device).eval()
            self.lpips.requires_grad_(False)
        self.name = f"LPIPS-{cfg.lpips_net}" if self.lpips is not None else "D-SSIM (no LPIPS weights given)"

    def __call__(self, pred, target):
        if self.lpips is not None:
            return self.lpips(pred, target).mean()
        return dssim_loss(pred, target)


def _flat(x: torch.Tensor) -> torch.Tensor:
    return x.reshape(-1, *x.shape[-3:])


def _channels_first(x: torch.Tensor) -> torch.Tensor:
    """(B, V, H, W, C) renders -> (B, V, C, H, W)."""
    return x.permute(0, 1, 4, 2, 3)


def bf16_autocast(device) -> bool:
    """Whether training on ``device`` (a torch.device or its name) runs the network under bf16 autocast:
    on CUDA, where bf16 matrix products are several times faster; elsewhere float32 (CPU bf16 is
    slower than float32 on most CPUs)."""
    return torch.device(device).type == "cuda"


def compute_losses(model: PanoLAM, batch: Views, cfg: TrainConfig, perceptual: Perceptual, autocast: bool = False):
    """Forward the inputs (under bf16 autocast when ``autocast``), render the targets in float32;
    returns (total loss, named parts, renders for logging)."""
    core = model.module if hasattr(model, "module") else model
    inputs = batch.inputs if batch.inputs is not None else batch.images[:, 0]
    first = first_target(cfg)
    targets, masks = batch.images[:, first:], batch.masks[:, first:]
    cam2world, K = batch.cam2world[:, first:], batch.K[:, first:]
    with torch.autocast(inputs.device.type, dtype=torch.bfloat16, enabled=autocast):
        rec: Reconstruction = model(inputs)
    res = cfg.render_resolution
    bg = constant(BACKGROUND, inputs.device)
    parts, renders = {}, {}
    rgb_terms = []
    for name, g in (("dense", rec.dense), ("coarse", rec.coarse)):
        if g is None:
            continue
        rgb, alpha, _ = render_views(g.to(torch.float32), cam2world, K, res, background=bg, backend=cfg.rasterizer)
        rgb, alpha = _channels_first(rgb), _channels_first(alpha)
        renders[name] = rgb
        parts[f"l1_{name}"] = (rgb - targets).abs().mean()
        parts[f"perceptual_{name}"] = perceptual(_flat(rgb), _flat(targets))
        parts[f"mask_{name}"] = (alpha - masks).abs().mean()
        rgb_terms.append(cfg.lambda_l1 * parts[f"l1_{name}"] + cfg.lambda_perceptual * parts[f"perceptual_{name}"])
    total = cfg.lambda_gaussians * sum(rgb_terms)
    total = total + cfg.lambda_mask * sum(v for k, v in parts.items() if k.startswith("mask_"))
    if rec.planes is not None:
        planes = rec.planes.float()
        r, n = core.cfg.triplane_render_resolution, core.cfg.triplane_render_views
        # the first n views after the input: drawn at random, whatever the targets of the Gaussian renders
        rgb_t, _ = core.render_triplane(planes, batch.cam2world[:, 1:][:, :n], batch.K[:, 1:][:, :n],
                                        batch.radius[:, 1:][:, :n], r)
        premultiplied = _flat(batch.images[:, 1:][:, :n] - (1 - batch.masks[:, 1:][:, :n]) * bg.view(1, 1, 3, 1, 1))
        target_t = F.interpolate(premultiplied, size=(r, r), mode="area").view_as(rgb_t)
        parts["l1_triplane"] = (rgb_t - target_t).abs().mean()
        parts["perceptual_triplane"] = perceptual(_flat(rgb_t).clamp(0, 1), _flat(target_t).clamp(0, 1))
        total = total + cfg.lambda_triplane_rgb * (cfg.lambda_l1 * parts["l1_triplane"] +
                                                   cfg.lambda_perceptual * parts["perceptual_triplane"])
        renders["triplane"] = rgb_t
        if batch.planes is not None and batch.planes.shape[:4] == planes.shape[:4]:
            gan = batch.planes.to(planes).flatten(0, 2)  # SphereHead's (B, 2, 3, C, R, R) -> (B 2 3, C, R, R)
            gan = F.interpolate(gan, size=planes.shape[-2:], mode="area").view_as(planes)
            parts["planes"] = (planes - gan).abs().mean()
            total = total + cfg.lambda_planes * parts["planes"]
    with torch.no_grad():
        parts["psnr_dense"] = psnr(_flat(renders["dense"]).clamp(0, 1), _flat(targets)).mean()
    return total, parts, renders


# -- schedule --------------------------------------------------------------------------------
def first_target(cfg: TrainConfig) -> int:
    """Index of the first supervised view of a sample: 0 (the input view among the targets) or 1."""
    return 0 if cfg.targets == "all" else 1


def steps_share(step: int, cfg: TrainConfig) -> float:
    """The share of the steps after warm-up that ``step`` has done (the decay's progress without a time limit)."""
    return (step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps)


def lr_factor(step: int, cfg: TrainConfig, progress: Optional[float] = None) -> float:
    """Linear warm-up to 1 over ``cfg.warmup_steps``, then cosine decay to ``cfg.lr_floor`` as
    ``progress`` goes from 0 to 1 (default: the share of the steps after warm-up done)."""
    if step < cfg.warmup_steps:
        return (step + 1) / cfg.warmup_steps
    if progress is None:
        progress = steps_share(step, cfg)
    return cfg.lr_floor + (1 - cfg.lr_floor) * 0.5 * (1 + math.cos(math.pi * min(1.0, progress)))


class Schedule:
    """The learning-rate factor of a run, fitted to its time limit.

    The decay's progress is the larger of the steps' share and, with a time limit (``deadline``, a
    ``time.monotonic()``), the time's: from where the decay stood when it started in this process
    (after warm-up, or at the resumed step) to 1 at the deadline. So ``--time-limit`` alone, with
    more ``--steps`` than fit, still ends at the floor; without a limit the schedule is the steps'
    and a resumed run continues it exactly. ``progress`` never goes back (it is kept in the
    checkpoint), so resuming a time-limited run, with or without a new limit, continues its decay.
    Processes agree on the time's share (:meth:`time_progress`, then :meth:`advance`) before the
    scheduler reads :meth:`factor`, so they all take the same learning rate.
    """

    def __init__(self, cfg: TrainConfig, deadline: Optional[float] = None, progress: float = 0.0, clock=time.monotonic):
        self.cfg, self.deadline, self.progress, self.clock = cfg, deadline, progress, clock
        self.decay_start: Optional[tuple[float, float]] = None  # (time, progress) the decay started at here

    def time_progress(self, step: int) -> float:
        """Where the time limit puts the decay for ``step`` (0 without a limit and during warm-up)."""
        if self.deadline is None or step < self.cfg.warmup_steps:
            return 0.0
        now = self.clock()
        if self.decay_start is None:
            self.decay_start = (now, self.progress)
        t0, p0 = self.decay_start
        return 1.0 if self.deadline <= t0 else p0 + (1 - p0) * (now - t0) / (self.deadline - t0)

    def advance(self, progress: float) -> None:
        self.progress = min(1.0, max(self.progress, progress))

    def factor(self, step: int) -> float:
        """The factor of ``step`` (LambdaLR's function): warm-up, then the decay at the progress reached."""
        if step >= self.cfg.warmup_steps:
            self.advance(steps_share(step, self.cfg))
        return lr_factor(step, self.cfg, self.progress)


def training_data(dataset: TrainingSamples, manifest) -> dict:
    """The identity of a run's training data: manifest and dataset hashes, the training subjects."""
    m = read_manifest(manifest)
    return {"manifest": str(manifest), "manifest_version": m["header"].get("version"),
            "manifest_sha256": sha256_file(manifest),
            "dataset_index_sha256": m["header"].get("dataset_index_sha256"),
            "subjects": [key for key, _ in dataset.subjects]}


# -- the loop -----------------------------------------------------------------------------------------------
def _distributed() -> tuple[int, int]:
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def check_start(data, manifest, model_cfg: ModelConfig, cfg: TrainConfig, out, resume: bool):
    """What a run checks before it starts (UserError on a mistake, nothing written).

    Returns the checkpoint to resume (or None), the training samples and the data identity.
    """
    out = Path(out)
    state = None
    if resume:
        state = read_checkpoint(out)
        if not same_model_config(state["model_config"], model_cfg.to_dict()):
            raise UserError(f"{out}: the checkpoint was trained with config {state['model_config']['name']!r}; "
                            f"resume with the same config")
    elif (out / CHECKPOINT).exists():
        raise SettingError(f"{out} already holds a run; pass "
                           "{resume} to continue it or choose another {out}")
    dataset = TrainingSamples(data, manifest, "train", cfg.views_per_sample, cfg.render_resolution, cfg.seed,
                              input_resolution=model_cfg.image_size, input_views=cfg.input_views)
    data_info = training_data(dataset, manifest)
    if state is not None and state.get("data", {}).get("manifest_sha256") not in (None, data_info["manifest_sha256"]):
        raise UserError(f"{out}: this run trains on manifest {state['data'].get('manifest_version')!r} "
                        f"({state['data'].get('manifest')}); resume it with that manifest")
    return state, dataset, data_info


def _agreed(world: int, device: torch.device, *values: float) -> list[float]:
    """Each value's maximum over the processes (the values themselves with a single process): flags
    (true on any process) and the time limit's share of the schedule. With several, one all-reduce on
    ``device`` (NCCL reduces CUDA tensors only) and its read, taken right after the step's read,
    when the device has nothing else queued."""
    if world == 1:
        return [float(v) for v in values]
    t = torch.tensor([float(v) for v in values], device=device, dtype=torch.float64)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return t.cpu().tolist()


def sample_indices(step: int, cfg: TrainConfig, rank: int, world: int) -> list[int]:
    """Global sample indices of this process's share of the global batch at ``step``."""
    first = (step * world + rank) * cfg.batch_size
    return list(range(first, first + cfg.batch_size))


class _Steps(torch.utils.data.Sampler):
    def __init__(self, start: int, cfg: TrainConfig, rank: int, world: int):
        self.start, self.cfg, self.rank, self.world = start, cfg, rank, world

    def __iter__(self):
        for step in range(self.start, self.cfg.steps):
            yield sample_indices(step, self.cfg, self.rank, self.world)

    def __len__(self):
        return max(0, self.cfg.steps - self.start)


def train(data, manifest, model_cfg: ModelConfig, cfg: TrainConfig, out, resume: bool = False,
          device="cpu", progress: bool = True, until: Optional[int] = None,
          started: Optional[float] = None) -> dict:
    """Train (or resume) a run in ``out`` on ``device`` (a torch.device or its name; this process's
    own GPU under torch.distributed); returns the final log entry. Rank 0 writes files.

    ``until``: stop (with a checkpoint) after this step without changing the schedule, which is set
    by ``cfg.steps``; resuming then continues exactly (used to evaluate a run part way).
    ``started``: the ``time.monotonic()`` the time limit counts from (default: now), e.g. when the
    command started. Before each step the run predicts when it would end (the slowest of the last
    few steps, and the last checkpoint's write) and stops with a checkpoint instead of overrunning;
    the first step always runs.
    """
    rank, world = _distributed()
    out, device = Path(out), torch.device(device)
    started = time.monotonic() if started is None else started
    torch.manual_seed(cfg.seed)
    state, dataset, data_info = check_start(data, manifest, model_cfg, cfg, out, resume)
    model = PanoLAM(model_cfg).to(device)
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(params, lr=cfg.lr, betas=cfg.betas)
    schedule = Schedule(cfg, None if cfg.time_limit_s is None else started + cfg.time_limit_s,
                        state.get("schedule_progress", 0.0) if state is not None else 0.0)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, schedule.factor)
    step, history = 0, []
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        torch.set_rng_state(state["rng"])
        step, history = state["step"], state["history"]
    if world > 1:
        model = torch.nn.parallel.DistributedDataParallel(model, device_ids=[device] if device.type == "cuda" else None)
    perceptual = Perceptual(cfg, device)
    loader = torch.utils.data.DataLoader(dataset, batch_sampler=_Steps(step, cfg, rank, world), collate_fn=collate,
                                         num_workers=cfg.num_workers)
    writer = _writer(out) if rank == 0 else None
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        _log_text(out, f"perceptual loss: {perceptual.name}; {len(dataset)} training subjects; "
                       f"{world} process(es); start at step {step}")
    shown = progress and rank == 0  # a progress bar, else each logged step echoed
    bar = progress_bar(cfg.steps, "step", "train", shown, initial=step)
    clock = _Clock(started, cfg.time_limit_s)
    entry, start = {}, step
    model.train()
    ready = time.perf_counter()
    for batch in _batches(loader):
        data_s = time.perf_counter() - ready  # waiting for the loader (decoding, resizing), apart from the step
        batch = batch.to(device)
        t0 = time.perf_counter()
        loss, parts, renders = compute_losses(model, batch, cfg, perceptual, autocast=bf16_autocast(device))
        if step == start and rank == 0:
            _log_text(out, "tri-plane feature loss (lambda_6): " + (
                "on (the dataset stores SphereHead planes)" if "planes" in parts else
                "off (no SphereHead planes of this layout in the dataset, or no tri-plane branch)"))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)  # of the averaged gradients: agreed
        lr = scheduler.get_last_lr()[0]
        _update(optimizer, step, lr)
        updated = torch.nn.utils.get_total_norm([p.detach() for p in params], float("inf"))
        # The step's one read from the device: the loss, its parts, the gradient norm and the largest
        # parameter after the update, copied to the host together.
        loss_v, norm_v, updated_v, *part_v = torch.stack([loss.detach().float(), grad_norm.float(), updated.float(),
                                                          *(v.detach().float() for v in parts.values())]).cpu().tolist()
        # Every process takes the same decisions: a bad loss anywhere or the time limit stops them all.
        bad_loss, out_of_time, time_progress = _agreed(world, device, not math.isfinite(loss_v),
                                                       clock.next_step_overruns(), schedule.time_progress(step + 1))
        if bad_loss:
            bad = ", ".join(f"{k}={v:.4g}" for k, v in zip(parts, part_v))
            raise TrainingError(f"non-finite loss at step {step} (subjects {batch.key} on process {rank}): {bad}")
        if not math.isfinite(norm_v):
            raise TrainingError(f"non-finite gradient at step {step} (subjects {batch.key} on process {rank}); "
                                f"the last checkpoint is intact")
        if not math.isfinite(updated_v):
            raise TrainingError(f"{_update_failed(step, lr)}: parameters are no longer finite; the last checkpoint "
                                f"is intact")
        schedule.advance(time_progress)
        scheduler.step()
        step += 1
        entry = {"step": step, "loss": loss_v, "lr": lr, "grad_norm": norm_v,
                 "seconds": time.perf_counter() - t0, "data_s": data_s, **dict(zip(parts, part_v))}
        history.append(entry)
        bar.update(1)
        bar.set_postfix(loss=f"{entry['loss']:.4f}", psnr=f"{entry['psnr_dense']:.2f}")
        if writer is not None:
            logged = step % cfg.log_every == 0 or step == cfg.steps
            _log_text(out, f"step {step}: loss {entry['loss']:.4f}, PSNR {entry['psnr_dense']:.2f} dB, "
                           f"lr {entry['lr']:.2e}, {entry['seconds']:.2f} s/step, {data_s:.3f} s data",
                      echo=logged and not shown)
            if logged:
                for k, v in entry.items():
                    if k != "step":
                        writer.add_scalar(f"train/{k}", v, step)
            if step % cfg.image_every == 0 or step == 1:
                writer.add_image("train/input|dense|coarse|target", _grid(batch, renders, first_target(cfg)), step)
        stop = out_of_time or (until is not None and step >= until)
        if rank == 0 and (step % cfg.checkpoint_every == 0 or step == cfg.steps or stop):
            with clock.checkpoint():
                save_checkpoint(out, model, optimizer, scheduler, step, model_cfg, cfg, history, data_info,
                                schedule_progress=schedule.progress)
        if stop:
            if out_of_time and rank == 0:
                _log_text(out, f"stopped at step {step}: another step would end after the {cfg.time_limit_s:g} s "
                               f"time limit; --resume continues", echo=not shown)
            break
        ready = time.perf_counter()
    bar.close()
    if writer is not None:
        writer.close()
    return entry


def _batches(loader):
    """The loader's batches; a UserError raised in a loader worker keeps its one line (torch re-raises
    it in this process with the worker's traceback appended)."""
    batches = iter(loader)
    while True:
        try:
            batch = next(batches)
        except StopIteration:
            return
        except UserError as e:
            lines = str(e).strip().splitlines()
            if len(lines) > 1:  # "...Traceback...", last line "module.Type: message"
                raise type(e)(lines[-1].partition(": ")[2] or lines[-1]) from None
            raise
        yield batch


def _update_failed(step: int, lr: float) -> str:
    return f"non-finite update at step {step} (learning rate {lr:.3g})"


def _update(optimizer, step: int, lr: float) -> None:
    """The optimizer step; a TrainingError when it cannot be taken (a learning rate too large for
    float32, say: the checkpoint on disk is still the last good one). Whether it left every
    parameter finite is read with the step's other values."""
    try:
        optimizer.step()
    except RuntimeError as e:
        if "overflow" not in str(e):
            raise
        raise TrainingError(f"{_update_failed(step, lr)}: the step overflows float32; the last checkpoint is "
                            f"intact") from None


class _Clock:
    """The time limit: whether one more step and the checkpoint after it would end past it.

    A step's time runs from one call of :meth:`next_step_overruns` to the next (loading, forward,
    backward, update, logging), without the checkpoint writes in between, which count apart.
    """

    def __init__(self, started: float, limit_s: Optional[float]):
        self.deadline = None if limit_s is None else started + limit_s
        self.last = time.monotonic()
        self.steps: list[float] = []
        self.checkpoint_s = 0.0  # the last checkpoint write
        self.writing_s = 0.0     # checkpoint writes since the last call

    def next_step_overruns(self) -> bool:
        """Called once per step: records the step's duration and predicts the end of the next one."""
        now = time.monotonic()
        self.steps = (self.steps + [now - self.last - self.writing_s])[-STEP_TIMES_KEPT:]
        self.last, self.writing_s = now, 0.0
        return self.deadline is not None and now + max(self.steps) + self.checkpoint_s > self.deadline

    @contextlib.contextmanager
    def checkpoint(self):
        t0 = time.monotonic()
        yield
        self.checkpoint_s = time.monotonic() - t0
        self.writing_s += self.checkpoint_s


def _grid(batch: Views, renders: dict, first: int) -> torch.Tensor:
    """One image (3, H, W): rows input | dense | coarse | target for the first sample's targets (views ``first:``)."""
    targets = batch.images[0, first:]
    size = targets.shape[-1]
    inp = resized(batch.images[:1, 0], size).expand(len(targets), -1, -1, -1)
    rows = [inp, renders["dense"][0]] + ([renders["coarse"][0]] if "coarse" in renders else []) + [targets]
    rows = [torch.cat(list(r.detach().float().clamp(0, 1).cpu()), dim=-1) for r in rows]
    return torch.cat(rows, dim=-2)


def _writer(out: Path):
    from torch.utils.tensorboard import SummaryWriter
    return SummaryWriter(str(out / "tb"))


def _log_text(out: Path, line: str, echo: bool = True) -> None:
    """Append a line to ``out/train.log`` (and print it); an OSError names the log."""
    path = out / "train.log"
    try:
        with open(path, "a") as f:
            f.write(line + "\n")
    except OSError as e:
        raise OSError(e.errno, e.strerror, str(path)) from None
    if echo:
        print(line, flush=True)


