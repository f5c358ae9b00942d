"""Automatic pre-flags: cheap, explainable per-subject scores so reviewers see the worst subjects first.

Each detector gives every subject a score in [0, 1] (0.5 and above means flagged) and a short
explanation with the number it measured. Scores only order the review queue; nothing is deleted.

Detectors
    janus        a face on the back of the head: the back view (yaw ~180) is compared with the front
                 view (yaw ~0, as is and mirrored) on edge structure and on the colour layout of the face
                 region, and checked for a nose-like depth bump where the front view has its nose; the
                 mean of the three robust z-scores against the dataset.
                 Not applicable (score 0) without a back view, e.g. for the 'frontal' protocol.
    floaters     parts of the silhouette detached from the head (connected components of alpha > 127):
                 area share of the components other than the largest, worst view.
    holes        see-through holes in the silhouette (filled mask minus mask), and craters: round
                 depressions of the depth map in the upper head (determinant-of-Hessian blob response of
                 depth), compared with the same viewing direction over the dataset.
    washed_out   low colour saturation and lifted dark tones inside the mask, relative to the dataset.
    blur         soft silhouette edges: the colour image's gradient energy across the silhouette compared
                 with a sharp cut-out composed from the same view's mask, relative to the dataset
                 (interior detail, Laplacian over grey variance, is reported alongside).
    empty        views whose mask is (almost) empty; subjects that do not decode.
    implausible  mask area or median depth far from the dataset's distribution (robust z-score).
    duplicate    near-duplicates of another subject: cosine similarity of small grey thumbnails of the
                 frontal view (cropped to the head, dataset mean removed), blocked so it scales.

How it runs: one pass decodes what the detectors need (all masks; RGB and depth of up to 8 views
around the equator) and stores a small feature record per subject; dataset statistics (median and
MAD) are then computed from those records and every subject is scored, without decoding again.
Image features are computed at a working resolution of about 64 px (larger images are averaged
down by an integer factor), so thresholds do not depend on the image size.

Only what reviewers may see is read: ``index.json`` and the shard tars (plus sidecars to know which
shards are complete). The hidden ``truth/`` folder is never opened.

    from labeling_tool.preflags import score_dataset, write_preflags, read_preflags
    report = score_dataset("/data/heads", progress=True, workers=2)
    write_preflags("/data/heads", report)          # -> /data/heads/preflags.json (atomic)
"""
from __future__ import annotations

import itertools
import json
import math
import multiprocessing as mp
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

from datagen.errors import DatasetError
from datagen.files import atomic_write, read_json
from datagen.shards import SubjectSample, index_sha256, decode_exr, decode_png, iter_tar_samples, read_index, view_name

FORMAT = "panolam-preflags/1"
PREFLAGS_NAME = "preflags.json"
FLAG_AT = 0.5                # a detector flags a subject when its score is at least this
WORK_RES = 64                # image features are computed at about this size
EQUATOR_STEP = 45.0          # the views used for colour/depth features: one per 45 degrees of yaw
EQUATOR_TOL = 22.5           # ... within this many degrees of the target yaw
BACK_TOL = 20.0              # a janus back view: |yaw - 180| and |pitch| within this
DETECTOR_NAMES = ("janus", "floaters", "holes", "washed_out", "blur", "empty", "implausible", "duplicate")


@dataclass(frozen=True)
class Params:
    """Thresholds and scales. A detector's measure m maps to a score by a ramp: 0.5 * m / t below the
    threshold t, then linearly from 0.5 at t to 1.0 at the saturation s. Thresholds were chosen on a
    procedural dataset made with one seed (see benchmarks/preflags_quality.py) and are evaluated on
    another seed."""

    janus_z: float = 1.5              # mean of the edge, face-colour and nose-bump robust z-scores
    janus_z_sat: float = 4.0
    floater_share: float = 0.002      # detached area / silhouette area in the worst view
    floater_share_sat: float = 0.02
    floater_min_px: float = 3.0       # at 64 px; smaller specks are ignored (scaled with image area)
    silhouette_hole_share: float = 0.002
    silhouette_hole_share_sat: float = 0.02
    crater_z: float = 4.5             # crater blob response, robust z against views from the same
                                      # direction (scale: MAD or the 90th-percentile spread)
    crater_z_sat: float = 10.0
    crater_sigma: float = 2.0         # blob scale in px at 64 px
    crater_erode: float = 4.0         # ignore this many px (at 64 px) inside the silhouette edge
    crater_upper: float = 0.6         # search the top 60% of the silhouette (the face/neck have natural concavities)
    crater_mad_floor: float = 0.001   # world units
    washed_z: float = 2.0             # mean of -z(log saturation) and z(10th percentile grey)
    washed_z_sat: float = 5.0
    blur_z: float = 6.0               # -z of the silhouette edge sharpness (log gradient-energy ratio)
    blur_z_sat: float = 15.0
    blur_edge_floor: float = 0.02     # scale floor of that log ratio
    empty_area: float = 0.0005        # a view is empty below this mask fraction of the image
    implausible_z: float = 6.0        # |z| of log mask area or median depth
    implausible_z_sat: float = 12.0
    duplicate_dissim: float = 0.01    # 1 - cosine similarity; 0.5 at this, 1.0 at identical
    duplicate_block: int = 2048       # rows/columns per block of the similarity computation
    thumb: int = 16                   # thumbnail side in px


DEFAULT_PARAMS = Params()


