"""What the detectors look at: one subject's masks and its equator views at the working resolution.

Only what reviewers may see is read: ``index.json``, the sidecars (for the byte ranges) and the
shard tars; the hidden ``truth/`` folder is never opened. Of a subject, the metadata, every mask and
the colour and depth of up to 8 views around the equator (one per 45 degrees of yaw) are decoded.
Image features are computed at about ``WORK_RES`` px (larger images are averaged down by an integer
factor), so thresholds do not depend on the image size.
"""
from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field

import numpy as np

from datagen.errors import DatasetError
from datagen.dataset.shards import decode_exr, decode_png, read_range, view_name

from .imaging import downsample, wrap

WORK_RES = 64                # image features are computed at about this size
EQUATOR_STEP = 45.0          # the views used for colour/depth features: one per 45 degrees of yaw
EQUATOR_TOL = 22.5           # ... within this many degrees of the target yaw
BACK_TOL = 20.0              # a back (or front) view: |yaw - 180| (|yaw|) and |pitch| within this


def equator_views(views: list[dict]) -> dict:
    """{target yaw: view index}: per 45-degree yaw target the closest view near the equator."""
    yaw = np.array([v["yaw_deg"] for v in views], dtype=np.float64)
    pitch = np.array([v["pitch_deg"] for v in views], dtype=np.float64)
    chosen = {}
    for t in np.arange(0.0, 360.0, EQUATOR_STEP):
        dy = np.abs(wrap(yaw - t))
        cost = np.where(dy <= EQUATOR_TOL, dy + np.abs(pitch), np.inf)
        if np.isfinite(cost).any():
            i = int(np.argmin(cost))
            if i not in chosen.values():
                chosen[float(t)] = i
    return chosen


def needed(field_name: str, fields: dict) -> bool:
    """Which members to read: metadata, every mask, and colour/depth of the equator views only (known
    once the subject's metadata, its first member, has been read; otherwise everything is read)."""
    if field_name == "json" or field_name.endswith(".mask.png"):
        return True
    if not (field_name.endswith(".png") or field_name.endswith(".depth.exr")):
        return False
    try:
        return int(field_name[1:].split(".", 1)[0]) in _equator_set(fields["json"])
    except (KeyError, ValueError, TypeError):
        return True


@functools.lru_cache(maxsize=4)
def _equator_set(metadata: bytes) -> frozenset:
    """The equator views' indices of a subject's metadata JSON (parsed once per subject, not per member)."""
    return frozenset(equator_views(json.loads(metadata)["views"]).values())


@dataclass
class SubjectViews:
    """A subject as the detectors see it.

    ``alpha`` (every view, uint8 at full resolution); ``rgb``/``depth`` of the equator views at full
    resolution; ``work``: {view: (colour (h,w,3) in [0,1], mask (h,w), depth (h,w))} at the working
    resolution for the equator views with at least 16 mask pixels; ``eq_used``: their (target yaw,
    view) in yaw order; ``front``/``back``: the equator views nearest yaw 0 / 180 (``back`` None
    unless within ``BACK_TOL``); ``s``: working pixels per pixel at 64 px.
    """

    key: str
    meta: dict
    alpha: list
    rgb: dict
    depth: dict
    k: int
    s: float
    eq: dict
    work: dict = field(default_factory=dict)
    memo: dict = field(default_factory=dict)

    def once(self, key, compute):
        """``compute()``, computed once per subject under ``key`` (measures several detectors share)."""
        if key not in self.memo:
            self.memo[key] = compute()
        return self.memo[key]

    @property
    def views(self) -> list:
        return self.meta["views"]

    @property
    def n(self) -> int:
        return len(self.alpha)

    @property
    def resolution(self) -> int:
        return int(self.alpha[0].shape[0])

    @property
    def eq_used(self) -> list:
        return [(t, i) for t, i in sorted(self.eq.items()) if i in self.work and self.work[i][1].sum() >= 16]

    @property
    def front(self):
        return self.eq.get(0.0)

    @property
    def back(self):
        b = self.eq.get(180.0)
        if b is not None and (abs(wrap(self.views[b]["yaw_deg"] - 180.0)) > BACK_TOL
                              or abs(self.views[b]["pitch_deg"]) > BACK_TOL):
            return None
        return b

    def mask(self, i: int) -> np.ndarray:
        return np.asarray(self.alpha[i]) > 127

    @classmethod
    def from_arrays(cls, key: str, meta: dict, alpha: list, rgb: dict, depth: dict) -> "SubjectViews":
        """From decoded images: every mask, and rgb/depth {view: array} of (at least) the equator views."""
        if not meta.get("views") or not alpha:
            raise DatasetError(f"subject {key} has no views")
        res = int(alpha[0].shape[0])
        k = max(1, int(round(res / WORK_RES)))
        eq = equator_views(meta["views"])
        v = cls(key, meta, alpha, rgb, depth, k, (res / k) / WORK_RES, eq)
        for _, i in eq.items():
            if rgb.get(i) is not None and depth.get(i) is not None:
                v.work[i] = downsample(rgb[i], alpha[i], depth[i], k)
        return v

    @classmethod
    def from_fields(cls, key: str, fields: dict, where: str = "") -> "SubjectViews":
        """Decode the metadata, all masks, and RGB + depth of the equator views of raw tar fields."""
        try:
            meta = json.loads(fields["json"])
            views = meta["views"]
            keep = set(equator_views(views).values())
            alpha = [decode_png(fields[f"{view_name(i)}.mask.png"]) for i in range(len(views))]
            rgb = {i: decode_png(fields[f"{view_name(i)}.png"]) for i in keep}
            depth = {i: decode_exr(fields[f"{view_name(i)}.depth.exr"]) for i in keep}
        except KeyError as e:
            raise DatasetError(f"{where}: subject {key} lacks field {e}") from None
        except DatasetError:
            raise
        except Exception as e:
            raise DatasetError(f"{where}: subject {key} does not decode ({type(e).__name__}: {e})") from None
        return cls.from_arrays(key, meta, alpha, rgb, depth)

    @classmethod
    def read(cls, tar, key: str, start: int, end: int) -> "SubjectViews":
        """Read one subject by its byte range in a shard (only the members the detectors need)."""
        return cls.from_fields(key, read_range(tar, key, start, end, needed), str(tar))
