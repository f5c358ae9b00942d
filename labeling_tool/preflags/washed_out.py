"""washed_out: a texture faded toward grey-white, relative to the dataset.

A fade reaches every colour, so even the most saturated pixels (lips, irises, clothes) lose their
colour; a pale, grey-haired person in grey clothes is desaturated in bulk but keeps some. The
feature is -log of the 98th percentile of saturation inside the mask (mean over the equator views
used). The darkest pixels, which a fade lifts too, are left out: light and dark hair split clean
subjects into two groups there, which widened the clean tail more than it separated fades (tuning
seeds 50 and 51: 48 clean subjects, 16 fades; the fades' lowest value over the clean spread from
median to 90th percentile 2.09 alone, 1.72 with the darkest 1 % added; clean subjects past z 3.2: 2
against 5).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .detector import Detector, Flag, ramp_flag
from .imaging import robust_below


class WashedOut(Detector):
    name = "washed_out"
    description = ("a faded texture: -log(98th percentile of saturation) inside the mask, z against the dataset, "
                   "the scale from the subjects below its median")

    @dataclass(frozen=True)
    class Settings:
        z: float = 3.2             # z of the fade feature at which it flags
        z_sat: float = 6.0         # z at which the score reaches 1
        floor: float = 0.05        # scale floor (-log saturation)

    def threshold(self):
        return self.settings.z

    def measure(self, v):
        sat = []
        for _, i in v.eq_used:
            c, m, _ = v.work[i]
            mx, mn = c.max(-1), c.min(-1)
            sat.append(float(np.percentile(((mx - mn) / np.maximum(mx, 1e-3))[m], 98)))
        return {"sat98": float(np.mean(sat)) if sat else np.nan}

    @staticmethod
    def _fade(m) -> float:
        return -math.log(max(m["sat98"], 1e-4))

    def baseline(self, measured):
        ok = [m for m in measured if m and np.isfinite(m["sat98"])]
        return {"fade": robust_below([self._fade(m) for m in ok], self.settings.floor)}

    def score(self, m, base, index, keys):
        if not np.isfinite(m["sat98"]):
            return Flag(0.0, "no colour views to measure")
        med, scale = base["fade"]
        fade = self._fade(m)
        z = (fade - med) / scale
        t = self.settings
        return ramp_flag(z, t.z, t.z_sat,
                    f"most saturated 2 % at saturation {m['sat98']:.2f} (fade -log {fade:.2f}, dataset median "
                    f"{med:.2f}, scale {scale:.2f}); z {z:.1f} (flag at {t.z:g})", z)
