"""duplicate: near-duplicates of another subject.

Cosine similarity of small grey thumbnails of the frontal view (cropped to the head, the dataset's
mean removed), computed in blocks so it scales to large datasets.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .detector import Detector, Flag
from .imaging import bbox


def thumbnail(rgb, mask, side: int):
    """Grey thumbnail of the head crop (square around the mask's bounding box), flattened float32."""
    from PIL import Image

    top, bot, left, right = bbox(mask)
    cy, cx = (top + bot) / 2.0, (left + right) / 2.0
    half = max(bot - top, right - left) / 2.0 + 1.0
    box = (int(math.floor(cx - half)), int(math.floor(cy - half)), int(math.ceil(cx + half)) + 1,
           int(math.ceil(cy + half)) + 1)
    grey = Image.fromarray(np.asarray(rgb, dtype=np.uint8)).convert("L")
    return np.asarray(grey.crop(box).resize((side, side), Image.BILINEAR), dtype=np.float32).ravel()


def nearest(thumbs: list, block: int):
    """For each row: (best cosine similarity to another row, its index), blocked over rows and columns."""
    n = len(thumbs)
    best = np.full(n, -np.inf, dtype=np.float32)
    arg = np.full(n, -1, dtype=np.int64)
    valid = [i for i, t in enumerate(thumbs) if t is not None]
    if len(valid) < 2:
        return best, arg
    x = np.empty((len(valid), thumbs[valid[0]].size))  # float64, filled in place: one copy of the thumbnails
    for row, i in enumerate(valid):
        x[row] = thumbs[i]
    x -= x.mean(axis=0, keepdims=True)            # remove what every head has in common
    B = max(1, block)
    unit = np.empty(x.shape, np.float32)
    for i0 in range(0, len(x), B):  # a block of rows at a time, so no second float64 copy exists
        rows = x[i0:i0 + B]
        rows -= rows.mean(axis=1, keepdims=True)
        unit[i0:i0 + B] = rows / np.maximum(np.linalg.norm(rows, axis=1, keepdims=True), 1e-9)
    x = unit
    m = len(valid)
    vb = np.full(m, -np.inf, dtype=np.float32)
    va = np.full(m, -1, dtype=np.int64)
    for i0 in range(0, m, B):
        xi = x[i0:i0 + B]
        for j0 in range(i0, m, B):
            sim = xi @ x[j0:j0 + B].T
            if j0 == i0:
                np.fill_diagonal(sim, -np.inf)
            r = sim.argmax(axis=1)
            rv = sim[np.arange(sim.shape[0]), r]
            upd = rv > vb[i0:i0 + B]
            vb[i0:i0 + B][upd] = rv[upd]
            va[i0:i0 + B][upd] = j0 + r[upd]
            if j0 != i0:
                c = sim.argmax(axis=0)
                cv = sim[c, np.arange(sim.shape[1])]
                upd = cv > vb[j0:j0 + B]
                vb[j0:j0 + B][upd] = cv[upd]
                va[j0:j0 + B][upd] = i0 + c[upd]
    valid = np.asarray(valid)
    best[valid] = vb
    arg[valid] = np.where(va >= 0, valid[np.clip(va, 0, None)], -1)
    return best, arg


class Duplicate(Detector):
    name = "duplicate"
    description = ("near-duplicate of another subject: cosine similarity of 16x16 grey thumbnails of the frontal "
                   "view (head crop, dataset mean removed)")
    calibrated = False  # an absolute similarity to the nearest other subject, not a ramp from 0

    @dataclass(frozen=True)
    class Settings:
        dissim: float = 0.01       # 1 - cosine similarity; 0.5 at this, 1.0 at identical
        block: int = 2048          # rows/columns per block of the similarity computation
        thumb: int = 16            # thumbnail side in px

    def threshold(self):
        return 1.0 - self.settings.dissim

    def measure(self, v):
        f = v.front
        if f is None or v.rgb.get(f) is None or v.mask(f).sum() < 4:
            return None
        return {"thumb": thumbnail(v.rgb[f], v.mask(f), self.settings.thumb), "view": f}

    def baseline(self, measured):
        return nearest([m["thumb"] if m else None for m in measured], self.settings.block)

    def score(self, m, base, index, keys):
        best, arg = base
        sim, other = float(best[index]), int(arg[index])
        if other < 0 or not math.isfinite(sim):
            return Flag(0.0, "no frontal thumbnail to compare")
        d = self.settings.dissim
        dis = max(0.0, 1.0 - sim)
        score = 1.0 - 0.5 * dis / d if dis < 2 * d else 0.0
        return Flag(float(np.clip(score, 0.0, 1.0)), f"frontal view closest to {keys[other]} (cosine {sim:.4f}, flag "
                                                       f"at {1 - d:.2f})", sim)
