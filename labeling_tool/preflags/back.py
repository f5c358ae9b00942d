"""Three things 3D GANs get wrong at the back of the head, each measured on the back view (yaw ~180).

flat_back    a flattened or truncated back: a round head's back view bulges toward the camera, its
             depth at 80 % of the silhouette's half-width lying about 0.4 half-widths behind its
             centre; a cut-off back is nearly flat. Measure: that depth difference over the
             half-width (world units, from the view's focal), robust z against the dataset.
seam         a seam or discontinuity down the back: the horizontal colour gradient of the columns
             at the centre of the back view against the busiest tenth of the head's other columns
             (log ratio), robust z against the dataset; and a step in the surface there: per column,
             the median over the head's rows of the depth's step to the next column less the mean of
             the steps beside it (a step, not the head's slope), in pixels at the head's distance, the largest
             near the centre, robust z against the dataset. The larger z counts.
blurry_back  a blurry or smeared back: how wide the silhouette's edge is in the back views (yaw
             135-225; a soft density blurs the outline), robust z against the dataset; and, for
             colour blurred over a crisp outline, the colour edges' sharpness against the alpha's
             in the back views relative to the front views (yaw 315-45, log ratio), robust z.
             The larger z counts.

Not applicable without a back view (the ``frontal`` protocol); the colour cue also needs a front view.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from datagen.cameras import fov_to_focal
from datagen.dataset.shards import view_name

from .blur import alpha_edge_width, edge_sharpness
from .detector import Detector, Flag, ramp_flag
from .imaging import bbox, erode, robust

BACK_SIDE, FRONT_SIDE = (135.0, 180.0, 225.0), (315.0, 0.0, 45.0)  # equator targets of each side
NA = "not applicable: no back view (yaw 180 +- 20, pitch within 20) among this subject's cameras"


def _back(v):
    """(view index, colour, mask, depth) of the back view at the working resolution, or None."""
    b = v.back
    if b is None or b not in v.work or v.work[b][1].sum() < 40:
        return None
    return (b, *v.work[b])


def bulge(mask: np.ndarray, depth: np.ndarray, focal_px: float) -> float | None:
    """(depth at 80 % of the half-width - depth at the centre) / half-width (world units), or None."""
    top, bot, left, right = bbox(mask)
    rows = slice(top + int(0.25 * (bot - top)), top + int(0.6 * (bot - top)) + 1)
    sub_m, sub_d = mask[rows], depth[rows]
    cols = np.nonzero(sub_m.any(0))[0]
    if cols.size < 8:
        return None
    cx, half = 0.5 * (cols[0] + cols[-1]), 0.5 * (cols[-1] - cols[0])
    x = np.arange(mask.shape[1])
    centre = sub_m & (np.abs(x - cx) <= 0.15 * half)[None]
    rim = sub_m & (np.abs(np.abs(x - cx) - 0.8 * half) <= 0.08 * half)[None]
    if centre.sum() < 3 or rim.sum() < 3:
        return None
    zc, zr = float(np.median(sub_d[centre])), float(np.median(sub_d[rim]))
    half_world = half * zc / focal_px
    return (zr - zc) / max(half_world, 1e-6)


def seam_ratio(colour: np.ndarray, mask: np.ndarray) -> float | None:
    """log of the mean |horizontal colour gradient| of the central columns over the 90th percentile of the
    other head columns' (hair strands make some columns busy; a seam makes the centre stand out)."""
    top, bot, left, right = bbox(mask)
    inner = erode(mask, 2)
    inner[top + int(0.7 * (bot - top)):] = False  # the head, not the neck
    g = np.abs(np.diff(colour, axis=1)).sum(-1)
    ok = inner[:, 1:] & inner[:, :-1]
    cols = np.nonzero(ok.any(0))[0]
    if cols.size < 10:
        return None
    per_col = np.array([g[ok[:, c], c].mean() if ok[:, c].sum() >= 3 else np.nan for c in range(g.shape[1])])
    cx, half = 0.5 * (cols[0] + cols[-1]), 0.5 * (cols[-1] - cols[0])
    x = np.arange(g.shape[1])
    central = (np.abs(x - cx) <= max(1.0, 0.12 * half)) & np.isfinite(per_col)
    other = (np.abs(x - cx) > 0.2 * half) & (np.abs(x - cx) < 0.8 * half) & np.isfinite(per_col)
    if not central.any() or other.sum() < 3:
        return None
    return float(np.log((per_col[central].max() + 1e-4) / (np.quantile(per_col[other], 0.9) + 1e-4)))


