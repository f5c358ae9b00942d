"""empty: views whose mask is (almost) empty, and subjects that do not decode."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datagen.dataset.shards import view_name

from .detector import Detector, Flag


class Empty(Detector):
    name = "empty"
    description = "views with (almost) no mask, or a subject that does not decode"
    calibrated = False  # a count of empty views, not a ramp: clean subjects have none

    @dataclass(frozen=True)
    class Settings:
        area: float = 0.0005       # a view is empty below this mask fraction of the image

    def threshold(self):
        return self.settings.area

    def measure(self, v):
        return {"area": np.asarray([float(v.mask(i).mean()) for i in range(v.n)], dtype=np.float32)}

    def score(self, m, base, index, keys):
        area = m["area"]
        empty = [i for i, a in enumerate(area) if a < self.settings.area]
        if empty:
            names = ", ".join(view_name(i) for i in empty[:6]) + (", ..." if len(empty) > 6 else "")
            return Flag(0.5 + 0.5 * len(empty) / len(area), f"{len(empty)} of {len(area)} views empty ({names})",
                        len(empty))
        return Flag(0.0, f"no empty views (smallest mask {100 * float(area.min()):.1f}% of the image)"
                    if len(area) else "no views")
