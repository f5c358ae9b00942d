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
import pickletools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import UserError
from ..files import sha256_file
from .kinds import GAN_KINDS
from .triplane import TriPlaneGenerator

STUB_PREFIXES = ("training.", "torch_utils.", "dnnlib.", "torch.nn.modules.")
# Bounds on what a file may make the loader do (the released checkpoints are far inside them).
MAX_FILE_BYTES = 8 << 30
MAX_OPCODES = 20_000_000
MAX_DEPTH = 64
MAX_KWARG_NODES = 100_000


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


def _prescan(data: bytes) -> int:
    """Walk the pickle's opcodes without building anything; returns how many there are.

    Length claims beyond the file (a 'bytes8' of 1 PiB in a small file) raise ValueError here,
    before the real unpickler would try to allocate them; more than ``MAX_OPCODES`` is refused.
    """
    count = 0
    for count, _ in enumerate(pickletools.genops(io.BytesIO(data)), 1):  # ValueError where truncated
        if count > MAX_OPCODES:
            raise Refused(f"more than {MAX_OPCODES} pickle opcodes")
    return count


def flat_state(stub, max_nodes: int) -> dict:
    """Parameters and buffers of a stubbed module tree as a flat {dotted name: tensor}.

    Walks the tree iteratively: a module reached twice (the memo lets a small file share one
    child 2^N ways), deeper than ``MAX_DEPTH``, more than ``max_nodes`` modules, or state of the
    wrong type is refused instead of being expanded.
    """
    out, seen = {}, set()
    todo = [(stub, "", 0)]
    while todo:
        node, prefix, depth = todo.pop()
        where = prefix.rstrip(".") or "G_ema"
        if id(node) in seen:
            raise Refused(f"module {where} appears more than once in the module tree")
        seen.add(id(node))
        if depth > MAX_DEPTH or len(seen) > max_nodes:
            raise Refused(f"module tree deeper than {MAX_DEPTH} or larger than {max_nodes} modules (at {where})")
        state = node.state
        skip = state.get("_non_persistent_buffers_set") or set()
        for group in ("_parameters", "_buffers"):
            entries = state.get(group) or {}
            if not isinstance(entries, dict):
                raise Refused(f"{where}.{group} is a {type(entries).__name__}, not a dict")
            for name, t in entries.items():
                if t is None or (isinstance(skip, (set, frozenset)) and name in skip):
                    continue
                if not isinstance(name, str) or not isinstance(t, torch.Tensor):
                    raise Refused(f"{where}.{group}[{name!r}] is not a tensor")
                out[prefix + name] = t.detach()
        children = state.get("_modules") or {}
        if not isinstance(children, dict):
            raise Refused(f"{where}._modules is a {type(children).__name__}, not a dict")
        for name, child in reversed(list(children.items())):
            if child is None:
                continue
            if not isinstance(name, str) or not isinstance(child, Stub):
                raise Refused(f"{where}._modules[{name!r}] is not a module")
            todo.append((child, f"{prefix}{name}.", depth + 1))
    return out


