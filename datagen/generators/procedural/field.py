"""The whole head as one field: signed distance and albedo of skin, features, clothing, facial hair,
hair, glasses, cap and the injected defects (``head_field``, world units in and out)."""
from __future__ import annotations

import torch

from .anatomy import EYE_RADIUS, anchors_of, eye_centre, face_base, facial_hair_field, face_features, skin_colour
from .clothing import cap_sdf, glasses_sdf, torso_sdf
from .inject import effects
from .hair import hair_field, hair_rgb_of, hair_strands
from .sdf import HEAD_SCALE, gauss, near_box, f32, wave_noise, sd_sphere, smax, smin


def head_field(p: torch.Tensor, P: dict, defects: list[dict], colour=True):
    """Signed distance (N,) and unshaded albedo (N, 3) of one head at world points p (N, 3). The
    albedo is None when ``colour`` is False (the distance alone is cheaper); ``colour`` may also be a
    function of the signed distance (world units) that says where the albedo is needed (zero elsewhere)."""
    sdf, rgb = _head_field_local(p / HEAD_SCALE, P, defects, colour)
    return sdf * HEAD_SCALE, rgb


def _body(p, P, A):
    """The skin surface with eye sockets, and the torso's skin; and the clothing's distance (1 with
    ``P["torso"]`` False: the head and neck alone, as the PanoLAM head template is made)."""
    body = face_base(p, P)
    for sx in (-1.0, 1.0):
        c = eye_centre(P, A, sx)
        body = smax(body, -sd_sphere(p, (c[0], c[1] + 0.004, c[2] + 0.012), EYE_RADIUS * 1.12), 0.018)
    if not P.get("torso", True):
        return body, torch.full_like(body, 1.0)
    sw = P["shoulder_width"] + 0.13
    (skin_d, _), (cloth_d, _) = near_box(p, (-sw, -1.2, -0.24), (sw, -0.14, 0.16),
                                       lambda q: [(d, None) for d in torso_sdf(q, P)], margin=0.05)
    return smin(body, skin_d, 0.04), cloth_d


def _head_field_local(p: torch.Tensor, P: dict, defects: list[dict], colour=True):
    """``head_field`` in head units."""
    A = anchors_of(P)
    injected = effects(p, P, A, defects)
    body, cloth_d = _body(p, P, A)
    parts = face_features(p, P, A) + [part for e in injected for part in e.features]

    # (sdf, albedo) of every part; the albedo is a callable so that it is only made when needed.
    sdf_parts = [(body, lambda q, sel: skin_rgb)]
    sdf = body
    for d, rgb, k in parts:
        sdf = smin(sdf, d, k) if k > 0 else torch.minimum(sdf, d)
        sdf_parts.append((d, (lambda q, sel: skin_rgb) if rgb is None else (lambda q, sel: lip_rgb)
                          if isinstance(rgb, str) else (lambda q, sel, rgb=rgb: rgb[sel])))
    sdf = torch.minimum(sdf, cloth_d)
    sdf_parts.append((cloth_d, lambda q, sel: f32(P["clothing_rgb"]) * (0.92 + 0.08 * torch.sin(q @ f32([9.0, 31.0, 5.0])))[:, None]))
    extra = []
    if P["facial_hair"] not in ("none", "stubble"):
        beard = near_box(p, (-0.2, P["chin_y"] - 0.08, -0.1), (0.2, P["mouth_y"] + 0.08, 0.3),
                       lambda q: [(facial_hair_field(q, P, A), None)])[0][0]
        extra.append((beard, lambda q, sel: f32(P["brow_rgb"]) * 1.1 * hair_strands(q * 1.6, P)[:, None]))
    hair = hair_field(p, P, A)
    if hair is not None:
        for e in injected:
            if e.hair_window is not None:
                hair = smax(hair, -e.hair_window, 0.01)
        extra.append((hair, lambda q, sel: hair_rgb_of(q, P)))
    if P["glasses"]:
        extra.append((glasses_sdf(p, P, A), lambda q, sel: f32(P["glasses_rgb"]).expand(q.shape[0], 3)))
    if P["cap"]:
        extra.append((cap_sdf(p, P), lambda q, sel: f32(P["cap_rgb"]).expand(q.shape[0], 3)))
    for d, albedo in extra + [part for e in injected for part in e.parts]:
        sdf_parts.append((d, albedo))
        sdf = torch.minimum(sdf, d)
    recolours = []
    for e in injected:
        if e.reshape is not None:
            sdf, recolour = e.reshape(sdf)
            if recolour is not None:
                recolours.append(recolour)
    if colour is False:
        return sdf, None
    # The albedo, where it is asked for.
    sel = torch.arange(p.shape[0]) if colour is True else torch.nonzero(colour(sdf * HEAD_SCALE)).squeeze(1)
    q = p[sel]
    skin_rgb = skin_colour(q, P, A)
    for e in injected:
        if e.skin is not None:
            skin_rgb = e.skin(skin_rgb, q, sel)
    lip_rgb = f32(P["lip_rgb"]) * (1.0 + 0.5 * wave_noise(q, P["skin_waves"][:2]))[:, None]
    mouth = gauss(q[:, 1] - P["mouth_y"], 0.003)
    lip_rgb = lip_rgb * (1 - 0.7 * mouth[:, None]) + f32([0.12, 0.03, 0.03]) * 0.7 * mouth[:, None]
    # Colour of the nearest part, softly blended across seams.
    d_all = torch.stack([d[sel] for d, _ in sdf_parts], dim=-1)
    w = torch.softmax(-(d_all - d_all.min(-1, keepdim=True).values) / 0.004, dim=-1)
    rgb = sum(w[:, i:i + 1] * c(q, sel) for i, (_, c) in enumerate(sdf_parts))
    for recolour in recolours:
        rgb = recolour(rgb, q, sel)
    if colour is not True:
        rgb = torch.zeros(p.shape[0], 3).index_put((sel,), rgb)
    return sdf, rgb.clamp(0.0, 1.0)
