"""The 3D surface of a subject: its stored mesh, or a triangle mesh from every view's depth and mask,
each point coloured by the views that see it most head-on."""
from __future__ import annotations

import numpy as np
import pyvista as pv

from datagen.cameras import depth_points
from datagen.errors import DatasetError
from datagen.shapes import checked_mesh
from datagen.dataset.shards import SHAPE_FIELD, decode_exr

from .reader import decode_image

OPAQUE = 250          # alpha (0-255) above which a pixel is all surface, not blended with the background


def view_grid(c2w, K, alpha, depth, max_grid: int, slope: float, min_facing: float):
    """One view's surface: (points (N, 3), triangles (M, 3)) from its depth sampled on a grid of at
    most ``max_grid`` pixels a side, away from its silhouette; (None, None) when it has none.

    Each cell of four neighbouring samples becomes two triangles, dropped when the depths of its
    corners differ by more than ``slope`` times the cell's size (a depth discontinuity: glasses in
    front of the eyes, the side of the nose, not a surface) or when they face the camera at a
    grazing angle (|cos| < ``min_facing``).
    """
    R = depth.shape[0]
    step = max(1, -(-R // max_grid))
    idx = np.arange(step // 2, R, step)
    rr, cc = np.meshgrid(idx, idx, indexing="ij")
    d = depth[rr, cc].astype(np.float64)
    inside = alpha > OPAQUE
    reach = step // 2 + 1
    valid = inside[rr, cc] & np.isfinite(d) & (d > 0)
    for dr, dc in ((reach, 0), (-reach, 0), (0, reach), (0, -reach)):
        valid &= inside[np.clip(rr + dr, 0, R - 1), np.clip(cc + dc, 0, R - 1)]
    if not valid.any():
        return None, None
    pts = depth_points(c2w, K, R, rr[valid], cc[valid], d[valid])
    number = np.full(valid.shape, -1)
    number[valid] = np.arange(valid.sum())
    quad = np.stack([number[:-1, :-1], number[:-1, 1:], number[1:, :-1], number[1:, 1:]])
    dq = np.stack([d[:-1, :-1], d[:-1, 1:], d[1:, :-1], d[1:, 1:]])
    size = dq.mean(axis=0) * step / (K[0, 0] * R)   # the cell's side in world units, at its depth
    keep = np.all(quad >= 0, axis=0) & (dq.max(axis=0) - dq.min(axis=0) <= slope * size)
    a, b, c, e = quad[:, keep]
    tris = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, e], 1)])
    normal = np.cross(pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]])
    ray = pts[tris].mean(axis=1) - c2w[:3, 3]
    facing = np.abs((normal * ray).sum(1)) / (np.linalg.norm(normal, axis=1) * np.linalg.norm(ray, axis=1) + 1e-12)
    return pts, tris[facing >= min_facing]


