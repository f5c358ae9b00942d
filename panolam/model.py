"""PanoLAM: one head image in, a full head of 3D Gaussians out, in one forward pass.

Stages (paper, Sec. 3; sizes in :mod:`panolam.config`):

1. Image tokens (B, T, C_t): DINOv2 intermediate layers fused by an MLP, or the small CPU encoder.
2. Coarse stage: template vertices -> NeRF positional encoding -> MLP -> L blocks in which the point
   tokens cross-attend to the image tokens -> a Gaussian head (colour, opacity, scale, rotation and
   an offset clamped to +-eps_OC). Each block also lets the point tokens attend to each other and
   ends in an MLP (pre-LN, as LAM's "cond" block): self-attention is what lets points that the photo
   does not show (the back of the head) borrow from the points it does show, at a cost that stays
   small because the coarse set is sparse.
3. Densification without a network: precomputed barycentric weights of the subdivided template
   spread the coarse positions (after their offsets) and the point features to M_D points.
4. Spherical tri-plane branch: 6 x H_T x W_T learnable tokens cross-attend to the image tokens
   (cross-attention and MLP only: self-attention over 6 x 64 x 64 tokens would cost more than the
   rest of the model) and are projected to SphereHead's plane channels. Each dense point gathers
   features along rays from 4 virtual cameras (front, left, right, back): K_m samples within
   +-``ray_half_length_m`` of the point on each ray, queried with SphereHead's spherical tri-plane
   sampling (shared with the GAN backend), concatenated (camera-major, 4 K_m C values) and fused by
   an MLP. A decoder (SphereHead's, frozen, when a checkpoint is given; otherwise a small trainable
   one of the same shape) volume-renders the planes into an image for the branch's own loss.
5. Dense stage: concat(point features, tri-plane features) -> a Gaussian head with a residual
   offset clamped to +-eps_OD.

Activations are bounded: colour and opacity sigmoids, scales ``lo + (hi - lo) sigmoid`` (no exp),
offsets ``eps tanh``, rotations normalized (a zero quaternion renders as the identity).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from datagen.cameras import ray_range, rays
from datagen.device import constant
from datagen.errors import UserError
from datagen.gans.triplane import OSGDecoder, crop_outside, sample_planes
from datagen.render import RenderSettings, render_rays

from .config import ModelConfig
from .encoder import build_encoder
from .gaussians import Gaussians
from .template import densification, densify, load_template

# Virtual cameras of the ray aggregation, unit directions from the head: front (+z, where the face
# looks), the head's left (+x), its right (-x) and back (-z).
VIRTUAL_CAMERAS = ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, -1.0))
SPHEREHEAD = "spherehead"


def mlp(dims, activation=nn.GELU) -> nn.Sequential:
    """Linear layers of widths ``dims`` with ``activation`` between them (none after the last)."""
    layers = []
    for i, (a, b) in enumerate(zip(dims[:-1], dims[1:])):
        layers.append(nn.Linear(a, b))
        if i < len(dims) - 2:
            layers.append(activation())
    return nn.Sequential(*layers)


def positional_encoding(x: torch.Tensor, frequencies: int) -> torch.Tensor:
    """NeRF encoding (..., 3) -> (..., 3 + 6 F): x, sin(2^k pi x), cos(2^k pi x) for k < F."""
    freqs = (2.0 ** torch.arange(frequencies, device=x.device, dtype=x.dtype)) * math.pi
    xf = (x[..., None, :] * freqs[:, None]).flatten(-2)
    return torch.cat([x, torch.sin(xf), torch.cos(xf)], -1)


class AttentionBlock(nn.Module):
    """Pre-LN block: cross-attention to image tokens, optional self-attention, MLP; all residual."""

    def __init__(self, dim: int, heads: int, self_attention: bool):
        super().__init__()
        self.norm_query, self.norm_context = nn.LayerNorm(dim), nn.LayerNorm(dim)
        self.cross = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.norm_self = nn.LayerNorm(dim) if self_attention else None
        self.attend = nn.MultiheadAttention(dim, heads, batch_first=True) if self_attention else None
        self.norm_mlp = nn.LayerNorm(dim)
        self.mlp = mlp([dim, 4 * dim, dim])

    def forward(self, x: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        c = self.norm_context(context)
        h = self.norm_query(x)
        x = x + self.cross(h, c, c, need_weights=False)[0]
        if self.attend is not None:
            h = self.norm_self(x)
            x = x + self.attend(h, h, h, need_weights=False)[0]
        return x + self.mlp(self.norm_mlp(x))


class GaussianHead(nn.Module):
    """Features (B, N, C) at anchors (B, N, 3) -> Gaussians and the clamped offsets (B, N, 3).

    A 3-layer MLP; bounded activations. At initialisation offsets are 0, scales ``init_scale``,
    opacity 0.5 and rotations the identity, so an untrained head renders the anchor shape.
    """

    OUT = (3, 1, 3, 4, 3)  # colour, opacity, scale, rotation (wxyz), offset

    def __init__(self, in_dim: int, hidden: int, scale_range, offset_max: float, init_scale: float):
        super().__init__()
        self.lo, self.hi = float(scale_range[0]), float(scale_range[1])
        self.offset_max = float(offset_max)
        self.net = mlp([in_dim, hidden, hidden, sum(self.OUT)], activation=nn.SiLU)
        last = self.net[-1]
        with torch.no_grad():
            last.weight[3:].mul_(0.1)
            last.weight[-3:].zero_()
            last.bias.zero_()
            frac = min(max((init_scale - self.lo) / (self.hi - self.lo), 1e-3), 1 - 1e-3)
            last.bias[4:7] = math.log(frac / (1 - frac))
            last.bias[7] = 1.0

    def forward(self, features: torch.Tensor, anchors: torch.Tensor):
        colour, opacity, scale, rotation, offset = self.net(features).split(self.OUT, dim=-1)
        offset = self.offset_max * torch.tanh(offset)
        g = Gaussians(means=anchors + offset, quats=F.normalize(rotation, dim=-1, eps=1e-8),
                      scales=self.lo + (self.hi - self.lo) * torch.sigmoid(scale),
                      opacities=torch.sigmoid(opacity[..., 0]), colors=torch.sigmoid(colour))
        return g, offset


class SphericalTriplane(nn.Module):
    """Learnable tokens -> spherical tri-planes (B, 2, 3, C, H_T, W_T), SphereHead's layout."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        r = cfg.triplane_resolution
        self.resolution, self.channels = r, cfg.triplane_channels
        self.queries = nn.Parameter(torch.randn(6 * r * r, cfg.token_dim) * 0.02)
        self.blocks = nn.ModuleList(AttentionBlock(cfg.token_dim, cfg.heads, self_attention=False)
                                    for _ in range(cfg.triplane_blocks))
        self.project = nn.Sequential(nn.LayerNorm(cfg.token_dim), nn.Linear(cfg.token_dim, cfg.triplane_channels))

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        b, r = tokens.shape[0], self.resolution
        x = self.queries.expand(b, -1, -1)
        for block in self.blocks:
            x = block(x, tokens)
        planes = self.project(x).view(b, 6, r, r, self.channels).permute(0, 1, 4, 2, 3)
        return planes.reshape(b, 2, 3, self.channels, r, r)


