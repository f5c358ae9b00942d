"""Hair as a signed distance (head units): nine styles over the skull, and its strand texture."""
from __future__ import annotations

import math

import numpy as np
import torch

from .anatomy import cranium
from .sdf import gauss, interp, near_box, smoothstep, f32, sd_capsule, sd_ellipsoid, sd_sphere, smax, smin


PONYTAIL_RADII = (0.034, 0.022)  # at the tie and at the end (head units; the end at least 2 grid voxels thick)


def hair_strands(p, P, flow_y=True):
    """Hair texture: fine streaks along the flow (random directions across it, no centre) and clumps."""
    s = torch.zeros(p.shape[0])
    for i, v in enumerate(P["hair_seed"]):
        k = np.asarray(v, dtype=np.float64)
        if flow_y:
            k[1] *= 0.12
        k = k / (np.linalg.norm(k) + 1e-9) * (170.0 + 28.0 * i)
        s = s + torch.sin(p @ f32(k) + float(v[0] * 3.0))
    fine = s / math.sqrt(len(P["hair_seed"]))  # about unit variance
    clump = torch.sin(p @ f32(np.asarray(P["hair_seed"][0]) * 22.0) + 1.0) * torch.sin(p @ f32(np.asarray(P["hair_seed"][1]) * 17.0))
    return 0.86 + 0.12 * fine.clamp(-2, 2) / 2 + 0.08 * clump


