"""Evaluation on held-out subjects (paper protocol): the front view in, front/back/left/right views out.

Per subject, the input is the view nearest yaw 0 deg and the targets are the views nearest yaw
0/90/180/270 deg (the 360 protocol stores these exactly; a subject without a view within
``YAW_TOLERANCE`` of each is skipped and counted). Metrics per view on [0, 1] images over the
dataset background: PSNR, SSIM (11x11 Gaussian window, sigma 1.5), LPIPS when its weights are
given; CSIM on the front view where the target has a face (the render is read at the target's
face box: both share the camera) and APD on the views where a face is found in both images, with
dlib's models (:mod:`datagen.faces`; not ArcFace and not a 3DMM pose estimator, see there).
Times: reconstruction (one forward pass) and render per view, medians.
"""
from __future__ import annotations

import json
import math
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from datagen.device import constant
from datagen.files import atomic_write
from datagen.shards import read_fields, tar_path, to_uint8
from datagen.text import plural

from .data import BACKGROUND, accepted_subjects, check_subject_shards, decode_views, view_yaws
from .gaussians import Gaussians
from .metrics import psnr, ssim
from .model import PanoLAM
from .rasterizer import render_views

EVAL_VIEWS = {"front": 0.0, "left": 90.0, "back": 180.0, "right": 270.0}
YAW_TOLERANCE = 10.0


def nearest_views(yaw_deg: np.ndarray) -> dict | None:
    """{name: view index} of the views nearest each evaluation yaw, or None if one is missing."""
    picked = {}
    for name, target in EVAL_VIEWS.items():
        diff = np.abs((np.asarray(yaw_deg) - target + 180.0) % 360.0 - 180.0)
        i = int(diff.argmin())
        if diff[i] > YAW_TOLERANCE:
            return None
        picked[name] = i
    return picked


def _median(values):
    values = [v for v in values if v is not None and not math.isnan(v)]
    return statistics.median(values) if values else float("nan")


def _mean(values):
    values = [v for v in values if v is not None and not math.isnan(v)]
    return float(np.mean(values)) if values else float("nan")


@torch.no_grad()
def evaluate(model: PanoLAM, data, manifest: dict, split: str = "test", resolution: int | None = None,
             lpips=None, faces=None, limit: int | None = None, progress=None) -> dict:
    """Metrics per subject and view plus their means; ``faces``: the :mod:`datagen.faces` module (CSIM, APD) or None."""
    device = next(model.parameters()).device
    subjects = accepted_subjects(manifest, split, data)[:limit]
    check_subject_shards(data, subjects)
    rows, skipped, rec_times, render_times, front_targets = [], [], [], [], []
    for key, shard in subjects:
        fields = read_fields(data, shard, key)
        picked = nearest_views(view_yaws(fields))
        if picked is None:
            skipped.append(key)
            continue
        idx = list(picked.values())
        meta_views = decode_views(key, fields, idx, resolution, model.cfg.image_size, str(tar_path(data, shard)))
        images = meta_views.images.to(device)
        x = meta_views.inputs[None].to(device)
        t0 = time.perf_counter()
        rec = model(x)
        _sync(device)
        rec_times.append(time.perf_counter() - t0)
        g = Gaussians(*(t.float() for t in (rec.dense.means, rec.dense.quats, rec.dense.scales,
                                            rec.dense.opacities, rec.dense.colors)))
        res = images.shape[-1]
        t0 = time.perf_counter()
        rgb, _, _ = render_views(g, meta_views.cam2world[None].to(device), meta_views.K[None].to(device),
                                 res, background=constant(BACKGROUND, device))
        _sync(device)
        render_times.append((time.perf_counter() - t0) / len(idx))
        pred = rgb[0].permute(0, 3, 1, 2).clamp(0, 1)
        scores = [psnr(pred, images), ssim(pred, images)]
        scores += [lpips(pred, images).flatten()] if lpips is not None else []
        p, s, *lp = torch.stack(scores).cpu().tolist()  # one read per subject
        if faces is not None:  # (2, views, H, W, 3): renders and targets, copied to the host together
            pictures = to_uint8(torch.stack([pred, images]).permute(0, 1, 3, 4, 2).cpu().numpy())
        for j, name in enumerate(picked):
            row = {"subject": key, "view": name, "psnr": p[j], "ssim": s[j], "lpips": lp[0][j] if lp else None}
            if faces is not None:
                a, b = pictures[:, j]
                row["csim"] = faces.csim(a, b, box_from_b=True) if name == "front" else None
                if name == "front":
                    front_targets.append(b)
                row["apd"] = faces.apd(a, b, focal=float(meta_views.K[j, 0, 0]))  # both seen by this camera
            rows.append(row)
        if progress is not None:
            progress()
    result = summarize(rows, skipped, rec_times, render_times)
    if faces is not None:
        result["csim_between_subjects"], result["csim_between_subjects_faces"] = faces.csim_between_subjects(front_targets)
    return result


def _sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def summarize(rows: list, skipped: list, rec_times: list, render_times: list) -> dict:
    metrics = ["psnr", "ssim", "lpips", "csim", "apd"]
    per_view = {}
    for name in list(EVAL_VIEWS) + ["all"]:
        sel = [r for r in rows if name == "all" or r["view"] == name]
        per_view[name] = {m: _mean([r.get(m) for r in sel]) for m in metrics}
        per_view[name]["counted"] = {m: sum(1 for r in sel if r.get(m) is not None and not math.isnan(r[m]))
                                     for m in metrics}
    return {"subjects": len({r["subject"] for r in rows}), "skipped_subjects": skipped, "per_view": per_view,
            "reconstruct_s_median": _median(rec_times), "render_ms_per_view_median": _median(render_times) * 1000,
            "rows": rows}


def write_report(result: dict, out: Path, title: str, notes: list[str] = ()) -> tuple[Path, Path]:
    """Markdown table + JSON of an :func:`evaluate` result."""
    out.mkdir(parents=True, exist_ok=True)
    fmt = lambda v: "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.4f}"  # noqa: E731
    lines = [f"# {title}", "", f"{result['subjects']} subjects evaluated, {len(result['skipped_subjects'])} skipped "
             f"(no view within {YAW_TOLERANCE:g} deg of front/left/back/right).", "",
             "| view | PSNR dB | SSIM | LPIPS | CSIM | APD deg |", "|---|---|---|---|---|---|"]
    for name, m in result["per_view"].items():
        lines.append(f"| {name} | " + " | ".join(fmt(m[k]) for k in ("psnr", "ssim", "lpips", "csim", "apd")) + " |")
    counted = result["per_view"]["all"]["counted"]
    lines += ["", "Counted views: " + ", ".join(f"{k} {v}" for k, v in counted.items()) + ".",
              f"Reconstruction {result['reconstruct_s_median'] * 1000:.1f} ms (median, one forward pass); "
              f"render {result['render_ms_per_view_median']:.1f} ms per view (median).", ""]
    if "csim_between_subjects" in result:
        lines += [f"CSIM between the front targets of different subjects: {fmt(result['csim_between_subjects'])} "
                  f"({plural(result['csim_between_subjects_faces'], 'face')}): what an identity-blind prediction "
                  "scores; CSIM above it shows identity.", ""]
    lines += ["\n\n".join(notes)] if notes else []  # each note a paragraph of its own
    md, js = out / "eval.md", out / "eval.json"
    atomic_write(md, ("\n".join(lines) + "\n").encode())
    atomic_write(js, (json.dumps(result, indent=1) + "\n").encode())
    return md, js