def virtual_ray_samples(points: torch.Tensor, radius: float, half_length: float, k: int) -> torch.Tensor:
    """Samples (B, 4, M, K, 3) on the rays from the 4 virtual cameras through each point (B, M, 3)."""
    origins = constant(VIRTUAL_CAMERAS, points.device).to(points.dtype) * radius
    dirs = F.normalize(points[:, None] - origins[None, :, None], dim=-1, eps=1e-8)
    t = torch.linspace(-half_length, half_length, k, device=points.device, dtype=points.dtype)
    return points[:, None, :, None] + dirs[..., None, :] * t[:, None]


@dataclass
class Reconstruction:
    """What one forward pass returns (batched Gaussians; ``coarse`` is None without coarse-to-fine)."""

    dense: Gaussians
    coarse: Optional[Gaussians]
    planes: Optional[torch.Tensor]          # (B, 2, 3, C, H_T, W_T)
    coarse_offsets: Optional[torch.Tensor]  # (B, V, 3) world units
    dense_offsets: torch.Tensor             # (B, M_D, 3) world units


class PanoLAM(nn.Module):
    """The reconstruction network for one :class:`ModelConfig`."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.template = load_template(cfg.template, cfg.template_vertices)
        upm = self.template.units_per_metre
        self.encoder = build_encoder(cfg.encoder, cfg.encoder_weights, cfg.token_dim, **self._encoder_kwargs())
        d = densification(self.template, target_points=cfg.dense_points)
        self.register_buffer("template_points", torch.from_numpy(self.template.vertices.astype(np.float32)))
        self.register_buffer("dense_index", torch.from_numpy(d.indices.astype(np.int64)), persistent=False)
        self.register_buffer("dense_weights", torch.from_numpy(d.weights.astype(np.float32)), persistent=False)
        self.dense_count = len(d.indices)

        c = cfg.token_dim
        self.point_embed = mlp([3 + 6 * cfg.pe_frequencies, c, c])
        self.blocks = nn.ModuleList(AttentionBlock(c, cfg.heads, cfg.point_self_attention) for _ in range(cfg.blocks))
        self.point_norm = nn.LayerNorm(c)
        coarse_spacing = _mean_spacing(self.template_points)
        dense_spacing = coarse_spacing * math.sqrt(len(self.template_points) / self.dense_count)
        if cfg.coarse_to_fine:
            self.coarse_head = GaussianHead(c, cfg.head_hidden, cfg.coarse_scale_range, cfg.coarse_offset_m * upm,
                                            0.5 * coarse_spacing)
            dense_offset = cfg.dense_offset_m * upm
        else:
            dense_offset = cfg.coarse_offset_m * upm  # direct regression has to carve the shape itself
        dense_in = c
        if cfg.triplane != "none":
            self.triplane = SphericalTriplane(cfg)
            samples = 4 * cfg.ray_samples if cfg.triplane == "rays" else 1
            self.aggregate = mlp([samples * cfg.triplane_channels, cfg.triplane_aggregate_dim,
                                  cfg.triplane_aggregate_dim])
            self.triplane_decoder, self.box_warp = self._triplane_decoder()
            dense_in += cfg.triplane_aggregate_dim
        self.dense_head = GaussianHead(dense_in, cfg.head_hidden, cfg.dense_scale_range, dense_offset,
                                       0.5 * dense_spacing)

    def _encoder_kwargs(self) -> dict:
        cfg = self.cfg
        if cfg.encoder == "dinov2":
            return dict(layers=cfg.encoder_layers, image_size=cfg.image_size)
        return dict(image_size=cfg.image_size, patch_size=cfg.patch_size, width=cfg.encoder_width,
                    depth=cfg.encoder_depth, heads=cfg.heads, layers=cfg.encoder_layers)

    def _triplane_decoder(self):
        """SphereHead's decoder, frozen, from the configured checkpoint; else a small trainable one."""
        cfg = self.cfg
        if cfg.spherehead_checkpoint is None:
            return OSGDecoder(cfg.triplane_channels, activation="sigmoid"), cfg.box_warp
        from datagen.gans.checkpoint import read_checkpoint
        loaded = read_checkpoint(cfg.spherehead_checkpoint, SPHEREHEAD)
        decoder = loaded.generator.decoder
        first = decoder.net[0]
        if first.weight.shape[1] != cfg.triplane_channels:
            raise UserError(f"{cfg.spherehead_checkpoint}: SphereHead planes have {first.weight.shape[1]} channels, "
                             f"the config asks for {cfg.triplane_channels}")
        decoder.requires_grad_(False)
        return decoder, float(loaded.rendering_kwargs["box_warp"])

    # -- stages -------------------------------------------------------------------------------------
    def densify(self, values: torch.Tensor) -> torch.Tensor:
        """(B, V, C) per template vertex -> (B, M_D, C) by the precomputed barycentric weights."""
        return densify(values, self.dense_index, self.dense_weights)

    def query_triplane(self, planes: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """Tri-plane features (B, M, C) at world points (B, M, 3), the 3 planes of SphereHead averaged."""
        return sample_planes(SPHEREHEAD, planes, points, self.box_warp).mean(1)

    def aggregate_triplane(self, planes: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """Per-point tri-plane features (B, M, D): multi-layer ray aggregation, or the point alone."""
        cfg = self.cfg
        b, m, _ = points.shape
        if cfg.triplane == "point":
            return self.aggregate(self.query_triplane(planes, points))
        samples = virtual_ray_samples(points, cfg.virtual_camera_radius, cfg.ray_half_length_m *
                                      self.template.units_per_metre, cfg.ray_samples)
        feats = self.query_triplane(planes, samples.reshape(b, -1, 3))
        feats = feats.view(b, 4, m, cfg.ray_samples, -1).permute(0, 2, 1, 3, 4).reshape(b, m, -1)
        return self.aggregate(feats)

    def forward(self, images: torch.Tensor) -> Reconstruction:
        """images (B, 3, H, W) RGB in [0, 1] (any size; the encoder resizes)."""
        cfg = self.cfg
        tokens = self.encoder(torch.nan_to_num(images, nan=0.0).clamp(0.0, 1.0))
        b = tokens.shape[0]
        template = self.template_points[None].expand(b, -1, -1)
        anchors = template if cfg.coarse_to_fine else self.densify(template)
        x = self.point_embed(positional_encoding(anchors, cfg.pe_frequencies))
        for block in self.blocks:
            x = block(x, tokens)
        x = self.point_norm(x)
        coarse = coarse_offsets = None
        if cfg.coarse_to_fine:
            coarse, coarse_offsets = self.coarse_head(x, anchors)
            anchors, x = self.densify(coarse.means), self.densify(x)
        planes = None
        if cfg.triplane != "none":
            planes = self.triplane(tokens)
            x = torch.cat([x, self.aggregate_triplane(planes, anchors)], -1)
        dense, dense_offsets = self.dense_head(x, anchors)
        return Reconstruction(dense, coarse, planes, coarse_offsets, dense_offsets)

    # -- the tri-plane branch's own image -------------------------------------------------------------
    def render_triplane(self, planes: torch.Tensor, cam2world: torch.Tensor, K_norm: torch.Tensor,
                        radius: torch.Tensor, resolution: Optional[int] = None):
        """Volume-render planes (B, ...) seen by cameras (B, V, 4, 4), (B, V, 3, 3) at ``radius`` (B, V)
        from their look-at pivot -> RGB (B, V, 3, r, r), alpha (B, V, 1, r, r).

        Deterministic sampling on EG3D's ray ranges moved with each radius; RGB is the decoder's first 3
        feature channels, in [0, 1] (over a black background).
        """
        cfg = self.cfg
        r = resolution or cfg.triplane_render_resolution
        b, v = cam2world.shape[:2]
        dev = planes.device
        origins, dirs = rays(cam2world.reshape(b * v, 4, 4).float().to(dev), K_norm.reshape(b * v, 3, 3).float().to(dev), r)
        origins, dirs = origins.reshape(b, v * r * r, 3), dirs.reshape(b, v * r * r, 3)
        near, far = (t.reshape(b, v).repeat_interleave(r * r, dim=1)
                     for t in ray_range(radius.detach().float().to(dev)))
        decoder, box = self.triplane_decoder, self.box_warp

        def field(points, _dirs):
            feats, sigma = decoder(sample_planes(SPHEREHEAD, planes, points, box))
            return feats, torch.where(crop_outside(points, box), torch.full_like(sigma, -1e3), sigma)

        settings = RenderSettings(*cfg.triplane_render_samples, density_activation="softplus", deterministic=True)
        feats, _, alpha = render_rays(field, origins, dirs, near, far, settings)
        rgb = feats[..., :3] if decoder.activation == "sigmoid" else (feats[..., :3] + 1) / 2
        image = lambda t: t.reshape(b, v, r, r, -1).permute(0, 1, 4, 2, 3)  # noqa: E731
        return image(rgb), image(alpha)


def _mean_spacing(points: torch.Tensor) -> float:
    """Mean distance from a point to its nearest neighbour (world units)."""
    from scipy.spatial import cKDTree
    p = points.detach().cpu().numpy()
    dist, _ = cKDTree(p).query(p, k=2)
    return float(dist[:, 1].mean())


def parameter_count(module: nn.Module, trainable_only: bool = True) -> int:
    return sum(p.numel() for p in module.parameters() if p.requires_grad or not trainable_only)
