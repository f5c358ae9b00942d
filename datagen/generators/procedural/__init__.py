"""The procedural head generator: the embedded default that needs no downloaded weights.

A subject is a person as an analytic signed-distance field with a colour field, both drawn from
the subject's seed: face shape, nose, lips, eyes, ears and brows, skin, sex and age, facial hair,
nine hair styles, glasses, caps, neck, shoulders and clothing (see ``sample_params``). Per subject
(once) the field is baked into a grid of signed distance and shaded colour: the distance coarse to
fine, exact in a narrow band around the surface, the colour only next to it. Per view, a sphere
tracer on that grid, inside the box around the head, finds where each ray meets it, and the shared
volume renderer integrates only a short band around that point (rays that miss get no samples;
the distance alone drives the sampling, the colour is looked up at the final intervals'
midpoints). Density is VolSDF's Laplace density of the signed distance, so alpha and depth are
those of the surface. Thin parts (cap brims, glasses rims) are at least two grid voxels thick, so
that a ray meets one clean edge.

Defects modelled on 3D-GAN failures can be injected at a set rate (``DEFECT_TYPES``, in ``defects``); what
was injected, with its severity, is returned as ``Subject.truth``.

Units: world units (the head is about 0.5 wide, the box is [-0.48, 0.48]^3); y up, face toward +z.

Modules: ``params`` (sampling a person), ``shapes`` (units, signed-distance building blocks),
``anatomy`` (face and head, skin albedo), ``hair``, ``clothing`` (clothing, glasses, cap),
``defects`` (sampling and applying each defect class), ``field`` (the whole head), ``bake`` (the
grid), ``generator`` (tracing and rendering; ``ProceduralHeads``).
"""
from .bake import HeadGrid, bake_head, sample_grid
from .inject import DEFECT_TYPES, sample_defects
from .field import head_field
from .generator import ProceduralConfig, ProceduralHeads, laplace_density, sphere_trace, trace_interval
from .params import HAIR_STYLES, LUMA, SKIN_TONES, sample_params
from .sdf import BOX, HEAD_SCALE

__all__ = ["BOX", "DEFECT_TYPES", "HAIR_STYLES", "HEAD_SCALE", "LUMA", "SKIN_TONES", "HeadGrid", "ProceduralConfig",
           "ProceduralHeads", "bake_head", "head_field", "laplace_density", "sample_defects", "sample_grid",
           "sample_params", "sphere_trace", "trace_interval"]
