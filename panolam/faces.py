"""Faces in photos and renders, offline, with dlib: detection, head crops for inference, identity
similarity (CSIM) and head pose (APD) for evaluation.

Needs ``dlib`` (the ``dlib-bin`` wheel) and the model files of ``face-recognition-models`` (dlib's
HOG detector is built in; the MMOD CNN detector, the 5- and 68-point shape predictors and the
face-recognition ResNet are read from that package). Images are numpy arrays (H, W, 3) RGB, uint8
or float in [0, 1]; points and boxes are in pixels of the image they came from, (x, y), pixel (row
i, column j) centred at (j, i).

Detection: dlib's HOG frontal detector (upsample 1, then 2 when nothing is found), each candidate
confirmed by the MMOD CNN detector on a crop around it (HOG alone fires on e.g. the mission patch
of ``skimage.data.astronaut``). Found: upright, roughly frontal faces (|yaw| up to ~45 deg, in-plane
roll up to ~30 deg) of at least ~20 px.

Head crop: the training images are EG3D-style FFHQ crops (camera radius 2.7, FOV 18.84 deg). EG3D's
``crop_images_in_the_wild.py`` fits Deep3DFaceRecon's 5-point mean face (eye centres, nose tip,
mouth corners; eye-centre distance 0.6213 units, eyes to mouth 0.6714 units, template origin 0.2900
units below the eyes), maps 1 unit to 300 px of a 1024 px image and keeps the central 700 px. So
the crop is 700/300 = 2.333 units wide, centred 0.432 eye-to-mouth lengths below the eye midpoint:
in a 512 px crop the eyes are 136 px apart at y = 192 px and the mouth is at y = 340 px. We build
the crop as FFHQ does (a square oriented by the eye-to-eye and eye-to-mouth vectors of dlib's 68
landmarks, sized by the larger of the two, which is robust to yaw and pitch) with those EG3D sizes.
"""
from __future__ import annotations

import functools
import io
import math
import os
import warnings
from dataclasses import dataclass
from importlib.util import find_spec
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError
from scipy.spatial.transform import Rotation

from datagen.cameras import FOV_MEAN, fov_to_focal, intrinsics, pixel_intrinsics
from datagen.errors import UserError
from datagen.shards import to_uint8

# EG3D framing of the 5-point mean face (module docstring), in template units.
CROP_SIDE = 700 / 300
EYE_DISTANCE = 0.62129
EYE_TO_MOUTH = 0.67135
CENTRE_BELOW_EYES = 0.29004 / EYE_TO_MOUTH  # fraction of eye-to-mouth
DEFAULT_FOCAL = float(fov_to_focal(FOV_MEAN))  # normalized focal of the datasets' mean camera
MAX_PHOTO_PIXELS = 100_000_000  # photos above this are refused before they are decoded
WORK_MAX_SIDE = 4096  # px; larger photos are downscaled to this long side as they are decoded
PHOTO_STRIP_ROWS = 256  # rows (of the working image) OpenImageIO decodes at a time
VERIFY_FACE_PX = 90  # a HOG candidate is confirmed by MMOD on a crop 1.6x its width, at this face width

# Generic adult face, mm: x toward the image right of a frontal face, y down, z away from the
# camera (OpenCV camera axes for a frontal pose); keys are dlib 68-point indices. Eye centres,
# nose tip and mouth corners follow the Deep3DFaceRecon mean face above (0.1 unit = 10 mm); the
# other points are generic anthropometric estimates. Jaw contour, brows and lips (which slide or
# move with expression) are left out, except the chin.
GENERIC_FACE = {
    8: (0.0, 85.0, -15.0),                                   # chin
    27: (0.0, -31.0, -26.0),                                 # top of the nose bridge
    30: (0.0, 4.6, -55.2),                                   # nose tip
    31: (-14.0, 10.0, -36.0), 33: (0.0, 14.0, -40.0), 35: (14.0, 10.0, -36.0),  # nostrils
    36: (-45.0, -29.0, -6.0), 39: (-17.0, -29.0, -20.0),     # eye corners (outer, inner)
    42: (17.0, -29.0, -20.0), 45: (45.0, -29.0, -6.0),
    48: (-25.0, 38.1, -22.3), 54: (25.0, 38.1, -22.3),       # mouth corners
}