def _hairline(p, P, nape, front=None, ear_gap=True):
    """Positive below the hairline (no hair), negative above it: a curve from the forehead round the
    temples and over the ears to the nape."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2] + 0.02
    az = torch.atan2(x.abs(), z)
    f = P["hairline_height"] if front is None else front
    ear_top = P["ear_y"] + P["ear_size"] * 0.95
    xs = [0.0, 0.5, 0.95, 1.2, 1.45, 1.75, 2.05, 2.5, math.pi]
    if ear_gap:
        ys = [f, f - 0.012, f - 0.035, P["ear_y"] - 0.01, ear_top + 0.008, ear_top + 0.004, ear_top - 0.04, nape + 0.02, nape]
    else:
        ys = [f, f - 0.012, f - 0.04, P["ear_y"] - 0.02, P["ear_y"] - 0.03, P["ear_y"] - 0.05, nape + 0.04, nape + 0.02, nape]
    return 0.7 * (interp(az, xs, ys) - y)


def _ponytail(p, P, A):
    """A ponytail tied at the back of the crown and lying along the back of the head and the neck down to
    ``hair_length``: tapering capsules through the skin's profile there (``A["ponytail"]``), each centre
    0.4 of its radius out from the skin, so that the tail is sunk into the head along its whole length."""
    knots = A["ponytail"]
    radii = np.linspace(PONYTAIL_RADII[0], PONYTAIL_RADII[1], len(knots))
    centres = [(0.0, y, z - 0.4 * r) for (y, z), r in zip(knots, radii)]

    def tube(q):
        d = sd_capsule(q, centres[0], centres[1], radii[0], radii[1])
        for k in range(1, len(centres) - 1):
            d = torch.minimum(d, sd_capsule(q, centres[k], centres[k + 1], radii[k], radii[k + 1]))
        return [(d, None)]
    r = float(radii[0])
    lo = (-r, knots[-1][0] - r, min(z for _, z in knots) - 1.4 * r)
    hi = (r, knots[0][0] + r, max(z for _, z in knots) + r)
    return near_box(p, lo, hi, tube)[0][0]


def hair_field(p, P, A):
    """The signed distance of the subject's hair, or None when bald (its colour: ``hair_rgb_of``); ``A``: the
    anchors (``anatomy.anchors_of``)."""
    style = P["hair_style"]
    cc, (rx, ry, rz) = cranium(P)
    cy = cc[1]
    th = P["hair_thickness"]
    E = P["eye_height"]
    if style == "bald":
        return None
    if style == "afro":
        big = sd_ellipsoid(p, (0.0, cy + 0.02, cc[2] - 0.015), (rx + th, ry + th * 0.85, rz + th * 0.9))
        curls = 0.008 * torch.sin(p @ f32([70.0, 40.0, 20.0]) + 1.0) * torch.sin(p @ f32([-30.0, 75.0, 45.0])) \
            + 0.005 * torch.sin(p @ f32(np.asarray(P["hair_seed"][2]) * 55.0))
        hair = smax(big + curls, _hairline(p, P, -0.14), 0.02)
    else:
        nape = {"crop": -0.12, "ponytail": -0.1, "bun": -0.1}.get(style, -0.15)
        front = P["hairline_height"]
        if style == "fringe":
            front = E + P["brow_height"] + 0.012
        skull = sd_ellipsoid(p, cc, (rx, ry, rz))
        shell = skull - th
        if style == "side_part":
            side = math.copysign(1.0, P["hair_part"])
            vol = sd_ellipsoid(p, (-side * 0.04, cy + ry * 0.62, 0.03), (0.13, 0.04 + 0.02 * P["hair_volume"], 0.17))
            shell = smin(shell, vol, 0.04)
            # The swept side comes lower on the forehead.
            sweep = 0.035 * smoothstep(-0.05, 0.12, -side * p[:, 0])
            hl = _hairline(p, P, nape) - 0.7 * sweep * smoothstep(0.0, 0.1, p[:, 2])
        else:
            hl = _hairline(p, P, nape, front=front, ear_gap=style not in ("fringe", "bob", "long"))
        if style != "fringe":
            # Thinner toward the hairline, where hair grows out of the skin.
            shell = torch.minimum(shell, skull - th * smoothstep(0.0, 0.035, -hl) + 0.002)
        hair = smax(shell, hl, 0.006)
        if style in ("bob", "long", "fringe"):
            length = P["hair_length"] if style != "fringe" else -0.16
            drop = (cy - p[:, 1]).clamp_min(0.0)
            flare = 1.0 + (0.18 if style == "long" else 0.08) * drop
            q = torch.stack([p[:, 0] / flare, torch.clamp(p[:, 1], min=cy), p[:, 2]], dim=-1)
            fall = sd_ellipsoid(q, (0.0, cy, cc[2] - 0.01), (rx + th + 0.008, ry + th, rz + th + 0.01))
            fall = smax(fall, (length - p[:, 1]), 0.03)
            fall = smax(fall, p[:, 1] - (cy - 0.02), 0.04)  # above, the hairline decides
            face_cut = p[:, 2] - (0.06 - 0.45 * drop).clamp_min(-0.02 if style == "long" else 0.0)
            fall = smax(fall, face_cut, 0.02)
            hair = smin(hair, fall, 0.02)
        if style == "ponytail":
            hair = smin(hair, _ponytail(p, P, A), 0.015)
        if style == "bun":
            if P["hair_volume"] > 0.5:
                centre, r = (0.0, cy + ry * 0.78, cc[2] - rz * 0.45), 0.07
            else:
                centre, r = (0.0, cy - 0.06, cc[2] - rz - 0.035), 0.062
            hair = smin(hair, sd_sphere(p, centre, r) + 0.004 * torch.sin(p @ f32([90.0, 30.0, 60.0])), 0.02)
        if style in ("side_part", "bob", "long"):
            # The parting: a narrow groove on top.
            part_x = P["hair_part"] if style == "side_part" else P["hair_part"] * 0.3
            groove = gauss(p[:, 0] - part_x, 0.006) * smoothstep(-0.05, 0.1, p[:, 2]) * smoothstep(cy + 0.1, cy + 0.2, p[:, 1])
            hair = hair + 0.006 * groove
    return hair


def hair_rgb_of(q, P):
    """Hair colour times the strand texture, plus a sheen along the strands (so that dark hair shows
    them too)."""
    s = hair_strands(q, P, P["hair_style"] != "afro")[:, None]
    return (f32(P["hair_rgb"]) * s + 0.3 * (s - 0.86)).clamp(0.0, 1.0)
