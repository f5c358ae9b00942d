"""Baking a subject: its field evaluated on a grid of signed distance and shaded colour, and the
trilinear lookup the renderer samples it with (world units, the box [-BOX, BOX]^3)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from datagen.device import one_cpu_thread

from .inject import smear_back
from .field import head_field
from .sdf import BOX, f32


@dataclass
class HeadGrid:
    """A baked subject: signed distance (1,1,R,R,R) and shaded RGB (1,3,R,R,R), axes z-y-x."""

    sdf: torch.Tensor
    rgb: torch.Tensor


def _grid_points(res: int) -> torch.Tensor:
    """The (res^3, 3) points of a res^3 grid over the box, x fastest (grid axes z, y, x)."""
    t = torch.linspace(-BOX, BOX, res)
    z, y, x = torch.meshgrid(t, t, t, indexing="ij")
    return torch.stack([x, y, z], dim=-1).reshape(-1, 3)


def sample_grid(grid: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Trilinear lookup of a (1,C,R,R,R) grid at points (N,3) -> (N,C); clamps at the box faces.

    On the CPU the points are split into one batch per torch thread over the same (expanded, not
    copied) grid: the kernel runs batches in parallel and each point alone, so the values are the
    same as in one batch."""
    n = p.shape[0]
    parts = max(1, min(torch.get_num_threads(), n // 4096)) if p.device.type == "cpu" else 1
    per = -(-n // parts)
    if per * parts > n:
        p = torch.cat([p, p.new_zeros(per * parts - n, 3)])
    out = F.grid_sample(grid.expand(parts, -1, -1, -1, -1), (p / BOX).reshape(parts, 1, 1, per, 3),
                        mode="bilinear", padding_mode="border", align_corners=True)
    return out.reshape(parts, grid.shape[1], per).transpose(1, 2).reshape(parts * per, -1)[:n]


def bake_head(params: dict, defects: list[dict], res: int) -> HeadGrid:
    """Evaluate the head on a res^3 grid: the distance exactly in a band around the surface (found
    coarse to fine: res/4, res/2, res), interpolated elsewhere; the colour only next to the surface.
    On one CPU thread (``one_cpu_thread``), so the same subject bakes to the same bits on any machine."""
    with one_cpu_thread():
        return _bake(params, defects, res)


def _bake(params: dict, defects: list[dict], res: int) -> HeadGrid:
    coarse_res, mid_res = max(8, res // 4), max(8, res // 2)
    coarse = head_field(_grid_points(coarse_res), params, defects, colour=False)[0]
    coarse = coarse.reshape(1, 1, coarse_res, coarse_res, coarse_res)
    mid = F.interpolate(coarse, size=(mid_res,) * 3, mode="trilinear", align_corners=True).reshape(-1)
    coarse_voxel, mid_voxel, fine_voxel = (2 * BOX / (r - 1) for r in (coarse_res, mid_res, res))
    mid_band = mid.abs() < coarse_voxel * math.sqrt(3.0) + 2.0 * mid_voxel
    mid[mid_band] = head_field(_grid_points(mid_res)[mid_band], params, defects, colour=False)[0]
    sdf = F.interpolate(mid.reshape(1, 1, mid_res, mid_res, mid_res), size=(res,) * 3, mode="trilinear",
                        align_corners=True).reshape(-1)
    band = sdf.abs() < mid_voxel * math.sqrt(3.0) + 2.0 * fine_voxel
    # Colour is also needed where the head is cut by the box (the bottom of the body).
    idx = torch.arange(res)
    on_face = torch.zeros(res, res, res, dtype=torch.bool)
    on_face[idx == 0] = on_face[idx == res - 1] = True
    on_face[:, idx == 0] = on_face[:, idx == res - 1] = True
    on_face[:, :, idx == 0] = on_face[:, :, idx == res - 1] = True
    on_face = on_face.reshape(-1)
    band |= on_face & (sdf < 0)
    points = _grid_points(res)
    band_idx = torch.nonzero(band).squeeze(1)
    # Colour where the renderer can see it: the voxels whose trilinear cells touch the surface, and
    # the inside where the box cuts the body.
    box_cut = on_face[band_idx]

    def visible(d):
        return (d.abs() < 2.5 * fine_voxel) | (box_cut & (d < 0))
    sdf_band, rgb_band = head_field(points[band_idx], params, defects, colour=visible)
    sdf[band_idx] = sdf_band
    coloured = visible(sdf_band)
    near = band_idx[coloured]
    rgb_near = rgb_band[coloured]
    pts = points[near]
    rgb = torch.zeros(res ** 3, 3)
    sdf_grid = sdf.reshape(res, res, res)
    # Bake simple lighting: normals from the distance gradient, a key, a fill and a back light, and ambient
    # occlusion from the distance along the normal.
    gz, gy, gx = torch.gradient(sdf_grid, spacing=fine_voxel)
    normal = F.normalize(torch.stack([gx, gy, gz], dim=-1).reshape(-1, 3)[near], dim=-1)
    key = F.normalize(f32(params["light_dir"]), dim=0)
    fill = F.normalize(f32([-params["light_dir"][0], 0.2, -0.6]), dim=0)
    back = F.normalize(f32([-0.3 * params["light_dir"][0], 0.6, -0.8]), dim=0)  # from behind and above
    amb = params["ambient"]
    grid = sdf_grid[None, None]
    occlusion = torch.zeros(pts.shape[0])
    for step, weight in ((0.012, 0.5), (0.03, 0.3), (0.06, 0.2)):
        d = sample_grid(grid, pts + step * normal)[:, 0]
        occlusion += weight * ((step - d) / step).clamp(0.0, 1.0)
    ao = 1.0 - 0.55 * occlusion.clamp(0.0, 1.0)
    shade = ao * (amb + (1 - amb) * (normal @ key).clamp(min=0) + 0.25 * (normal @ fill).clamp(min=0)
                  + 0.35 * (normal @ back).clamp(min=0))
    rgb[near] = (rgb_near * (shade * params["exposure"])[:, None]).clamp(0.0, 1.0)
    rgb_grid = rgb.t().reshape(3, res, res, res)
    rgb_grid = smear_back(rgb_grid, near, params, defects, res)
    return HeadGrid(sdf=sdf_grid[None, None].contiguous(), rgb=rgb_grid[None].contiguous())