def vertex_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit normals (N, 3) of a mesh's vertices, the area-weighted mean of their triangles' (zero
    for a vertex of no triangle)."""
    face = np.cross(points[triangles[:, 1]] - points[triangles[:, 0]], points[triangles[:, 2]] - points[triangles[:, 0]])
    out = np.zeros_like(points)
    for k in range(3):
        np.add.at(out, triangles[:, k], face)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)


def project(c2w, K, resolution: int, points: np.ndarray):
    """Where world ``points`` (N, 3) fall in a view: (row, col) as float pixel coordinates of a
    ``resolution`` px image (pixel centres at integers, as :func:`datagen.cameras.camera_directions`)
    and their distance from the camera (world units)."""
    rel = points - c2w[:3, 3]
    cam = rel @ c2w[:3, :3]
    uv = (cam / np.maximum(cam[:, 2:], 1e-9)) @ K.T
    return uv[:, 1] * resolution - 0.5, uv[:, 0] * resolution - 0.5, np.linalg.norm(rel, axis=1)


def depth_edges(alpha: np.ndarray, depth: np.ndarray, K, slope: float) -> np.ndarray:
    """(R, R) bool: pixels whose 3x3 neighbourhood holds a depth discontinuity (a depth range above
    ``slope`` times the neighbourhood's size at its depth) or a pixel not all surface. Their colour
    and depth blend two surfaces (a glasses rim and the eye behind it), so they colour nothing."""
    R = depth.shape[0]
    inside = alpha > OPAQUE
    d = np.where(inside, depth.astype(np.float64), np.nan)
    pad = np.pad(d, 1, constant_values=np.nan)
    stack = np.stack([pad[r:r + R, c:c + R] for r in range(3) for c in range(3)])
    with np.errstate(invalid="ignore"):
        spread = stack.max(axis=0) - stack.min(axis=0)
    return ~(spread <= slope * 2.0 * d / (K[0, 0] * R))    # NaN (a pixel not all surface) counts as an edge


def sample_rgb(rgb: np.ndarray, resolution: int, rows, cols) -> np.ndarray:
    """Bilinear colours (N, 3) float of an image of any size at pixel coordinates of a
    ``resolution`` px view."""
    h, w = rgb.shape[:2]
    y = np.clip((rows + 0.5) * h / resolution - 0.5, 0, h - 1)
    x = np.clip((cols + 0.5) * w / resolution - 0.5, 0, w - 1)
    y0, x0 = np.minimum(y.astype(int), h - 2), np.minimum(x.astype(int), w - 2)
    fy, fx = (y - y0)[:, None], (x - x0)[:, None]
    img = rgb.astype(np.float64)
    top = img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx
    bottom = img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


def colour_from_views(points, normals, views, slope: float, tolerance: float, sharpness: float):
    """Colour each point from the views that see it, and say which points the views contradict:
    (colours (N, 3) float, seen (N,) bool, contradicted (N,) int).

    A view sees a point when the point falls inside its mask away from a depth edge and its distance
    from the camera matches the view's depth there within ``tolerance`` pixel footprints; the
    colour is the mean over those views weighted by cos^``sharpness`` of the angle between the
    point's normal and the view's ray (the most head-on view dominates; an oblique view, whose
    pixels stretch over the surface, hardly counts). A view contradicts a point when, away from its
    depth edges, it sees a surface farther than the point by more than ``tolerance`` footprints:
    the point floats in space that view saw through.
    """
    n = len(points)
    total, weight = np.zeros((n, 3)), np.zeros(n)
    contradicted = np.zeros(n, np.int64)
    for c2w, K, rgb, alpha, depth in views:
        R = depth.shape[0]
        facing = ((c2w[:3, 3] - points) * normals).sum(1)      # > 0: the point's front faces the camera
        idx = np.nonzero(facing > 0)[0]
        rows, cols, dist = project(c2w, K, R, points[idx])
        r, c = np.rint(rows).astype(int), np.rint(cols).astype(int)
        frame = (r >= 0) & (r < R) & (c >= 0) & (c < R)
        r, c = np.where(frame, r, 0), np.where(frame, c, 0)
        clean = frame & ~depth_edges(alpha, depth, K, slope)[r, c]
        footprint = dist / (K[0, 0] * R)
        gap = depth[r, c] - dist
        sees = clean & (np.abs(gap) <= tolerance * footprint)
        contradicted[idx] += clean & (gap > tolerance * footprint)
        hit = np.nonzero(sees)[0]
        w = np.minimum(facing[idx[hit]] / dist[hit], 1.0) ** sharpness
        total[idx[hit]] += w[:, None] * sample_rgb(rgb, R, rows[hit], cols[hit])
        weight[idx[hit]] += w
    seen = weight > 0
    total[seen] /= weight[seen, None]
    return total, seen, contradicted


def fill_from_neighbours(colours, known, triangles, rings: int):
    """Colours (N, 3) where ``known`` is False taken from the known vertices of their triangles,
    ``rings`` times outwards (each time from the ones just filled too): (colours, known)."""
    colours, known = colours.copy(), known.copy()
    for _ in range(rings):
        total, count = np.zeros_like(colours), np.zeros(len(colours))
        for a in range(3):
            for b in range(3):
                src, dst = triangles[:, a], triangles[:, b]
                use = known[src] & ~known[dst]
                np.add.at(total, dst[use], colours[src[use]])
                np.add.at(count, dst[use], 1)
        new = count > 0
        if not new.any():
            break
        colours[new] = total[new] / count[new, None]
        known |= new
    return colours, known


def surface_mesh(views, max_grid: int = 96, slope: float = 2.0, min_facing: float = 0.2, tolerance: float = 2.0,
                 sharpness: float = 8.0, fill_rings: int = 3):
    """A triangle surface coloured by the images, from each view's depth and mask: (points (N, 3)
    float32, triangles (M, 3) int64, colours (N, 3) uint8), or None.

    ``views``: [(cam2world 4x4, K 3x3, rgb (h, w, 3) at any size, alpha (R, R), depth (R, R)), ...].
    Every view adds its surface (:func:`view_grid`); the surfaces of all views occlude each other, so
    what is hidden from a direction stays hidden. Every point is coloured from the views that see
    it most head-on (weights cos^``sharpness``), never from pixels at a depth edge, whose colours
    mix a glasses rim with the eye behind it (each view painting its own points, edges included,
    put that rim colour on the eye, where other directions show it beside the real rim: doubled
    glasses; the same at any depth edge, such as the side of the nose). A point that a view saw through (farther than ``tolerance``
    pixel footprints behind it) is dropped; one that no view sees cleanly takes the colour of its
    neighbours up to ``fill_rings`` triangles away, or is dropped. None when no view has any
    surface. Plain arrays: safe to make in the background thread.
    """
    views = [(np.asarray(c, np.float64), np.asarray(k, np.float64), rgb, a, d) for c, k, rgb, a, d in views]
    points, faces, base = [], [], 0
    for c2w, K, _, alpha, depth in views:
        p, tris = view_grid(c2w, K, alpha, depth, max_grid, slope, min_facing)
        if p is None or not len(tris):
            continue
        normals = vertex_normals(p, tris)
        normals *= np.sign(((c2w[:3, 3] - p) * normals).sum(1))[:, None]   # towards the camera that saw them
        points.append((p, normals))
        faces.append(tris + base)
        base += len(p)
    if not faces:
        return None
    pts = np.concatenate([p for p, _ in points])
    normals = np.concatenate([nr for _, nr in points])
    tris = np.concatenate(faces)
    colours, seen, contradicted = colour_from_views(pts, normals, views, slope, tolerance, sharpness)
    tris = tris[(contradicted[tris] == 0).all(axis=1)]
    colours, seen = fill_from_neighbours(colours, seen, tris, fill_rings)
    tris = tris[seen[tris].all(axis=1)]
    if not len(tris):
        return None
    used = np.unique(tris)
    renumber = np.full(len(pts), -1)
    renumber[used] = np.arange(len(used))
    return (pts[used].astype(np.float32), renumber[tris].astype(np.int64),
            np.clip(np.rint(colours[used]), 0, 255).astype(np.uint8))


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


def subject_surface(reader, item, meta: dict):
    """The subject's 3D surface, (arrays as :func:`surface_mesh` gives them, or None; what they are).
    The mesh stored with the subject (``datagen sample --save-shape``), checked against its record,
    when there is one: it is the head's own surface. Otherwise :func:`surface_mesh` from its
    metadata and its views' images, masks and depths, read here at their full size (the review
    grid's cells are smaller: colours from them blur the face). Also in the background."""
    where = f"{item.shard}: {item.subject}"
    record = meta.get("shape")
    if record is not None:
        mesh, problems = checked_mesh(reader.read(item, [SHAPE_FIELD])[SHAPE_FIELD], record, where)
        if problems:
            raise DatasetError(problems[0])
        return ((mesh.vertices, mesh.faces, mesh.colors),
                f"the stored mesh ({SHAPE_FIELD}, {len(mesh.vertices):,} vertices)")
    names = [v["name"] for v in meta["views"]]
    data = reader.read(item, [f"{n}{kind}" for n in names for kind in (".png", ".mask.png", ".depth.exr")])
    views = []
    for n, v in zip(names, meta["views"]):
        try:
            depth = decode_exr(data[f"{n}.depth.exr"])
        except Exception as e:  # the decoder's own error
            raise DatasetError(f"{where} {n}.depth.exr does not decode ({type(e).__name__}: {e})") from None
        views.append((np.array(v["cam2world"]), np.array(v["intrinsics"]), decode_image(data[f"{n}.png"], f"{where} {n}.png"),
                      decode_image(data[f"{n}.mask.png"], f"{where} {n}.mask.png"), depth))
    return surface_mesh(views), "built from the views' depth and masks (no stored mesh)"


