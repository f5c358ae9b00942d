"""The face and head as signed distances (head units) and the skin's albedo.

``face_base`` is the skin surface before the features (skull, face mass, jaw, neck); ``face_features``
adds eyes, lids, nose, lips and ears, each seated on that surface at ``_anchors``.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from .params import oldness
from .sdf import (ellipsoid_front_z, extrude, gauss, near_box, segment_2d, smoothstep, f32, wave_noise, sd_capsule,
                     sd_ellipse_2d, sd_ellipsoid, sd_sphere, sd_triangle_2d, smax, smin)


def cranium(P):
    """The skull's ellipsoid: (centre, radii), head units."""
    rx, ry, rz = P["skull_radii"]
    return (0.0, P["skull_center_y"], -0.02 - 0.012 * P["forehead_slope"]), (rx, ry, rz)


def face_base(p, P):
    """Skull, face mass, cheekbones, brow ridge, jaw and chin, neck: the skin surface before the features."""
    E, fw = P["eye_height"], P["face_width"]
    cc, cr = cranium(P)
    d = sd_ellipsoid(p, cc, cr)
    half = max(fw, P["jaw_width"] + 0.02) + 0.01
    face = near_box(p, (-half, P["chin_y"] - 0.01, -0.26), (half, E + 0.075, 0.26), lambda q: [(_face_mass(q, P), None)],
                  margin=0.08)[0][0]
    d = smin(d, face, 0.07)
    neck = sd_capsule(p, (0.0, P["jaw_angle_y"] + 0.03, -0.05), (0.0, -0.62, -0.06), P["neck_radius"], P["neck_radius"] * 1.12)
    return smin(d, neck, 0.06)


def _face_mass(p, P):
    """The face in front of the skull: brow ridge, cheeks, jaw and chin."""
    E, fw = P["eye_height"], P["face_width"]
    cc, cr = cranium(P)
    d = sd_ellipsoid(p, (0.0, E - 0.05, -0.01), (fw, 0.12, 0.205))
    # Brow ridge: a bar across the forehead above the eyes, more prominent in masculine faces.
    zb = ellipsoid_front_z(cc, cr, 0.0, E + 0.045)
    ridge = sd_ellipsoid(p, (0.0, E + 0.042, zb - 0.03 + 0.012 * P["brow_ridge"]), (0.105, 0.022, 0.035))
    d = smin(d, ridge, 0.03)
    # Cheekbones and cheek fat.
    cb = 0.6 + 0.6 * P["cheekbone"]
    cf = 0.6 + 0.5 * P["cheek_fat"]
    for sx in (-1.0, 1.0):
        d = smin(d, sd_ellipsoid(p, (sx * (fw - 0.055), E - 0.045, 0.11), (0.05 * cb, 0.03, 0.06)), 0.03)
        d = smin(d, sd_ellipsoid(p, (sx * 0.075, P["mouth_y"] + 0.045, 0.125), (0.05 * cf, 0.045, 0.05 * cf)), 0.03)
    # Lower face and jaw: an ellipsoid tapering from the jaw angles to the chin, and the chin.
    jw, jy, cy_, cw = P["jaw_width"], P["jaw_angle_y"], P["chin_y"], P["chin_width"]
    zc = 0.172 + P["chin_projection"]
    top = E - 0.03
    ry_l = (top - cy_) / 2
    taper = 1.0 - (1.0 - (cw + 0.03) / (jw + 0.02)) * smoothstep(jy + 0.02, cy_, p[:, 1]) ** 0.8
    q = torch.stack([p[:, 0] / taper, p[:, 1], p[:, 2]], dim=-1)
    jaw = sd_ellipsoid(q, (0.0, cy_ + ry_l, -0.02), (jw + 0.02, ry_l, zc + 0.02)) * taper
    chin = sd_ellipsoid(p, (0.0, cy_ + 0.035, zc - 0.03), (cw + 0.012, 0.035, 0.032))
    jaw = smin(jaw, chin, 0.03)
    return smin(d, jaw, 0.04)


