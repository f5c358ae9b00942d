"""Automatic pre-flags: each detector on synthetic heads with one injected defect, the report's shape
and order, determinism, that truth/ is never read, and the atomic write of preflags.json.

The detector tests use analytic heads (an ellipsoid with neck, nose, eyes, lips and hair, ray-cast in
numpy) so they run in milliseconds; one end-to-end test renders a tiny procedural dataset.
"""
from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage as ndi

from datagen.errors import DatasetError
from datagen.pipeline import JobSpec, run_sample, software_info
from datagen.dataset.shards import FORMAT as DATASET_FORMAT, iter_tar_samples
from datagen.dataset.shards import ShardWriter, SubjectSample, encode_subject, shard_name, subject_id
from datagen.dataset import Dataset, preflags as report_format
from datagen.runner import Placement
from labeling_tool import preflags
from labeling_tool.preflags.detector import FALSE_ALARM_RATE, ramp_flag
from labeling_tool.preflags.duplicate import nearest
from labeling_tool.preflags.views import SubjectViews

RES = 48
VIEWS = 16
HALF = 0.32          # half the image width in world units (about the procedural framing)
CAMERA = 2.7


# ----------------------------------------------------------------------------------------------
# Analytic heads

def _ellipsoid_hit(o, d, c, r):
    """Nearest t >= 0 where rays o + t d meet the ellipsoid (centre c, radii r); inf where they miss."""
    oc = (o - c) / r
    dd = d / r
    a = (dd * dd).sum(-1)
    b = 2 * (oc * dd).sum(-1)
    cc = (oc * oc).sum(-1) - 1
    disc = b * b - 4 * a * cc
    t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def _cylinder_hit(o, d, c, radius, y0, y1):
    """Vertical cylinder (axis y through c) between heights y0 and y1."""
    ox, oz = o[..., 0] - c[0], o[..., 2] - c[2]
    dx, dz = d[..., 0], d[..., 2]
    a = dx * dx + dz * dz + 1e-12
    b = 2 * (ox * dx + oz * dz)
    cc = ox * ox + oz * oz - radius * radius
    disc = b * b - 4 * a * cc
    t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
    y = o[..., 1] + t * d[..., 1]
    return np.where((disc >= 0) & (t > 0) & (y >= y0) & (y <= y1), t, np.inf)


def make_head(rng, key, views=VIEWS, protocol="360", defect=None, hair_rgb=None):
    """A SubjectSample of an analytic head; defect in (None, 'janus', 'floaters', 'hole', 'see_through',
    'flat_back', 'seam', 'seam_step'); ``hair_rgb`` replaces the drawn hair colour."""
    radii = np.array([0.19, 0.23, 0.22]) * rng.uniform(0.95, 1.05, 3)
    tone = rng.uniform(0.45, 1.0)
    skin = (np.array([0.97, 0.80, 0.69]) * (1 - tone) + np.array([0.33, 0.20, 0.13]) * tone)
    skin = skin * rng.uniform(0.98, 1.02, 3)
    hair = np.array([[0.05, 0.04, 0.04], [0.17, 0.10, 0.06], [0.36, 0.23, 0.13], [0.50, 0.20, 0.09],
                     [0.82, 0.66, 0.40]][rng.integers(5)]) * rng.uniform(0.9, 1.1)
    if hair_rgb is not None:
        hair = np.asarray(hair_rgb, dtype=np.float64)
    light = np.array([rng.uniform(-0.4, 0.4), 0.6, 0.8])
    light /= np.linalg.norm(light)
    hairline = rng.uniform(0.03, 0.1)
    hair_drop = rng.uniform(0.1, 0.3)          # how far the hair comes down at the back
    strands = rng.uniform(40, 120)
    eye_y = rng.uniform(0.02, 0.04)
    if protocol == "360":
        yaw = np.concatenate([np.arange(8) * 45.0, rng.uniform(0, 360, views - 8)])
        pitch = np.concatenate([np.zeros(8), rng.uniform(-20, 20, views - 8)])
    else:
        yaw = rng.uniform(-36, 36, views)
        pitch = rng.uniform(-20, 20, views)
    nose_c = np.array([0.0, -0.02, radii[2] + 0.005])
    blobs = []
    if defect == "floaters":
        for _ in range(3):
            v = rng.normal(size=3)
            v[1] = abs(v[1])
            blobs.append((v / np.linalg.norm(v) * 0.36, 0.035, rng.uniform(0.2, 0.9, 3)))
    u = (np.arange(RES) + 0.5) / RES * 2 - 1
    uu, vv = np.meshgrid(u * HALF, -u * HALF)
    rgb, alpha, depth, records = [], [], [], []
    for yw, pt in zip(yaw, pitch):
        a, e = math.radians(yw), math.radians(pt)
        fwd = -np.array([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)])
        right = np.array([math.cos(a), 0.0, -math.sin(a)])
        up = np.cross(right, fwd)
        o = uu[..., None] * right + vv[..., None] * up - CAMERA * fwd
        d = np.broadcast_to(fwd, o.shape)
        hits = [_ellipsoid_hit(o, d, np.zeros(3), radii),
                _cylinder_hit(o, d, np.array([0.0, 0, -0.02]), 0.09, -0.5, -0.1),
                _ellipsoid_hit(o, d, nose_c, np.array([0.018, 0.03, 0.03]))]
        if defect == "janus":
            hits.append(_ellipsoid_hit(o, d, nose_c * np.array([1, 1, -1]), np.array([0.018, 0.03, 0.03])))
        for c, r, _ in blobs:
            hits.append(_ellipsoid_hit(o, d, c, np.array([r, r, r])))
        t = np.min(np.stack(hits), 0)
        which = np.argmin(np.stack(hits), 0)
        if defect == "flat_back":  # the head cut by the plane z = -0.06: rays meet the plane first
            cut = -0.06
            with np.errstate(divide="ignore", invalid="ignore"):
                t_plane = (cut - o[..., 2]) / d[..., 2]
            behind = (which == 0) & np.isfinite(t) & (o[..., 2] + t * d[..., 2] < cut)
            t = np.where(behind, t_plane, t)
        m = np.isfinite(t)
        p = o + np.where(m, t, 0)[..., None] * d
        n = p / radii ** 2
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        col = np.broadcast_to(skin, p.shape).copy()
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        face_side = [1.0, -1.0] if defect == "janus" else [1.0]
        in_hair = (y > hairline - hair_drop * (z < 0)) & (which == 0)
        if defect == "janus":
            in_hair &= ~((z < 0) & (np.hypot(x / 0.12, (y + 0.01) / 0.14) < 1.0))
        col[in_hair] = hair * (0.8 + 0.2 * np.sin(strands * np.arctan2(x, z) + 8 * y))[in_hair][:, None]
        for side in face_side:
            zs = side * z
            for ex in (-0.07, 0.07):
                eye = (np.hypot(x - ex, y - eye_y) < 0.022) & (zs > 0.1)
                col[eye] = [0.95, 0.95, 0.95]
                col[eye & (np.hypot(x - ex, y - eye_y) < 0.011)] = [0.1, 0.08, 0.06]
            col[(np.abs(x) < 0.04) & (np.abs(y + 0.11) < 0.012) & (zs > 0.1)] = [0.7, 0.2, 0.2]
        for i, (_, _, bc) in enumerate(blobs):
            col[which == 3 + i] = bc
        if defect == "seam":  # the two halves of the back do not meet: one side a shade lighter
            col[(which == 0) & (z < 0) & (x > 0)] = 0.5 * col[(which == 0) & (z < 0) & (x > 0)] + 0.3
        shade = 0.4 + 0.6 * np.clip((n * light).sum(-1), 0, 1)
        col = np.clip(col * shade[..., None], 0, 1)
        dep = np.where(m, CAMERA - (p * -fwd).sum(-1) + 0.0, 0.0)
        if defect == "seam_step":  # one half of the back stands 12 mm out: a step in the surface, same colour
            dep = np.where((which == 0) & (z < 0) & (x > 0), dep - 0.012 * max(0.0, fwd[2]), dep)
        if defect == "hole":
            cdir = np.array([0.0, 0.55, -0.84])
            centre = cdir * radii * 1.0
            vis = (cdir * -fwd).sum()
            if vis > 0.2:
                ci = (centre * right).sum() / HALF, (centre * up).sum() / HALF
                r2 = ((uu / HALF - ci[0]) ** 2 + (vv / HALF - ci[1]) ** 2) / 0.22 ** 2
                bowl = m & (r2 < 1) & (which == 0)
                dep = np.where(bowl, dep + 0.12 * vis * (1 - r2), dep)  # a gross crater (the flag is for those)
                col[bowl] *= 0.45
        a8 = m.astype(np.float64)
        if defect == "see_through" and abs(yw - 90) < 1:
            a8[(np.hypot(uu - 0.0, vv - 0.05) < 0.04)] = 0.0
        bg = 1.0
        img = col * a8[..., None] + bg * (1 - a8[..., None])
        rgb.append(np.clip(np.rint(img * 255), 0, 255).astype(np.uint8))
        alpha.append(np.clip(np.rint(a8 * 255), 0, 255).astype(np.uint8))
        depth.append(np.where(a8 > 0, dep, 0.0).astype(np.float32))
        records.append({"yaw_deg": float(yw), "pitch_deg": float(pt), "radius": CAMERA, "fov_deg": 18.83})
    meta = {"subject_id": key, "views": records, "protocol": protocol, "resolution": RES}
    return SubjectSample(key, meta, rgb, alpha, depth, {})


