import numpy as np
import pytest
import torch

from datagen.cameras import ViewSet, named_views, sample_views
from datagen.generators.base import STREAM_CAMERAS, STREAM_LATENT, subject_rng
from datagen.generators.procedural import (DEFECT_TYPES, HAIR_STYLES, SKIN_TONES, ProceduralConfig, ProceduralHeads,
                                           laplace_density, sample_defects, sample_params)

GEN = ProceduralHeads(ProceduralConfig(grid_resolution=64, defect_rate=0.0))
WHITE = np.array([1.0, 1.0, 1.0])


def views(yaw, pitch=0.0, radius=2.7, fov=18.83, pivot=(0.0, 0.0, 0.0)):
    n = len(yaw)
    return ViewSet("test", np.array(yaw, float), np.full(n, float(pitch)), np.full(n, float(radius)),
                   np.full(n, float(fov)), pivot)


@pytest.fixture(scope="module")
def subject():
    return GEN.sample_subject(0, 1)


def assert_clean(out):
    for a in (out.rgb, out.alpha, out.depth):
        assert np.isfinite(a).all()
    assert out.alpha.min() >= 0 and out.alpha.max() <= 1
    assert out.rgb.min() >= 0 and out.rgb.max() <= 1
    assert out.depth.min() >= 0


def test_subjects_are_reproducible_from_seed_and_index():
    a, b = GEN.sample_subject(3, 11), GEN.sample_subject(3, 11)
    assert a.latent == b.latent
    assert torch.equal(a.state.rgb, b.state.rgb)
    c = GEN.sample_subject(3, 12)
    assert c.latent != a.latent
    v = named_views(["front", "left"])
    assert np.array_equal(GEN.render(a, v, 32).rgb, GEN.render(b, v, 32).rgb)


def test_subjects_are_diverse():
    params = [sample_params(subject_rng(0, i, STREAM_LATENT)) for i in range(200)]
    styles = {p["hair_style"] for p in params}
    assert styles == set(HAIR_STYLES)
    tones = np.array([np.mean(p["skin_rgb"]) for p in params])
    assert tones.max() - tones.min() > 0.35
    assert 0.08 < np.mean([p["glasses"] for p in params]) < 0.35
    assert 0.04 < np.mean([p["cap"] for p in params]) < 0.25
    assert len({p["hair_colour"] for p in params}) >= 8
    assert all(p["hair_length"] < -0.45 for p in params if p["hair_style"] == "long")  # past the shoulders
    for key in ("face_width", "jaw_width", "chin_width", "nose_width", "nose_length", "mouth_width", "eye_width",
                "eye_spacing", "brow_thickness", "ear_size"):
        values = np.array([p[key] for p in params])
        assert values.max() > 1.3 * values.min(), key


def attribute_shares(params, key, value=None):
    from collections import Counter
    counts = Counter(value(p) if value else p[key] for p in params)
    return {k: v / len(params) for k, v in counts.items()}


def test_attribute_coverage_over_a_thousand_seeds():
    """Every hair style, natural hair colour, skin tone bracket, sex and age bracket is at least 3 % of
    subjects; unnatural (dyed) hair is rare on purpose; grey hair comes with age."""
    params = [sample_params(subject_rng(0, i, STREAM_LATENT)) for i in range(1000)]
    for key in ("hair_style", "skin_tone", "sex", "age_bracket", "neckline", "iris"):
        shares = attribute_shares(params, key)
        assert min(shares.values()) >= 0.03 and len(shares) >= 2, (key, shares)
    assert set(attribute_shares(params, "hair_style")) == set(HAIR_STYLES)
    assert set(attribute_shares(params, "skin_tone")) == set(SKIN_TONES)
    colours = attribute_shares(params, "hair_colour")
    assert colours.get("dyed", 0) <= 0.03
    assert sum(v >= 0.03 for k, v in colours.items() if k != "dyed") >= 7
    for key in ("glasses", "cap", "makeup"):
        assert 0.03 <= np.mean([p[key] for p in params]) <= 0.5, key
    assert 0.03 <= np.mean([p["facial_hair"] != "none" for p in params]) <= 0.5
    grey = [p["hair_colour"] in ("grey", "white") for p in params]
    age = np.array([p["age"] for p in params])
    assert np.mean(np.array(grey)[age > 60]) > 3 * max(np.mean(np.array(grey)[age < 35]), 0.01)
    assert all(p["facial_hair"] == "none" for p in params if p["sex"] == "female")


