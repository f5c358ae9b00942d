"""Defects modelled on 3D-GAN failures, injected into the head field (truth in ``Subject.truth``).

Each defect class has a ``sample_*`` function (its parameters, from the subject's generator, given
its severity in [0, 1]; none for janus, flat_back and blurry_back) and an ``apply_*`` function that
says how it changes one evaluation of the field (an ``Effect``). Several defects on one head (the
generator injects at most one) apply in ``APPLY_ORDER``.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from ...defects import INJECTED
from .anatomy import cranium, face_features, skin_colour
from .hair import hair_rgb_of
from .params import pick_one
from .sdf import BOX, HEAD_SCALE, near_box, smoothstep, f32, sd_capsule, sd_ellipsoid, sd_sphere, smax

# The injected classes of the taxonomy (datagen.defects), in its draw order. As modelled here:
# janus        a second face on the back of the head (eyes, brows, nose, lips), seen through the hair;
#              severity sets the size of the face's window (at low severity: partial, blended into hair)
# flat_back    the back of the head cut flat (severity: the depth of the cut)
# haze         semi-transparent wisps floating near the head (severity: how many and how dense)
# seam         a vertical discontinuity down the back: a step in the surface and in colour
# blurry_back  a smeared back: colour blurred and the surface softened over the back half
# holes        a crater in the back or top of the head
# floaters     opaque blobs detached from the head
# washed_out   the whole texture faded toward grey-white
DEFECT_TYPES = INJECTED
APPLY_ORDER = ("janus", "haze", "floaters", "holes", "seam", "blurry_back", "flat_back", "washed_out")


@dataclass
class Effect:
    """How a defect changes one evaluation of the field at points p (head units).

    features: [(sdf, rgb, blend)] joined to the face's features (as ``anatomy.face_features`` returns them);
    hair_window: a distance below 0 where the hair is cut away; skin: (skin albedo, q, sel) -> skin
    albedo at the points p[sel] = q; parts: [(sdf, albedo(q, sel))] of extra material; reshape:
    sdf -> (sdf, recolour or None), recolour: (rgb, q, sel) -> rgb, applied to the blended albedo.
    """

    features: list = field(default_factory=list)
    hair_window: torch.Tensor | None = None
    skin: Callable | None = None
    parts: list = field(default_factory=list)
    reshape: Callable | None = None


def _back_weight(p, cc):
    """0 on the front half of the head, rising to 1 over the back (head units)."""
    return smoothstep(cc[2] + 0.03, cc[2] - 0.12, p[:, 2])


def _severity_only(rng, severity):
    """The parameters of a defect that its severity alone sets: none."""
    return {}


# --- janus

def apply_janus(p, P, A, spec):
    """The same face mirrored onto the back of the head (rotated 180 degrees about y), seated on the
    skull; it shows through a window in the hair, as a GAN's mirrored face does."""
    cc, (rx, ry, rz) = cranium(P)
    zf = A["nasion"]
    mirrored = torch.stack([-p[:, 0], p[:, 1], -p[:, 2] - (rz - cc[2]) + zf - 0.06], dim=-1)
    plate_center = (0.0, P["eye_height"] - 0.05, zf - 0.1)
    k = 0.55 + 0.45 * spec.get("severity", 1.0)  # below 1: a partial face, hair over its edges
    plate = sd_ellipsoid(mirrored, plate_center, (rx * 0.7 * k, ry * 0.62 * k, 0.08))
    window = sd_ellipsoid(mirrored, plate_center, (rx * 0.8 * k, ry * 0.7 * k, 0.6))

    def skin(skin_rgb, q, sel):  # the mirrored face's brows, lash lines and lips on the back
        back = (window[sel] < 0) & (q[:, 2] < cc[2])
        return torch.where(back[:, None], skin_colour(mirrored[sel], P, A), skin_rgb)
    return Effect(features=[(plate, None, 0.02)] + face_features(mirrored, P, A), hair_window=window, skin=skin)


# --- haze

def sample_haze(rng, severity):
    """3 to 8 wisps (more with severity) over the back and top: direction (azimuth, elevation; radians),
    lift beyond the head and strand radius (head units), arc and turn of its plane (radians)."""
    wisps = []
    for _ in range(3 + int(round(5 * severity))):
        az, el = rng.uniform(math.pi * 0.4, math.pi * 1.6), rng.uniform(-0.3, 1.2)
        wisps.append({"azimuth": float(az), "elevation": float(el), "lift": float(rng.uniform(0.05, 0.12)),
                      "arc": float(rng.uniform(0.5, 1.2)), "turn": float(rng.uniform(0, 2 * math.pi)),
                      "radius": float(rng.uniform(0.004, 0.008))})
    return {"wisps": wisps}


