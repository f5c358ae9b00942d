"""Evaluation on held-out subjects (paper protocol): the front view in, front/back/left/right views out.

Per subject, the input is the view nearest yaw 0 deg and the targets are the views nearest yaw
0/90/180/270 deg (the 360 protocol stores these exactly; a subject without a view within
``YAW_TOLERANCE`` of each is skipped and counted). The front target is the input view itself, so
the left, back and right views are reported apart as the *novel* views. Metrics per view on
[0, 1] images over the dataset background: PSNR and SSIM (11x11 Gaussian window, sigma 1.5) over
the full frame and over the *foreground* (the pixels where the target's or the render's alpha is
at least ``FOREGROUND_ALPHA``: on a white frame most pixels are background, which any head-shaped
blob gets right), LPIPS when its weights are given; CSIM on the front view where the target has a
face (the render is read at the target's face box: both share the camera) and APD on the views
where a face is found in both images, with dlib's models (:mod:`datagen.faces`; not ArcFace and
not a 3DMM pose estimator, see there). Times: reconstruction (one forward pass) and render per
view, medians.

Baselines (:func:`baselines`) give every figure its floor: the untrained model (same config, same
seeded initialisation as the run's step 0) and :class:`MeanColourTemplate`, the template rendered
opaque in the mean foreground colour of the training subjects.

The gallery (:func:`write_gallery`) shows what the numbers mean: per subject the input, the
reconstruction seen from the front, left, back and right, and the ground truth of those views.
"""
from __future__ import annotations

import io
import json
import math
import statistics
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch
from PIL import Image, ImageDraw

from datagen.cameras import angle_between
from datagen.device import constant
from datagen.files import atomic_write
from datagen.preview import font
from datagen.dataset import Dataset
from datagen.dataset.shards import read_fields, tar_path, to_uint8
from datagen.text import plural

from .data import BACKGROUND, accepted_subjects, check_subject_shards, decode_views, load_views, view_yaws
from .gaussians import Gaussians
from .metrics import psnr, ssim
from .model import PanoLAM
from .rasterizer import render_views

EVAL_VIEWS = {"front": 0.0, "left": 90.0, "back": 180.0, "right": 270.0}
INPUT_VIEW = "front"
NOVEL = "novel"  # the evaluation views other than the input view, pooled
YAW_TOLERANCE = 10.0
FOREGROUND_ALPHA = 0.5
METRICS = ("psnr", "psnr_fg", "ssim", "ssim_fg", "lpips", "csim", "apd")
COLOUR_SUBJECTS = 32  # training subjects averaged for the mean-colour template
GALLERY_SUBJECTS = 8  # subjects in eval's gallery.png (the first of the split)
GALLERY_TILE = 128  # px of a gallery tile at least (smaller renders are enlarged, nearest neighbour)


def nearest_views(yaw_deg: np.ndarray) -> dict | None:
    """{name: view index} of the views nearest each evaluation yaw, or None if one is missing."""
    picked = {}
    for name, target in EVAL_VIEWS.items():
        diff = angle_between(yaw_deg, target)
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
             lpips=None, faces=None, limit: int | None = None, progress=None, gallery: list | None = None,
             gallery_subjects: int = GALLERY_SUBJECTS) -> dict:
    """Metrics per subject and view plus their means; ``faces``: the :mod:`datagen.faces` module (CSIM, APD) or None.
    ``gallery``: a list that receives, for the first ``gallery_subjects`` subjects, (subject, input,
    renders, targets) as uint8 HxWx3 images (renders and targets in ``EVAL_VIEWS`` order)."""
    device = next(model.parameters()).device
    dataset = Dataset.of(data)
    subjects = accepted_subjects(manifest, split, dataset)[:limit]
    check_subject_shards(dataset, subjects)
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
        rgb, alpha, _ = render_views(g, meta_views.cam2world[None].to(device), meta_views.K[None].to(device),
                                     res, background=constant(BACKGROUND, device))
        _sync(device)
        render_times.append((time.perf_counter() - t0) / len(idx))
        pred = rgb[0].permute(0, 3, 1, 2).clamp(0, 1)
        fg = torch.maximum(alpha[0].permute(0, 3, 1, 2), meta_views.masks.to(device)) >= FOREGROUND_ALPHA
        scores = [psnr(pred, images), psnr(pred, images, fg), ssim(pred, images), ssim(pred, images, fg)]
        scores += [lpips(pred, images).flatten()] if lpips is not None else []
        p, p_fg, s, s_fg, *lp = torch.stack(scores).cpu().tolist()  # one read per subject
        keep = gallery is not None and len(gallery) < gallery_subjects
        if faces is not None or keep:  # (2, views, H, W, 3): renders and targets, copied to the host together
            pictures = to_uint8(torch.stack([pred, images]).permute(0, 1, 3, 4, 2).cpu().numpy())
        if keep:
            gallery.append((key, to_uint8(meta_views.inputs.permute(1, 2, 0).cpu().numpy()), pictures[0], pictures[1]))
        for j, name in enumerate(picked):
            row = {"subject": key, "view": name, "psnr": p[j], "psnr_fg": p_fg[j], "ssim": s[j], "ssim_fg": s_fg[j],
                   "lpips": lp[0][j] if lp else None}
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
    """Means per evaluation view, over the novel views and over all (``per_view``), with counts."""
    per_view = {}
    for name in list(EVAL_VIEWS) + [NOVEL, "all"]:
        sel = [r for r in rows if name == "all" or r["view"] == name or (name == NOVEL and r["view"] != INPUT_VIEW)]
        per_view[name] = {m: _mean([r.get(m) for r in sel]) for m in METRICS}
        per_view[name]["counted"] = {m: sum(1 for r in sel if r.get(m) is not None and not math.isnan(r[m]))
                                     for m in METRICS}
    return {"subjects": len({r["subject"] for r in rows}), "skipped_subjects": skipped, "per_view": per_view,
            "reconstruct_s_median": _median(rec_times), "render_ms_per_view_median": _median(render_times) * 1000,
            "rows": rows}


