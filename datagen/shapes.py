"""Subjects' head surfaces as coloured triangle meshes (``datagen sample --save-shape``, ``datagen shape``).

Vertices are in the dataset's world frame and units (the cameras' frame, ``datagen/cameras.py``:
y up, face toward +z), faces wind counter-clockwise seen from outside (normals point out).

* GANs (EG3D, PanoHead, SphereHead): as the originals' samplers' ``--shapes`` option, the raw
  density (the decoder's sigma, before the renderer's softplus) is sampled on a RES^3 grid of
  points spaced box_warp / (RES - 1) apart from corner to corner of the generator's box, the
  outermost 30 / 256 of the grid on every side is set to -1000 (the originals' trim; it also
  closes the surface), and the surface is the level 10 of that density (the level the originals
  mesh at). PanoHead and SphereHead's density crop applies, as in their renders. Grid points are
  made and evaluated on the generator's device, in chunks sized by its memory budget (the ray
  chunks' memory model); one copy of the density comes back to the host for marching cubes.
  Vertex colours: the generator's own decoder evaluated at each vertex, turned into RGB as its
  raw (neural) image is (EG3D: the first three feature channels; PanoHead/SphereHead: their
  ToRGB layer), in [-1, 1] mapped to 0..255 as the dataset's images are.
* Procedural heads: the zero level of the signed distance the renderer traces (the subject's baked
  grid, sampled trilinearly as the renderer samples it) on a RES^3 grid over its box [-BOX, BOX]^3,
  closed where the box cuts the body (the renderer fills that cut too). Vertex colours: the head's
  unshaded albedo at each vertex (the renders add baked lighting).

The originals' own PLY (EG3D ``shape_utils``) is in voxel units with the axes swapped and has no
colour; ours needs no conversion to overlay the cameras and views.
"""
from __future__ import annotations

import io
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import DatasetError, SettingError, UserError
from .files import atomic_write
from .dataset import Dataset
from .dataset.shards import SHAPE_FIELD, read_range, read_sidecar, subject_id, tar_path, to_uint8

FORMATS = ("ply", "obj", "glb")
DEFAULT_RESOLUTION = 256  # datagen shape, for a dataset that stores no shape
MIN_RESOLUTION, MAX_RESOLUTION = 16, 1024
GAN_LEVEL = 10.0  # raw density level the originals mesh at (EG3D gen_samples.py --shape-format .ply)
TRIM_PER_256 = 30  # the originals' trim: int(30 * RES / 256) grid points on every side get TRIM_DENSITY
TRIM_DENSITY = -1000.0
SDF_LEVEL = 0.0  # procedural heads: the surface is where the signed distance is 0
OUTSIDE_DISTANCE = 1000.0  # procedural: the layer around the grid that closes the surface at the box
POINTS_PER_CHUNK = 1 << 21  # procedural grid lookups per batch (CPU; 2M points is about 40 MB)
VERTICES_PER_CHUNK = 1 << 16  # procedural albedo evaluations per batch
BOX_TOLERANCE = 1e-4  # world units: how far outside its box ``check_mesh`` lets a vertex be (float32 rounding)


@dataclass
class Mesh:
    """A subject's surface: vertices (V, 3) float32 world units, faces (F, 3) int64 vertex indices
    (counter-clockwise from outside), colours (V, 3) uint8, and ``record``, what the subject's
    metadata says of it (resolution, level, field, box, counts)."""

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    record: dict


def check_resolution(res: int, setting: str) -> None:
    """A SettingError naming ``setting`` for a grid resolution outside what a mesh can be made at."""
    if not MIN_RESOLUTION <= res <= MAX_RESOLUTION:
        raise SettingError(f"{{{setting}}} must be between {MIN_RESOLUTION} and {MAX_RESOLUTION}")


def default_level(gan: str) -> float:
    """The surface level of a generator by its --gan name: the GANs' raw density level, the procedural 0."""
    return SDF_LEVEL if gan == "procedural" else GAN_LEVEL


def extract_shape(generator, subject, resolution: int, level: float | None = None) -> Mesh:
    """The surface of ``subject`` (from ``generator.sample_subject``) on a ``resolution``^3 grid.
    ``level``: GANs only, the raw density level (default 10, the originals')."""
    from .generators.gan import GANHeads  # torch: imported only where shapes are made

    check_resolution(resolution, "resolution")
    if isinstance(generator, GANHeads):
        return _gan_shape(generator, subject, resolution, GAN_LEVEL if level is None else float(level))
    if level is not None and level != SDF_LEVEL:
        raise UserError("a shape level is only for the GAN generators (the procedural surface is the zero "
                        "level of its signed distance)")
    return _procedural_shape(generator, subject, resolution)


