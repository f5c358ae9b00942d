"""haze: semi-transparent material around the head (haze, wisps, smoke-like floaters).

Pixels of partial alpha (between ``low`` and ``high``) farther than a few pixels (at 64 px) from the
head's solid silhouette, as a share of the silhouette, in the worst view. A clean head's soft rim is
one or two pixels wide and does not count; opaque detached parts are the floaters detector's.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from datagen.shards import view_name

from .detector import Detector, Flag
from .imaging import ramp


class Haze(Detector):
    name = "haze"
    description = ("semi-transparent material around the head: partial-alpha pixels more than 3 px (at 64 px) "
                   "from the solid silhouette, share of the silhouette in the worst view")

    @dataclass(frozen=True)
    class Settings:
        low: float = 0.04          # alpha range of "partial" pixels
        high: float = 0.75
        distance: float = 3.0      # px at 64 px from the solid silhouette
        share: float = 0.003       # haze area / silhouette area in the worst view (clean heads: 0)
        share_sat: float = 0.05

    def threshold(self):
        return self.settings.share

    def measure(self, v):
        st = self.settings
        shares = []
        for i in range(v.n):
            a = np.asarray(v.alpha[i], dtype=np.float32) / 255.0
            solid = a > 0.5
            if solid.sum() < 16:
                shares.append(0.0)
                continue
            far = ndi.distance_transform_edt(~solid) > st.distance * v.resolution / 64.0
            partial = (a > st.low) & (a < st.high) & far
            shares.append(float(partial.sum() / solid.sum()))
        return {"share": np.asarray(shares, dtype=np.float32)}

    def score(self, m, base, index, keys):
        sh = m["share"]
        if not len(sh) or sh.max() <= 0:
            return Flag(0.0, f"no semi-transparent material around the head in {len(sh)} views")
        i = int(np.argmax(sh))
        t = self.settings
        return Flag(ramp(float(sh[i]), t.share, t.share_sat),
                    f"{view_name(i)}: semi-transparent material {100 * sh[i]:.1f}% of the silhouette away from the "
                    f"head; in {int((sh > t.share).sum())} of {len(sh)} views above {100 * t.share:g}%", float(sh[i]))
