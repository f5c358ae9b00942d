"""janus: a second face on the back of the head.

Two cues; the subject's score is the stronger. (1) Detectors that work offline: dlib's HOG face
detector on the back and back-diagonal views (yaw ~135, ~180, ~225), at a scale where a face of the
subject's size is large enough for it; dlib's MMOD CNN face detector on the head of the back view
(yaw ~180), the view scaled to ``CNN_VIEW_PX`` wide; and OpenCV's Haar eye cascade on the back view
(scaled to ``EYE_VIEW_PX`` wide), looking for a pair of eyes where a face would have them. The
strongest of the three counts. The CNN, half the cost of a subject at 128 px, runs only where the
cheaper two see something face-like (``face_like``: HOG above -0.6 or a pair of eyes;
``Settings.cnn_always`` runs it everywhere).
(2) The back view (yaw ~180) compared with the front view (yaw ~0, as is and mirrored) on edge
structure and on the colour layout of the face region, and searched for a nose-like depth bump where
the front view has its nose: the mean of the three robust z-scores against the dataset, each capped
so that no one cue carries it.
Not applicable (score 0) without a back view, e.g. in the ``frontal`` protocol.
"""
from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage as ndi

from datagen.faces import cnn_detector, hog_detector
from datagen.dataset.shards import view_name

from .detector import Detector, Flag, ramp_flag
from .imaging import blob_response, central, erode, nearest_fill, ramp, robust
from .views import BACK_TOL

BACK_TARGETS = (135.0, 180.0, 225.0)  # equator targets whose views should never show a face
NO_FACE = -1.0                        # the detector's score when it reports nothing (its floor here)
CNN_VIEW_PX = 192  # px: width a back view is scaled to before the CNN face detector reads its head
EYE_VIEW_PX = 256  # px: width a back view is scaled to before the eye cascade reads it
# Largest mean absolute RGB difference (0-255) between the bridge of the nose of an eye pair and the
# front view's face for the pair to count (a second face has the first one's skin; textured hair does not).
SKIN_TOL = 60.0


@functools.lru_cache(maxsize=None)
def eye_cascade():
    """OpenCV's frontal eye Haar cascade (shipped with the opencv wheels)."""
    path = os.path.join(cv2.data.haarcascades, "haarcascade_eye.xml")
    cascade = cv2.CascadeClassifier(path)
    if cascade.empty():
        raise RuntimeError(f"{path}: OpenCV's eye cascade is missing or unreadable")
    return cascade


def head_extent(mask: np.ndarray):
    """(top row, height in rows, left column, right column) of the head in a silhouette: its columns are
    those of the top 45 % of the silhouette's rows (shoulders do not widen it); None for an empty mask."""
    ys, _ = np.nonzero(mask)
    if not ys.size:
        return None
    top, height = int(ys.min()), int(ys.max()) - int(ys.min()) + 1
    cols = np.nonzero(mask[top:top + max(1, int(0.45 * height))].any(0))[0]
    return top, height, int(cols[0]), int(cols[-1])