class MeanColourTemplate(torch.nn.Module):
    """Baseline: a model's dense Gaussians at initialisation (the template), opaque, in one colour (3,)."""

    def __init__(self, model: PanoLAM, colour: torch.Tensor):
        super().__init__()
        self.model, self.cfg = model, model.cfg
        self.register_buffer("colour", colour.float())

    def forward(self, x):
        d = self.model(x).dense
        return SimpleNamespace(dense=Gaussians(d.means, d.quats, d.scales, torch.full_like(d.opacities, 0.99),
                                               self.colour.to(d.colors).expand_as(d.colors)))


def mean_foreground_colour(data, manifest: dict, resolution: int | None = None,
                           limit: int = COLOUR_SUBJECTS) -> torch.Tensor:
    """Mean RGB (3,) of the foreground (alpha-weighted) of the first ``limit`` training subjects."""
    total, weight = torch.zeros(3), 0.0
    for key, shard in accepted_subjects(manifest, "train", data)[:limit]:
        v = load_views(data, key, shard, resolution=resolution)
        total += (v.images * v.masks).sum(dim=(0, 2, 3))
        weight += float(v.masks.sum())
    return total / max(weight, 1.0)


def untrained_model(model: PanoLAM, seed: int) -> PanoLAM:
    """A model of ``model``'s config as a run seeded ``seed`` starts it (its step 0), on its device."""
    torch.manual_seed(seed)
    return PanoLAM(model.cfg).to(next(model.parameters()).device).eval()


def baselines(model: PanoLAM, seed: int, data, manifest: dict, split: str = "test", **options) -> dict:
    """:func:`evaluate` results of the untrained model and the mean-colour template on the same subjects
    (``options`` as for evaluate; ``faces`` is left out: neither baseline has a face to measure)."""
    options.pop("faces", None)
    untrained = untrained_model(model, seed)
    colour = mean_foreground_colour(data, manifest, options.get("resolution"))
    template = MeanColourTemplate(untrained, colour.to(next(untrained.parameters()).device))
    return {"untrained": evaluate(untrained, data, manifest, split, **options),
            "mean_colour_template": {**evaluate(template, data, manifest, split, **options),
                                     "colour": colour.tolist()}}


def _fmt(v) -> str:
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.4f}"


def paired_difference(a: dict, b: dict, metric: str = "psnr_fg", views=(NOVEL,)) -> tuple[float, float, int]:
    """Mean and standard error of ``a - b`` per subject (the subject's mean ``metric`` over ``views``),
    on the subjects both results scored; (nan, nan, 0) without any."""
    def per_subject(r):
        keep = [n for n in EVAL_VIEWS if n in views or (NOVEL in views and n != INPUT_VIEW)]
        out = {}
        for row in r["rows"]:
            if row["view"] in keep and row.get(metric) is not None and not math.isnan(row[metric]):
                out.setdefault(row["subject"], []).append(row[metric])
        return {k: float(np.mean(v)) for k, v in out.items()}
    pa, pb = per_subject(a), per_subject(b)
    d = np.array([pa[k] - pb[k] for k in pa if k in pb])
    if not len(d):
        return math.nan, math.nan, 0
    se = float(d.std(ddof=1) / math.sqrt(len(d))) if len(d) > 1 else math.nan
    return float(d.mean()), se, len(d)


