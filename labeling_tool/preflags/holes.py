"""holes: see-through holes in the silhouette, and craters in the surface.

See-through: the filled mask minus the mask, as a share of the silhouette, in the worst view; gaps
centred in the lower part of the silhouette (between long hair, neck and shoulders) do not count.
Craters: round depressions of the depth map in the upper head (determinant-of-Hessian blob response
of depth), as a robust z-score against views of the dataset from the same direction.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from datagen.shards import view_name

from .detector import Detector, Flag
from .imaging import bbox, blob_response, nearest_fill, ramp, robust_tail
from .views import EQUATOR_STEP, WORK_RES


def deepest_crater(depth, mask, s: float, st):
    """Strongest round depression in the upper part of the silhouette: (response, (row, col))."""
    if mask.sum() < 16:
        return 0.0, (0, 0)
    dd = nearest_fill(depth.astype(np.float64), mask)
    resp = blob_response(dd, st.sigma * s, -1.0)
    top, bot, _, _ = bbox(mask)
    yrel = (np.arange(mask.shape[0])[:, None] - top) / max(bot - top, 1)
    region = ndi.binary_erosion(mask, iterations=max(1, int(round(st.erode * s)))) & (yrel <= st.upper)
    r = np.where(region, resp, 0.0)
    j = np.unravel_index(int(np.argmax(r)), r.shape)
    return float(r[j]), (int(j[0]), int(j[1]))


class Holes(Detector):
    name = "holes"
    description = ("see-through holes in the silhouette, or a crater: a round depression of the depth map in the "
                   "upper head, robust z against the same viewing direction")

    @dataclass(frozen=True)
    class Settings:
        silhouette_share: float = 0.002
        silhouette_share_sat: float = 0.02
        min_px: float = 3.0         # at 64 px; smaller holes are ignored (scaled with image area)
        z: float = 7.5              # crater blob response, robust z against views from the same direction
                                    # (scale: MAD or the 90th-percentile spread); tuning seeds: hairline dips
                                    # of clean heads reach 7.3 (97 %: 4.9), injected craters 1.2 to 7.2, so
                                    # only gross craters flag; the score still ranks the rest
        z_sat: float = 12.0
        sigma: float = 2.0          # blob scale in px at 64 px
        erode: float = 4.0          # ignore this many px (at 64 px) inside the silhouette edge
        upper: float = 0.6          # search the top 60% of the silhouette (the face/neck have natural concavities)
        gap_below: float = 0.6      # see-through gaps centred below this share of the silhouette's height are
                                    # gaps between hair, neck and shoulders, not holes
        mad_floor: float = 0.001    # world units

    def threshold(self):
        return {"crater_z": self.settings.z, "silhouette_share": self.settings.silhouette_share}

    def measure(self, v):
        st = self.settings
        min_px = max(2.0, st.min_px * (v.resolution / WORK_RES) ** 2)
        silh = []
        for i in range(v.n):
            m = v.mask(i)
            if not m.any():
                silh.append(0.0)
                continue
            holes = ndi.binary_fill_holes(m) & ~m
            lab, nh = ndi.label(holes)
            big = np.bincount(lab.ravel())[1:] if nh else np.zeros(0)
            if nh:
                top, bot, _, _ = bbox(m)
                rows = ndi.center_of_mass(holes, lab, range(1, nh + 1))
                big = big[[(r - top) / max(bot - top, 1) < st.gap_below for r, _ in rows]]
            big = big[big >= min_px]
            silh.append(float(big.sum() / m.sum()) if big.size else 0.0)
        craters = []
        for _, i in v.eq_used:
            _, m, d = v.work[i]
            r, at = deepest_crater(d, m, v.s, st)
            top, bot, left, right = bbox(m)
            craters.append((i, float(v.views[i]["yaw_deg"]), r,
                            (round((at[0] - top) / max(bot - top, 1), 2), round((at[1] - left) / max(right - left, 1), 2))))
        return {"silhouette": np.asarray(silh, dtype=np.float32), "craters": craters}

    def baseline(self, measured):
        bins = {}
        for m in measured:
            for _, yaw, c, _ in (m or {}).get("craters", []):
                bins.setdefault(int(round(yaw / EQUATOR_STEP)) % 8, []).append(float(np.float32(c)))
        return {b: robust_tail(v, self.settings.mad_floor) for b, v in bins.items()}

    def score(self, m, base, index, keys):
        st = self.settings
        sh = m["silhouette"]
        s_sil, why_sil = 0.0, None
        if len(sh) and sh.max() > 0:
            i = int(np.argmax(sh))
            s_sil = ramp(float(sh[i]), st.silhouette_share, st.silhouette_share_sat)
            why_sil = f"{view_name(i)}: see-through hole, {100 * sh[i]:.2f}% of the silhouette"
        s_cr, why_cr, best_z = 0.0, None, -np.inf
        for v, yaw, c, at in m["craters"]:
            stat = base.get(int(round(yaw / EQUATOR_STEP)) % 8)
            if stat is None:
                continue
            c = float(np.float32(c))
            z = (c - stat[0]) / stat[1]
            if z > best_z:
                best_z = z
                why_cr = (f"{view_name(v)}: round depression {c:.4f} deep at {int(100 * at[0])}% height "
                          f"(views from yaw {yaw:.0f}: median {stat[0]:.4f}); z {z:.1f} (flag at {st.z:g})")
        if why_cr is not None:
            s_cr = ramp(best_z, st.z, st.z_sat)
        if s_sil >= s_cr and why_sil:
            return Flag(s_sil, why_sil, best_z if why_cr else None)
        if why_cr:
            return Flag(s_cr, why_cr, best_z)
        return Flag(0.0, "no depth views to search")
