"""haze: semi-transparent material around the head (haze, wisps, smoke-like floaters).

Two shares of the silhouette, each in its worst view; the stronger counts. (1) Pixels of partial
alpha (between ``low`` and ``high``) farther than a few pixels (at 64 px) from the solid silhouette.
(2) Thin material (alpha above ``low``; what a morphological opening of a few pixels removes, so not
blobs) farther than those pixels from the head's solid body (the largest solid component): wisps
dense enough to be opaque, which (1) counts as solid. A clean head's soft rim is one or two pixels
wide and does not count; opaque detached blobs are the floaters detector's.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from datagen.dataset.shards import view_name

from .detector import Detector, Flag, ramp_flag
from .imaging import farther_than, label


def _material_box(a: np.ndarray, low: float) -> np.ndarray:
    """``a`` cut to the bounding box of its pixels above ``low`` and a 1-pixel margin: every solid pixel
    and all material lie inside, so distances to them, components and openings measured in the box
    equal those of the whole view (pixels outside hold no material), at the cost of the box only."""
    rows, cols = np.nonzero((a > low).any(1))[0], np.nonzero((a > low).any(0))[0]
    if not rows.size:
        return a[:0, :0]
    return a[max(rows[0] - 1, 0):rows[-1] + 2, max(cols[0] - 1, 0):cols[-1] + 2]


class Haze(Detector):
    name = "haze"
    description = ("semi-transparent material around the head: partial-alpha pixels more than 3 px (at 64 px) "
                   "from the solid silhouette, or thin material (wisps) more than 3 px from the head's solid body; "
                   "shares of the silhouette in the worst view")

    @dataclass(frozen=True)
    class Settings:
        low: float = 0.04          # alpha range of "partial" pixels
        high: float = 0.75
        distance: float = 3.0      # px at 64 px from the solid silhouette
        share: float = 0.003       # haze area / silhouette area in the worst view (clean heads: 0)
        share_sat: float = 0.05
        opening: float = 1.5       # px at 64 px: material an opening of this radius removes is thin
        thin: float = 0.02         # thin material far from the body / silhouette area at which it flags
        thin_sat: float = 0.06     # that share at which the score reaches 1

    def threshold(self):
        return self.settings.share

    def measure(self, v):
        st = self.settings
        k = v.resolution / 64.0
        shares, thin = [], []
        for i in range(v.n):
            a = _material_box(np.asarray(v.alpha[i], dtype=np.float32) / 255.0, st.low)
            solid = a > 0.5
            if solid.sum() < 16:
                shares.append(0.0)
                thin.append(0.0)
                continue
            seen = a > st.low
            far = farther_than(solid, seen, st.distance * k)
            shares.append(float((far & (a < st.high)).sum() / solid.sum()))
            parts, n = label(solid)
            if n == 1:  # the body is the solid silhouette
                material = far
            else:
                body = parts == 1 + int(np.argmax(ndi.sum(solid, parts, range(1, n + 1))))
                material = farther_than(body, seen, st.distance * k)
            if material.any():  # an opening of nothing is nothing
                material &= ~ndi.binary_opening(material, iterations=max(1, int(round(st.opening * k))))
            thin.append(float(material.sum() / solid.sum()))
        return {"share": np.asarray(shares, dtype=np.float32), "thin": np.asarray(thin, dtype=np.float32)}

    def score(self, m, base, index, keys):
        sh = m["share"]
        thin = m.get("thin", np.zeros_like(sh))
        if not len(sh) or max(sh.max(), thin.max()) <= 0:
            return Flag(0.0, f"no semi-transparent material around the head in {len(sh)} views")
        t = self.settings
        i, j = int(np.argmax(sh)), int(np.argmax(thin))
        partial = ramp_flag(float(sh[i]), t.share, t.share_sat,
                       f"{view_name(i)}: semi-transparent material {100 * sh[i]:.1f}% of the silhouette away from the "
                       f"head; in {int((sh > t.share).sum())} of {len(sh)} views above {100 * t.share:g}%", float(sh[i]))
        wisps = ramp_flag(float(thin[j]), t.thin, t.thin_sat,
                     f"{view_name(j)}: thin material (wisps) {100 * thin[j]:.1f}% of the silhouette away from the head's "
                     f"body (flag at {100 * t.thin:g}%)", float(thin[j]))
        return partial if partial.score >= wisps.score else wisps