def washed(s: SubjectSample, strength=0.7) -> SubjectSample:
    rgb = []
    for c, a in zip(s.rgb, s.alpha):
        x = c.astype(np.float64) / 255
        grey = x.mean(-1, keepdims=True)
        y = (1 - strength) * x + strength * (0.25 * grey + 0.75 * 0.93)
        m = (a > 0)[..., None]
        rgb.append(np.clip(np.rint(np.where(m, y, x) * 255), 0, 255).astype(np.uint8))
    return SubjectSample(s.key, s.metadata, rgb, s.alpha, s.depth, {})


def blurred(s: SubjectSample, sigma=1.5) -> SubjectSample:
    rgb = [np.clip(ndi.gaussian_filter(c.astype(np.float64), (sigma, sigma, 0)), 0, 255).astype(np.uint8)
           for c in s.rgb]
    return SubjectSample(s.key, s.metadata, rgb, s.alpha, s.depth, {})


def emptied(s: SubjectSample, views=(3, 9)) -> SubjectSample:
    alpha = [np.zeros_like(a) if i in views else a for i, a in enumerate(s.alpha)]
    rgb = [np.full_like(c, 255) if i in views else c for i, c in enumerate(s.rgb)]
    depth = [np.zeros_like(d) if i in views else d for i, d in enumerate(s.depth)]
    return SubjectSample(s.key, s.metadata, rgb, alpha, depth, {})


def back_views(s: SubjectSample, within=70.0):
    return [i for i, v in enumerate(s.metadata["views"]) if abs((v["yaw_deg"] - 180 + 180) % 360 - 180) <= within]


def blurry_back(s: SubjectSample, sigma=1.6) -> SubjectSample:
    back = set(back_views(s))
    rgb = [np.clip(ndi.gaussian_filter(c.astype(np.float64), (sigma, sigma, 0)), 0, 255).astype(np.uint8)
           if i in back else c for i, c in enumerate(s.rgb)]
    return SubjectSample(s.key, s.metadata, rgb, s.alpha, s.depth, {})


def beside(s: SubjectSample, shape: np.ndarray, grey=150) -> SubjectSample:
    """``shape`` (alpha in [0, 1], RES x RES) drawn opaque-over where the head is not, in every view."""
    alpha, rgb = [], []
    for a, c in zip(s.alpha, s.rgb):
        a0 = a.astype(np.float64) / 255
        a1 = np.maximum(a0, shape * (a0 < 0.5))
        add = (a1 - a0)[..., None]
        rgb.append(np.clip(np.rint(c * (1 - add) + grey * add), 0, 255).astype(np.uint8))
        alpha.append(np.clip(np.rint(a1 * 255), 0, 255).astype(np.uint8))
    return SubjectSample(s.key, s.metadata, rgb, alpha, s.depth, {})


def hazy(s: SubjectSample, level=0.3) -> SubjectSample:
    """A semi-transparent grey cloud beside the head in every view."""
    yy, xx = np.mgrid[:RES, :RES] / RES
    return beside(s, np.clip(1 - np.hypot(xx - 0.85, yy - 0.35) / 0.16, 0, 1) * level)


def face_on_the_back(s: SubjectSample) -> SubjectSample:
    """A photographed face (scikit-image's astronaut) painted over the back views' hair."""
    from PIL import Image
    from skimage import data
    face = Image.fromarray(data.astronaut()[70:190, 165:285])
    rgb = list(s.rgb)
    for i in back_views(s, 50.0):
        m = s.alpha[i] > 127
        rows, cols = np.nonzero(m.any(1))[0], np.nonzero(m.any(0))[0]
        h, w = int(0.62 * (rows[-1] - rows[0])), int(0.62 * (cols[-1] - cols[0]))
        r0, c0 = rows[0] + int(0.12 * (rows[-1] - rows[0])), int(cols.mean() - w / 2)
        patch = np.asarray(face.resize((w, h), Image.BILINEAR))
        img = rgb[i].copy()
        region = img[r0:r0 + h, c0:c0 + w]
        inside = m[r0:r0 + h, c0:c0 + w, None]
        img[r0:r0 + h, c0:c0 + w] = np.where(inside, patch[:region.shape[0], :region.shape[1]], region)
        rgb[i] = img
    return SubjectSample(s.key, s.metadata, rgb, s.alpha, s.depth, {})


def far_away(s: SubjectSample, factor=1.6) -> SubjectSample:
    return SubjectSample(s.key, s.metadata, s.rgb, s.alpha, [d * factor for d in s.depth], {})


def renamed(s: SubjectSample, key: str) -> SubjectSample:
    return SubjectSample(key, dict(s.metadata, subject_id=key), s.rgb, s.alpha, s.depth, {})


def views_of(s: SubjectSample) -> SubjectViews:
    return SubjectViews.from_arrays(s.key, s.metadata, s.alpha, dict(enumerate(s.rgb)), dict(enumerate(s.depth)))


def records(samples):
    return [("shard-000000", preflags.measure_subject(views_of(s))) for s in samples]


def score_samples(samples, false_alarm_rate=None):
    """Scored with each detector at its own threshold (default) or calibrated to ``false_alarm_rate``."""
    report = preflags.score({"index_sha256": "0" * 64, "records": records(samples), "seconds": 1.0},
                            false_alarm_rate=false_alarm_rate)
    return {s["subject"]: s for s in report["subjects"]}, report


@pytest.fixture(scope="module")
def clean_heads():
    rng = np.random.default_rng(11)
    return [make_head(rng, subject_id(i)) for i in range(24)]


