"""Load the official EG3D / PanoHead / SphereHead ``.pkl`` checkpoints without running their code.

The released files are plain pickles of ``{"G_ema": generator, ...}`` whose modules reduce to
``torch_utils.persistence._reconstruct_persistent_obj(meta)`` (meta carries the class name, the
module's ``__dict__`` and the source text, which would be executed on a normal load). A restricted
unpickler maps those references, and every other class the file names, to inert stubs that only
keep their state; tensors are rebuilt with ``torch.load(weights_only=True)``; any other global is
refused. The stored constructor kwargs then build our own modules, whose state dict must match
the file's parameter for parameter.
"""
from __future__ import annotations

import collections
import io
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import UserError
from ..files import sha256_file
from .triplane import TriPlaneGenerator

OFFICIAL_SOURCES = {
    "eg3d": "EG3D checkpoints (e.g. ffhq512-128.pkl, ffhqrebalanced512-128.pkl) come from NVIDIA's NGC catalog, "
            "linked from github.com/NVlabs/eg3d (docs/models.md)",
    "panohead": "PanoHead checkpoints (e.g. easy-khair-180-gpc0.8-trans10-025000.pkl) are linked from "
                "github.com/SizheAn/PanoHead",
    "spherehead": "SphereHead checkpoints (e.g. spherehead-ckpt-025000.pkl) are linked from github.com/lhyfst/SphereHead",
}
STUB_PREFIXES = ("training.", "torch_utils.", "dnnlib.", "torch.nn.modules.")


class CheckpointError(UserError):
    """A checkpoint that cannot be loaded, stated in one line naming the file."""


class Refused(pickle.UnpicklingError):
    """The file names something the loader will not construct."""


class Stub:
    """An inert stand-in for a pickled object: its class name and state, nothing else."""

    class_name = "?"

    def __init__(self, *args, **kwargs):
        self.state = {}

    def __setstate__(self, state):
        self.state = state if isinstance(state, dict) else {"state": state}


class EasyDictStub(dict):
    """Stand-in for dnnlib.util.EasyDict."""

    def __setstate__(self, state):
        self.update(state or {})


_STUB_CLASSES: dict = {}


def _stub_class(module: str, name: str):
    key = f"{module}.{name}"
    if key not in _STUB_CLASSES:
        _STUB_CLASSES[key] = type(name, (Stub,), {"class_name": key})
    return _STUB_CLASSES[key]


def _persistent(meta):
    """Stand-in for torch_utils.persistence._reconstruct_persistent_obj: never runs meta['module_src']."""
    if not isinstance(meta, dict) or meta.get("type") != "class" or "class_name" not in meta:
        raise Refused("malformed persistent object")
    stub = _stub_class("persistent", str(meta["class_name"]))()
    stub.__setstate__(meta.get("state", {}))
    return stub


def _load_storage(data: bytes):
    return torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)


def _newobj(cls, *args):
    if not (isinstance(cls, type) and (issubclass(cls, (Stub, EasyDictStub)) or cls in (collections.OrderedDict, dict))):
        raise Refused(f"refusing to construct {cls!r}")
    return cls.__new__(cls)


def _reconstructor(cls, base, state):
    obj = _newobj(cls)
    if state is not None and isinstance(obj, dict):
        obj.update(state)
    return obj


def _numpy_scalar(dtype, data=None):
    return np.frombuffer(data, dtype=dtype)[0] if data is not None else dtype.type()


ALLOWED = {
    ("torch_utils.persistence", "_reconstruct_persistent_obj"): _persistent,
    ("torch.storage", "_load_from_bytes"): _load_storage,
    ("torch._utils", "_rebuild_tensor_v2"): torch._utils._rebuild_tensor_v2,
    ("torch._utils", "_rebuild_parameter"): torch._utils._rebuild_parameter,
    ("torch", "Size"): torch.Size,
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("builtins", "set"): set,
    ("copyreg", "__newobj__"): _newobj,
    ("copyreg", "_reconstructor"): _reconstructor,
    ("builtins", "object"): object,
    ("dnnlib.util", "EasyDict"): EasyDictStub,
    ("numpy", "dtype"): np.dtype,
    ("numpy.core.multiarray", "scalar"): _numpy_scalar,
    ("numpy._core.multiarray", "scalar"): _numpy_scalar,
}


class RestrictedUnpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if (module, name) in ALLOWED:
            return ALLOWED[(module, name)]
        if module.startswith(STUB_PREFIXES):
            return _stub_class(module, name)
        raise Refused(f"unexpected global {module}.{name} (code in a checkpoint is never run)")


def flat_state(stub, prefix="") -> dict:
    """Parameters and buffers of a stubbed module tree as a flat {dotted name: tensor}."""
    out = {}
    state = stub.state
    for group in ("_parameters", "_buffers"):
        for name, t in (state.get(group) or {}).items():
            if t is not None and name not in (state.get("_non_persistent_buffers_set") or set()):
                out[prefix + name] = t.detach() if isinstance(t, torch.Tensor) else t
    for name, child in (state.get("_modules") or {}).items():
        if child is not None:
            out.update(flat_state(child, f"{prefix}{name}."))
    return out


def detect_kind(state: dict, rendering_kwargs: dict) -> str:
    if "ConvA.0.weight" in state:
        return "spherehead"
    if any(k.startswith(("bcg_synthesis.", "t_mapping.")) for k in state) or rendering_kwargs.get("triplane_depth"):
        return "panohead"
    return "eg3d"


@dataclass
class LoadedCheckpoint:
    kind: str
    generator: TriPlaneGenerator
    init_kwargs: dict
    rendering_kwargs: dict
    neural_rendering_resolution: int
    sha256: str
    path: str


def read_checkpoint(path, expected_kind: str | None = None) -> LoadedCheckpoint:
    """Load ``G_ema`` from an official checkpoint into our modules (CPU, eval mode, float32)."""
    path = Path(path)
    hint = f" ({OFFICIAL_SOURCES[expected_kind]})" if expected_kind in OFFICIAL_SOURCES else ""
    if not path.exists():
        raise CheckpointError(f"{path}: checkpoint not found{hint}")
    try:
        with open(path, "rb") as f:
            data = RestrictedUnpickler(f).load()
    except Refused as e:
        raise CheckpointError(f"{path}: refused to load: {e}") from None
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError, KeyError,
            RuntimeError, OSError) as e:
        raise CheckpointError(f"{path}: not a readable generator checkpoint (truncated or corrupt? {type(e).__name__})") from None
    if not isinstance(data, dict) or not isinstance(data.get("G_ema"), Stub):
        raise CheckpointError(f"{path}: no G_ema generator in this file (is it an EG3D-family checkpoint?)")
    g = data["G_ema"]
    if not g.class_name.endswith("TriPlaneGenerator"):
        raise CheckpointError(f"{path}: G_ema is a {g.class_name}, not a tri-plane generator")
    init_kwargs = dict(g.state.get("_init_kwargs") or {})
    rendering_kwargs = dict(g.state.get("rendering_kwargs") or init_kwargs.get("rendering_kwargs") or {})
    state = flat_state(g)
    kind = detect_kind(state, rendering_kwargs)
    if expected_kind and kind != expected_kind:
        raise CheckpointError(f"{path}: this is a {kind} checkpoint, not {expected_kind}")
    init_kwargs["rendering_kwargs"] = rendering_kwargs
    try:
        model = TriPlaneGenerator(kind, **_plain(init_kwargs))
    except (KeyError, ValueError, TypeError) as e:
        raise CheckpointError(f"{path}: unsupported generator configuration ({e})") from None
    own = model.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    if missing or unexpected:
        raise CheckpointError(f"{path}: parameters do not match a {kind} generator "
                              f"(missing {missing[:3]}, unexpected {unexpected[:3]})")
    bad = [k for k in own if tuple(own[k].shape) != tuple(state[k].shape)]
    if bad:
        k = bad[0]
        raise CheckpointError(f"{path}: shape mismatch for {k}: file {tuple(state[k].shape)}, "
                              f"expected {tuple(own[k].shape)}")
    model.load_state_dict({k: state[k].float() for k in own})
    model.neural_rendering_resolution = int(g.state.get("neural_rendering_resolution", 64))
    model.eval().requires_grad_(False)
    return LoadedCheckpoint(kind, model, init_kwargs, rendering_kwargs, model.neural_rendering_resolution,
                            sha256_file(path), str(path))


def _plain(obj):
    """EasyDict stubs -> dicts, recursively."""
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    return obj

