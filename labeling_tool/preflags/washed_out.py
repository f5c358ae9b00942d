"""washed_out: a texture faded toward grey-white, relative to the dataset.

A fade reaches every colour: the most saturated pixels (lips, irises, clothes) lose their colour and
the darkest (pupils, lash lines, nostrils) are lifted. A pale, grey-haired person in grey clothes has
a low saturation and light tones overall but keeps both extremes; so the features are the 98th
percentile of saturation and the 1st percentile of grey inside the mask (means over the equator
views used), not their bulk.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .detector import Detector, Flag, ramp_flag
from .imaging import robust_below


class WashedOut(Detector):
    name = "washed_out"
    description = ("a faded texture: -log(98th percentile of saturation) + 1st percentile of grey inside the mask, "
                   "z against the dataset, the scale from the subjects below its median")

    @dataclass(frozen=True)
    class Settings:
        z: float = 3.2             # z of the fade feature at which it flags
        z_sat: float = 6.0         # z at which the score reaches 1
        floor: float = 0.05        # scale floor (log saturation + grey, 0..1)

    def threshold(self):
        return self.settings.z

    def measure(self, v):
        sat, dark = [], []
        for _, i in v.eq_used:
            c, m, _ = v.work[i]
            mx, mn = c.max(-1), c.min(-1)
            sat.append(float(np.percentile(((mx - mn) / np.maximum(mx, 1e-3))[m], 98)))
            dark.append(float(np.percentile(c.mean(-1)[m], 1)))
        if not sat:
            return {"sat98": np.nan, "grey1": np.nan}
        return {"sat98": float(np.mean(sat)), "grey1": float(np.mean(dark))}

    @staticmethod
    def _fade(m) -> float:
        return -math.log(max(m["sat98"], 1e-4)) + m["grey1"]

    def baseline(self, measured):
        ok = [m for m in measured if m and np.isfinite(m["sat98"]) and np.isfinite(m["grey1"])]
        return {"fade": robust_below([self._fade(m) for m in ok], self.settings.floor)}

    def score(self, m, base, index, keys):
        if not (np.isfinite(m["sat98"]) and np.isfinite(m["grey1"])):
            return Flag(0.0, "no colour views to measure")
        med, scale = base["fade"]
        fade = self._fade(m)
        z = (fade - med) / scale
        t = self.settings
        return ramp_flag(z, t.z, t.z_sat,
                    f"most saturated 2 % at saturation {m['sat98']:.2f}, darkest 1 % at grey {m['grey1']:.2f} "
                    f"(fade {fade:.2f}, dataset median {med:.2f}, scale {scale:.2f}); z {z:.1f} (flag at {t.z:g})", z)