def _surface_z(P, xy, z_out, z_in):
    """z where the skin before the features (``face_base``) is first met going along z from ``z_out``
    (outside) toward ``z_in`` (inside), at each (x, y) of ``xy``: a list of floats."""
    q = torch.tensor(xy, dtype=torch.float32)
    zs = torch.linspace(z_out, z_in, 101)
    pts = torch.cat([q[:, None, :].expand(-1, 101, 2), zs[None, :, None].expand(len(xy), -1, 1)], -1)
    d = face_base(pts.reshape(-1, 3), P).reshape(len(xy), 101)
    first_in = torch.argmax((d < 0).to(torch.int8), dim=1).clamp(min=1)
    out = zs[first_in - 1].clone()
    inn = zs[first_in].clone()
    for _ in range(18):
        mid = 0.5 * (out + inn)
        inside = face_base(torch.cat([q, mid[:, None]], -1), P) < 0
        inn, out = torch.where(inside, mid, inn), torch.where(inside, out, mid)
    return (0.5 * (out + inn)).tolist()


PONYTAIL_KNOTS = 12  # points down the back of the head and neck that a ponytail follows


def _anchors(P):
    """Where the features sit: z of the skin surface (before features) at their (x, y); for a ponytail,
    also the back's profile it lies on: [(y, z)] down the midline from its tie to its end."""
    E, ex = P["eye_height"], P["eye_spacing"]
    tip_y = E - P["nose_length"]
    xy = [(0.0, E + 0.005), (ex, E), (0.0, tip_y), (0.0, P["mouth_y"]), (0.0, P["chin_y"] + 0.04),
          (P["nose_width"], tip_y)]
    z = _surface_z(P, xy, 0.5, 0.0)
    A = {"nasion": z[0], "eye": z[1], "nose": z[2], "mouth": z[3], "chin": z[4], "ala": z[5]}
    if P["hair_style"] == "ponytail":
        ys = np.linspace(cranium(P)[0][1] + 0.06, P["hair_length"], PONYTAIL_KNOTS).tolist()
        A["ponytail"] = list(zip(ys, _surface_z(P, [(0.0, y) for y in ys], -0.5, 0.0)))
    return A


_ANCHORS: dict = {}


def anchors_of(P):
    """``_anchors``, memoised per parameter set (keyed by its scalar values; emptied past 64 sets)."""
    key = repr(sorted((k, v) for k, v in P.items() if not isinstance(v, list)))
    if key not in _ANCHORS:
        if len(_ANCHORS) > 64:
            _ANCHORS.clear()
        _ANCHORS[key] = _anchors(P)
    return _ANCHORS[key]


EYE_RADIUS = 0.029
NOSE_FLARE = 0.5    # how fast the nose widens below its bridge line (half-width per unit of depth)
NOSE_ROUND = 0.006  # rounding of the nose body's edges (head units)


def eye_centre(P, A, sx):
    """Centre of the eyeball on side ``sx`` (-1 or 1), set back from the skin surface."""
    return (sx * P["eye_spacing"], P["eye_height"], A["eye"] - EYE_RADIUS * 0.72)


def _aperture(p, P, sx):
    """2D distance to the eye opening (negative inside), in the face plane."""
    ex, E = P["eye_spacing"], P["eye_height"]
    u = (p[:, 0] - sx * ex) * sx  # toward the temple
    v = p[:, 1] - E - 0.002 - P["eye_tilt"] * u
    ay = torch.where(v > 0, f32(P["eye_open"] * 1.15), f32(P["eye_open"] * 0.8))
    ay = ay * (1.0 - 0.25 * (u / P["eye_width"]).clamp(-1, 1))  # the inner corner is rounder
    return sd_ellipse_2d(u + 0.002, v, P["eye_width"], ay)


