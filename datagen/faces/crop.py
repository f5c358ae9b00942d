"""EG3D-framed square head crops from dlib's 68 landmarks.

The training images are EG3D-style FFHQ crops (camera radius 2.7, FOV 18.84 deg). EG3D's
``crop_images_in_the_wild.py`` fits Deep3DFaceRecon's 5-point mean face (eye centres, nose tip,
mouth corners; eye-centre distance 0.6213 units, eyes to mouth 0.6714 units, template origin 0.2900
units below the eyes), maps 1 unit to 300 px of a 1024 px image and keeps the central 700 px. So
the crop is 700/300 = 2.333 units wide, centred 0.432 eye-to-mouth lengths below the eye midpoint:
in a 512 px crop the eyes are 136 px apart at y = 192 px and the mouth is at y = 340 px. We build
the crop as FFHQ does (a square oriented by the eye-to-eye and eye-to-mouth vectors of dlib's 68
landmarks, sized by the larger of the two, which is robust to yaw and pitch) with those EG3D sizes.
"""
from __future__ import annotations

import cv2
import numpy as np

from datagen.dataset.shards import to_uint8

from .detect import Box, landmarks
from .images import to_float_rgb

# EG3D framing of the 5-point mean face (module docstring), in template units.
CROP_SIDE = 700 / 300
EYE_DISTANCE = 0.62129
EYE_TO_MOUTH = 0.67135
CENTRE_BELOW_EYES = 0.29004 / EYE_TO_MOUTH  # fraction of eye-to-mouth


def head_quad(lm68: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Corners (top-left, bottom-left, bottom-right, top-right), (4, 2) px, of the EG3D-framed
    square head crop of a face with these 68 landmarks (module docstring); ``scale`` > 1 widens it."""
    eye_l, eye_r = lm68[36:42].mean(axis=0), lm68[42:48].mean(axis=0)
    eye_avg, eye_to_eye = (eye_l + eye_r) / 2, eye_r - eye_l
    eye_to_mouth = (lm68[48] + lm68[54]) / 2 - eye_avg
    x = eye_to_eye - np.flipud(eye_to_mouth) * [-1, 1]  # FFHQ: right direction from both vectors
    x /= np.hypot(*x)
    half = scale * CROP_SIDE / 2 * max(np.hypot(*eye_to_eye) / EYE_DISTANCE, np.hypot(*eye_to_mouth) / EYE_TO_MOUTH)
    x *= half
    y = np.flipud(x) * [-1, 1]
    c = eye_avg + CENTRE_BELOW_EYES * eye_to_mouth
    return np.stack([c - x - y, c - x + y, c + x + y, c + x - y])


def _pad(img: np.ndarray, pads: tuple[int, int, int, int], side: float, pad) -> np.ndarray:
    """Pad (top, bottom, left, right) px; 'blur' mirrors the image, blurs the mirrored part and fades
    it to the median colour over 0.3 crop sides (as FFHQ); an RGB tuple in [0, 1] fills with it."""
    t, b, l, r = pads
    if pad != "blur":
        out = np.empty((img.shape[0] + t + b, img.shape[1] + l + r, 3), np.float32)
        out[:] = np.asarray(pad, np.float32)
        out[t:t + img.shape[0], l:l + img.shape[1]] = img
        return out
    mode = "reflect" if min(img.shape[:2]) > 1 else "edge"
    out = np.pad(img, ((t, b), (l, r), (0, 0)), mode=mode)
    yy, xx = np.arange(out.shape[0]), np.arange(out.shape[1])
    dy = np.maximum(np.maximum(t - yy, yy - (t + img.shape[0] - 1)), 0)
    dx = np.maximum(np.maximum(l - xx, xx - (l + img.shape[1] - 1)), 0)
    outside = np.maximum(dy[:, None], dx[None, :])[..., None].astype(np.float32)
    blurred = cv2.GaussianBlur(out, (0, 0), 0.02 * side, borderType=cv2.BORDER_REFLECT)
    out += (blurred - out) * np.clip(outside / (0.05 * side), 0, 1)
    out += (np.median(img.reshape(-1, 3), axis=0) - out) * np.clip(outside / (0.3 * side), 0, 1)
    return out


def warp_quad(rgb: np.ndarray, quad: np.ndarray, out_size: int, pad="blur") -> np.ndarray:
    """Resample the square ``quad`` (head_quad's corner order) of a float RGB image to
    (out_size, out_size, 3) float32: area-averaged first (OpenCV INTER_AREA) when it is 2x or more
    larger, then one bilinear affine warp (``cv2.warpAffine``), padded with ``pad`` (see _pad) where
    it leaves the image."""
    quad = np.asarray(quad, np.float64)
    side = float(np.hypot(*(quad[3] - quad[0])))
    h, w = rgb.shape[:2]
    lo = np.floor(quad.min(axis=0)).astype(int) - 2
    hi = np.ceil(quad.max(axis=0)).astype(int) + 3
    x0, y0 = np.clip(lo, 0, [w - 1, h - 1])
    x1, y1 = np.maximum(np.minimum(hi, [w, h]), [x0 + 1, y0 + 1])
    img, quad = np.ascontiguousarray(rgb[y0:y1, x0:x1], np.float32), quad - [x0, y0]
    if side >= 2 * out_size:
        k = out_size / side  # the quad's side becomes out_size px
        size = (max(1, round(img.shape[1] * k)), max(1, round(img.shape[0] * k)))
        scale = np.array([size[0] / img.shape[1], size[1] / img.shape[0]])
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        quad, side = (quad + 0.5) * scale - 0.5, side * float(scale.mean())  # pixel centres at integers
    lo = np.floor(quad.min(axis=0)).astype(int) - 2
    hi = np.ceil(quad.max(axis=0)).astype(int) + 3
    l, t = np.maximum(-lo, 0)
    r, b = np.maximum(hi - [img.shape[1], img.shape[0]], 0)
    if l or t or r or b:
        img = _pad(img, (t, b, l, r), side, pad)
        quad = quad + [l, t]
    # output pixel (row i, column j) samples quad[0] + u (quad[3] - quad[0]) + v (quad[1] - quad[0]),
    # u = (j + 0.5) / out_size, v = (i + 0.5) / out_size: an affine map from output to source pixels
    across, down = (quad[3] - quad[0]) / out_size, (quad[1] - quad[0]) / out_size
    to_source = np.column_stack([across, down, quad[0] + 0.5 * (across + down)])
    return cv2.warpAffine(img, to_source, (out_size, out_size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)


def crop_head(image, box: Box, out_size: int, scale: float = 1.0, pad="blur") -> np.ndarray:
    """EG3D-framed (out_size, out_size, 3) float32 head crop in [0, 1] of the face in ``box``."""
    rgb = to_float_rgb(image)
    return warp_quad(rgb, head_quad(landmarks(to_uint8(rgb), box), scale), out_size, pad)