def surface_mesh(volume: np.ndarray, level: float, origin: float, voxel: float, inside_above: bool, what: str):
    """Marching cubes on ``volume`` (indexed x, y, z) at ``level``: vertices (world units) and faces
    oriented outward. ``inside_above``: the inside is where values exceed the level (a density)."""
    from skimage.measure import marching_cubes

    if not np.isfinite(volume).all():
        raise UserError(f"{what}: the field has NaN or Inf values; no surface can be made")
    if not volume.min() < level < volume.max():  # the trim / closing layer hold the other side
        extreme = f"max {volume.max():.3g}" if inside_above else f"min {volume.min():.3g}"
        hint = "; a lower --shape-level meshes a weaker density" if inside_above else ""
        raise UserError(f"{what}: the field never crosses level {level:g} on the grid ({extreme}), so there is "
                        f"no surface to mesh{hint}")
    verts, faces, _normals, _values = marching_cubes(volume, level=level, spacing=(voxel,) * 3,
                                                     gradient_direction="ascent" if inside_above else "descent")
    return (verts + origin).astype(np.float32), faces.astype(np.int64)


def _gan_shape(heads, subject, res: int, level: float) -> Mesh:
    import torch

    G, dev = heads.G, heads.device
    ws, planes, _background = subject.state
    half = G.rendering_kwargs["box_warp"] / 2
    voxel = 2 * half / (res - 1)
    trim = TRIM_PER_256 * res // 256
    inner = res - 2 * trim
    field = G.field(planes)
    rk = G.rendering_kwargs
    # The ray chunks' memory model: a chunk of rays holds this many decoded points.
    chunk = heads.plan.rays * (rk["depth_resolution"] + rk["depth_resolution_importance"])
    with torch.no_grad():
        axis = torch.linspace(-half, half, res, device=dev)[trim:res - trim]
        n = inner ** 3
        sigma = torch.empty(n, device=dev)
        for start in range(0, n, chunk):
            idx = torch.arange(start, min(n, start + chunk), device=dev)
            points = torch.stack([axis[idx // (inner * inner)], axis[idx // inner % inner], axis[idx % inner]], -1)
            sigma[start:start + idx.shape[0]] = field(points[None], None)[1][0, :, 0]
        volume = np.full((res, res, res), TRIM_DENSITY, dtype=np.float32)
        volume[trim:res - trim, trim:res - trim, trim:res - trim] = sigma.reshape(inner, inner, inner).cpu().numpy()
        del sigma
        what = f"{heads.name} {subject_id(subject.index)}"
        verts, faces = surface_mesh(volume, level, -half, voxel, inside_above=True, what=what)
        del volume
        rgb = []
        on_device = torch.from_numpy(verts).to(dev)
        for start in range(0, len(verts), chunk):
            features = field(on_device[None, start:start + chunk], None)[0]
            rgb.append(_raw_rgb(G, ws, features[0]))
        colors = ((torch.cat(rgb).clamp(-1, 1) + 1) / 2).cpu().numpy()
    if not np.isfinite(colors).all():
        raise UserError(f"{what}: the decoder gives NaN or Inf colours at the surface")
    record = {"field": "raw density (decoder sigma)", "level": level, "resolution": res,
              "box_half_extent": [half] * 3, "trim_points": trim, "colour": "decoder raw RGB"}
    return _mesh(verts, faces, to_uint8(colors), record)


def _raw_rgb(G, ws, features):
    """Decoder features (M, 32) at points -> RGB (M, 3) in about [-1, 1], as ``TriPlaneGenerator.compose``
    makes its raw image from a feature image: a sigmoid decoder's features scaled to [-1, 1], then
    ``TriPlaneGenerator.raw_rgb`` (ToRGB is a 1x1 convolution, so exact per point)."""
    x = features.t()[None, :, :, None]  # a (1, 32, M, 1) feature image
    if G.decoder.activation == "sigmoid":
        x = x * 2 - 1
    return G.raw_rgb(x, ws[:1, -1])[0, :, :, 0].t()


def _procedural_shape(heads, subject, res: int) -> Mesh:
    import torch

    from .generators.procedural import BOX, head_field, sample_grid

    grid = subject.state
    voxel = 2 * BOX / (res - 1)
    axis = torch.linspace(-BOX, BOX, res)
    # One layer of OUTSIDE_DISTANCE around the grid closes the surface where the box cuts the body.
    volume = np.full((res + 2,) * 3, OUTSIDE_DISTANCE, dtype=np.float32)
    slab = max(1, POINTS_PER_CHUNK // (res * res))
    for a in range(0, res, slab):
        b = min(res, a + slab)
        points = torch.stack(torch.meshgrid(axis[a:b], axis, axis, indexing="ij"), -1).reshape(-1, 3)
        volume[1 + a:1 + b, 1:-1, 1:-1] = sample_grid(grid.sdf, points)[:, 0].reshape(b - a, res, res).numpy()
    verts, faces = surface_mesh(volume, SDF_LEVEL, -BOX - voxel, voxel, inside_above=False,
                                what=f"procedural {subject_id(subject.index)}")
    del volume
    verts = np.clip(verts, -BOX, BOX)  # the closing faces lie within 1e-4 voxels of the box
    params, defects = subject.latent["params"], subject.truth.get("defects", [])
    albedo = [head_field(torch.from_numpy(verts[i:i + VERTICES_PER_CHUNK]), params, defects)[1]
              for i in range(0, len(verts), VERTICES_PER_CHUNK)]
    record = {"field": "signed distance (the renderer's baked grid)", "level": SDF_LEVEL, "resolution": res,
              "box_half_extent": [BOX] * 3, "colour": "albedo (unshaded)"}
    return _mesh(verts, faces, to_uint8(torch.cat(albedo).numpy()), record)


def _mesh(verts, faces, colors, record) -> Mesh:
    record = {**record, "member": SHAPE_FIELD, "units": "world", "vertices": len(verts), "faces": len(faces)}
    return Mesh(vertices=verts, faces=faces, colors=colors, record=record)


# ----------------------------------------------------------------------------------------------
# Files

def encode_mesh(mesh: Mesh, fmt: str = "ply") -> bytes:
    """The mesh as a file's bytes: binary PLY (vertex colours as uchar red, green, blue, alpha),
    Wavefront OBJ (colours after each vertex, in [0, 1]) or binary glTF (COLOR_0)."""
    import trimesh

    if fmt not in FORMATS:
        raise UserError(f"unknown shape format {fmt!r}; choose {', '.join(FORMATS)}")
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, vertex_colors=mesh.colors, process=False)
    data = tm.export(file_type=fmt, **({"encoding": "binary"} if fmt == "ply" else {}))
    return data.encode() if isinstance(data, str) else data


def decode_mesh(data: bytes, where: str) -> Mesh:
    """A PLY file's bytes -> Mesh (record empty), checked to be usable: a DatasetError naming ``where``
    when it does not decode (its length disagrees with its header's counts), has no faces or no
    vertex colours, has vertices that are NaN or Inf, or faces that are not triangles of existing
    vertices. Every path that hands a mesh on goes through here (``datagen shape`` in any format,
    ``datagen verify``)."""
    from trimesh.exchange.ply import load_ply

    try:  # the reader's raw arrays: a trimesh.Trimesh would index colours by the faces before any check
        ply = load_ply(io.BytesIO(data))
        vertices, faces = np.asarray(ply["vertices"], dtype=np.float32), np.asarray(ply.get("faces", ()))
        colors = ply.get("vertex_colors")
    except Exception as e:  # the reader's own error: say which file
        raise DatasetError(f"{where}: the shape does not decode as a PLY mesh ({type(e).__name__}: {e})") from None
    if faces.size == 0:
        raise DatasetError(f"{where}: the shape is empty (no faces)")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise DatasetError(f"{where}: the shape's faces are not triangles")
    if colors is None or len(colors) != len(vertices):
        raise DatasetError(f"{where}: the shape has no vertex colours")
    if not np.isfinite(vertices).all():
        raise DatasetError(f"{where}: the shape has NaN or Inf vertices")
    low, high = int(faces.min()), int(faces.max())
    if low < 0 or high >= len(vertices):
        bad = low if low < 0 else high
        raise DatasetError(f"{where}: the shape's faces index vertex {bad:,} of {len(vertices):,}, which does not "
                           "exist (damaged bytes; datagen verify checks the whole dataset)")
    return Mesh(vertices=vertices, faces=faces.astype(np.int64), colors=np.asarray(colors)[:, :3].astype(np.uint8),
                record={})


def checked_mesh(data: bytes, record: dict, where: str) -> tuple[Mesh | None, list[str]]:
    """The one check of a shape against its record, for ``datagen verify`` and ``datagen shape``:
    (the mesh, or None when it does not decode; the problems). On top of :func:`decode_mesh`: its
    vertex and face counts are those its record gives, and every vertex is inside the box the record
    names (give or take ``BOX_TOLERANCE``)."""
    try:
        mesh = decode_mesh(data, where)
    except DatasetError as e:
        return None, [str(e)]
    problems = []
    if [len(mesh.vertices), len(mesh.faces)] != [record.get("vertices"), record.get("faces")]:
        problems.append(f"{where}: the shape has {len(mesh.vertices)} vertices and {len(mesh.faces)} faces, its "
                        f"record says {record.get('vertices')} and {record.get('faces')}")
    half = np.asarray(record.get("box_half_extent", [0.0] * 3), dtype=np.float64)
    if (np.abs(mesh.vertices) > half + BOX_TOLERANCE).any():
        problems.append(f"{where}: the shape has vertices outside its box (half extent {half.tolist()})")
    return mesh, problems


def check_mesh(data: bytes, record: dict, where: str) -> list[str]:
    """What ``datagen verify`` reports of a stored shape: the problems :func:`checked_mesh` finds."""
    return checked_mesh(data, record, where)[1]


def stored_shape(dataset, key: str):
    """(PLY bytes, record) of the shape stored with subject ``key`` of ``dataset`` (a Dataset or its folder),
    or None when its shard is not complete or holds none."""
    dataset = Dataset.of(dataset)
    root, shard = dataset.root, dataset.shard(key)
    side = read_sidecar(root, shard)
    if side is None or key not in side["offsets"]:
        return None
    start, end = side["offsets"][key]
    fields = read_range(tar_path(root, shard), key, start, end, wanted=lambda name, _: name in ("json", SHAPE_FIELD))
    record = json.loads(fields["json"]).get("shape")
    if record is None or SHAPE_FIELD not in fields:
        return None
    return fields[SHAPE_FIELD], record


def shapes_summary(dataset: Dataset) -> dict | str:
    """What ``datagen info`` says of a dataset's shapes: 'none', or the grid resolution, level and
    how many subjects of complete shards hold one."""
    settings = dataset.index["settings"]
    if not settings.get("save_shape"):
        return "none"
    done = len(dataset.complete_subjects)
    level = settings.get("shape_level")
    return {"resolution": settings["save_shape"], "level": default_level(settings["gan"]) if level is None else level,
            "subjects": done, "stored": f"{SHAPE_FIELD} in each subject's record"}


def subject_shape(dataset: Dataset, key: str, resolution: int | None = None, level: float | None = None,
                  checkpoint: str | None = None, device: str | None = None, budget_mb: float | None = None):
    """Subject ``key``'s shape: (PLY bytes, record, how) where how is 'stored' or 'extracted'.

    The stored one when the dataset holds it at the asked ``resolution`` and ``level`` (or none is
    asked for); otherwise the subject is sampled again from the settings in the index (GANs: from
    ``checkpoint``, default the path the dataset was made from, which must have the recorded
    sha256; ``device`` and ``budget_mb`` as ``datagen sample``'s) and its surface extracted."""
    from .generators import make_generator

    index = dataset.index
    dataset.shard(key)
    settings = index["settings"]
    stored = stored_shape(dataset, key) if settings.get("save_shape") else None
    if stored is not None and resolution in (None, stored[1]["resolution"]) and level in (None, stored[1]["level"]):
        return stored[0], stored[1], "stored"
    gan = settings["gan"]
    options = dict(settings["generator_options"])
    if gan != "procedural":
        options.update({k: v for k, v in (("device", device), ("memory_budget_mb", budget_mb)) if v is not None})
    elif device is not None or budget_mb is not None or checkpoint is not None:
        raise SettingError("{device}, {memory_budget_mb} and {checkpoint} are only for GAN datasets")
    generator = make_generator(gan, checkpoint or settings.get("checkpoint"), options)
    recorded = index["generator"].get("checkpoint_sha256")
    if generator.describe()["checkpoint_sha256"] != recorded:
        raise UserError(f"the checkpoint {checkpoint or settings.get('checkpoint')} is not the one {dataset.root} was made "
                        f"with (sha256 {str(recorded)[:12]}...)")
    subject = generator.sample_subject(settings["seed"], int(key[4:]))
    mesh = extract_shape(generator, subject, resolution or DEFAULT_RESOLUTION, level)
    return encode_mesh(mesh), mesh.record, "extracted"


def write_shape(dataset, key: str, out, **options) -> dict:
    """Write subject ``key``'s shape of ``dataset`` (a Dataset or its folder) to ``out`` (.ply, .obj or .glb, by its suffix) atomically;
    ``options`` as :func:`subject_shape`. Returns the record, with how it was made and the seconds."""
    out = Path(out)
    fmt = out.suffix.lower().lstrip(".")
    if fmt not in FORMATS:
        raise UserError(f"{out}: the file name must end in .ply, .obj or .glb")
    start = time.perf_counter()
    dataset = Dataset.of(dataset)
    data, record, how = subject_shape(dataset, key, **options)
    mesh, problems = checked_mesh(data, record, f"{dataset.root}: {key}")
    if problems:
        raise DatasetError("; ".join(problems))
    if fmt != "ply":  # the PLY is copied as it is, once it has passed the same check
        data = encode_mesh(mesh, fmt)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(out, data)
    except OSError as e:
        raise UserError(f"cannot write {out}: {e.strerror}") from None
    return {**record, "how": how, "seconds": time.perf_counter() - start, "bytes": len(data), "path": str(out)}
