"""3D-GAN generators (EG3D, PanoHead, SphereHead) behind the generator interface.

Per subject (once): z from the subject's seed, w = mapping(z, frontal conditioning) with
truncation, the backbone's planes and (PanoHead/SphereHead) the background. Per call, all rays of
all views are marched in chunks and ToRGB / super-resolution run on batches of views; both sizes
come from a memory budget (:func:`chunk_plan`), so one code path suits a 2-core CPU and a GPU.
The ray range of each view moves with its camera radius. Images come out in [0, 1]; mask and
depth are upsampled from the neural rendering resolution to the output size. Everything stays on
the device until the views are returned; every random number is drawn on the CPU from the
subject's seed, so a dataset does not depend on the device's random generator or the budget.
"""
from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ..cameras import (EG3D_FOCAL, ViewSet, camera_position, conditioning_vector, intrinsics, look_at,
                       protocol_pivot, rays)
from ..device import resolve_device
from ..gans.checkpoint import LoadedCheckpoint, read_checkpoint
from ..render import render_rays_chunked
from .settings import NAMED_COLOURS, NOT_RECORDED, GANConfig
from .base import STREAM_LATENT, STREAM_RENDER, Generator, RenderedViews, Subject, subject_rng

BACKGROUNDS = ("own", "black", "white", "grey")
# Working memory for one chunk of rays or one batch of super-resolved views, per device type.
# CPU: small batches keep the activations in cache (measured in benchmarks/gan_speed.py);
# CUDA: a quarter of the device's memory.
CPU_BUDGET_MB = 64
CUDA_BUDGET_FRACTION = 0.25
# Ray chunks are whole multiples of this (measured: the decoder's matrix products then give the same
# bits for every ray whatever the chunk size). Super-resolution batches hold at least two views; the
# convolution kernels MKL-DNN picks depend on the batch size, so on some CPUs (AMD EPYC, AVX2) two
# batch sizes differ in the last bits of the image (measured: at most 2e-6 on [0, 1]).
CHUNK_RAYS_QUANTUM = 1024
MIN_SR_BATCH = 2




@dataclass(frozen=True)
class ChunkPlan:
    """How one render call splits its work: rays per march chunk, views per super-resolution batch."""

    rays: int
    images: int


