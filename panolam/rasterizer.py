"""Differentiable 3D Gaussian splatting in pure PyTorch: fast enough to train on a CPU, and the
rasterizer on GPUs where gsplat (CUDA kernels; the optional extra ``.[cuda]``) is not installed.

The API follows ``gsplat.rasterization`` and so do the constants (gsplat >= 1.5, "classic" mode):
a model trained with one backend renders the same with the other. Every function in this module
shares these conventions.

Inputs
    means (N, 3) world units; quats (N, 4) wxyz (normalized here; a zero quaternion is the
    identity); scales (N, 3) activated standard deviations, world units; opacities (N,) in [0, 1];
    colors (N, D) any D features (RGB for D = 3).
Camera
    viewmat: world-to-camera 4x4, OpenCV (+x right, +y down, +z forward); K: 3x3 pixel
    intrinsics, ``uv = K x / z`` (skew ignored). Pixel (row i, column j) has its centre at
    ``(j + 0.5, i + 0.5)``. Pass ``datagen.cameras.pixel_intrinsics(K_norm, W, H)`` and the inverse
    of a cam2world. A batch of cameras, viewmat (C, 4, 4) and K (C, 3, 3) or (3, 3), is rendered
    one camera after the other and every output gains a leading C.
Projection (EWA splatting)
    ``cov2d = J W Sigma W^T J^T + 0.3 I`` (px^2), with J the perspective Jacobian at the camera-space
    mean whose x/z and y/z are clamped to the image border plus 0.3 of the half field of view
    (gsplat's frustum clamp). Culled: z < near_plane, z > far_plane or z <= 0; opacity < 1/255 (it
    could never pass the alpha threshold); a non-finite parameter or projection. The projection is
    computed in float64 so that huge or tiny scales stay finite, with a cancellation-free
    determinant (see project), positive for every finite Gaussian.
Tiles
    A Gaussian takes part only in the tiles (``tile_size`` px squares) that its box
    ``[u - rx, u + rx] x [v - ry, v + ry]`` touches, with ``rx = ceil(e sqrt(cov2d_xx))``,
    ``ry = ceil(e sqrt(cov2d_yy))`` px and ``e = min(3.33, sqrt(2 ln(255 o)))`` (gsplat's
    opacity-aware box): the bounding box of the ellipse where ``o exp(-0.5 d^T cov2d^-1 d)`` reaches
    1/255, capped at 3.33 standard deviations per axis. The cap binds only above opacity 1.0036, so
    for opacities in [0, 1] every pixel where a Gaussian passes the alpha threshold lies in its
    tiles, and the output does not depend on ``tile_size`` (up to rounding on the ellipse itself).
Compositing, front to back by the camera z of each mean
    ``alpha_i = min(0.999, o_i exp(-0.5 d^T cov2d^-1 d))``; alpha < 1/255 is skipped; a pixel stops
    before the first Gaussian that would take its transmittance below 1e-4 (gsplat: at or below).
    ``w_i = alpha_i T_i`` with ``T_i = prod_{j<i} (1 - alpha_j)``.
Outputs
    rgb (H, W, D) = sum w_i c_i + (1 - alpha) background (background defaults to 0);
    alpha (H, W, 1) = sum w_i; depth (H, W, 1) = sum w_i z_i / alpha, the expected depth (gsplat's
    "ED", 0 where alpha is 0). Gradients reach means, quats, scales, opacities, colors, background
    (and viewmat); nothing reaches K.

Implementation. Projection and binning run once for all Gaussians. Binning pairs each Gaussian with
the 4x4 px blocks of its tiles that its alpha >= 1/255 ellipse reaches (exact: dropped pairs could
only be skipped) and sorts the pairs by (block, depth) with one stable sort. Compositing is a custom
autograd Function that walks the blocks' depth-sorted lists in chunks of k Gaussians, many blocks at
once, so each step is a dozen tensor ops on a (blocks, pixels, k) array of bounded size (a
preallocated workspace). Transmittance is a cumulative sum of log(1 - alpha). The backward pass
replays the walk back to front, recomputes each step and applies the closed-form 3DGS gradients
``dL/dalpha_i = T_i (c_i . g) - (sum_{j>i} w_j c_j . g) / (1 - alpha_i)`` (g = dL/d pixel), the
suffix sums carried from the steps behind; pixel sums of dL/dexponent times [1, x, y, x^2, xy, y^2]
give the gradients of the 2D mean, conic and opacity. No N x H x W tensor is ever built.
:mod:`panolam.rasterizer_reference` is a separate brute-force implementation (every pixel against
every Gaussian, autograd only) that the tests check this one against.

Devices. ``backend="auto"`` uses ``gsplat.rasterization`` for CUDA tensors when gsplat's kernels
load; otherwise (saying why once per process for CUDA) the pure-PyTorch path, which runs on the
inputs' device (CPU, CUDA, any device with float64; not Apple's MPS) with autocast off (sums in the
inputs' dtype). Its host reads per camera are two, both in bin_gaussians and both sizing buffers:
the number of (Gaussian, block row) pairs, then the per-block list lengths, from which the walk is
planned on the host; the walk and the backward pass read nothing back. On a CPU the walk also drops
blocks whose pixels have all stopped, a free check there; on a device that check would be a host
read per step, so blocks walk their whole lists (stopped pixels add zeros). float64 is used only in
the O(N) projection and binning, negligible next to compositing even at a consumer GPU's float64
rate.
"""
from __future__ import annotations