def depth_step(mask: np.ndarray, depth: np.ndarray, focal_px: float) -> float | None:
    """The largest step in the surface down the centre of a back view (|x - centre| <= 0.15 of the
    half-width), in pixels at the head's distance: per column, the median over the head's rows (the
    top 70 %, two pixels inside the outline) of the depth's step from one column to the next less the
    mean of the steps beside it."""
    top, bot, left, right = bbox(mask)
    inner = erode(mask, 2)
    inner[top + int(0.7 * (bot - top)):] = False
    ok = inner[:, 3:] & inner[:, 2:-1] & inner[:, 1:-2] & inner[:, :-3]  # columns c .. c + 3 on the head
    cols = np.nonzero(ok.any(0))[0]
    if cols.size < 10:
        return None
    # The step between columns c + 1 and c + 2 less the mean of the steps on either side of it.
    step = np.diff(depth, axis=1)
    second = step[:, 1:-1] - 0.5 * (step[:, :-2] + step[:, 2:])
    per_col = np.array([np.median(second[ok[:, c], c]) if ok[:, c].sum() >= 8 else np.nan
                        for c in range(second.shape[1])])
    cx, half = 0.5 * (cols[0] + cols[-1]), 0.5 * (cols[-1] - cols[0])
    central = (np.abs(np.arange(second.shape[1]) - cx) <= max(1.5, 0.15 * half)) & np.isfinite(per_col)
    if not central.any():
        return None
    pixel = float(np.median(depth[mask])) / focal_px  # world units per pixel at the head
    return float(np.abs(per_col[central]).max() / pixel)


class _BackDetector(Detector):
    """A robust z-score of one back-view measure against the dataset (``sign`` -1: low is bad)."""

    sign = 1.0
    floor = 0.05
    unit = ""

    @dataclass(frozen=True)
    class Settings:
        z: float = 4.0
        z_sat: float = 8.0

    def threshold(self):
        return self.settings.z

    def explain(self, m, med) -> str:
        raise NotImplementedError

    def baseline(self, measured):
        return robust([m["x"] for m in measured if m and "na" not in m], self.floor)

    def score(self, m, base, index, keys):
        if m is None:
            return Flag(0.0, "not measured (the back view is (almost) empty)")
        if "na" in m:
            return Flag(0.0, m["na"])
        med, scale = base
        z = self.sign * (m["x"] - med) / scale
        t = self.settings
        return ramp_flag(z, t.z, t.z_sat, f"{self.explain(m, med)}; z {z:.1f} (flag at {t.z:g})", z)


class FlatBack(_BackDetector):
    name = "flat_back"

    @dataclass(frozen=True)
    class Settings:
        z: float = 3.0   # robust z of the back's curvature at which it flags (score 0.5)
        z_sat: float = 8.0  # z at which the score reaches 1

    description = ("a flattened or truncated back of the head: how far the back view's surface curves away from "
                   "the camera across the head (depth at 80% of the half-width minus at the centre, over the "
                   "half-width), robust z against the dataset; n/a without a back view")
    sign = -1.0

    def measure(self, v):
        got = _back(v)
        if v.back is None:
            return {"na": NA}
        if got is None:
            return None
        b, _, m, d = got
        focal_px = float(fov_to_focal(v.views[b]["fov_deg"])) * m.shape[1]
        x = bulge(m, d, focal_px)
        return None if x is None else {"x": x, "view": b}

    def explain(self, m, med):
        return (f"back view {view_name(m['view'])}: the surface falls back {m['x']:.2f} half-widths from centre to "
                f"rim (dataset median {med:.2f})")


