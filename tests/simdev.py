"""A simulated accelerator: catches device mix-ups and host syncs without a GPU.

Inside :func:`simulated_device`, tensors made with ``device=torch.device("simdev", 0)`` (or moved
there with ``.to``) report that device and hold real CPU values, so every op really runs, backward
included. The rules are CUDA's:

* an op that mixes a simulated-device tensor with a host tensor of one or more dimensions raises
  :class:`DeviceMismatch` (host 0-dim tensors are scalars and allowed; host index tensors in
  advanced indexing are allowed, as CUDA allows them);
* ``.to``/``copy_`` move data between host and device (the only way across);
* ``.item()``, ``float()`` and ``bool()`` of a device tensor, and ops whose output size depends
  on its values (``nonzero``, boolean-mask selection), are host syncs: each is counted in
  ``mode.syncs`` (with the op), and with ``strict_syncs=True`` it raises :class:`HostSync`;
  ``.cpu()``, ``.to("cpu")`` and ``.tolist()`` are copies to the host, counted in ``mode.transfers``;
* ``.numpy()`` of a device tensor fails, as on CUDA.

Half-precision convolutions are computed in float32 and cast back (the harness checks placement
and dtypes, not float16 rounding).

Modules move with ``module.to(device)``: their parameters become device tensors (the harness
turns on torch's ``overwrite_module_params_on_conversion`` while it is active). ``torch.autocast``
with the simulated device type runs and casts nothing (it checks the code path, not bf16 numerics).
"""
from __future__ import annotations

import contextlib

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten, tree_map

NAME = "simdev"
DEVICE = None  # torch.device(NAME, 0) once registered
_registered = []

aten = torch.ops.aten
# Ops that move data between host and device: never a mix-up.
_TRANSFERS = {aten._to_copy.default, aten.copy_.default, aten._copy_from.default, aten._copy_from_and_resize.default}
# Ops whose result the host must wait for on CUDA (a value, or an output size that depends on values).
_SYNCS = {aten._local_scalar_dense.default, aten.nonzero.default, aten.masked_select.default}
# Advanced indexing accepts host index tensors on CUDA.
_HOST_INDICES_OK = {aten.index.Tensor, aten.index_put_.default, aten.index_put.default, aten._index_put_impl_.default}


class DeviceMismatch(RuntimeError):
    """A simulated-device tensor met a host tensor in one op."""


class HostSync(RuntimeError):
    """A device value was read on the host where the test forbids it."""


class _Backend:
    """What torch asks of a device module (device count, AMP dtypes)."""

    def is_initialized(self):
        return True

    def is_available(self):
        return True

    def current_device(self):
        return 0

    def _is_in_bad_fork(self):
        return False

    def manual_seed_all(self, seed):
        pass

    def device_count(self):
        return 1

    def get_amp_supported_dtype(self):
        return [torch.float16, torch.bfloat16]


def register() -> torch.device:
    """Register the simulated device type with torch once per process; returns its device 0."""
    global DEVICE
    if not _registered:
        from torch.utils.backend_registration import _setup_privateuseone_for_python_backend
        _setup_privateuseone_for_python_backend(NAME, backend_module=_Backend())
        DEVICE = torch.device(NAME, 0)
        autocast = torch.library.Library("_", "IMPL")
        autocast.fallback(torch.library.fallthrough_kernel, dispatch_key="AutocastPrivateUse1")
        # Kernels for the few allocations and copies that torch's C++ makes on a device below the
        # Python dispatch key (e.g. the index tensor of ``x[..., [0, 2]]``).
        kernels = torch.library.Library("aten", "IMPL")
        kernels.impl("empty_strided", _empty_strided, "PrivateUse1")
        kernels.impl("empty.memory_format", _empty, "PrivateUse1")
        kernels.impl("copy_", _copy, "PrivateUse1")
        kernels.impl("_copy_from", lambda src, dst, non_blocking=False: _copy(dst, src), "PrivateUse1")
        _registered.extend([autocast, kernels])
    return DEVICE


def _empty_strided(size, stride, dtype=None, layout=None, device=None, pin_memory=None):
    return SimTensor(torch.empty_strided(size, stride, dtype=dtype, layout=layout))


def _empty(size, dtype=None, layout=None, device=None, pin_memory=None, memory_format=None):
    return SimTensor(torch.empty(size, dtype=dtype, layout=layout, memory_format=memory_format))


