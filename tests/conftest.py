"""Shared test helpers: tiny dataset jobs and the location of the shared GAN fixtures."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from datagen.pipeline import JobSpec, run_sample, software_info

# ../shared beside the project root; override with PANOLAM_SHARED=/path/to/shared
SHARED = Path(os.environ.get("PANOLAM_SHARED", Path(__file__).resolve().parents[2] / "shared"))
FAST_PROCEDURAL = {"grid_resolution": 48}


GAN_SETS = {"gan": "tiny", "gan-sr": "sr"}  # fixture set -> file name tag


def gan_fixture(model: str, suffix: str, fixture_set: str = "gan") -> Path:
    """Path of a shared GAN fixture file; skips the test (with the reason) when it is absent.

    Sets: 'gan' (tiny generators with the 2X super-resolution), 'gan-sr' (the released 512
    checkpoints' 8XDC super-resolution at full size, 512 px from a 128 px neural render).
    """
    path = SHARED / "fixtures" / fixture_set / model / f"{model}-{GAN_SETS[fixture_set]}{suffix}"
    if not path.exists():
        pytest.skip(f"shared GAN fixture {path} not found (set PANOLAM_SHARED to the shared/ folder)")
    return path


def tiny_spec(out, **overrides) -> JobSpec:
    """A job that renders in about a second: few subjects, few views, small images."""
    fields = dict(out=str(out), gan="procedural", generator_options=dict(FAST_PROCEDURAL), protocol="360",
                  subjects=3, resolution=32, views=4, seed=7, shard_size=2, software=software_info())
    fields.update(overrides)
    return JobSpec(**fields)


def all_files(root) -> dict:
    """{relative path: bytes} of every file under root."""
    root = Path(root)
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """A small complete dataset, shared read-only by tests."""
    out = tmp_path_factory.mktemp("tiny") / "ds"
    run_sample(tiny_spec(out), progress=False)
    return out
