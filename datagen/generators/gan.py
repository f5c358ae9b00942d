"""3D-GAN generators (EG3D, PanoHead, SphereHead) behind the generator interface.

Per subject (once): z from the subject's seed, w = mapping(z, frontal conditioning) with
truncation, the backbone's planes and (PanoHead/SphereHead) the background. Per batch of views:
all rays of all views are rendered as one flat, chunked batch through the shared volume renderer
at the checkpoint's neural rendering resolution, then ToRGB / super-resolution run per view.
The ray range of each view moves with its camera radius. Images come out in [0, 1]; mask and
depth are upsampled from the neural rendering resolution to the output size.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ..cameras import (EG3D_FOCAL, EG3D_PIVOT, HEAD360_PIVOT, ViewSet, camera_position, conditioning_vector,
                       intrinsics, look_at, rays)
from ..gans.checkpoint import read_checkpoint
from ..render import render_rays_chunked
from .base import STREAM_LATENT, STREAM_RENDER, Generator, RenderedViews, Subject, subject_rng

BACKGROUNDS = ("own", "black", "white", "grey")


@dataclass(frozen=True)
class GANConfig:
    """truncation_cutoff None = all layers. background: 'own' (the GAN's own: EG3D black,
    PanoHead/SphereHead their generated background) or a solid colour composited with the mask.
    save_planes: resolution at which the plane features are stored in fp16 (0 = not stored)."""

    truncation_psi: float = 0.7
    truncation_cutoff: int | None = 14
    background: object = "own"
    save_planes: int = 0
    deterministic: bool = False
    noise_mode: str = "const"
    device: str = "auto"
    chunk_rays: int = 1 << 14


def _solid(background):
    named = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0), "grey": (0.5, 0.5, 0.5)}
    return named.get(background, background) if background != "own" else None


class GANHeads(Generator):
    def __init__(self, kind: str, checkpoint: str, config: GANConfig = GANConfig()):
        self.name = kind
        self.config = config
        loaded = read_checkpoint(checkpoint, kind)
        self.checkpoint = loaded
        if config.device == "auto":
            self.device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
        else:
            self.device = torch.device(config.device)
        self.G = loaded.generator.to(self.device)
        self.pivot = EG3D_PIVOT if kind == "eg3d" else HEAD360_PIVOT

    def describe(self) -> dict:
        ck = self.checkpoint
        cfg = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self.config).items() if k != "device"}
        cfg.update(neural_rendering_resolution=ck.neural_rendering_resolution, image_resolution=self.G.img_resolution,
                   ray_start=ck.rendering_kwargs["ray_start"], ray_end=ck.rendering_kwargs["ray_end"])
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
        gen = torch.Generator(device=self.device).manual_seed(int(rng.integers(2 ** 62)))
        ws = self.G.mapping(torch.from_numpy(z)[None].to(self.device), self.conditioning().to(self.device),
                            cfg.truncation_psi, cfg.truncation_cutoff)
        planes = self.G.planes(ws, cfg.noise_mode, gen)
        background = self.G.background(ws, cfg.noise_mode, gen) if self.name != "eg3d" else None
        arrays = {"z": z, "w": ws[0, 0].cpu().numpy()}
        if cfg.save_planes:
            arrays["planes"] = self._planes_fp16(planes, cfg.save_planes)
        latent = {"truncation_psi": cfg.truncation_psi, "truncation_cutoff": cfg.truncation_cutoff,
                  "noise_mode": cfg.noise_mode, "conditioning": self.conditioning()[0].tolist(),
                  "arrays": sorted(arrays)}
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
        cfg = self.config
        ws, planes, background = subject.state
        G, rk = self.G, self.checkpoint.rendering_kwargs
        nrr = self.checkpoint.neural_rendering_resolution
        gen = torch.Generator(device=self.device).manual_seed(
            int(subject_rng(subject.seed, subject.index, STREAM_RENDER).integers(2 ** 62)))
        origins, dirs = rays(views.cam2world, views.K, nrr)
        V, R = origins.shape[:2]
        shift = torch.tensor(views.radius - rk.get("avg_camera_radius", 2.7), dtype=torch.float32)
        start = (rk["ray_start"] + shift).repeat_interleave(R).to(self.device)
        end = (rk["ray_end"] + shift).repeat_interleave(R).to(self.device)
        settings = G.render_settings(cfg.deterministic)
        settings = type(settings)(**{**asdict(settings), "chunk_rays": cfg.chunk_rays})
        feats, depth, weights = render_rays_chunked(G.field(planes), origins.reshape(-1, 3).to(self.device),
                                                    dirs.reshape(-1, 3).to(self.device), start, end, settings, gen)
        out = G.compose(ws, feats, depth[:, None], weights[:, None], nrr, background, cfg.noise_mode, gen)
        rgb = ((out["image"].clamp(-1, 1) + 1) / 2).float()
        alpha = weights.reshape(V, 1, nrr, nrr).clamp(0, 1)
        depth = out["image_depth"]
        rgb, alpha, depth = _resize(rgb, resolution), _resize(alpha, resolution), _resize_depth(depth, alpha, resolution)
        solid = _solid(cfg.background)
        if solid is not None:
            bg = torch.tensor(solid, dtype=rgb.dtype, device=rgb.device).view(1, 3, 1, 1)
            rgb = rgb * alpha + bg * (1 - alpha)
        return RenderedViews(rgb=rgb.permute(0, 2, 3, 1).cpu().numpy(), alpha=alpha[:, 0].cpu().numpy(),
                             depth=depth[:, 0].cpu().numpy())


def _resize(x: torch.Tensor, res: int) -> torch.Tensor:
    if x.shape[-1] == res:
        return x
    return F.interpolate(x, size=(res, res), mode="bilinear", align_corners=False, antialias=res < x.shape[-1])


def _resize_depth(depth: torch.Tensor, alpha: torch.Tensor, res: int) -> torch.Tensor:
    """Depth resized with the mask as weight, so background depth never bleeds in; 0 where alpha is 0."""
    a = _resize(alpha, depth.shape[-1]) if alpha.shape[-1] != depth.shape[-1] else alpha
    num, den = _resize(depth * a, res), _resize(a, res)
    return torch.where(den > 1e-6, num / den.clamp(min=1e-6), torch.zeros_like(den))
