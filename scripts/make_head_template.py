"""Regenerate the embedded head templates, panolam/assets/head_template_<V>.npz.

    python scripts/make_head_template.py                  # write the shipped sizes (1280 and 5023)
    python scripts/make_head_template.py --vertices 2000  # another size
    python scripts/make_head_template.py --check          # verify the shipped files equal a fresh generation

Files hold ``vertices`` (V, 3) float32 in world units and ``faces`` (F, 3) int32; the zip entries carry
a fixed date, so the same mesh gives the same bytes. Writes go to a temporary file, fsynced, then a rename.
"""
from __future__ import annotations

import argparse
import io
import sys
import zipfile

import numpy as np

from datagen.files import atomic_write
from panolam.template import SHIPPED_VERTICES, asset_path, generate_template

ATOL = 1e-5  # world units: float32 field evaluation may differ in the last bits between machines


def npz_bytes(arrays: dict) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for name, a in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy")  # date 1980-01-01
            info.compress_type = zipfile.ZIP_DEFLATED
            with z.open(info, "w") as f:
                np.lib.format.write_array(f, a, allow_pickle=False)
    return buf.getvalue()


def write(n: int) -> None:
    vertices, faces = generate_template(n)
    path = asset_path(n)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, npz_bytes({"vertices": vertices, "faces": faces.astype(np.int32)}))
    print(f"wrote {path}: {len(vertices)} vertices, {len(faces)} faces, {path.stat().st_size} bytes")


def check(n: int) -> str | None:
    """None when the shipped file equals a fresh generation, else what differs."""
    path = asset_path(n)
    if not path.exists():
        return f"{path} is missing"
    vertices, faces = generate_template(n)
    with np.load(path) as z:
        if not np.array_equal(z["faces"], faces):
            return f"{path}: faces differ from a fresh generation"
        error = np.abs(z["vertices"] - vertices).max()
    return None if error <= ATOL else f"{path}: vertices differ by up to {error:.3g} world units (> {ATOL})"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vertices", type=int, nargs="+", default=list(SHIPPED_VERTICES))
    ap.add_argument("--check", action="store_true", help="verify instead of writing")
    args = ap.parse_args(argv)
    if not args.check:
        for n in args.vertices:
            write(n)
        return 0
    problems = [p for p in map(check, args.vertices) if p]
    print("\n".join(problems) or "shipped head templates match a fresh generation")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