def detector_table(p: Params = DEFAULT_PARAMS) -> dict:
    """{name: {"threshold", "description", "measure"}}: what goes into the report's header."""
    return {
        "janus": {"threshold": FLAG_AT, "measure_threshold": p.janus_z,
                  "description": "a face on the back of the head: back view vs front view (edge correlation and "
                                 "face-region colour correlation, as is and mirrored) and a nose-like depth bump "
                                 "where the front has its nose; mean of the three robust z-scores against the "
                                 "dataset; n/a without a back view"},
        "floaters": {"threshold": FLAG_AT, "measure_threshold": p.floater_share,
                     "description": "silhouette parts detached from the head (alpha > 127 components other than "
                                    "the largest), area share of the silhouette in the worst view"},
        "holes": {"threshold": FLAG_AT, "measure_threshold": {"crater_z": p.crater_z,
                                                              "silhouette_share": p.silhouette_hole_share},
                  "description": "see-through holes in the silhouette, or a crater: a round depression of the "
                                 "depth map in the upper head, robust z against the same viewing direction"},
        "washed_out": {"threshold": FLAG_AT, "measure_threshold": p.washed_z,
                       "description": "low saturation and lifted dark tones inside the mask: mean of -z(log "
                                      "saturation) and z(10th percentile grey) against the dataset"},
        "blur": {"threshold": FLAG_AT, "measure_threshold": p.blur_z,
                 "description": "soft silhouette edges: -z (against the dataset) of the log ratio of gradient "
                                "energy across the silhouette to that of a sharp cut-out from the same mask"},
        "empty": {"threshold": FLAG_AT, "measure_threshold": p.empty_area,
                  "description": "views with (almost) no mask, or a subject that does not decode"},
        "implausible": {"threshold": FLAG_AT, "measure_threshold": p.implausible_z,
                        "description": "mean mask area or median depth far from the dataset (robust |z|)"},
        "duplicate": {"threshold": FLAG_AT, "measure_threshold": 1.0 - p.duplicate_dissim,
                      "description": "near-duplicate of another subject: cosine similarity of 16x16 grey "
                                     "thumbnails of the frontal view (head crop, dataset mean removed)"},
    }


# ----------------------------------------------------------------------------------------------
# Small helpers

def _ramp(m: float, t: float, s: float) -> float:
    """Measure -> score: 0 at m <= 0, 0.5 at the threshold t, 1 at the saturation s."""
    if m is None or not math.isfinite(m) or m <= 0:
        return 0.0
    if m < t:
        return 0.5 * m / t
    return float(min(1.0, 0.5 + 0.5 * (m - t) / max(s - t, 1e-12)))