class FaceError(UserError, ValueError):
    """No usable face (or an unreadable image); the message is one line for the user."""


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


# ---------------------------------------------------------------------------------------- models

def _dlib():
    try:
        import dlib
    except ImportError:
        raise ImportError("panolam.faces needs dlib: pip install dlib-bin (prebuilt wheels of dlib)") from None
    return dlib


def models_dir() -> Path:
    """Folder of dlib's model files from the face-recognition-models package."""
    spec = find_spec("face_recognition_models")  # not imported: its __init__ needs pkg_resources
    if spec is None or not spec.submodule_search_locations:
        raise ImportError("dlib's face models are missing: pip install face-recognition-models")
    return Path(next(iter(spec.submodule_search_locations))) / "models"


def _model_file(name: str) -> str:
    path = models_dir() / name
    if not path.is_file():
        raise ImportError(f"{path} is missing: pip install --force-reinstall face-recognition-models")
    return str(path)


def check_dlib() -> None:
    """Raise ImportError (one line, with the pip command) unless dlib and its model files are installed."""
    _dlib()
    for name in ("mmod_human_face_detector.dat", "shape_predictor_5_face_landmarks.dat",
                 "shape_predictor_68_face_landmarks.dat", "dlib_face_recognition_resnet_model_v1.dat"):
        _model_file(name)


@functools.lru_cache(maxsize=None)
def hog_detector():
    """dlib's HOG frontal face detector (built in; one per process)."""
    return _dlib().get_frontal_face_detector()


@functools.lru_cache(maxsize=None)
def cnn_detector():
    """dlib's MMOD CNN face detector (``mmod_human_face_detector.dat``; one per process). Its window
    finds faces of about 80 px and larger; detections have confidence above 0."""
    return _dlib().cnn_face_detection_model_v1(_model_file("mmod_human_face_detector.dat"))


@functools.lru_cache(maxsize=None)
def _predictor(points: int):
    return _dlib().shape_predictor(_model_file(f"shape_predictor_{points}_face_landmarks.dat"))


@functools.lru_cache(maxsize=None)
def _resnet():
    return _dlib().face_recognition_model_v1(_model_file("dlib_face_recognition_resnet_model_v1.dat"))


# ---------------------------------------------------------------------------------------- images

def _to_float_rgb(image) -> np.ndarray:
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


def _rgb_u8(image) -> np.ndarray:
    a = np.asarray(image)
    if a.dtype == np.uint8 and a.ndim == 3 and a.shape[2] == 3:
        return np.ascontiguousarray(a)
    return to_uint8(_to_float_rgb(a))


def _resize(u8: np.ndarray, k: float) -> np.ndarray:
    h, w = u8.shape[:2]
    size = (max(1, round(w * k)), max(1, round(h * k)))
    return np.asarray(Image.fromarray(u8).resize(size, Image.Resampling.LANCZOS))


def load_image(src) -> tuple[np.ndarray, str]:
    """(H, W, 3) float32 RGB in [0, 1] and a name for messages, from a path, encoded bytes or an
    array (see :func:`read_photo`)."""
    photo = read_photo(src)
    return photo.rgb, photo.name


@dataclass(frozen=True)
class Photo:
    """A decoded photo: rgb (H, W, 3) float32 in [0, 1], downscaled by ``scale`` (<= 1) from the
    file's ``size`` (W, H) px when that is larger than WORK_MAX_SIDE."""

    rgb: np.ndarray
    name: str
    size: tuple[int, int]
    scale: float