import functools
import importlib
import math
import warnings
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch.autograd.function import once_differentiable

from datagen.cameras import pixel_intrinsics
from datagen.errors import optional_import

from .gaussians import Gaussians

EPS2D = 0.3                 # px^2 added to the 2D covariance diagonal
ALPHA_MAX = 0.999           # alpha clamp
ALPHA_MIN = 1.0 / 255.0     # smaller alphas are skipped
T_MIN = 1e-4                # a pixel stops before its transmittance would drop below this
EXTENT_SIGMAS = 3.33        # cap of the tile box, in standard deviations along each image axis
DEPTH_ALPHA_FLOOR = 1e-10   # expected depth = sum(w z) / max(alpha, this), as gsplat's "ED"
SCALE_MAX = 1e30            # world units; larger scales are clamped (the projection stays finite)

# The fast path evaluates at most this many (pixel, Gaussian) pairs per vectorized step: on a CPU
# about 1 MiB per float32 buffer, so a step's working set stays in the caches; on other devices
# 16 MiB, so that each kernel has work enough to hide its launch (a choice, not a measurement; the
# backward pass holds 7 such buffers).
STEP_PAIRS = 1 << 18
DEVICE_STEP_PAIRS = 1 << 22
CHUNK_MIN, CHUNK_MAX = 16, 256   # Gaussians per block per step (a power of two in this range)
BLOCK = 4                        # px side of the work blocks (a divisor of tile_size, see bin_gaussians)
_REACH_MARGIN = 1e-2             # slack on the 1/255 ellipse so rounding never drops a visible pair
# Exponents are raised to this before exp(): exp() of it is below ALPHA_MIN (skipped either way),
# and exp() of very negative numbers is slow on x86 (denormal results).
_EXPONENT_FLOOR = math.log(ALPHA_MIN) - 1.0


# ---------------------------------------------------------------------------------------------
# Public API


def rasterize(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int, background=None,
              near_plane: float = 0.01, far_plane: float = 1e10, tile_size: int = 16, backend: str = "auto"):
    """Render Gaussians -> (rgb (H, W, D), alpha (H, W, 1), expected depth (H, W, 1)).

    Conventions are in the module docstring. With viewmat (C, 4, 4) every output gets a leading C
    (background may then be (C, D)); the pure-PyTorch path renders the cameras one after the
    other, gsplat all of them in one call. ``backend``: "torch" (the pure-PyTorch path, any
    device), "gsplat" (``gsplat.rasterization``, CUDA) or "auto" (gsplat for CUDA tensors when its
    kernels load, else torch). Autocast is off inside. A Gaussian with a non-finite parameter is
    culled: it changes no pixel and gets zero gradients.
    """
    means, quats, scales, opacities, colors = _finite_or_culled(means, quats, scales, opacities, colors)
    with torch.autocast(means.device.type, enabled=False):
        if _use_gsplat(backend, means.device):
            return _rasterize_gsplat(means, quats, scales, opacities, colors, viewmat, K, width, height, background,
                                     near_plane, far_plane, tile_size)
        if viewmat.dim() == 3:
            return over_cameras(_rasterize_torch, means, quats, scales, opacities, colors, viewmat, K, width,
                                height, background, near_plane=near_plane, far_plane=far_plane, tile_size=tile_size)
        return _rasterize_torch(means, quats, scales, opacities, colors, viewmat, K, width, height, background,
                                near_plane, far_plane, tile_size)


def _rasterize_torch(means, quats, scales, opacities, colors, viewmat, K, width, height, background, near_plane,
                     far_plane, tile_size):
    """One camera through the fast path (projection, binning, block compositing)."""
    proj = project(means, quats, scales, opacities, viewmat, K, width, height, near_plane, far_plane)
    bins = bin_gaussians(proj, width, height, tile_size)
    acc = _Composite.apply(proj.means2d, proj.conics, proj.log_opacities, colors, proj.depths, bins)
    return finish(acc, background)


def _finite_or_culled(means, quats, scales, opacities, colors):
    """The inputs with every Gaussian that has a NaN or infinite parameter replaced by a harmless one
    of opacity 0 (culled). ``torch.where`` passes no gradient to the replaced values, so a NaN
    never reaches a gradient (arithmetic on it would, even multiplied by zero). Applied to every
    Gaussian, so that nothing is read back from the device."""
    finite = (torch.isfinite(means).all(-1) & torch.isfinite(quats).all(-1) & torch.isfinite(scales).all(-1)
              & torch.isfinite(opacities) & torch.isfinite(colors).all(-1))
    keep = finite[:, None]
    identity = torch.eye(1, 4, dtype=quats.dtype, device=quats.device)[0]  # (1, 0, 0, 0), made on the device
    return (torch.where(keep, means, 0.0), torch.where(keep, quats, identity), torch.where(keep, scales, 1.0),
            torch.where(finite, opacities, 0.0), torch.where(keep, colors, 0.0))


