"""Training and evaluation data: the subjects a manifest accepts, read from the shards by byte range.

Data flows one way: manifest -> subject list -> (global sample index -> subject, views) -> decoded
tensors. Which subject and which views a sample index ``g`` gets is a pure function of
(seed, g): epoch ``e = g // N`` visits the subjects in the permutation drawn from (seed, e), and
the N_v views come from (seed, g). A run resumed at step s therefore sees exactly the samples an
uninterrupted run would, on any number of processes and loader workers.

Images are (3, H, W) float32 in [0, 1] composited over white with the view's alpha (the procedural
generator already renders on white; for GAN backgrounds this drops the background so the Gaussians,
which model only the head, are compared on the same background). Cameras: OpenCV cam2world (4, 4)
and normalized intrinsics (3, 3), as stored (:mod:`datagen.cameras`). The model's input (the first view) is
resized from the stored image to the encoder's input size, apart from the targets, which are resized
to the render resolution: the encoder sees the same detail in training as on a photo.
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from datagen.cameras import FRONTAL_YAW_DEG, angle_between
from datagen.errors import DatasetError, UserError
from datagen.dataset.manifests import check_dataset, read_manifest
from datagen.dataset import Dataset
from datagen.dataset.shards import decode_sample, read_fields, shard_index, tar_path

BACKGROUND = (1.0, 1.0, 1.0)
SPHEREHEAD_PLANES_NDIM = 5  # (2, D, C, R, R); EG3D's and PanoHead's are (3, C, R, R)
SPLITS = ("train", "test")


def accepted_subjects(manifest: dict, split: str, dataset=None) -> list[tuple[str, int]]:
    """(subject id, shard) of the accepted subjects of ``split``, in manifest order.

    With ``dataset`` (a Dataset or its folder), the manifest must have been compiled for it (UserError otherwise).
    """
    if dataset is not None:
        check_dataset(manifest, dataset)
    if split not in SPLITS:
        raise UserError(f"unknown split {split!r}; choose train or test")
    out = [(s["subject"], shard_index(s["shard"])) for s in manifest["subjects"]
           if s.get("verdict") == "accepted" and s.get("split") == split]
    if not out:
        raise UserError(f"the manifest accepts no {split} subjects")
    return out


def check_subject_shards(dataset, subjects: list[tuple[str, int]]) -> None:
    """DatasetError naming the first shard holding one of ``subjects`` of ``dataset`` (a Dataset or its
    folder) that fails the fast integrity
    check (:func:`datagen.dataset.shards.check_shards`: sidecar, size, sha256, subjects and byte ranges; cached,
    so cheap the second time)."""
    problems = list(Dataset.of(dataset).check_shards({shard for _, shard in subjects}).values())
    if problems:
        more = f" (and {len(problems) - 1} more problems: run datagen verify)" if len(problems) > 1 else ""
        raise DatasetError(problems[0] + more)


def _rng(seed: int, *stream: int) -> np.random.Generator:
    return np.random.default_rng([seed, *stream])


@dataclass(frozen=True)
class Views:
    """Some views of one subject: images (V, 3, H, W), masks (V, 1, H, W), cam2world (V, 4, 4), K (V, 3, 3),
    yaw (deg) and camera radius (world units, to the look-at pivot) per view.

    ``planes``: SphereHead's plane features (2, D, C, R, R) when the dataset stores them (other GANs'
    planes are left out: the tri-plane branch is distilled from SphereHead's). ``inputs`` (3, H_in,
    W_in): the first view at the encoder's input size, when it was asked for.
    """

    key: str
    images: torch.Tensor
    masks: torch.Tensor
    cam2world: torch.Tensor
    K: torch.Tensor
    yaw_deg: torch.Tensor
    radius: torch.Tensor
    planes: torch.Tensor | None = None
    inputs: torch.Tensor | None = None

    def to(self, device) -> "Views":
        return Views(**{f.name: v.to(device) if torch.is_tensor(v) else v
                        for f in dataclasses.fields(self) for v in [getattr(self, f.name)]})


def resized(images: torch.Tensor, size: int) -> torch.Tensor:
    """(N, C, H, W) -> (N, C, size, size): area average to shrink, bilinear to enlarge."""
    if images.shape[-2:] == (size, size):
        return images
    if size < images.shape[-1]:
        return F.interpolate(images, size=(size, size), mode="area")
    return F.interpolate(images, size=(size, size), mode="bilinear", align_corners=False)


def load_views(root, key: str, shard: int, views=None, resolution: int | None = None,
               input_resolution: int | None = None) -> Views:
    """Decode views (indices, default all) of one subject, optionally resized to ``resolution`` px.

    With ``input_resolution``, ``inputs`` holds the first of these views resized from the stored image.
    """
    return decode_views(key, read_fields(root, shard, key), views, resolution, input_resolution,
                        str(tar_path(root, shard)))


def decode_views(key: str, fields: dict, views=None, resolution: int | None = None,
                 input_resolution: int | None = None, where: str = "") -> Views:
    """:func:`load_views` on a subject's raw fields (:func:`datagen.dataset.shards.read_fields`); ``where``
    (the shard file) starts a decoding error's message, which names the subject."""
    if views is None:
        views = range(len(json.loads(fields["json"])["views"]))
    views = [int(v) for v in views]
    sample = decode_sample(key, fields, where=where, views=views, depth=False)
    records = sample.metadata["views"]
    rgb = torch.from_numpy(np.stack(sample.rgb)).float().div(255).permute(0, 3, 1, 2)
    alpha = torch.from_numpy(np.stack(sample.alpha)).float().div(255)
    alpha = alpha.reshape(len(views), 1, *alpha.shape[-2:])
    bg = torch.tensor(BACKGROUND).view(1, 3, 1, 1)
    images = rgb * alpha + bg * (1 - alpha)
    inputs = None if input_resolution is None else resized(images[:1], input_resolution)[0].clamp(0, 1)
    if resolution is not None:
        images, alpha = resized(images, resolution), resized(alpha, resolution)
    cam2world = torch.tensor([records[v]["cam2world"] for v in views], dtype=torch.float32)
    K = torch.tensor([records[v]["intrinsics"] for v in views], dtype=torch.float32)
    yaw = torch.tensor([records[v]["yaw_deg"] for v in views], dtype=torch.float32)
    radius = torch.tensor([records[v]["radius"] for v in views], dtype=torch.float32)
    planes = sample.arrays.get("planes")
    if planes is not None and np.ndim(planes) == SPHEREHEAD_PLANES_NDIM:
        planes = torch.from_numpy(np.asarray(planes, dtype=np.float32))
    else:
        planes = None
    return Views(key, images.clamp(0, 1), alpha.clamp(0, 1), cam2world, K, yaw, radius, planes, inputs)