class Seam(_BackDetector):
    name = "seam"

    @dataclass(frozen=True)
    class Settings:
        z: float = 3.0   # robust z of the colour gradient or the depth step at which it flags
        z_sat: float = 8.0  # z at which the score reaches 1
        colour_floor: float = 0.05  # least scale of the colour feature, log ratio
        step_floor: float = 0.13  # least scale of the depth step, px at the working resolution

    description = ("a seam or discontinuity down the back: horizontal colour gradient of the back view's central "
                   "columns against the head's other columns (log ratio), or a step in depth down the centre "
                   "(px), robust z against the dataset; n/a without a back view")

    def measure(self, v):
        got = _back(v)
        if v.back is None:
            return {"na": NA}
        if got is None:
            return None
        b, c, m, d = got
        x = seam_ratio(c, m)
        if x is None:
            return None
        step = depth_step(m, d, float(fov_to_focal(v.views[b]["fov_deg"])) * m.shape[1])
        return {"x": x, "step": step, "view": b}

    def baseline(self, measured):
        ok = [m for m in measured if m and "na" not in m]
        return {"x": robust([m["x"] for m in ok], self.settings.colour_floor),
                "step": robust([m.get("step") for m in ok], self.settings.step_floor)}

    def score(self, m, base, index, keys):
        if m is None or "na" in m:
            return super().score(m, base["x"], index, keys)
        (med, scale), (smed, sscale) = base["x"], base["step"]
        z = (m["x"] - med) / scale
        why = (f"back view {view_name(m['view'])}: the centre columns change colour {math.exp(m['x']):.1f}x as much "
               f"as the rest of the head (dataset median {math.exp(med):.1f}x)")
        if m.get("step") is not None and (m["step"] - smed) / sscale > z:
            z = (m["step"] - smed) / sscale
            why = (f"back view {view_name(m['view'])}: a step of {m['step']:.2f} px in depth down the centre "
                   f"(dataset median {smed:.2f})")
        t = self.settings
        return ramp_flag(z, t.z, t.z_sat, f"{why}; z {z:.1f} (flag at {t.z:g})", z)


class BlurryBack(_BackDetector):
    name = "blurry_back"
    description = ("a blurry or smeared back: the width of the back views' silhouette edge, or their colour edges' "
                   "sharpness against the front views' (log ratio), robust z against the dataset; n/a without a "
                   "back view")

    @dataclass(frozen=True)
    class Settings:
        z: float = 3.0   # robust z of the outline width or the sharpness ratio at which it flags
        z_sat: float = 8.0  # z at which the score reaches 1
        width_floor: float = 0.08  # least scale of the outline width, px (curly and long hair widen clean outlines)
        colour_floor: float = 0.05  # least scale of the sharpness ratio, log ratio

    def measure(self, v):
        if v.back is None:
            return {"na": NA}
        sides = {}
        for name, targets in (("back", BACK_SIDE), ("front", FRONT_SIDE)):
            sides[name] = [v.eq[t] for t in targets if t in v.eq and v.rgb.get(v.eq[t]) is not None]
        widths = [x for x in (alpha_edge_width(v.alpha[i]) for i in sides["back"]) if np.isfinite(x)]
        if not widths:
            return None
        colour = None
        sharp = {name: [x for x in (v.once(("edge_sharpness", i), lambda: edge_sharpness(v.rgb[i], v.alpha[i]))
                                    for i in views) if np.isfinite(x)]
                 for name, views in sides.items()}
        if sharp["back"] and sharp["front"]:
            colour = float(np.median(sharp["back"]) - np.median(sharp["front"]))
        return {"x": float(np.median(widths)), "colour": colour, "view": v.back, "front": v.front}

    def baseline(self, measured):
        ok = [m for m in measured if m and "na" not in m]
        return {"x": robust([m["x"] for m in ok], self.settings.width_floor),
                "colour": robust([m["colour"] for m in ok], self.settings.colour_floor)}

    def score(self, m, base, index, keys):
        if m is None:
            return Flag(0.0, "not measured (the back views are (almost) empty)")
        if "na" in m:
            return Flag(0.0, m["na"])
        (med, scale), (cmed, cscale) = base["x"], base["colour"]
        z = (m["x"] - med) / scale
        why = (f"the back views' outline (around {view_name(m['view'])}) is {m['x']:.1f} px wide "
               f"(dataset median {med:.1f})")
        if m["colour"] is not None and -(m["colour"] - cmed) / cscale > z:
            z = -(m["colour"] - cmed) / cscale
            why = (f"the back views' colour edges (around {view_name(m['view'])}) carry "
                   f"{100 * math.exp(m['colour']):.0f}% of the front views' sharpness (around "
                   f"{view_name(m['front'])}; dataset median {100 * math.exp(cmed):.0f}%)")
        t = self.settings
        return ramp_flag(z, t.z, t.z_sat, f"{why}; z {z:.1f} (flag at {t.z:g})", z)