def _check(clean_heads, bad, detector):
    by_key, _ = score_samples(clean_heads + [bad])
    got = by_key[bad.key]
    assert got["detectors"][detector]["score"] >= 0.5, got["detectors"][detector]
    assert detector in got["flags"]
    for s in clean_heads:
        d = by_key[s.key]["detectors"][detector]
        assert d["score"] < 0.5, (s.key, d)
    return got


# ----------------------------------------------------------------------------------------------
# Each detector flags its synthetic defect and not the clean heads

@pytest.mark.parametrize("rate", [None, FALSE_ALARM_RATE])
def test_clean_heads_are_not_flagged(clean_heads, rate):
    by_key, report = score_samples(clean_heads, rate)
    assert all(not s["flags"] for s in by_key.values()), [(k, s["flags"]) for k, s in by_key.items() if s["flags"]]
    assert report["summary"]["flagged"] == 0
    assert report["calibration"]["false_alarm_rate"] == rate
    cuts = [d["calibrated_cut"] for d in report["detectors"].values()]
    assert all(c >= 1.0 for c in cuts) and (rate is not None or cuts == [1.0] * len(cuts))
    shares = [d["false_alarm_share"] for d in report["detectors"].values()]
    assert shares == [None] * len(shares) if rate is None else 0.0 <= min(shares) and sum(shares) <= rate + 1e-5


# ----------------------------------------------------------------------------------------------
# Calibrating the union of detectors: a stated share of clean subjects flagged on any dataset

class _NullDetector(preflags.Detector):
    """A detector whose measure is a number drawn from a null: robust z against the dataset, flag at 3."""

    def __init__(self, name):
        super().__init__()
        self.name = name

    def baseline(self, measured):
        from labeling_tool.preflags.imaging import robust
        return robust([m["x"] for m in measured if m], 1e-9)

    def score(self, m, base, index, keys):
        z = (m["x"] - base[0]) / base[1]
        return ramp_flag(z, 3.0, 8.0, f"z {z:.1f}", z)


NULLS = {"laplace": lambda rng, n: rng.laplace(size=n), "t5": lambda rng, n: rng.standard_t(5, size=n),
         "gamma2": lambda rng, n: rng.gamma(2.0, size=n), "normal": lambda rng, n: rng.normal(size=n),
         "point": lambda rng, n: np.zeros(n)}


def _null_report(draws, n, seed, rate, outliers=0):
    """The report of ``n`` synthetic subjects, one detector per entry of ``draws`` (NULLS keys); the first
    ``outliers`` subjects lie 40 null scales above the median on every detector."""
    rng = np.random.default_rng(seed)
    dets = [_NullDetector(f"d{k}") for k in range(len(draws))]
    xs = {d.name: NULLS[kind](rng, n) for d, kind in zip(dets, draws)}
    for x in xs.values():
        x[:outliers] = np.median(x) + 40.0 * np.median(np.abs(x - np.median(x)))
    recs = [("shard-000000", {"key": f"s{i:05d}", "measured": {name: {"x": float(x[i])} for name, x in xs.items()}})
            for i in range(n)]
    return preflags.score({"index_sha256": "0" * 64, "records": recs, "seconds": 1.0}, dets, false_alarm_rate=rate)


@pytest.mark.parametrize("draws", [("laplace",) * 12, ("laplace", "t5", "gamma2", "normal") * 3,
                                   ("laplace", "point") * 6])
def test_union_false_alarm_share_stays_near_the_stated_rate(draws):
    """Twelve nulls, each flagged at its own z 3: heavy tails make the union flag a tenth to a quarter of
    clean subjects; calibrated, about FALSE_ALARM_RATE (exact for Laplace nulls, less for lighter tails),
    at any size. Detectors that find nothing on clean subjects hand their shares to the others, so six
    Laplace nulls beside six point masses still use the whole rate, not half of it."""
    rate = FALSE_ALARM_RATE
    for n, seeds in ((64, range(20)), (300, range(4)), (3000, range(1))):
        own = np.mean([_null_report(draws, n, s, None)["summary"]["flagged"] / n for s in seeds])
        union = np.mean([_null_report(draws, n, s, rate)["summary"]["flagged"] / n for s in seeds])
        assert own > 0.1, (n, own)
        assert union <= 1.3 * rate, (n, union)
        if "t5" not in draws:
            assert union >= 0.7 * rate, (n, union)


def test_calibration_keeps_strong_defects_flagged():
    """10 % of subjects far out on every detector: they widen nothing (censored) and stay flagged."""
    report = _null_report(("laplace", "t5") * 6, 200, 7, FALSE_ALARM_RATE, outliers=20)
    flagged = {s["subject"] for s in report["subjects"] if s["flags"]}
    assert {f"s{i:05d}" for i in range(20)} <= flagged
    assert len(flagged) - 20 <= 0.05 * 180


def test_other_detectors_defects_leave_the_null_fit():
    """Five other detectors each flag their defect on 5 % of the subjects, and those defects also raise
    detector 0's measure (they fill its top quarter): fitted to every subject, detector 0's cut rises by
    half and misses its own defect at evidence 2.3; fitted without the subjects the others flag, it
    stays where the clean dataset has it."""
    from labeling_tool.preflags.detector import calibrated_cut, calibrated_cuts

    rng = np.random.default_rng(0)
    clean = np.maximum(rng.laplace(size=(400, 6)), 0.0) / 3.0
    dirty = clean.copy()
    for j in range(1, 6):
        dirty[20 * (j - 1):20 * j, j] = 4.0
    dirty[:100, 0] += rng.uniform(0.3, 0.9, 100)
    base = calibrated_cuts(clean, clean >= 1.0, FALSE_ALARM_RATE)[0][0]
    assert calibrated_cut(dirty[:, 0], FALSE_ALARM_RATE / 6) > max(1.5 * base, 2.3)
    cuts, shares = calibrated_cuts(dirty, dirty >= 1.0, FALSE_ALARM_RATE)
    assert abs(cuts[0] - base) < 0.1 * base and cuts[0] < 2.3
    assert np.allclose(shares, FALSE_ALARM_RATE / 6)
    assert calibrated_cuts(dirty, dirty >= 1.0, FALSE_ALARM_RATE, [False] + [True] * 5)[0][0] == 1.0


class _LevelDetector(preflags.Detector):
    """A detector whose measure ``x`` is its evidence (threshold 1, saturated at 20); 0: nothing found."""

    def __init__(self, name):
        super().__init__()
        self.name = name

    def score(self, m, base, index, keys):
        return ramp_flag(m["x"], 1.0, 20.0, f"x {m['x']:.2f}", m["x"]) if m["x"] > 0 else preflags.Flag(0.0, "none")


def test_point_mass_detector_keeps_its_threshold_beside_other_defects():
    """A detector that finds nothing on clean subjects (detached parts): 15 % of the subjects carry one of
    three other detectors' defects, which it also sees a little of (0.1 to 0.9 of its threshold), 3 % its
    own at 1.5 to 2.5. Its cut stays its own threshold, it flags exactly its own defects and hands its share
    of the false-alarm rate to the others."""
    from labeling_tool.preflags.detector import calibrated_cut

    rng = np.random.default_rng(4)
    n = 200
    x = {"point": np.zeros(n), **{f"other{j}": np.maximum(rng.laplace(size=n), 0.0) / 3.0 for j in range(3)}}
    x["point"][:30] = rng.uniform(0.1, 0.9, 30)
    for j in range(3):
        x[f"other{j}"][10 * j:10 * (j + 1)] = rng.uniform(3.0, 6.0, 10)
    x["point"][30:36] = rng.uniform(1.5, 2.5, 6)
    dets = [_LevelDetector(name) for name in x]
    recs = [("shard-000000", {"key": f"s{i:05d}", "measured": {name: {"x": float(v[i])} for name, v in x.items()}})
            for i in range(n)]
    report = preflags.score({"index_sha256": "0" * 64, "records": recs, "seconds": 1.0}, dets,
                            false_alarm_rate=FALSE_ALARM_RATE)
    head = report["detectors"]
    assert head["point"]["calibrated_cut"] == 1.0 and head["point"]["false_alarm_share"] == 0.0
    assert all(head[f"other{j}"]["false_alarm_share"] == FALSE_ALARM_RATE / 3 for j in range(3))
    assert {s["subject"] for s in report["subjects"] if "point" in s["flags"]} == {f"s{i:05d}" for i in range(30, 36)}
    assert (x["point"][30:36] >= calibrated_cut(x["point"], FALSE_ALARM_RATE / 4)).sum() == 0  # fitted to all


