"""washed_out: low colour saturation and lifted dark tones inside the mask, relative to the dataset.

Saturation is that of the most colourful tenth of the subject (skin, lips, clothes): grey or white
hair lowers a subject's mean saturation but leaves that tenth alone; a washed-out texture fades all of it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .detector import Detector, Flag
from .imaging import ramp, robust


class WashedOut(Detector):
    name = "washed_out"
    description = ("low saturation and lifted dark tones inside the mask: mean of -z(log saturation of the most "
                   "colourful tenth) and z(10th percentile grey) against the dataset")

    @dataclass(frozen=True)
    class Settings:
        z: float = 3.1             # mean of -z(log saturation) and z(10th percentile grey); tuning seeds:
                                   # pale, grey-haired, grey-clad clean subjects up to 3.0, injected 2.5 to 6.0
        z_sat: float = 5.0

    def threshold(self):
        return self.settings.z

    def measure(self, v):
        sat, p10 = [], []
        for _, i in v.eq_used:
            c, m, _ = v.work[i]
            mx, mn = c.max(-1), c.min(-1)
            sat.append(float(np.percentile(((mx - mn) / np.maximum(mx, 1e-3))[m], 90)))
            p10.append(float(np.percentile(c.mean(-1)[m], 10)))
        return {"sat": float(np.mean(sat)) if sat else np.nan, "p10": float(np.mean(p10)) if p10 else np.nan}

    def baseline(self, measured):
        ok = [m for m in measured if m]
        return {"log_sat": robust([math.log(max(m["sat"], 1e-4)) for m in ok if np.isfinite(m["sat"])], 0.02),
                "p10": robust([m["p10"] for m in ok if np.isfinite(m["p10"])], 0.005)}

    def score(self, m, base, index, keys):
        if not (np.isfinite(m["sat"]) and np.isfinite(m["p10"])):
            return Flag(0.0, "no colour views to measure")
        (ms, ss), (mp, sp) = base["log_sat"], base["p10"]
        z = 0.5 * (-(math.log(max(m["sat"], 1e-4)) - ms) / ss + (m["p10"] - mp) / sp)
        t = self.settings
        return Flag(ramp(z, t.z, t.z_sat),
                    f"saturation of the most colourful tenth {m['sat']:.2f} (median {math.exp(ms):.2f}), darkest decile {m['p10']:.2f} "
                    f"(median {mp:.2f}); z {z:.1f} (flag at {t.z:g})", z)
