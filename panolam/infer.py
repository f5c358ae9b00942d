"""Inference: a photo -> head crop -> one forward pass -> a 3DGS .ply, a turntable, optional views.

Gaussians whose opacity is below ``prune_opacity`` are dropped before export; the error that costs
is measured (PSNR of the pruned against the unpruned turntable renders) and reported. Below 1/255
the rasterizer never draws a Gaussian, so that threshold is lossless. The outputs are all or
nothing: every file is encoded, then written under a temporary name beside its final one, then all
are renamed; when any step fails (a read-only folder, a full disk, a path under a regular file)
the files written so far are removed and a UserError names the path. Turntables are H.264 MP4
(through PyAV's bundled FFmpeg) or animated GIF, by the file's suffix.
"""
from __future__ import annotations

import io
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from datagen.cameras import FOV_MEAN, HEAD360_PIVOT, RADIUS_MEAN, ViewSet, named_views
from datagen.device import constant
from datagen.errors import SettingError, UserError, optional_import
from datagen.files import atomic_write
from datagen.dataset.shards import to_uint8

from .data import BACKGROUND
from .gaussians import Gaussians, ply_bytes
from .metrics import psnr
from .model import PanoLAM
from .rasterizer import render_views


def turntable_views(frames: int, pitch_deg: float = 0.0, radius: float = RADIUS_MEAN, fov: float = FOV_MEAN) -> ViewSet:
    """``frames`` cameras evenly spaced in yaw around the head, starting at the front."""
    yaw = np.linspace(0.0, 360.0, frames, endpoint=False)
    n = len(yaw)
    return ViewSet("turntable", yaw, np.full(n, pitch_deg), np.full(n, radius), np.full(n, fov), HEAD360_PIVOT)


def render_set(g: Gaussians, views: ViewSet, resolution: int) -> torch.Tensor:
    """One set of Gaussians seen from ``views`` -> RGB (V, 3, H, W) in [0, 1] over the dataset background."""
    c2w = torch.from_numpy(views.cam2world).float()[None]
    K = torch.from_numpy(views.K).float()[None]
    g1 = Gaussians(*(t[None].float() for t in (g.means, g.quats, g.scales, g.opacities, g.colors)))
    with torch.no_grad():
        rgb, _, _ = render_views(g1, c2w.to(g.means.device), K.to(g.means.device), resolution,
                                 background=constant(BACKGROUND, g.means.device))
    return rgb[0].permute(0, 3, 1, 2).clamp(0, 1)


@torch.no_grad()
def reconstruct(model: PanoLAM, image: np.ndarray) -> tuple[Gaussians, float]:
    """image (H, W, 3) float in [0, 1] -> the dense Gaussians and the seconds the forward pass took."""
    device = next(model.parameters()).device
    x = torch.from_numpy(np.array(image, dtype=np.float32)).permute(2, 0, 1)[None].to(device)
    if device.type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    rec = model(x)
    if device.type == "cuda":
        torch.cuda.synchronize()
    return rec.dense[0].to(torch.float32), time.perf_counter() - t0


def prune(g: Gaussians, min_opacity: float) -> Gaussians:
    keep = g.opacities >= min_opacity
    return Gaussians(g.means[keep], g.quats[keep], g.scales[keep], g.opacities[keep], g.colors[keep])


@dataclass
class InferenceReport:
    gaussians: int
    kept: int
    prune_psnr_db: float
    reconstruct_s: float
    render_ms: float
    written: list = field(default_factory=list)  # the files written, in order

    def lines(self) -> list[str]:
        return [f"reconstruction {self.reconstruct_s * 1000:.0f} ms; render {self.render_ms:.1f} ms per view",
                f"kept all {self.gaussians} Gaussians (none below the opacity threshold)"
                if self.kept == self.gaussians else
                f"kept {self.kept} of {self.gaussians} Gaussians; the pruned turntable matches the unpruned "
                f"one at {self.prune_psnr_db:.1f} dB PSNR", *(f"wrote {path}" for path in self.written)]


def _encoded(image: Image.Image, **options) -> bytes:
    buf = io.BytesIO()
    image.save(buf, **options)
    return buf.getvalue()


