"""Reconstructions as a dataset: each subject's reconstruction (from its front view, as ``panolam eval``
feeds it) rendered from every one of its stored cameras, written in the dataset format.

The folder has the source's shard numbering and subject ids, its cameras and metadata, and the
reconstruction's colour, alpha and depth (distance along the unit ray from the camera centre, world
units, 0 where nothing was rendered; the rasterizer's expected camera-space z times the ray's length
per unit z), so everything that reads datasets reads it: ``label-tool auto`` measures which defects
a model draws, ``label-tool review`` shows them, ``datagen verify`` checks them.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from datagen.cameras import camera_directions
from datagen.errors import UserError
from datagen.files import atomic_write
from datagen.dataset import Dataset
from datagen.dataset.shards import (INDEX_NAME, ShardWriter, dumps, encode_subject, read_fields, shard_index,
                            tar_path)

from .data import BACKGROUND, decode_views, view_yaws
from .evaluate import nearest_views
from .gaussians import Gaussians
from .rasterizer import render_views


def ray_lengths(K_norm: np.ndarray, resolution: int) -> np.ndarray:
    """(H, W): the length of each pixel's camera ray per unit of camera-space z."""
    rows, cols = np.mgrid[:resolution, :resolution]
    return np.linalg.norm(camera_directions(K_norm, resolution, rows.ravel(), cols.ravel()), axis=-1).reshape(
        resolution, resolution)


@torch.no_grad()
def write_reconstructions(model, data, subjects: list[tuple[str, int]], out) -> Path:
    """Write the reconstructions of ``subjects`` ((id, shard) of the dataset ``data``) as a dataset in ``out``.

    A subject without a view near the front (see :func:`panolam.evaluate.nearest_views`) is left out.
    """
    out = Path(out)
    if (out / INDEX_NAME).exists():
        raise UserError(f"{out} already holds a dataset; choose another folder for the renders")
    device = next(model.parameters()).device
    index = Dataset.of(data).index
    out.mkdir(parents=True, exist_ok=True)
    by_shard: dict[int, list[str]] = {}
    for key, shard in subjects:
        by_shard.setdefault(shard, []).append(key)
    written = {}
    for shard, keys in sorted(by_shard.items()):
        writer = ShardWriter(out, shard)
        try:
            for key in keys:
                fields = read_fields(data, shard, key)
                yaws = view_yaws(fields)
                picked = nearest_views(yaws)
                if picked is None:
                    continue
                n = len(yaws)
                front = picked["front"]
                views = decode_views(key, fields, [front] + [v for v in range(n) if v != front], None,
                                     model.cfg.image_size, str(tar_path(data, shard)))
                rec = model(views.inputs[None].to(device)).dense
                g = Gaussians(*(t.float() for t in (rec.means, rec.quats, rec.scales, rec.opacities, rec.colors)))
                res = views.images.shape[-1]
                rgb, alpha, depth = render_views(g, views.cam2world[None].to(device), views.K[None].to(device), res,
                                                 background=torch.tensor(BACKGROUND, device=device))
                order = np.argsort([front] + [v for v in range(n) if v != front])  # back to stored view order
                rgb, alpha, depth = (t[0].cpu().numpy()[order] for t in (rgb, alpha, depth))
                K = views.K.numpy()[order]
                ray = np.stack([ray_lengths(k, res) for k in K])[..., None]
                depth = np.where(alpha > 1e-3, depth * ray, 0.0)[..., 0].astype(np.float32)
                metadata = json.loads(fields["json"])
                metadata["reconstruction"] = {"input_view": front}
                writer.add_subject(key, encode_subject(metadata, rgb.clip(0, 1), alpha[..., 0].clip(0, 1), depth))
                written.setdefault(shard, []).append(key)
            if written.get(shard):
                writer.commit({"views_per_subject": n})
            else:
                writer.abort()
        except BaseException:
            writer.abort()
            raise
    shards = [dict(s, subjects=written[shard_index(s["name"])]) for s in index["shards"]
              if written.get(shard_index(s["name"]))]
    atomic_write(out / INDEX_NAME, dumps({**index, "shards": shards, "num_subjects": sum(map(len, written.values())),
                                          "reconstructions_of": str(Path(data).resolve())}))
    return out
