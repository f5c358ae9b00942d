"""Image arrays as the face tools take them, and FaceError.

Images are numpy arrays (H, W, 3) RGB, uint8 or float in [0, 1]; gray, gray+alpha and RGBA, uint16
and other floats are converted here.
"""
from __future__ import annotations

import numpy as np

from datagen.errors import UserError
from datagen.dataset.shards import to_uint8


class FaceError(UserError, ValueError):
    """No usable face (or an unreadable image); the message is one line for the user."""


def to_float_rgb(image) -> np.ndarray:
    """(H, W, 3) float32 in [0, 1] from gray / gray+alpha / RGB / RGBA, uint8 / uint16 / float;
    transparent pixels are composited on white."""
    a = np.asarray(image)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] not in (1, 2, 3, 4) or min(a.shape[:2]) < 1:
        raise FaceError(f"expected an image (H, W) or (H, W, 1-4 channels), got shape {a.shape}")
    if a.dtype.kind not in "uifb":
        raise FaceError(f"unsupported image dtype {a.dtype}")
    source, a = a, a.astype(np.float32)  # one float copy, scaled in place
    if source.dtype.kind == "u" and source.itemsize == 1:
        a /= 255
    elif source.dtype.kind in "ui":  # 16-bit data (Pillow reads 16-bit gray PNGs as int32 or uint16)
        a /= 65535
    if source.dtype.kind != "u" or source.itemsize > 1:
        np.clip(np.nan_to_num(a, copy=False), 0, 1, out=a)
    if a.shape[2] in (2, 4):
        a, alpha = a[..., :-1], a[..., -1:]
        a = a * alpha + (1 - alpha)
    return np.ascontiguousarray(np.broadcast_to(a, a.shape[:2] + (3,)), dtype=np.float32)


def rgb_u8(image) -> np.ndarray:
    """(H, W, 3) contiguous uint8 RGB of any image to_float_rgb takes (uint8 RGB as is)."""
    a = np.asarray(image)
    if a.dtype == np.uint8 and a.ndim == 3 and a.shape[2] == 3:
        return np.ascontiguousarray(a)
    return to_uint8(to_float_rgb(a))
