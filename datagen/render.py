"""The volume renderer every generator uses: ray sampling, importance sampling, compositing.

It follows the semantics of EG3D's importance renderer so that GAN backends reproduce the
originals: stratified depths from ``ray_start`` to ``ray_end`` (last sample exactly at the end),
importance samples from the coarse weights (max-pool + avg-pool smoothed, +0.01), midpoint
compositing, depth clamped to the sampled range.

Shapes: B batch, R rays, S samples per ray, C feature channels. Depths are distances along unit
ray directions (world units). ``deterministic=True`` turns off stratified jitter and uses fixed
importance quantiles, so the output does not depend on any random state; otherwise randomness
comes only from the given ``torch.Generator`` (seeded per subject for reproducible datasets).

A field is a callable ``field(points (B,R*S,3), dirs (B,R*S,3)) -> (features (B,R*S,C), raw_density (B,R*S,1))``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import torch
import torch.nn.functional as F

Field = Callable[[torch.Tensor, torch.Tensor], tuple]


@dataclass(frozen=True)
class RenderSettings:
    """Samples per ray and how raw densities are activated.

    density_activation: 'softplus' = softplus(raw - 1) (EG3D's ``clamp_mode='softplus'``),
    'none' = the field already returns non-negative densities.
    """

    depth_resolution: int = 48
    depth_resolution_importance: int = 48
    density_activation: str = "softplus"
    deterministic: bool = False
    chunk_rays: int = 1 << 15


def sample_stratified(ray_start, ray_end, n: int, shape, deterministic: bool,
                      generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """Depths (B, R, n, 1) from ray_start to ray_end; jittered by up to one bin unless deterministic.

    ray_start/ray_end: floats, or tensors broadcastable to (B, R, 1).
    """
    B, R = shape
    start = torch.as_tensor(ray_start, dtype=torch.float32)
    end = torch.as_tensor(ray_end, dtype=torch.float32, device=start.device)
    t = torch.linspace(0.0, 1.0, n, device=start.device).reshape(1, 1, n, 1)
    if start.dim() > 0:
        start, end = start.reshape(B, R, 1, 1), end.reshape(B, R, 1, 1)
    depths = (start + (end - start) * t).expand(B, R, n, 1).contiguous()
    if not deterministic and n > 1:
        delta = (end - start) / (n - 1)
        depths = depths + torch.rand(depths.shape, generator=generator).to(start.device) * delta
    return depths


def sample_pdf(bins: torch.Tensor, weights: torch.Tensor, n: int, deterministic: bool,
               generator: Optional[torch.Generator] = None, eps: float = 1e-5) -> torch.Tensor:
    """Inverse-CDF samples (N, n) from piecewise-constant weights (N, M-1) over bin edges (N, M)."""
    N, M = weights.shape
    weights = weights + eps
    pdf = weights / weights.sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, -1)], -1)
    if deterministic:
        u = torch.linspace(0.0, 1.0, n).expand(N, n).contiguous()
    else:
        u = torch.rand((N, n), generator=generator)
    u = u.to(cdf.device)
    idx = torch.searchsorted(cdf, u, right=True)
    below = (idx - 1).clamp(min=0)
    above = idx.clamp(max=M)
    pair = torch.stack([below, above], -1).view(N, 2 * n)
    cdf_g = torch.gather(cdf, 1, pair).view(N, n, 2)
    bins_g = torch.gather(bins, 1, pair).view(N, n, 2)
    denom = cdf_g[..., 1] - cdf_g[..., 0]
    denom = torch.where(denom < eps, torch.ones_like(denom), denom)
    return bins_g[..., 0] + (u - cdf_g[..., 0]) / denom * (bins_g[..., 1] - bins_g[..., 0])


def sample_importance(depths: torch.Tensor, weights: torch.Tensor, n: int, deterministic: bool,
                      generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """Extra depths (B, R, n, 1) drawn where the coarse compositing weights (B, R, S-1, 1) are large."""
    with torch.no_grad():
        B, R, S, _ = depths.shape
        z = depths.reshape(B * R, S)
        w = weights.reshape(B * R, 1, -1).float()
        w = F.max_pool1d(w, 2, 1, padding=1)
        w = F.avg_pool1d(w, 2, 1).reshape(B * R, -1) + 0.01
        mids = 0.5 * (z[:, :-1] + z[:, 1:])
        fine = sample_pdf(mids, w[:, 1:-1], n, deterministic, generator)
    return fine.reshape(B, R, n, 1)


def activate_density(raw: torch.Tensor, mode: str) -> torch.Tensor:
    if mode == "softplus":
        return F.softplus(raw - 1.0)
    if mode == "none":
        return raw
    raise ValueError(f"unknown density activation {mode!r}")


def march(features: torch.Tensor, densities: torch.Tensor, depths: torch.Tensor, density_activation: str):
    """Composite samples (B,R,S,C)/(B,R,S,1)/(B,R,S,1) at interval midpoints.

    Returns features (B,R,C), depth (B,R,1) clamped to the sampled range, weights (B,R,S-1,1).
    """
    deltas = depths[:, :, 1:] - depths[:, :, :-1]
    feats_mid = 0.5 * (features[:, :, :-1] + features[:, :, 1:])
    dens_mid = activate_density(0.5 * (densities[:, :, :-1] + densities[:, :, 1:]), density_activation)
    depths_mid = 0.5 * (depths[:, :, :-1] + depths[:, :, 1:])
    # Non-finite optical depths (an infinite density over a zero-length interval, a field's NaN)
    # are mapped to finite ones; finite values pass unchanged.
    optical = torch.nan_to_num(dens_mid * deltas, nan=0.0, posinf=1e4, neginf=0.0)
    alpha = 1.0 - torch.exp(-optical)
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :, :1]), 1.0 - alpha + 1e-10], -2), -2)[:, :, :-1]
    weights = alpha * trans
    out = (weights * feats_mid).sum(-2)
    total = weights.sum(2)
    depth = torch.nan_to_num((weights * depths_mid).sum(-2) / total, float("inf"))
    depth = torch.clamp(depth, depths.min(), depths.max())
    return out, depth, weights


def merge_samples(depths1, feats1, dens1, depths2, feats2, dens2):
    """Concatenate two sample sets along the ray and sort them by depth."""
    depths = torch.cat([depths1, depths2], -2)
    feats = torch.cat([feats1, feats2], -2)
    dens = torch.cat([dens1, dens2], -2)
    _, order = torch.sort(depths, dim=-2)
    depths = torch.gather(depths, -2, order)
    feats = torch.gather(feats, -2, order.expand(-1, -1, -1, feats.shape[-1]))
    dens = torch.gather(dens, -2, order)
    return depths, feats, dens


def _query(field: Field, origins, dirs, depths):
    B, R, S, _ = depths.shape
    pts = (origins.unsqueeze(-2) + depths * dirs.unsqueeze(-2)).reshape(B, R * S, 3)
    d = dirs.unsqueeze(-2).expand(B, R, S, 3).reshape(B, R * S, 3)
    feats, dens = field(pts, d)
    return feats.reshape(B, R, S, -1), dens.reshape(B, R, S, 1)


def render_rays(field: Field, origins: torch.Tensor, dirs: torch.Tensor, ray_start, ray_end,
                settings: RenderSettings, generator: Optional[torch.Generator] = None):
    """Render rays (B, R, 3) through ``field``: coarse pass, importance pass, final composite.

    Returns (features (B,R,C), depth (B,R,1), alpha (B,R,1)); alpha is the sum of the weights.
    """
    B, R, _ = origins.shape
    depths = sample_stratified(ray_start, ray_end, settings.depth_resolution, (B, R), settings.deterministic,
                               generator).to(origins.device)
    feats, dens = _query(field, origins, dirs, depths)
    if settings.depth_resolution_importance > 0:
        _, _, weights = march(feats, dens, depths, settings.density_activation)
        fine = sample_importance(depths, weights, settings.depth_resolution_importance, settings.deterministic, generator)
        feats_f, dens_f = _query(field, origins, dirs, fine)
        depths, feats, dens = merge_samples(depths, feats, dens, fine, feats_f, dens_f)
    out, depth, weights = march(feats, dens, depths, settings.density_activation)
    return out, depth, weights.sum(2)


def render_rays_chunked(field: Field, origins: torch.Tensor, dirs: torch.Tensor, ray_start, ray_end,
                        settings: RenderSettings, generator: Optional[torch.Generator] = None):
    """:func:`render_rays` over flat rays (N, 3) in chunks of ``settings.chunk_rays`` to bound memory.

    ray_start/ray_end: floats or (N,) tensors. Returns (features (N,C), depth (N,), alpha (N,)).
    """
    outs, depths, alphas = [], [], []
    per_ray = torch.is_tensor(ray_start) and ray_start.dim() > 0
    for i in range(0, origins.shape[0], settings.chunk_rays):
        sl = slice(i, i + settings.chunk_rays)
        o, d = origins[None, sl], dirs[None, sl]
        s = ray_start[sl] if per_ray else ray_start
        e = ray_end[sl] if per_ray else ray_end
        f, z, a = render_rays(field, o, d, s, e, settings, generator)
        outs.append(f[0])
        depths.append(z[0, :, 0])
        alphas.append(a[0, :, 0])
    return torch.cat(outs), torch.cat(depths), torch.cat(alphas)
