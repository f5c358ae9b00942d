"""Sampling a person: shape, colours and accessories drawn from the subject's random generator.

Every value is JSON-ready (floats, strings, lists). Lengths are in head units (world units /
HEAD_SCALE); the face looks toward +z. The draws happen in a fixed order (the groups below, in the
order ``sample_params`` calls them), so a seed always makes the same person.
"""
from __future__ import annotations

import math

import numpy as np

HAIR_STYLES = ("bald", "crop", "side_part", "fringe", "bob", "long", "ponytail", "bun", "afro")
# Skin albedo (sRGB) at the centre of each tone bracket, light to dark (brackets as Fitzpatrick I-VI).
SKIN_TONES = ("I", "II", "III", "IV", "V", "VI")
LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 luminance weights
SKIN_PALETTE = np.array([[0.96, 0.82, 0.73], [0.91, 0.73, 0.60], [0.82, 0.61, 0.46],
                         [0.66, 0.46, 0.32], [0.47, 0.31, 0.21], [0.30, 0.19, 0.13]])
HAIR_COLOURS = {
    "black": [0.08, 0.068, 0.06], "dark_brown": [0.13, 0.08, 0.05], "brown": [0.30, 0.19, 0.11],
    "light_brown": [0.50, 0.35, 0.21], "auburn": [0.48, 0.19, 0.08], "red": [0.66, 0.29, 0.12],
    "blond": [0.80, 0.64, 0.40], "platinum": [0.90, 0.84, 0.70], "grey": [0.56, 0.55, 0.53],
    "white": [0.86, 0.85, 0.83], "dyed": None,
}
DYES = [[0.75, 0.15, 0.45], [0.15, 0.35, 0.75], [0.55, 0.25, 0.70], [0.20, 0.60, 0.50], [0.85, 0.35, 0.55]]
IRIS_COLOURS = {"dark_brown": [0.16, 0.09, 0.05], "brown": [0.33, 0.19, 0.08], "hazel": [0.42, 0.33, 0.14],
                "green": [0.27, 0.40, 0.22], "blue": [0.25, 0.42, 0.62], "grey": [0.45, 0.50, 0.54]}
LIPSTICKS = [[0.62, 0.10, 0.14], [0.78, 0.36, 0.40], [0.55, 0.22, 0.22], [0.70, 0.28, 0.33]]
EYE_SHADOWS = [[0.75, 0.62, 0.62], [0.62, 0.55, 0.65], [0.7, 0.6, 0.5]]  # multiplies the skin's albedo
CLOTHING_COLOURS = [[0.10, 0.11, 0.14], [0.92, 0.92, 0.90], [0.20, 0.27, 0.45], [0.55, 0.12, 0.13],
                    [0.28, 0.40, 0.26], [0.55, 0.55, 0.57], [0.80, 0.66, 0.36], [0.35, 0.22, 0.42],
                    [0.60, 0.75, 0.85], [0.85, 0.45, 0.30]]
# Glasses frames: (albedo, wire). A wire frame (metal, about 1 mm) is thinner than the rim the grid can
# hold (>= 2 voxels, ~4 mm): its colour is mixed with the skin's by the share of the rim a wire covers, as
# a camera's pixels would mix them (drawn at full strength, bright rims on dark skin hid the eyes).
GLASSES_FRAMES = {"black": ([0.05, 0.05, 0.05], False), "gold": ([0.55, 0.45, 0.25], True),
                  "silver": ([0.6, 0.6, 0.65], True), "tortoise": ([0.35, 0.12, 0.1], False)}
WIRE_COVER = 0.35
AGE_BRACKETS = ((18, 30, "18-29"), (30, 45, "30-44"), (45, 60, "45-59"), (60, 200, "60+"))
# Hair style probabilities by sex (HAIR_STYLES order).
STYLE_PROBS = {"female": [0.02, 0.05, 0.10, 0.13, 0.14, 0.24, 0.13, 0.11, 0.08],
               "male": [0.13, 0.27, 0.20, 0.09, 0.04, 0.06, 0.05, 0.04, 0.12]}


