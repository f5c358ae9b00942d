"""Run checkpoints: writing them atomically, reading them back, the trained model they hold.

A checkpoint (``<run>/checkpoint.pt``, format ``panolam-checkpoint/1``) holds the model, optimizer
and scheduler states, the decay's progress, the CPU RNG state, the step, both configs, the recent per-step log and what
the run trains on (:func:`panolam.train.training_data`). Its tensors are written from the CPU and
read onto the CPU whatever device trained or resumes the run, so a run moves between CPU and GPU
machines; loading the states into a model and optimizer on a device moves them there. It is read
with ``torch.load(weights_only=True)``: nothing in it executes. Inference and evaluation need only
this module, not the training code.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import torch

from datagen.errors import UserError
from datagen.files import atomic_write

from .config import PATH_FIELDS, ModelConfig, TrainConfig
from .model import PanoLAM

CHECKPOINT = "checkpoint.pt"
FORMAT = "panolam-checkpoint/1"
HISTORY_KEPT = 10_000  # most recent per-step log entries carried in a checkpoint (TensorBoard has them all)


class _WriteErrors:
    """A binary file for ``torch.save`` that keeps the OSError of a failed write.

    torch's archive writer turns an exception from ``write`` into a RuntimeError about stream
    positions; the kept OSError (a full disk, say) is what the user needs to hear.
    """

    def __init__(self, f):
        self.f, self.error = f, None

    def write(self, data) -> int:
        try:
            return self.f.write(data)
        except OSError as e:
            self.error = e
            raise

    def flush(self):
        self.f.flush()


def _torch_save(state: dict, f) -> None:
    sink = _WriteErrors(f)
    try:
        torch.save(state, sink)
    except RuntimeError:
        if sink.error is not None:
            raise sink.error from None
        raise


def _on_host(value):
    """``value`` with every tensor in it (through dicts, lists and tuples) copied to the CPU; a state
    dict keeps its type and the ``_metadata`` that ``load_state_dict`` reads."""
    if isinstance(value, torch.Tensor):
        return value.detach().cpu()
    if isinstance(value, dict):
        copy = type(value)((k, _on_host(v)) for k, v in value.items())
        if hasattr(value, "_metadata"):
            copy._metadata = value._metadata
        return copy
    if isinstance(value, (list, tuple)):
        return type(value)(_on_host(v) for v in value)
    return value


def save_checkpoint(out: Path, model, optimizer, scheduler, step: int, model_cfg: ModelConfig, cfg: TrainConfig,
                    history: list, data: Optional[dict] = None, schedule_progress: float = 0.0) -> Path:
    """Write ``out/checkpoint.pt`` atomically (temporary name, then rename; the temporary is removed
    and an OSError names the file when writing fails, e.g. on a full disk).

    ``data``: what the run trains on, checked on resume and by evaluation; ``schedule_progress``:
    how far the learning-rate decay has come (:class:`panolam.train.Schedule`).
    """
    core = model.module if hasattr(model, "module") else model
    state = {"format": FORMAT, "step": step, "model": _on_host(core.state_dict()),
             "optimizer": _on_host(optimizer.state_dict()), "scheduler": scheduler.state_dict(),
             "rng": torch.get_rng_state(), "model_config": model_cfg.to_dict(), "train_config": cfg.to_dict(),
             "history": history[-HISTORY_KEPT:], "data": data or {}, "schedule_progress": float(schedule_progress)}
    return atomic_write(Path(out) / CHECKPOINT, lambda f: _torch_save(state, f))


def read_checkpoint(path) -> dict:
    """A checkpoint file or a run directory holding one, its tensors on the CPU (also those of a file
    written from a GPU); one-line errors."""
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT
    if not path.exists():
        raise UserError(f"{path}: no checkpoint here")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several types for truncated or foreign files
        raise UserError(f"{path}: not a readable checkpoint ({type(e).__name__})") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise UserError(f"{path}: not a PanoLAM checkpoint")
    return state


def same_model_config(a: dict, b: dict) -> bool:
    """Equal model configs, file locations aside (the weights they name are in the checkpoint)."""
    return {k: v for k, v in a.items() if k not in PATH_FIELDS} == {k: v for k, v in b.items() if k not in PATH_FIELDS}


def load_model(path, device="cpu", **overrides) -> PanoLAM:
    """The trained model of a checkpoint, in eval mode; ``overrides`` replace config fields (file paths, M_D)."""
    return model_from_checkpoint(read_checkpoint(path), path, device, **overrides)


def model_from_checkpoint(state: dict, path, device="cpu", **overrides) -> PanoLAM:
    """:func:`load_model` on a checkpoint already read (:func:`read_checkpoint`) from ``path``."""
    try:
        cfg = ModelConfig.from_dict(state["model_config"]).replace(**overrides)
    except (TypeError, ValueError) as e:
        raise UserError(f"{path}: its model config does not fit this version ({e})") from None
    model = PanoLAM(cfg)
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as e:
        first = str(e).splitlines()[0]
        raise UserError(f"{path}: checkpoint does not fit config {cfg.name!r} ({first})") from None
    return model.to(device).eval()
