"""Shared test helpers: tiny dataset jobs, the location of the shared GAN fixtures, and writers of
official-format checkpoint pickles."""
from __future__ import annotations

import os
import sys
import time
import types
from collections import OrderedDict
from pathlib import Path

import pytest

from datagen.gans.checkpoint import RestrictedUnpickler, Stub
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


def curated_dataset(root, subjects: int, views: int, test_count: int) -> tuple[Path, Path]:
    """A tiny procedural dataset under ``root/ds`` and its manifest (no verdicts, ``test_count`` held
    out): (dataset folder, manifest path)."""
    from labeling_tool.compiler import compile_manifest, write_manifest

    root = Path(root)
    data = root / "ds"
    run_sample(tiny_spec(data, subjects=subjects, views=views), progress=False)
    (root / "labels").mkdir()
    return data, write_manifest(compile_manifest(data, root / "labels", test_count=test_count), root / "m-v1.json")


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


# -- helpers that write official-format pickles ------------------------------------------------------

@pytest.fixture
def toy_study_reports(tmp_path, monkeypatch):
    """A reports folder for a study of arms (benchmarks.data_value and what reuses its stages) at toy
    size: 64 px datasets, 4 training subjects scored; the caller points its module's REPORTS here."""
    from benchmarks import data_value
    reports = tmp_path / "reports"
    reports.mkdir()
    monkeypatch.setattr(data_value, "TRAIN_EVAL_SUBJECTS", 4)
    monkeypatch.setattr(data_value, "RESOLUTION", 64)
    return reports


@pytest.fixture
def persistence_module(monkeypatch):
    """A stand-in 'torch_utils.persistence' so tests can write pickles in the official format."""
    pkg, mod = types.ModuleType("torch_utils"), types.ModuleType("torch_utils.persistence")

    def _reconstruct_persistent_obj(meta):  # never called: only its name is pickled
        raise AssertionError

    _reconstruct_persistent_obj.__module__ = "torch_utils.persistence"
    _reconstruct_persistent_obj.__qualname__ = "_reconstruct_persistent_obj"
    mod._reconstruct_persistent_obj = _reconstruct_persistent_obj
    pkg.persistence = mod
    monkeypatch.setitem(sys.modules, "torch_utils", pkg)
    monkeypatch.setitem(sys.modules, "torch_utils.persistence", mod)
    return mod


class Persistent:
    def __init__(self, fn, class_name, state):
        self.fn, self.meta = fn, {"type": "class", "version": 6, "module_src": "<omitted>",
                                  "class_name": class_name, "state": state}

    def __reduce__(self):
        return (self.fn, (self.meta,))


def repickle(stub, fn):
    """A loaded stub tree -> an official-format object tree (every module persistent)."""
    def conv(v):
        if isinstance(v, Stub):
            return repickle(v, fn)
        if isinstance(v, dict):  # OrderedDicts stay ordered; our EasyDict stand-ins become plain dicts
            return (OrderedDict if isinstance(v, OrderedDict) else dict)((k, conv(x)) for k, x in v.items())
        return v
    return Persistent(fn, stub.class_name.rsplit(".", 1)[-1], {k: conv(v) for k, v in stub.state.items()})


def load_stub(path):
    with open(path, "rb") as f:
        return RestrictedUnpickler(f).load()["G_ema"]


def group_ended(pgid: int, seconds: float) -> bool:
    """Whether no process of process group ``pgid`` is left within ``seconds``."""
    deadline = time.time() + seconds
    while time.time() < deadline:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.1)
    return False