def _robust(values, floor: float) -> tuple[float, float]:
    """(median, 1.4826 * MAD) of the finite values, the scale at least ``floor``."""
    x = np.asarray([v for v in values if v is not None], dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return 0.0, floor
    med = float(np.median(x))
    return med, max(float(1.4826 * np.median(np.abs(x - med))), floor)


def _robust_tail(values, floor: float) -> tuple[float, float]:
    """(median, scale) where the scale is the larger of 1.4826 * MAD and the spread up to the 90th
    percentile (as a normal's sigma): a feature that a minority of subjects has naturally (e.g. a cap's
    brim seen from the front) widens the scale instead of looking like an outlier."""
    med, scale = _robust(values, floor)
    x = np.asarray(values, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size:
        scale = max(scale, float(np.quantile(x, 0.9) - med) / 1.2816)
    return med, scale


def _wrap(deg):
    """Angle difference folded into [-180, 180)."""
    return (np.asarray(deg, dtype=np.float64) + 180.0) % 360.0 - 180.0


def _nearest_fill(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Outside the mask, the value of the nearest pixel inside (so filters see no silhouette step)."""
    if mask.all() or not mask.any():
        return x
    idx = ndi.distance_transform_edt(~mask, return_distances=False, return_indices=True)
    return x[idx[0], idx[1]]


def _bbox(mask: np.ndarray):
    rows = np.nonzero(mask.any(1))[0]
    cols = np.nonzero(mask.any(0))[0]
    return rows[0], rows[-1], cols[0], cols[-1]


def equator_views(views: list[dict]) -> dict:
    """{target yaw: view index}: per 45-degree yaw target the closest view near the equator."""
    yaw = np.array([v["yaw_deg"] for v in views], dtype=np.float64)
    pitch = np.array([v["pitch_deg"] for v in views], dtype=np.float64)
    chosen = {}
    for t in np.arange(0.0, 360.0, EQUATOR_STEP):
        dy = np.abs(_wrap(yaw - t))
        cost = np.where(dy <= EQUATOR_TOL, dy + np.abs(pitch), np.inf)
        if np.isfinite(cost).any():
            i = int(np.argmin(cost))
            if i not in chosen.values():
                chosen[float(t)] = i
    return chosen


# ----------------------------------------------------------------------------------------------
# Reading only the members we need

class _NotPlainUstar(Exception):
    pass


def _subject_groups(path: Path, wanted):
    """Yield (key, {field: bytes}) per subject of a shard, reading only fields where wanted(field, fields).

    A small reader for the plain USTAR tars the dataset writer makes (checksums verified); anything
    else (pax or GNU headers) falls back to the tarfile module."""
    try:
        yield from _subject_groups_fast(path, wanted)
    except _NotPlainUstar:
        yield from iter_tar_samples(path, wanted)


def _subject_groups_fast(path: Path, wanted):
    current, fields, started = None, {}, False
    with open(path, "rb") as f:
        while True:
            head = f.read(512)
            if len(head) < 512:
                raise DatasetError(f"{path}: corrupt or truncated shard (short header)")
            if head == b"\0" * 512:
                break
            chk = head[148:156].strip(b"\0 ")
            try:
                expected = int(chk, 8)
            except ValueError:
                raise DatasetError(f"{path}: corrupt shard (bad header checksum field)") from None
            if expected != sum(head[:148]) + 256 + sum(head[156:]):
                raise DatasetError(f"{path}: corrupt shard (header checksum mismatch)")
            kind = head[156:157]
            if head[124] & 0x80 or kind not in (b"0", b"\0", b"5"):
                if not started:
                    raise _NotPlainUstar()
                raise DatasetError(f"{path}: unexpected member type {kind!r} inside the shard")
            started = True
            name = head[:100].split(b"\0", 1)[0].decode()
            prefix = head[345:500].split(b"\0", 1)[0].decode() if head[257:262] == b"ustar" else ""
            if prefix:
                name = f"{prefix}/{name}"
            size = int(head[124:136].strip(b"\0 ") or b"0", 8)
            padded = size + (-size % 512)
            if kind == b"5":
                f.seek(padded, 1)
                continue
            key, _, field = name.partition(".")
            if key != current and current is not None:
                yield current, fields
                fields = {}
            current = key
            if wanted(field, fields):
                data = f.read(size)
                if len(data) < size:
                    raise DatasetError(f"{path}: corrupt or truncated shard (member {name})")
                fields[field] = data
                f.seek(padded - size, 1)
            else:
                f.seek(padded, 1)
    if current is not None:
        yield current, fields


KEEP = "__keep__"  # per-subject set of view indices whose colour and depth are read


def _wanted_field(field: str, fields: dict) -> bool:
    """Which members to read: metadata, every mask, and colour/depth of the equator views only (known
    once the subject's metadata, its first member, has been read; otherwise everything is read)."""
    if field == "json" or field.endswith(".mask.png"):
        return True
    if not (field.endswith(".png") or field.endswith(".depth.exr")):
        return False
    if KEEP not in fields:
        try:
            fields[KEEP] = frozenset(equator_views(json.loads(fields["json"])["views"]).values())
        except (KeyError, ValueError, TypeError):
            fields[KEEP] = None
    keep = fields[KEEP]
    if keep is None:
        return True
    try:
        return int(field[1:].split(".", 1)[0]) in keep
    except ValueError:
        return True


def _decode_needed(key: str, fields: dict, where: str = "") -> SubjectSample:
    """Decode the metadata, all masks, and RGB + depth of the equator views only (others stay None)."""
    try:
        meta = json.loads(fields["json"])
        views = meta["views"]
        n = len(views)
        keep = set(equator_views(views).values())
        alpha = [decode_png(fields[f"{view_name(i)}.mask.png"]) for i in range(n)]
        rgb = [decode_png(fields[f"{view_name(i)}.png"]) if i in keep else None for i in range(n)]
        depth = [decode_exr(fields[f"{view_name(i)}.depth.exr"]) if i in keep else None for i in range(n)]
    except KeyError as e:
        raise DatasetError(f"{where}: subject {key} lacks field {e}") from None
    except DatasetError:
        raise
    except Exception as e:
        raise DatasetError(f"{where}: subject {key} does not decode ({type(e).__name__}: {e})") from None
    return SubjectSample(key, meta, rgb, alpha, depth, {})


# ----------------------------------------------------------------------------------------------
# Per-subject features (the one pass over the images)

def _downsample(rgb, alpha, depth, k: int):
    """Working-resolution float images: rgb (h,w,3) in [0,1], mask (h,w) bool, depth (h,w) (masked mean)."""
    a = alpha.astype(np.float32) / 255.0
    c = rgb.astype(np.float32) / 255.0
    d = np.nan_to_num(np.asarray(depth, dtype=np.float32))
    if k > 1:
        h, w = (a.shape[0] // k) * k, (a.shape[1] // k) * k
        def pool(x):
            x = x[:h, :w]
            return x.reshape(h // k, k, w // k, k, *x.shape[2:]).mean(axis=(1, 3))
        wsum = pool(a)
        d = pool(d * a) / np.maximum(wsum, 1e-6)
        c = pool(c)
        a = wsum
    return c, a > 0.5, d


def _components(mask: np.ndarray, min_px: float):
    """Detached share: area of components other than the largest (each >= min_px) over all mask area."""
    lab, n = ndi.label(mask, structure=np.ones((3, 3), bool))
    if n <= 1:
        return 0.0, 0, 0
    areas = np.bincount(lab.ravel())[1:]
    main = int(np.argmax(areas))
    others = np.delete(areas, main)
    others = others[others >= min_px]
    if others.size == 0:
        return 0.0, 0, 0
    return float(others.sum() / areas.sum()), int(others.size), int(others.max())


def _blob_response(depth: np.ndarray, sigma: float, sign: float) -> np.ndarray:
    """Scale-normalised determinant-of-Hessian blob strength of depth (depth units).

    sign=-1: depth maxima (depressions seen from the camera); sign=+1: depth minima (bumps)."""
    lxx = ndi.gaussian_filter(depth, sigma, order=(0, 2))
    lyy = ndi.gaussian_filter(depth, sigma, order=(2, 0))
    lxy = ndi.gaussian_filter(depth, sigma, order=(1, 1))
    det = (lxx * lyy - lxy * lxy) * sigma ** 4
    ok = (sign * lxx > 0) & (sign * lyy > 0) & (det > 0)
    return np.where(ok, np.sqrt(np.maximum(det, 0.0)), 0.0)


def _crater(depth, mask, s: float, p: Params):
    """Strongest round depression in the upper part of the silhouette: (response, (row, col))."""
    if mask.sum() < 16:
        return 0.0, (0, 0)
    dd = _nearest_fill(depth.astype(np.float64), mask)
    resp = _blob_response(dd, p.crater_sigma * s, -1.0)
    top, bot, _, _ = _bbox(mask)
    yrel = (np.arange(mask.shape[0])[:, None] - top) / max(bot - top, 1)
    region = ndi.binary_erosion(mask, iterations=max(1, int(round(p.crater_erode * s)))) & (yrel <= p.crater_upper)
    r = np.where(region, resp, 0.0)
    j = np.unravel_index(int(np.argmax(r)), r.shape)
    return float(r[j]), (int(j[0]), int(j[1]))


def _edge_ncc(a_grey, a_mask, b_grey, b_mask, s: float) -> float:
    """Best normalised correlation of Sobel edge magnitude inside both (eroded) masks over small shifts."""
    ga = np.hypot(ndi.sobel(a_grey, 0), ndi.sobel(a_grey, 1))
    gb = np.hypot(ndi.sobel(b_grey, 0), ndi.sobel(b_grey, 1))
    it = max(1, int(round(2 * s)))
    ia = ndi.binary_erosion(a_mask, iterations=it)
    ib = ndi.binary_erosion(b_mask, iterations=it)
    sh = max(1, int(round(3 * s)))
    best = -1.0
    for dy in range(-sh, sh + 1):
        for dx in range(-sh, sh + 1):
            gbs = np.roll(gb, (dy, dx), (0, 1))
            m = ia & np.roll(ib, (dy, dx), (0, 1))
            if m.sum() < 20:
                continue
            x = ga[m] - ga[m].mean()
            y = gbs[m] - gbs[m].mean()
            den = math.sqrt(float((x * x).sum() * (y * y).sum()))
            if den > 0:
                best = max(best, float((x * y).sum() / den))
    return best


def _central(mask, x0=0.3, x1=0.7, y0=0.3, y1=0.8):
    top, bot, left, right = _bbox(mask)
    yy, xx = np.mgrid[:mask.shape[0], :mask.shape[1]]
    return (mask & (yy >= top + y0 * (bot - top)) & (yy <= top + y1 * (bot - top))
            & (xx >= left + x0 * (right - left)) & (xx <= left + x1 * (right - left)))


def _colour_ncc(back_c, front_c, region, s: float) -> float:
    """Best normalised correlation of colour (channels centred separately) over the region, shifting the
    front view (and the region with it) by a few px."""
    sh = max(1, int(round(3 * s)))
    best = -1.0
    for dy in range(-sh, sh + 1):
        for dx in range(-sh, sh + 1):
            r = np.roll(region, (dy, dx), (0, 1))
            if r.sum() < 20:
                continue
            x = back_c[r]
            y = np.roll(front_c, (dy, dx), (0, 1))[r]
            x = x - x.mean(0)
            y = y - y.mean(0)
            den = math.sqrt(float((x * x).sum() * (y * y).sum()))
            if den > 0:
                best = max(best, float((x * y).sum() / den))
    return best


def _janus(front, back, s: float):
    """Face evidence in a back view: (edge similarity, colour similarity in the face region, nose-bump
    strength), each against the front view as is and mirrored."""
    (fc, fm, fd), (bc, bm, bd) = front, back
    fg, bg = fc.mean(-1), bc.mean(-1)
    sim = max(_edge_ncc(bg, bm, fg, fm, s), _edge_ncc(bg, bm, fg[:, ::-1], fm[:, ::-1], s))
    it2 = max(1, int(round(2 * s)))
    face = (_central(ndi.binary_erosion(fm, iterations=it2), 0.25, 0.75, 0.3, 0.85)
            & ndi.binary_erosion(bm, iterations=it2))
    colour = max(_colour_ncc(bc, fc, face, s), _colour_ncc(bc, fc[:, ::-1], face[:, ::-1], s)) if face.any() else -1.0
    it = max(1, int(round(3 * s)))
    f_inner = ndi.binary_erosion(fm, iterations=it)
    b_inner = ndi.binary_erosion(bm, iterations=it)
    if not f_inner.any() or not b_inner.any():
        return sim, colour, 0.0
    sig = 1.0 * s
    fb = np.where(_central(f_inner), _blob_response(_nearest_fill(fd.astype(np.float64), fm), sig, +1.0), 0.0)
    bb = np.where(b_inner, _blob_response(_nearest_fill(bd.astype(np.float64), bm), sig, +1.0), 0.0)
    y, x = np.unravel_index(int(np.argmax(fb)), fb.shape)
    w = max(1, int(round(2 * s)))
    relief = 0.0
    for xx in (x, fb.shape[1] - 1 - x):
        win = bb[max(y - w, 0):y + w + 1, max(xx - w, 0):xx + w + 1]
        if win.size:
            relief = max(relief, float(win.max()))
    return sim, colour, relief


def _edge_sharpness(rgb, alpha) -> float:
    """log of the grey gradient energy across the silhouette over that of a sharp composite (alpha *
    inside colour + (1 - alpha) * background) built from the same view: about 0 when the colour image
    is as sharp as its mask, negative when it is blurred. NaN when there is too little edge."""
    a = alpha.astype(np.float64) / 255.0
    g = rgb.astype(np.float64).mean(-1) / 255.0
    m = a > 0.5
    if m.sum() < 30 or (~m).sum() < 30:
        return float("nan")
    outside = a < 0.01
    bg = float(np.median(g[outside])) if outside.any() else 1.0
    full = ndi.binary_erosion(a > 0.99, iterations=1)
    if not full.any():
        return float("nan")
    inside = _nearest_fill(np.where(full, g, 0.0), full)
    sharp = a * inside + (1.0 - a) * bg
    band = ndi.binary_dilation(m, iterations=2) & ~ndi.binary_erosion(m, iterations=2)
    e_img = np.hypot(ndi.sobel(g, 0), ndi.sobel(g, 1))[band]
    e_ref = np.hypot(ndi.sobel(sharp, 0), ndi.sobel(sharp, 1))[band]
    keep = e_ref > 0.1
    if keep.sum() < 10:
        return float("nan")
    return float(np.log((e_img[keep] ** 2).mean() / (e_ref[keep] ** 2).mean()))


def _thumbnail(rgb, mask, side: int):
    """Grey thumbnail of the head crop (square around the mask's bounding box), flattened float32."""
    from PIL import Image

    top, bot, left, right = _bbox(mask)
    cy, cx = (top + bot) / 2.0, (left + right) / 2.0
    half = max(bot - top, right - left) / 2.0 + 1.0
    box = (int(math.floor(cx - half)), int(math.floor(cy - half)), int(math.ceil(cx + half)) + 1,
           int(math.ceil(cy + half)) + 1)
    grey = Image.fromarray(np.asarray(rgb, dtype=np.uint8)).convert("L")
    return np.asarray(grey.crop(box).resize((side, side), Image.BILINEAR), dtype=np.float32).ravel()


def subject_features(sample: SubjectSample, params: Params = DEFAULT_PARAMS) -> dict:
    """The per-subject feature record (JSON-free, small). Uses all masks and the RGB and depth of the
    equator views (see :func:`equator_views`); other views' RGB/depth may be None."""
    p = params
    views = sample.metadata["views"]
    n = len(views)
    if n == 0:
        raise DatasetError(f"subject {sample.key} has no views")
    res = int(sample.alpha[0].shape[0])
    k = max(1, int(round(res / WORK_RES)))
    s = (res / k) / WORK_RES                     # working px per px at 64
    rec = {"key": sample.key, "n_views": n, "resolution": res, "protocol": sample.metadata.get("protocol")}

    # Masks of every view: empty views, area, detached parts, see-through holes.
    min_px = max(2.0, p.floater_min_px * (res / WORK_RES) ** 2)
    area, floats, silh = [], [], []
    for i in range(n):
        m = np.asarray(sample.alpha[i]) > 127
        area.append(float(m.mean()))
        floats.append(_components(m, min_px) if m.any() else (0.0, 0, 0))
        if m.any():
            holes = ndi.binary_fill_holes(m) & ~m
            lab, nh = ndi.label(holes)
            big = np.bincount(lab.ravel())[1:] if nh else np.zeros(0)
            big = big[big >= min_px]
            silh.append(float(big.sum() / m.sum()) if big.size else 0.0)
        else:
            silh.append(0.0)
    rec["area"] = np.asarray(area, dtype=np.float32)
    rec["float_share"] = np.asarray([f[0] for f in floats], dtype=np.float32)
    rec["float_n"] = np.asarray([f[1] for f in floats], dtype=np.int32)
    rec["float_px"] = np.asarray([f[2] for f in floats], dtype=np.int32)
    rec["silh_share"] = np.asarray(silh, dtype=np.float32)

    # Colour and depth of the equator views at working resolution.
    eq = equator_views(views)
    work = {}
    for t, i in eq.items():
        if sample.rgb[i] is None or sample.depth[i] is None:
            continue
        c, m, d = _downsample(sample.rgb[i], sample.alpha[i], sample.depth[i], k)
        work[i] = (c, m, d)
    eq_used = [(t, i) for t, i in sorted(eq.items()) if i in work and work[i][1].sum() >= 16]
    rec["eq_views"] = [i for _, i in eq_used]
    rec["eq_yaw"] = [float(views[i]["yaw_deg"]) for _, i in eq_used]
    sat, p10, detail, dmed, crater, crater_at, edges = [], [], [], [], [], [], []
    for _, i in eq_used:
        edges.append(_edge_sharpness(sample.rgb[i], sample.alpha[i]))
        c, m, d = work[i]
        mx, mn = c.max(-1), c.min(-1)
        sat.append(float(((mx - mn) / np.maximum(mx, 1e-3))[m].mean()))
        grey = c.mean(-1)
        p10.append(float(np.percentile(grey[m], 10)))
        inner = ndi.binary_erosion(m, iterations=max(1, int(round(2 * s))))
        if inner.sum() >= 16:
            lap = ndi.laplace(_nearest_fill(grey, m))
            gv = float(grey[inner].var())
            detail.append(float(np.log((lap[inner].var() + 1e-12) / (gv + 1e-12))) if gv > 1e-8 else np.nan)
        dmed.append(float(np.median(d[m])))
        r, at = _crater(d, m, s, p)
        top, bot, left, right = _bbox(m)
        crater.append(r)
        crater_at.append((round((at[0] - top) / max(bot - top, 1), 2), round((at[1] - left) / max(right - left, 1), 2)))
    rec["sat"] = float(np.mean(sat)) if sat else np.nan
    rec["p10"] = float(np.mean(p10)) if p10 else np.nan
    detail = [x for x in detail if np.isfinite(x)]
    rec["detail"] = float(np.median(detail)) if detail else np.nan
    edges = [x for x in edges if np.isfinite(x)]
    rec["edge"] = float(np.median(edges)) if edges else np.nan
    rec["depth_median"] = float(np.median(dmed)) if dmed else np.nan
    rec["crater"] = np.asarray(crater, dtype=np.float32)
    rec["crater_at"] = crater_at

    # Janus: the back view against the front view.
    rec["janus"] = None
    front = eq.get(0.0)
    back = eq.get(180.0)
    if back is not None and (abs(_wrap(views[back]["yaw_deg"] - 180.0)) > BACK_TOL
                             or abs(views[back]["pitch_deg"]) > BACK_TOL):
        back = None
    if back is None or front is None:
        rec["janus_na"] = (f"not applicable: no {'back' if back is None else 'front'} view (|yaw - "
                           f"{180 if back is None else 0}| and |pitch| <= {BACK_TOL:g}) among this subject's cameras")
    elif front not in work or back not in work or work[front][1].sum() < 30 or work[back][1].sum() < 30:
        rec["janus_na"] = "not measured: the front or back view is (almost) empty"
    else:
        j = _janus(work[front], work[back], s)
        rec["janus"] = {"back": back, "front": front, "sim": j[0], "colour": j[1], "relief": j[2]}

    # Duplicate thumbnail from the frontal view (the view closest to yaw 0 / pitch 0).
    rec["thumb"] = None
    if front is not None and sample.rgb[front] is not None:
        m = np.asarray(sample.alpha[front]) > 127
        if m.sum() >= 4:
            rec["thumb"] = _thumbnail(sample.rgb[front], m, p.thumb)
            rec["thumb_view"] = front
    return rec


def _failed_record(key: str, error: str) -> dict:
    return {"key": key, "error": error}


def _extract(item):
    """Worker: (shard, key, fields) -> (shard, feature record)."""
    shard, key, fields, where, params = item
    try:
        sample = _decode_needed(key, fields, where)
        return shard, subject_features(sample, params)
    except DatasetError as e:
        return shard, _failed_record(key, str(e))
    except Exception as e:  # a detector crashing on odd input must not stop the whole dataset
        return shard, _failed_record(key, f"{where}: subject {key}: feature extraction failed "
                                          f"({type(e).__name__}: {e})")


# ----------------------------------------------------------------------------------------------
# The dataset pass

def _complete_shards(root: Path, index: dict):
    """(name, path) of shards whose tar and sidecar exist; and the names of those that do not."""
    ok, missing = [], []
    for shard in index.get("shards", []):
        name = shard["name"]
        tar, side = root / f"{name}.tar", root / f"{name}.json"
        (ok if tar.exists() and side.exists() else missing).append((name, tar))
    return ok, [n for n, _ in missing]


def extract_features(root, progress: bool = False, workers: int = 1, params: Params = DEFAULT_PARAMS) -> dict:
    """First pass: {"index_sha256", "features": [(shard, record), ...] in index order, "missing_shards",
    "seconds"}. Reads index.json and complete shards only."""
    root = Path(root)
    index = read_index(root)
    index_sha = index_sha256(root)
    shards, missing = _complete_shards(root, index)
    total = sum(len(s["subjects"]) for s in index.get("shards", []) if s["name"] not in missing)

    def items():
        for name, path in shards:
            for key, fields in _subject_groups(path, _wanted_field):
                yield name, key, fields, str(path), params

    bar = None
    if progress:
        try:
            from tqdm import tqdm
            bar = tqdm(total=total, unit="subj", desc="preflags", file=sys.stderr)
        except ImportError:
            bar = None
    t0 = time.perf_counter()
    out = []
    if workers > 1:
        # Bounded batches: the reader runs at most one batch ahead of the workers.
        ctx = mp.get_context("fork") if "fork" in mp.get_all_start_methods() else mp.get_context()
        stream = items()
        with ctx.Pool(workers) as pool:
            pending = None
            while True:
                batch = list(itertools.islice(stream, workers * 16))   # read ahead while the pool works
                if pending is not None:
                    done = pending.get()
                    out.extend(done)
                    if bar is not None:
                        bar.update(len(done))
                if not batch:
                    break
                pending = pool.map_async(_extract, batch, chunksize=2)
    else:
        for item in items():
            out.append(_extract(item))
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    return {"index_sha256": index_sha, "features": out, "missing_shards": missing,
            "seconds": time.perf_counter() - t0}


# ----------------------------------------------------------------------------------------------
# Scoring (dataset statistics, then per subject)

def _duplicates(thumbs: list, p: Params):
    """For each row: (best cosine similarity to another row, its index), blocked over rows and columns."""
    n = len(thumbs)
    best = np.full(n, -np.inf, dtype=np.float32)
    arg = np.full(n, -1, dtype=np.int64)
    valid = [i for i, t in enumerate(thumbs) if t is not None]
    if len(valid) < 2:
        return best, arg
    x = np.stack([thumbs[i] for i in valid]).astype(np.float64)
    x -= x.mean(axis=0, keepdims=True)            # remove what every head has in common
    x -= x.mean(axis=1, keepdims=True)
    norm = np.linalg.norm(x, axis=1, keepdims=True)
    x = (x / np.maximum(norm, 1e-9)).astype(np.float32)
    m = len(valid)
    vb = np.full(m, -np.inf, dtype=np.float32)
    va = np.full(m, -1, dtype=np.int64)
    B = max(1, p.duplicate_block)
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


def dataset_stats(records: list, p: Params = DEFAULT_PARAMS) -> dict:
    """Robust statistics over the per-subject records (median and MAD-based scale per feature)."""
    ok = [r for r in records if "error" not in r]
    st = {}
    st["log_sat"] = _robust([math.log(max(r["sat"], 1e-4)) for r in ok if np.isfinite(r["sat"])], 0.02)
    st["p10"] = _robust([r["p10"] for r in ok if np.isfinite(r["p10"])], 0.005)
    st["detail"] = _robust([r["detail"] for r in ok if np.isfinite(r["detail"])], 0.05)
    st["edge"] = _robust([r["edge"] for r in ok if np.isfinite(r.get("edge", np.nan))], p.blur_edge_floor)
    st["log_area"] = _robust([math.log(max(float(np.mean(r["area"])), 1e-6)) for r in ok if len(r["area"])], 0.02)
    st["depth_median"] = _robust([r["depth_median"] for r in ok if np.isfinite(r["depth_median"])], 0.005)
    jan = [r["janus"] for r in ok if r.get("janus")]
    st["janus_sim"] = _robust([j["sim"] for j in jan], 0.05)
    st["janus_colour"] = _robust([j["colour"] for j in jan], 0.05)
    st["janus_relief"] = _robust([math.log(j["relief"] + 1e-4) for j in jan], 0.05)
    bins = {}
    for r in ok:
        for yaw, c in zip(r["eq_yaw"], r["crater"]):
            bins.setdefault(int(round(yaw / EQUATOR_STEP)) % 8, []).append(float(c))
    st["crater"] = {b: _robust_tail(v, p.crater_mad_floor) for b, v in bins.items()}
    return st


def _z(x, stat):
    med, scale = stat
    return (x - med) / scale


def score_record(r: dict, st: dict, dup, keys: list, p: Params = DEFAULT_PARAMS) -> dict:
    """{detector: {"score", "why"}} for one feature record."""
    out = {}
    if "error" in r:
        out["empty"] = {"score": 1.0, "why": f"does not decode: {r['error']}"}
        for name in DETECTOR_NAMES:
            out.setdefault(name, {"score": 0.0, "why": "not measured (subject does not decode)"})
        return out

    # janus
    j = r.get("janus")
    if j is None:
        out["janus"] = {"score": 0.0, "why": r.get("janus_na", "not measured")}
    else:
        zs = _z(j["sim"], st["janus_sim"])
        zc = _z(j["colour"], st["janus_colour"])
        zr = _z(math.log(j["relief"] + 1e-4), st["janus_relief"])
        m = (zs + zc + zr) / 3.0
        out["janus"] = {"score": _ramp(m, p.janus_z, p.janus_z_sat), "value": m,
                        "why": f"back view {view_name(j['back'])} vs front {view_name(j['front'])}: edge corr "
                               f"{j['sim']:.2f} (dataset median {st['janus_sim'][0]:.2f}), face-colour corr "
                               f"{j['colour']:.2f} (median {st['janus_colour'][0]:.2f}), nose-like bump "
                               f"{j['relief']:.4f} (median {math.exp(st['janus_relief'][0]) - 1e-4:.4f}); "
                               f"z {m:.1f} (flag at {p.janus_z:g})"}

    # floaters
    fs = r["float_share"]
    if len(fs) and fs.max() > 0:
        i = int(np.argmax(fs))
        out["floaters"] = {"score": _ramp(float(fs[i]), p.floater_share, p.floater_share_sat), "value": float(fs[i]),
                           "why": f"{view_name(i)}: {int(r['float_n'][i])} detached part(s), {100 * fs[i]:.1f}% of "
                                  f"the silhouette (largest {int(r['float_px'][i])} px); detached parts in "
                                  f"{int((fs > 0).sum())} of {len(fs)} views"}
    else:
        out["floaters"] = {"score": 0.0, "why": f"no detached parts in {len(fs)} views"}

    # holes: see-through holes and craters
    sh = r["silh_share"]
    s_sil, why_sil = 0.0, None
    if len(sh) and sh.max() > 0:
        i = int(np.argmax(sh))
        s_sil = _ramp(float(sh[i]), p.silhouette_hole_share, p.silhouette_hole_share_sat)
        why_sil = f"{view_name(i)}: see-through hole, {100 * sh[i]:.2f}% of the silhouette"
    s_cr, why_cr, best_z = 0.0, None, -np.inf
    for v, yaw, c, at in zip(r["eq_views"], r["eq_yaw"], r["crater"], r["crater_at"]):
        stat = st["crater"].get(int(round(yaw / EQUATOR_STEP)) % 8)
        if stat is None:
            continue
        z = _z(float(c), stat)
        if z > best_z:
            best_z = z
            why_cr = (f"{view_name(v)}: round depression {float(c):.4f} deep at {int(100 * at[0])}% height "
                      f"(views from yaw {yaw:.0f}: median {stat[0]:.4f}); z {z:.1f} (flag at {p.crater_z:g})")
    if why_cr is not None:
        s_cr = _ramp(best_z, p.crater_z, p.crater_z_sat)
    if s_sil >= s_cr and why_sil:
        out["holes"] = {"score": s_sil, "value": best_z if why_cr else None, "why": why_sil}
    elif why_cr:
        out["holes"] = {"score": s_cr, "value": best_z, "why": why_cr}
    else:
        out["holes"] = {"score": 0.0, "why": "no depth views to search"}

    # washed_out
    if np.isfinite(r["sat"]) and np.isfinite(r["p10"]):
        zs = -_z(math.log(max(r["sat"], 1e-4)), st["log_sat"])
        zp = _z(r["p10"], st["p10"])
        m = 0.5 * (zs + zp)
        out["washed_out"] = {"score": _ramp(m, p.washed_z, p.washed_z_sat), "value": m,
                             "why": f"saturation {r['sat']:.2f} (median {math.exp(st['log_sat'][0]):.2f}), darkest "
                                    f"decile {r['p10']:.2f} (median {st['p10'][0]:.2f}); z {m:.1f} "
                                    f"(flag at {p.washed_z:g})"}
    else:
        out["washed_out"] = {"score": 0.0, "why": "no colour views to measure"}

    # blur: silhouette edge sharpness (content-independent), interior detail for the explanation
    edge = r.get("edge", np.nan)
    detail_txt = (f"; interior detail {math.exp(r['detail'] - st['detail'][0]):.2f}x the dataset median"
                  if np.isfinite(r["detail"]) else "")
    if np.isfinite(edge):
        z = -_z(edge, st["edge"])
        out["blur"] = {"score": _ramp(z, p.blur_z, p.blur_z_sat), "value": z,
                       "why": f"silhouette edges carry {100 * math.exp(edge):.0f}% of the gradient energy of a sharp "
                              f"cut-out (dataset median {100 * math.exp(st['edge'][0]):.0f}%); z {-z:.1f} (flag at "
                              f"-{p.blur_z:g}){detail_txt}"}
    else:
        out["blur"] = {"score": 0.0, "why": "no usable silhouette edge to measure" + detail_txt}

    # empty
    area = r["area"]
    empty = [i for i, a in enumerate(area) if a < p.empty_area]
    if empty:
        names = ", ".join(view_name(i) for i in empty[:6]) + (", ..." if len(empty) > 6 else "")
        out["empty"] = {"score": 0.5 + 0.5 * len(empty) / len(area), "value": len(empty),
                        "why": f"{len(empty)} of {len(area)} views empty ({names})"}
    else:
        out["empty"] = {"score": 0.0,
                        "why": f"no empty views (smallest mask {100 * float(area.min()):.1f}% of the image)"
                        if len(area) else "no views"}

    # implausible
    parts = []
    if len(area) and float(np.mean(area)) > 0:
        za = _z(math.log(max(float(np.mean(area)), 1e-6)), st["log_area"])
        parts.append((abs(za), f"mean mask area {100 * float(np.mean(area)):.1f}% of the image (median "
                                f"{100 * math.exp(st['log_area'][0]):.1f}%, z {za:+.1f})"))
    if np.isfinite(r["depth_median"]):
        zd = _z(r["depth_median"], st["depth_median"])
        parts.append((abs(zd), f"median depth {r['depth_median']:.3f} (median {st['depth_median'][0]:.3f}, "
                               f"z {zd:+.1f})"))
    if parts:
        zmax, why = max(parts)
        out["implausible"] = {"score": _ramp(zmax, p.implausible_z, p.implausible_z_sat), "value": zmax, "why": why}
    else:
        out["implausible"] = {"score": 0.0, "why": "nothing to measure (all views empty)"}

    # duplicate
    sim, other = dup
    if other is not None and other >= 0 and np.isfinite(sim):
        dis = max(0.0, 1.0 - float(sim))
        score = 1.0 - 0.5 * dis / p.duplicate_dissim if dis < 2 * p.duplicate_dissim else 0.0
        out["duplicate"] = {"score": float(np.clip(score, 0.0, 1.0)), "value": float(sim),
                            "why": f"frontal view closest to {keys[other]} (cosine {float(sim):.4f}, flag at "
                                   f"{1 - p.duplicate_dissim:.2f})"}
    else:
        out["duplicate"] = {"score": 0.0, "why": "no frontal thumbnail to compare"}
    return out


def score_features(extracted: dict, params: Params = DEFAULT_PARAMS) -> dict:
    """Second step: dataset statistics from the stored records, then the report (worst first)."""
    p = params
    pairs = extracted["features"]
    records = [r for _, r in pairs]
    keys = [r["key"] for r in records]
    st = dataset_stats(records, p)
    best, arg = _duplicates([r.get("thumb") if "error" not in r else None for r in records], p)
    subjects = []
    for idx, (shard, r) in enumerate(pairs):
        dets = score_record(r, st, (float(best[idx]), int(arg[idx])), keys, p)
        for d in dets.values():
            d["score"] = round(float(min(1.0, max(0.0, d["score"]))), 4)
            if d.get("value") is not None and np.isfinite(d["value"]):
                d["value"] = round(float(d["value"]), 4)
            else:
                d.pop("value", None)
        dets = {name: dets[name] for name in DETECTOR_NAMES}
        score = max(d["score"] for d in dets.values())
        subjects.append({"subject": r["key"], "shard": shard, "score": score,
                         "flags": [n for n in DETECTOR_NAMES if dets[n]["score"] >= FLAG_AT], "detectors": dets})
    subjects.sort(key=lambda s: (-s["score"], -len(s["flags"]), s["subject"]))
    n = len(subjects)
    secs = extracted.get("seconds")
    return {
        "format": FORMAT,
        "dataset_index_sha256": extracted["index_sha256"],
        "detectors": detector_table(p),
        "summary": {
            "subjects": n,
            "flagged": sum(1 for s in subjects if s["flags"]),
            "per_detector": {name: sum(1 for s in subjects if name in s["flags"]) for name in DETECTOR_NAMES},
            "missing_shards": list(extracted.get("missing_shards", [])),
        },
        "timing": {"seconds": round(secs, 3) if secs is not None else None,
                   "subjects_per_second": round(n / secs, 2) if secs else None},
        "subjects": subjects,
    }


def score_dataset(root, progress: bool = False, workers: int = 1, params: Params = DEFAULT_PARAMS) -> dict:
    """Score every subject of the dataset at ``root``; returns the report (subjects sorted worst first).

    Reads ``index.json`` and the complete shards only (never ``truth/``). ``workers`` > 1 decodes and
    measures subjects in that many processes."""
    t0 = time.perf_counter()
    extracted = extract_features(root, progress=progress, workers=max(1, int(workers)), params=params)
    report = score_features(extracted, params)
    total = time.perf_counter() - t0
    n = report["summary"]["subjects"]
    report["timing"] = {"extract_seconds": round(extracted["seconds"], 3), "total_seconds": round(total, 3),
                        "subjects_per_second": round(n / total, 2) if total > 0 else None,
                        "workers": max(1, int(workers))}
    return report


# ----------------------------------------------------------------------------------------------
# Reading and writing preflags.json

def _canonical(report: dict) -> bytes:
    return (json.dumps(report, indent=1, sort_keys=False, allow_nan=False) + "\n").encode()


def write_preflags(root, report: dict, path=None) -> Path:
    """Write the report to ``path`` (default ``<root>/preflags.json``) atomically: a temporary file in
    the same folder, flushed and fsynced, then renamed over the target."""
    if report.get("format") != FORMAT:
        raise ValueError(f"not a pre-flags report (format {report.get('format')!r})")
    path = Path(path) if path is not None else Path(root) / PREFLAGS_NAME
    return atomic_write(path, _canonical(report))


def read_preflags(root, path=None) -> dict:
    """Read ``<root>/preflags.json`` (or ``path``); errors name the file."""
    path = Path(path) if path is not None else Path(root) / PREFLAGS_NAME
    if not path.exists():
        raise DatasetError(f"{path}: no pre-flags here (run the pre-flag scoring first)")
    return read_json(path, "pre-flags report", FORMAT)


def is_stale(root, report: dict) -> bool:
    """True when the dataset's index.json changed since the report was made."""
    return index_sha256(root) != report.get("dataset_index_sha256")


# ----------------------------------------------------------------------------------------------
# Command line: python -m labeling_tool.preflags DATASET

def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m labeling_tool.preflags",
                                 description="Score every subject of a dataset with the automatic pre-flags and "
                                             "write <dataset>/preflags.json (worst first). Nothing is deleted.")
    ap.add_argument("dataset")
    ap.add_argument("--workers", type=int, default=1, help="processes that decode and measure subjects")
    ap.add_argument("--out", help="where to write the report (default: <dataset>/preflags.json)")
    ap.add_argument("--top", type=int, default=10, help="print the N worst subjects (default 10)")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    args = ap.parse_args(argv)
    try:
        report = score_dataset(args.dataset, progress=not args.quiet, workers=args.workers)
        path = write_preflags(args.dataset, report, args.out)
    except DatasetError as e:
        print(f"preflags: error: {e}", file=sys.stderr)
        return 1
    summ, t = report["summary"], report["timing"]
    print(f"{summ['subjects']} subjects scored in {t['total_seconds']:.1f} s ({t['subjects_per_second']} subjects/s); "
          f"{summ['flagged']} flagged -> {path}")
    for s in report["subjects"][:max(0, args.top)]:
        why = "; ".join(f"{n}: {s['detectors'][n]['why']}" for n in s["flags"]) or "no flags"
        print(f"  {s['subject']}  {s['score']:.2f}  {why}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
