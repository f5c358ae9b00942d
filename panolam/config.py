"""Model configuration: one dataclass, named presets, ablation switches.

``full`` carries the paper's values (DINOv2 ViT-L/14 layers 5/12/18/24 fused to C_t = 512 tokens,
a 5,023-vertex template, 8 blocks of 16 heads, M_D ~ 10K dense Gaussians, a 6 x 64 x 64 spherical
tri-plane queried by K_m = 32 samples on rays from 4 virtual cameras, offsets clamped to 0.15 m
(coarse) and 0.056 m (dense)). ``tiny`` keeps every stage but is sized to train on a 2-core CPU.

Lengths named ``*_m`` are in FLAME metres, as in the paper; the model converts them to world units
with the template's ``units_per_metre``. Other lengths are world units (CONVENTIONS.md: the head is
about one unit tall). Ablations (the paper's): ``coarse_to_fine=False`` regresses the dense points
directly from the attention stack; ``triplane="point"`` queries the tri-plane at the point only;
``triplane="none"`` drops the branch.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

TRIPLANE_MODES = ("rays", "point", "none")
PATH_FIELDS = ("encoder_weights", "template", "spherehead_checkpoint")  # name files, which may move


@dataclass(frozen=True)
class ModelConfig:
    name: str = "tiny"
    # image encoder
    encoder: str = "small"                     # "dinov2" (frozen, weights from the user) or "small" (from scratch)
    encoder_weights: Optional[str] = None      # DINOv2: a Hugging Face folder or Meta's .pth
    encoder_layers: tuple = (2, 4)             # 1-based blocks whose normalized outputs are fused
    image_size: int = 128                      # encoder input, px (images are resized to it)
    patch_size: int = 8                        # small encoder only
    encoder_width: int = 192                   # small encoder only
    encoder_depth: int = 4                     # small encoder only
    token_dim: int = 192                       # C_t
    # template and coarse stage
    template: Optional[str] = None             # a FLAME model file; None: the embedded head template
    template_vertices: int = 1280              # embedded template size
    pe_frequencies: int = 8                    # NeRF encoding: sin/cos of 2^k pi x, k < this
    blocks: int = 4                            # L: cross-attention blocks of the point tokens
    heads: int = 4
    point_self_attention: bool = True          # self-attention among point tokens in every block
    head_hidden: int = 128                     # width of the 3-layer Gaussian decoder heads
    coarse_offset_m: float = 0.15              # eps_OC
    dense_offset_m: float = 0.056              # eps_OD
    coarse_scale_range: tuple = (0.003, 0.08)  # world units, bounds of the scale activation
    dense_scale_range: tuple = (0.001, 0.04)
    # densification
    coarse_to_fine: bool = True
    dense_points: int = 5000                   # M_D target (the barycentric split reaches it closely)
    # spherical tri-plane branch
    triplane: str = "rays"                     # TRIPLANE_MODES
    triplane_resolution: int = 16              # H_T = W_T
    triplane_channels: int = 32                # SphereHead's plane channels
    triplane_blocks: int = 2
    ray_samples: int = 8                       # K_m per virtual camera
    ray_half_length_m: float = 0.02            # samples lie within +- this of the point along each ray
    virtual_camera_radius: float = 2.7         # world units, the 4 cameras (front, left, right, back)
    box_warp: float = 1.0                      # SphereHead's tri-plane extent, world units
    triplane_aggregate_dim: int = 64           # width of the aggregated tri-plane feature per point
    spherehead_checkpoint: Optional[str] = None  # frozen SphereHead decoder; None: a small trainable one
    triplane_render_resolution: int = 32       # px of the branch's own supervision image
    triplane_render_views: Optional[int] = 2   # targets per sample it renders (None: all); its loss weighs 0.1
    triplane_render_samples: tuple = (12, 12)  # stratified, importance samples per ray

    def __post_init__(self):
        if self.triplane not in TRIPLANE_MODES:
            raise ValueError(f"triplane must be one of {TRIPLANE_MODES}, not {self.triplane!r}")
        if self.encoder not in ("dinov2", "small"):
            raise ValueError(f"encoder must be 'dinov2' or 'small', not {self.encoder!r}")
        if self.token_dim % self.heads:
            raise ValueError(f"token_dim {self.token_dim} is not divisible by heads {self.heads}")

    def replace(self, **changes) -> "ModelConfig":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> "ModelConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown model settings: {', '.join(unknown)}")
        tuples = {k: tuple(v) for k, v in values.items() if isinstance(v, list)}
        return cls(**{**values, **tuples})


PRESETS = {
    "tiny": ModelConfig(),
    "full": ModelConfig(
        name="full", encoder="dinov2", encoder_layers=(5, 12, 18, 24), image_size=518, token_dim=512,
        template_vertices=5023, blocks=8, heads=16, head_hidden=512, dense_points=10000,
        triplane_resolution=64, triplane_blocks=2, ray_samples=32, triplane_aggregate_dim=256,
        triplane_render_resolution=64, triplane_render_samples=(48, 48), triplane_render_views=None),
}

ABLATIONS = {
    "no_c2f": dict(coarse_to_fine=False),
    "single_point": dict(triplane="point"),
    "no_triplane": dict(triplane="none"),
}


def preset(name: str, **overrides) -> ModelConfig:
    """A named preset, optionally with an ablation suffix (``tiny+no_c2f``) and field overrides."""
    base, *ablations = name.split("+")
    if base not in PRESETS:
        raise ValueError(f"unknown config {base!r}; choose from {', '.join(PRESETS)}")
    changes = {}
    for a in ablations:
        if a not in ABLATIONS:
            raise ValueError(f"unknown ablation {a!r}; choose from {', '.join(ABLATIONS)}")
        changes.update(ABLATIONS[a])
    return PRESETS[base].replace(name=name, **changes, **overrides)