def _eyes(p, P, A):
    """Eyeballs (iris, pupil, sclera) and eyelids; returns [(sdf, rgb or None)]."""
    out_ball, out_lid, ball_rgb = [], [], []
    for sx in (-1.0, 1.0):
        c = eye_centre(P, A, sx)
        ball = sd_sphere(p, c, EYE_RADIUS)
        look = F.normalize(p - f32(c), dim=-1)
        cosang = look[:, 2]
        iris_edge = 0.87  # cosine of the iris's angular radius (iris radius 0.0143 head units)
        # The sclera as photos show it (the lids shade it): a light grey, not paper white, which on dark
        # skin stood out as two bright dots where a face has a dark band.
        rgb = f32([0.7, 0.66, 0.63]).expand(p.shape[0], 3) * (0.85 + 0.15 * smoothstep(0.5, 0.8, cosang))[:, None]
        iris = f32(P["iris_rgb"]) * (0.75 + 0.5 * ((cosang - iris_edge) / (1 - iris_edge)).clamp(0, 1))[:, None]
        iris = iris * (1.0 + 0.15 * torch.sin(90.0 * torch.atan2(look[:, 1], look[:, 0])))[:, None]
        rgb = torch.where((cosang > iris_edge)[:, None], iris, rgb)
        rgb = torch.where((cosang > iris_edge - 0.012)[:, None] & (cosang <= iris_edge)[:, None], f32([0.1, 0.08, 0.07]), rgb)
        rgb = torch.where((cosang > 0.975)[:, None], f32([0.02, 0.02, 0.02]), rgb)
        out_ball.append(ball)
        ball_rgb.append(rgb)
        shell = sd_sphere(p, c, EYE_RADIUS + 0.0045)
        opening = smax(_aperture(p, P, sx), c[2] - p[:, 2], 0.002)
        out_lid.append(smax(shell, -opening, 0.0025))
    sel = out_ball[0] < out_ball[1]
    balls = torch.minimum(*out_ball)
    rgb = torch.where(sel[:, None], ball_rgb[0], ball_rgb[1])
    return [(balls, rgb), (torch.minimum(*out_lid), None)]


def _nose(p, P, A):
    """Bridge, tip (and a hump), the body under the bridge closed by the columella, and the wings."""
    E, L = P["eye_height"], P["nose_length"]
    tip_y = E - L + P["nose_tilt"]
    r_tip = P["nose_tip"]
    tip_z = A["nose"] + P["nose_projection"]
    top = (0.0, E + 0.005, A["nasion"] - 0.012)
    tip = (0.0, tip_y + 0.006, tip_z - r_tip)
    d = sd_capsule(p, top, tip, P["nose_bridge"], r_tip * 0.8)
    d = smin(d, sd_sphere(p, (0.0, tip_y, tip_z - r_tip), r_tip), 0.012)
    hump = P["nose_hump"]
    if hump > 0.2:
        mid = (0.0, E - 0.4 * L, 0.6 * top[2] + 0.4 * tip[2] + 0.004 * hump)
        d = smin(d, sd_sphere(p, mid, P["nose_bridge"] * (0.9 + 0.5 * hump)), 0.01)
    # Closed underneath: in the midplane the triangle nasion - tip - subnasale (its back edge set into the
    # face), widening away from the bridge line; its lower edge is the columella, which joins the tip to
    # the face between the nostrils however far the nose projects.
    nasion, centre, sub = (top[1], top[2]), (tip_y, tip_z - r_tip), (E - L - 0.008, A["nose"] - 0.012)
    profile = sd_triangle_2d(p[:, 1], p[:, 2], nasion, centre, sub)
    below_bridge = segment_2d(p[:, 1], p[:, 2], nasion, centre)
    w = P["nose_width"]
    half = (0.7 * P["nose_bridge"] + NOSE_FLARE * below_bridge).clamp_max(max(0.8 * w, 0.7 * P["nose_bridge"]))
    across = (p[:, 0].abs() - half + NOSE_ROUND) / math.sqrt(1.0 + NOSE_FLARE ** 2)
    d = smin(d, extrude(profile + NOSE_ROUND, across) - NOSE_ROUND, 0.008)
    for sx in (-1.0, 1.0):
        ala = sd_ellipsoid(p, (sx * (w - 0.012), tip_y - 0.004, A["ala"] + 0.006), (0.014, 0.012, 0.016))
        d = smin(d, ala, 0.012)
        # The lobule's side, from under the tip to the wing.
        d = smin(d, sd_capsule(p, (0.0, tip_y - 0.006, tip_z - 1.3 * r_tip), (sx * (w - 0.012), tip_y - 0.006,
                                                                               A["ala"] + 0.006), 0.011, 0.011), 0.01)
    return d


