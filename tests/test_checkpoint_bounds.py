"""Crafted checkpoints: the loader's work and memory stay bounded by the file, each refusal is one line."""
import pickle
import resource
import sys
import time


import pytest
import torch

from datagen.gans.checkpoint import CheckpointError, read_checkpoint
from tests.conftest import Persistent, gan_fixture, load_stub, repickle


def module(fn, name, children=None, params=None, **state):
    return Persistent(fn, name, {"_parameters": params or {}, "_buffers": {}, "_modules": children or {}, **state})


def write(tmp_path, name, obj, recursion=None):
    path = tmp_path / name
    old = sys.getrecursionlimit()
    if recursion:
        sys.setrecursionlimit(recursion)
    try:
        path.write_bytes(pickle.dumps({"G_ema": obj}, protocol=4))
    finally:
        sys.setrecursionlimit(old)
    return path


def refused(path, match):
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start = time.perf_counter()
    with pytest.raises(CheckpointError, match=match) as info:
        read_checkpoint(path, "eg3d")
    assert str(path) in str(info.value) and "\n" not in str(info.value)
    assert time.perf_counter() - start < 30
    grown_mib = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss) / 1024
    assert grown_mib < 512, f"peak memory grew by {grown_mib:.0f} MiB"


def test_module_tree_shared_two_to_the_n_ways(persistence_module, tmp_path):
    fn = persistence_module._reconstruct_persistent_obj
    node = module(fn, "Leaf", params={"w": torch.zeros(4)})
    for _ in range(60):  # 2^60 paths through 60 objects
        node = module(fn, "Pair", {"a": node, "b": node})
    path = write(tmp_path, "shared.pkl", module(fn, "TriPlaneGenerator", {"backbone": node}))
    assert path.stat().st_size < 100_000
    refused(path, "refused to load: module backbone.a.* appears more than once")


def test_a_dict_shared_many_times_in_the_kwargs(persistence_module, tmp_path):
    fn = persistence_module._reconstruct_persistent_obj
    d = {"x": 1}
    for _ in range(60):
        d = {"a": d, "b": d}
    g = module(fn, "TriPlaneGenerator", _init_kwargs={"mapping_kwargs": d, "z_dim": 512})
    path = write(tmp_path, "dict.pkl", g)
    refused(path, r"tmp.*dict.pkl: ")  # converted once per container: linear, then refused by the state check


def test_absurd_kwargs_are_refused_before_anything_is_allocated(persistence_module, tmp_path):
    g = load_stub(gan_fixture("eg3d", ".pkl"))
    g.state["_init_kwargs"]["channel_base"] = 1 << 40
    path = write(tmp_path, "huge.pkl", repickle(g, persistence_module._reconstruct_persistent_obj))
    refused(path, r"channel_base=1099511627776 is outside")
    g.state["_init_kwargs"]["channel_base"] = 32768
    g.state["_init_kwargs"]["channel_max"] = 4096  # plausible sizes, but not what the file holds
    path = write(tmp_path, "big.pkl", repickle(g, persistence_module._reconstruct_persistent_obj))
    refused(path, r"big.pkl: shape mismatch")


def test_views_that_repeat_a_few_stored_elements(persistence_module, tmp_path):
    """Right names and shapes, but each tensor a stride-0 view of one stored element."""
    g = load_stub(gan_fixture("eg3d", ".pkl", "gan-sr"))
    todo = [g]
    while todo:
        node = todo.pop()
        for group in ("_parameters", "_buffers"):
            for name, t in (node.state.get(group) or {}).items():
                if t is not None:
                    node.state[group][name] = torch.zeros((), dtype=t.dtype).expand(t.shape)
        todo += [m for m in (node.state.get("_modules") or {}).values() if m is not None]
    path = write(tmp_path, "views.pkl", repickle(g, persistence_module._reconstruct_persistent_obj))
    refused(path, r"views.pkl: refused to load: its tensors claim \d+ elements, more than its \d+ bytes")


def test_a_bytes8_claiming_a_pebibyte(tmp_path):
    path = tmp_path / "claim.pkl"
    path.write_bytes(b"\x80\x04\x8e" + (1 << 50).to_bytes(8, "little") + b"abc.")
    refused(path, "not a readable generator checkpoint")


def test_a_5000_deep_module_chain(persistence_module, tmp_path):
    fn = persistence_module._reconstruct_persistent_obj
    node = module(fn, "Leaf")
    for _ in range(5000):
        node = module(fn, "Wrap", {"m": node})
    path = write(tmp_path, "deep.pkl", module(fn, "TriPlaneGenerator", {"backbone": node}), recursion=100_000)
    refused(path, "refused to load: (module tree deeper than 64|objects nested too deeply)")


@pytest.mark.parametrize("params, match", [
    (["not", "a", "dict"], r"_parameters is a list, not a dict"),
    ({"weight": "text"}, r"_parameters\['weight'\] is not a tensor"),
])
def test_malformed_parameters(persistence_module, tmp_path, params, match):
    fn = persistence_module._reconstruct_persistent_obj
    g = module(fn, "TriPlaneGenerator", {"decoder": module(fn, "OSGDecoder", params=params)})
    refused(write(tmp_path, "params.pkl", g), match)


def test_a_real_checkpoint_still_loads_quickly():
    start = time.perf_counter()
    ck = read_checkpoint(gan_fixture("eg3d", ".pkl", "gan-sr"), "eg3d")
    assert time.perf_counter() - start < 20 and ck.generator.superresolution.block1.conv1.weight.is_floating_point()
    assert not any(p.is_meta for p in ck.generator.parameters())
