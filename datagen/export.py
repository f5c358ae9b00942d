"""``datagen export``: subjects' views and cameras in the layouts of nerfstudio, instant-ngp/Blender
(what graphdeco's 3DGS ``train.py`` reads) and COLMAP text.

Source conventions (``datagen/cameras.py``, ``datagen/dataset/shards.py``): OpenCV cam2world (x right, y
down, z forward), intrinsics normalized by image size, pixel centres at half-integers of pixel K,
depth = distance along the unit ray from the camera centre (world units, 0 where alpha is 0).
Targets: nerfstudio and instant-ngp/Blender take OpenGL cam2world (x right, y up, z backward);
COLMAP takes world-to-camera rotation (quaternion) and translation in OpenCV axes. Depth maps
(nerfstudio, instant-ngp) are z-depth (along the camera's forward axis) in millimetres, 16-bit PNG.

Every requested subject is resolved and checked (:func:`check_subjects`) before anything is written,
so a wrong id or an incomplete shard writes nothing. Then every subject goes to ``OUT/<subject id>/``
all or nothing: it is written under a temporary folder (each file through :func:`atomic_write`) and
renamed into place when complete.
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from .cameras import camera_directions, depth_points, pixel_intrinsics
from .errors import DatasetError
from .files import atomic_write
from .dataset import Dataset
from .dataset.shards import dumps, encode_png, is_complete, read_sidecar, tar_path

FORMATS = ("nerfstudio", "instant-ngp", "colmap")
BACKGROUNDS = {"transparent": None, "white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])  # flips the camera's y and z axes (an involution)
DEPTH_PNG_SCALE = 1000.0  # depth PNG units per world unit (nerfstudio's default depth_unit_scale_factor 1e-3)
TEST_EVERY = 8  # instant-ngp/Blender: views 0, 8, 16, ... go to transforms_test.json
POINTS_PER_VIEW = 2000  # COLMAP points3D and points3d.ply: at most this many depth pixels per view


# ----------------------------------------------------------------------------------------------
# Pure conversions

def opengl_cam2world(cam2world) -> np.ndarray:
    """OpenCV cam2world (..., 4, 4) -> OpenGL/Blender cam2world (camera y up, z backward); and back."""
    return np.asarray(cam2world, dtype=np.float64) @ OPENCV_TO_OPENGL


def pixel_camera(K_norm, width: int, height: int) -> dict:
    """Normalized K -> pixel ``fl_x, fl_y, cx, cy, w, h`` (pixel centres at half-integers)."""
    K = pixel_intrinsics(np.asarray(K_norm, dtype=np.float64), width, height)
    return {"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
            "w": int(width), "h": int(height)}


def camera_angle_x(K_norm) -> float:
    """The true horizontal FOV in radians (Blender's ``camera_angle_x``) of a normalized K."""
    return float(2.0 * np.arctan(0.5 / np.asarray(K_norm, dtype=np.float64)[0, 0]))


def rotation_to_quaternion(R) -> np.ndarray:
    """3x3 rotation -> unit quaternion (w, x, y, z) with w >= 0 (COLMAP's order)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    q = np.array([w, x, y, z])
    return q if w >= 0 else -q


def colmap_pose(cam2world) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV cam2world -> COLMAP (qvec (w, x, y, z), tvec) of world-to-camera."""
    c2w = np.asarray(cam2world, dtype=np.float64)
    R = c2w[:3, :3].T
    return rotation_to_quaternion(R), -R @ c2w[:3, 3]


def ray_to_z_depth(depth, K_norm) -> np.ndarray:
    """Distance along the unit ray (R, R) -> depth along the camera's z axis (0 stays 0)."""
    depth = np.asarray(depth, dtype=np.float64)
    rows, cols = np.indices(depth.shape)
    return depth / np.linalg.norm(camera_directions(np.asarray(K_norm), depth.shape[0], rows, cols), axis=-1)


def backproject(depth, cam2world, K_norm) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) of the pixels with ray depth > 0 of a square view, and those pixels'
    (row, col) (N, 2)."""
    depth = np.asarray(depth, dtype=np.float64)
    rows, cols = np.nonzero(depth > 0)
    points = depth_points(np.asarray(cam2world, dtype=np.float64), np.asarray(K_norm, dtype=np.float64),
                          depth.shape[0], rows, cols, depth[rows, cols])
    return points, np.stack([rows, cols], -1)


def composite(rgb, alpha, source_background, background) -> np.ndarray:
    """uint8 RGBA (``background`` None: straight colour, the mask as alpha) or RGB on ``background``.

    ``rgb`` was composited on ``source_background`` (an R,G,B in [0, 1]); that is removed first.
    With a source background that is not a colour (a GAN's own), edge pixels keep some of it.
    """
    a = np.asarray(alpha, dtype=np.float64)[..., None] / 255.0
    colour = np.asarray(rgb, dtype=np.float64) / 255.0
    premultiplied = colour - (1.0 - a) * np.asarray(source_background) if source_background is not None else colour * a
    premultiplied = np.clip(premultiplied, 0.0, a)
    if background is None:
        straight = np.divide(premultiplied, a, out=np.zeros_like(premultiplied), where=a > 0)
        return np.rint(np.concatenate([straight, a], -1) * 255.0).astype(np.uint8)
    return np.rint((premultiplied + (1.0 - a) * np.asarray(background)) * 255.0).astype(np.uint8)


def depth_png(z_depth) -> np.ndarray:
    """z-depth in world units -> uint16 millimetres (0 = no depth)."""
    return np.clip(np.rint(np.asarray(z_depth) * DEPTH_PNG_SCALE), 0, 65535).astype(np.uint16)


def fov_pixel_error(K_norm_views, alphas, file_angle_x: float) -> float:
    """Largest pixel shift, over the masks of all views, of drawing each view with the one horizontal
    FOV ``file_angle_x`` (radians) instead of its own (what a 3DGS user of the Blender layout gets)."""
    worst = 0.0
    for K, alpha in zip(K_norm_views, alphas):
        h, w = alpha.shape
        own = pixel_camera(K, w, h)
        ratio = (0.5 / np.tan(file_angle_x / 2.0)) / K[0, 0]
        rows, cols = np.nonzero(alpha > 127)
        if rows.size:
            radius = np.hypot(cols + 0.5 - own["cx"], rows + 0.5 - own["cy"])
            worst = max(worst, float(radius.max() * abs(ratio - 1.0)))
    return worst


# ----------------------------------------------------------------------------------------------
# One subject, read once

class ExportViews:
    """One subject's views ready to export: names, cam2world (OpenCV), normalized K, images, depth."""

    def __init__(self, dataset: Dataset, key: str, background: str):
        sample = dataset.read_subject(key)
        meta = sample.metadata
        source_bg = meta.get("background")
        source_bg = source_bg if isinstance(source_bg, list) and len(source_bg) == 3 else None
        self.key = key
        self.names = [v["name"] for v in meta["views"]]
        self.cam2world = np.array([v["cam2world"] for v in meta["views"]], dtype=np.float64)
        self.K = np.array([v["intrinsics"] for v in meta["views"]], dtype=np.float64)
        self.alpha = sample.alpha
        self.depth = sample.depth
        self.rgb = sample.rgb
        self.images = [composite(rgb, a, source_bg, BACKGROUNDS[background]) for rgb, a in zip(sample.rgb, sample.alpha)]
        self.height, self.width = sample.alpha[0].shape

    def z_depth_png(self, i: int) -> np.ndarray:
        return depth_png(ray_to_z_depth(self.depth[i], self.K[i]))

    def points(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Per view: world points (N, 3) back-projected from evenly spaced depth pixels (at most
        2000), their (row, col) (N, 2) and uint8 colours (N, 3) from the view."""
        out = []
        for i in range(len(self.names)):
            world, pixels = backproject(self.depth[i], self.cam2world[i], self.K[i])
            keep = np.unique(np.linspace(0, len(world) - 1, min(POINTS_PER_VIEW, len(world))).astype(int))
            out.append((world[keep], pixels[keep], self.rgb[i][pixels[keep, 0], pixels[keep, 1]]))
        return out


def _write_json(path: Path, doc: dict) -> None:
    atomic_write(path, (json.dumps(doc, indent=1) + "\n").encode())


def _write_views(folder: Path, views: ExportViews, images: str, depth: str | None) -> None:
    """Images ``<images>/vII.png`` and, with ``depth``, z-depth PNGs ``<depth>/vII.png``."""
    (folder / images).mkdir(parents=True)
    for name, image in zip(views.names, views.images):
        atomic_write(folder / images / f"{name}.png", encode_png(image))
    if depth:
        (folder / depth).mkdir()
        for i, name in enumerate(views.names):
            atomic_write(folder / depth / f"{name}.png", encode_png(views.z_depth_png(i)))


def _write_ply(path: Path, points) -> None:
    """Points as the binary PLY 3DGS reads and writes: x y z, nx ny nz (zero), red green blue."""
    from plyfile import PlyData, PlyElement

    world = np.concatenate([p[0] for p in points])
    colours = np.concatenate([p[2] for p in points])
    fields = [(k, "f4") for k in ("x", "y", "z", "nx", "ny", "nz")] + [(k, "u1") for k in ("red", "green", "blue")]
    vertex = np.zeros(len(world), dtype=fields)
    vertex["x"], vertex["y"], vertex["z"] = world.T
    vertex["red"], vertex["green"], vertex["blue"] = colours.T
    atomic_write(path, lambda f: PlyData([PlyElement.describe(vertex, "vertex")]).write(f))


def _opengl_frame(views: ExportViews, i: int) -> dict:
    return {"transform_matrix": opengl_cam2world(views.cam2world[i]).tolist(),
            **pixel_camera(views.K[i], views.width, views.height)}


# ----------------------------------------------------------------------------------------------
# Formats: each writes one subject into ``folder`` and returns notes for the summary

def export_nerfstudio(views: ExportViews, folder: Path) -> dict:
    """``transforms.json`` (OpenGL cam2world, per-frame ``fl_x fl_y cx cy``, ``depth_file_path``),
    ``images/vII.png``, ``depth/vII.png`` (z-depth, mm)."""
    _write_views(folder, views, "images", "depth")
    frames = [{"file_path": f"images/{n}.png", "depth_file_path": f"depth/{n}.png", **_opengl_frame(views, i)}
              for i, n in enumerate(views.names)]
    _write_json(folder / "transforms.json", {"camera_model": "OPENCV", "w": views.width, "h": views.height,
                                             "frames": frames})
    return {}


def export_instant_ngp(views: ExportViews, folder: Path) -> dict:
    """``transforms_train.json`` / ``transforms_test.json`` (every 8th view from v00 is a test view):
    OpenGL cam2world; per frame ``camera_angle_x`` and ``fl_x fl_y cx cy w h`` (instant-ngp reads
    these), file-level ``camera_angle_x`` the median (3DGS reads only this one); ``file_path`` without
    extension (3DGS appends .png); ``depth_path`` z-depth PNGs with ``integer_depth_scale``; and
    ``points3d.ply``, the depth points, which 3DGS starts from instead of random points."""
    _write_views(folder, views, "images", "depth")
    _write_ply(folder / "points3d.ply", views.points())
    angles = [camera_angle_x(K) for K in views.K]
    file_angle = float(np.median(angles))
    splits = {"train": [], "test": []}
    for i, name in enumerate(views.names):
        frame = {"file_path": f"images/{name}", "depth_path": f"depth/{name}.png",
                 "camera_angle_x": angles[i], **_opengl_frame(views, i)}
        splits["test" if i % TEST_EVERY == 0 else "train"].append(frame)
    for split, frames in splits.items():
        _write_json(folder / f"transforms_{split}.json",
                    {"camera_angle_x": file_angle, "w": views.width, "h": views.height,
                     "integer_depth_scale": 1.0 / DEPTH_PNG_SCALE, "frames": frames})
    return {"file_fov_max_px_error": fov_pixel_error(views.K, views.alpha, file_angle)}


def export_colmap(views: ExportViews, folder: Path) -> dict:
    """``images/vII.png`` and ``sparse/0/{cameras,images,points3D}.txt``: one PINHOLE camera per view
    (``fx fy cx cy`` in pixels), world-to-camera poses, the depth points (:meth:`ExportViews.points`)
    with a one-image track each (their pixel centre in ``images.txt``)."""
    _write_views(folder, views, "images", None)
    sparse = folder / "sparse" / "0"
    sparse.mkdir(parents=True)
    cameras, images, points = [], [], []
    for i, (name, (world, pixels, colours)) in enumerate(zip(views.names, views.points())):
        cam = pixel_camera(views.K[i], views.width, views.height)
        cameras.append(f"{i + 1} PINHOLE {cam['w']} {cam['h']} {cam['fl_x']!r} {cam['fl_y']!r} {cam['cx']!r} {cam['cy']!r}")
        q, t = colmap_pose(views.cam2world[i])
        ids = range(len(points) + 1, len(points) + 1 + len(world))
        points += [f"{pid} {x!r} {y!r} {z!r} {r} {g} {b} 0 {i + 1} {k}"
                   for k, (pid, (x, y, z), (r, g, b)) in enumerate(zip(ids, world.tolist(), colours.tolist()))]
        observations = " ".join(f"{c + 0.5} {r + 0.5} {pid}" for (r, c), pid in zip(pixels.tolist(), ids))
        images.append(f"{i + 1} {' '.join(repr(float(x)) for x in (*q, *t))} {i + 1} {name}.png\n{observations}")
    for what, lines in (("cameras", cameras), ("images", images), ("points3D", points)):
        atomic_write(sparse / f"{what}.txt", (f"# {what} of {views.key}, written by datagen export\n"
                                              + "\n".join(lines) + "\n").encode())
    return {"points3D": len(points)}


EXPORTERS = {"nerfstudio": export_nerfstudio, "instant-ngp": export_instant_ngp, "colmap": export_colmap}


# ----------------------------------------------------------------------------------------------
# Datasets

def check_subjects(dataset: Dataset, keys) -> list[str]:
    """``keys`` without repeats, once every one is known to be readable: in the dataset's index, in a
    complete shard (its sidecar, and its tar at the recorded size) that records the subject's byte
    range. Otherwise one DatasetError naming the dataset and every subject that is not (at most
    three, then how many more), before anything is written."""
    root, shard_of = dataset.root, dataset.shard_of
    keys = list(dict.fromkeys(keys))
    problems = []
    for key in keys:
        if key not in shard_of:
            problems.append(f"{dataset.index_path}: no subject {key} in this dataset")
        elif not is_complete(root, shard_of[key]):
            problems.append(f"{tar_path(root, shard_of[key])}: the shard holding {key} is not complete "
                            "(see datagen verify)")
        elif key not in read_sidecar(root, shard_of[key])["offsets"]:
            problems.append(f"{tar_path(root, shard_of[key])}: its sidecar has no byte range for {key}")
    if problems:
        more = f"; and {len(problems) - 3} more" if len(problems) > 3 else ""
        raise DatasetError("; ".join(problems[:3]) + more + "; nothing was exported")
    return keys


def export_subject(dataset: Dataset, key: str, fmt: str, out, background: str = "transparent") -> dict:
    """Export one subject to ``out/<key>/`` (replacing an earlier export) all or nothing; a summary."""
    out = Path(out)
    views = ExportViews(dataset, key, background)
    out.mkdir(parents=True, exist_ok=True)
    final, tmp = out / key, out / f".{key}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        notes = EXPORTERS[fmt](views, tmp)
        atomic_write(tmp / "export.json", dumps({"source": str(dataset.root.resolve()), "subject": key,
                                                 "format": fmt, "background": background, **notes}))
        old = out / f".{key}.old-{os.getpid()}"
        if final.exists():
            os.replace(final, old)
        try:
            os.replace(tmp, final)
        except OSError:
            if old.exists():
                os.replace(old, final)
            raise
        shutil.rmtree(old, ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {"subject": key, "path": str(final), "views": len(views.names), **notes}
