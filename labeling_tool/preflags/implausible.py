"""implausible: mean mask area or median depth far from the dataset (robust |z|)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .detector import Detector, Flag, ramp_flag
from .imaging import robust


class Implausible(Detector):
    name = "implausible"
    description = "mean mask area or median depth far from the dataset (robust |z|)"

    @dataclass(frozen=True)
    class Settings:
        z: float = 8.0             # |z| of log mask area or median depth at which it flags
        z_sat: float = 12.0        # |z| at which the score reaches 1

    def threshold(self):
        return self.settings.z

    def measure(self, v):
        area = float(np.mean([np.float32(v.mask(i).mean()) for i in range(v.n)]))
        depths = [float(np.median(v.work[i][2][v.work[i][1]])) for _, i in v.eq_used]
        return {"area": area, "depth": float(np.median(depths)) if depths else np.nan}

    def baseline(self, measured):
        ok = [m for m in measured if m]
        return {"log_area": robust([math.log(max(m["area"], 1e-6)) for m in ok], 0.02),
                "depth": robust([m["depth"] for m in ok if np.isfinite(m["depth"])], 0.02)}  # world units

    def score(self, m, base, index, keys):
        parts = []
        if m["area"] > 0:
            za = (math.log(max(m["area"], 1e-6)) - base["log_area"][0]) / base["log_area"][1]
            parts.append((abs(za), f"mean mask area {100 * m['area']:.1f}% of the image (median "
                                   f"{100 * math.exp(base['log_area'][0]):.1f}%, z {za:+.1f})"))
        if np.isfinite(m["depth"]):
            zd = (m["depth"] - base["depth"][0]) / base["depth"][1]
            parts.append((abs(zd), f"median depth {m['depth']:.3f} (median {base['depth'][0]:.3f}, z {zd:+.1f})"))
        if not parts:
            return Flag(0.0, "nothing to measure (all views empty)")
        zmax, why = max(parts)
        return ramp_flag(zmax, self.settings.z, self.settings.z_sat, why, zmax)
