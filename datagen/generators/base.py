"""The interface every head generator implements (procedural now; 3D GANs share it).

A generator first samples a subject from (dataset seed, subject index): all per-subject work
(for a GAN: mapping + backbone; for the procedural head: building its field) happens there, once.
It then renders any batch of views of that subject, reusing that work.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..cameras import ViewSet


def subject_rng(dataset_seed: int, subject_index: int, stream: int) -> np.random.Generator:
    """The random stream ``stream`` of one subject, seeded only by (dataset seed, subject index)."""
    return np.random.default_rng([int(dataset_seed), int(subject_index), int(stream)])


# Stream ids: one independent random stream per purpose, so adding draws to one never shifts another.
STREAM_LATENT, STREAM_CAMERAS, STREAM_RENDER = 0, 1, 2


@dataclass
class Subject:
    """One sampled subject.

    latent: JSON-ready description recorded with the subject (for a GAN: truncation, conditioning).
    truth: ground truth only the generator knows (e.g. injected defects); stored apart from what
    reviewers see. state: the generator's precomputed per-subject data, reused for every view.
    arrays: numeric data stored with the subject as ``.npy`` fields (for a GAN: z, w, planes).
    """

    index: int
    seed: int
    latent: dict
    truth: dict = field(default_factory=dict)
    state: Any = None
    arrays: dict = field(default_factory=dict)


@dataclass
class RenderedViews:
    """Views of one subject: rgb (V,H,W,3) in [0,1] on the background, alpha (V,H,W) in [0,1],
    depth (V,H,W) as distance along the ray in world units (0 where alpha is 0)."""

    rgb: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray


class Generator(abc.ABC):
    name: str = ""

    @abc.abstractmethod
    def describe(self) -> dict:
        """Provenance: generator name, checkpoint sha256 (or None), configuration."""

    @abc.abstractmethod
    def sample_subject(self, dataset_seed: int, index: int) -> Subject:
        """Sample subject ``index`` of a dataset seeded with ``dataset_seed`` (per-subject work happens here)."""

    @abc.abstractmethod
    def render(self, subject: Subject, views: ViewSet, resolution: int) -> RenderedViews:
        """Render a batch of views of ``subject`` at ``resolution`` x ``resolution``."""
