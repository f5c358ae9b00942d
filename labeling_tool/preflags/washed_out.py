"""washed_out: a texture faded toward grey-white, relative to the dataset.

A fade reaches every colour, so even the most saturated pixels (lips, irises, clothes) lose their
colour; a pale, grey-haired person in grey clothes is desaturated in bulk but keeps some. The
measure is the 98th percentile of saturation inside the mask (mean over the equator views used),
read as its inverse to the power ``POWER`` (1.5), the fade feature. The darkest pixels, which a fade
lifts too, are left out: light and dark hair split clean subjects into two groups there, which
widened the clean tail more than it separated fades (tuning seeds 50 and 51, 48 clean subjects and 16
fades, in -log saturation: 2 clean subjects past z 3.2 against 5).

Why the power: the dataset's calibration (``detector.py``) models the clean tail above the median as
exponential. Read as -log saturation, the clean tail is lighter than that, so the calibrated cut
was spent on nothing: in 64-subject samples of tuning seed 6197 (500 subjects at 128 px, 22 fades),
scored in full, no clean subject passed washed_out's cut and 14 of 42 fades were found; with the
inverse saturation to the power 1.5, 32 of 42, the union's clean flags unchanged (8 of 535). This
detector alone, cut at a share of 0.4 % fitted to its own evidence, found 51 % of fades (-log) and
69, 81, 93 and 97 % with powers 0.5, 1, 1.5 and 2, passing 0.07, 0.36, 0.40 and 0.51 % of clean
subjects: 1.5 spends about its share. 15 other features (other percentiles, chroma, luminance and
its range, sums of them) separated fades from clean subjects less than the 98th percentile of
saturation.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .detector import Detector, Flag, ramp_flag
from .imaging import robust_below

POWER = 1.5  # the fade feature: saturation ** -POWER (see the module docstring)
SATURATION_FLOOR = 0.02  # saturation read as at least this (a grey texture's feature stays finite)


class WashedOut(Detector):
    name = "washed_out"
    description = (f"a faded texture: (98th percentile of saturation inside the mask) ** -{POWER:g}, z against "
                   "the dataset, the scale from the subjects below its median")

    @dataclass(frozen=True)
    class Settings:
        z: float = 6.5             # z of the fade feature at which it flags
        z_sat: float = 12.0        # z at which the score reaches 1
        floor: float = 0.05        # scale floor (fade feature)

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
        return max(m["sat98"], SATURATION_FLOOR) ** -POWER

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
                    f"most saturated 2 % at saturation {m['sat98']:.2f} (fade {fade:.2f}, dataset median "
                    f"{med:.2f}, scale {scale:.2f}); z {z:.1f} (flag at {t.z:g})", z)