def chunk_plan(G, budget_bytes: float, fp16: bool) -> ChunkPlan:
    """Chunk sizes that keep the largest temporaries of each stage within ``budget_bytes``.

    March: per sample, the sampled plane features (two spheres for SphereHead), their mean, the
    decoder's hidden and output activations and the merge's sorted copies, float32. Super-
    resolution: about five live activations of its largest block per view.
    """
    rk = G.rendering_kwargs
    samples = rk["depth_resolution"] + rk["depth_resolution_importance"]
    per_sample = 4 * (G.spec.sampled_planes * 32 + 32 + 2 * 64 + 3 * 33)
    rays = max(1, int(budget_bytes // (per_sample * samples * CHUNK_RAYS_QUANTUM))) * CHUNK_RAYS_QUANTUM
    sr = G.superresolution
    (ch0, ch1), res1 = sr.variant.channels, sr.variant.output_resolution
    res0 = sr.input_resolution * (2 if sr.variant.block0_upsamples else 1)
    per_image = 5 * max(ch0 * res0 ** 2, ch1 * res1 ** 2) * (2 if fp16 else 4)
    return ChunkPlan(rays=rays, images=max(MIN_SR_BATCH, int(budget_bytes // per_image)))


def _solid(background):
    return NAMED_COLOURS.get(background, background) if background != "own" else None


class GANHeads(Generator):
    """``checkpoint``: an official checkpoint file, or a :class:`LoadedCheckpoint` already in memory."""

    def __init__(self, kind: str, checkpoint, config: GANConfig = GANConfig()):
        self.name = kind
        self.config = config
        self.device = resolve_device(config.device)
        loaded = checkpoint if isinstance(checkpoint, LoadedCheckpoint) else read_checkpoint(checkpoint, kind)
        self.checkpoint = loaded
        self.G = loaded.generator.to(self.device)
        self.G.precision = config.precision
        self.fp16 = self.G.fp16(torch.empty(0, device=self.device))
        self.plan = chunk_plan(self.G, self.budget_bytes(), self.fp16)
        self.pivot = protocol_pivot(self.G.spec.protocol)

    def budget_bytes(self) -> float:
        if self.config.memory_budget_mb:
            return self.config.memory_budget_mb * 2 ** 20
        if self.device.type == "cuda":
            return CUDA_BUDGET_FRACTION * torch.cuda.get_device_properties(self.device).total_memory
        return CPU_BUDGET_MB * 2 ** 20

    def describe(self) -> dict:
        ck = self.checkpoint
        cfg = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self.config).items()
               if k not in NOT_RECORDED}
        cfg.update(neural_rendering_resolution=ck.neural_rendering_resolution, image_resolution=self.G.img_resolution,
                   ray_start=ck.rendering_kwargs["ray_start"], ray_end=ck.rendering_kwargs["ray_end"],
                   precision="fp16" if self.fp16 else "fp32")
        if cfg["background"] != "own":
            cfg["background"] = list(_solid(self.config.background))
        return {"name": self.name, "checkpoint": ck.path.rsplit("/", 1)[-1], "checkpoint_sha256": ck.sha256,
                "config": cfg}

    def conditioning(self) -> torch.Tensor:
        """The frontal camera the mapping network is conditioned on (as the official samplers do)."""
        radius = self.checkpoint.rendering_kwargs.get("avg_camera_radius", 2.7)
        c2w = look_at(camera_position(0.0, 0.0, radius), self.pivot)
        return torch.tensor(conditioning_vector(c2w, intrinsics(EG3D_FOCAL)), dtype=torch.float32)[None]

    @torch.no_grad()
    def sample_subject(self, dataset_seed: int, index: int) -> Subject:
        cfg = self.config
        rng = subject_rng(dataset_seed, index, STREAM_LATENT)
        z = rng.standard_normal(self.G.z_dim).astype(np.float32)
        gen = torch.Generator().manual_seed(int(rng.integers(2 ** 62)))
        c = self.conditioning()
        ws = self.G.mapping(torch.from_numpy(z)[None].to(self.device), c.to(self.device),
                            cfg.truncation_psi, cfg.truncation_cutoff)
        planes = self.G.planes(ws, cfg.noise_mode, gen)
        background = self.G.background(ws, cfg.noise_mode, gen)
        arrays = {"z": z, "w": ws[0, 0].cpu().numpy()}
        if cfg.save_planes:
            arrays["planes"] = self._planes_fp16(planes, cfg.save_planes)
        latent = {"truncation_psi": cfg.truncation_psi, "truncation_cutoff": cfg.truncation_cutoff,
                  "noise_mode": cfg.noise_mode, "conditioning": c[0].tolist(), "arrays": sorted(arrays)}
        return Subject(index=index, seed=dataset_seed, latent=latent, state=(ws, planes, background), arrays=arrays)

    @staticmethod
    def _planes_fp16(planes: torch.Tensor, res: int) -> np.ndarray:
        lead, (h, w) = planes.shape[:-2], planes.shape[-2:]
        flat = planes.reshape(-1, 1, h, w)
        if (h, w) != (res, res):
            flat = F.interpolate(flat, size=(res, res), mode="bilinear", align_corners=False, antialias=res < h)
        return flat.reshape(*lead[1:], res, res).to(torch.float16).cpu().numpy()

    @torch.no_grad()
    def render(self, subject: Subject, views: ViewSet, resolution: int) -> RenderedViews:
        cfg, plan, dev = self.config, self.plan, self.device
        ws, planes, background = subject.state
        G, rk = self.G, self.checkpoint.rendering_kwargs
        nrr = self.checkpoint.neural_rendering_resolution
        gen = torch.Generator().manual_seed(int(subject_rng(subject.seed, subject.index, STREAM_RENDER).integers(2 ** 62)))
        origins, dirs = rays(torch.tensor(views.cam2world, dtype=torch.float32, device=dev), views.K, nrr)
        V, R = origins.shape[:2]
        shift = torch.tensor(views.radius - rk.get("avg_camera_radius", 2.7), dtype=torch.float32, device=dev)
        start = (rk["ray_start"] + shift).repeat_interleave(R)
        end = (rk["ray_end"] + shift).repeat_interleave(R)
        settings = dataclasses.replace(G.render_settings(cfg.deterministic), chunk_rays=plan.rays)
        feats, depth, weights = render_rays_chunked(G.field(planes), origins.reshape(-1, 3), dirs.reshape(-1, 3),
                                                    start, end, settings, gen,
                                                    box=G.content_box() if cfg.clip_rays else None)
        out_rgb, out_alpha, out_depth = [], [], []
        solid = _solid(cfg.background)
        for first, last in sr_batches(V, plan.images):
            sl = slice(first * R, last * R)
            out = G.compose(ws, feats[sl], depth[sl, None], weights[sl, None], nrr, background, cfg.noise_mode, gen)
            rgb = ((out["image"].clamp(-1, 1) + 1) / 2).float()
            alpha = weights[sl].reshape(-1, 1, nrr, nrr).clamp(0, 1)
            z = _resize_depth(out["image_depth"], alpha, resolution)
            rgb, alpha = _resize(rgb, resolution), _resize(alpha, resolution)
            if solid is not None:
                bg = torch.tensor(solid, dtype=rgb.dtype, device=dev).view(1, 3, 1, 1)
                rgb = rgb * alpha + bg * (1 - alpha)
            out_rgb.append(rgb.permute(0, 2, 3, 1))
            out_alpha.append(alpha[:, 0])
            out_depth.append(z[:, 0])
        return RenderedViews(rgb=torch.cat(out_rgb).cpu().numpy(), alpha=torch.cat(out_alpha).cpu().numpy(),
                             depth=torch.cat(out_depth).cpu().numpy())


def sr_batches(n_views: int, size: int) -> list:
    """(first, last) view ranges of at most ``size`` views; a lone last view joins the batch before it."""
    bounds = list(range(0, n_views, size)) + [n_views]
    if len(bounds) > 2 and bounds[-1] - bounds[-2] < MIN_SR_BATCH:
        del bounds[-2]
    return list(zip(bounds[:-1], bounds[1:]))


def _resize(x: torch.Tensor, res: int) -> torch.Tensor:
    if x.shape[-1] == res:
        return x
    return F.interpolate(x, size=(res, res), mode="bilinear", align_corners=False, antialias=res < x.shape[-1])


def _resize_depth(depth: torch.Tensor, alpha: torch.Tensor, res: int) -> torch.Tensor:
    """Depth resized with the mask as weight, so background depth never bleeds in; 0 where alpha is 0."""
    a = _resize(alpha, depth.shape[-1]) if alpha.shape[-1] != depth.shape[-1] else alpha
    num, den = _resize(depth * a, res), _resize(a, res)
    return torch.where(den > 1e-6, num / den.clamp(min=1e-6), torch.zeros_like(den))