def pick_one(rng, options, probs=None):
    """One of ``options``, uniformly or with weights ``probs`` (normalised here)."""
    if probs is not None:
        probs = np.asarray(probs, dtype=np.float64)
        probs = probs / probs.sum()
    return options[int(rng.choice(len(options), p=probs))]


def oldness(age: float) -> float:
    """0 at 18, 1 at 80: how far age has worked on a face."""
    return (age - 18.0) / 62.0


def age_bracket(age: float) -> str:
    return next(name for lo, hi, name in AGE_BRACKETS if lo <= age < hi)


def _frame_rgb(frame: str, skin) -> list:
    rgb, wire = GLASSES_FRAMES[frame]
    rgb = np.asarray(rgb)
    return list(WIRE_COVER * rgb + (1 - WIRE_COVER) * np.asarray(skin) if wire else rgb)


def _hair_colour(rng, age):
    """Natural colours by default (greyer with age); unnatural dyes are rare (2 %)."""
    grey = float(np.clip((age - 40) / 35, 0.0, 0.85))
    names = ["black", "dark_brown", "brown", "light_brown", "auburn", "red", "blond", "platinum", "grey", "white", "dyed"]
    probs = np.array([0.22, 0.22, 0.17, 0.10, 0.06, 0.03, 0.11, 0.03, 0.0, 0.0, 0.0]) * (1 - grey)
    probs[8], probs[9] = 0.7 * grey, 0.3 * grey
    probs = probs / probs.sum() * 0.98
    probs[10] = 0.02
    name = pick_one(rng, names, probs)
    rgb = HAIR_COLOURS[name]
    if rgb is None:
        rgb = pick_one(rng, DYES)
    jitter = rng.uniform(0.9, 1.1, 3)
    # Brightness varies +-10 %, hue little: independent channels turned grey hair green or pink.
    jitter = jitter.mean() + 0.25 * (jitter - jitter.mean())
    rgb = np.clip(np.asarray(rgb) * jitter, 0.0, 1.0)
    return name, rgb


def _person(u, rng) -> dict:
    """Sex, masculinity (0..1, about 0.2 for women and 0.8 for men), age (years) and weight (0..1)."""
    sex = pick_one(rng, ["female", "male"])
    masc = float(np.clip((0.8 if sex == "male" else 0.2) + rng.normal(0.0, 0.08), 0.0, 1.0))
    age = u(18.0, 80.0)
    return {"sex": sex, "age": age, "age_bracket": age_bracket(age), "masculinity": masc, "weight": u(0.0, 1.0)}


def _skin(u) -> tuple[float, dict]:
    """The skin tone (0 light .. 1 dark) and its albedo, interpolated in SKIN_PALETTE and jittered."""
    tone = u(0.0, 1.0)
    k = tone * (len(SKIN_PALETTE) - 1)
    i0 = min(int(k), len(SKIN_PALETTE) - 2)
    skin = SKIN_PALETTE[i0] * (1 - (k - i0)) + SKIN_PALETTE[i0 + 1] * (k - i0)
    skin = skin * np.array([1.0, u(0.96, 1.03), u(0.93, 1.05)]) * u(0.96, 1.04)
    skin = np.clip(skin, 0.0, 1.0)
    return tone, {"skin_tone": SKIN_TONES[min(int(tone * 6), 5)], "skin_rgb": list(skin)}


def _hair_colour_and_style(u, rng, person) -> tuple[float, dict]:
    """Hair colour and style, with the style's thickness and length (head units; every style's
    thickness range and three lengths are drawn whatever the style); and how far the hairline
    recedes (0..1, with age and masculinity)."""
    name, rgb = _hair_colour(rng, person["age"])
    style = pick_one(rng, list(HAIR_STYLES), STYLE_PROBS[person["sex"]])
    receding = u(0.0, 1.0) * oldness(person["age"]) * person["masculinity"]
    thickness = {"bald": 0.0, "crop": u(0.010, 0.018), "side_part": u(0.022, 0.034), "fringe": u(0.02, 0.03),
                 "bob": u(0.022, 0.032), "long": u(0.018, 0.03), "ponytail": u(0.010, 0.016),
                 "bun": u(0.010, 0.016), "afro": u(0.06, 0.10)}[style]
    length = {"bob": u(-0.22, -0.15), "long": u(-0.62, -0.45), "ponytail": u(-0.34, -0.2)}.get(style, 0.0)
    return receding, {"hair_style": style, "hair_colour": name, "hair_rgb": list(rgb), "hair_thickness": thickness,
                      "hair_length": length}


