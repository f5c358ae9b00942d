"""Face detection and landmarks with dlib.

Detection: dlib's HOG frontal detector (upsample 1, then 2 when nothing is found), each candidate
confirmed by the MMOD CNN detector on a crop around it (HOG alone fires on e.g. the mission patch
of ``skimage.data.astronaut``). Found: upright, roughly frontal faces (|yaw| up to ~45 deg, in-plane
roll up to ~30 deg) of at least ~20 px. Points and boxes are in pixels of the image they came from,
(x, y), pixel (row i, column j) centred at (j, i).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from PIL import Image

from .images import rgb_u8
from .models import cnn_detector, hog_detector, load_dlib, shape_predictor

VERIFY_FACE_PX = 90  # a HOG candidate is confirmed by MMOD on a crop 1.6x its width, at this face width


@dataclass(frozen=True)
class Box:
    """A face: [left, right) x [top, bottom) in pixels; score: HOG detector confidence."""
    left: float
    top: float
    right: float
    bottom: float
    score: float

    @property
    def width(self) -> float:
        return self.right - self.left

    @property
    def area(self) -> float:
        return self.width * (self.bottom - self.top)

    def scaled(self, k: float) -> Box:
        return Box(self.left * k, self.top * k, self.right * k, self.bottom * k, self.score)


def _resize(u8: np.ndarray, k: float) -> np.ndarray:
    h, w = u8.shape[:2]
    size = (max(1, round(w * k)), max(1, round(h * k)))
    return np.asarray(Image.fromarray(u8).resize(size, Image.Resampling.LANCZOS))


def dlib_rect(box: Box):
    """``box`` as a dlib rectangle (inclusive right and bottom)."""
    return load_dlib().rectangle(round(box.left), round(box.top), round(box.right) - 1, round(box.bottom) - 1)


def _confirmed(u8: np.ndarray, box: Box) -> bool:
    """Whether the MMOD CNN detector finds a face centred inside ``box`` on a crop around it."""
    h, w = u8.shape[:2]
    cx, cy, half = (box.left + box.right) / 2, (box.top + box.bottom) / 2, 0.8 * box.width
    x0, y0 = max(0, int(cx - half)), max(0, int(cy - half))
    x1, y1 = min(w, int(math.ceil(cx + half))), min(h, int(math.ceil(cy + half)))
    k = VERIFY_FACE_PX / box.width
    crop = _resize(u8[y0:y1, x0:x1], k)
    for det in cnn_detector()(crop, 0):
        r = det.rect
        fx, fy = x0 + (r.left() + r.right()) / 2 / k, y0 + (r.top() + r.bottom()) / 2 / k
        if box.left <= fx < box.right and box.top <= fy < box.bottom:
            return True
    return False


def detect_faces(image, max_side: int = 1024, verify: bool = True) -> list[Box]:
    """Faces in an RGB image, largest first, boxes in its pixels. Images larger than ``max_side`` px
    are searched downscaled; ``verify=False`` skips the CNN confirmation (faster, more false hits)."""
    u8 = rgb_u8(image)
    k = min(1.0, max_side / max(u8.shape[:2]))
    work = _resize(u8, k) if k < 1 else u8
    for upsample in (1, 2):
        rects, scores, _ = hog_detector().run(work, upsample, 0.0)
        boxes = [Box(r.left(), r.top(), r.right() + 1, r.bottom() + 1, s) for r, s in zip(rects, scores)]
        if verify:
            boxes = [b for b in boxes if _confirmed(work, b)]
        if boxes:
            return sorted((b.scaled(1 / k) for b in boxes), key=lambda b: -b.area)
    return []


def landmarks(image, box: Box, points: int = 68) -> np.ndarray:
    """dlib's 68- or 5-point landmarks of the face in ``box``, (points, 2) float64 pixels (x, y)."""
    shape = shape_predictor(points)(rgb_u8(image), dlib_rect(box))
    return np.array([(p.x, p.y) for p in shape.parts()], dtype=np.float64)
