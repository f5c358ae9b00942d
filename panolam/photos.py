"""Photos for ``panolam infer``: decoding (any size, Pillow or OpenImageIO) and the EG3D-framed head
crop the model takes (face detection and crops: :mod:`datagen.faces`)."""
from __future__ import annotations

import functools
import io
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from datagen.errors import optional_import
from datagen.faces import FaceError, detect_faces, head_quad, landmarks, to_float_rgb, warp_quad
from datagen.dataset.shards import to_uint8

MAX_PHOTO_PIXELS = 100_000_000  # photos above this are refused before they are decoded
WORK_MAX_SIDE = 4096  # px; larger photos are downscaled to this long side as they are decoded
PHOTO_STRIP_ROWS = 256  # rows (of the working image) OpenImageIO decodes at a time


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
        return _photo(to_float_rgb(_fit(np.asarray(src), name)), name, (w, h))
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
    return _photo(to_float_rgb(_fit(pixels, name)), name, size)


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
    oiio = optional_import("OpenImageIO", "photos", "a photo Pillow cannot decode")
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
    return _photo(to_float_rgb(pixels), name, size)



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
