"""Reference Gaussian rasterizer: :func:`panolam.rasterizer.rasterize` written as directly as
possible, to check it (the tests compare the two in float64, forward and backward).

Same conventions and constants (the docstring of :mod:`panolam.rasterizer`); brute force: the
projection is re-derived per Gaussian (3D covariance, camera covariance, Jacobian, 2x2 inverse) in
the input dtype, then every pixel visits every Gaussian in depth order with the sequential
transmittance update of the CUDA rasterizers, gradients by autograd. O(N H W) memory and a Python
loop over the Gaussians: small scenes only. The fast path never imports this module.
"""
from __future__ import annotations

import torch

from .rasterizer import ALPHA_MAX, ALPHA_MIN, EPS2D, EXTENT_SIGMAS, T_MIN, finish, over_cameras



def rasterize_reference(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int,
                        background=None, near_plane: float = 0.01, far_plane: float = 1e10, tile_size: int = 16):
    """``rasterize`` by brute force (module docstring); use float64 for tight comparisons."""
    if viewmat.dim() == 3:
        return over_cameras(rasterize_reference, means, quats, scales, opacities, colors, viewmat, K, width,
                                  height, background, near_plane=near_plane, far_plane=far_plane,
                                  tile_size=tile_size)
    mean2d, conic, z, radius, valid = _reference_projection(means, quats, scales, opacities, viewmat, K, width,
                                                            height, near_plane, far_plane)
    pixels = _reference_pixel_centres(width, height, means.dtype)                       # (P, 2)
    d = pixels[:, None, :] - mean2d[None, :, :]                                          # (P, N, 2)
    power = -0.5 * torch.einsum("pni,nij,pnj->pn", d, conic, d)
    alpha = (opacities * torch.exp(power)).clamp(max=ALPHA_MAX)
    covered = _reference_tile_cover(mean2d.detach(), radius, width, height, tile_size) & valid
    alpha = torch.where(covered & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
    trans = torch.ones(pixels.shape[0], dtype=means.dtype)
    stopped = torch.zeros(pixels.shape[0], dtype=torch.bool)
    rgb_sum = torch.zeros(pixels.shape[0], colors.shape[-1], dtype=means.dtype)
    depth_sum = torch.zeros(pixels.shape[0], dtype=means.dtype)
    alpha_sum = torch.zeros(pixels.shape[0], dtype=means.dtype)
    for i in torch.argsort(z.detach(), stable=True).tolist():
        next_trans = trans * (1.0 - alpha[:, i])
        stopped = stopped | (next_trans < T_MIN)
        w = torch.where(stopped, torch.zeros_like(trans), alpha[:, i] * trans)
        rgb_sum = rgb_sum + w[:, None] * colors[i]
        depth_sum = depth_sum + w * z[i]
        alpha_sum = alpha_sum + w
        trans = torch.where(stopped, trans, next_trans)
    acc = torch.cat([rgb_sum, depth_sum[:, None], alpha_sum[:, None]], -1).reshape(height, width, -1)
    return finish(acc, background)


def _reference_projection(means, quats, scales, opacities, viewmat, K, width, height, near_plane, far_plane):
    """-> means2d (N, 2), conic matrices (N, 2, 2), depths (N,), radii (N, 2) (rx, ry), valid (N,)."""
    dtype = means.dtype
    rot_w, trans_w = viewmat[:3, :3].to(dtype), viewmat[:3, 3].to(dtype)
    cam = means @ rot_w.T + trans_w
    z = cam[:, 2]
    in_depth = (z >= near_plane) & (z <= far_plane) & (z > 0)
    z_safe = torch.where(in_depth, z, torch.ones_like(z))
    norm = quats.norm(dim=-1, keepdim=True)
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dtype)
    q = torch.where(norm > 0, quats / norm.clamp_min(1e-12), identity)
    w, v = q[:, :1, None], q[:, 1:]
    cross = torch.zeros(len(q), 3, 3, dtype=dtype)
    cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    cross = cross - cross.transpose(1, 2)
    eye = torch.eye(3, dtype=dtype)
    rot = (w * w - (v * v).sum(-1)[:, None, None]) * eye + 2 * v[:, :, None] * v[:, None, :] + 2 * w * cross
    cov_world = rot @ torch.diag_embed(scales * scales) @ rot.transpose(1, 2)
    cov_cam = rot_w @ cov_world @ rot_w.T
    fx, fy, cx, cy = (K[i, j].to(dtype) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)))
    lim_x, lim_y = 0.3 * 0.5 * width / fx, 0.3 * 0.5 * height / fy
    xz = torch.clamp(cam[:, 0] / z_safe, -cx / fx - lim_x, (width - cx) / fx + lim_x)
    yz = torch.clamp(cam[:, 1] / z_safe, -cy / fy - lim_y, (height - cy) / fy + lim_y)
    jac = torch.zeros(len(q), 2, 3, dtype=dtype)
    jac[:, 0, 0], jac[:, 0, 2] = fx / z_safe, -fx * xz / z_safe
    jac[:, 1, 1], jac[:, 1, 2] = fy / z_safe, -fy * yz / z_safe
    cov2d = jac @ cov_cam @ jac.transpose(1, 2) + EPS2D * torch.eye(2, dtype=dtype)
    det = torch.linalg.det(cov2d)
    valid = in_depth & (det > 0) & (opacities >= ALPHA_MIN)
    conic = torch.linalg.inv(torch.where(valid[:, None, None], cov2d, torch.eye(2, dtype=dtype)))
    # Half box of the ellipse o exp(-0.5 d^T cov2d^-1 d) >= ALPHA_MIN, at most EXTENT_SIGMAS sigma per axis.
    sigmas = torch.sqrt(2.0 * torch.log(opacities.detach().clamp_min(ALPHA_MIN) / ALPHA_MIN)).clamp_max(EXTENT_SIGMAS)
    radius = torch.ceil(sigmas[:, None] * torch.sqrt(torch.diagonal(cov2d.detach(), dim1=1, dim2=2)))
    mean2d = torch.stack([fx * cam[:, 0] / z_safe + cx, fy * cam[:, 1] / z_safe + cy], -1)
    return mean2d, conic, z, radius, valid


def _reference_pixel_centres(width, height, dtype):
    rows, cols = torch.meshgrid(torch.arange(height, dtype=dtype), torch.arange(width, dtype=dtype), indexing="ij")
    return torch.stack([cols, rows], -1).reshape(-1, 2) + 0.5


def _reference_tile_cover(mean2d, radius, width, height, tile_size):
    """(P, N) bool: the pixel's tile lies in the Gaussian's tile box."""
    rows, cols = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    tile_x, tile_y = (cols.reshape(-1, 1) // tile_size), (rows.reshape(-1, 1) // tile_size)
    u, v = mean2d[:, 0].double(), mean2d[:, 1].double()
    rx, ry = radius[:, 0].double(), radius[:, 1].double()
    return ((tile_x >= torch.floor((u - rx) / tile_size)) & (tile_x < torch.ceil((u + rx) / tile_size))
            & (tile_y >= torch.floor((v - ry) / tile_size)) & (tile_y < torch.ceil((v + ry) / tile_size)))
