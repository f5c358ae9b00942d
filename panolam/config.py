"""Configuration: the model (one dataclass, named presets, ablation switches) and training.

``full`` carries the paper's values (DINOv2 ViT-L/14 layers 5/12/18/24 fused to C_t = 512 tokens,
a 5,023-vertex template, 8 blocks of 16 heads, M_D ~ 10K dense Gaussians, a 6 x 64 x 64 spherical
tri-plane queried by K_m = 32 samples on rays from 4 virtual cameras, offsets clamped to 0.15 m
(coarse) and 0.056 m (dense)). ``tiny`` keeps every stage but is sized to train on a 2-core CPU; its
K_m = 2: a ray's +-0.02 m (0.08 world units) spans about 1.2 texels of its 16 x 16 planes, so more
samples read the same texels (K_m = 8 cost ~45 % of a training step for no measured gain).

Lengths named ``*_m`` are in FLAME metres, as in the paper; the model converts them to world units
with the template's ``units_per_metre``. Other lengths are world units (:mod:`datagen.cameras`: the head is
about one unit tall). Ablations (the paper's): ``coarse_to_fine=False`` regresses the dense points
directly from the attention stack; ``triplane="point"`` queries the tri-plane at the point only;
``triplane="none"`` drops the branch. ``cross_only`` keeps the paper's blocks exactly: point tokens
cross-attend to the image and do not attend to each other.

Fields made with :func:`datagen.command_line.setting` are also command-line options, with that help.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

from datagen.command_line import at_least, non_negative, path_fields, positive, setting, unit_interval

TRIPLANE_MODES = ("rays", "point", "none")
INPUT_VIEW_POLICIES = ("frontal", "any")
TARGET_POLICIES = ("all", "others")


@dataclass(frozen=True)
class ModelConfig:
    name: str = "tiny"
    # image encoder
    encoder: str = "small"                     # "dinov2" (frozen, weights from the user) or "small" (from scratch)
    encoder_weights: Optional[str] = setting(None, "DINOv2 weights (Hugging Face folder or Meta .pth); needed by "
                                                   "'full'", path=True)
    encoder_layers: tuple = (2, 4)             # 1-based blocks whose normalized outputs are fused
    image_size: int = 128                      # encoder input, px (images are resized to it)
    patch_size: int = 8                        # small encoder only
    encoder_width: int = 192                   # small encoder only
    encoder_depth: int = 4                     # small encoder only
    token_dim: int = 192                       # C_t
    # template and coarse stage
    template: Optional[str] = setting(None, "a FLAME model file (default: the embedded head template)", path=True)
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
    ray_samples: int = 2                       # K_m per virtual camera: 2 span ~1.2 texels of 16 x 16 planes
    ray_half_length_m: float = 0.02            # samples lie within +- this of the point along each ray
    virtual_camera_radius: float = 2.7         # world units, the 4 cameras (front, left, right, back)
    box_warp: float = 1.0                      # SphereHead's tri-plane extent, world units
    triplane_aggregate_dim: int = 64           # width of the aggregated tri-plane feature per point
    spherehead_checkpoint: Optional[str] = setting(
        None, "a SphereHead checkpoint whose frozen decoder renders the tri-plane branch (default: a small "
              "trainable decoder)", flag="--spherehead", path=True)
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
        return _from_dict(cls, values)


def _from_dict(cls, values: dict):
    """A config from its ``to_dict`` (JSON turns tuples into lists); ValueError on an unknown setting."""
    unknown = sorted(set(values) - {f.name for f in dataclasses.fields(cls)})
    if unknown:
        raise ValueError(f"unknown settings: {', '.join(unknown)}")
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})


PATH_FIELDS = path_fields(ModelConfig)  # name files, which may move


@dataclass(frozen=True)
class TrainConfig:
    """Training settings; every field is a ``panolam train`` option (its help is the text here)."""

    steps: int = setting(2000, "optimizer steps; the cosine schedule ends there", parse=at_least(1), fixed=True)
    batch_size: int = setting(2, "subjects per step and process", parse=at_least(1), fixed=True)
    views_per_sample: int = setting(6, "N_v views per sample: 1 input and N_v - 1 other views", parse=at_least(2),
                                    fixed=True)
    input_views: str = setting("frontal", "the views a sample's input is drawn from: within the frontal yaw range "
                                          "(+-36 deg), as evaluation feeds, or any (the paper's)",
                               choices=INPUT_VIEW_POLICIES, fixed=True)
    targets: str = setting("all", "views the renders are supervised on: all N_v (the input view among them) or "
                                  "the N_v - 1 others", choices=TARGET_POLICIES, fixed=True)
    render_resolution: int = setting(64, "px of the supervised renders (targets are area-resized)",
                                     parse=at_least(16), fixed=True)
    lr: float = setting(4e-4, "peak learning rate", parse=positive, fixed=True)
    betas: tuple = setting((0.9, 0.95), "Adam's beta1 beta2", parse=unit_interval, nargs=2, fixed=True)
    warmup_steps: int = setting(100, "linear warm-up steps", parse=at_least(0), fixed=True)
    lr_floor: float = setting(0.1, "the cosine decay ends at this fraction of the peak learning rate",
                              parse=unit_interval, fixed=True)
    grad_clip: float = setting(1.0, "gradient-norm clipping threshold", parse=positive, fixed=True)
    lambda_l1: float = setting(1.0, "lambda_1, weight of L1 in L_rgb", parse=non_negative, fixed=True)
    lambda_perceptual: float = setting(1.0, "lambda_2, weight of the perceptual term in L_rgb", parse=non_negative,
                                       fixed=True)
    lambda_gaussians: float = setting(1.0, "lambda_3, weight of L_rgb of the Gaussian renders", parse=non_negative,
                                      fixed=True)
    lambda_triplane_rgb: float = setting(0.1, "lambda_4, weight of L_rgb of the tri-plane render",
                                         parse=non_negative, fixed=True)
    lambda_mask: float = setting(1.0, "lambda_5, weight of the silhouette L1", parse=non_negative, fixed=True)
    lambda_planes: float = setting(1e-4, "lambda_6, weight of the tri-plane feature L1", parse=non_negative,
                                   fixed=True)
    lpips_backbone: Optional[str] = setting(None, "torchvision-format AlexNet/VGG16 weights for LPIPS")
    lpips_lin: Optional[str] = setting(None, "LPIPS linear-layer weights (alex.pth / vgg.pth)")
    lpips_net: str = setting("alex", "LPIPS backbone", choices=("alex", "vgg"))
    rasterizer: str = setting("auto", "Gaussian rasterizer: gsplat's CUDA kernels for CUDA tensors when they load, "
                                      "else the pure-PyTorch one (auto); or either one",
                              choices=("auto", "torch", "gsplat"))
    seed: int = setting(0, "data order and initialisation", parse=at_least(0), fixed=True)
    num_workers: int = setting(0, "data loader processes; 0 loads in this process", parse=at_least(0), flag="--workers")
    log_every: int = setting(10, "steps between TensorBoard scalars and console lines", parse=at_least(1))
    image_every: int = setting(200, "steps between TensorBoard image grids", parse=at_least(1))
    checkpoint_every: int = setting(100, "steps between checkpoints", parse=at_least(1))
    time_limit_s: Optional[float] = setting(None, "seconds; stop with a checkpoint before a step that would end "
                                                  "later (predicted from the steps so far)", parse=positive,
                                            flag="--time-limit")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> "TrainConfig":
        """A config from its ``to_dict``; settings a run predates take the value it trained with
        (:data:`LEGACY_TRAINING`), so older runs resume and report what they did."""
        return _from_dict(cls, {**LEGACY_TRAINING, **values})


# What runs written before a setting existed did: inputs from any view, the other views as targets, cosine to 0.
LEGACY_TRAINING = {"input_views": "any", "targets": "others", "lr_floor": 0.0}

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
    # not an ablation of the paper's: its point tokens only cross-attend to the image; tiny's also attend to
    # each other in every block (about a quarter of a CPU training step)
    "cross_only": dict(point_self_attention=False),
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
