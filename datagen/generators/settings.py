"""The generators' settings: one dataclass per generator, each field that ``datagen sample`` offers declared
once (:func:`datagen.command_line.setting`) and every value checked when the settings are made, so a library
caller and the command line get the same errors (:class:`datagen.errors.SettingError`). Imports no torch:
the command line builds its options from these at once.
"""
from __future__ import annotations

import argparse
import math
from dataclasses import dataclass

from ..command_line import setting
from ..defects import INJECTED
from ..errors import SettingError
from ..gans.kinds import PRECISIONS

# GAN settings that change how the work is split, not what is computed: not recorded with the data.
NOT_RECORDED = ("device", "memory_budget_mb")
NAMED_COLOURS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0), "grey": (0.5, 0.5, 0.5)}


def background_colour(text: str):
    """'own', a named colour or R,G,B in [0, 1] -> 'own' or an (r, g, b) tuple (an argparse type)."""
    if text == "own":
        return text
    if text in NAMED_COLOURS:
        return NAMED_COLOURS[text]
    try:
        rgb = tuple(float(v) for v in text.split(","))
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        raise argparse.ArgumentTypeError(f"must be own (GANs), white, black, grey or R,G,B with values in [0, 1], "
                                         f"not {text!r}")
    return rgb


def names(text: str) -> tuple:
    """'a,b' -> ('a', 'b') (an argparse type; empty names dropped)."""
    return tuple(k.strip() for k in text.split(",") if k.strip())


def number_pair(text: str) -> tuple:
    """'LO,HI' -> (lo, hi), NaN for what is not a number (checked by the settings; an argparse type)."""
    def number(v: str) -> float:
        try:
            return float(v)
        except ValueError:
            return math.nan
    values = tuple(number(v) for v in text.split(","))
    return values if len(values) == 2 else (math.nan, math.nan)


@dataclass(frozen=True)
class ProceduralConfig:
    """Settings of the procedural generator (``--gan procedural``)."""

    grid_resolution: int = 128
    defect_rate: float = setting(0.04, "fraction of subjects with an injected defect, 0 to 1", parse=float)
    defect_types: tuple = setting(INJECTED, "the defect classes drawn (uniformly) when a defect is injected",
                                  parse=names, metavar="A,B")
    defect_severity: tuple = setting((0.3, 1.0), "severity range of injected defects (0: barely there, 1: gross)",
                                     parse=number_pair, metavar="LO,HI")
    background: tuple = setting((1.0, 1.0, 1.0), "white, black, grey or R,G,B in [0, 1] (default: white); GANs "
                                                 "also 'own', their generated background (their default)",
                                parse=background_colour)
    beta: float = 0.003           # width of the density transition (world units)
    band_before: float = 0.015    # sampled band around the sphere-traced hit (world units)
    band_after: float = 0.05
    # Samples in the band (colour at interval midpoints): deterministic (6, 6) reaches 53.6 dB
    # foreground PSNR (51.7 on the worst of 4 subjects) against a (96, 96) reference; (8, 8) 60 dB.
    samples: int = 6              # coarse samples in the band
    samples_importance: int = 6   # importance samples in the band
    max_bands: int = 3            # bands per ray (more only where a ray grazes a thin edge)
    deterministic: bool = True

    def __post_init__(self):
        if not 0.0 <= self.defect_rate <= 1.0:
            raise SettingError("{defect_rate} must be between 0 and 1")
        unknown = [k for k in self.defect_types if k not in INJECTED]
        if not self.defect_types or unknown:
            raise SettingError(f"{{defect_types}}: unknown {', '.join(unknown) or '(none given)'}; choose from "
                               f"{', '.join(INJECTED)}")
        lo, hi = self.defect_severity
        if not 0.0 <= lo <= hi <= 1.0:
            raise SettingError("{defect_severity} must be LO,HI with 0 <= LO <= HI <= 1")
        if isinstance(self.background, str) or len(self.background) != 3 \
                or not all(isinstance(v, (int, float)) and 0.0 <= v <= 1.0 for v in self.background):
            raise SettingError("{background} must be white, black, grey or R,G,B with values in [0, 1] for the "
                               "procedural generator ('own' is the GANs' own background)")


@dataclass(frozen=True)
class GANConfig:
    """Settings of the GAN generators. truncation_cutoff None = all layers. background: 'own' (the GAN's own:
    EG3D black, PanoHead/SphereHead their generated background) or a solid colour composited with the mask.
    save_planes: resolution at which the plane features are stored in fp16 (0 = not stored). precision:
    'auto' (the originals' fp16 blocks in fp16 on CUDA, fp32 on CPU), 'fp32' or 'fp16'. clip_rays: clip each
    ray's sample range to the generator's box and skip rays that miss it (the originals march the whole
    range). memory_budget_mb: working memory that sets the chunk and batch sizes (0 = the device's default)."""

    truncation_psi: float = setting(0.7, "truncation psi, 0 to 2", parse=float, flag="--truncation")
    truncation_cutoff: int | None = setting(14, "truncate the first N ws", parse=int, metavar="N")
    background: object = setting("own", "'own' or a solid colour", parse=background_colour)
    save_planes: int = setting(0, "also store the plane features in fp16 at RES x RES, 8 to 1024 (for distillation)",
                               parse=int, metavar="RES")
    deterministic: bool = False
    noise_mode: str = "const"
    device: str = setting("auto", "cpu, cuda (every GPU, see --workers), cuda:N (that GPU only; local backend) or "
                                  "auto (cuda when available). The procedural generator runs on the CPU")
    precision: str = setting("auto", "'auto' runs the originals' fp16 blocks (the super-resolution of the released "
                                     "checkpoints) in fp16 on CUDA and everything in fp32 on CPU; 'fp32' never uses "
                                     "fp16", choices=PRECISIONS)
    clip_rays: bool = setting(False, "march each ray only where it crosses the generator's box and skip rays that "
                                     "miss it (the originals march the whole ray range)")
    memory_budget_mb: float = setting(0, "working memory per chunk of rays / batch of super-resolved views (default "
                                         "64 on CPU, a quarter of the GPU's memory on CUDA)", parse=float, metavar="MB")

    def __post_init__(self):
        if not 0.0 <= self.truncation_psi <= 2.0:
            raise SettingError("{truncation_psi} must be between 0 and 2")
        if self.truncation_cutoff is not None and self.truncation_cutoff < 0:
            raise SettingError("{truncation_cutoff} must be at least 0")
        if self.save_planes and not 8 <= self.save_planes <= 1024:
            raise SettingError("{save_planes} must be between 8 and 1024")
        if self.precision not in PRECISIONS:
            raise SettingError(f"{{precision}} {self.precision!r}: choose one of {', '.join(PRECISIONS)}")
        if not (math.isfinite(self.memory_budget_mb) and self.memory_budget_mb >= 0):
            raise SettingError("{memory_budget_mb} must be above 0 (or 0 for the device's default)")
