"""What a person wears: clothing over the shoulders, glasses and a cap (signed distances, head units)."""
from __future__ import annotations

import math

import torch

from .anatomy import cranium
from .sdf import extrude, smoothstep, sd_capsule, sd_ellipsoid, smax, smin


ARM_DEPTH = 1.3  # upper arms: depth (front to back) over width


def torso_sdf(p, P):
    """Shoulders and chest (skin) and the garment over them below the neckline: (skin sdf, cloth sdf)."""
    sw = P["shoulder_width"]
    d = sd_ellipsoid(p, (0.0, -0.74, -0.045), (sw * 0.85, 0.33, 0.21))
    # The upper arms hang straight down from the shoulders, out of the box, and are deeper (front to back)
    # than wide: round capsules made ARM_DEPTH times deeper (a lower bound of the distance). Seen from
    # below, the body runs out of the picture instead of ending in a ball under the chin.
    q = torch.stack([p[:, 0], p[:, 1], (p[:, 2] + 0.05) / ARM_DEPTH - 0.05], dim=-1)
    for sx in (-1.0, 1.0):
        d = smin(d, sd_capsule(p, (sx * 0.06, -0.40, -0.055), (sx * sw, -0.515, -0.05), 0.1, 0.115), 0.05)
        d = torch.minimum(d, sd_capsule(q, (sx * sw, -0.515, -0.05), (sx * sw, -1.2, -0.05), 0.115, 0.105))
    d = smin(d, sd_capsule(p, (0.0, -0.25, -0.055), (0.0, -0.5, -0.05), P["neck_radius"] * 1.05, P["neck_radius"] * 1.2), 0.05)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    # The neck opening: a cylinder round the neck, deeper at the front (and a V for v-necks).
    around = torch.sqrt(x ** 2 + ((z + 0.05) * 1.1) ** 2)
    open_r = P["neck_radius"] * 1.25 + 0.03 * smoothstep(-0.02, 0.1, z) * (P["neckline"] != "collar")
    opening = torch.maximum(around - open_r, -0.45 - y)
    if P["neckline"] == "v":
        vee = torch.maximum(x.abs() - 0.09 * ((y + 0.62) / 0.2).clamp(0.0, 1.0), -z)
        opening = torch.minimum(opening, torch.maximum(vee, -0.62 - y))
    cloth = smax(d - 0.007, -opening, 0.01)
    if P["neckline"] == "collar":
        ring = torch.sqrt((around - P["neck_radius"] * 1.2) ** 2 + ((y + 0.43) / 1.5) ** 2) - 0.016
        cloth = torch.minimum(cloth, ring)
    return d, cloth


def glasses_sdf(p, P, A):
    """Glasses: two rims (round or rectangular) in front of the eyes, a bridge and the arms to the ears."""
    ex, E = P["eye_spacing"], P["eye_height"]
    zg = A["eye"] + 0.028
    w, h, t = 0.038, 0.028, 0.011  # half width, half height of a lens; rim thickness (>= 2 grid voxels)
    parts = []
    for sx in (-1.0, 1.0):
        x, y = p[:, 0] - sx * (ex + 0.004), p[:, 1] - E
        if P["glasses_shape"] == "round":
            ring = (torch.sqrt(x ** 2 + y ** 2) - 0.034).abs() - t / 2
        else:
            qx, qy = x.abs() - (w - 0.012), y.abs() - (h - 0.012)
            box = torch.stack([qx.clamp_min(0), qy.clamp_min(0)], -1).norm(dim=-1) + torch.maximum(qx, qy).clamp_max(0) - 0.012
            ring = box.abs() - t / 2
        parts.append(extrude(ring, (p[:, 2] - zg).abs() - 0.006))
    rim = torch.minimum(*parts)
    bridge = sd_capsule(p, (-ex + 0.03, E + 0.008, zg), (ex - 0.03, E + 0.008, zg), 0.006, 0.006)
    rx = P["skull_radii"][0]
    arms = torch.minimum(
        sd_capsule(p, (-ex - 0.036, E + 0.005, zg), (-rx - 0.008, E - 0.005, -0.04), 0.006, 0.006),
        sd_capsule(p, (ex + 0.036, E + 0.005, zg), (rx + 0.008, E - 0.005, -0.04), 0.006, 0.006))
    return torch.minimum(torch.minimum(rim, bridge), arms)


CAP_BRIM_HALF = 0.011  # half-thickness of a cap brim (head units): about 2.4 grid voxels thick at 128^3


def cap_sdf(p, P):
    """A cap: a dome over the skull (and its hair) and a brim over the forehead."""
    cc, (rx, ry, rz) = cranium(P)
    cy = cc[1]
    th = max(P["hair_thickness"], 0.0) * (0.5 if P["hair_style"] == "afro" else 1.0) + 0.015
    dome = sd_ellipsoid(p, cc, (rx + th, ry + th, rz + th))
    # The band sits high on the forehead, as most people wear a cap: lower, it hid the brows and the
    # upper face (a face detector then missed about half the faces in caps).
    dome = smax(dome, (cy + 0.12 - 0.1 * smoothstep(-0.1, -0.2, p[:, 2])) - p[:, 1], 0.01)
    # Brim: a flat plate of constant thickness with a rounded edge (an exact distance), tilted down.
    tilt = 0.18
    yb = cy + 0.125
    zb = 0.115
    q_y = (p[:, 1] - yb) * math.cos(tilt) + (p[:, 2] - zb) * math.sin(tilt)
    q_z = -(p[:, 1] - yb) * math.sin(tilt) + (p[:, 2] - zb) * math.cos(tilt)
    outline = torch.sqrt((p[:, 0] * 1.05) ** 2 + q_z ** 2) - 0.19
    outline = torch.maximum(outline, 0.02 - q_z)  # the front half only
    brim = extrude(outline + 0.006, q_y.abs() - (CAP_BRIM_HALF - 0.006)) - 0.006
    return torch.minimum(dome, brim)