def detect_kind(state: dict, rendering_kwargs: dict) -> str:
    """The kind of a checkpoint: the last of the GAN kinds table that recognises it (EG3D's takes any)."""
    return next(k.name for k in reversed(GAN_KINDS.values()) if k.recognise(state, rendering_kwargs))


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
    """Load ``G_ema`` from an official checkpoint into our modules (CPU, eval mode, float32).

    Nothing in the file runs, and the work and memory the file can cause are bounded by its size:
    the opcodes are scanned before unpickling, the module tree and the stored kwargs are walked
    once each (sharing and depth refused), the kwargs are range-checked, and our modules are first
    built without memory (the meta device) and compared name by name and shape by shape with the
    file's tensors, whose elements must fit in the file's bytes, before anything is allocated.
    Every refusal is one line naming the file.
    """
    path = Path(path)
    hint = f" ({GAN_KINDS[expected_kind].source})" if expected_kind in GAN_KINDS else ""
    if not path.exists():
        raise CheckpointError(f"{path}: checkpoint not found{hint}")
    try:
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise Refused(f"{size} bytes; no generator checkpoint is larger than {MAX_FILE_BYTES >> 30} GiB")
        raw = path.read_bytes()
        opcodes = _prescan(raw)
        data = RestrictedUnpickler(io.BytesIO(raw)).load()
        del raw
        g = _generator_stub(data)
        init_kwargs = _plain(g.state.get("_init_kwargs") or {}, [MAX_KWARG_NODES])
        rendering_kwargs = _plain(g.state.get("rendering_kwargs") or init_kwargs.get("rendering_kwargs") or {},
                                  [MAX_KWARG_NODES])
        state = flat_state(g, max_nodes=opcodes)
    except CheckpointError as e:
        raise CheckpointError(f"{path}: {e}") from None
    except Refused as e:
        raise CheckpointError(f"{path}: refused to load: {e}") from None
    except MemoryError:
        raise CheckpointError(f"{path}: refused to load: it claims more memory than it holds") from None
    except RecursionError:
        raise CheckpointError(f"{path}: refused to load: objects nested too deeply") from None
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError, KeyError,
            RuntimeError, OSError) as e:
        raise CheckpointError(f"{path}: not a readable generator checkpoint (truncated or corrupt? {type(e).__name__})") from None
    kind = detect_kind(state, rendering_kwargs)
    if expected_kind and kind != expected_kind:
        raise CheckpointError(f"{path}: this is a {kind} checkpoint, not {expected_kind}")
    if not isinstance(init_kwargs, dict) or not isinstance(rendering_kwargs, dict):
        raise CheckpointError(f"{path}: the stored constructor kwargs are not a dict")
    init_kwargs["rendering_kwargs"] = rendering_kwargs
    problem = implausible_kwargs(init_kwargs)
    if problem:
        raise CheckpointError(f"{path}: unsupported generator configuration ({problem})")
    try:
        with torch.device("meta"):
            model = TriPlaneGenerator(kind, **init_kwargs)
    except (KeyError, ValueError, TypeError, AttributeError) as e:
        raise CheckpointError(f"{path}: unsupported generator configuration ({type(e).__name__}: {e})") from None
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
    elements = sum(state[k].numel() for k in own)
    if elements > size:  # every stored element takes a byte or more: the rest are views repeating them
        raise CheckpointError(f"{path}: refused to load: its tensors claim {elements} elements, more than its "
                              f"{size} bytes can hold (stride-0 or overlapping views)")
    model = model.to_empty(device="cpu")  # now bounded: the file holds tensors of these very shapes
    model.load_state_dict({k: state[k].float() for k in own})
    nrr = g.state.get("neural_rendering_resolution", 64)
    if not isinstance(nrr, int) or not 16 <= nrr <= 1024:
        raise CheckpointError(f"{path}: unsupported neural rendering resolution {nrr!r}")
    model.neural_rendering_resolution = nrr
    model.eval().requires_grad_(False)
    return LoadedCheckpoint(kind, model, init_kwargs, rendering_kwargs, nrr, sha256_file(path), str(path))


def _generator_stub(data) -> Stub:
    if not isinstance(data, dict) or not isinstance(data.get("G_ema"), Stub):
        raise CheckpointError("no G_ema generator in this file (is it an EG3D-family checkpoint?)")
    g = data["G_ema"]
    if not g.class_name.endswith("TriPlaneGenerator"):
        raise CheckpointError(f"G_ema is a {g.class_name}, not a tri-plane generator")
    return g


def _plain(obj, budget: list, depth: int = 0, memo=None):
    """EasyDict stubs -> dicts, lists/tuples kept; each shared container converted once.

    ``budget``: a one-element list, the containers still allowed (decremented); exhausting it, or
    nesting deeper than ``MAX_DEPTH``, is refused.
    """
    memo = {} if memo is None else memo
    if not isinstance(obj, (dict, list, tuple)):
        return obj
    if id(obj) in memo:
        return memo[id(obj)]
    budget[0] -= 1
    if budget[0] < 0 or depth > MAX_DEPTH:
        raise Refused("the stored constructor kwargs are too large or nested too deeply")
    if isinstance(obj, dict):
        out = memo[id(obj)] = {}
        for k, v in obj.items():
            out[k] = _plain(v, budget, depth + 1, memo)
    else:
        out = memo[id(obj)] = type(obj)(_plain(v, budget, depth + 1, memo) for v in obj)
    return out


# Plausible ranges of the kwargs that size the networks (the released models are well inside).
KWARG_RANGES = {"z_dim": (1, 4096), "w_dim": (1, 4096), "c_dim": (0, 1024), "img_resolution": (32, 2048),
                "channel_base": (1, 1 << 17), "channel_max": (1, 4096), "num_fp16_res": (0, 16),
                "sr_num_fp16_res": (0, 16)}
MAPPING_RANGES = {"num_layers": (1, 32), "layer_features": (1, 8192), "embed_features": (1, 8192)}
RENDERING_RANGES = {"triplane_size": (4, 2048), "triplane_depth": (1, 64), "depth_resolution": (1, 4096),
                    "depth_resolution_importance": (0, 4096)}


def implausible_kwargs(kwargs: dict) -> str | None:
    """What is wrong with the network-sizing kwargs, or None (checked before anything is built)."""
    groups = ((kwargs, KWARG_RANGES, ""), (kwargs.get("mapping_kwargs") or {}, MAPPING_RANGES, "mapping_kwargs."),
              (kwargs["rendering_kwargs"], RENDERING_RANGES, "rendering_kwargs."))
    for values, ranges, prefix in groups:
        if not isinstance(values, dict):
            return f"{prefix.rstrip('.')} is not a dict"
        for key, (lo, hi) in ranges.items():
            v = values.get(key)
            if v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                return f"{prefix}{key}={v!r} is outside [{lo}, {hi}]"
    for key in ("img_resolution",):
        v = kwargs.get(key)
        if v is not None and v & (v - 1):
            return f"{key}={v} is not a power of two"
    return None