def _iris(rng, tone) -> str:
    """The iris colour's name; dark eyes are likelier on dark skin (tone > 0.55)."""
    dark = tone > 0.55
    return pick_one(rng, list(IRIS_COLOURS), [0.6, 0.3, 0.06, 0.01, 0.02, 0.01] if dark else [0.12, 0.25, 0.16, 0.14, 0.23, 0.10])


def _grooming(rng, P) -> dict:
    """Facial hair (men), make-up (women: painted lips) and the colours of lips and brows."""
    male = P["sex"] == "male"
    skin = np.asarray(P["skin_rgb"])
    facial_hair = "none"
    if male:
        facial_hair = pick_one(rng, ["none", "stubble", "moustache", "beard", "goatee"], [0.45, 0.2, 0.07, 0.18, 0.10])
    makeup = (not male) and rng.uniform() < 0.45
    lip_base = skin * np.array([0.86, 0.60, 0.60]) + np.array([0.07, 0.0, 0.01])
    if makeup:
        paint = pick_one(rng, LIPSTICKS)
        lip_base = 0.35 * lip_base + 0.65 * np.asarray(paint)
    hair_name, hair_rgb = P["hair_colour"], np.asarray(P["hair_rgb"])
    brow_rgb = hair_rgb * 0.75 if hair_name not in ("dyed", "platinum", "white") else np.asarray(
        HAIR_COLOURS["brown"]) * (0.7 + 1.2 * (hair_name != "dyed") * oldness(P["age"]))
    if hair_name in ("blond", "light_brown", "red"):
        brow_rgb = hair_rgb * 0.55
    # Brows stay visible: at most 0.55 of the skin's luminance (grey brows on tan skin vanish otherwise,
    # and with them what face detectors and recognisers look for).
    brow_rgb = brow_rgb * min(1.0, 0.55 * float(skin @ LUMA) / max(float(brow_rgb @ LUMA), 1e-6))
    return {"facial_hair": facial_hair, "makeup": bool(makeup), "lip_rgb": list(np.clip(lip_base, 0.0, 1.0)),
            "brow_rgb": list(np.clip(brow_rgb, 0.0, 1.0))}


def _profile(u, masc, dim) -> dict:
    """Heights down the face's midline: eyes, mouth and chin (y), and the nose's length."""
    eye_height = u(0.018, 0.04)
    nose_length = u(0.07, 0.13) + 0.01 * masc
    mouth_y = eye_height - nose_length - u(0.04, 0.065)
    chin_y = mouth_y - u(0.08, 0.125) - 0.012 * masc
    return {"eye_height": eye_height, "nose_length": nose_length + 0.016 * dim, "mouth_y": mouth_y,
            "chin_y": chin_y - 0.02 * dim}


def _head_shape(u, P, dim) -> dict:
    """Skull, face mass, cheeks, jaw, chin and brow ridge."""
    masc, weight, old = P["masculinity"], P["weight"], oldness(P["age"])
    return {
        "skull_radii": [u(0.182, 0.2) + 0.01 * masc, u(0.215, 0.24), u(0.225, 0.25) + 0.01 * masc],
        "skull_center_y": u(0.035, 0.06),
        "face_width": u(0.145, 0.2) + 0.012 * masc + 0.016 * dim,
        "cheekbone": u(0.0, 1.0),
        "cheek_fat": min(1.0, u(0.0, 0.6) + 0.6 * weight) * (1.0 - 0.4 * old),
        "jaw_width": u(0.075, 0.135) + 0.025 * masc + 0.025 * weight + 0.04 * dim,
        "jaw_angle_y": u(-0.17, -0.12),
        "chin_width": max(0.012, u(0.018, 0.04) + 0.018 * masc + 0.024 * dim),  # > 0: the jaw tapers to it
        "chin_projection": u(-0.012, 0.018),
        "brow_ridge": float(np.clip(u(0.0, 0.45) + 0.6 * masc * u(0.4, 1.0) + 0.6 * dim, 0.0, 1.0)),
        "forehead_slope": u(0.0, 1.0) * (0.4 + 0.6 * masc),
    }