def test_defect_rate_and_types():
    rng = np.random.default_rng(0)
    p = sample_params(rng)
    hits = sum(bool(sample_defects(rng, 0.04, p)) for _ in range(2000))
    assert 50 <= hits <= 110  # 4 % of 2000 = 80
    kinds = {sample_defects(rng, 1.0, p)[0]["type"] for _ in range(200)}
    assert kinds == set(DEFECT_TYPES)
    assert not any(sample_defects(rng, 0.0, p) for _ in range(200))


def test_truth_is_recorded_apart_from_the_latent():
    gen = ProceduralHeads(ProceduralConfig(grid_resolution=48, defect_rate=1.0))
    s = gen.sample_subject(0, 2)
    assert s.truth["defects"] and s.truth["defects"][0]["type"] in DEFECT_TYPES
    assert "defect" not in repr(s.latent)


def test_head_is_framed_with_background_around(subject):
    out = GEN.render(subject, views([0, 90, 180, 270]), 64)
    assert_clean(out)
    c = 32
    assert (out.alpha[:, c - 4:c + 4, c - 4:c + 4] > 0.99).all()  # the head fills the centre of every view
    corners = out.alpha[:, [0, 0], [0, -1]]  # the top corners are background
    assert (corners < 1e-3).all()
    np.testing.assert_allclose(out.rgb[:, 0, 0], np.tile(WHITE, (4, 1)), atol=1e-6)
    assert 0.25 < out.alpha.mean() < 0.85
    # Neck and shoulders reach the bottom of the frame, as in FFHQ-style crops: most of the bottom
    # row is covered seen from the front and the back, and the shoulders are wider than the head.
    assert (out.alpha[[0, 2], -1].mean(-1) > 0.8).all()
    head_row, shoulder_row = out.alpha[0, 20] > 0.5, out.alpha[0, -3] > 0.5
    assert shoulder_row.sum() > 1.3 * head_row.sum()
    # The front of the head is between 0.1 and 0.45 units in front of the origin.
    d = out.depth[0, c - 2:c + 2, c - 2:c + 2]
    assert (d > 2.7 - 0.45).all() and (d < 2.7 - 0.1).all()
    assert (out.depth[out.alpha == 0] == 0).all()


def test_alpha_is_binary_inside_and_outside(subject):
    out = GEN.render(subject, views([30]), 64)
    a = out.alpha.ravel()
    assert np.mean((a > 0.01) & (a < 0.99)) < 0.08  # only silhouette pixels are fractional


def _with_defect(index, defect, res=128, yaw=(0.0, 180.0)):
    """(clean, defective) renders of one subject (grid 128: eyes and lips need it) at 128 px."""
    from datagen.generators.base import Subject
    from datagen.generators.procedural import bake_head

    params = sample_params(subject_rng(0, index, STREAM_LATENT))
    gen = ProceduralHeads(ProceduralConfig(grid_resolution=128))
    out = []
    for d in ([], [defect]):
        s = Subject(index=index, seed=0, latent={"params": params}, truth={"defects": d}, state=bake_head(params, d, 128))
        out.append(gen.render(s, views(list(yaw)), res))
        assert_clean(out[-1])
    return out