def frames_uint8(images: torch.Tensor) -> list[np.ndarray]:
    """(N, 3, H, W) in [0, 1] -> N uint8 (H, W, 3) frames (one copy to the host for all of them)."""
    return list(to_uint8(images.permute(0, 2, 3, 1).cpu().numpy()))


TURNTABLE_FORMATS = (".mp4", ".gif")


def _mp4(frames: list[np.ndarray], fps: int) -> bytes:
    """H.264 (yuv420p, CRF 18) in MP4; odd frame sizes are padded by one edge pixel."""
    av = optional_import("av", "model", "an .mp4 turntable")
    h, w = frames[0].shape[:2]
    buf = io.BytesIO()
    with av.open(buf, mode="w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.width, stream.height, stream.pix_fmt = w + w % 2, h + h % 2, "yuv420p"
        stream.options = {"crf": "18"}
        for frame in frames:
            frame = np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
            container.mux(stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")))
        container.mux(stream.encode())
    return buf.getvalue()


def encode_turntable(suffix: str, frames: list[np.ndarray], fps: int = 24) -> bytes:
    """The frames as an MP4 video or an animated GIF, by the file ``suffix``."""
    if suffix.lower() == ".mp4":
        return _mp4(frames, fps)
    images = [Image.fromarray(f) for f in frames]
    return _encoded(images[0], format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)


def run(model: PanoLAM, image: np.ndarray, out_ply: Path | None, turntable: Path | None = None,
        views_dir: Path | None = None, resolution: int = 256, frames: int = 36, prune_opacity: float = 0.02
        ) -> InferenceReport:
    """Reconstruct one prepared image and write the requested outputs."""
    if out_ply is not None and out_ply.suffix.lower() != ".ply":
        raise UserError(f"{out_ply}: the Gaussians are written as a .ply file")
    if turntable is not None and turntable.suffix.lower() not in TURNTABLE_FORMATS:
        raise UserError(f"{turntable}: a turntable is written as {' or '.join(TURNTABLE_FORMATS)}; name it so")
    full, seconds = reconstruct(model, image)
    kept = prune(full, prune_opacity)
    if len(kept) == 0:
        raise SettingError(f"{{prune_opacity}} {prune_opacity} removes every Gaussian (the most opaque has "
                           f"{float(full.opacities.max()):.3f}); give a lower threshold")
    views = turntable_views(frames)
    t0 = time.perf_counter()
    frames_full = render_set(full, views, resolution)
    render_ms = (time.perf_counter() - t0) * 1000 / len(views)
    frames_kept = frames_full if len(kept) == len(full) else render_set(kept, views, resolution)
    loss_db = float(psnr(frames_kept, frames_full).mean())
    outputs = {}  # everything is encoded before anything is written
    if out_ply is not None:
        outputs[out_ply] = ply_bytes(kept.detach().to("cpu"))
    if turntable is not None:
        outputs[turntable] = encode_turntable(turntable.suffix, frames_uint8(frames_kept))
    if views_dir is not None:
        named = ["front", "left", "back", "right"]
        for name, img in zip(named, frames_uint8(render_set(kept, named_views(named), resolution))):
            outputs[views_dir / f"{name}.png"] = _encoded(Image.fromarray(img), format="PNG")
    write_all(outputs)
    return InferenceReport(len(full), len(kept), loss_db, seconds, render_ms, list(outputs))


def write_all(outputs: dict[Path, bytes]) -> None:
    """Write every file or none (module docstring); a UserError naming the path when one cannot be written."""
    staged, created, done = {}, [], []
    path = None
    try:
        for path, data in outputs.items():
            created += reversed([p for p in [path.parent, *path.parent.parents] if not p.exists()])
            path.parent.mkdir(parents=True, exist_ok=True)
            staged[path] = atomic_write(path.with_name(f".{path.name}.partial-{os.getpid()}"), data)
        for path, tmp in staged.items():
            os.replace(tmp, path)
            done.append(path)
    except BaseException as e:  # an interrupt too: nothing is left behind
        for p in [*staged.values(), *done]:
            p.unlink(missing_ok=True)
        for d in reversed(created):
            try:
                d.rmdir()
            except OSError:
                pass
        if isinstance(e, OSError):
            raise UserError(f"cannot write {path}: {e.strerror or e}") from None
        raise