def set_view_camera(plotter: pv.Plotter, c2w, K) -> None:
    """Look through a dataset camera (OpenCV cam2world, normalized intrinsics, square image, centred
    principal point): ``plotter``'s window shows what the view's image shows."""
    c2w = np.asarray(c2w, np.float64)
    plotter.camera.parallel_projection = False
    plotter.camera.position = tuple(c2w[:3, 3])
    plotter.camera.focal_point = tuple(c2w[:3, 3] + c2w[:3, 2])
    plotter.camera.up = tuple(-c2w[:3, 1])
    plotter.camera.view_angle = float(np.degrees(2.0 * np.arctan(0.5 / K[1][1])))
    distance = np.linalg.norm(c2w[:3, 3])
    plotter.camera.clipping_range = (0.1 * distance, 3.0 * distance)


def renders_from_views(arrays, cameras, resolution: int, background=(255, 255, 255)) -> list:
    """The surface (arrays as :func:`surface_mesh` gives them) drawn off-screen as the review window
    draws it, through each of ``cameras`` [(cam2world, K), ...] at ``resolution`` px:
    [(rgb (R, R, 3) uint8 on ``background``, covered (R, R) bool), ...]."""
    from .window import Window

    window = Window(True, (resolution, resolution), "surface check")
    try:
        window.plotter.set_background(background)
        surface_actor(window.plotter, polydata(*arrays))
        out = []
        for c2w, K in cameras:
            set_view_camera(window.plotter, c2w, K)
            window.render()
            out.append((window.screenshot(), np.isfinite(window.plotter.get_image_depth(fill_value=np.nan))))
        return out
    finally:
        window.close()