def test_janus_is_a_face_the_face_detectors_find_on_the_back():
    from labeling_tool.preflags.janus import NO_FACE, best_cnn_face, best_face

    clean, janus = _with_defect(2, {"type": "janus", "severity": 1.0})
    u8 = lambda rgb: (rgb * 255 + 0.5).astype(np.uint8)  # noqa: E731
    assert best_face(u8(clean.rgb[0])) > 0 and best_face(u8(janus.rgb[0])) > 0  # the real face, both
    assert best_face(u8(clean.rgb[1])) == NO_FACE
    assert best_face(u8(janus.rgb[1])) > 0                                      # a second one behind
    # the CNN detector on the head of each view, 128 px: the real face, none on the clean back, the second face
    cnn = [[best_cnn_face(u8(o.rgb[i]), o.alpha[i] > 0.5) for i in (0, 1)] for o in (clean, janus)]
    assert cnn[0][0] > 0 and cnn[1][0] > 0
    assert cnn[0][1] == NO_FACE and cnn[1][1] > 0
    assert np.abs(clean.rgb[0] - janus.rgb[0]).mean() < 2e-3


def test_flat_back_brings_the_back_of_the_head_closer():
    clean, flat = _with_defect(3, {"type": "flat_back", "severity": 1.0}, yaw=(180.0,))
    c = slice(52, 76)  # the middle of the back of the head at 128 px
    solid = (clean.alpha[0, c, c] > 0.99) & (flat.alpha[0, c, c] > 0.99)
    gained = flat.depth[0, c, c][solid] - clean.depth[0, c, c][solid]
    assert np.median(gained) > 0.08  # at least 0.12 head units (0.098 world) cut off, hair included


def test_haze_is_partly_transparent_material_away_from_the_head():
    from scipy import ndimage as ndi
    clean, hazy = _with_defect(5, {"type": "haze", "severity": 1.0, "wisps": sample_defects(
        np.random.default_rng(3), 1.0, {}, ("haze",), (1.0, 1.0))[0]["wisps"]}, yaw=(0.0, 90.0, 180.0))

    def far_partial(out):
        solid = out.alpha > 0.9
        far = np.stack([ndi.distance_transform_edt(~m) > 3 for m in solid])
        return int(((out.alpha > 0.04) & (out.alpha < 0.75) & far).sum())
    n_clean, n_hazy = far_partial(clean), far_partial(hazy)
    assert n_clean <= 10 and n_hazy > 10 * max(n_clean, 5), (n_clean, n_hazy)


def test_seam_is_a_step_in_colour_down_the_back():
    defect = {"type": "seam", "severity": 1.0, "x": 0.0, "side": 1.0}
    clean, seam = _with_defect(12, defect, yaw=(180.0,))
    rows = slice(30, 70)
    ratio = seam.rgb[0, rows].mean(-1) / np.maximum(clean.rgb[0, rows].mean(-1), 1e-3)
    solid = (clean.alpha[0, rows] > 0.99).all(0)
    # Seen from behind, +x is on the image's left: that half darkens by about 40 %, the other keeps its colour.
    left, right = ratio[:, 40:60][:, solid[40:60]], ratio[:, 68:88][:, solid[68:88]]
    assert np.median(left) < 0.7 and abs(np.median(right) - 1.0) < 0.03


def test_blurry_back_smears_the_back_and_leaves_the_face_sharp():
    clean, blurry = _with_defect(1, {"type": "blurry_back", "severity": 1.0})

    from scipy import ndimage as ndi

    def detail(out, v):
        """Mean horizontal colour step inside the silhouette (3 px in from its edge)."""
        inside = ndi.binary_erosion(out.alpha[v] > 0.99, iterations=3)
        step = np.abs(np.diff(out.rgb[v].mean(-1), axis=1))
        return float(step[inside[:, 1:] & inside[:, :-1]].mean())
    assert detail(blurry, 1) < 0.6 * detail(clean, 1), (detail(blurry, 1), detail(clean, 1))
    assert abs(detail(blurry, 0) - detail(clean, 0)) < 0.05 * detail(clean, 0)


