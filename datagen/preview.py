"""``datagen preview`` (a labelled contact sheet of one subject) and ``datagen info``."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from .errors import SettingError, UserError
from .files import atomic_write
from .dataset import Dataset
from .dataset.shards import subject_id

MIN_CELL = 160
LABEL_HEIGHT = 30
TITLE_HEIGHT = 26


def font(size: int):
    """Pillow's default font at ``size`` px (its bitmap font on a Pillow without sized fonts)."""
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # older Pillow without sized default fonts
        return ImageFont.load_default()


def _depth_image(depth: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Depth as grey levels (near = bright) inside the mask, black outside."""
    inside = alpha > 127
    out = np.zeros(depth.shape, dtype=np.uint8)
    if inside.any():
        d = depth[inside]
        lo, hi = float(d.min()), float(d.max())
        out[inside] = np.clip(255 * (1 - (d - lo) / max(hi - lo, 1e-6)) * 0.8 + 40, 0, 255).astype(np.uint8)
    return out


def contact_sheet(dataset, subject: str, columns: int = 8, with_mask_depth: bool = False) -> Image.Image:
    """All views of one subject of ``dataset`` (a Dataset or its folder) in a grid, each labelled with its camera."""
    dataset = Dataset.of(dataset)
    sample = dataset.read_subject(subject)
    meta = sample.metadata
    res = meta["resolution"]
    scale = max(1, -(-MIN_CELL // res))
    tile = res * scale
    parts = 3 if with_mask_depth else 1
    n = len(sample.rgb)
    columns = max(1, min(columns, n))
    rows = -(-n // columns)
    cell_w, cell_h = tile * parts, tile + LABEL_HEIGHT
    sheet = Image.new("RGB", (columns * cell_w, TITLE_HEIGHT + rows * cell_h), (30, 30, 30))
    draw = ImageDraw.Draw(sheet)
    title = (f"{dataset.root.name}  {sample.key}  generator={meta['generator']['name']}  protocol={meta['protocol']}"
             f"  {res}x{res}  {n} views")
    draw.text((6, 5), title, fill=(235, 235, 235), font=font(14))
    small = font(11)
    for i, view in enumerate(meta["views"]):
        r, c = divmod(i, columns)
        x0, y0 = c * cell_w, TITLE_HEIGHT + r * cell_h
        images = [sample.rgb[i]]
        if with_mask_depth:
            images += [np.repeat(sample.alpha[i][..., None], 3, -1),
                       np.repeat(_depth_image(sample.depth[i], sample.alpha[i])[..., None], 3, -1)]
        for k, im in enumerate(images):
            big = Image.fromarray(im).resize((tile, tile), Image.NEAREST)
            sheet.paste(big, (x0 + k * tile, y0))
        label = (f"{view['name']} yaw {view['yaw_deg']:.0f} pitch {view['pitch_deg']:+.0f}\n"
                 f"r {view['radius']:.2f}  fov {view['fov_deg']:.1f}")
        draw.multiline_text((x0 + 4, y0 + tile + 2), label, fill=(220, 220, 220), font=small, spacing=1)
    return sheet


def parse_subject(arg: str) -> str:
    """'3' -> 'subj00000003'; a full subject id passes through."""
    if arg.isdigit():
        return subject_id(int(arg))
    if arg.startswith("subj") and arg[4:].isdigit():
        return arg
    raise SettingError(f"{{subject}} must be a subject number or id like subj00000003, not {arg!r}")


def write_contact_sheet(root, subject: str, out, columns: int = 8, with_mask_depth: bool = False) -> Path:
    out = Path(out)
    sheet = contact_sheet(root, parse_subject(subject), columns, with_mask_depth)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        fmt = Image.registered_extensions().get(out.suffix.lower(), "PNG")
        atomic_write(out, lambda f: sheet.save(f, format=fmt))
    except OSError as e:
        raise UserError(f"cannot write {out}: {e.strerror}") from None
    return out


def dataset_info(dataset) -> dict:
    dataset = Dataset.of(dataset)
    root, index, shards = dataset.root, dataset.index, dataset.shards
    size = sum(p.stat().st_size for p in root.glob("shard-*.tar"))
    s = index["settings"]
    return {
        "path": str(root),
        "generator": index["generator"]["name"],
        "protocol": s["protocol"],
        "resolution": s["resolution"],
        "views_per_subject": index["views_per_subject"],
        "subjects": index["num_subjects"],
        "subjects_complete": len(dataset.complete_subjects),
        "shards": len(shards),
        "shards_complete": len(dataset.complete_shards),
        "seed": s["seed"],
        "bytes": size,
        "software": s.get("software", {}),
    }