def test_calibrated_cut_and_rescoring():
    from labeling_tool.preflags.detector import MIN_SUBJECTS, calibrated_cut, evidence, recalibrated

    tail = 0.0025
    assert calibrated_cut(np.zeros(500), tail) == 1.0                 # a point mass keeps the own threshold
    assert calibrated_cut([0.0] * 450 + [5.0] * 50, tail) == 1.0      # nothing between median and 90th pct
    assert calibrated_cut(np.linspace(0, 9, MIN_SUBJECTS - 1), tail) == 1.0
    x = np.abs(np.random.default_rng(3).laplace(size=200000)) * np.sign(np.arange(200000) % 2 - 0.5)
    exact = np.log(0.5 / tail)                                         # Laplace: P(x > q) = exp(-q) / 2
    assert abs(calibrated_cut(np.maximum(x, 0.0), tail) - exact) < 0.1
    assert abs(calibrated_cut(np.maximum(np.append(x, [np.inf, np.nan, 1e9] * 10), 0.0), tail) - exact) < 0.1
    f = ramp_flag(6.0, 3.0, 8.0, "")                                  # evidence 2, ratio 8/3
    assert abs(evidence(f.score, f.ratio) - 2.0) < 1e-9
    assert recalibrated(f, 1.0) == f.score
    assert recalibrated(f, 2.0) == 0.5 and recalibrated(f, 2.5) < 0.5 < recalibrated(f, 1.5)
    assert recalibrated(ramp_flag(99.0, 3.0, 8.0, ""), 50.0) >= 0.5  # saturated: stays flagged
    assert recalibrated(preflags.Flag(0.7, "not a ramp"), 3.0) == 0.7


def test_janus_cue_needs_more_than_one_measure():
    """A bump on a smooth back alone (relief z ~9) is not a face; edges, colour and bump together are."""
    from labeling_tool.preflags.janus import Janus

    det = Janus()
    base = {"sim": (0.10, 0.05), "colour": (0.20, 0.05), "relief": (math.log(1e-4), 0.5)}
    bump = {"back": 4, "front": 0, "sim": 0.10, "colour": 0.20, "relief": 0.01, "faces": {}}
    assert det.score(bump, base, 0, []).score < 0.5
    face = dict(bump, sim=0.30, colour=0.40)
    assert det.score(face, base, 0, []).score >= 0.5


def test_janus(clean_heads):
    bad = make_head(np.random.default_rng(101), "subj99999990", defect="janus")
    got = _check(clean_heads, bad, "janus")
    assert "back view v04" in got["detectors"]["janus"]["why"]


def test_floaters(clean_heads):
    bad = make_head(np.random.default_rng(102), "subj99999991", defect="floaters")
    got = _check(clean_heads, bad, "floaters")
    assert "detached" in got["detectors"]["floaters"]["why"]


def test_crater(clean_heads):
    bad = make_head(np.random.default_rng(103), "subj99999992", defect="hole")
    got = _check(clean_heads, bad, "holes")
    assert "depression" in got["detectors"]["holes"]["why"]


def test_crater_seen_from_both_mirrored_sides_is_not_a_crater():
    """A dip the yaw 45 and yaw 315 views both show (a hairline at the temples) cancels; one side alone
    flags, and so does a dip on the back view, which is its own mirror."""
    from labeling_tool.preflags.holes import Holes

    det = Holes()
    base = {b: (0.0, 0.002) for b in range(8)}
    no_silhouette_holes = np.zeros(8, np.float32)

    def score(*craters):
        return det.score({"silhouette": no_silhouette_holes, "craters": list(craters)}, base, 0, [])

    left, right, back = (1, 45.0, 0.012, (0.3, 0.4)), (7, 315.0, 0.011, (0.3, 0.6)), (4, 180.0, 0.008, (0.3, 0.5))
    both = score(left, right, (4, 180.0, 0.0, (0.3, 0.5)))
    assert both.score < 0.5 and both.value == pytest.approx(0.5)  # z 6 less the mirror's 5.5
    one = score(left, (7, 315.0, 0.0, (0.3, 0.6)))
    assert one.score >= 0.5 and one.value == pytest.approx(6.0) and "v01" in one.why and "mirrored view v07" in one.why
    assert score(back, (0, 0.0, 0.0, (0.3, 0.5))).value == pytest.approx(4.0)


def test_see_through_hole(clean_heads):
    bad = make_head(np.random.default_rng(104), "subj99999993", defect="see_through")
    got = _check(clean_heads, bad, "holes")
    assert "see-through" in got["detectors"]["holes"]["why"]


def test_washed_out(clean_heads):
    bad = washed(make_head(np.random.default_rng(105), "subj99999994"))
    _check(clean_heads, bad, "washed_out")


def test_grey_hair_is_not_washed_out(clean_heads):
    grey = [make_head(np.random.default_rng(200 + k), f"subj9999990{k}", hair_rgb=[0.78, 0.77, 0.76]) for k in range(2)]
    by_key, _ = score_samples(clean_heads + grey)
    assert all("washed_out" not in by_key[g.key]["flags"] for g in grey), [by_key[g.key]["detectors"]["washed_out"] for g in grey]
    by_key, _ = score_samples(clean_heads + [washed(grey[0])])
    assert "washed_out" in by_key[grey[0].key]["flags"]


def test_blur(clean_heads):
    bad = blurred(make_head(np.random.default_rng(106), "subj99999995"))
    _check(clean_heads, bad, "blur")


def test_empty_views(clean_heads):
    bad = emptied(make_head(np.random.default_rng(107), "subj99999996"))
    got = _check(clean_heads, bad, "empty")
    assert "2 of 16 views empty (v03, v09)" in got["detectors"]["empty"]["why"]


def test_implausible_depth(clean_heads):
    bad = far_away(make_head(np.random.default_rng(108), "subj99999997"))
    got = _check(clean_heads, bad, "implausible")
    assert "median depth" in got["detectors"]["implausible"]["why"]


def test_duplicate(clean_heads):
    copy = renamed(clean_heads[5], "subj99999998")
    by_key, _ = score_samples(clean_heads + [copy])
    for key in (copy.key, clean_heads[5].key):
        assert "duplicate" in by_key[key]["flags"]
    assert clean_heads[5].key in by_key[copy.key]["detectors"]["duplicate"]["why"]
    others = [k for k in by_key if k not in (copy.key, clean_heads[5].key)]
    assert all("duplicate" not in by_key[k]["flags"] for k in others)


def test_flat_back(clean_heads):
    bad = make_head(np.random.default_rng(109), "subj99999980", defect="flat_back")
    got = _check(clean_heads, bad, "flat_back")
    assert "back view v04" in got["detectors"]["flat_back"]["why"]