@pytest.mark.parametrize("case", [
    dict(yaw=[0], pitch=90.0), dict(yaw=[0], pitch=-90.0),          # poles
    dict(yaw=[0, 180], radius=0.05), dict(yaw=[45], radius=0.3),    # camera inside the head / the bound
    dict(yaw=[10], radius=1.2), dict(yaw=[10], radius=50.0),        # extreme radius draws
    dict(yaw=[0], fov=0.5), dict(yaw=[0], fov=150.0),               # extreme FOV draws
])
def test_hard_cameras_stay_finite(subject, case):
    out = GEN.render(subject, views(**case), 24)
    assert_clean(out)


def test_grid_lookup_is_the_same_split_over_threads_and_empty_grids_are_missed(subject):
    import torch.nn.functional as F

    from datagen.generators import procedural as P

    grid = torch.cat([subject.state.sdf, subject.state.rgb], 1)
    p = (torch.rand(50_001, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1) * 0.5  # also outside the box
    one = F.grid_sample(grid, (p / P.BOX).reshape(1, 1, 1, -1, 3), mode="bilinear", padding_mode="border",
                        align_corners=True).reshape(4, -1).t()
    threads = torch.get_num_threads()
    try:
        for n in (1, 2, 3):
            torch.set_num_threads(n)
            assert torch.equal(P.sample_grid(grid, p), one)
    finally:
        torch.set_num_threads(threads)
    o, d = torch.zeros(4, 3), F.normalize(torch.randn(4, 3), dim=-1)
    t0, t1 = P.trace_interval(torch.ones(1, 1, 8, 8, 8), o, d, 0.012, 0.0)  # nothing below the level
    assert (t1 <= t0).all()


def test_grazing_rays_and_camera_looking_away(subject):
    from datagen.cameras import rays
    from datagen.generators import procedural as P

    # Parallel-ish rays skimming the side of the head (camera beside it, looking along -z).
    c2w = np.eye(4)
    c2w[:3, :3] = np.diag([1.0, -1.0, -1.0])
    c2w[:3, 3] = [0.2, 0.0, 2.0]
    K = views([0]).K
    o, d = rays(torch.tensor(c2w[None]), torch.tensor(K), 32)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    t0, t1 = P.trace_interval(subject.state.sdf, o, d, 0.012, 0.0)
    from datagen.render import box_interval
    b0, b1 = box_interval(o, d, P.BOX)  # the box around the head lies inside the bounding box
    assert (t0 >= b0 - 1e-5).all() and (t1 <= b1 + 1e-5).all() and (t1 - t0).sum() < (b1 - b0).sum()
    t, hit = P.sphere_trace(subject.state.sdf, o, d, t0, t1, 0.012)
    assert torch.isfinite(t).all() and 0 < hit.float().mean() < 1
    # Looking away from the head (forward = +z from in front of it): no ray enters the box.
    c2w[:3, :3] = np.diag([-1.0, -1.0, 1.0])
    c2w[:3, 3] = [0.0, 0.0, 2.7]
    o, d = rays(torch.tensor(c2w[None]), torch.tensor(K), 16)
    t0, t1 = P.trace_interval(subject.state.sdf, o.reshape(-1, 3), d.reshape(-1, 3), 0.012, 0.0)
    assert (t0 >= t1).all()


def test_empty_render_is_background(subject):
    out = GEN.render(subject, views([0], radius=2.7, pivot=(0.0, 3.0, 0.0)), 16)  # looking far above the head
    assert_clean(out)
    assert out.alpha.max() < 1e-6
    np.testing.assert_allclose(out.rgb.reshape(-1, 3), np.tile(WHITE, (256, 1)))


def test_laplace_density_is_finite_for_extreme_distances():
    sdf = torch.tensor([-1e30, -1.0, -1e-9, 0.0, 1e-9, 1.0, 1e30, float("inf"), float("-inf")])
    d = laplace_density(sdf, 0.003)
    assert torch.isfinite(d).all() and (d >= 0).all()
    assert d[0] == pytest.approx(1 / 0.003, rel=1e-6) and d[6] < 1e-20


def test_protocol_views_render(subject):
    v = sample_views("frontal", subject_rng(0, 1, STREAM_CAMERAS), 4)
    out = GEN.render(subject, v, 32)
    assert_clean(out)
    assert out.rgb.shape == (4, 32, 32, 3) and out.alpha.shape == (4, 32, 32)


def brim_columns(alpha, gap=3):
    """{column: rows} of the columns in the front half (the face looks toward column 0 at yaw 90) whose first
    opaque band (the brim, from above) has background below it; the back half is left out, where the cap's
    back edge stands a little off the hair."""
    out = {}
    for c in range(alpha.shape[1] // 2):
        col = alpha[:, c]
        solid = np.flatnonzero(col > 0.5)
        if not solid.size:
            continue
        end = solid[0]
        while end + 1 < len(col) and col[end + 1] > 0.5:
            end += 1
        below = col[end + 2:end + 2 + gap]
        if below.size == gap and (below < 0.02).all() and end < len(col) // 2:
            out[c] = col[:end + 2 + gap]
    return out


def cap_params(index=5):
    params = sample_params(subject_rng(0, index, STREAM_LATENT))
    params.update(cap=True, glasses=False, hair_style="crop", hair_thickness=0.014)
    return params


@pytest.mark.parametrize("resolution", [128, 256])
def test_cap_brim_seen_edge_on_is_one_clean_edge(resolution):
    """A brim seen edge-on (from the side) is one opaque band with at most one partial pixel at each
    side: no ghost copies above or below it, no ragged edge (its top and thickness change by at most
    a pixel from column to column)."""
    from datagen.generators.procedural import bake_head

    gen = ProceduralHeads(ProceduralConfig(grid_resolution=128, defect_rate=0.0))
    subject = gen.sample_subject(0, 0)
    subject.state = bake_head(cap_params(), [], 128)
    alpha = gen.render(subject, views([90]), resolution).alpha[0]
    cols = brim_columns(alpha)
    assert len(cols) >= resolution // 40, "no brim sticks out in front of the face"
    tops, widths = [], []
    for c, col in cols.items():
        solid = np.flatnonzero(col > 0.5)
        assert solid[-1] - solid[0] + 1 == solid.size, f"column {c}: more than one band"
        # One peak: alpha rises monotonically to the band and falls monotonically after it (a ghost
        # copy would be a second bump), within 2 px of it (the Laplace density's falloff along rays
        # that skim the brim), with few partial pixels.
        assert (np.diff(col[:solid[0] + 1]) >= -1e-3).all() and (np.diff(col[solid[-1]:]) <= 1e-3).all(), \
            f"column {c}: a ghost beside the brim"
        seen = np.flatnonzero(col > 0.02)
        assert seen[0] >= solid[0] - 2 and seen[-1] <= solid[-1] + 2, f"column {c}: a halo beside the brim"
        partial = (col > 0.02) & (col < 0.98)
        assert partial[:solid[0]].sum() <= 2 and partial[solid[-1] + 1:].sum() <= 2, f"column {c}: a soft edge"
        tops.append(solid[0])
        widths.append(solid.size)
    # Within a pixel at 128 px (two at 256) between neighbouring columns, leaving out the outermost
    # column, where the rounded tip of the brim turns.
    step = max(1, resolution // 128)
    assert np.abs(np.diff(tops[1:])).max(initial=0) <= step and np.abs(np.diff(widths[1:])).max(initial=0) <= step
    assert max(widths) <= resolution // 10  # a thin brim (tilted down a little), not a slab


def first_params(match, seed=0):
    """The first subject's parameters (index order) for which ``match`` holds."""
    for i in range(500):
        params = sample_params(subject_rng(seed, i, STREAM_LATENT))
        if match(params):
            return params
    raise AssertionError("no subject matches")


def test_baked_beard_edge_matches_the_analytic_field():
    """The baked grid reproduces the field where the beard meets the skin to within a voxel: a beard
    region thresholded without scaling to a distance left the exact band a voxel thin there, and the
    beard's edge rendered in steps."""
    from datagen.generators.procedural import HEAD_SCALE, bake_head, head_field, sample_grid

    params = first_params(lambda p: p["facial_hair"] == "beard")
    grid = bake_head(params, [], 128)
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(300000, 3, generator=g) * 2 - 1  # the lower front of the face (head units)
    pts = torch.stack([0.3 * pts[:, 0], 0.12 * pts[:, 1] - 0.12, 0.15 * pts[:, 2].abs() + 0.05], -1) * HEAD_SCALE
    exact = head_field(pts, params, [], colour=False)[0]
    near = exact.abs() < 0.004
    baked = sample_grid(grid.sdf, pts[near])[:, 0]
    voxel = 0.96 / 127
    assert near.sum() > 1000
    assert (baked - exact[near]).abs().max() < 0.9 * voxel


def test_sexes_differ_in_face_shape_and_brows_stay_visible():
    from datagen.generators.procedural import LUMA

    params = [sample_params(subject_rng(0, i, STREAM_LATENT)) for i in range(2000)]
    male = [p for p in params if p["sex"] == "male"]
    female = [p for p in params if p["sex"] == "female"]
    med = lambda group, key: np.median([p[key] for p in group])  # noqa: E731
    for key, gap in (("jaw_width", 0.05), ("chin_width", 0.03), ("brow_thickness", 0.008), ("nose_width", 0.015)):
        assert med(male, key) - med(female, key) > gap, key
    for key, gap in (("brow_height", 0.01), ("upper_lip", 0.004), ("brow_arch", 0.003)):
        assert med(female, key) - med(male, key) > gap, key
    for p in params:
        assert np.asarray(p["brow_rgb"]) @ LUMA <= 0.55 * (np.asarray(p["skin_rgb"]) @ LUMA) + 1e-6
        assert p["upper_lip"] > 0 and p["lower_lip"] > 0 and p["eye_open"] > 0
        # the widths the face's shape divides by or tapers to stay positive at the extremes of sex
        assert p["chin_width"] > 0 and p["nose_width"] > 0.01 and p["brow_thickness"] > 0 and p["brow_arch"] >= 0
    # darker skin is exposed brighter, as a camera metering on the face would
    expo = {t: np.mean([p["exposure"] for p in params if p["skin_tone"] == t]) for t in ("I", "VI")}
    assert expo["I"] == 1.0 and 1.2 < expo["VI"] <= 1.35


def test_age_brings_nasolabial_folds_and_forehead_lines():
    from datagen.generators.procedural.anatomy import anchors_of, skin_colour

    young = first_params(lambda p: p["facial_hair"] == "none" and not p["makeup"])
    old = dict(young, age=80.0)
    young = dict(young, age=18.0)
    A = anchors_of(young)
    tip_y = young["eye_height"] - young["nose_length"] + young["nose_tilt"]
    mw, nw, my = young["mouth_width"], young["nose_width"], young["mouth_y"]
    fold = (0.25 * (nw + 0.006) + 0.5 * (mw + 0.032) + 0.25 * (mw + 0.012),  # the fold's middle
            0.25 * (tip_y + 0.01) + 0.25 * (tip_y + my) + 0.25 * (my - 0.022))
    forehead = (0.0, young["eye_height"] + young["brow_height"] + 0.035)
    for (x, y), ratio in ((fold, 0.8), (forehead, 0.93)):
        p = torch.tensor([[x, y, 0.3]])
        assert skin_colour(p, old, A).mean() < ratio * skin_colour(p, young, A).mean()
