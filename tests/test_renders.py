"""Reconstructions written as a dataset (panolam eval --renders): readable by everything that reads
datasets, same cameras, depth in the datasets' convention, views in their stored order."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from datagen.cameras import depth_points
from datagen.dataset.shards import decode_sample, read_fields
from datagen.verify import verify_dataset
from labeling_tool.preflags import score_dataset
from panolam.data import BACKGROUND, accepted_subjects, load_views
from panolam.gaussians import Gaussians
from panolam.model import PanoLAM
from panolam.rasterizer import render_views
from panolam.renders import write_reconstructions
from tests.conftest import curated_dataset
from tests.test_train import MODEL


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    root = tmp_path_factory.mktemp("renders")
    data, manifest = curated_dataset(root, subjects=4, views=8, test_count=2)
    torch.manual_seed(0)
    model = PanoLAM(MODEL).eval()
    subjects = accepted_subjects(json.loads(manifest.read_text()), "test", data)
    return model, data, subjects, write_reconstructions(model, data, subjects, root / "renders")


def test_the_renders_are_a_dataset_that_verifies_and_scores(written):
    _, data, subjects, out = written
    report = verify_dataset(out)
    assert report["problems"] == [] and report["complete"] == report["shards"]
    assert sorted(s for sh in json.loads((out / "index.json").read_text())["shards"] for s in sh["subjects"]) == \
        sorted(k for k, _ in subjects)
    scored = score_dataset(out, false_alarm_rate=0)
    assert {r["subject"] for r in scored["subjects"]} == {k for k, _ in subjects}


def test_cameras_order_and_depth_follow_the_source(written):
    model, data, subjects, out = written
    key, shard = subjects[0]
    source = decode_sample(key, read_fields(data, shard, key), depth=False)
    ours = decode_sample(key, read_fields(out, shard, key))
    assert [v["cam2world"] for v in ours.metadata["views"]] == [v["cam2world"] for v in source.metadata["views"]]
    views = load_views(data, key, shard, input_resolution=model.cfg.image_size)
    front = ours.metadata["reconstruction"]["input_view"]
    with torch.no_grad():
        d = model(load_views(data, key, shard, views=[front], input_resolution=model.cfg.image_size)
                  .inputs[None]).dense
        g = Gaussians(d.means, d.quats, d.scales, d.opacities, d.colors)
        res = views.images.shape[-1]
        rgb, alpha, z = render_views(g, views.cam2world[None], views.K[None], res, torch.tensor(BACKGROUND))
    v = 3  # any view: the stored order is kept
    assert np.abs(ours.rgb[v].astype(float) - (rgb[0, v].clamp(0, 1).numpy() * 255)).max() <= 1
    # the stored depth is a distance along the unit ray: back-projected, its camera-space z is the render's
    rows, cols = np.nonzero(ours.alpha[v] > 128)
    assert len(rows) > 10
    cam2world = np.asarray(ours.metadata["views"][v]["cam2world"])
    points = depth_points(cam2world, np.asarray(ours.metadata["views"][v]["intrinsics"]), res, rows, cols,
                          ours.depth[v][rows, cols])
    z_back = (points - cam2world[:3, 3]) @ cam2world[:3, 2]
    np.testing.assert_allclose(z_back, z[0, v, rows, cols, 0].numpy(), rtol=1e-3, atol=1e-3)
    assert (ours.depth[v][ours.alpha[v] == 0] == 0).all()


def test_a_folder_that_holds_a_dataset_is_refused(written):
    from datagen.errors import UserError
    model, data, subjects, out = written
    with pytest.raises(UserError, match="already holds a dataset"):
        write_reconstructions(model, data, subjects, out)