def face_colour(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Median RGB (0-255) of a front view's face: rows 35-50 % down the silhouette, the middle half of
    the head's width (cheeks and nose, below the eyes)."""
    top, height, left, right = head_extent(mask)
    half, axis = max(1, (right - left) // 4), (left + right) // 2
    patch = rgb[top + int(0.35 * height):top + int(0.5 * height) + 1, max(axis - half, 0):axis + half + 1]
    return np.median(patch.reshape(-1, 3), 0)


def eye_pair(rgb: np.ndarray, mask: np.ndarray, skin=None, view_px: int = EYE_VIEW_PX) -> int:
    """How strongly a view shows a pair of eyes where a face has them: the eye cascade's raw detections
    (no neighbour rule) on the view scaled to ``view_px`` wide, grouped (overlap rule of
    cv2.groupRectangles); over pairs of groups of similar size, level with each other, 1.2-3.5 sizes
    apart, their midpoint within 0.2 head widths of the head's vertical axis and 10-60 % down the
    silhouette, 0.15-0.6 head widths apart, and (given ``skin``, the face's RGB from the front view)
    skin between them: the median colour of the bridge of the nose (half an eye's size, 0.4 sizes below
    the pair's midpoint) within SKIN_TOL of ``skin``. Returns the larger of the pairs' smaller detection
    counts (0: none)."""
    k = view_px / rgb.shape[1]
    big = cv2.resize(np.ascontiguousarray(rgb), None, fx=k, fy=k, interpolation=cv2.INTER_LINEAR)
    grey = cv2.cvtColor(big, cv2.COLOR_RGB2GRAY)
    m = cv2.resize(mask.astype(np.uint8), (grey.shape[1], grey.shape[0]), interpolation=cv2.INTER_NEAREST) > 0
    if m.sum() < 100:
        return 0
    top, height, left, right = head_extent(m)
    width, axis = float(right - left), 0.5 * float(left + right)
    raw = [list(map(int, r)) for r in eye_cascade().detectMultiScale(grey, 1.05, 0, minSize=(8, 8), maxSize=(48, 48))]
    raw = [r for r in raw if m[r[1] + r[3] // 2, r[0] + r[2] // 2]]
    if len(raw) < 2:
        return 0
    boxes, counts = cv2.groupRectangles(raw + raw, 1, 0.3)  # each twice, so that single detections are kept
    eyes = [(x + w / 2, y + h / 2, 0.5 * (w + h), int(n) // 2) for (x, y, w, h), n in zip(boxes, np.ravel(counts))]

    def skin_between(x, y, size):
        if skin is None:
            return True
        r, cy = max(1, int(0.25 * size)), int(y + 0.4 * size)
        patch = big[max(cy - r, 0):cy + r + 1, max(int(x) - r, 0):int(x) + r + 1].reshape(-1, 3)
        return patch.size > 0 and float(np.abs(np.median(patch, 0) - skin).mean()) < SKIN_TOL
    best = 0
    for i, (xa, ya, sa, na) in enumerate(eyes):
        for xb, yb, sb, nb in eyes[i + 1:]:
            s, dx = 0.5 * (sa + sb), abs(xa - xb)
            if (abs(sa - sb) <= 0.5 * s and abs(ya - yb) <= 0.4 * s and 1.2 * s <= dx <= 3.5 * s
                    and abs(0.5 * (xa + xb) - axis) < 0.2 * width and 0.15 * width < dx < 0.6 * width
                    and top + 0.1 * height < 0.5 * (ya + yb) < top + 0.6 * height
                    and min(na, nb) > best and skin_between(0.5 * (xa + xb), 0.5 * (ya + yb), s)):
                best = min(na, nb)
    return best


def best_face(rgb: np.ndarray) -> float:
    """The best HOG face-detection score in an RGB image (NO_FACE when none reaches it). The image is
    upsampled until a face about a third of the image wide is some 80 px, the detector's minimum."""
    up = max(0, math.ceil(math.log2(80.0 / (0.35 * rgb.shape[1])))) if rgb.shape[1] < 230 else 0
    _, scores, _ = hog_detector().run(np.ascontiguousarray(rgb), up, NO_FACE)
    return float(max(scores, default=NO_FACE))


def head_crop(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The head in a view (see head_extent): the top 80 % of the silhouette's rows, with a margin of 6 %
    of the image width."""
    extent = head_extent(mask)
    if extent is None:
        return rgb
    top, height, left, right = extent
    pad = int(0.06 * mask.shape[1])
    return rgb[max(top - pad, 0):top + int(0.8 * height), max(left - pad, 0):right + pad + 1]


def best_cnn_face(rgb: np.ndarray, mask: np.ndarray, view_px: int = CNN_VIEW_PX) -> float:
    """The best confidence of dlib's MMOD CNN face detector on the head in an RGB view, the view scaled
    to ``view_px`` wide (NO_FACE when it finds nothing; its detections are above 0)."""
    head = head_crop(rgb, mask)
    k = view_px / rgb.shape[1]
    img = cv2.resize(head, (max(1, round(head.shape[1] * k)), max(1, round(head.shape[0] * k))),
                     interpolation=cv2.INTER_AREA if k < 1 else cv2.INTER_LINEAR)
    return float(max((d.confidence for d in cnn_detector()(np.ascontiguousarray(img), 0)), default=NO_FACE))


def face_like(faces: dict, eyes: int, face_at: float, eyes_at: int) -> bool:
    """Whether the cheap face cues see something face-like on the back views, so that the CNN face
    detector is worth running: a HOG score above ``face_at`` on any of them (``faces`` {view: best
    score}) or an eye pair of at least ``eyes_at`` detections an eye (``eye_pair``). On the tuning
    datasets every face the CNN found passed (HOG -0.57 the lowest without eyes), and clean backs whose
    hair gave HOG -0.92 to -0.64 or a single eye detection did not (benchmarks/reports/preflags_tuning.md)."""
    return eyes >= eyes_at or max(faces.values(), default=NO_FACE) > face_at


def _match(image, template, mask, sh: int, method) -> np.ndarray:
    """cv2.matchTemplate of ``template`` (cut to the bounding box of ``mask``) against ``image`` padded with
    zeros by ``sh`` px: a (2 sh + 1, 2 sh + 1) map, one value per shift of up to ``sh`` px each way (the
    centre is no shift). The image is empty beyond its edges: nothing wraps around."""
    ys, xs = np.nonzero(mask)
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    padded = cv2.copyMakeBorder(np.asarray(image, np.float32), sh, sh, sh, sh, cv2.BORDER_CONSTANT, value=0)
    window = np.ascontiguousarray(padded[y0:y1 + 2 * sh, x0:x1 + 2 * sh])
    cut = np.ascontiguousarray(template[y0:y1, x0:x1], dtype=np.float32)
    weights = None if method == cv2.TM_CCORR else np.ascontiguousarray(mask[y0:y1, x0:x1], dtype=np.uint8)
    return cv2.matchTemplate(window, cut, method, mask=weights)


def edge_ncc(a_grey, a_mask, b_grey, b_mask, s: float) -> float:
    """Best normalised correlation of Sobel edge magnitude inside both (eroded) masks over small shifts.

    For each shift of b (up to 3 s px each way) the correlation is over the overlap of the two masks (at
    least 20 px). OpenCV's matchTemplate masks the template only, so the overlap's pixel count, sums and
    sums of products come from six plain cross-correlations (TM_CCORR) of the masked images.
    """
    ga = np.hypot(ndi.sobel(a_grey, 0), ndi.sobel(a_grey, 1))
    gb = np.hypot(ndi.sobel(b_grey, 0), ndi.sobel(b_grey, 1))
    it = max(1, int(round(2 * s)))
    ia = erode(a_mask, it)
    ib = erode(b_mask, it)
    sh = max(1, int(round(3 * s)))
    if not ia.any() or not ib.any():
        return -1.0
    a, b = ia.astype(np.float32), ib.astype(np.float32)
    # centred on each mask's mean (the correlation does not change): smaller sums, less cancellation
    x = np.where(ia, ga - ga[ia].mean(), 0.0).astype(np.float32)
    y = np.where(ib, gb - gb[ib].mean(), 0.0).astype(np.float32)
    n, sx, sy, sxx, syy, sxy = (_match(img, tpl, ia, sh, cv2.TM_CCORR).astype(np.float64)
                                for tpl, img in ((a, b), (x, b), (a, y), (x * x, b), (a, y * y), (x, y)))
    n = np.rint(n)
    with np.errstate(divide="ignore", invalid="ignore"):
        vx = sxx - sx * sx / n
        vy = syy - sy * sy / n
        r = (sxy - sx * sy / n) / np.sqrt(vx * vy)
    ok = (n >= 20) & (vx > 1e-6 * sxx) & (vy > 1e-6 * syy)
    return float(r[ok].max()) if ok.any() else -1.0


def colour_ncc(back_c, front_c, region, s: float) -> float:
    """Best normalised correlation of colour (channels centred separately) over the region, shifting the
    front view (and the region with it) by up to 3 s px: matchTemplate's TM_CCOEFF_NORMED with the region
    as the front view's mask."""
    sh = max(1, int(round(3 * s)))
    if region.sum() < 20:
        return -1.0
    r = _match(back_c, front_c, region, sh, cv2.TM_CCOEFF_NORMED)
    r = r[np.isfinite(r)]  # NaN where the back view is flat under the shifted region
    return float(r.max()) if r.size else -1.0


def face_evidence(front, back, s: float):
    """Face evidence in a back view: (edge similarity, colour similarity in the face region, nose-bump
    strength), each against the front view as is and mirrored."""
    (fc, fm, fd), (bc, bm, bd) = front, back
    fg, bg = fc.mean(-1), bc.mean(-1)
    sim = max(edge_ncc(bg, bm, fg, fm, s), edge_ncc(bg, bm, fg[:, ::-1], fm[:, ::-1], s))
    it2 = max(1, int(round(2 * s)))
    face = central(erode(fm, it2), 0.25, 0.75, 0.3, 0.85) & erode(bm, it2)
    colour = max(colour_ncc(bc, fc, face, s), colour_ncc(bc, fc[:, ::-1], face[:, ::-1], s)) if face.any() else -1.0
    it = max(1, int(round(3 * s)))
    f_inner = erode(fm, it)
    b_inner = erode(bm, it)
    if not f_inner.any() or not b_inner.any():
        return sim, colour, 0.0
    sig = 1.0 * s
    fb = np.where(central(f_inner), blob_response(nearest_fill(fd.astype(np.float64), fm), sig, +1.0), 0.0)
    bb = np.where(b_inner, blob_response(nearest_fill(bd.astype(np.float64), bm), sig, +1.0), 0.0)
    y, x = np.unravel_index(int(np.argmax(fb)), fb.shape)
    w = max(1, int(round(2 * s)))
    relief = 0.0
    for xx in (x, fb.shape[1] - 1 - x):
        win = bb[max(y - w, 0):y + w + 1, max(xx - w, 0):xx + w + 1]
        if win.size:
            relief = max(relief, float(win.max()))
    return sim, colour, relief


class Janus(Detector):
    name = "janus"
    description = ("a face on the back of the head: dlib's face detectors (HOG on the back and back-diagonal "
                   "views, CNN on the back view's head where HOG or the eye cascade sees anything), OpenCV's eye "
                   "cascade (a pair of eyes on the back view), or "
                   "the back view vs the front view (edge correlation and face-region colour correlation, as is and "
                   "mirrored) and a nose-like depth bump where the front has its nose, the mean of the three robust "
                   "z-scores (each capped at 3); n/a without a back view")

    @dataclass(frozen=True)
    class Settings:
        z: float = 2.5          # mean of the edge, face-colour and nose-bump robust z-scores at which it flags
        z_sat: float = 4.0      # that mean at which the score reaches 1
        cue_cap: float = 3.0    # each z counts up to this, so that no one cue carries the mean
        face: float = -0.3      # HOG score at which the back view's face flags (below dlib's own 0: partial
        face_sat: float = 0.5   # faces score -0.4 to 0); the score at which the flag reaches 1
        face_diagonal: float = 0.0  # HOG score on the back-diagonal views, where the real face's cheek and nose
                                    # show at the edge
        cnn: float = 0.0        # CNN confidence at which it flags (any detection)
        cnn_sat: float = 0.8    # confidence at which the score reaches 1
        eyes: int = 2           # eye-pair strength (detections per eye, skin between) at which it flags
        eyes_sat: int = 8       # strength at which the score reaches 1
        cnn_gate_face: float = -0.6  # the CNN runs where HOG scores above this on a back view (``face_like``)
        cnn_gate_eyes: int = 2       # ... or the eye cascade finds a pair of at least this strength
        cnn_always: bool = False  # run the CNN on every back view, not only where ``face_like`` (slower)

    def threshold(self):
        return {"cue_z": self.settings.z, "face_score": self.settings.face,
                "face_score_diagonal": self.settings.face_diagonal, "cnn_confidence": self.settings.cnn,
                "eye_pair": self.settings.eyes}

    @staticmethod
    def _faces(v) -> dict:
        """{view: best HOG face score} of the back and back-diagonal views."""
        views = {v.eq[t] for t in BACK_TARGETS if t in v.eq and v.rgb.get(v.eq[t]) is not None}
        return {i: best_face(v.rgb[i]) for i in sorted(views)}

    def measure(self, v):
        front, back = v.front, v.back
        if back is None or front is None:
            return {"na": f"not applicable: no {'back' if back is None else 'front'} view (|yaw - "
                          f"{180 if back is None else 0}| and |pitch| <= {BACK_TOL:g}) among this subject's cameras"}
        if front not in v.work or back not in v.work or v.work[front][1].sum() < 30 or v.work[back][1].sum() < 30:
            return {"na": "not measured: the front or back view is (almost) empty"}
        sim, colour, relief = face_evidence(v.work[front], v.work[back], v.s)
        faces = self._faces(v)
        seen = v.rgb.get(back) is not None
        eyes = eye_pair(v.rgb[back], v.mask(back), face_colour(v.rgb[front], v.mask(front))) \
            if seen and v.rgb.get(front) is not None else 0
        cnn = NO_FACE
        t = self.settings
        if seen and (t.cnn_always or face_like(faces, eyes, t.cnn_gate_face, t.cnn_gate_eyes)):
            cnn = best_cnn_face(v.rgb[back], v.mask(back))
        elif seen:
            cnn = None  # not run
        return {"back": back, "front": front, "sim": sim, "colour": colour, "relief": relief, "faces": faces,
                "cnn": cnn, "eyes": eyes, "yaw": {i: float(v.views[i]["yaw_deg"]) for i in faces}}

    def baseline(self, measured):
        jan = [m for m in measured if m and "na" not in m]
        return {"sim": robust([j["sim"] for j in jan], 0.05), "colour": robust([j["colour"] for j in jan], 0.05),
                # at least a factor 1.6 in relief: where most backs are smooth the log's MAD is about 0
                "relief": robust([math.log(j["relief"] + 1e-4) for j in jan], 0.5)}

    def score(self, j, base, index, keys):
        if j is None or "na" in j:
            return Flag(0.0, j["na"] if j else "not measured")
        t = self.settings
        zs = min((j["sim"] - base["sim"][0]) / base["sim"][1], t.cue_cap)
        zc = min((j["colour"] - base["colour"][0]) / base["colour"][1], t.cue_cap)
        zr = min((math.log(j["relief"] + 1e-4) - base["relief"][0]) / base["relief"][1], t.cue_cap)
        m = (zs + zc + zr) / 3.0
        cue = ramp_flag(m, t.z, t.z_sat,
                        f"back view {view_name(j['back'])} vs front {view_name(j['front'])}: edge corr "
                   f"{j['sim']:.2f} (dataset median {base['sim'][0]:.2f}), face-colour corr "
                   f"{j['colour']:.2f} (median {base['colour'][0]:.2f}), nose-like bump "
                   f"{j['relief']:.4f} (median {math.exp(base['relief'][0]) - 1e-4:.4f}); z {m:.1f} (flag at {t.z:g})",
                   m)
        faces = j.get("faces") or {}
        if not faces:
            return cue
        at = {k: t.face if k == j["back"] else t.face_diagonal for k in faces}  # the back view's own threshold
        hog = {k: ramp(faces[k] - NO_FACE, at[k] - NO_FACE, t.face_sat - NO_FACE) for k in faces}
        view = max(faces, key=lambda k: (hog[k], faces[k]))
        best = faces[view]
        cnn = j.get("cnn", NO_FACE)
        ran = cnn is not None
        cnn = cnn if ran else NO_FACE
        eyes = j.get("eyes", 0)
        # (score, saturation over threshold) of each face cue; the strongest counts
        face, ratio = max((hog[view], (t.face_sat - NO_FACE) / (at[view] - NO_FACE)),
                          (ramp(cnn - NO_FACE, t.cnn - NO_FACE, t.cnn_sat - NO_FACE), (t.cnn_sat - NO_FACE) / (t.cnn - NO_FACE)),
                          (ramp(eyes, t.eyes, t.eyes_sat), t.eyes_sat / t.eyes))
        seen = (f"face detector on {view_name(view)} (yaw {j.get('yaw', {}).get(view, 0):.0f}): score {best:.2f} "
                f"(flag at {at[view]:g})") if best > NO_FACE else "no face found by HOG on the back views"
        seen += (f"; CNN face detector on {view_name(j['back'])}: confidence {cnn:.2f} (flag at {t.cnn:g})"
                 if cnn > NO_FACE else "; none by the CNN on the back view" if ran
                 else "; CNN not run (nothing face-like for HOG or the eye cascade)")
        seen += (f"; a pair of eyes on {view_name(j['back'])} ({eyes} detections each, flag at {t.eyes})" if eyes
                 else "; no pair of eyes on the back view")
        if face > cue.score:
            return Flag(face, f"{seen}; {cue.why}", cue.value, ratio)
        return Flag(cue.score, f"{cue.why}; {seen}", cue.value, cue.ratio)
