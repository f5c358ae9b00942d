"""holes: see-through holes in the silhouette, and craters in the surface.

See-through: the filled mask minus the mask, as a share of the silhouette, in the worst view; gaps
centred in the lower part of the silhouette (between long hair, neck and shoulders) do not count.
Craters: round depressions of the depth map in the upper head (determinant-of-Hessian blob response
of depth), as a robust z-score against views of the dataset from the same direction, less the z of
the mirrored view (yaw -> -yaw; not for the front and back views, their own mirrors): heads are
near-symmetric, so a dip both sides show (the hairline at the temples) cancels, a crater does not.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from datagen.dataset.shards import view_name

from .detector import Detector, Flag
from .imaging import bbox, blob_response, box, erode, fill_holes, label, nearest_fill, ramp, robust_tail
from .views import EQUATOR_STEP, WORK_RES


def deepest_crater(depth, mask, s: float, st, symmetric: bool = False):
    """Strongest round depression in the upper part of the silhouette: (response, (row, col)).

    ``symmetric`` (the front and back views, each its own mirror image): the response less the one at
    the column mirrored about the head's centre (the middle of the top 45 % of the silhouette), more
    than 2 sigma from the centre (its largest within 1.5 sigma, as hair skews the centre), so that paired
    dips (eye sockets, the nape's sides) cancel.
    """
    if mask.sum() < 16:
        return 0.0, (0, 0)
    dd = nearest_fill(depth.astype(np.float64), mask)
    resp = blob_response(dd, st.sigma * s, -1.0)
    top, bot, _, _ = bbox(mask)
    if symmetric:
        cols = np.nonzero(mask[top:top + max(1, int(0.45 * (bot - top + 1)))].any(0))[0]
        twice_centre = int(cols[0] + cols[-1])
        x = np.arange(mask.shape[1])
        mirrored = np.maximum(resp[:, np.clip(twice_centre - x, 0, mask.shape[1] - 1)], 0.0)
        mirrored = ndi.maximum_filter(mirrored, size=2 * int(round(1.5 * st.sigma * s)) + 1)  # hair skews the centre
        off_centre = np.abs(2 * x - twice_centre) > 4.0 * st.sigma * s
        resp = np.where(off_centre[None, :], resp - mirrored, resp)
    yrel = (np.arange(mask.shape[0])[:, None] - top) / max(bot - top, 1)
    region = erode(mask, max(1, int(round(st.erode * s)))) & (yrel <= st.upper)
    r = np.where(region, resp, 0.0)
    j = np.unravel_index(int(np.argmax(r)), r.shape)
    return float(r[j]), (int(j[0]), int(j[1]))


class Holes(Detector):
    name = "holes"
    description = ("see-through holes in the silhouette, or a crater: a round depression of the depth map in the "
                   "upper head, robust z against the same viewing direction, less the mirrored view's")

    @dataclass(frozen=True)
    class Settings:
        silhouette_share: float = 0.002
        silhouette_share_sat: float = 0.02
        min_px: float = 3.0         # at 64 px; smaller holes are ignored (scaled with image area)
        z: float = 3.0              # crater blob response at which it flags: robust z against views from the
                                    # same direction (scale: MAD or the 80th-percentile spread), less the
                                    # mirrored view's
        z_sat: float = 6.0          # that z at which the score reaches 1
        sigma: float = 2.0          # blob scale in px at 64 px
        erode: float = 4.0          # ignore this many px (at 64 px) inside the silhouette edge
        upper: float = 0.5          # search the top half of the silhouette, the head above the ears (lower, the
                                    # nape and jaw line have natural dips: clean back views, 53-60 % height)
        gap_below: float = 0.6      # see-through gaps centred below this share of the silhouette's height are
                                    # gaps between hair, neck and shoulders, not holes
        mad_floor: float = 0.002    # world units (most back views have no dip at all: a smaller floor made
                                    # any nape dip a crater at a 4 % defect rate)

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
            near = box(m, 1)  # holes lie inside the silhouette's box; outside it all is background
            m = m[near]
            holes = fill_holes(m) & ~m
            lab, nh = label(holes)
            big = np.bincount(lab.ravel())[1:] if nh else np.zeros(0)
            if nh:
                top, bot, _, _ = bbox(m)
                y0 = near[0].start  # rows (centres of mass) in the view's pixels, summed as in ndi.center_of_mass
                rows = ndi.sum(holes * (np.arange(m.shape[0], dtype=float)[:, None] + y0), lab, range(1, nh + 1)) \
                    / ndi.sum(holes, lab, range(1, nh + 1))
                big = big[[(r - (top + y0)) / max(bot - top, 1) < st.gap_below for r in rows]]
            big = big[big >= min_px]
            silh.append(float(big.sum() / m.sum()) if big.size else 0.0)
        craters = []
        for t, i in v.eq_used:
            _, m, d = v.work[i]
            r, at = deepest_crater(d, m, v.s, st, symmetric=t in (0.0, 180.0))
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
        zs = {}  # yaw bin -> (view, yaw, depth, where, z)
        for v, yaw, c, at in m["craters"]:
            b = int(round(yaw / EQUATOR_STEP)) % 8
            stat = base.get(b)
            if stat is not None:
                c = float(np.float32(c))
                zs[b] = (v, yaw, c, at, (c - stat[0]) / stat[1], stat[0])
        for b, (v, yaw, c, at, z, med) in zs.items():
            mirror = zs.get((8 - b) % 8) if (8 - b) % 8 != b else None
            less = max(mirror[4], 0.0) if mirror else 0.0
            if z - less > best_z:
                best_z = z - less
                why_cr = (f"{view_name(v)}: round depression {c:.4f} deep at {int(100 * at[0])}% height "
                          f"(views from yaw {yaw:.0f}: median {med:.4f}); z {z:.1f}"
                          + (f" less {less:.1f} of the mirrored view {view_name(mirror[0])}" if mirror else "")
                          + f" (flag at {st.z:g})")
        if why_cr is not None:
            s_cr = ramp(best_z, st.z, st.z_sat)
        if s_sil >= s_cr and why_sil:
            return Flag(s_sil, why_sil, best_z if why_cr else None, st.silhouette_share_sat / st.silhouette_share)
        if why_cr:
            return Flag(s_cr, why_cr, best_z, st.z_sat / st.z)
        return Flag(0.0, "no depth views to search")
