"""The 3D surface of a subject: its stored mesh, or a triangle mesh from every view's depth and mask,
coloured by the images."""
from __future__ import annotations

import numpy as np
import pyvista as pv

from datagen.cameras import depth_points
from datagen.errors import DatasetError
from datagen.shapes import checked_mesh
from datagen.shards import SHAPE_FIELD, decode_exr

from .reader import decode_image


def surface_mesh(views, max_grid: int = 80, slope: float = 2.0, min_facing: float = 0.2):
    """A triangle surface coloured by the images, from each view's depth and mask: (points (N, 3)
    float32, triangles (M, 3) int64, colours (N, 3) uint8), or None.

    ``views``: [(cam2world 4x4, K 3x3, rgb (h, w, 3) at any size, alpha (R, R), depth (R, R)), ...].
    Each view is sampled on a grid of at most ``max_grid`` pixels a side, away from its silhouette
    (whose depth and colour blend with the background); each cell of four neighbouring samples
    becomes two triangles. Both are dropped when the depths of the cell's corners differ by more than
    ``slope`` times the cell's size (the spacing of its samples at its depth): that is a depth
    discontinuity (glasses in front of the eyes, the side of the nose, an ear), not a surface, and
    meshing it stretches triangles across the gap, smeared with both sides' colours (the spikes
    around glasses, eyes and nose of a slope of 5, which let a jump of 5 cells through). A surface
    steeper than ~63 degrees (slope 2) is left to the views that see it less obliquely (32 views
    around the head), as are triangles facing the camera at a grazing angle (|cos| < ``min_facing``).
    The surfaces of all views occlude each other, so what is hidden from a direction stays hidden.
    None when no view has any surface. Plain arrays: safe to make in the background thread.
    """
    points, colors, faces, base = [], [], [], 0
    for c2w, K, rgb, alpha, depth in views:
        c2w, K = np.asarray(c2w, np.float64), np.asarray(K, np.float64)
        R = depth.shape[0]
        step = max(1, -(-R // max_grid))
        idx = np.arange(step // 2, R, step)
        rr, cc = np.meshgrid(idx, idx, indexing="ij")
        d = depth[rr, cc].astype(np.float64)
        inside = alpha > 250
        reach = step // 2 + 1
        valid = inside[rr, cc] & np.isfinite(d) & (d > 0)
        for dr, dc in ((reach, 0), (-reach, 0), (0, reach), (0, -reach)):
            valid &= inside[np.clip(rr + dr, 0, R - 1), np.clip(cc + dc, 0, R - 1)]
        if not valid.any():
            continue
        pts = depth_points(c2w, K, R, rr, cc, np.where(valid, d, 0))
        scale = rgb.shape[0] / R
        col = rgb[np.minimum((rr * scale).astype(int), rgb.shape[0] - 1),
                  np.minimum((cc * scale).astype(int), rgb.shape[1] - 1)]
        number = np.full(valid.shape, -1)
        number[valid] = np.arange(valid.sum())
        quad = np.stack([number[:-1, :-1], number[:-1, 1:], number[1:, :-1], number[1:, 1:]])
        dq = np.stack([d[:-1, :-1], d[:-1, 1:], d[1:, :-1], d[1:, 1:]])
        size = dq.mean(axis=0) * step / (K[0, 0] * R)   # the cell's side in world units, at its depth
        keep = np.all(quad >= 0, axis=0) & (dq.max(axis=0) - dq.min(axis=0) <= slope * size)
        a, b, c, e = quad[:, keep]
        tris = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, e], 1)])
        p = pts[valid]
        normal = np.cross(p[tris[:, 1]] - p[tris[:, 0]], p[tris[:, 2]] - p[tris[:, 0]])
        ray = p[tris].mean(axis=1) - c2w[:3, 3]
        norms = np.linalg.norm(normal, axis=1) * np.linalg.norm(ray, axis=1) + 1e-12
        facing = np.abs((normal * ray).sum(1)) / norms
        tris = tris[facing >= min_facing]
        faces.append(tris + base)
        points.append(p)
        colors.append(col[valid])
        base += len(p)
    if not faces or not sum(len(f) for f in faces):
        return None
    return (np.concatenate(points).astype(np.float32), np.concatenate(faces).astype(np.int64),
            np.concatenate(colors).astype(np.uint8))


def polydata(points: np.ndarray, triangles: np.ndarray, colors: np.ndarray) -> pv.PolyData:
    """A triangle mesh with RGB point colours (point array "rgb", active)."""
    mesh = pv.PolyData.from_regular_faces(points, triangles)
    mesh.point_data.set_array(colors, "rgb")
    mesh.point_data.active_scalars_name = "rgb"
    return mesh


def surface_actor(plotter: pv.Plotter, mesh: pv.PolyData) -> pv.Actor:
    """Add the surface to ``plotter``, drawn with its own colours, unlit (the images carry their
    shading); the camera and the frame are left as they are."""
    return plotter.add_mesh(mesh, scalars="rgb", rgb=True, lighting=False, show_scalar_bar=False,
                            reset_camera=False, render=False)


def subject_surface(reader, item, meta: dict, rgb_views: list):
    """The subject's 3D surface, (arrays as :func:`surface_mesh` gives them, or None; what they are).
    The mesh stored with the subject (``datagen sample --save-shape``), checked against its record,
    when there is one: it is the head's own surface. Otherwise :func:`surface_mesh` from its
    metadata, its views' images (any size) and the masks and depths read here. Also in the background."""
    where = f"{item.shard}: {item.subject}"
    record = meta.get("shape")
    if record is not None:
        mesh, problems = checked_mesh(reader.read(item, [SHAPE_FIELD])[SHAPE_FIELD], record, where)
        if problems:
            raise DatasetError(problems[0])
        return ((mesh.vertices, mesh.faces, mesh.colors),
                f"the stored mesh ({SHAPE_FIELD}, {len(mesh.vertices):,} vertices)")
    names = [v["name"] for v in meta["views"]]
    data = reader.read(item, [f"{n}.mask.png" for n in names] + [f"{n}.depth.exr" for n in names])
    views = []
    for n, v, rgb in zip(names, meta["views"], rgb_views):
        try:
            depth = decode_exr(data[f"{n}.depth.exr"])
        except Exception as e:  # the decoder's own error
            raise DatasetError(f"{where} {n}.depth.exr does not decode ({type(e).__name__}: {e})") from None
        views.append((np.array(v["cam2world"]), np.array(v["intrinsics"]), rgb,
                      decode_image(data[f"{n}.mask.png"], f"{where} {n}.mask.png"), depth))
    return surface_mesh(views), "built from the views' depth and masks (no stored mesh)"


def frame_front(plotter: pv.Plotter, bounds) -> None:
    """Point ``plotter``'s camera at a surface with ``bounds`` from the front (+z), all of it in view
    (a 30 degree view angle, perspective, y up)."""
    b = bounds
    center = np.array([(b[0] + b[1]) / 2, (b[2] + b[3]) / 2, (b[4] + b[5]) / 2])
    radius = 0.5 * np.linalg.norm([b[1] - b[0], b[3] - b[2], b[5] - b[4]])
    plotter.camera.parallel_projection = False
    plotter.camera.view_angle = 30.0
    eye = center + np.array([0.0, 0.0, 1.05 * radius / np.sin(np.radians(15.0))])
    plotter.camera_position = [tuple(eye), tuple(center), (0.0, 1.0, 0.0)]   # resets the clipping range too