def view_yaws(fields: dict) -> np.ndarray:
    """The yaw (deg) of each stored view of a subject, from its raw fields' metadata alone."""
    return np.array([v["yaw_deg"] for v in json.loads(fields["json"])["views"]])


class TrainingSamples(torch.utils.data.Dataset):
    """Sample index g -> N_v views of one accepted training subject (the first view is the input)."""

    def __init__(self, root, manifest_path, split: str, views_per_sample: int, resolution: int, seed: int,
                 input_resolution: int | None = None, input_views: str = "any"):
        self.root, self.seed, self.input_views = root, seed, input_views
        dataset = Dataset(root)
        self.subjects = accepted_subjects(read_manifest(manifest_path), split, dataset)
        check_subject_shards(dataset, self.subjects)
        self.views_per_sample, self.resolution, self.input_resolution = views_per_sample, resolution, input_resolution
        key, shard = self.subjects[0]
        n = len(view_yaws(read_fields(root, shard, key)))
        if views_per_sample > n:
            raise UserError(f"{views_per_sample} views per sample, but subjects have {n}")

    def __len__(self) -> int:
        return len(self.subjects)

    def pick(self, g: int) -> tuple[str, int]:
        """The subject (id, shard) of global sample ``g``: epoch g // N visits all N in a seeded order."""
        n = len(self.subjects)
        return self.subjects[_rng(self.seed, 0, g // n).permutation(n)[g % n]]

    def view_choice(self, g: int, n_views: int, yaw_deg=None) -> list[int]:
        """The N_v distinct views of global sample ``g`` among its subject's ``n_views`` (the first is the input).

        With the ``frontal`` input policy (``yaw_deg``: the views' yaws) the input is drawn among the views
        within +-FRONTAL_YAW_DEG of yaw 0 (the one nearest yaw 0 when there is none), the others among the rest.
        """
        rng = _rng(self.seed, 1, g)
        if self.input_views == "any":
            return [int(v) for v in rng.choice(n_views, self.views_per_sample, replace=False)]
        off = angle_between(yaw_deg)
        frontal = np.flatnonzero(off <= FRONTAL_YAW_DEG)
        first = int(rng.choice(frontal)) if len(frontal) else int(off.argmin())
        rest = np.delete(np.arange(n_views), first)
        return [first] + [int(v) for v in rng.choice(rest, self.views_per_sample - 1, replace=False)]

    def __getitem__(self, g: int) -> Views:
        key, shard = self.pick(g)
        fields = read_fields(self.root, shard, key)
        yaws = view_yaws(fields)
        n = len(yaws)
        if n < self.views_per_sample:
            raise UserError(f"{self.root}: subject {key} has {n} views, fewer than {self.views_per_sample} per sample")
        return decode_views(key, fields, self.view_choice(g, n, yaws), self.resolution, self.input_resolution,
                            str(tar_path(self.root, shard)))


def collate(items: list[Views]) -> Views:
    """Stack equally shaped Views into a batch (every tensor gains a leading B; a field any item lacks is None)."""
    def stacked(name):
        values = [getattr(v, name) for v in items]
        return None if any(x is None for x in values) else torch.stack(values)
    return Views(",".join(v.key for v in items), **{f.name: stacked(f.name) for f in dataclasses.fields(Views)
                                                     if f.name != "key"})