def _copy(dst, src, non_blocking=False):
    (dst.elem if isinstance(dst, SimTensor) else dst).copy_(src.elem if isinstance(src, SimTensor) else src)
    return dst


class SimTensor(torch.Tensor):
    """A tensor that reports the simulated device and keeps its real values in ``elem`` (CPU)."""

    elem: torch.Tensor

    @staticmethod
    def __new__(cls, elem: torch.Tensor):
        t = torch.Tensor._make_wrapper_subclass(cls, elem.shape, strides=elem.stride(),
                                                storage_offset=elem.storage_offset(), dtype=elem.dtype,
                                                layout=elem.layout, device=DEVICE, requires_grad=elem.requires_grad)
        t.elem = elem
        return t

    def __repr__(self):
        return f"SimTensor({self.elem!r})"

    def tolist(self):
        """As on CUDA: one copy to the host (counted in ``mode.transfers``), then the list."""
        return self.cpu().tolist()

    __torch_function__ = torch._C._disabled_torch_function_impl

    @classmethod
    def __torch_dispatch__(cls, func, types, args=(), kwargs=None):
        raise RuntimeError(f"{func} on a simulated-device tensor outside simulated_device()")


def _is_sim_device(d) -> bool:
    return d is not None and torch.device(d).type == NAME


class SimulatedDevice(TorchDispatchMode):
    """The dispatch mode behind :func:`simulated_device` (see the module docstring)."""

    def __init__(self, strict_syncs: bool = False):
        super().__init__()
        self.strict_syncs = strict_syncs
        self.syncs: list = []
        self.transfers: list = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        flat, _ = tree_flatten((args, kwargs))
        on_device = any(isinstance(t, SimTensor) for t in flat)
        target = kwargs.get("device")
        to_device = _is_sim_device(target)
        if func in _SYNCS and on_device:
            self.syncs.append(func)
            if self.strict_syncs:
                raise HostSync(f"{func}: a device value read on the host")
        if func not in _TRANSFERS and (on_device or to_device):
            self._check_mix(func, args, flat)
        host_args = tree_map(lambda t: t.elem if isinstance(t, SimTensor) else t, (args, kwargs))
        if to_device:
            host_args[1]["device"] = torch.device("cpu")
        out = self._run(func, *host_args)
        if func is aten.copy_.default:
            return args[0]
        if func is aten._to_copy.default and target is not None and not to_device:
            if on_device:
                self.transfers.append(func)
            return out
        if not (on_device or to_device):
            return out
        if func._schema.is_mutable and args and isinstance(args[0], SimTensor) and out is host_args[0][0]:
            return args[0]
        return tree_map(lambda t: SimTensor(t) if type(t) is torch.Tensor else t, out)

    @staticmethod
    def _run(func, args, kwargs):
        """The op on the host values; half-precision convolutions in float32 (CPU float16
        convolutions are slow), cast back."""
        if func is aten.convolution.default and args[0].dtype in (torch.float16, torch.bfloat16):
            dtype = args[0].dtype
            args = tree_map(lambda t: t.float() if isinstance(t, torch.Tensor) else t, args)
            return func(*args, **kwargs).to(dtype)
        return func(*args, **kwargs)

    @staticmethod
    def _check_mix(func, args, flat):
        host = [t for t in flat if isinstance(t, torch.Tensor) and not isinstance(t, SimTensor) and t.dim() > 0]
        if func in _HOST_INDICES_OK and len(args) > 1:
            indices = tree_flatten(args[1])[0]
            host = [t for t in host if not any(t is i for i in indices)]
        if host:
            raise DeviceMismatch(f"{func}: a {NAME} tensor mixed with a host tensor of shape "
                                 f"{tuple(host[0].shape)}")


@contextlib.contextmanager
def simulated_device(strict_syncs: bool = False):
    """Yields (device, mode): run code with its tensors on ``device``; ``mode.syncs`` and
    ``mode.transfers`` list the host reads seen."""
    device = register()
    mode = SimulatedDevice(strict_syncs)
    overwrite = torch.__future__.get_overwrite_module_params_on_conversion()
    torch.__future__.set_overwrite_module_params_on_conversion(True)
    try:
        with mode:
            yield device, mode
    finally:
        torch.__future__.set_overwrite_module_params_on_conversion(overwrite)


def on_device(t) -> bool:
    """True for a tensor on the simulated device."""
    return isinstance(t, SimTensor)


register()  # at import: the autograd engine sizes its device queues at the process's first backward pass