def surface_errors(arrays, views, margin: int = 3, wrong_above: float = 16.0) -> dict:
    """How far the surface drawn through each view's camera is from the view's image, over the
    view's interior (its all-surface pixels, ``margin`` px in from the silhouette, which the surface
    leaves to the views that see it less obliquely): per view lists of "mae" (mean absolute error,
    0-255), "psnr" (dB, on [0, 1]), "wrong" (the share of interior pixels off by more than
    ``wrong_above`` on average over RGB: specks, ghost rims, holes) and "covered" (the share drawn).
    ``views`` as :func:`surface_mesh` takes them; the images must have the depth's size."""
    from scipy.ndimage import binary_erosion

    R = views[0][4].shape[0]
    renders = renders_from_views(arrays, [(c2w, K) for c2w, K, *_ in views], R)
    out = {"mae": [], "psnr": [], "wrong": [], "covered": []}
    for (rgb, covered), (_, _, image, alpha, _) in zip(renders, views):
        interior = binary_erosion(alpha > OPAQUE, iterations=margin)
        diff = np.abs(rgb.astype(np.float64) - image)[interior]
        mse = float((diff ** 2).mean()) / 255.0 ** 2
        out["mae"].append(float(diff.mean()))
        out["psnr"].append(float(10.0 * np.log10(1.0 / max(mse, 1e-12))))
        out["wrong"].append(float((diff.mean(axis=1) > wrong_above).mean()))
        out["covered"].append(float(covered[interior].mean()))
    return out


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