def test_seam(clean_heads):
    bad = make_head(np.random.default_rng(110), "subj99999981", defect="seam")
    got = _check(clean_heads, bad, "seam")
    assert "centre columns" in got["detectors"]["seam"]["why"]


def test_seam_step_in_the_surface(clean_heads):
    bad = make_head(np.random.default_rng(112), "subj99999978", defect="seam_step")
    got = _check(clean_heads, bad, "seam")
    assert "px in depth down the centre" in got["detectors"]["seam"]["why"]


def test_depth_step_measures_the_step_not_the_curve():
    from labeling_tool.preflags.back import depth_step

    n, focal_px, dist = 64, 272.0, 2.5
    y, x = np.mgrid[0:n, 0:n] - (n - 1) / 2
    mask = x ** 2 + y ** 2 < 26 ** 2
    pixel = dist / focal_px
    sphere = dist - np.sqrt(np.clip((26 * pixel) ** 2 - (x * pixel) ** 2 - (y * pixel) ** 2, 0, None))
    assert depth_step(mask, np.where(mask, sphere, 0), focal_px) < 0.1
    for shift in (0.0, 2.0):  # the step on the centre column, or two columns off it
        stepped = sphere - 0.6 * pixel * (x > shift)
        assert abs(depth_step(mask, np.where(mask, stepped, 0), focal_px) - 0.6) < 0.1
    assert depth_step(mask, np.where(mask, sphere - 0.6 * pixel * (x > 12), 0), focal_px) < 0.1  # not the centre


def test_blurry_back(clean_heads):
    bad = blurry_back(make_head(np.random.default_rng(111), "subj99999982"))
    got = _check(clean_heads, bad, "blurry_back")
    assert "front views' sharpness (around v00" in got["detectors"]["blurry_back"]["why"]
    assert "blur" not in got["flags"]  # the front is sharp: it is the back that is blurred


def test_blurry_back_soft_outline(clean_heads):
    """A soft density over the back widens the back views' outline (the colour follows the alpha)."""
    s = make_head(np.random.default_rng(113), "subj99999979")
    back = set(back_views(s, within=50.0))
    alpha = [np.clip(ndi.gaussian_filter(a.astype(np.float64), 1.5), 0, 255).astype(np.uint8) if i in back else a
             for i, a in enumerate(s.alpha)]
    rgb = list(s.rgb)
    for i in back:  # recomposite over white: the head's colour (nearest opaque pixel) times the new alpha
        near = ndi.distance_transform_edt(s.alpha[i] < 255, return_distances=False, return_indices=True)
        fg = s.rgb[i][tuple(near)].astype(np.float64)
        a = alpha[i][..., None] / 255.0
        rgb[i] = np.clip(np.rint(fg * a + 255.0 * (1 - a)), 0, 255).astype(np.uint8)
    got = _check(clean_heads, SubjectSample(s.key, s.metadata, rgb, alpha, s.depth, {}), "blurry_back")
    assert "outline (around v" in got["detectors"]["blurry_back"]["why"]


def test_alpha_edge_width_grows_with_a_soft_outline():
    from labeling_tool.preflags.blur import alpha_edge_width

    yy, xx = np.mgrid[:128, :128]
    disc = np.clip(40.5 - np.hypot(yy - 64, xx - 64), 0, 1) * 255  # a crisp, anti-aliased disc
    widths = [alpha_edge_width(ndi.gaussian_filter(disc, sigma)) for sigma in (0.01, 1.0, 2.5)]
    assert widths[0] < 2.5 and widths[0] < widths[1] < widths[2], widths
    assert np.isnan(alpha_edge_width(np.zeros((64, 64))))
    speck = np.zeros((64, 64))
    speck[30:32, 30:32] = 255
    assert np.isnan(alpha_edge_width(speck))  # too short an outline


def test_haze(clean_heads):
    bad = hazy(make_head(np.random.default_rng(112), "subj99999983"))
    got = _check(clean_heads, bad, "haze")
    assert "floaters" not in got["flags"]  # semi-transparent, attached to nothing opaque


def test_opaque_wisps_are_haze_and_a_detached_blob_is_not(clean_heads):
    """Thin opaque arcs beside the head (wisps dense enough to count as solid) flag haze by their thin
    material away from the head's body; an opaque disc there is a floater, not haze."""
    yy, xx = (np.mgrid[:RES, :RES] + 0.5) / RES
    ring = np.abs(np.hypot(xx - 0.86, yy - 0.35) - 0.11) < 0.6 / RES
    arcs = (ring & (xx > 0.84)).astype(np.float64)
    got = _check(clean_heads, beside(make_head(np.random.default_rng(114), "subj99999982"), arcs), "haze")
    assert "thin material (wisps)" in got["detectors"]["haze"]["why"]
    disc = (np.hypot(xx - 0.9, yy - 0.3) < 4.5 / RES).astype(np.float64)
    by_key, _ = score_samples(clean_heads + [beside(make_head(np.random.default_rng(115), "subj99999981"), disc)])
    blob = by_key["subj99999981"]
    assert blob["detectors"]["haze"]["score"] < 0.5 and "floaters" in blob["flags"], blob["detectors"]["haze"]


def test_face_detector_finds_a_photographed_face_on_the_back(clean_heads):
    bad = face_on_the_back(make_head(np.random.default_rng(113), "subj99999984"))
    got = _check(clean_heads, bad, "janus")
    assert "face detector on v0" in got["detectors"]["janus"]["why"]


def test_head_crop_is_the_head_not_the_shoulders():
    from labeling_tool.preflags.janus import head_crop, head_extent

    yy, xx = np.mgrid[:128, :128]
    mask = (yy - 45) ** 2 + (xx - 64) ** 2 < 30 ** 2          # a head: columns 35-93, rows 16-74
    mask |= (yy > 90) & (np.abs(xx - 64) < 60)                # shoulders 119 px wide, to the frame (row 127)
    rgb = np.dstack([xx, yy, np.zeros_like(xx)]).astype(np.uint8)
    assert head_extent(mask) == (16, 112, 35, 93)
    crop = head_crop(rgb, mask)
    pad = int(0.06 * 128)
    assert crop[0, 0, 0] == 35 - pad and crop[0, -1, 0] == 93 + pad  # columns of the head, with the margin
    assert crop[0, 0, 1] == 16 - pad and crop.shape[0] == pad + int(0.8 * 112)  # top 80 % of 112 rows
    assert head_crop(rgb, np.zeros_like(mask)).shape == rgb.shape  # nothing to crop to: the whole view


def test_eye_pair_where_a_face_has_its_eyes():
    """A photographed face on a textured back view shows a pair of eyes; the same face low on the head
    (eyes below 60 % of the silhouette) and the texture alone do not; a pair flags the subject."""
    from PIL import Image
    from skimage import data

    from labeling_tool.preflags.janus import Janus, eye_pair

    face = Image.fromarray(data.astronaut()[70:190, 165:285]).resize((56, 56), Image.BILINEAR)
    yy, xx = np.mgrid[:128, :128]
    mask = ((yy - 60) / 48.0) ** 2 + ((xx - 64) / 40.0) ** 2 < 1
    hair = np.clip(0.3 + 0.05 * np.random.default_rng(0).standard_normal((128, 128, 1)), 0, 1) * [0.8, 0.6, 0.4]
    back = (np.where(mask[..., None], hair, 1.0) * 255).astype(np.uint8)

    def with_face(row):
        img = back.copy()
        img[row:row + 56, 36:92] = np.asarray(face)
        return img

    assert eye_pair(back, mask) == 0
    assert eye_pair(with_face(26), mask) >= 8
    assert eye_pair(with_face(70), mask) == 0
    # Given the front view's face colour, a pair counts only with skin of that colour between the eyes.
    skin = np.median(np.asarray(face)[30:40, 20:36].reshape(-1, 3), 0)
    assert eye_pair(with_face(26), mask, skin) >= 8
    assert eye_pair(with_face(26), mask, np.array([60.0, 90.0, 200.0])) == 0
    base = {"sim": (0.10, 0.05), "colour": (0.20, 0.05), "relief": (math.log(1e-4), 0.5)}
    record = {"back": 4, "front": 0, "sim": 0.10, "colour": 0.20, "relief": 1e-4, "faces": {4: -1.0}, "cnn": -1.0}
    assert Janus().score(dict(record, eyes=1), base, 0, []).score < 0.5
    flag = Janus().score(dict(record, eyes=3), base, 0, [])
    assert flag.score >= 0.5 and "a pair of eyes on v04 (3 detections each" in flag.why