def _eye_shape(u, P, dim, iris) -> dict:
    """Eyes: x of each eye, the opening's half-width, half-height and tilt, and the iris's colour."""
    masc, old = P["masculinity"], oldness(P["age"])
    return {
        "eye_spacing": u(0.064, 0.098),
        # The opening's height is 0.6-1.0 of the iris's diameter, as in most adults: the lids cover the
        # iris's top and often its bottom (wider openings gave goggle eyes, sclera all round the iris).
        "eye_width": u(0.03, 0.042) - 0.002 * masc,
        "eye_open": max(0.004, u(0.008, 0.015) - 0.002 * old - 0.004 * dim),
        "eye_tilt": u(-0.12, 0.22),
        "iris": iris, "iris_rgb": list(np.clip(np.asarray(IRIS_COLOURS[iris]) * u(0.85, 1.15), 0, 1)),
    }


def _nose_shape(u, masc, dim) -> dict:
    """Nose: projection, half-width at the wings, bridge and tip radii, hump (0..1) and tip tilt (y)."""
    return {
        "nose_projection": u(0.025, 0.075) + 0.008 * masc,
        "nose_width": max(0.014, u(0.02, 0.058) + 0.006 * masc + 0.012 * dim),
        "nose_bridge": u(0.011, 0.017) + 0.003 * masc,
        "nose_tip": u(0.013, 0.022),
        "nose_hump": u(0.0, 1.0) * (0.3 + 0.7 * masc),
        "nose_tilt": u(-0.012, 0.014),
    }


def _mouth_shape(u, rng, P, dim) -> dict:
    """The mouth's width and the lips' half-heights; then the eye shadow's colour (drawn for everyone,
    worn with make-up)."""
    masc, old = P["masculinity"], oldness(P["age"])
    return {
        "mouth_width": u(0.034, 0.072) + 0.004 * masc,
        # Half-heights of the lips; at least 0.005 (thinner, a lip is less than a grid voxel thick at 128^3).
        "upper_lip": max(0.005, u(0.006, 0.014) - 0.002 * old + 0.002 * (1 - masc) - 0.003 * dim),
        "lower_lip": max(0.005, u(0.008, 0.018) - 0.002 * old + 0.002 * (1 - masc) - 0.003 * dim),
        "eye_shadow_rgb": list(np.clip(np.asarray(P["skin_rgb"]) * pick_one(rng, EYE_SHADOWS), 0, 1)),
    }


def _ears_and_build(u, P) -> dict:
    """Ears, neck and shoulders."""
    masc, old = P["masculinity"], oldness(P["age"])
    return {
        "ear_size": u(0.045, 0.056) + 0.006 * old,
        "ear_protrusion": u(0.0, 1.0),
        "ear_y": P["eye_height"] - u(0.025, 0.04),
        "neck_radius": u(0.08, 0.092) + 0.02 * masc + 0.015 * P["weight"],
        "shoulder_width": u(0.38, 0.41) + 0.03 * masc,  # the arms hang from here; their outer side stays inside the box
    }


def _skin_marks(u, rng, P) -> dict:
    """Blush, shadows under the eyes and the skin's mottling (sinusoids: amplitude, wave vector, phase)."""
    return {
        "cheek_blush": u(0.03, 0.16) * (1.2 if P["makeup"] else 1.0),
        "under_eye": u(0.03, 0.10) + 0.06 * oldness(P["age"]),
        "skin_waves": [[u(0.01, 0.025), list(rng.normal(0, 22, 3)), u(0, 6.3)] for _ in range(4)],
    }


def _brow_shape(u, masc, dim) -> dict:
    """Brows: thickness, arch, length, height above the eyes and tilt."""
    return {
        "brow_thickness": max(0.003, u(0.004, 0.013) + 0.004 * masc + 0.006 * dim),
        "brow_arch": u(0.002, 0.012) * (1.2 - 0.6 * masc) * (1.0 - dim),
        "brow_length": u(0.05, 0.066),
        "brow_height": u(0.027, 0.05) - 0.012 * dim,
        "brow_tilt": u(-0.01, 0.012),
    }


