"""The procedural head holds together for every sampled shape: the nose is closed underneath (a
columella joins its tip to the face), a ponytail lies on the head and neck, and the body seen from
below runs out of the picture; checked on the field at the ends of the sampled ranges and on renders."""
import itertools

import numpy as np
import pytest
import torch
from scipy import ndimage as ndi

from datagen.cameras import ViewSet
from datagen.generators.base import STREAM_LATENT, Subject, subject_rng
from datagen.generators.procedural import (BOX, HEAD_SCALE, ProceduralConfig, ProceduralHeads, bake_head, head_field,
                                           sample_params)
from datagen.generators.procedural.anatomy import anchors_of, cranium
from datagen.generators.procedural.hair import hair_field

GEN = ProceduralHeads(ProceduralConfig(grid_resolution=96, defect_rate=0.0))
NOSE = ("nose_length", "nose_projection", "nose_tilt", "nose_tip", "nose_width")


def people(n, seed=7):
    """``n`` sampled parameter sets (seed ``seed``, subjects 0..n-1)."""
    return [sample_params(subject_rng(seed, i, STREAM_LATENT)) for i in range(n)]


@pytest.fixture(scope="module")
def ranges():
    """The lowest and highest value of every nose parameter and of a ponytail's length over 3000 draws."""
    many = people(3000, seed=1)
    out = {k: (min(P[k] for P in many), max(P[k] for P in many)) for k in NOSE + ("nose_bridge",)}
    tails = [P["hair_length"] for P in many if P["hair_style"] == "ponytail"]
    out["hair_length"] = (min(tails), max(tails))
    return out


def sdf(points_head, P):
    """The whole head's signed distance (head units) at points given in head units."""
    world = torch.as_tensor(points_head, dtype=torch.float32) * HEAD_SCALE
    return head_field(world, P, [], colour=False)[0] / HEAD_SCALE


def views(yaw, pitch):
    """Cameras at the mean radius and FOV, at each of the yaws (degrees) and one pitch."""
    n = len(yaw)
    return ViewSet("360", np.asarray(yaw, float), np.full(n, float(pitch)), np.full(n, 2.7), np.full(n, 18.83),
                   (0.0, 0.0, 0.0))


def render(P, yaw, pitch, res=64):
    """Masks (alpha > 0.5) of the person ``P`` (no defects) seen from ``yaw`` at ``pitch``."""
    subject = Subject(index=0, seed=0, latent={"params": P}, state=bake_head(P, [], GEN.config.grid_resolution))
    return GEN.render(subject, views(yaw, pitch), res).alpha > 0.5


def pieces_and_holes(mask):
    """(connected parts of the silhouette, see-through holes in it), 8- and 4-connected."""
    _, parts = ndi.label(mask, structure=np.ones((3, 3), bool))
    _, holes = ndi.label(ndi.binary_fill_holes(mask) & ~mask)
    return parts, holes


def test_the_nose_is_closed_underneath_at_the_ends_of_every_range(ranges):
    """Every corner of the nose's ranges on three faces: the side profile between the bridge, the tip and
    the face (the triangle nasion - tip - subnasale in the midplane, up to the columella) is solid."""
    u, v = np.meshgrid(np.linspace(0, 1, 11), np.linspace(0, 1, 11))
    keep = u + v <= 0.9  # the lower edge (tip - subnasale) is the nose's underside: on the surface
    u, v = u[keep], v[keep]  # barycentric weights of the tip and of the subnasale
    for base in people(3):
        for corner in itertools.product(*((0, 1),) * len(NOSE)):
            P = dict(base, nose_bridge=ranges["nose_bridge"][0], nose_hump=1.0,
                     **{k: ranges[k][c] for k, c in zip(NOSE, corner)})
            A = anchors_of(P)
            E, L = P["eye_height"], P["nose_length"]
            nasion = np.array([0.0, E + 0.005, A["nasion"] - 0.01])
            tip = np.array([0.0, E - L + P["nose_tilt"], A["nose"] + P["nose_projection"] - P["nose_tip"]])
            subnasale = np.array([0.0, E - L - 0.008, A["nose"] - 0.01])
            pts = (1 - u - v)[:, None] * nasion + u[:, None] * tip + v[:, None] * subnasale
            d = sdf(pts, P)
            assert (d < 0).all(), (corner, pts[d >= 0][:3].tolist())


def test_a_long_hooked_nose_leaves_no_gap_in_profile(ranges):
    P = dict(people(1)[0], hair_style="crop", cap=False, glasses=False, nose_hump=1.0,
             nose_length=ranges["nose_length"][1], nose_projection=ranges["nose_projection"][1],
             nose_tilt=ranges["nose_tilt"][0], nose_tip=ranges["nose_tip"][0], nose_bridge=ranges["nose_bridge"][0])
    for mask in render(P, [90.0, 270.0, 75.0, 285.0], 0.0):
        assert pieces_and_holes(mask) == (1, 0)


def test_a_ponytail_lies_on_the_head_and_neck_down_to_its_end(ranges):
    """Rays from behind along the midline meet one solid (tail and head without air between them), and
    the tail's hair is on each ray, from its tie down to its end."""
    z = torch.linspace(-0.6, 0.0, 601)
    for base, length in itertools.product(people(4), ranges["hair_length"]):
        P = dict(base, hair_style="ponytail", hair_length=length, cap=False)
        A = anchors_of(P)
        for y in np.linspace(cranium(P)[0][1] + 0.05, length + 0.01, 12):
            pts = torch.stack([torch.zeros_like(z), torch.full_like(z, float(y)), z], dim=-1)
            inside = (sdf(pts, P) < 0).to(torch.int8)
            assert int((inside[1:] != inside[:-1]).sum()) == 1, (length, float(y))
            assert (hair_field(pts, P, A) < 0).any(), (length, float(y))


def test_a_ponytail_is_one_silhouette_without_gaps(ranges):
    for length in ranges["hair_length"]:
        P = dict(people(1, seed=3)[0], hair_style="ponytail", hair_length=length)
        for pitch in (0.0, -24.0):
            for mask in render(P, [90.0, 135.0, 225.0, 270.0], pitch):
                assert pieces_and_holes(mask) == (1, 0), (length, pitch)


def test_the_shoulders_run_down_out_of_the_box():
    """Seen from the side, the outer shoulder and arm (x from 0.1 inside the shoulder's end outward) are
    deepest where the box cuts them at its floor, not above it: a shoulder that rounded off inside the
    box showed from below as a ball under the chin."""
    floor = BOX / HEAD_SCALE
    ys = torch.linspace(-floor, -0.3, 58)
    zs = torch.linspace(-0.35, 0.3, 131)
    for P in people(3, seed=5):
        xs = torch.arange(P["shoulder_width"] - 0.1, floor, 0.01)
        x, y, z = torch.meshgrid(xs, ys, zs, indexing="ij")
        solid = (sdf(torch.stack([x, y, z], -1).reshape(-1, 3), P) < 0).reshape(x.shape).any(0)  # (y, z)
        depth = solid.sum(1).float() * float(zs[1] - zs[0])
        assert depth[0] > 0.2 and depth[0] >= depth.max() - 0.01, depth.tolist()


def test_seen_from_below_the_head_and_body_are_one_silhouette():
    for P in people(2, seed=5):
        for mask in render(dict(P, hair_style="crop"), [0.0, 60.0, 90.0, 120.0, 180.0, 270.0], -26.0):
            assert pieces_and_holes(mask) == (1, 0)