def world_to_camera(cam2world: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid OpenCV cam2world matrices (..., 4, 4), in closed form (R^T, -R^T t)."""
    rot_t = cam2world[..., :3, :3].transpose(-1, -2)
    out = torch.zeros_like(cam2world)
    out[..., :3, :3] = rot_t
    out[..., :3, 3] = -(rot_t @ cam2world[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def render_views(g: Gaussians, cam2world: torch.Tensor, K_norm: torch.Tensor, resolution: int, background=None,
                 backend: str = "auto"):
    """A batch of Gaussian sets (B, N, ...) seen by the dataset's cameras.

    cam2world (B, V, 4, 4) OpenCV, K_norm (B, V, 3, 3) normalized intrinsics (:mod:`datagen.cameras`),
    square images of ``resolution`` px; background (D,) or None (black). Returns rgb (B, V, H, W, D),
    alpha (B, V, H, W, 1), expected depth (B, V, H, W, 1).
    """
    viewmats = world_to_camera(cam2world.to(g.means.dtype))
    Ks = pixel_intrinsics(K_norm.to(g.means.dtype), resolution, resolution)  # every set: all its cameras at once
    outs = [rasterize(g.means[b], g.quats[b], g.scales[b], g.opacities[b], g.colors[b], viewmats[b], Ks[b],
                      resolution, resolution, background, backend=backend) for b in range(g.means.shape[0])]
    return tuple(torch.stack(parts) for parts in zip(*outs))


class Projection(NamedTuple):
    """Per-Gaussian screen-space quantities for one camera (culled Gaussians hold zeros)."""

    means2d: torch.Tensor        # (N, 2) px
    conics: torch.Tensor         # (N, 3) (a, b, c) of the inverse 2D covariance [[a, b], [b, c]], px^-2
    depths: torch.Tensor         # (N,) camera-space z of the mean
    log_opacities: torch.Tensor  # (N,) log(opacity)
    cov2d: torch.Tensor          # (N, 3) float64 (xx, xy, yy) of the 2D covariance, px^2 (no gradient)
    det2d: torch.Tensor          # (N,) float64 determinant of the 2D covariance, px^4 (no gradient; 1 if culled)
    radii: torch.Tensor          # (N, 2) float64 half sizes (rx, ry) of the tile box, px (no gradient)
    valid: torch.Tensor          # (N,) bool: not culled


def project(means, quats, scales, opacities, viewmat, K, width: int, height: int, near_plane: float = 0.01,
            far_plane: float = 1e10) -> Projection:
    """EWA projection of N Gaussians into one camera (differentiable, float64 inside).

    Scales above ``SCALE_MAX`` world units are clamped to it, so float64 never overflows. With M the
    2x3 projected factor (rows m0, m1: cov2d = M M^T + EPS2D I), the determinant is computed as
    ``|m0 x m1|^2 + EPS2D (|m0|^2 + |m1|^2) + EPS2D^2`` (Lagrange's identity): positive, and free of
    the cancellation of ``a c - b^2`` that culls or distorts needle-like Gaussians (one axis of
    1e6 px and more).
    """
    wd = torch.float64
    view, Kd = viewmat.to(wd), K.detach().to(wd)
    cam = means.to(wd) @ view[:3, :3].T + view[:3, 3]
    x, y, z = cam.unbind(-1)
    in_depth = (z >= near_plane) & (z <= far_plane) & (z > 0)
    z = torch.where(in_depth, z, torch.ones_like(z))  # culled depths replaced so nothing divides by 0
    fx, fy, cx, cy = Kd[0, 0], Kd[1, 1], Kd[0, 2], Kd[1, 2]
    jac = _perspective_jacobian(x, y, z, fx, fy, cx, cy, width, height)
    m = (jac @ view[:3, :3] @ quat_to_rotmat(quats.to(wd))) * scales.to(wd).clamp(max=SCALE_MAX)[:, None, :]
    m0, m1 = m.unbind(1)
    n0, n1 = m0.square().sum(-1), m1.square().sum(-1)
    a, b, c = n0 + EPS2D, (m0 * m1).sum(-1), n1 + EPS2D
    det = torch.linalg.cross(m0, m1).square().sum(-1) + EPS2D * (n0 + n1) + EPS2D * EPS2D
    ok = in_depth & torch.isfinite(det)
    det = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c, -b, a], -1) / det[:, None]
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], -1)
    dtype = means.dtype
    valid = ok & (opacities >= ALPHA_MIN) & torch.isfinite(means2d.to(dtype)).all(-1)
    keep = valid[:, None]
    cov2d = torch.stack([a, b, c], -1).detach()
    return Projection(
        means2d=torch.where(keep, means2d, 0.0).to(dtype),
        conics=torch.where(keep, conics, 0.0).to(dtype),
        depths=torch.where(valid, z, 0.0).to(dtype),
        log_opacities=torch.log(torch.where(valid, opacities, torch.ones_like(opacities))),
        cov2d=torch.where(keep, cov2d, 0.0),
        det2d=torch.where(valid, det, 1.0).detach(),
        radii=torch.where(keep, tile_radii(cov2d, opacities.detach().to(wd)), 0.0),
        valid=valid,
    )


def tile_radii(cov2d, opacities):
    """(N, 2) half sizes (rx, ry) px of the tile boxes, ``ceil(e sqrt(cov2d_xx))`` and
    ``ceil(e sqrt(cov2d_yy))`` with ``e = min(3.33, sqrt(2 ln(o / (1/255))))``, from cov2d (N, 3)
    (xx, xy, yy) px^2 and the (N,) opacities (module docstring; NaN below opacity 1/255: culled)."""
    extent = torch.sqrt(2.0 * torch.log(opacities / ALPHA_MIN)).clamp_max(EXTENT_SIGMAS)
    return torch.ceil(extent[:, None] * torch.sqrt(cov2d[:, 0::2]))


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """(N, 4) wxyz quaternions, any norm -> (N, 3, 3) rotation matrices (a zero quaternion -> identity)."""
    w, x, y, z = F.normalize(quats, dim=-1, eps=1e-12).unbind(-1)
    rows = [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]
    return torch.stack(rows, -1).reshape(-1, 3, 3)


def _perspective_jacobian(x, y, z, fx, fy, cx, cy, width, height):
    """(N, 2, 3) Jacobian of uv w.r.t. the camera-space point, x/z and y/z clamped as gsplat does."""
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    tx = z * torch.clamp(x / z, -(cx / fx + 0.3 * tan_x), (width - cx) / fx + 0.3 * tan_x)
    ty = z * torch.clamp(y / z, -(cy / fy + 0.3 * tan_y), (height - cy) / fy + 0.3 * tan_y)
    zero = torch.zeros_like(z)
    return torch.stack([fx / z, zero, -fx * tx / (z * z), zero, fy / z, -fy * ty / (z * z)], -1).reshape(-1, 2, 3)


class Bins(NamedTuple):
    """The (block, Gaussian) pairs of one camera, grouped by block, front to back within a block.

    Blocks are ``block`` px squares numbered row-major, ``id = by * blocks_x + bx``; block
    (bx, by) covers pixel columns ``[bx * block, (bx + 1) * block)`` and the same rows.
    """

    width: int
    height: int
    block: int
    blocks_x: int
    blocks_y: int
    gaussian_ids: torch.Tensor  # (M,) int64, on the device of the Gaussians
    offsets: torch.Tensor       # (blocks,) int64 on the CPU: start of each block's list in gaussian_ids
    counts: torch.Tensor        # (blocks,) int64 on the CPU: length of each block's list


def tile_ranges(means2d, radii, width: int, height: int, tile_size: int):
    """Tile box [x0, x1) x [y0, y1) (int64 tensors) that each Gaussian's [u +- rx] x [v +- ry] touches."""
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    u, v = means2d.detach().to(torch.float64).unbind(-1)
    rx, ry = radii.to(torch.float64).unbind(-1)
    box = lambda lo, hi, n: (torch.floor(lo / tile_size).clamp(0, n).long(),  # noqa: E731
                             torch.ceil(hi / tile_size).clamp(0, n).long())
    x0, x1 = box(u - rx, u + rx, tiles_x)
    y0, y1 = box(v - ry, v + ry, tiles_y)
    return x0, x1, y0, y1


@torch.no_grad()
def bin_gaussians(proj: Projection, width: int, height: int, tile_size: int = 16) -> Bins:
    """Pair every valid Gaussian with the pixel blocks where it can be visible; lists sorted by depth.

    Blocks are ``gcd(tile_size, BLOCK)`` px. A block is paired with a Gaussian when (i) its tile lies
    in the Gaussian's tile box (the rasterization rule of the module docstring) and (ii) the ellipse
    ``o exp(-0.5 d^T conic d) >= 1/255`` spans a pixel column of the block within the block's rows.
    (ii) only drops pairs whose alpha is below 1/255 on the whole block, which compositing skips
    anyway: the image is the one whole tiles give, for much less work. The ellipse's exact column
    range is computed once per (Gaussian, block row). Reads two numbers back from the device: the
    count of (Gaussian, block row) pairs and the per-block list lengths (see the module docstring).
    """
    block = math.gcd(tile_size, BLOCK)
    per_tile = tile_size // block
    blocks_x, blocks_y = -(-width // block), -(-height // block)
    x0, x1, y0, y1 = tile_ranges(proj.means2d, proj.radii, width, height, tile_size)
    u, v = proj.means2d.detach().to(torch.float64).unbind(-1)
    sxx, sxy, syy = proj.cov2d.unbind(-1)
    reach = torch.where(proj.valid, 2.0 * (proj.log_opacities.detach().double() - math.log(ALPHA_MIN)), 0.0)
    reach = reach + _REACH_MARGIN                       # the ellipse is d^T cov2d^-1 d <= reach
    det = proj.det2d
    half_y = torch.sqrt(reach * syy)
    # Block rows holding a pixel-centre row inside the ellipse, within the tile box and the image.
    by0 = torch.maximum(y0 * per_tile, torch.floor(torch.ceil(v - half_y - 0.5) / block).clamp(0, blocks_y).long())
    by1 = torch.minimum((y1 * per_tile).clamp_max(blocks_y),
                        torch.floor(torch.floor(v + half_y - 0.5) / block).clamp(-1, blocks_y).long() + 1)
    n_rows = torch.where(proj.valid, (by1 - by0).clamp_min(0), 0)
    order = torch.argsort(proj.depths.detach(), stable=True)  # pairs are generated front to back
    n_rows = n_rows[order]
    total_rows = int(n_rows.sum())                      # host read 1: sizes the row pairs
    g_row = torch.repeat_interleave(order, n_rows, output_size=total_rows)
    by = by0[g_row] + _ranks(n_rows, total_rows)
    per_gaussian = torch.stack([u, v, sxx, sxy, syy, det, reach, half_y, (x0 * per_tile).double(),
                                (x1 * per_tile).clamp_max(blocks_x).double()], 1)
    u, v, sxx, sxy, syy, det, reach, half_y, bx_first, bx_end = per_gaussian.index_select(0, g_row).unbind(1)
    y_lo = torch.maximum(by * block + 0.5 - v, -half_y)     # pixel-centre rows of the block, in the ellipse
    y_hi = torch.minimum(by * block + (block - 0.5) - v, half_y)
    x_lo, x_hi = _ellipse_columns(sxx, sxy, syy, det, reach, y_lo, y_hi)
    bx0 = torch.maximum(torch.floor(torch.ceil(u + x_lo - 0.5) / block), bx_first)
    bx1 = torch.minimum(torch.floor(torch.floor(u + x_hi - 0.5) / block) + 1, bx_end)
    n_blocks = torch.where(y_lo <= y_hi, (bx1 - bx0).clamp_min(0), 0.0).long()
    first = torch.where(n_blocks > 0, by * blocks_x + bx0.long(), 0)  # each row's run of block ids
    # Per-block list lengths from the runs' ends (+1 at the first block, -1 after the last), read
    # back once: they size the pairs and plan the compositing walk.
    edges = torch.zeros(blocks_x * blocks_y + 1, dtype=torch.long, device=first.device)
    edges.index_add_(0, first, torch.ones_like(first)).index_add_(0, first + n_blocks, -torch.ones_like(first))
    counts = torch.cumsum(edges[:-1], 0).cpu()           # host read 2
    total = int(counts.sum())
    gid = torch.repeat_interleave(g_row, n_blocks, output_size=total)
    ids = torch.repeat_interleave(first, n_blocks, output_size=total) + _ranks(n_blocks, total)
    ids, perm = torch.sort(ids, stable=True)            # stable: depth order survives within a block
    return Bins(width, height, block, blocks_x, blocks_y, gid[perm], torch.cumsum(counts, 0) - counts, counts)


def _ranks(counts: torch.Tensor, total: int) -> torch.Tensor:
    """0, 1, ..., counts[0] - 1, 0, 1, ..., counts[1] - 1, ...: the index of each repeat (total =
    counts.sum(), known on the host)."""
    starts = torch.cumsum(counts, 0) - counts
    return (torch.arange(total, device=counts.device)
            - torch.repeat_interleave(starts, counts, output_size=total))


def _ellipse_columns(sxx, sxy, syy, det, reach, y_lo, y_hi):
    """Range of x over the ellipse ``d^T S^-1 d <= reach`` (S = [[sxx, sxy], [sxy, syy]], det = |S|)
    within the band y_lo <= y <= y_hi (a non-empty part of [-sqrt(reach syy), sqrt(reach syy)]).

    The right edge x(y) = (sxy y + sqrt(det (reach syy - y^2))) / syy is concave, largest at the
    ellipse's rightmost point y = sxy sqrt(reach / sxx); the left edge mirrors it. Clamping that y
    into the band gives the band's extreme.
    """
    y_extreme = sxy * torch.sqrt(reach / sxx)
    y_right, y_left = torch.clamp(y_extreme, y_lo, y_hi), torch.clamp(-y_extreme, y_lo, y_hi)
    root = lambda y: torch.sqrt((det * (reach * syy - y * y)).clamp_min(0.0))  # noqa: E731
    return (sxy * y_left - root(y_left)) / syy, (sxy * y_right + root(y_right)) / syy


# ---------------------------------------------------------------------------------------------
# Helpers of the public API


def over_cameras(render, means, quats, scales, opacities, colors, viewmats, Ks, width, height, background,
                       **options):
    """Loop ``render`` over C cameras and stack the outputs."""
    C = viewmats.shape[0]
    Ks = Ks.expand(C, 3, 3)
    bgs = [None] * C if background is None else background.expand(C, colors.shape[-1])
    outs = [render(means, quats, scales, opacities, colors, viewmats[i], Ks[i], width, height, bgs[i], **options)
            for i in range(C)]
    return tuple(torch.stack(parts) for parts in zip(*outs))


def finish(acc, background):
    """(H, W, D + 2) sums [w c, w z, w] -> (rgb, alpha, expected depth), background composited."""
    colors, depth_sum, alpha = acc[..., :-2], acc[..., -2:-1], acc[..., -1:]
    depth = depth_sum / alpha.clamp_min(DEPTH_ALPHA_FLOOR)
    if background is not None:
        colors = colors + (1.0 - alpha) * background
    return colors, alpha, depth


def _use_gsplat(backend: str, device: torch.device) -> bool:
    """Whether ``rasterize`` hands tensors on ``device`` to gsplat (its docstring). "auto" checks that
    gsplat's CUDA kernels load (gsplat builds them on first use, which takes minutes once) and
    otherwise takes the pure-PyTorch path, saying why once per reason."""
    if backend not in ("auto", "torch", "gsplat"):
        raise ValueError(f"unknown backend {backend!r}; choose auto, torch or gsplat")
    if backend != "auto" or device.type != "cuda":
        return backend == "gsplat"
    try:
        kernels = importlib.import_module("gsplat.cuda._backend")._C
    except (ImportError, RuntimeError, OSError) as e:  # not installed, or torch's extension build failed
        _say_torch_on_cuda(f"gsplat is unusable here ({type(e).__name__}: {(str(e) or '-').splitlines()[0]})")
        return False
    if kernels is None:
        _say_torch_on_cuda("gsplat found no CUDA toolkit (nvcc) to build its kernels")
    return kernels is not None


@functools.cache
def _say_torch_on_cuda(reason: str) -> None:
    """The warning, once per process and reason, that CUDA tensors take the pure-PyTorch path."""
    warnings.warn(f"{reason}: CUDA tensors are rendered by the pure-PyTorch rasterizer (same images, slower); "
                  "see 'Rasterizer on GPUs' in the README", stacklevel=4)


def _rasterize_gsplat(means, quats, scales, opacities, colors, viewmat, K, width, height, background, near_plane,
                      far_plane, tile_size):
    """All cameras in one ``gsplat.rasterization`` call ("RGB+ED"), the background composited by
    gsplat (``backgrounds=``, one row per camera)."""
    rasterization = optional_import("gsplat", "cuda", "the gsplat rasterizer").rasterization

    cameras = viewmat.dim() == 3
    viewmats = viewmat if cameras else viewmat[None]
    Ks = K.expand(len(viewmats), 3, 3) if cameras else K[None]
    backgrounds = None if background is None else background.expand(len(viewmats), colors.shape[-1])
    render, alpha, _ = rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                                     near_plane=near_plane, far_plane=far_plane, tile_size=tile_size, eps2d=EPS2D,
                                     backgrounds=backgrounds, render_mode="RGB+ED", rasterize_mode="classic")
    out = render[..., :-1], alpha, render[..., -1:]
    return out if cameras else tuple(t[0] for t in out)


# ---------------------------------------------------------------------------------------------
# Fast path: chunked block compositing with a closed-form backward

# Columns of the per-Gaussian table the compositing steps gather from.
_U, _V, _A, _B, _C, _LOGO, _FEAT = range(7)   # _FEAT: first of the features [colors..., z, 1]


class _Step(NamedTuple):
    """One vectorized step: k Gaussians (padded) from each of b blocks."""

    blocks: torch.Tensor     # (b,) block ids
    gids: torch.Tensor       # (b, k) Gaussian ids (padding repeats a valid id; its log-opacity is -inf)
    params: torch.Tensor     # (b, k, cols) gathered table rows, u and v relative to the block centre
    carry_in: torch.Tensor   # (b, P) log transmittance of each pixel before the step (-inf: stopped)


class _Geometry:
    """Pixel coordinates of a block and block centres, in the dtype and on the device of the computation."""

    def __init__(self, bins: Bins, dtype, device: torch.device):
        bs = bins.block
        self.pixels = bs * bs
        # Pixel centres from the block centre.
        self.coords = torch.arange(bs, dtype=dtype, device=device) + (0.5 - bs / 2)
        yy, xx = torch.meshgrid(self.coords, self.coords, indexing="ij")
        self.moment_basis = torch.stack([torch.ones_like(xx), xx, yy, xx * xx, xx * yy, yy * yy]).reshape(6, -1)
        block = torch.arange(bins.blocks_x * bins.blocks_y, device=device)
        self.centres = torch.stack([(block % bins.blocks_x) * bs, (block // bins.blocks_x) * bs], -1).to(dtype) + bs / 2
        step_pairs = STEP_PAIRS if device.type == "cpu" else DEVICE_STEP_PAIRS
        self.capacity = max(step_pairs, self.pixels * CHUNK_MIN)

    def chunk_length(self, n_blocks: int, longest: int) -> int:
        """Gaussians per block for a step over n_blocks blocks whose longest remaining list is
        ``longest``: a power of two that fills the capacity, no longer than needed."""
        k = min(max(self.capacity // (n_blocks * self.pixels), CHUNK_MIN), CHUNK_MAX)
        return min(1 << (k.bit_length() - 1), 1 << (longest - 1).bit_length())


def _outside_image(bins: Bins, device: torch.device) -> torch.Tensor:
    """(blocks, P) bool: pixels of edge blocks that lie outside the image."""
    bs = bins.block
    cols = torch.arange(bins.blocks_x * bs, device=device).reshape(bins.blocks_x, 1, bs) >= bins.width
    rows = torch.arange(bins.blocks_y * bs, device=device).reshape(bins.blocks_y, bs, 1) >= bins.height
    mask = rows[:, None, :, :] | cols[None, :, :, :]  # (blocks_y, blocks_x, bs, bs)
    return mask.reshape(bins.blocks_x * bins.blocks_y, bs * bs)


def _blocks_to_image(x: torch.Tensor, bins: Bins) -> torch.Tensor:
    """(blocks, F, P) -> (H, W, F)."""
    bs = bins.block
    x = x.reshape(bins.blocks_y, bins.blocks_x, -1, bs, bs).permute(0, 3, 1, 4, 2)
    return x.reshape(bins.blocks_y * bs, bins.blocks_x * bs, -1)[: bins.height, : bins.width]


def _image_to_blocks(x: torch.Tensor, bins: Bins) -> torch.Tensor:
    """(H, W, F) -> (blocks, F, P), zero outside the image."""
    bs = bins.block
    x = F.pad(x, (0, 0, 0, bins.blocks_x * bs - bins.width, 0, bins.blocks_y * bs - bins.height))
    x = x.reshape(bins.blocks_y, bs, bins.blocks_x, bs, -1).permute(0, 2, 4, 1, 3)
    return x.reshape(bins.blocks_x * bins.blocks_y, -1, bs * bs).contiguous()


def _gather(table, bins: Bins, geo: _Geometry, blocks, start, remaining, k: int):
    """Gaussian ids and table rows of the next k Gaussians of each block (padded with log-opacity -inf):
    those from position ``start`` of its list, of which ``remaining`` are left ((b,) device tensors)."""
    j = torch.arange(k, device=table.device)
    idx = start[:, None] + j
    pad = j >= remaining[:, None]
    gids = torch.take(bins.gaussian_ids, idx.clamp_max(bins.gaussian_ids.numel() - 1))
    params = table.index_select(0, gids.flatten()).view(*gids.shape, -1)
    params[..., _U:_V + 1] -= geo.centres[blocks][:, None, :]
    params[..., _LOGO].masked_fill_(pad, -math.inf)
    return gids, params


def _raw_alpha(out, params, coords):
    """(b, P, k) ``o exp(-0.5 d^T conic d)`` (before clamping and skipping) into ``out``.

    The exponent is a per-row term plus a per-column term plus the product of the two offsets,
    so only two full-size ops build it.
    """
    b, k = params.shape[:2]
    bs = coords.numel()
    u, v, a, bb, c, logo = (params[..., i][:, None, :] for i in range(_FEAT))
    dx = coords[None, :, None] - u                      # (b, bs, k): per column
    dy = coords[None, :, None] - v                      # (b, bs, k): per row
    row = logo - 0.5 * c * dy * dy
    col = -0.5 * a * dx * dx
    grid = out.view(b, bs, bs, k)                       # (block row, block column)
    torch.addcmul(row[:, :, None, :], (bb * dy)[:, :, None, :], dx[:, None, :, :], value=-1.0, out=grid)
    grid.add_(col[:, None, :, :])
    return out.clamp_min_(_EXPONENT_FLOOR).exp_()


def _views(workspace, b: int, pixels: int, k: int, count: int):
    """``count`` (b, P, k) views into the preallocated workspace."""
    return [workspace[i, : b * pixels * k].view(b, pixels, k) for i in range(count)]


def _forward_step(workspace, params, carry, coords, pixels):
    """Composite one step -> ((b, F, P) sums of w * features, (b, P) log transmittance after it)."""
    b, k = params.shape[:2]
    alpha, log1m, log_t, weight = _views(workspace, b, pixels, k, 4)
    _raw_alpha(alpha, params, coords).clamp_max_(ALPHA_MAX)
    F.threshold_(alpha, _below(ALPHA_MIN, alpha.dtype), 0.0)
    torch.neg(alpha, out=log1m).log1p_()
    torch.cumsum(log1m, 2, out=log_t).add_(carry[:, :, None])    # log T after each Gaussian
    F.threshold_(log_t, _below(math.log(T_MIN), log_t.dtype), -math.inf)  # stopped: -inf from here on
    torch.sub(log_t, log1m, out=weight).exp_().mul_(alpha)    # w = T_before * alpha
    return torch.bmm(params[..., _FEAT:].transpose(1, 2), weight.transpose(1, 2)), log_t[:, :, -1].clone()


def _backward_step(workspace, params, carry, grad, behind, geo: _Geometry):
    """Gradients of one step.

    grad (b, F, P) = dL/d(per-pixel sums); behind (b, P) = sum of w_j (c_j . grad) over the
    Gaussians of later steps. Returns ((b, k, 6 + F) dL/d table columns, (b, P) this step's sum).
    """
    b, k = params.shape[:2]
    alpha, neg_alpha, log1m, log_t, trans, weight, dot = _views(workspace, b, geo.pixels, k, 7)
    _raw_alpha(alpha, params, geo.coords)
    F.threshold_(alpha, _below(ALPHA_MIN, alpha.dtype), 0.0)
    F.threshold_(torch.neg(alpha, out=neg_alpha), -ALPHA_MAX, 0.0)  # -alpha where not clamped, else 0
    alpha.clamp_max_(ALPHA_MAX)
    torch.neg(alpha, out=log1m).log1p_()
    torch.cumsum(log1m, 2, out=log_t).add_(carry[:, :, None])
    F.threshold_(log_t, _below(math.log(T_MIN), log_t.dtype), -math.inf)
    torch.sub(log_t, log1m, out=trans).exp_()              # T_i, 0 once the pixel has stopped
    torch.mul(trans, alpha, out=weight)                   # w_i
    features = params[..., _FEAT:]
    d_features = torch.bmm(grad, weight).transpose(1, 2)  # dL/dc_i = sum_p w_i g
    torch.bmm(grad.transpose(1, 2), features.transpose(1, 2), out=dot)  # c_i . g
    suffix = torch.cumsum(weight.mul_(dot), 2, out=log_t)  # prefix sums of w_j (c_j . g) within the step
    total = suffix[:, :, -1].clone()
    torch.sub((behind + total)[:, :, None], suffix, out=suffix)  # sum over j > i (0 once stopped)
    suffix.div_(torch.neg(alpha, out=log1m).add_(1.0))
    d_alpha = dot.mul_(trans).sub_(suffix)               # dL/dalpha_i
    neg_d_exponent = d_alpha.mul_(neg_alpha)             # -dL/d(log o - 0.5 d^T conic d)
    moments = torch.matmul(geo.moment_basis, neg_d_exponent).neg_()  # (b, 6, k): sum_p dG [1 x y xx xy yy]
    return torch.cat([_exponent_grads(moments, params), d_features], -1), total


def _exponent_grads(moments, params):
    """(b, k, 6) dL/d(u, v, a, b, c, log o) from the pixel moments of dL/dG, G = log o - 0.5 d^T conic d."""
    m0, mx, my, mxx, mxy, myy = moments.unbind(1)
    u, v, a, b, c = (params[..., i] for i in range(_LOGO))
    sx, sy = mx - u * m0, my - v * m0                           # sum dG dx, sum dG dy (dx = x - u)
    sxx = mxx - 2 * u * mx + u * u * m0
    sxy = mxy - u * my - v * mx + u * v * m0
    syy = myy - 2 * v * my + v * v * m0
    return torch.stack([a * sx + b * sy, b * sx + c * sy, -0.5 * sxx, -sxy, -0.5 * syy, m0], -1)


@functools.cache
def _below(x: float, dtype) -> float:
    """The largest value of ``dtype`` below x: ``threshold_(t, _below(x), v)`` keeps t >= x."""
    return torch.nextafter(torch.tensor(x, dtype=dtype), torch.tensor(-math.inf, dtype=dtype)).item()


def _composite_forward(table, bins: Bins, geo: _Geometry):
    """Walk every block's list front to back -> ((blocks, F, P) sums, steps for the backward pass).

    The walk is planned on the host from ``bins.counts``; each step's block ids and list positions
    go to the device in one non-blocking copy (no wait for the device). On a CPU, blocks whose
    pixels have all stopped leave the walk (module docstring)."""
    device, dtype = table.device, table.dtype
    n_blocks, pixels = bins.blocks_x * bins.blocks_y, geo.pixels
    carry = torch.zeros(n_blocks, pixels, dtype=dtype, device=device).masked_fill_(_outside_image(bins, device),
                                                                                   -math.inf)
    acc = torch.zeros(n_blocks, table.shape[1] - _FEAT, pixels, dtype=dtype, device=device)
    workspace = torch.empty(4, geo.capacity, dtype=dtype, device=device)
    done_count = torch.zeros(n_blocks, dtype=torch.long)   # host, as bins.counts and bins.offsets
    active = torch.nonzero(bins.counts > 0).flatten()
    steps = []
    while active.numel():
        k = geo.chunk_length(active.numel(), int((bins.counts[active] - done_count[active]).max()))
        for batch in active.split(max(1, geo.capacity // (pixels * k))):
            plan = torch.stack([batch, bins.offsets[batch] + done_count[batch], bins.counts[batch] - done_count[batch]])
            blocks, start, remaining = plan.to(device, non_blocking=True)
            gids, params = _gather(table, bins, geo, blocks, start, remaining, k)
            carry_in = carry.index_select(0, blocks)
            out, carry_out = _forward_step(workspace, params, carry_in, geo.coords, pixels)
            carry.index_copy_(0, blocks, carry_out)
            acc.index_add_(0, blocks, out)
            steps.append(_Step(blocks, gids, params, carry_in))
        done_count[active] += k
        finished = done_count[active] >= bins.counts[active]
        if device.type == "cpu":
            finished |= torch.isneginf(carry[active]).all(1)
        active = active[~finished]
    return acc, steps


def _composite_backward(grad_blocks, steps, n_gaussians: int, geo: _Geometry):
    """Replay the steps back to front -> (N, 6 + F) dL/d table columns."""
    like = dict(dtype=grad_blocks.dtype, device=grad_blocks.device)
    grads = torch.zeros(n_gaussians, _FEAT + grad_blocks.shape[1], **like)
    behind = torch.zeros(grad_blocks.shape[0], grad_blocks.shape[2], **like)
    workspace = torch.empty(7, geo.capacity, **like)
    for step in reversed(steps):
        g = grad_blocks.index_select(0, step.blocks)
        d_table, total = _backward_step(workspace, step.params, step.carry_in, g, behind.index_select(0, step.blocks),
                                        geo)
        behind.index_add_(0, step.blocks, total)
        grads.index_add_(0, step.gids.flatten(), d_table.flatten(0, 1))
    return grads


class _Composite(torch.autograd.Function):
    """(means2d, conics, log opacities, colors, depths, bins) -> (H, W, D + 2) sums [w c, w z, w]."""

    @staticmethod
    def forward(ctx, means2d, conics, log_opacities, colors, depths, bins: Bins):
        table = torch.cat([means2d, conics, log_opacities[:, None], colors, depths[:, None],
                           torch.ones_like(depths)[:, None]], -1).contiguous()
        geo = _Geometry(bins, table.dtype, table.device)
        acc, steps = _composite_forward(table, bins, geo)
        ctx.bins, ctx.geo, ctx.steps = bins, geo, steps
        ctx.n_gaussians, ctx.n_colors = means2d.shape[0], colors.shape[-1]
        return _blocks_to_image(acc, bins)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        d = ctx.n_colors
        grads = _composite_backward(_image_to_blocks(grad, ctx.bins), ctx.steps, ctx.n_gaussians, ctx.geo)
        return (grads[:, _U:_V + 1], grads[:, _A:_C + 1], grads[:, _LOGO], grads[:, _FEAT:_FEAT + d],
                grads[:, _FEAT + d], None)