def _hair_shape(u, rng, eye_height, receding) -> dict:
    """Hairline, parting (signed x: the side), volume and the seeds of the strands' texture."""
    return {
        "hairline_height": eye_height + u(0.14, 0.18) + 0.05 * receding,
        "hair_part": float(rng.choice([-1.0, 1.0])) * u(0.03, 0.07),
        "hair_volume": u(0.0, 1.0),
        "hair_seed": [list(rng.normal(0.0, 1.0, 3)) for _ in range(6)],
    }


def _accessories(rng, P) -> dict:
    """Glasses (more often with age), a cap, and the clothing's colour and neckline."""
    return {
        "glasses": bool(rng.uniform() < 0.12 + 0.12 * oldness(P["age"])),
        "glasses_shape": pick_one(rng, ["round", "rectangular"]),
        "glasses_rgb": _frame_rgb(pick_one(rng, list(GLASSES_FRAMES)), np.asarray(P["skin_rgb"])),
        "cap": bool(rng.uniform() < 0.1),
        "cap_rgb": list(rng.uniform(0.05, 0.9, 3)),
        "clothing_rgb": list(np.clip(np.asarray(pick_one(rng, CLOTHING_COLOURS)) * rng.uniform(0.85, 1.1, 3), 0, 1)),
        "neckline": pick_one(rng, ["crew", "v", "collar"]),
    }


def _lighting(u, light_az, skin) -> dict:
    """The key light's direction (azimuth ``light_az``, radians from +z), ambient share and exposure."""
    return {
        "light_dir": [math.sin(light_az) * 0.9, u(0.25, 0.7), math.cos(light_az) * 0.9],
        # Soft light, as in most portrait photos (harder light made the faces' shading, alike for all,
        # outweigh what tells people apart).
        "ambient": u(0.62, 0.75),
        # Exposure as a camera metering on the face would set it: darker skin is exposed up to 1.35x.
        "exposure": min(1.35, max(1.0, (0.42 / float(skin @ LUMA)) ** 0.4)),
    }


def sample_params(rng: np.random.Generator, dimorphism: float = 1.0) -> dict:
    """Draw one person's shape, colours and accessories (JSON-ready floats, strings and lists).

    Lengths are in head units (world units / HEAD_SCALE); the face looks toward +z. ``dimorphism``
    scales how far sex moves the face's shape beyond its masculinity terms (0 for a sex-neutral head,
    as the model's embedded template is made of).
    """
    u = lambda a, b: float(rng.uniform(a, b))
    P = _person(u, rng)
    tone, skin = _skin(u)
    P |= skin
    receding, hair = _hair_colour_and_style(u, rng, P)
    P |= hair
    iris = _iris(rng, tone)
    P |= _grooming(rng, P)
    masc = P["masculinity"]
    # Sexual dimorphism on top of the terms in ``masc``: -1 feminine .. +1 masculine (about +-0.9
    # for most people; the ranges assume |dim| <= 1). Masculine faces: wider jaw and chin, heavier
    # brow ridge and brows, lower and flatter brows, longer and wider nose, longer chin, thinner lips,
    # narrower eyes. With it a face recogniser places two people of different sex further apart than two
    # of the same sex.
    dim = float(np.clip(3.0 * (masc - 0.5), -1.0, 1.0)) * dimorphism
    P |= _profile(u, masc, dim)
    light_az = u(-0.6, 0.6)
    P |= _head_shape(u, P, dim)
    P |= _eye_shape(u, P, dim, iris)
    P |= _nose_shape(u, masc, dim)
    P |= _mouth_shape(u, rng, P, dim)
    P |= _ears_and_build(u, P)
    P |= _skin_marks(u, rng, P)
    P |= _brow_shape(u, masc, dim)
    P |= _hair_shape(u, rng, P["eye_height"], receding)
    P |= _accessories(rng, P)
    P |= _lighting(u, light_az, np.asarray(P["skin_rgb"]))
    return P
