"""blur: soft silhouette edges.

The colour image's gradient energy across the silhouette against a sharp cut-out composed from the
same view's mask, relative to the dataset (content-independent); interior detail (Laplacian over grey
variance) is reported alongside.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from .detector import Detector, Flag, ramp_flag
from .imaging import box, dilate, erode, fill_holes, label, nearest_fill, robust


def edge_sharpness(rgb, alpha) -> float:
    """log of the grey gradient energy across the silhouette over that of a sharp composite (alpha *
    inside colour + (1 - alpha) * background) built from the same view: about 0 when the colour image
    is as sharp as its mask, negative when it is blurred. NaN when there is too little edge."""
    m = alpha > 127  # a > 0.5 of a = alpha / 255
    if m.sum() < 30 or (~m).sum() < 30:
        return float("nan")
    outside = alpha < 2.55  # a < 0.01
    bg = float(np.median(rgb[outside].astype(np.float64).mean(-1) / 255.0)) if outside.any() else 1.0
    near = box(m, 4)  # the band around the silhouette (2 px) and the Sobel filters' reach (1 px)
    a = alpha[near].astype(np.float64) / 255.0
    g = rgb[near].astype(np.float64).mean(-1) / 255.0
    m = m[near]
    full = erode(a > 0.99)
    if not full.any():
        return float("nan")
    inside = nearest_fill(np.where(full, g, 0.0), full)
    sharp = a * inside + (1.0 - a) * bg
    band = dilate(m, 2) & ~erode(m, 2)
    e_img = np.hypot(ndi.sobel(g, 0), ndi.sobel(g, 1))[band]
    e_ref = np.hypot(ndi.sobel(sharp, 0), ndi.sobel(sharp, 1))[band]
    keep = e_ref > 0.1
    if keep.sum() < 10:
        return float("nan")
    return float(np.log((e_img[keep] ** 2).mean() / (e_ref[keep] ** 2).mean()))


def alpha_edge_width(alpha) -> float:
    """Median width in pixels (1 / |alpha gradient|, capped at 20) along the outline of the largest
    silhouette, holes filled: about 1-3 px for a crisp surface, more where the density is soft.
    NaN when the outline is too short."""
    solid = alpha > 127  # a > 0.5 of a = alpha / 255
    if not solid.any():
        return float("nan")
    near = box(solid, 2)  # the outline and the Sobel filter's reach
    a = alpha[near].astype(np.float64) / 255.0
    lab, n = label(solid[near])
    body = fill_holes(lab == 1 + int(np.argmax(np.bincount(lab.ravel())[1:])))
    outline = body & ~erode(body)
    if outline.sum() < 20:
        return float("nan")
    grad = np.hypot(ndi.sobel(a, 0), ndi.sobel(a, 1))[outline] / 8.0
    return float(np.median(1.0 / np.maximum(grad, 0.05)))


class Blur(Detector):
    name = "blur"
    description = ("soft silhouette edges: -z (against the dataset) of the log ratio of gradient energy across the "
                   "silhouette to that of a sharp cut-out from the same mask")

    @dataclass(frozen=True)
    class Settings:
        z: float = 6.0             # -z of the silhouette edge sharpness (log gradient-energy ratio)
        z_sat: float = 15.0
        edge_floor: float = 0.02   # scale floor of that log ratio

    def threshold(self):
        return self.settings.z

    def measure(self, v):
        edges, detail = [], []
        for _, i in v.eq_used:
            edges.append(v.once(("edge_sharpness", i), lambda: edge_sharpness(v.rgb[i], v.alpha[i])))
            c, m, _ = v.work[i]
            grey = c.mean(-1)
            inner = erode(m, max(1, int(round(2 * v.s))))
            if inner.sum() >= 16:
                lap = ndi.laplace(nearest_fill(grey, m))
                gv = float(grey[inner].var())
                detail.append(float(np.log((lap[inner].var() + 1e-12) / (gv + 1e-12))) if gv > 1e-8 else np.nan)
        edges = [x for x in edges if np.isfinite(x)]
        detail = [x for x in detail if np.isfinite(x)]
        return {"edge": float(np.median(edges)) if edges else np.nan,
                "detail": float(np.median(detail)) if detail else np.nan}

    def baseline(self, measured):
        ok = [m for m in measured if m]
        return {"edge": robust([m["edge"] for m in ok if np.isfinite(m["edge"])], self.settings.edge_floor),
                "detail": robust([m["detail"] for m in ok if np.isfinite(m["detail"])], 0.05)}

    def score(self, m, base, index, keys):
        detail = (f"; interior detail {math.exp(m['detail'] - base['detail'][0]):.2f}x the dataset median"
                  if np.isfinite(m["detail"]) else "")
        if not np.isfinite(m["edge"]):
            return Flag(0.0, "no usable silhouette edge to measure" + detail)
        med, scale = base["edge"]
        z = -(m["edge"] - med) / scale
        t = self.settings
        return ramp_flag(z, t.z, t.z_sat,
                         f"silhouette edges carry {100 * math.exp(m['edge']):.0f}% of the gradient energy of a sharp "
                    f"cut-out (dataset median {100 * math.exp(med):.0f}%); z {-z:.1f} (flag at -{t.z:g}){detail}", z)