def _baseline_lines(result: dict) -> list[str]:
    rows = [("this model", result)] + [(f"baseline: {k.replace('_', ' ')}", r)
                                       for k, r in result.get("baselines", {}).items()]
    lines = ["## Against the baselines (same subjects)", "",
             "| model | novel PSNR fg dB | novel SSIM fg | novel PSNR dB | input view PSNR fg dB | all PSNR dB | "
             "novel PSNR fg gain over it dB |", "|---|---|---|---|---|---|---|"]
    for name, r in rows:
        nv, fr, al = r["per_view"][NOVEL], r["per_view"][INPUT_VIEW], r["per_view"]["all"]
        gain = "-"
        if r is not result:
            d, se, n = paired_difference(result, r)
            gain = "n/a" if not n else f"{d:+.2f}" + (f" +- {se:.2f} ({plural(n, 'subject')})" if n > 1 else "")
        lines.append(f"| {name} | {_fmt(nv['psnr_fg'])} | {_fmt(nv['ssim_fg'])} | {_fmt(nv['psnr'])} | "
                     f"{_fmt(fr['psnr_fg'])} | {_fmt(al['psnr'])} | {gain} |")
    return lines + ["", "Gain: mean +- standard error of the per-subject difference of the novel-view foreground "
                        "PSNR.", ""]


def write_gallery(entries: list, path: Path) -> Path:
    """A PNG of :func:`evaluate`'s ``gallery`` entries: a row per subject with the input, the renders
    and the targets (front, left, back, right), columns labelled; written atomically."""
    if not entries:
        raise ValueError("no gallery entries")
    res = entries[0][2].shape[1]
    tile = res * max(1, -(-GALLERY_TILE // res))
    names = list(EVAL_VIEWS)
    heads = ["input"] + [f"ours {n}" for n in names] + [f"truth {n}" for n in names]
    gap, top = 6, 22
    width = len(heads) * tile + (len(heads) - 1) * gap + 2 * gap  # a wider gap between the three groups
    sheet = Image.new("RGB", (width, top + len(entries) * (tile + 18)), (30, 30, 30))
    draw = ImageDraw.Draw(sheet)
    label = font(13)
    x = [i * (tile + gap) + gap * ((i > 0) + (i > len(names))) for i in range(len(heads))]
    for x0, head in zip(x, heads):
        draw.text((x0 + 4, 4), head, fill=(235, 235, 235), font=label)
    for row, (key, photo, renders, targets) in enumerate(entries):
        y0 = top + row * (tile + 18)
        for x0, im in zip(x, [photo, *renders, *targets]):
            sheet.paste(Image.fromarray(im).resize((tile, tile), Image.NEAREST if im.shape[0] <= tile else Image.BILINEAR),
                        (x0, y0))
        draw.text((x[0] + 4, y0 + tile + 2), key, fill=(200, 200, 200), font=label)
    buf = io.BytesIO()
    sheet.save(buf, format="PNG")
    atomic_write(path, buf.getvalue())
    return path


def write_report(result: dict, out: Path, title: str, notes: list[str] = ()) -> tuple[Path, Path]:
    """Markdown tables + JSON of an :func:`evaluate` result (with ``baselines`` when it holds them)."""
    out.mkdir(parents=True, exist_ok=True)
    lines = [f"# {title}", "", f"{plural(result['subjects'], 'subject')} evaluated, "
             f"{len(result['skipped_subjects'])} skipped (no view within {YAW_TOLERANCE:g} deg of "
             f"front/left/back/right). The {INPUT_VIEW} view is the input; {NOVEL}: left, back and right. "
             f"fg: over the foreground (target or render alpha >= {FOREGROUND_ALPHA:g}).", "",
             "| view | PSNR dB | PSNR fg dB | SSIM | SSIM fg | LPIPS | CSIM | APD deg |", "|---|---|---|---|---|---|---|---|"]
    for name, m in result["per_view"].items():
        lines.append(f"| {name} | " + " | ".join(_fmt(m[k]) for k in METRICS) + " |")
    counted = result["per_view"]["all"]["counted"]
    lines += ["", "Counted views: " + ", ".join(f"{k} {v}" for k, v in counted.items()) + ".",
              f"Reconstruction {result['reconstruct_s_median'] * 1000:.1f} ms (median, one forward pass); "
              f"render {result['render_ms_per_view_median']:.1f} ms per view (median).", ""]
    if "csim_between_subjects" in result:
        lines += [f"CSIM between the front targets of different subjects: {_fmt(result['csim_between_subjects'])} "
                  f"({plural(result['csim_between_subjects_faces'], 'face')}): what an identity-blind prediction "
                  "scores; CSIM above it shows identity.", ""]
    if result.get("baselines"):
        lines += _baseline_lines(result)
    lines += ["\n\n".join(notes)] if notes else []  # each note a paragraph of its own
    md, js = out / "eval.md", out / "eval.json"
    atomic_write(md, ("\n".join(lines) + "\n").encode())
    atomic_write(js, (json.dumps(result, indent=1) + "\n").encode())
    return md, js