def read_photo(src) -> Photo:
    """Decode a photo from a path, encoded bytes or an array.

    Pillow reads JPEG, PNG, WebP, TIFF, ... (paths and bytes); files in formats Pillow lacks (EXR,
    HDR, DPX, JPEG XL, ...) are read by OpenImageIO (paths only: its Python bindings read no
    in-memory files), linear float data encoded to sRGB. Applies the EXIF orientation; composites
    transparency on white; keeps 16-bit gray precision (16-bit RGB files are read at 8 bits by
    Pillow). A photo above MAX_PHOTO_PIXELS is refused from its header, before decoding; one whose
    long side exceeds WORK_MAX_SIDE is downscaled (area averaging) as it is decoded (a JPEG at 1/2,
    1/4 or 1/8 scale by its decoder), so memory stays bounded by the working size.
    """
    if isinstance(src, np.ndarray):
        h, w = src.shape[:2] if src.ndim >= 2 else (0, 0)
        name = f"array {src.shape}"
        return _photo(_to_float_rgb(_fit(np.asarray(src), name)), name, (w, h))
    name = "image bytes" if isinstance(src, (bytes, bytearray)) else str(src)
    try:
        with warnings.catch_warnings():  # the pixel limit below replaces Pillow's bomb warning
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im = Image.open(io.BytesIO(src) if isinstance(src, (bytes, bytearray)) else os.fspath(src))
    except UnidentifiedImageError:
        if isinstance(src, (bytes, bytearray)) or Path(src).suffix.lower() not in _openimageio_only():
            raise FaceError(f"cannot read image {name}: not an image format Pillow can decode") from None
        return _read_with_openimageio(src, name)
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
        raise FaceError(f"cannot read image {name}: {e}") from None
    try:
        with im:
            size = im.size
            _check_pixels(size, name)
            k = _reduction(size)
            if k > 1 and im.format == "JPEG":  # decode at a reduced scale: the full image is never in memory
                im.draft(im.mode, (-(-size[0] // k), -(-size[1] // k)))
            im = ImageOps.exif_transpose(im)
            im.load()
            if im.mode.startswith("I") or im.mode == "F":
                pixels = np.asarray(im)
            else:
                has_alpha = "A" in im.getbands() or "transparency" in im.info
                pixels = np.asarray(im.convert("RGBA" if has_alpha else "RGB"))
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
        raise FaceError(f"cannot read image {name}: {e}") from None
    return _photo(_to_float_rgb(_fit(pixels, name)), name, size)


def _photo(rgb: np.ndarray, name: str, size: tuple[int, int]) -> Photo:
    return Photo(rgb, name, size, rgb.shape[1] / size[0] if size[0] else 1.0)


def _check_pixels(size: tuple[int, int], name: str) -> None:
    if size[0] * size[1] > MAX_PHOTO_PIXELS:
        raise FaceError(f"{name}: {size[0]}x{size[1]} px is {size[0] * size[1] / 1e6:.0f} megapixels, above the "
                        f"limit of {MAX_PHOTO_PIXELS / 1e6:.0f}; downscale it first (a head crop needs far fewer)")


def _reduction(size: tuple[int, int]) -> int:
    """The integer factor that brings the long side to WORK_MAX_SIDE or less."""
    return max(1, -(-max(size) // WORK_MAX_SIDE))


def _fit(pixels: np.ndarray, name: str) -> np.ndarray:
    """``pixels`` (H, W[, C]) area-averaged to a long side of at most WORK_MAX_SIDE."""
    h, w = pixels.shape[:2]
    if max(h, w) <= WORK_MAX_SIDE:
        return pixels
    k = WORK_MAX_SIDE / max(h, w)
    if pixels.dtype not in (np.uint8, np.uint16, np.float32):
        pixels = pixels.astype(np.float32) / (65535 if pixels.dtype.kind in "ui" else 1)
    return cv2.resize(pixels, (max(1, round(w * k)), max(1, round(h * k))), interpolation=cv2.INTER_AREA)


def _box_reduce(a: np.ndarray, k: int) -> np.ndarray:
    """(H, W, C) -> (ceil(H / k), W // k, C): means of k x k blocks (the last block row may be shorter)."""
    if k == 1:
        return a
    w = a.shape[1] // k * k
    return np.stack([a[i:i + k, :w].reshape(-1, w // k, k, a.shape[2]).mean(axis=(0, 2)) for i in range(0, len(a), k)])


@functools.lru_cache(maxsize=None)
def _openimageio_only() -> frozenset:
    """File suffixes of the formats OpenImageIO reads and Pillow does not (.exr, .hdr, .dpx, ...):
    a file Pillow cannot read goes to OpenImageIO only when its name says it is one of them."""
    import OpenImageIO as oiio
    suffixes = {"." + ext for fmt in oiio.get_string_attribute("extension_list").split(";")
                for ext in fmt.partition(":")[2].split(",") if ext}
    return frozenset(suffixes - set(Image.registered_extensions()))


def _read_with_openimageio(path, name: str) -> Photo:
    """A photo in a format Pillow lacks, through OpenImageIO, read in strips of rows that are
    box-averaged to the working size as they come (module docstring of read_photo)."""
    import OpenImageIO as oiio
    source = oiio.ImageInput.open(os.fspath(path))
    if source is None:
        message = (oiio.geterror() or "unknown format").splitlines()[0]
        raise FaceError(f"cannot read image {name}: not an image format Pillow or OpenImageIO can decode "
                        f"({message})")
    try:
        spec = source.spec()
        size = (spec.width, spec.height)
        _check_pixels(size, name)
        names = [c.upper() for c in spec.channelnames]
        wanted = [names.index(c) for c in ("R", "G", "B", "A") if c in names] or list(range(min(3, spec.nchannels)))
        k = _reduction(size)
        rows = []
        for top in range(0, spec.height, k * PHOTO_STRIP_ROWS):
            strip = source.read_scanlines(0, 0, top, min(spec.height, top + k * PHOTO_STRIP_ROWS), 0, 0,
                                          spec.nchannels, "float")
            if strip is None:
                raise FaceError(f"cannot read image {name}: {oiio.geterror().splitlines()[0]}")
            strip = np.asarray(strip, np.float32).reshape(-1, spec.width, spec.nchannels)[..., wanted]
            rows.append(_box_reduce(strip, k))
    finally:
        source.close()
    pixels = np.concatenate(rows)
    linear = spec.format.basetype in (oiio.HALF, oiio.FLOAT, oiio.DOUBLE) and \
        "srgb" not in spec.get_string_attribute("oiio:ColorSpace").lower()
    if linear:  # scene-linear (EXR, HDR): the sRGB encoding photos and training images carry
        c = np.clip(np.nan_to_num(pixels[..., :3]), 0, 1)
        pixels[..., :3] = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)
    return _photo(_to_float_rgb(pixels), name, size)


# ------------------------------------------------------------------------------------- detection

def _dlib_rect(box: Box):
    return _dlib().rectangle(round(box.left), round(box.top), round(box.right) - 1, round(box.bottom) - 1)


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
    u8 = _rgb_u8(image)
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
    shape = _predictor(points)(_rgb_u8(image), _dlib_rect(box))
    return np.array([(p.x, p.y) for p in shape.parts()], dtype=np.float64)


# ------------------------------------------------------------------------------------------ crop

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
    rgb = _to_float_rgb(image)
    return warp_quad(rgb, head_quad(landmarks(to_uint8(rgb), box), scale), out_size, pad)


def prepare_photo(src, out_size: int = 512, pick: str = "single", scale: float = 1.0, pad="blur",
                  max_side: int = 1024) -> tuple[np.ndarray, dict]:
    """A photo (path, encoded bytes or array) -> its EG3D-framed head crop, (out_size, out_size, 3)
    float32 in [0, 1], and an info dict (source, size (W, H) of the file, scale of the working image
    (see read_photo), n_faces, box and quad in working px, face_px = eye distance in the file's px,
    upsampled = the crop enlarges the source).

    Raises FaceError for an unreadable file, no face, or several faces unless ``pick='largest'``.
    """
    if pick not in ("single", "largest"):
        raise ValueError(f"pick must be 'single' or 'largest', got {pick!r}")
    photo = read_photo(src)
    rgb, name = photo.rgb, photo.name
    h, w = rgb.shape[:2]
    u8 = to_uint8(rgb)
    faces = detect_faces(u8, max_side=max_side)
    if not faces:
        raise FaceError(f"no face found in {name} ({w}x{h} px): a face must be upright, roughly frontal "
                        f"and at least ~20 px wide")
    if len(faces) > 1 and pick == "single":
        raise FaceError(f"{len(faces)} faces found in {name}; take the largest with --pick largest "
                        f"(pick='largest' in Python)")
    lm = landmarks(u8, faces[0])
    quad = head_quad(lm, scale)
    side = float(np.hypot(*(quad[3] - quad[0])))
    info = dict(source=name, size=photo.size, scale=photo.scale, n_faces=len(faces), box=faces[0], quad=quad,
                face_px=float(np.hypot(*(lm[42:48].mean(0) - lm[36:42].mean(0)))) / photo.scale,
                upsampled=side < out_size)
    return warp_quad(rgb, quad, out_size, pad), info


# ------------------------------------------------------------------------------ identity, pose

class FaceEmbedder:
    """dlib's face-recognition ResNet (128-d, 5-point aligned 150 px chips) on the largest face.

    This is dlib's network, NOT the ArcFace (insightface) network the paper's CSIM uses: values
    are comparable between our own runs only, not with published CSIM numbers.
    """

    def embed(self, image, box: Box | None = None) -> np.ndarray | None:
        """128-d descriptor of the face in ``box`` (default: the largest face found), or None when no face is found."""
        u8 = _rgb_u8(image)
        if box is None:
            faces = detect_faces(u8)
            if not faces:
                return None
            box = faces[0]
        shape = _predictor(5)(u8, _dlib_rect(box))
        return np.asarray(_resnet().compute_face_descriptor(u8, shape), dtype=np.float64)


@functools.lru_cache(maxsize=None)
def _embedder() -> FaceEmbedder:
    return FaceEmbedder()


def csim(img_a, img_b, embedder: FaceEmbedder | None = None, box_from_b: bool = False) -> float:
    """Identity similarity: cosine of dlib ResNet embeddings (not ArcFace, see FaceEmbedder), in
    [-1, 1]; nan when either image has no face (the caller counts and reports those skipped).

    ``box_from_b``: the face box found in ``img_b`` locates the face in ``img_a`` too (landmarks
    are still fitted in each image), for a render and its target seen from the same camera: a
    blurry render the detector misses is still compared where the target's face is."""
    embedder = embedder or _embedder()
    if box_from_b:
        faces = detect_faces(img_b)
        if not faces:
            return math.nan
        a, b = embedder.embed(img_a, faces[0]), embedder.embed(img_b, faces[0])
    else:
        a, b = embedder.embed(img_a), embedder.embed(img_b)
    if a is None or b is None:
        return math.nan
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


def csim_between_subjects(images, embedder: FaceEmbedder | None = None) -> tuple[float, int]:
    """Mean CSIM over all pairs of different images, each at its own largest face, and how many
    faces were found; (nan, n) with fewer than two. Over targets of different subjects this is
    what an identity-blind prediction scores: a reconstruction shows identity only above it."""
    embedder = embedder or _embedder()
    found = [e / np.linalg.norm(e) for e in map(embedder.embed, images) if e is not None]
    if len(found) < 2:
        return math.nan, len(found)
    sim = np.stack(found) @ np.stack(found).T
    return float(sim[~np.eye(len(found), dtype=bool)].mean()), len(found)


@dataclass(frozen=True)
class HeadPose:
    """A face's pose in the camera: degrees; yaw > 0: the face turns toward the image right; pitch > 0:
    it looks up; roll > 0: it tilts clockwise in the image. Rotation = Ry(-yaw) Rx(-pitch) Rz(roll)
    in OpenCV camera axes (GENERIC_FACE's axes for a frontal face). translation_mm: GENERIC_FACE's
    origin in camera coordinates, mm."""

    yaw: float
    pitch: float
    roll: float
    translation_mm: tuple

    @property
    def angles(self) -> tuple[float, float, float]:
        return self.yaw, self.pitch, self.roll


def pose_from_landmarks(lm68: np.ndarray, width: int, height: int, focal: float = DEFAULT_FOCAL) -> HeadPose:
    """The head pose of 68 landmarks: OpenCV's perspective PnP of GENERIC_FACE (Levenberg-Marquardt
    on the reprojection error from a frontal start) through the camera of :mod:`datagen.cameras`:
    normalized focal ``focal`` (EG3D's convention, the one every render uses), principal point at
    the image centre."""
    lm68 = np.asarray(lm68, np.float64)
    model = np.array(list(GENERIC_FACE.values()), np.float64)
    obs = lm68[list(GENERIC_FACE)] + 0.5  # pixel centres at +0.5, as the cameras' K
    K = pixel_intrinsics(intrinsics(focal), width, height)
    # start frontal, at the distance where the outer eye corners are as far apart as observed: a
    # free start can land on the mirror solution (the face upside down, roll 180 deg)
    z0 = K[0, 0] * (GENERIC_FACE[45][0] - GENERIC_FACE[36][0]) / max(np.hypot(*(lm68[45] - lm68[36])), 1e-6)
    centre = obs.mean(axis=0)
    tvec = np.array([(centre[0] - K[0, 2]) / K[0, 0] * z0, (centre[1] - K[1, 2]) / K[1, 1] * z0, z0])
    found, rvec, tvec = cv2.solvePnP(model, obs, K, None, np.zeros(3), tvec, useExtrinsicGuess=True,
                                     flags=cv2.SOLVEPNP_ITERATIVE)
    if not found:
        raise FaceError(f"no head pose fits these landmarks ({width}x{height} px)")
    y_angle, x_angle, z_angle = Rotation.from_rotvec(rvec.ravel()).as_euler("YXZ", degrees=True)
    return HeadPose(-y_angle, -x_angle, z_angle, tuple(tvec.ravel()))


def head_pose(image, focal: float = DEFAULT_FOCAL) -> HeadPose:
    """The head pose of the largest face (see pose_from_landmarks); FaceError when there is none.
    Landmark PnP with a generic face, not the paper's 3DMM-based estimator."""
    u8 = _rgb_u8(image)
    faces = detect_faces(u8)
    if not faces:
        raise FaceError(f"no face found ({u8.shape[1]}x{u8.shape[0]} px)")
    return pose_from_landmarks(landmarks(u8, faces[0]), u8.shape[1], u8.shape[0], focal)


def apd(img_a, img_b, focal: float = DEFAULT_FOCAL) -> float:
    """Average pose distance: mean |difference| of yaw, pitch and roll in degrees between the faces
    of two images seen with normalized focal ``focal``; nan when either has no face (the caller
    reports how many were skipped). Ours is landmark PnP with a generic face; the paper's APD uses
    3DMM (Deep3DFaceRecon) angles."""
    try:
        a, b = head_pose(img_a, focal).angles, head_pose(img_b, focal).angles
    except FaceError:
        return math.nan
    return float(np.mean([abs((x - y + 180) % 360 - 180) for x, y in zip(a, b)]))