def test_cnn_runs_only_where_the_cheap_face_cues_see_something():
    """face_like opens where HOG scores above the gate on any back view or the eye pair reaches its gate, not
    on hair's faint HOG responses or a single eye detection; a record whose CNN was not run scores as one
    where the CNN found nothing, and its explanation says the CNN was not run."""
    from labeling_tool.preflags.janus import NO_FACE, Janus, face_like

    gate = Janus.Settings()
    at = (gate.cnn_gate_face, gate.cnn_gate_eyes)
    assert not face_like({3: NO_FACE, 4: NO_FACE, 5: NO_FACE}, 0, *at) and not face_like({}, 0, *at)
    assert not face_like({3: NO_FACE, 4: -0.64}, 1, *at)  # a clean back's hair (tuning seed 41)
    assert face_like({3: -0.57, 4: -0.95}, 0, *at) and face_like({4: NO_FACE}, 3, *at)  # janus (tuning seed 4)
    base = {"sim": (0.10, 0.05), "colour": (0.20, 0.05), "relief": (math.log(1e-4), 0.5)}
    record = {"back": 4, "front": 0, "sim": 0.30, "colour": 0.20, "relief": 1e-4, "faces": {4: NO_FACE}, "eyes": 0}
    skipped, empty = Janus().score(dict(record, cnn=None), base, 0, []), Janus().score(dict(record, cnn=NO_FACE), base, 0, [])
    assert (skipped.score, skipped.value, skipped.ratio) == (empty.score, empty.value, empty.ratio) and skipped.score > 0
    assert "CNN not run" in skipped.why and "none by the CNN" in empty.why


def test_opencv_masks_match_scipys():
    """fill_holes, label and farther_than (OpenCV's labelling and exact distance transform) give scipy's
    results (label: the same numbers in the same order, 4- and 8-connected), regions touching the image's
    edge included; farther_than at the radii the haze detector uses (3 px at 64 px for 96 to 512 px) and
    at a radius between pixels."""
    from labeling_tool.preflags.imaging import farther_than, fill_holes, label

    rng = np.random.default_rng(3)
    for _ in range(40):
        h, w = rng.integers(8, 120, 2)
        region = ndi.gaussian_filter(rng.random((h, w)), 2.0) > 0.52
        assert np.array_equal(fill_holes(region), ndi.binary_fill_holes(region))
        for eight, structure in ((False, None), (True, np.ones((3, 3), bool))):
            want, n = ndi.label(region, structure=structure)
            got, m = label(region, eight)
            assert m == n and np.array_equal(got, want)
        if not region.any():
            continue
        candidates = rng.random((h, w)) < 0.8
        for r in (4.5, 6.0, 12.0, 24.0, 2.3):
            want = candidates & (ndi.distance_transform_edt(~region) > r)
            assert np.array_equal(farther_than(region, candidates, r), want)


def test_back_diagonal_views_need_a_full_face_detection():
    """On the back view a partial face (HOG -0.2) flags; on a back-diagonal view, where the real face's
    cheek and nose show at the edge, the same score does not, and a full detection (0.3) does."""
    from labeling_tool.preflags.janus import Janus

    base = {"sim": (0.10, 0.05), "colour": (0.20, 0.05), "relief": (math.log(1e-4), 0.5)}
    record = {"back": 4, "front": 0, "sim": 0.10, "colour": 0.20, "relief": 1e-4, "cnn": -1.0, "eyes": 0}
    assert Janus().score(dict(record, faces={4: -0.2, 5: -1.0}), base, 0, []).score >= 0.5
    assert Janus().score(dict(record, faces={4: -1.0, 5: -0.2}), base, 0, []).score < 0.5
    flag = Janus().score(dict(record, faces={4: -0.9, 5: 0.3}), base, 0, [])
    assert flag.score >= 0.5 and "face detector on v05" in flag.why and "flag at 0)" in flag.why


def test_robust_below_ignores_what_defects_add_above():
    """The scale of a feature that defects only raise comes from the subjects below the median: clean
    subjects alone give their sigma; with a quarter of the subjects far above, the scale grows less than
    a two-sided MAD does (only through the median's shift)."""
    from labeling_tool.preflags.imaging import robust, robust_below

    clean = np.random.default_rng(0).normal(1.0, 0.1, 300)
    mixed = np.concatenate([clean, np.full(100, 3.0)])
    assert 0.08 < robust_below(clean, 1e-3)[1] < 0.12
    assert robust_below(mixed, 1e-3)[1] < 0.9 * robust(mixed, 1e-3)[1]
    assert robust_below([], 0.05) == (0.0, 0.05) and robust_below([2.0, 2.0], 0.05) == (2.0, 0.05)


def test_janus_not_applicable_without_back_views():
    rng = np.random.default_rng(5)
    heads = [make_head(rng, subject_id(i), protocol="frontal") for i in range(6)]
    by_key, _ = score_samples(heads)
    for s in by_key.values():
        assert s["detectors"]["janus"]["score"] == 0.0
        assert "not applicable" in s["detectors"]["janus"]["why"]


def _shifted(x, dy, dx):
    """x moved by (dy, dx) px, zero where nothing moves in (no wrap-around)."""
    out = np.zeros_like(x)
    h, w = x.shape[:2]
    out[max(dy, 0):h + min(dy, 0), max(dx, 0):w + min(dx, 0)] = x[max(-dy, 0):h + min(-dy, 0), max(-dx, 0):w + min(-dx, 0)]
    return out


def _pearson(x, y):
    x, y = x - x.mean(0), y - y.mean(0)
    den = math.sqrt(float((x * x).sum() * (y * y).sum()))
    return float((x * y).sum() / den) if den > 0 else None


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_shifted_ncc_matches_its_definition_at_the_image_edges(seed):
    """janus's edge and colour correlations (cv2.matchTemplate) against a per-shift numpy loop, with masks
    that run into the image edges: nothing wraps around."""
    from labeling_tool.preflags.janus import colour_ncc, edge_ncc
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:40, :44]
    a_c, b_c = (ndi.gaussian_filter(rng.random((40, 44, 3)), (1.5, 1.5, 0)) for _ in range(2))
    a_m = np.hypot(yy - rng.uniform(0, 40), xx - rng.uniform(0, 8)) < 24       # against the left edge
    b_m = np.hypot(yy - rng.uniform(0, 40), xx - rng.uniform(36, 44)) < 24     # against the right edge
    ga, gb = (np.hypot(ndi.sobel(g, 0), ndi.sobel(g, 1)) for g in (a_c.mean(-1), b_c.mean(-1)))
    ia, ib = (ndi.binary_erosion(m, iterations=2) for m in (a_m, b_m))
    region = a_m & b_m
    edge, colour = [], []
    for dy in range(-3, 4):
        for dx in range(-3, 4):
            m = ia & _shifted(ib, -dy, -dx)
            edge.append(_pearson(ga[m], _shifted(gb, -dy, -dx)[m]) if m.sum() >= 20 else None)
            colour.append(_pearson(_shifted(a_c, -dy, -dx)[region], b_c[region]))
    assert edge_ncc(a_c.mean(-1), a_m, b_c.mean(-1), b_m, 1.0) == pytest.approx(max(filter(None, edge)), abs=1e-4)
    assert colour_ncc(a_c, b_c, region, 1.0) == pytest.approx(max(filter(None, colour)), abs=1e-4)


