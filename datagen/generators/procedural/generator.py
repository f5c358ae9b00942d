"""The generator: subjects baked once (``bake``), views rendered by sphere tracing the baked
distance and integrating a short band of VolSDF density around the hit."""
from __future__ import annotations


import torch

from ...cameras import ViewSet, rays
from ...render import RenderSettings, box_interval, render_rays_chunked
from ..settings import ProceduralConfig
from ..base import STREAM_LATENT, STREAM_RENDER, Generator, RenderedViews, Subject, subject_rng
from .bake import HeadGrid, bake_head, sample_grid
from .inject import sample_defects
from .params import sample_params
from .sdf import BOX, f32


def laplace_density(sdf: torch.Tensor, beta: float) -> torch.Tensor:
    """VolSDF density (1/beta) * LaplaceCDF(-sdf / beta); finite for any sdf."""
    s = (-sdf / beta).clamp(-60.0, 60.0)
    return torch.where(s <= 0, 0.5 * torch.exp(s), 1.0 - 0.5 * torch.exp(-s)) / beta


def trace_interval(sdf_grid, origins, dirs, level, margin):
    """Entry and exit distances (N,) of rays (N, 3) through the box around the voxels of the grid
    (1,1,R,R,R) whose distance is below ``level``, widened by one voxel (so that no trilinear cell
    with such a corner is cut) and ``margin`` (world units); entry >= 0. A ray misses where
    exit <= entry; every ray misses an empty grid."""
    res = sdf_grid.shape[-1]
    below = sdf_grid[0, 0] < level
    if not below.any():
        none = torch.zeros(origins.shape[0])
        return none, none
    axis = torch.linspace(-BOX, BOX, res)
    pad = 2 * BOX / (res - 1) + margin
    lo, hi = [], []
    for dims in ((0, 1), (0, 2), (1, 2)):  # x, y, z: grid axes 2, 1, 0
        used = torch.nonzero(below.any(dim=dims)).squeeze(1)
        lo.append(axis[used[0]] - pad)
        hi.append(axis[used[-1]] + pad)
    lo, hi = torch.stack(lo).clamp(min=-BOX), torch.stack(hi).clamp(max=BOX)
    t_near, t_far = box_interval(origins - 0.5 * (lo + hi), dirs, 0.5 * (hi - lo))
    return t_near.clamp(min=0.0), t_far


def sphere_trace(sdf_grid, origins, dirs, t_near, t_far, hit_eps, max_steps=96):
    """First t where the grid distance drops below ``hit_eps``; returns (t, hit mask)."""
    t = t_near.clone()
    hit = torch.zeros_like(t, dtype=torch.bool)
    active = torch.nonzero(t_near < t_far).squeeze(1)
    for _ in range(max_steps):
        if active.numel() == 0:
            break
        ta = t[active]
        d = sample_grid(sdf_grid, origins[active] + ta[:, None] * dirs[active])[:, 0]
        done = d < hit_eps
        hit[active[done]] = True
        ta = ta + torch.clamp(d * 0.9, min=hit_eps * 0.5)
        t[active] = torch.where(done, t[active], ta)
        keep = ~done & (ta < t_far[active])
        active = active[keep]
    return t, hit


class ProceduralHeads(Generator):
    """Seeded procedural full heads; see the package docstring."""

    name = "procedural"

    def __init__(self, config: ProceduralConfig = ProceduralConfig()):
        self.config = config
        self.settings = RenderSettings(config.samples, config.samples_importance, "none", config.deterministic)

    def describe(self) -> dict:
        return {"name": self.name, "checkpoint": None, "checkpoint_sha256": None,
                "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.config.__dict__.items()}}

    def sample_subject(self, dataset_seed: int, index: int) -> Subject:
        rng = subject_rng(dataset_seed, index, STREAM_LATENT)
        params = sample_params(rng)
        defects = sample_defects(rng, self.config.defect_rate, params, self.config.defect_types,
                                 self.config.defect_severity)
        grid = bake_head(params, defects, self.config.grid_resolution)
        return Subject(index=index, seed=dataset_seed, latent={"params": params},
                       truth={"defects": defects}, state=grid)

    def render(self, subject: Subject, views: ViewSet, resolution: int) -> RenderedViews:
        cfg = self.config
        grid: HeadGrid = subject.state
        gen = torch.Generator().manual_seed(int(subject_rng(subject.seed, subject.index, STREAM_RENDER).integers(2 ** 62)))
        origins, dirs = rays(views.cam2world, views.K, resolution)
        V, N = origins.shape[:2]
        origins, dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)
        hit_eps = 4.0 * cfg.beta
        t_near, t_far = trace_interval(grid.sdf, origins, dirs, hit_eps, cfg.band_before)
        rgb = torch.zeros(V * N, 3)
        alpha = torch.zeros(V * N)
        depth_sum = torch.zeros(V * N)

        def density(pts, _dirs):  # no features: the renderer looks ``colour`` up per final interval
            d = sample_grid(grid.sdf, pts.reshape(-1, 3))
            return d.new_zeros(*pts.shape[:-1], 0), laplace_density(d, cfg.beta).reshape(*pts.shape[:-1], 1)

        def colour(pts):
            return sample_grid(grid.rgb, pts)

        # Trace to the surface, integrate a short band there; rays that are still not opaque
        # (grazing a thin edge) continue behind the band, up to ``max_bands`` times.
        todo = torch.nonzero(t_near < t_far).squeeze(1)
        t_start = t_near
        for _ in range(cfg.max_bands):
            if todo.numel() == 0:
                break
            t_hit, hit = sphere_trace(grid.sdf, origins[todo], dirs[todo], t_start[todo], t_far[todo], hit_eps)
            idx, t_hit = todo[hit], t_hit[hit]
            if idx.numel() == 0:
                break
            start = torch.maximum(t_hit - cfg.band_before, t_start[idx])
            end = torch.maximum(t_hit + cfg.band_after, start + 1e-4)
            f, z, a = render_rays_chunked(density, origins[idx], dirs[idx], start, end, self.settings, gen,
                                          features=colour)
            behind = 1.0 - alpha[idx]
            rgb[idx] += behind[:, None] * f
            depth_sum[idx] += behind * a * z
            alpha[idx] += behind * a
            open_ = alpha[idx] < 0.995
            todo = idx[open_]
            t_start = t_start.clone()
            t_start[todo] = end[open_]
        depth = torch.where(alpha > 0, depth_sum / alpha.clamp(min=1e-8), torch.zeros_like(alpha))
        bg = f32(cfg.background)
        alpha = alpha.clamp(0.0, 1.0)
        rgb = (rgb + (1.0 - alpha[:, None]) * bg).clamp(0.0, 1.0)
        return RenderedViews(
            rgb=rgb.reshape(V, resolution, resolution, 3).numpy(),
            alpha=alpha.reshape(V, resolution, resolution).numpy(),
            depth=depth.reshape(V, resolution, resolution).numpy(),
        )
