"""A working model fits one subject: a short training run on its views must beat both evaluation floors.

The real losses, rasterizer and training loop on a 1-subject procedural dataset (8 views of 32 px),
a small model of every stage (tests/test_model.py's SMALL). The floors are measured, not assumed:
the untrained model (the run's own step 0, as ``panolam eval`` reports it) and the mean-colour
template both score about 13.2 dB of foreground PSNR on this subject's views. Measured: 40 steps
reach 17.9 dB (18.6 dB on the novel views), 80 steps 19.2 dB, and the same 40 steps at a learning
rate of 1e-9 stay at 13.2 dB, the untrained floor; so 40 steps must clear the better floor by 3 dB.
About 15 s on 2 quiet cores.
"""
from __future__ import annotations

import time

import pytest
import torch

from datagen.dataset.manifests import read_manifest
from panolam.checkpoints import load_model
from panolam.config import TrainConfig, preset
from panolam.evaluate import NOVEL, baselines, evaluate
from panolam.train import train
from tests.conftest import curated_dataset
from tests.test_model import SMALL

MARGIN_DB = 3.0
OVERFIT = TrainConfig(steps=40, batch_size=1, views_per_sample=4, render_resolution=32, warmup_steps=3, lr=2e-3,
                      checkpoint_every=1000, log_every=1000, image_every=1000)


@pytest.fixture(scope="module")
def one_subject(tmp_path_factory):
    return curated_dataset(tmp_path_factory.mktemp("overfit"), subjects=1, views=8, test_count=0)


def test_the_model_overfits_one_subject_well_above_both_floors(one_subject, tmp_path):
    data, manifest = one_subject
    t0 = time.perf_counter()
    train(data, manifest, preset("tiny", **SMALL), OVERFIT, tmp_path / "run", progress=False)
    seconds = time.perf_counter() - t0
    model, m = load_model(tmp_path / "run"), read_manifest(manifest)
    fitted = evaluate(model, data, m, "train")
    floors = baselines(model, OVERFIT.seed, data, m, "train")
    got = {name: r["per_view"]["all"]["psnr_fg"] for name, r in [("trained", fitted), *floors.items()]}
    floor = max(got["untrained"], got["mean_colour_template"])
    assert got["trained"] > floor + MARGIN_DB, (got, f"{seconds:.0f} s of training")
    assert fitted["per_view"][NOVEL]["psnr_fg"] > floor + MARGIN_DB  # not the input view alone
    assert torch.isfinite(torch.tensor([r["psnr"] for r in fitted["rows"]])).all()