def _lips(p, P, A):
    """Upper lip (with Cupid's bow) and lower lip."""
    my, lw = P["mouth_y"], P["mouth_width"]
    z = A["mouth"]
    ut, lt = P["upper_lip"], P["lower_lip"]
    upper = sd_ellipsoid(p, (0.0, my + ut * 0.75, z - 0.012 + 0.4 * ut), (lw, ut, 0.02))
    # Cupid's bow: two small bumps on the upper lip.
    for sx in (-1.0, 1.0):
        upper = smin(upper, sd_ellipsoid(p, (sx * lw * 0.28, my + ut * 1.05, z - 0.012 + 0.4 * ut), (lw * 0.35, ut * 0.8, 0.017)), 0.004)
    lower = sd_ellipsoid(p, (0.0, my - lt * 0.8, z - 0.013 + 0.4 * lt), (lw * 0.86, lt, 0.02))
    return smin(upper, lower, 0.003)


def _ears(p, P):
    """Both ears: body, helix, lobe and concha."""
    rx = P["skull_radii"][0]
    es, ey = P["ear_size"], P["ear_y"]
    out = []
    for sx in (-1.0, 1.0):
        c = f32((sx * (rx + 0.004), ey, -0.035))
        q = p - c
        qx = q[:, 0] * sx - P["ear_protrusion"] * 0.25 * (-q[:, 2] - 0.01).clamp_min(0.0)  # backs stand off the head
        body = sd_ellipsoid(torch.stack([qx, q[:, 1], q[:, 2]], -1), (0.004, 0.0, 0.0), (0.012, es, es * 0.58))
        ring = torch.sqrt(q[:, 1] ** 2 + (q[:, 2] / 0.62) ** 2)
        helix = torch.sqrt((ring - es * 0.86) ** 2 + (qx - 0.01) ** 2) - 0.0085
        helix = smax(helix, q[:, 2] - 0.6 * q[:, 1] - 0.012, 0.01)  # open toward the lower front
        ear = smin(body, helix, 0.006)
        lobe = sd_ellipsoid(torch.stack([qx, q[:, 1], q[:, 2]], -1), (0.006, -es * 0.82, 0.006), (0.009, 0.016, 0.014))
        ear = smin(ear, lobe, 0.008)
        concha = sd_ellipsoid(torch.stack([qx, q[:, 1], q[:, 2]], -1), (0.02, -0.008, 0.004), (0.011, es * 0.42, es * 0.3))
        out.append(smax(ear, -concha, 0.005))
    return torch.minimum(*out)


def face_features(p, P, A):
    """Eyes, lids, nose, lips and ears: [(sdf, rgb, blend)], rgb None for skin and "lips" for the lips;
    each part is evaluated only near its own box."""
    E, ex = P["eye_height"], P["eye_spacing"]
    ze = A["eye"]
    lo, hi = (-ex - 0.05, E - 0.04, ze - 0.08), (ex + 0.05, E + 0.04, ze + 0.03)
    (ball, ball_rgb), (lids, _) = near_box(p, lo, hi, lambda q: _eyes(q, P, A))
    parts = [(ball, ball_rgb, 0.0), (lids, None, 0.004)]
    tip_y = E - P["nose_length"]
    w = P["nose_width"] + 0.02
    nose = near_box(p, (-w, tip_y - 0.03, A["ala"] - 0.03), (w, E + 0.02, A["nose"] + P["nose_projection"] + 0.01),
                  lambda q: [(_nose(q, P, A), None)])[0][0]
    parts.append((nose, None, 0.014))
    lw, my = P["mouth_width"], P["mouth_y"]
    lips = near_box(p, (-lw, my - 0.03, A["mouth"] - 0.04), (lw, my + 0.03, A["mouth"] + 0.03),
                  lambda q: [(_lips(q, P, A), None)])[0][0]
    parts.append((lips, "lips", 0.006))
    rx = P["skull_radii"][0]
    es = P["ear_size"]
    ears = near_box(p, (-rx - 0.05, P["ear_y"] - es - 0.02, -0.12), (rx + 0.05, P["ear_y"] + es + 0.02, 0.05),
                  lambda q: [(_ears(q, P), None)])[0][0]
    ears = smax(ears, 0.11 - p[:, 0].abs(), 0.01)  # only at the sides
    parts.append((ears, None, 0.008))
    return parts


