"""Training and evaluation data: the subjects a manifest accepts, read from the shards by byte range.

Data flows one way: manifest -> subject list -> (global sample index -> subject, views) -> decoded
tensors. Which subject and which views a sample index ``g`` gets is a pure function of
(seed, g): epoch ``e = g // N`` visits the subjects in the permutation drawn from (seed, e), and
the N_v views come from (seed, g). A run resumed at step s therefore sees exactly the samples an
uninterrupted run would, on any number of processes and loader workers.

Images are (3, H, W) float32 in [0, 1] composited over white with the view's alpha (the procedural
generator already renders on white; for GAN backgrounds this drops the background so the Gaussians,
which model only the head, are compared on the same background). Cameras: OpenCV cam2world (4, 4)
and normalized intrinsics (3, 3), as stored (CONVENTIONS.md).
"""
from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from datagen.errors import UserError
from datagen.shards import decode_sample, read_fields, shard_index
from labeling_tool.manifest import read_manifest

BACKGROUND = (1.0, 1.0, 1.0)
SPLITS = ("train", "test")


def accepted_subjects(manifest: dict, split: str) -> list[tuple[str, int]]:
    """(subject id, shard) of the accepted subjects of ``split``, in manifest order."""
    if split not in SPLITS:
        raise UserError(f"unknown split {split!r}; choose train or test")
    out = [(s["subject"], shard_index(s["shard"])) for s in manifest["subjects"]
           if s.get("verdict") == "accepted" and s.get("split") == split]
    if not out:
        raise UserError(f"the manifest accepts no {split} subjects")
    return out


def _rng(seed: int, *stream: int) -> np.random.Generator:
    return np.random.default_rng([seed, *stream])


@dataclass(frozen=True)
class Views:
    """Some views of one subject: images (V, 3, H, W), masks (V, 1, H, W), cam2world (V, 4, 4), K (V, 3, 3)."""

    key: str
    images: torch.Tensor
    masks: torch.Tensor
    cam2world: torch.Tensor
    K: torch.Tensor
    yaw_deg: torch.Tensor
    planes: torch.Tensor | None = None


def load_views(root, key: str, shard: int, views=None, resolution: int | None = None) -> Views:
    """Decode views (indices, default all) of one subject, optionally resized to ``resolution`` px (area)."""
    sample = decode_sample(key, read_fields(root, shard, key), where=str(root))
    records = sample.metadata["views"]
    views = list(range(len(records))) if views is None else [int(v) for v in views]
    rgb = torch.from_numpy(np.stack([sample.rgb[v] for v in views])).float().div(255).permute(0, 3, 1, 2)
    alpha = torch.from_numpy(np.stack([sample.alpha[v] for v in views])).float().div(255)
    alpha = alpha.reshape(len(views), 1, *alpha.shape[-2:])
    bg = torch.tensor(BACKGROUND).view(1, 3, 1, 1)
    images = rgb * alpha + bg * (1 - alpha)
    if resolution is not None and resolution != images.shape[-1]:
        images = F.interpolate(images, size=(resolution, resolution), mode="area")
        alpha = F.interpolate(alpha, size=(resolution, resolution), mode="area")
    cam2world = torch.tensor([records[v]["cam2world"] for v in views], dtype=torch.float32)
    K = torch.tensor([records[v]["intrinsics"] for v in views], dtype=torch.float32)
    yaw = torch.tensor([records[v]["yaw_deg"] for v in views], dtype=torch.float32)
    planes = sample.arrays.get("planes")
    planes = None if planes is None else torch.from_numpy(np.asarray(planes, dtype=np.float32))
    return Views(key, images.clamp(0, 1), alpha.clamp(0, 1), cam2world, K, yaw, planes)


class TrainingSamples(torch.utils.data.Dataset):
    """Sample index g -> N_v views of one accepted training subject (the first view is the input)."""

    def __init__(self, root, manifest_path, split: str, views_per_sample: int, resolution: int, seed: int):
        self.root, self.seed = root, seed
        self.subjects = accepted_subjects(read_manifest(manifest_path), split)
        self.views_per_sample, self.resolution = views_per_sample, resolution
        key, shard = self.subjects[0]
        self.n_views = len(json.loads(read_fields(root, shard, key)["json"])["views"])
        if views_per_sample > self.n_views:
            raise UserError(f"{views_per_sample} views per sample, but subjects have {self.n_views}")

    def __len__(self) -> int:
        return len(self.subjects)

    def pick(self, g: int) -> tuple[tuple[str, int], list[int]]:
        """The subject and views of global sample ``g`` (pure function of seed and g)."""
        n = len(self.subjects)
        order = _rng(self.seed, 0, g // n).permutation(n)
        views = _rng(self.seed, 1, g).choice(self.n_views, self.views_per_sample, replace=False)
        return self.subjects[order[g % n]], [int(v) for v in views]

    def __getitem__(self, g: int) -> Views:
        (key, shard), views = self.pick(g)
        return load_views(self.root, key, shard, views, self.resolution)


def collate(items: list[Views]) -> Views:
    """Stack equally shaped Views into a batch (every tensor gains a leading B)."""
    planes = [v.planes for v in items]
    return Views(",".join(v.key for v in items), *(torch.stack([getattr(v, f) for v in items])
                                                    for f in ("images", "masks", "cam2world", "K", "yaw_deg")),
                 None if any(p is None for p in planes) else torch.stack(planes))
