"""A dataset job (:class:`JobSpec`): everything that determines a dataset's bytes, each setting declared once
(the ``datagen sample`` options come from these fields) and checked in :meth:`JobSpec.check`, which names
settings by field (:class:`datagen.errors.SettingError`). Imports no torch.
"""
from __future__ import annotations

import argparse
import math
from dataclasses import asdict, dataclass, field

from .cameras import PROTOCOLS
from .command_line import setting
from .errors import SettingError
from .generators import AVAILABLE, GANS
from .generators.settings import NOT_RECORDED
from .runner import ArrayJobOptions
from .shapes import check_resolution


@dataclass(frozen=True)
class JobSpec:
    """Everything that determines a dataset's bytes (plus where to write it)."""

    out: str = setting(None, "output dataset folder", required=True)
    gan: str = setting("procedural", "head generator", choices=AVAILABLE)
    checkpoint: str | None = setting(None, "generator checkpoint file (GAN generators)")
    generator_options: dict = field(default_factory=dict)
    protocol: str = setting("360", "camera protocol", choices=PROTOCOLS)
    subjects: int = setting(16, "number of subjects", parse=int)
    resolution: int = setting(128, "image size in pixels (square)", parse=int)
    views: int = setting(32, "views per subject (paper: 32)", parse=int)
    seed: int = setting(0, "dataset seed; every draw derives from (seed, subject)", parse=int)
    shard_size: int = setting(8, "subjects per shard", parse=int)
    software: dict = field(default_factory=dict)
    save_shape: int = setting(0, "also store each subject's head surface, meshed on a RES^3 grid over the generator's "
                                 "box, as shape.ply in its record (binary PLY with vertex colours, world units; see "
                                 "datagen shape)", parse=int, metavar="RES")
    shape_level: float | None = setting(None, "GANs with --save-shape: the raw density level of the surface (default "
                                              "10, the originals')", parse=float, metavar="L")

    @property
    def num_shard_files(self) -> int:
        return -(-self.subjects // self.shard_size)

    def shard_subjects(self, shard: int) -> range:
        return range(shard * self.shard_size, min(self.subjects, (shard + 1) * self.shard_size))

    def check(self) -> None:
        """A SettingError for a value or combination that cannot make a dataset."""
        if self.protocol not in PROTOCOLS:
            raise SettingError(f"{{protocol}} {self.protocol!r}: choose one of {', '.join(PROTOCOLS)}")
        checks = [(self.subjects >= 1, "{subjects} must be at least 1"),
                  (16 <= self.resolution <= 4096, "{resolution} must be between 16 and 4096"),
                  (1 <= self.views <= 1024, "{views} must be between 1 and 1024"),
                  (self.shard_size >= 1, "{shard_size} must be at least 1"),
                  (self.seed >= 0, "{seed} must be non-negative")]
        for ok, message in checks:
            if not ok:
                raise SettingError(message)
        if self.save_shape:
            check_resolution(self.save_shape, "save_shape")
        if self.shape_level is not None:
            if not self.save_shape:
                raise SettingError("{shape_level}: only with {save_shape}")
            if self.gan not in GANS:
                raise SettingError("{shape_level}: only for the GAN generators (the procedural surface is the zero "
                                   "level of its signed distance)")
            if not math.isfinite(self.shape_level):
                raise SettingError("{shape_level} must be a finite number")

    def settings(self) -> dict:
        """What the index records: the job less its output folder and the generator options that
        only place or split the work (device, memory budget), so a dataset is the same, and resumes,
        wherever it runs. The shape settings appear only when shapes are stored (a dataset without
        them has the index it had before shapes existed)."""
        s = asdict(self)
        s.pop("out")
        if not self.save_shape:
            del s["save_shape"], s["shape_level"]
        s["generator_options"] = {k: v for k, v in s["generator_options"].items() if k not in NOT_RECORDED}
        return s


def parse_workers(text: str):
    """'auto' or a whole number (checked by the pipeline)."""
    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be auto or a number, not {text!r}") from None


@dataclass(frozen=True)
class SampleOptions(ArrayJobOptions):
    """Where ``datagen sample`` renders a job (none of it changes the dataset's bytes)."""

    workers: int | str = setting(1, "worker processes on this machine: N, or auto = one per GPU on CUDA (one with "
                                    "--device cuda:N), else one per CPU core up to this job's shard count. On CUDA "
                                    "worker k renders on cuda:(k mod the GPU count), so more workers than GPUs share "
                                    "them; --device cuda:N puts all on GPU N. With --backend ray, each task gets the "
                                    "CPU cores divided by N", parse=parse_workers, metavar="auto|N")
    gpus_per_task: float | None = setting(None, "--backend ray with CUDA: the share of one GPU each shard task asks "
                                                "Ray for, in (0, 1]; 0.5 runs two tasks per GPU (default 1). Each task "
                                                "renders on the GPU Ray gives it", parse=float, metavar="G")
    resume: bool = setting(False, "skip complete shards, redo partial ones")
    quiet: bool = setting(False, "no progress bar")