def skin_colour(p, P, A):
    """Albedo of the skin: tone, blush, under-eye, eyelids and lash lines, brows, nostrils, mouth line, stubble."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    ax = x.abs()
    E, ex, my = P["eye_height"], P["eye_spacing"], P["mouth_y"]
    front = smoothstep(0.02, 0.1, z)
    rgb = f32(P["skin_rgb"]) * (1.0 + wave_noise(p, P["skin_waves"]))[:, None]
    # Redder cheeks, nose and ears; darker under the eyes and around the eyes.
    blush = P["cheek_blush"] * gauss(ax - 0.085, 0.04) * gauss(y - my - 0.06, 0.035) * front
    blush = blush + 0.08 * gauss(ax, 0.025) * gauss(y - (E - P["nose_length"]), 0.03) * front
    blush = blush + 0.12 * smoothstep(0.15, 0.19, ax) * gauss(y - P["ear_y"], 0.07)
    rgb = rgb * (1.0 - blush[:, None] * f32([0.0, 0.45, 0.4]))
    under = P["under_eye"] * gauss(ax - ex, 0.03) * gauss(y - (E - 0.03), 0.013) * front
    socket = 0.3 * gauss(ax - ex, 0.04) * gauss(y - (E + 0.012), 0.022) * front
    rgb = rgb * (1.0 - (under + socket)[:, None] * f32([0.55, 0.65, 0.55]))
    if P["makeup"]:
        lid = 0.5 * gauss(ax - ex - 0.004, 0.034) * gauss(y - (E + 0.02), 0.011) * front
        rgb = rgb * (1 - lid[:, None]) + f32(P["eye_shadow_rgb"]) * lid[:, None]
    # Lash lines along the upper lid (and faintly the lower one).
    lash = torch.zeros(p.shape[0])
    for sx in (-1.0, 1.0):
        ap = _aperture(p, P, sx)
        upper = (p[:, 1] > P["eye_height"] - 0.002).float()
        lash = torch.maximum(lash, gauss(ap - 0.0015, 0.0032 + 0.0012 * P["makeup"]) * (0.95 * upper + 0.45 * (1 - upper)))
    lash = lash * (z > A["eye"] - 0.03).float()
    rgb = rgb * (1 - lash[:, None]) + f32([0.04, 0.03, 0.03]) * lash[:, None]
    # Eyebrows: a tapering arch of short hairs above each eye.
    t = (ax - (ex - 0.038)) / P["brow_length"]
    yb = E + P["brow_height"] + P["brow_arch"] * torch.sin(math.pi * t.clamp(0.0, 1.0) ** 0.8) + P["brow_tilt"] * t
    th = P["brow_thickness"] * (1.0 - 0.55 * t.clamp(0.0, 1.0))
    brow = torch.exp(-((y - yb) / th) ** 4) * smoothstep(-0.15, 0.05, t) * (1 - smoothstep(0.85, 1.1, t)) * front
    brow = brow * (0.8 + 0.2 * torch.sin(700.0 * x + 250.0 * y))
    rgb = rgb * (1 - 0.92 * brow[:, None]) + f32(P["brow_rgb"]) * 0.92 * brow[:, None]
    # Nostrils and the mouth line.
    tip_y = E - P["nose_length"] + P["nose_tilt"]
    nostril = gauss(ax - P["nose_width"] * 0.42, 0.008) * gauss(y - tip_y + 0.012, 0.006) * front
    mouth = gauss(y - my, 0.0032) * (1 - smoothstep(P["mouth_width"] * 0.85, P["mouth_width"] * 1.05, ax)) * front
    dark = (0.75 * nostril + 0.85 * mouth).clamp(0.0, 1.0)
    rgb = rgb * (1 - dark[:, None]) + f32([0.16, 0.05, 0.05]) * dark[:, None]
    # Beard shadow (stubble) over the jaw, chin and upper lip.
    if P["facial_hair"] != "none":
        region = _beard_region(p, P)
        s = 0.35 if P["facial_hair"] == "stubble" else 0.2
        rgb = rgb * (1 - s * region[:, None]) + f32(P["brow_rgb"]) * 0.6 * s * region[:, None]
    # Lines that come with age: nasolabial folds (from above the nose's wing, bowing out past the mouth
    # corner) and three forehead lines.
    old = oldness(P["age"])
    start = (P["nose_width"] + 0.006, tip_y + 0.01)
    bow = (P["mouth_width"] + 0.032, 0.5 * (tip_y + my))
    end = (P["mouth_width"] + 0.012, my - 0.022)
    fold = None
    for t in np.linspace(0.0, 1.0, 13):  # a quadratic Bezier curve, sampled
        cx, cy = ((1 - t) ** 2 * a + 2 * t * (1 - t) * b + t * t * c for a, b, c in zip(start, bow, end))
        dt = torch.sqrt((ax - cx) ** 2 + (y - cy) ** 2)
        fold = dt if fold is None else torch.minimum(fold, dt)
    lines = (0.05 + 0.3 * old) * gauss(fold, 0.0055)
    forehead = E + P["brow_height"] + 0.035
    lines = lines + 0.1 * old * sum(gauss(y - forehead - k * 0.02, 0.004) for k in range(3)) * (
        1 - smoothstep(0.05, 0.1, ax))
    return rgb * (1 - (lines * front).clamp(0.0, 0.8)[:, None])


def _beard_region(p, P):
    """0..1: where beard hair grows (jaw, chin, upper lip), on the front and sides of the lower face."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    my = P["mouth_y"]
    below_cheek = 1 - smoothstep(my + 0.02, my + 0.06, y + 0.3 * x.abs())
    on_jaw = smoothstep(P["chin_y"] - 0.035, P["chin_y"] + 0.005, y + 0.25 * (0.1 - z).clamp_min(0.0))
    forward = smoothstep(-0.08, 0.02, z)
    lips = gauss(y - my, 0.012) * (1 - smoothstep(P["mouth_width"] * 0.9, P["mouth_width"] * 1.1, x.abs()))
    return (below_cheek * on_jaw * forward * (1 - lips)).clamp(0.0, 1.0)