def _wisp_sdf(p, wisp, cc, reach):
    """A thin strand arcing over the head at ``lift`` beyond ``reach`` (head units) from its centre."""
    az, el, turn = wisp["azimuth"], wisp["elevation"], wisp["turn"]
    d0 = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    side = np.cross(d0, [0.0, 1.0, 0.0]) if abs(d0[1]) < 0.95 else np.array([1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    axis = math.cos(turn) * side + math.sin(turn) * np.cross(d0, side)
    knots = []
    for a in np.linspace(0.0, wisp["arc"], 9):
        # Rodrigues rotation of d0 about ``axis``; the strand drifts outward and back along its length.
        d = d0 * math.cos(a) + np.cross(axis, d0) * math.sin(a) + axis * (axis @ d0) * (1 - math.cos(a))
        knots.append(np.asarray(cc) + d * (reach + wisp["lift"] * (1.0 + 0.3 * math.sin(2.5 * a + turn))))
    knots = np.asarray(knots)
    r = wisp["radius"]
    lo, hi = knots.min(0) - r, knots.max(0) + r

    def strand(q):
        d = torch.stack([sd_capsule(q, a, b, r, r) for a, b in zip(knots[:-1], knots[1:])]).amin(0)
        return [(d, None)]
    return near_box(p, lo.tolist(), hi.tolist(), strand)[0][0]


def apply_haze(p, P, A, spec):
    """Grey wisps (tinted by the hair), never quite solid: the distance stays above a floor, so the
    density (and the opacity of a strand) stays partial; lower floors at higher severity."""
    cc, radii = cranium(P)
    reach = max(radii) + P["hair_thickness"]  # the head's largest radius over its hair
    grey = 0.3 * f32(P["hair_rgb"]) + 0.7 * f32([0.82, 0.8, 0.78])
    floor = 0.01 - 0.005 * spec["severity"]
    parts = [(_wisp_sdf(p, wisp, cc, reach).clamp_min(floor), lambda q, sel: grey.expand(q.shape[0], 3))
             for wisp in spec["wisps"]]
    return Effect(parts=parts)


# --- floaters

def sample_floaters(rng, severity):
    """2 to 5 blobs 0.30 to 0.40 from the centre: centre, radius (larger with severity) and colour."""
    blobs = []
    for _ in range(int(rng.integers(2, 6))):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        dist = float(rng.uniform(0.30, 0.40))
        center = np.clip(d * dist, -BOX + 0.06, BOX - 0.06)
        blobs.append({"center": center.tolist(), "radius": float(rng.uniform(0.012, 0.02) + 0.02 * severity),
                      "rgb": list(rng.uniform(0.2, 0.9, 3))})
    return {"blobs": blobs}


def apply_floaters(p, P, A, spec):
    """Opaque spheres of their own colour."""
    return Effect(parts=[(sd_sphere(p, blob["center"], blob["radius"]),
                          lambda q, sel, blob=blob: f32(blob["rgb"]).expand(q.shape[0], 3)) for blob in spec["blobs"]])


# --- holes

def sample_hole(rng, severity):
    """The crater's direction from the skull's centre (a unit vector over the back and top) and radius
    (head units, larger with severity)."""
    az, el = rng.uniform(math.pi * 0.5, math.pi * 1.5), rng.uniform(-0.2, 1.0)
    direction = [math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)]
    return {"direction": direction, "radius": 0.06 + 0.06 * severity}


def apply_hole(p, P, A, spec):
    """A sphere cut out of the head at ``direction``, its wall dark red."""
    cc, radii = cranium(P)
    center = np.asarray(spec["direction"]) * (max(radii) + 0.02) + np.array([0.0, cc[1], cc[2]])
    cut = sd_sphere(p, center, spec["radius"])

    def reshape(sdf):
        wall = torch.exp(-cut.abs() / 0.006) * (sdf < 0)  # where the cut, not the head, is the surface

        def recolour(rgb, q, sel):
            return rgb * (1 - wall[sel, None]) + f32([0.22, 0.07, 0.05]) * wall[sel, None]
        return smax(sdf, -cut, 0.005), recolour
    return Effect(reshape=reshape)


# --- seam

def sample_seam(rng, severity):
    """The seam's x (head units, near the midline) and the side of it (-1 or 1) that sinks."""
    return {"x": float(rng.uniform(-0.015, 0.015)), "side": float(rng.choice([-1.0, 1.0]))}


def apply_seam(p, P, A, spec):
    """Over the back above the jaw, the side of x = ``x`` that ``side`` points to is sunk and darkened."""
    cc = cranium(P)[0]
    backness = smoothstep(cc[2] - 0.02, cc[2] - 0.1, p[:, 2]) * smoothstep(P["jaw_angle_y"] - 0.05, P["jaw_angle_y"] + 0.05, p[:, 1])
    seam_side = (spec["side"] * (p[:, 0] - spec["x"]) > 0).float() * backness

    def reshape(sdf):
        return (sdf - (0.004 + 0.01 * spec["severity"]) * seam_side,
                lambda rgb, q, sel: rgb * (1.0 - (0.12 + 0.3 * spec["severity"]) * seam_side[sel, None]))
    return Effect(reshape=reshape)


# --- blurry_back

def apply_blurry_back(p, P, A, spec):
    """A softer surface (the density's transition widens) over the back; ``smear_back`` blurs its
    baked colour."""
    weight = _back_weight(p, cranium(P)[0])
    return Effect(reshape=lambda sdf: (sdf * (1.0 - (0.2 + 0.45 * spec["severity"]) * weight), None))


def smear_back(rgb_grid, near, params, defects, res):
    """With a blurry_back defect: blur the baked colour (3,R,R,R) over the back of the head, a Gaussian
    of (1 + 3 severity) voxels normalised over the coloured voxels ``near`` (flat indices), blended in
    by _back_weight. Without one, the grid as it is."""
    spec = by_type(defects).get("blurry_back")
    if spec is None:
        return rgb_grid
    from scipy.ndimage import gaussian_filter

    mask = np.zeros(res ** 3, np.float32)
    mask[near.numpy()] = 1.0
    mask = mask.reshape(res, res, res)
    sigma = 1.0 + 3.0 * spec["severity"]
    weight = gaussian_filter(mask, sigma, mode="constant")
    blurred = np.stack([gaussian_filter(c, sigma, mode="constant") for c in rgb_grid.numpy()]) / np.maximum(weight, 1e-6)
    z = torch.linspace(-BOX, BOX, res) / HEAD_SCALE  # grid axis 0 is z
    w = _back_weight(torch.stack([torch.zeros(res), torch.zeros(res), z], -1), cranium(params)[0])
    w = w[:, None, None] * torch.from_numpy(mask)
    return rgb_grid * (1 - w) + torch.from_numpy(blurred).float() * w


# --- flat_back

def apply_flat_back(p, P, A, spec):
    """A plane cuts the back of the head off (deeper with severity); below the jaw it leans back so
    that the neck and body stay whole. The cut face takes the hair's colour, as a GAN's flattened
    back keeps its hair texture."""
    cc, radii = cranium(P)
    depth = 0.03 + 0.09 * spec["severity"]
    plane = cc[2] - radii[2] + depth - 0.6 * (P["jaw_angle_y"] - p[:, 1]).clamp_min(0.0) - p[:, 2]

    def reshape(sdf):
        cut_face = smoothstep(-0.004, 0.004, plane - sdf)
        if P["hair_style"] == "bald":
            return smax(sdf, plane, 0.004), None
        return smax(sdf, plane, 0.004), lambda rgb, q, sel: rgb + (hair_rgb_of(q, P) - rgb) * cut_face[sel, None]
    return Effect(reshape=reshape)


# --- washed_out

def sample_washed_out(rng, severity):
    """How far the albedo fades toward grey (0.4 to 0.8 with severity)."""
    return {"strength": 0.4 + 0.4 * severity}


def apply_washed_out(p, P, A, spec):
    """The albedo faded toward a light grey by ``strength``."""
    def recolour(rgb, q, sel):
        s = spec["strength"]
        grey = rgb.mean(-1, keepdim=True)
        return (1 - s) * rgb + s * (0.25 * grey + 0.75 * 0.93)
    return Effect(reshape=lambda sdf: (sdf, recolour))


SAMPLE = {"janus": _severity_only, "flat_back": _severity_only, "haze": sample_haze, "seam": sample_seam,
          "blurry_back": _severity_only, "holes": sample_hole, "floaters": sample_floaters,
          "washed_out": sample_washed_out}
APPLY = {"janus": apply_janus, "flat_back": apply_flat_back, "haze": apply_haze, "seam": apply_seam,
         "blurry_back": apply_blurry_back, "holes": apply_hole, "floaters": apply_floaters,
         "washed_out": apply_washed_out}


def sample_defects(rng: np.random.Generator, rate: float, params: dict, types=DEFECT_TYPES,
                   severity=(0.3, 1.0)) -> list[dict]:
    """With probability ``rate`` inject one defect of one of ``types`` (uniformly), its severity drawn
    uniformly from ``severity``; returns the injected truth (possibly empty). ``params`` (the
    person) is not used."""
    if rng.uniform() >= rate:
        return []
    kind = pick_one(rng, list(types))
    s = float(rng.uniform(*severity))
    return [{"type": kind, "severity": s, **SAMPLE[kind](rng, s)}]


def by_type(defects: list[dict]) -> dict:
    """{type: defect} (the last of a type wins)."""
    return {d["type"]: d for d in defects}


def effects(p, P, A, defects: list[dict]) -> list[Effect]:
    """The defects' effects at points p (head units), in APPLY_ORDER."""
    kinds = by_type(defects)
    return [APPLY[kind](p, P, A, kinds[kind]) for kind in APPLY_ORDER if kind in kinds]