def test_undecodable_subject_is_flagged_not_dropped(clean_heads):
    recs = records(clean_heads[:4])
    error = "x.tar: subject subj00000099 lacks field 'v00.png'"
    recs.append(("shard-000000", {"key": "subj00000099", "error": error}))
    report = preflags.score({"index_sha256": "0" * 64, "records": recs, "seconds": 1.0})
    assert report["subjects"][0]["subject"] == "subj00000099"
    assert report["subjects"][0]["flags"] == ["empty"]
    assert len(report["subjects"]) == 5


def test_duplicates_blocked_matches_dense():
    rng = np.random.default_rng(0)
    thumbs = [rng.normal(size=16).astype(np.float32) for _ in range(37)]
    thumbs[30] = thumbs[3] + 0.01
    thumbs[7] = None
    small = nearest(thumbs, 5)
    big = nearest(thumbs, 4096)
    np.testing.assert_allclose(small[0], big[0], rtol=1e-5)
    assert list(small[1]) == list(big[1])
    assert small[1][30] == 3 and small[1][3] == 30 and small[1][7] == -1


# ----------------------------------------------------------------------------------------------
# Whole datasets on disk

def write_dataset(root: Path, samples, shard_size=8, truth=None):
    """A dataset folder in the panolam-heads layout from in-memory samples (hidden truth included)."""
    root.mkdir(parents=True)
    shards = []
    for i in range(0, len(samples), shard_size):
        w = ShardWriter(root, i // shard_size)
        keys = []
        for s in samples[i:i + shard_size]:
            meta = dict(s.metadata)
            members = encode_subject(meta, np.stack(s.rgb).astype(np.float32) / 255,
                                     np.stack(s.alpha).astype(np.float32) / 255, np.stack(s.depth))
            w.add_subject(s.key, members, (truth or {}).get(s.key, {"defects": []}))
            keys.append(s.key)
        w.commit()
        shards.append({"name": shard_name(i // shard_size), "subjects": keys})
    index = {"format": DATASET_FORMAT, "num_subjects": len(samples), "shards": shards, "settings": {},
             "generator": {"name": "synthetic"}, "views_per_subject": len(samples[0].rgb)}
    (root / "index.json").write_text(json.dumps(index, indent=1, sort_keys=True) + "\n")
    return root


@pytest.fixture(scope="module")
def synthetic_dataset(tmp_path_factory, clean_heads):
    rng = np.random.default_rng(3)
    bad = [make_head(rng, "subj00000100", defect="floaters"), washed(make_head(rng, "subj00000101")),
           make_head(rng, "subj00000102", defect="janus")]
    truth = {"subj00000100": {"defects": [{"type": "floaters"}]}, "subj00000101": {"defects": [{"type": "washed_out"}]},
             "subj00000102": {"defects": [{"type": "janus"}]}}
    root = tmp_path_factory.mktemp("preflags") / "ds"
    return write_dataset(root, clean_heads[:16] + bad, shard_size=7, truth=truth)


def strip_timing(report):
    return {k: v for k, v in report.items() if k != "timing"}


def test_report_shape_and_order(synthetic_dataset):
    report = preflags.score_dataset(synthetic_dataset)
    assert report["format"] == "panolam-preflags/1"
    import hashlib
    assert report["dataset_index_sha256"] == hashlib.sha256((synthetic_dataset / "index.json").read_bytes()).hexdigest()
    assert set(report["detectors"]) == set(preflags.DETECTOR_NAMES)
    assert all(d["threshold"] == 0.5 and d["description"] for d in report["detectors"].values())
    subjects = report["subjects"]
    assert len(subjects) == 19
    scores = [s["score"] for s in subjects]
    assert scores == sorted(scores, reverse=True)
    for s in subjects:
        assert set(s["detectors"]) == set(preflags.DETECTOR_NAMES)
        assert s["shard"].startswith("shard-")
        for d in s["detectors"].values():
            assert 0.0 <= d["score"] <= 1.0 and isinstance(d["why"], str) and d["why"]
        assert s["score"] == max(d["score"] for d in s["detectors"].values())
        assert s["flags"] == [n for n in preflags.DETECTOR_NAMES if s["detectors"][n]["score"] >= 0.5]
    worst = {s["subject"] for s in subjects[:3]}
    assert worst == {"subj00000100", "subj00000101", "subj00000102"}
    flags = {s["subject"]: s["flags"] for s in subjects}
    assert "floaters" in flags["subj00000100"]
    assert "washed_out" in flags["subj00000101"]
    assert "janus" in flags["subj00000102"]
    assert report["timing"]["subjects_per_second"] > 0


def test_deterministic_and_workers_agree(synthetic_dataset):
    a = preflags.score_dataset(synthetic_dataset)
    b = preflags.score_dataset(synthetic_dataset)
    c = preflags.score_dataset(synthetic_dataset, placement=Placement(("cpu", "cpu")))
    assert strip_timing(a) == strip_timing(b) == strip_timing(c)


def test_truth_folder_is_never_read(synthetic_dataset, tmp_path, monkeypatch):
    before = preflags.score_dataset(synthetic_dataset)
    copy = tmp_path / "copy"
    shutil.copytree(synthetic_dataset, copy, ignore=shutil.ignore_patterns("truth"))
    assert not (copy / "truth").exists()
    opened = []
    real_open = open

    def spy(file, *args, **kwargs):
        opened.append(str(file))
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr("builtins.open", spy)
    after = preflags.score_dataset(synthetic_dataset)
    monkeypatch.undo()
    assert not [p for p in opened if "truth" in Path(p).parts]
    assert strip_timing(after) == strip_timing(before)
    assert strip_timing(preflags.score_dataset(copy)) == strip_timing(before)


def test_workers_read_subjects_by_byte_range(synthetic_dataset):
    """What a worker reads through the sidecar's byte range equals a full scan of the tar."""
    tasks, skipped = preflags.scoring.plan(Dataset(synthetic_dataset))
    assert skipped == [] and len(tasks) == 19
    scanned = {}
    for i in range(3):
        scanned.update(dict(iter_tar_samples(synthetic_dataset / f"shard-00000{i}.tar")))
    for shard, tar, key, start, end in tasks:
        from datagen.dataset.shards import read_range
        assert read_range(tar, key, start, end) == scanned[key]


def test_incomplete_shards_are_named_not_skipped(synthetic_dataset, tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(synthetic_dataset, root)
    (root / "shard-000001.json").unlink()
    with pytest.raises(DatasetError, match=r"shard-000001.tar: incomplete \(no sidecar shard-000001.json\).*--skip-incomplete"):
        preflags.score_dataset(root)
    report = preflags.score_dataset(root, skip_incomplete=True)
    assert report["summary"]["skipped_shards"] == ["shard-000001"] and len(report["subjects"]) == 12


def test_write_read_atomic(synthetic_dataset, tmp_path, monkeypatch):
    root = tmp_path / "ds"
    shutil.copytree(synthetic_dataset, root)
    report = preflags.score_dataset(root)
    path = report_format.write_preflags(root, report)
    assert path == root / "preflags.json"
    assert report_format.read_preflags(root) == json.loads(json.dumps(report))
    assert Dataset(root).index_sha256 == report["dataset_index_sha256"]  # the report is the dataset's
    assert not [p.name for p in root.iterdir() if ".tmp" in p.name]
    old = path.read_bytes()

    def boom(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    changed = dict(report, subjects=report["subjects"][:1])
    with pytest.raises(OSError):
        report_format.write_preflags(root, changed)
    monkeypatch.undo()
    assert path.read_bytes() == old                       # the old file is untouched
    assert not [p.name for p in root.iterdir() if ".tmp" in p.name]
    other = tmp_path / "elsewhere.json"
    report_format.write_preflags(root, report, path=other)
    assert report_format.read_preflags(root, path=other)["subjects"] == report_format.read_preflags(root)["subjects"]
    (root / "index.json").write_text((root / "index.json").read_text() + " ")
    assert Dataset(root).index_sha256 != report["dataset_index_sha256"]  # stale once index.json changes


def test_the_review_queue_file_is_the_reports_and_only_while_the_report_is_unchanged(synthetic_dataset, tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(synthetic_dataset, root)
    report = preflags.score_dataset(root)
    report["subjects"][0]["rank"] = 0.123  # a learned rank, where --learn gave one
    report_format.write_preflags(root, report)
    rows = json.loads((root / "preflags-queue.json").read_text())["subjects"]
    assert rows == json.loads(json.dumps(report_format.queue_rows(report)))
    assert report_format.read_queue(root) == (report["dataset_index_sha256"], rows) and rows[0][2] == 0.123
    flagged = next(r for r in report["subjects"] if len(r["flags"]) >= 1)
    row = next(r for r in rows if r[0] == flagged["subject"])
    assert report_format.parse_flags(row[3]) == tuple(sorted(((k, flagged["detectors"][k]["score"]) for k in flagged["flags"]),
                                                             key=lambda f: -f[1]))  # exact scores, strongest first
    # The report rewritten without its queue (another writer): the queue is not used, the report is read.
    changed = dict(report, subjects=report["subjects"][1:])
    report_format.write_preflags(root, changed, path=root / "preflags.json")
    assert report_format.read_queue(root)[1] == json.loads(json.dumps(report_format.queue_rows(changed)))
    (root / "preflags.json").unlink()
    assert report_format.read_queue(root) is None


def test_procedural_dataset_end_to_end(tmp_path):
    """A tiny rendered dataset: scores in range, identical with and without truth/."""
    root = tmp_path / "proc"
    run_sample(JobSpec(out=str(root), gan="procedural", generator_options={"grid_resolution": 32, "defect_rate": 0.5},
                       protocol="360", subjects=4, resolution=32, views=10, seed=3, shard_size=2,
                       software=software_info()), progress=False)
    report = preflags.score_dataset(root, placement=Placement(("cpu", "cpu")))
    assert len(report["subjects"]) == 4
    assert all(0 <= s["score"] <= 1 for s in report["subjects"])
    shutil.rmtree(root / "truth")
    assert strip_timing(preflags.score_dataset(root)) == strip_timing(report)


# ----------------------------------------------------------------------------------------------
# Learning from reviewers

def _report(n=120, seed=0):
    """A report whose bad subjects carry a weak signal in one detector's value, below any flag."""
    rng = np.random.default_rng(seed)
    bad = rng.random(n) < 0.25
    subjects = []
    for i in range(n):
        v = rng.normal(1.0 if bad[i] else 0.0, 0.5)
        subjects.append({"subject": f"subj{i:08d}", "shard": "shard-000000", "score": 0.2, "flags": [],
                         "detectors": {"washed_out": {"score": 0.2, "why": "", "value": float(v)},
                                       "blur": {"score": float(rng.random() * 0.4), "why": ""}}})
    return {"detectors": {"washed_out": {}, "blur": {}}, "subjects": subjects}, bad


def test_learned_rank_puts_what_reviewers_reject_first():
    from labeling_tool.preflags.learn import learn_ranking
    report, bad = _report()
    labels = {s["subject"]: int(b) for s, b in list(zip(report["subjects"], bad))[:60]}
    learn_ranking(report, labels)
    assert report["learned"]["used"] and report["learned"]["cross_validated_auc"] > 0.8
    rest = [(s["rank"], b) for s, b in list(zip(report["subjects"], bad))[60:]]
    ranked = [b for _, b in sorted(rest, key=lambda t: -t[0])]
    k = sum(ranked)
    assert sum(ranked[:k]) / k > 0.6  # far above the 25 % an unranked queue would give
    assert report["learned"]["strongest"][0]["feature"].startswith("washed_out.value")


def test_thumbnail_components_are_kept_only_when_they_help():
    from labeling_tool.preflags.learn import learn_ranking
    report, bad = _report()
    labels = {s["subject"]: int(b) for s, b in list(zip(report["subjects"], bad))[:60]}
    rng = np.random.default_rng(5)
    noise = [rng.normal(size=64) for _ in bad]  # thumbnails that say nothing about the verdicts
    learn_ranking(report, labels, noise)
    assert not any(f.startswith("thumb.") for f in report["learned"]["features"])
    for s in report["subjects"]:  # now only the thumbnails carry the signal
        s["detectors"]["washed_out"]["value"] = 0.0
    telling = [rng.normal(size=64) + 3.0 * b for b in bad]
    learn_ranking(report, labels, telling)
    assert any(f.startswith("thumb.") for f in report["learned"]["features"])
    assert report["learned"]["cross_validated_auc"] > 0.9


def test_too_few_verdicts_learn_nothing():
    from labeling_tool.preflags.learn import learn_ranking
    report, bad = _report()
    learn_ranking(report, {report["subjects"][0]["subject"]: 1})
    assert not report["learned"]["used"] and all(s["rank"] == s["score"] for s in report["subjects"])


def test_auto_learn_from_event_logs(synthetic_dataset, tmp_path, capsys):
    from datagen.dataset.events import EventLog
    from labeling_tool.cli import main as label_main
    root = tmp_path / "ds"
    shutil.copytree(synthetic_dataset, root)
    labels = tmp_path / "labels"
    log = EventLog(labels, "ann")
    for i in range(16):
        log.append(subject_id(i), "shard-000000", "good")
    log.append("subj00000100", "shard-000002", "bad", ("artifacts",))
    log.append("subj00000101", "shard-000002", "bad", ("artifacts",))
    log.close()
    assert label_main(["auto", str(root), "--learn", str(labels), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "learned from 18 verdicts (2 bad): needs at least 20 verdicts" in out
    report = report_format.read_preflags(root)
    assert report["learned"]["verdicts"] == 18 and all("rank" in s for s in report["subjects"])


def test_a_report_is_written_piece_by_piece_as_json_dumps_would(tmp_path):
    report = {"format": report_format.FORMAT, "dataset_index_sha256": "0" * 64,
              "subjects": [{"subject": f"subj{i:08d}", "score": i / 7, "flags": ["janus"] if i % 2 else [],
                            "detectors": {"janus": {"score": 0.5, "why": "a face — on the back"}}} for i in range(40)]}
    path = report_format.write_preflags(tmp_path, report)
    assert path.read_bytes() == (json.dumps(report, indent=1, allow_nan=False) + "\n").encode()
    with pytest.raises(ValueError):
        report_format.write_preflags(tmp_path, dict(report, subjects=[{"score": float("nan")}]))
    assert path.read_bytes() == (json.dumps(report, indent=1, allow_nan=False) + "\n").encode()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["preflags-queue.json", "preflags.json"]  # no temporary left
