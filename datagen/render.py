"""The volume renderer every generator uses: ray sampling, importance sampling, compositing.

It follows the semantics of EG3D's importance renderer so that GAN backends reproduce the
originals: stratified depths from ``ray_start`` to ``ray_end`` (last sample exactly at the end),
importance samples from the coarse weights (max-pool + avg-pool smoothed, +0.01), midpoint
compositing, depth clamped to the sampled range.

Shapes: B batch, R rays, S samples per ray, C feature channels. Depths are distances along unit
ray directions (world units). ``deterministic=True`` turns off stratified jitter and uses fixed
importance quantiles, so the output does not depend on any random state; otherwise randomness
comes only from the given ``torch.Generator`` (seeded per subject for reproducible datasets). The
chunked renderer draws each ray's random numbers in fixed blocks of ``NOISE_BLOCK_RAYS`` rays on
the CPU, so an image does not depend on the chunk size (a memory budget) or on the device.

A field is a callable ``field(points (B,R*S,3), dirs (B,R*S,3)) -> (features (B,R*S,C), raw_density (B,R*S,1))``.
A field may instead return no features (C = 0) and pass them separately as
``features(points (K,3)) -> (K,C)``: the coarse pass then needs no features, and the final
composite looks them up once per interval, at its midpoint (midpoint quadrature, more accurate than
averaging the two ends at the same number of samples).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import torch
import torch.nn.functional as F

Field = Callable[[torch.Tensor, torch.Tensor], tuple]
NOISE_BLOCK_RAYS = 1 << 14


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
                      generator: Optional[torch.Generator] = None, u: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Depths (B, R, n, 1) from ray_start to ray_end; jittered by up to one bin unless deterministic.

    ray_start/ray_end: floats, or tensors broadcastable to (B, R, 1). ``u``: the jitter's uniform
    numbers (B*R, n), drawn from ``generator`` when not given.
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
        if u is None:
            u = torch.rand(depths.shape, generator=generator)
        depths = depths + u.to(start.device).reshape(depths.shape) * delta
    return depths


def sample_pdf(bins: torch.Tensor, weights: torch.Tensor, n: int, deterministic: bool,
               generator: Optional[torch.Generator] = None, eps: float = 1e-5,
               u: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Inverse-CDF samples (N, n) from piecewise-constant weights (N, M-1) over bin edges (N, M).

    ``u``: the uniform numbers (N, n) when not deterministic (drawn from ``generator`` if not given).
    """
    N, M = weights.shape
    weights = weights + eps
    pdf = weights / weights.sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, -1)], -1)
    if deterministic:
        u = torch.linspace(0.0, 1.0, n, device=cdf.device).expand(N, n).contiguous()
    elif u is None:
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
                      generator: Optional[torch.Generator] = None, u: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Extra depths (B, R, n, 1) drawn where the coarse compositing weights (B, R, S-1, 1) are large."""
    with torch.no_grad():
        B, R, S, _ = depths.shape
        z = depths.reshape(B * R, S)
        w = weights.reshape(B * R, 1, -1).float()
        w = F.max_pool1d(w, 2, 1, padding=1)
        w = F.avg_pool1d(w, 2, 1).reshape(B * R, -1) + 0.01
        mids = 0.5 * (z[:, :-1] + z[:, 1:])
        fine = sample_pdf(mids, w[:, 1:-1], n, deterministic, generator, u=u)
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
                settings: RenderSettings, generator: Optional[torch.Generator] = None, noise=None,
                features: Optional[Callable[[torch.Tensor], torch.Tensor]] = None):
    """Render rays (B, R, 3) through ``field``: coarse pass, importance pass, final composite.

    ``noise``: (stratified (B*R, S), importance (B*R, S_imp)) uniform numbers, e.g. a slice of
    :func:`draw_ray_noise`; drawn from ``generator`` when not given. ``features``: see the module
    docstring (the field's own features are then ignored).
    Returns (features (B,R,C), depth (B,R,1), alpha (B,R,1)); alpha is the sum of the weights.
    """
    B, R, _ = origins.shape
    u_strat, u_imp = noise if noise is not None else (None, None)
    depths = sample_stratified(ray_start, ray_end, settings.depth_resolution, (B, R), settings.deterministic,
                               generator, u_strat).to(origins.device)
    feats, dens = _query(field, origins, dirs, depths)
    if settings.depth_resolution_importance > 0:
        _, _, weights = march(feats, dens, depths, settings.density_activation)
        fine = sample_importance(depths, weights, settings.depth_resolution_importance, settings.deterministic,
                                 generator, u_imp)
        feats_f, dens_f = _query(field, origins, dirs, fine)
        depths, feats, dens = merge_samples(depths, feats, dens, fine, feats_f, dens_f)
    out, depth, weights = march(feats, dens, depths, settings.density_activation)
    if features is not None:
        out = _weighted_features(features, origins, dirs, depths, weights)
    return out, depth, weights.sum(2)


def _weighted_features(features, origins, dirs, depths, weights):
    """Sum over intervals of weight (B,R,S-1,1) x features at the interval midpoint."""
    mids = 0.5 * (depths[:, :, 1:] + depths[:, :, :-1])
    pts = origins.unsqueeze(-2) + mids * dirs.unsqueeze(-2)
    vals = features(pts.reshape(-1, 3))
    return (weights * vals.reshape(*weights.shape[:-1], -1)).sum(-2)


def draw_ray_noise(n_rays: int, settings: RenderSettings, generator: Optional[torch.Generator]):
    """Every ray's uniform numbers, (stratified (N, S), importance (N, S_imp) or None), or None if
    deterministic.

    Drawn on the CPU in blocks of ``NOISE_BLOCK_RAYS`` rays (a block's stratified numbers, then its
    importance numbers), so they depend neither on how the rays are chunked nor on the device.
    """
    if settings.deterministic:
        return None
    S, S_imp = settings.depth_resolution, settings.depth_resolution_importance
    strat, imp = [], []
    for i in range(0, n_rays, NOISE_BLOCK_RAYS):
        m = min(NOISE_BLOCK_RAYS, n_rays - i)
        strat.append(torch.rand((m, S), generator=generator) if S > 1 else torch.zeros(m, S))
        if S_imp > 0:
            imp.append(torch.rand((m, S_imp), generator=generator))
    return torch.cat(strat), (torch.cat(imp) if imp else None)


def box_interval(origins: torch.Tensor, dirs: torch.Tensor, half_extent) -> tuple:
    """Entry and exit distances (N,) of rays (N, 3) through the box [-h, h]^3 (h: (3,) or a float).

    Slab test; axis-parallel directions are exact (inside the slab the axis does not limit the
    ray, outside it the ray misses). A ray misses the box where exit <= entry.
    """
    h = torch.as_tensor(half_extent, dtype=origins.dtype, device=origins.device).expand(3)
    parallel = dirs == 0
    safe = torch.where(parallel, torch.ones_like(dirs), dirs)
    t0, t1 = (-h - origins) / safe, (h - origins) / safe
    inside = origins.abs() <= h
    unlimited = torch.where(inside, torch.inf, -torch.inf)
    lo = torch.where(parallel, -unlimited, torch.minimum(t0, t1))
    hi = torch.where(parallel, unlimited, torch.maximum(t0, t1))
    return lo.max(dim=-1).values, hi.min(dim=-1).values


def render_rays_chunked(field: Field, origins: torch.Tensor, dirs: torch.Tensor, ray_start, ray_end,
                        settings: RenderSettings, generator: Optional[torch.Generator] = None, box=None,
                        features: Optional[Callable[[torch.Tensor], torch.Tensor]] = None):
    """:func:`render_rays` over flat rays (N, 3) in chunks of ``settings.chunk_rays`` to bound memory.

    ray_start/ray_end: floats or (N,) tensors. ``box``: half extents of the axis-aligned box outside
    which the field shows nothing; each ray's range is clipped to it and rays that miss it are
    not marched (features 0, alpha 0, depth ray_end). ``features``: as in :func:`render_rays`. The
    random numbers of all rays are drawn first (:func:`draw_ray_noise`), so the result does not
    depend on ``chunk_rays``.
    Returns (features (N,C), depth (N,), alpha (N,)).
    """
    n, device = origins.shape[0], origins.device
    start = torch.as_tensor(ray_start, dtype=torch.float32, device=device).expand(n)
    end = torch.as_tensor(ray_end, dtype=torch.float32, device=device).expand(n)
    noise = draw_ray_noise(n, settings, generator)
    if noise is not None:
        noise = tuple(None if u is None else u.to(device, non_blocking=True) for u in noise)
    todo = None
    if box is not None:
        t_near, t_far = box_interval(origins, dirs, box)
        clipped_start, clipped_end = torch.maximum(start, t_near), torch.minimum(end, t_far)
        todo = torch.nonzero(clipped_end > clipped_start).squeeze(1)  # one host sync per call
        start, end_marched = clipped_start, clipped_end
    else:
        end_marched = end
    total = n if todo is None else todo.numel()
    feats, depths, alphas = [], [], []
    for i in range(0, total, settings.chunk_rays):
        idx = slice(i, i + settings.chunk_rays) if todo is None else todo[i:i + settings.chunk_rays]
        chunk_noise = None if noise is None else tuple(None if u is None else u[idx] for u in noise)
        f, z, a = render_rays(field, origins[None, idx], dirs[None, idx], start[idx][None, :, None],
                              end_marched[idx][None, :, None], settings, noise=chunk_noise, features=features)
        feats.append(f[0])
        depths.append(z[0, :, 0])
        alphas.append(a[0, :, 0])
    if todo is None:
        return torch.cat(feats), torch.cat(depths), torch.cat(alphas)
    if feats:
        channels = feats[0].shape[-1]
    elif features is not None:
        channels = features(origins[:1]).shape[-1]
    else:
        channels = field(origins[None, :1], dirs[None, :1])[0].shape[-1]
    out_f, out_z, out_a = origins.new_zeros(n, channels), end.clone(), origins.new_zeros(n)
    if feats:
        out_f.index_copy_(0, todo, torch.cat(feats))
        out_z.index_copy_(0, todo, torch.cat(depths))
        out_a.index_copy_(0, todo, torch.cat(alphas))
    return out_f, out_z, out_a
