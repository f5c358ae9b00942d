"""The GAN kinds: one row per 3D-GAN family, read by every place where the families differ.

Adding a backend is adding a row here (and, for a new plane layout, its sampler in
:data:`datagen.gans.triplane.PLANE_SAMPLERS`). This module imports no torch, so that the command
line can list the kinds without loading it.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

# 'auto': the originals' float16 blocks (super-resolution, and any backbone blocks the checkpoint
# marks fp16) run in float16 on CUDA and in float32 elsewhere, as in the originals; 'fp16' forces
# them to float16 on any device; 'fp32' never uses float16.
PRECISIONS = ("auto", "fp16", "fp32")


@dataclass(frozen=True)
class GANKind:
    """What sets one GAN family apart. D is the checkpoint's ``triplane_depth`` (1 where absent)."""

    name: str  # the --gan name, and the kind a checkpoint is recognised as
    source: str  # where its checkpoints come from (said when one is missing)
    layout: str  # its planes' sampler: a key of triplane.PLANE_SAMPLERS
    plane_shape: Callable[[int], tuple]  # D -> shape of its planes (of each projection's) before (H, W)
    backbone_channels: Callable[[int], int]  # D -> channels of the StyleGAN2 backbone's output
    backbone_resolution: int | None  # of the backbone's output, px; None: rendering_kwargs['triplane_size']
    projections: tuple  # names of the 1x1-conv modules that each turn the backbone output into a sphere
    sampled_planes: int  # planes sampled per 3D point (sizes the ray chunks)
    decoder_activation: str | None  # of the decoder's features; None: rendering_kwargs' (default sigmoid)
    crops_density: bool  # density -1e3 where |x| or |z| > box/2 - TRIPLANE_CROP
    panohead_modules: bool  # t_mapping, optional ToRGB and background (composited behind the render)
    protocol: str  # camera protocol it was trained on; its conditioning camera looks at that pivot
    recognise: Callable[[dict, dict], bool]  # (state dict, rendering_kwargs) -> of this kind or one built on it


def _panohead_checkpoint(state: dict, rendering_kwargs: dict) -> bool:
    """PanoHead's background or camera networks, or its tri-grid depth."""
    return bool(any(k.startswith(("bcg_synthesis.", "t_mapping.")) for k in state)
                or rendering_kwargs.get("triplane_depth"))


# Each kind is built on those listed before it: a checkpoint is the last kind that recognises it.
GAN_KINDS = {kind.name: kind for kind in (
    GANKind(name="eg3d",
            source="EG3D checkpoints (e.g. ffhq512-128.pkl, ffhqrebalanced512-128.pkl) come from NVIDIA's NGC "
                   "catalog, linked from github.com/NVlabs/eg3d (docs/models.md)",
            layout="triplane", plane_shape=lambda d: (3, 32), backbone_channels=lambda d: 32 * 3,
            backbone_resolution=256, projections=(), sampled_planes=3, decoder_activation="sigmoid",
            crops_density=False, panohead_modules=False, protocol="frontal", recognise=lambda state, rk: True),
    GANKind(name="panohead",
            source="PanoHead checkpoints (e.g. easy-khair-180-gpc0.8-trans10-025000.pkl) are linked from "
                   "github.com/SizheAn/PanoHead",
            layout="trigrid", plane_shape=lambda d: (3, 32 * d), backbone_channels=lambda d: 32 * 3 * d,
            backbone_resolution=None, projections=(), sampled_planes=3, decoder_activation=None,
            crops_density=True, panohead_modules=True, protocol="360", recognise=_panohead_checkpoint),
    GANKind(name="spherehead",
            source="SphereHead checkpoints (e.g. spherehead-ckpt-025000.pkl) are linked from "
                   "github.com/lhyfst/SphereHead",
            layout="spheres", plane_shape=lambda d: (d, 32), backbone_channels=lambda d: 512,
            backbone_resolution=None, projections=("ConvA", "ConvB"), sampled_planes=6, decoder_activation=None,
            crops_density=True, panohead_modules=True, protocol="360",
            recognise=lambda state, rk: "ConvA.0.weight" in state),
)}
KINDS = tuple(GAN_KINDS)


def gan_kind(name: str) -> GANKind:
    """The table's row for ``name``; ValueError for a name it lacks."""
    if name not in GAN_KINDS:
        raise ValueError(f"unknown generator kind {name!r}")
    return GAN_KINDS[name]
