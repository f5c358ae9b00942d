"""floaters: parts of the silhouette detached from the head.

Connected components of alpha > 127 other than the largest, as a share of the silhouette, in the
worst view; specks below a minimum size are ignored.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datagen.dataset.shards import view_name

from .detector import Detector, Flag, ramp_flag
from .imaging import label
from .views import WORK_RES


def components(mask: np.ndarray, min_px: float):
    """Detached share: area of components other than the largest (each >= min_px) over all mask area."""
    lab, n = label(mask, eight=True)
    if n <= 1:
        return 0.0, 0, 0
    areas = np.bincount(lab.ravel())[1:]
    main = int(np.argmax(areas))
    others = np.delete(areas, main)
    others = others[others >= min_px]
    if others.size == 0:
        return 0.0, 0, 0
    return float(others.sum() / areas.sum()), int(others.size), int(others.max())


class Floaters(Detector):
    name = "floaters"
    description = ("silhouette parts detached from the head (alpha > 127 components other than the largest), "
                   "area share of the silhouette in the worst view")

    @dataclass(frozen=True)
    class Settings:
        share: float = 0.002       # detached area / silhouette area in the worst view
        share_sat: float = 0.02
        min_px: float = 3.0        # at 64 px; smaller specks are ignored (scaled with image area)

    def threshold(self):
        return self.settings.share

    def measure(self, v):
        min_px = max(2.0, self.settings.min_px * (v.resolution / WORK_RES) ** 2)
        parts = [components(v.mask(i), min_px) if v.mask(i).any() else (0.0, 0, 0) for i in range(v.n)]
        return {"share": np.asarray([f[0] for f in parts], dtype=np.float32),
                "count": np.asarray([f[1] for f in parts], dtype=np.int32),
                "largest": np.asarray([f[2] for f in parts], dtype=np.int32)}

    def score(self, m, base, index, keys):
        fs = m["share"]
        if not (len(fs) and fs.max() > 0):
            return Flag(0.0, f"no detached parts in {len(fs)} views")
        i = int(np.argmax(fs))
        t = self.settings
        return ramp_flag(float(fs[i]), t.share, t.share_sat,
                    f"{view_name(i)}: {int(m['count'][i])} detached part(s), {100 * fs[i]:.1f}% of the silhouette "
                    f"(largest {int(m['largest'][i])} px); detached parts in {int((fs > 0).sum())} of {len(fs)} views",
                    float(fs[i]))