def facial_hair_field(p, P, A):
    """Moustache, beard or goatee as a shell over the skin; None without one."""
    kind = P["facial_hair"]
    if kind in ("none", "stubble"):
        return None
    x, y = p[:, 0], p[:, 1]
    my = P["mouth_y"]
    base = face_base(p, P)
    shell = base - (0.012 if kind == "beard" else 0.008)
    region = _beard_region(p, P)
    if kind == "moustache":
        region = region * gauss(y - (my + 0.016), 0.009) * (1 - smoothstep(P["mouth_width"], P["mouth_width"] + 0.015, x.abs()))
    elif kind == "goatee":  # a moustache and a rounded patch on the chin, from the lower lip down
        top, bottom = my - 0.008, P["chin_y"] - 0.012
        patch = (x / 0.034) ** 2 + ((y - 0.5 * (top + bottom)) / (0.5 * (top - bottom))) ** 2
        moustache = gauss(y - (my + 0.016), 0.009) * (1 - smoothstep(0.03, 0.05, x.abs()))
        region = region * torch.maximum(moustache, 1 - smoothstep(0.7, 1.0, patch))
    # The region (0..1, rising over 0.01 to 0.04 head units) scaled toward a distance: unscaled, its
    # gradient of up to ~90 leaves the baked band a voxel thin and the beard's edge in steps.
    d = smax(shell, 0.08 * (0.5 - region), 0.004) if kind != "beard" else smax(shell, 0.08 * (0.45 - region), 0.006)
    d = smax(d, -_lips(p, P, A) + 0.004, 0.003)
    return d
