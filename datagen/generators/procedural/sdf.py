"""Units and signed-distance building blocks: points are (N, 3) float32 tensors, distances (N,).

The head is modelled in head units (the skull about 0.4 wide, face toward +z, y up); ``HEAD_SCALE``
turns them into world units, in which the head lives in the box [-BOX, BOX]^3.
"""
from __future__ import annotations

import math

import torch

BOX = 0.48  # the head lives in [-BOX, BOX]^3 (world units)
HEAD_SCALE = 0.82  # head coordinates -> world: frames the head like an EG3D/FFHQ crop at radius 2.7


def f32(v):
    return torch.as_tensor(v, dtype=torch.float32)


def _norm3(x, y, z):
    return torch.sqrt(x * x + y * y + z * z)


def sd_ellipsoid(p, center, radii):
    """Bound of the distance to an axis-aligned ellipsoid (exact on the surface)."""
    (cx, cy, cz), (rx, ry, rz) = center, radii
    x, y, z = (p[:, 0] - cx) / rx, (p[:, 1] - cy) / ry, (p[:, 2] - cz) / rz
    k0 = _norm3(x, y, z)
    k1 = _norm3(x / rx, y / ry, z / rz).clamp_min(1e-9)
    return k0 * (k0 - 1.0) / k1


def sd_sphere(p, center, radius):
    cx, cy, cz = center
    return _norm3(p[:, 0] - cx, p[:, 1] - cy, p[:, 2] - cz) - radius


def sd_capsule(p, a, b, ra, rb):
    """Distance to a capsule from a to b whose radius goes linearly from ra to rb."""
    ax, ay, az = (float(v) for v in a)
    bx, by, bz = (float(v) - float(w) for v, w in zip(b, a))
    x, y, z = p[:, 0] - ax, p[:, 1] - ay, p[:, 2] - az
    h = ((x * bx + y * by + z * bz) / (bx * bx + by * by + bz * bz)).clamp(0.0, 1.0)
    return _norm3(x - h * bx, y - h * by, z - h * bz) - (ra + (rb - ra) * h)


def sd_ellipse_2d(x, y, ax, ay):
    """Bound of the distance to an ellipse in a plane (exact on the curve)."""
    qx, qy = x / ax, y / ay
    k0 = torch.sqrt(qx * qx + qy * qy)
    k1 = torch.sqrt((qx / ax) ** 2 + (qy / ay) ** 2).clamp_min(1e-9)
    return k0 * (k0 - 1.0) / k1


def segment_2d(x, y, a, b):
    """Distance in a plane from points (x, y) to the segment from a to b ((x, y) pairs)."""
    ex, ey = b[0] - a[0], b[1] - a[1]
    vx, vy = x - a[0], y - a[1]
    h = ((vx * ex + vy * ey) / (ex * ex + ey * ey)).clamp(0.0, 1.0)
    return torch.sqrt((vx - h * ex) ** 2 + (vy - h * ey) ** 2)


def sd_triangle_2d(x, y, a, b, c):
    """Exact signed distance in a plane from points (x, y) to the triangle a, b, c ((x, y) pairs, either
    winding); negative inside."""
    edges = ((a, b), (b, c), (c, a))
    d = torch.minimum(torch.minimum(segment_2d(x, y, a, b), segment_2d(x, y, b, c)), segment_2d(x, y, c, a))
    # Inside when the point lies on the same side of all three edges (cross products of one sign).
    side = [(v[0] - u[0]) * (y - u[1]) - (v[1] - u[1]) * (x - u[0]) for u, v in edges]
    inside = ((side[0] >= 0) & (side[1] >= 0) & (side[2] >= 0)) | ((side[0] <= 0) & (side[1] <= 0) & (side[2] <= 0))
    return torch.where(inside, -d, d)


def extrude(d2, h):
    """Exact distance of a 2D region (signed distance d2) extruded to a slab of half-thickness h (h signed
    distance to the slab's mid-plane given as ``h`` = |offset| - half)."""
    outside = torch.stack([d2.clamp_min(0.0), h.clamp_min(0.0)], -1).norm(dim=-1)
    return outside + torch.maximum(d2, h).clamp_max(0.0)


def ellipsoid_front_z(center, radii, x, y):
    """z of the front of an axis-aligned ellipsoid at (x, y) (its centre's z beyond the outline)."""
    cx, cy, cz = center
    rx, ry, rz = radii
    s = max(1e-4, 1.0 - ((x - cx) / rx) ** 2 - ((y - cy) / ry) ** 2)
    return cz + rz * math.sqrt(s)


def smin(a, b, k):
    """Smooth union of two distances, blended over about ``k``."""
    h = (0.5 + 0.5 * (b - a) / k).clamp(0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def smax(a, b, k):
    """Smooth intersection of two distances, blended over about ``k``."""
    return -smin(-a, -b, k)


def smoothstep(e0, e1, x):
    t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def gauss(a, sa):
    return torch.exp(-(a / sa) ** 2)


def interp(x, xs, ys):
    """Piecewise-linear y(x) through the knots (xs ascending), constant outside them."""
    xs_t, ys_t = f32(xs), f32(ys)
    i = torch.bucketize(x.clamp(xs[0], xs[-1]), xs_t).clamp(1, len(xs) - 1)
    x0, x1, y0, y1 = xs_t[i - 1], xs_t[i], ys_t[i - 1], ys_t[i]
    return y0 + (y1 - y0) * ((x - x0) / (x1 - x0)).clamp(0.0, 1.0)


def wave_noise(p, waves):
    """Smooth pseudo-noise: a sum of sinusoids; waves is a list of (amp, (wx, wy, wz), phase)."""
    out = torch.zeros(p.shape[0])
    for amp, w, ph in waves:
        out = out + amp * torch.sin(p @ f32(w) + ph)
    return out


def near_box(p, lo, hi, fn, margin=0.04):
    """Parts that lie inside the box [lo, hi], evaluated only within ``margin`` of it: fn(points) ->
    [(sdf, rgb or None)]. Elsewhere the distance to the box stands in for each sdf (a lower bound of
    the part's distance, and at least ``margin``, so it changes neither the surface nor its colour)."""
    lo, hi = f32(lo), f32(hi)
    gap = torch.maximum(lo - p, p - hi).clamp_min(0.0)
    outside = gap.norm(dim=-1)
    idx = torch.nonzero(gap.amax(-1) < margin).squeeze(1)
    if idx.numel() == 0:
        return [(outside, None)] * len(fn(p[:1]))
    out = []
    for ds, cs in fn(p[idx]):
        d = outside.index_put((idx,), ds)
        rgb = None if cs is None else torch.zeros(p.shape[0], 3).index_put((idx,), cs)
        out.append((d, rgb))
    return out
