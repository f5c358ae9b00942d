"""The head template (embedded procedural mesh or an official FLAME file) and its densification.

Units: world units (:mod:`datagen.cameras`: y up, face toward +z, head at the origin). ``Template.units_per_metre``
converts the paper's FLAME-metre lengths: ``world = metres * units_per_metre``.

Densification (paper): faces larger than an area threshold are split into 4 by their edge midpoints,
repeatedly, and every new point is a fixed barycentric combination of one template face's vertices, so
the dense points follow the (offset) template: ``densify(vertices, d)``.
"""
from __future__ import annotations

import codecs
import copyreg
import hashlib
import io
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse
import torch
from scipy.spatial import ConvexHull

from datagen.errors import UserError

ASSETS = Path(__file__).with_name("assets")
REGENERATE = "python scripts/make_head_template.py"
PAPER_VERTICES = 5023
SHIPPED_VERTICES = (1280, 5023)  # embedded sizes: the CPU 'tiny' config and the paper
FLAME_DEPTH_M = 0.222  # z extent (nose tip to back of head) of FLAME's v_template, metres

# Generation of the embedded template (world units).
RAY_CENTRE = (0.0, -0.05, -0.02)  # inside the head: every surface point is reached by a ray from here
NECK_CUT_Y = -0.46  # the neck is capped by this plane, just inside the generator's box (y >= -0.48)
RAY_STEP = 0.003  # march step before bisection; thinner protrusions than this can be missed


class TemplateError(UserError, ValueError):
    """A template file is missing, unreadable, unsafe or has the wrong contents."""


@dataclass(frozen=True, eq=False)
class Template:
    """A head mesh in world units; faces are counter-clockwise seen from outside."""

    vertices: np.ndarray  # (V, 3) float32
    faces: np.ndarray  # (F, 3) int64
    name: str  # "embedded-<V>" or "flame:<sha256[:12] of the file>"
    units_per_metre: float  # world units per FLAME metre


# ---------------------------------------------------------------------------------------------
# Embedded template

class _TypicalRng:
    """Stands in for a numpy Generator: ranges give their midpoint, normals their mean, choices the mode."""

    def uniform(self, low=0.0, high=1.0, size=None):
        return (low + high) / 2 if size is None else np.full(size, (low + high) / 2)

    def normal(self, loc=0.0, scale=1.0, size=None):
        return loc if size is None else np.full(size, float(loc))

    def choice(self, n, p=None):
        return 0 if p is None else int(np.argmax(p))


def neutral_head_params() -> dict:
    """The procedural generator's ``sample_params`` at mid-range values with the modal choices and no
    sexual dimorphism beyond the masculinity terms, then a short crop, no accessories or facial hair,
    and no shoulders: the head the template is made of."""
    from datagen.generators.procedural import sample_params

    params = sample_params(_TypicalRng(), dimorphism=0.0)
    params.update(hair_style="crop", hair_thickness=0.014, hair_length=0.0, glasses=False, cap=False,
                  facial_hair="none", torso=False)
    return params


def _head_sdf(points: np.ndarray) -> np.ndarray:
    """Signed distance (world units) of the neutral procedural head, neck capped at NECK_CUT_Y."""
    from datagen.generators.procedural import head_field

    params = neutral_head_params()
    out = np.empty(len(points))
    with torch.no_grad():
        for s in range(0, len(points), 1 << 18):
            p = torch.from_numpy(points[s:s + (1 << 18)].astype(np.float32))
            out[s:s + len(p)] = head_field(p, params, [], colour=False)[0].double().numpy()
    return np.maximum(out, NECK_CUT_Y - points[:, 1])


def _fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    y = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - y * y)
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=-1)


def _sphere_faces(dirs: np.ndarray) -> np.ndarray:
    """Triangles of the convex hull of unit vectors, counter-clockwise from outside, in canonical order."""
    faces = ConvexHull(dirs).simplices.astype(np.int64)
    a, b, c = dirs[faces[:, 0]], dirs[faces[:, 1]], dirs[faces[:, 2]]
    flip = np.einsum("ij,ij->i", np.cross(b - a, c - a), a) < 0
    faces[flip] = faces[flip][:, ::-1]
    first = faces.argmin(1)[:, None]
    faces = np.take_along_axis(faces, (first + np.arange(3)) % 3, axis=1)
    return faces[np.lexsort(faces.T[::-1])]


def generate_template(n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """A closed full-head mesh (scalp, back of head, face, ears, neck capped at NECK_CUT_Y).

    Deterministic: a Fibonacci sphere of ``n_vertices`` directions, triangulated by its convex hull,
    then each direction pushed from RAY_CENTRE to the outermost zero of the head's signed distance
    (march inward from the box edge, then bisect). The head is star-shaped around the centre once
    hidden parts (behind the ears, under the nose) are skipped, so faces keep the sphere's outward
    orientation. Returns vertices (V, 3) float32 in world units and faces (F, 3) int64, F = 2V - 4.
    """
    from datagen.generators.procedural import BOX

    if n_vertices < 4:
        raise ValueError(f"a template needs at least 4 vertices, not {n_vertices}")
    dirs = _fibonacci_sphere(n_vertices)
    faces = _sphere_faces(dirs)
    centre = np.asarray(RAY_CENTRE)
    with np.errstate(divide="ignore"):
        exit_r = np.min(np.where(dirs != 0, (np.sign(dirs) * BOX - centre) / dirs, np.inf), axis=1)
    steps = int(np.ceil(exit_r.max() / RAY_STEP))
    r = exit_r[:, None] * np.linspace(0.0, 1.0, steps + 1)  # (V, S)
    sdf = _head_sdf((centre + r[..., None] * dirs[:, None]).reshape(-1, 3)).reshape(r.shape)
    if (sdf[:, 0] >= 0).any() or (sdf[:, -1] <= 0).any():
        raise RuntimeError("template rays must start inside the head (RAY_CENTRE) and end outside it (box edge)")
    last_in = steps - np.argmax(sdf[:, ::-1] < 0, axis=1)  # outermost inside sample, < steps
    rows = np.arange(n_vertices)
    lo, hi = r[rows, last_in], r[rows, last_in + 1]
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        inside = _head_sdf(centre + mid[:, None] * dirs) < 0
        lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
    vertices = centre + (0.5 * (lo + hi))[:, None] * dirs
    return vertices.astype(np.float32), faces


def asset_path(n_vertices: int) -> Path:
    return ASSETS / f"head_template_{n_vertices}.npz"


def _units_per_metre(vertices: np.ndarray) -> float:
    """The embedded head's depth (nose tip to back of head) over FLAME's, FLAME_DEPTH_M."""
    return float(np.ptp(vertices[:, 2]) / FLAME_DEPTH_M)


_EMBEDDED: dict[int, Template] = {}


def embedded_template(n_vertices: int = PAPER_VERTICES) -> Template:
    """The shipped procedural head template with ``n_vertices`` vertices (see generate_template)."""
    if n_vertices not in _EMBEDDED:
        path = asset_path(n_vertices)
        if not path.exists():
            raise TemplateError(f"no embedded head template with {n_vertices} vertices ({path} is missing); "
                                f"create it with `{REGENERATE} --vertices {n_vertices}`")
        with np.load(path) as z:
            vertices, faces = z["vertices"].astype(np.float32), z["faces"].astype(np.int64)
        _EMBEDDED[n_vertices] = _checked(vertices, faces, f"embedded-{n_vertices}", _units_per_metre(vertices), path)
    return _EMBEDDED[n_vertices]


# ---------------------------------------------------------------------------------------------
# FLAME files

class _Stub:
    """An inert stand-in for a chumpy class: it only keeps the state it is given."""

    def __setstate__(self, state):
        self.state = state


def _numpy_safe() -> dict:
    """The (module, name) globals that numpy arrays and scalars pickle to, in numpy 1.x and 2.x spellings."""
    found = {"_reconstruct": np.empty(0).__reduce__()[0], "scalar": np.float64(0).__reduce__()[0],
             "_frombuffer": np.zeros(1).__reduce_ex__(5)[0]}
    safe = {("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype}
    for core in ("numpy.core", "numpy._core"):
        safe.update({(f"{core}.multiarray", n): found[n] for n in ("_reconstruct", "scalar")})
        safe[(f"{core}.numeric", "_frombuffer")] = found["_frombuffer"]
    return safe


# Also what Python 2 (and Python 3 at protocols < 3) writes around them: objects, sets, bytes.
_SAFE = {**_numpy_safe(), ("copy_reg", "_reconstructor"): copyreg._reconstructor,
         ("copyreg", "_reconstructor"): copyreg._reconstructor, ("_codecs", "encode"): codecs.encode,
         ("__builtin__", "object"): object, ("builtins", "object"): object,
         ("__builtin__", "set"): set, ("builtins", "set"): set}
_SPARSE = ("csc_matrix", "csr_matrix", "coo_matrix")


class _SafeUnpickler(pickle.Unpickler):
    """Rebuilds only numpy arrays, scipy.sparse matrices and inert chumpy stand-ins; refuses any other global."""

    def __init__(self, file, source: Path):
        super().__init__(file, encoding="latin1")
        self.source = source
        self.stubs: dict[str, type] = {}

    def find_class(self, module, name):
        if (module, name) in _SAFE:
            return _SAFE[(module, name)]
        if module.startswith("scipy.sparse") and name in _SPARSE:
            return getattr(scipy.sparse, name)
        if module == "chumpy" or module.startswith("chumpy."):
            return self.stubs.setdefault(f"{module}.{name}", type(name, (_Stub,), {"__module__": module}))
        raise TemplateError(f"{self.source}: refusing to load {module}.{name} from the pickle "
                            "(a FLAME model holds only numpy, scipy.sparse and chumpy data)")


def _array(value, key: str, source: Path) -> np.ndarray:
    if isinstance(value, _Stub):
        state = getattr(value, "state", None)
        if not isinstance(state, dict) or "x" not in state:
            raise TemplateError(f"{source}: {key} is a chumpy {type(value).__name__} without an 'x' array")
        value = state["x"]
    return np.asarray(value)


def _read_flame(path: Path) -> tuple[np.ndarray, np.ndarray, bytes]:
    """v_template (V, 3) float64 metres, f (F, 3) and the file's bytes."""
    try:
        data = path.read_bytes()
    except OSError as e:
        raise TemplateError(f"cannot read FLAME model {path}: {e.strerror or e}") from e
    if data[:4] == b"PK\x03\x04":
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as z:
                model = {k: z[k] for k in ("v_template", "f") if k in z.files}
        except (ValueError, OSError) as e:
            raise TemplateError(f"{path}: not a readable .npz ({e})") from e
    else:
        try:
            model = _SafeUnpickler(io.BytesIO(data), path).load()
        except TemplateError:
            raise
        except Exception as e:  # noqa: BLE001 - any malformed pickle is the file's fault
            raise TemplateError(f"{path}: not a FLAME model pickle ({type(e).__name__}: {e})") from e
    if not isinstance(model, dict) or not {"v_template", "f"} <= set(model):
        raise TemplateError(f"{path}: a FLAME model needs 'v_template' and 'f'")
    v, f = _array(model["v_template"], "v_template", path), _array(model["f"], "f", path)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3 or not np.issubdtype(v.dtype, np.floating):
        raise TemplateError(f"{path}: v_template must be (V, 3) floats (FLAME: (5023, 3)), not {v.dtype} {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise TemplateError(f"{path}: f must be (F, 3) integers (FLAME: (9976, 3)), not {f.dtype} {f.shape}")
    return v.astype(np.float64), f, data


def load_flame(path) -> Template:
    """The template of an official FLAME model (2020 chumpy pickle, 2023 plain pickle, or .npz).

    Nothing in the file is executed: unpickling rebuilds only numpy arrays, scipy.sparse matrices
    and inert stand-ins for chumpy objects. FLAME is in metres with the same axes as the world
    (y up, face toward +z); it is mapped by ``world = s * metres + t`` with ``s`` the embedded
    5023-vertex template's depth over the FLAME head's (z extent, nose tip to back of head; the
    necks differ in length, so heights are not comparable) and ``t`` putting the x and z centres of
    the bounding box and the top of the head where the embedded head has them.
    ``units_per_metre = s``.
    """
    path = Path(path)
    vertices, faces, data = _read_flame(path)
    target = embedded_template(PAPER_VERTICES).vertices.astype(np.float64)
    scale = np.ptp(target[:, 2]) / np.ptp(vertices[:, 2])

    def anchor(v):
        lo, hi = v.min(0), v.max(0)
        return np.array([(lo[0] + hi[0]) / 2, hi[1], (lo[2] + hi[2]) / 2])

    world = scale * vertices + (anchor(target) - scale * anchor(vertices))
    name = f"flame:{hashlib.sha256(data).hexdigest()[:12]}"
    return _checked(world.astype(np.float32), faces.astype(np.int64), name, float(scale), path)


def _checked(vertices, faces, name, units_per_metre, source) -> Template:
    if not np.isfinite(vertices).all():
        raise TemplateError(f"{source}: vertices are not finite")
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise TemplateError(f"{source}: face indices are outside 0..{len(vertices) - 1}")
    for a in (vertices, faces):
        a.flags.writeable = False
    return Template(vertices, faces, name, units_per_metre)


def load_template(path: str | None, n_vertices: int) -> Template:
    """The FLAME template in ``path`` when given, else the embedded template with ``n_vertices``."""
    return load_flame(path) if path else embedded_template(n_vertices)


# ---------------------------------------------------------------------------------------------
# Densification

@dataclass(frozen=True, eq=False)
class Densification:
    """Dense points as barycentric combinations of template vertices.

    Rows 0..V-1 are the template vertices (index (i, i, i), weights (1, 0, 0)); then edge points;
    then points inside faces. ``area_threshold`` is in world units^2; ``passes`` is the deepest
    subdivision used.
    """

    indices: np.ndarray  # (M, 3) int64
    weights: np.ndarray  # (M, 3) float32, rows sum to 1, >= 0
    area_threshold: float
    passes: int


class _Topology:
    """Face areas and the unique edges of a template (edge e joins edges[e]; face_edges (F, 3) -> e),
    from trimesh; edges in lexicographic order, which fixes the order of the dense points."""

    def __init__(self, t: Template):
        import trimesh
        mesh = trimesh.Trimesh(t.vertices.astype(np.float64), t.faces, process=False, validate=False)
        self.areas = mesh.area_faces
        order = np.lexsort(mesh.edges_unique.T[::-1])
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        self.edges = mesh.edges_unique[order]
        self.face_edges = rank[mesh.edges_unique_inverse].reshape(-1, 3)  # edges of face f: (v0 v1, v1 v2, v2 v0)

    def levels(self, threshold: float, max_passes: int) -> tuple[np.ndarray, np.ndarray]:
        """Subdivision level of every face (a split quarters the area) and of every edge (its finest face)."""
        quarters = 4.0 ** -np.arange(max_passes)
        face = (self.areas[:, None] * quarters > threshold).sum(1)
        edge = np.zeros(len(self.edges), dtype=np.int64)
        np.maximum.at(edge, self.face_edges.ravel(), np.repeat(face, 3))
        return face, edge

    def count(self, n_vertices: int, threshold: float, max_passes: int) -> int:
        face, edge = self.levels(threshold, max_passes)
        n_face, n_edge = 2 ** face, 2 ** edge
        return int(n_vertices + ((n_face - 1) * (n_face - 2) // 2).sum() + (n_edge - 1).sum())


def _split_points(t: Template, topo: _Topology, threshold: float, max_passes: int) -> Densification:
    """Points of the splits; each lies on exactly one vertex, edge or face interior, so none repeats."""
    face_level, edge_level = topo.levels(threshold, max_passes)
    n_v = len(t.vertices)
    ids = [np.repeat(np.arange(n_v), 3).reshape(-1, 3)]
    ws = [np.tile([1.0, 0.0, 0.0], (n_v, 1))]
    for level in range(1, max_passes + 1):
        n = 2 ** level
        e = topo.edges[edge_level == level]
        s = np.arange(1, n) / n
        ids.append(np.repeat(e[:, [0, 1, 1]], n - 1, axis=0))
        ws.append(np.tile(np.stack([1 - s, s, 0 * s], axis=1), (len(e), 1)))
    for level in range(2, max_passes + 1):
        n = 2 ** level
        f = t.faces[face_level == level]
        i, j = np.meshgrid(np.arange(1, n), np.arange(1, n), indexing="ij")
        keep = i + j < n
        grid = np.stack([i[keep], j[keep], n - i[keep] - j[keep]], axis=1) / n
        ids.append(np.repeat(f, len(grid), axis=0))
        ws.append(np.tile(grid, (len(f), 1)))
    indices, weights = np.concatenate(ids).astype(np.int64), np.concatenate(ws).astype(np.float32)
    indices.flags.writeable = weights.flags.writeable = False
    return Densification(indices, weights, float(threshold), int(face_level.max(initial=0)))


def _threshold_for(t: Template, topo: _Topology, target: int, max_passes: int) -> float:
    """The area threshold whose point count is closest to ``target`` (the count is a step function)."""
    cuts = np.concatenate([[0.0], np.unique(topo.areas[:, None] * 4.0 ** -np.arange(max_passes))])
    count = lambda k: topo.count(len(t.vertices), cuts[k], max_passes)  # noqa: E731 - nonincreasing in k
    if count(0) <= target:
        return cuts[0]
    lo, hi = 0, len(cuts) - 1  # count(hi) is V: no face exceeds the largest area
    if count(hi) >= target:
        return cuts[hi]
    while hi - lo > 1:  # count(lo) > target >= count(hi)
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if count(mid) <= target else (mid, hi)
    return cuts[lo] if count(lo) - target < target - count(hi) else cuts[hi]


_DENSE_CACHE: dict[tuple, Densification] = {}


def densification(template: Template, area_threshold: float | None = None, target_points: int | None = None,
                  max_passes: int = 4) -> Densification:
    """Split faces larger than ``area_threshold`` (world units^2; the paper's 2e-6 m^2 is
    ``2e-6 * units_per_metre**2``) into 4 by edge midpoints, up to ``max_passes`` times.

    With ``target_points`` instead, the threshold is chosen (bisection over the thresholds where the
    count changes) so that the number of points is as close as possible to it; the count is not
    padded or truncated. Results are cached per template name, geometry and arguments.
    """
    if (area_threshold is None) == (target_points is None):
        raise ValueError("give exactly one of area_threshold and target_points")
    if max_passes < 0 or (area_threshold is not None and not area_threshold > 0):
        raise ValueError("need area_threshold > 0 and max_passes >= 0")
    digest = hashlib.sha256(template.vertices.tobytes() + template.faces.tobytes()).hexdigest()
    key = (template.name, digest, area_threshold, target_points, max_passes)
    if key not in _DENSE_CACHE:
        topo = _Topology(template)
        if area_threshold is None:
            area_threshold = _threshold_for(template, topo, int(target_points), max_passes)
        _DENSE_CACHE[key] = _split_points(template, topo, area_threshold, max_passes)
    return _DENSE_CACHE[key]


def densify(values: torch.Tensor, d: Densification | torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Per-vertex values (..., V, C) -> per-point values (..., M, C) = sum_k w_k * values[..., idx_k, :].

    ``d`` is a Densification, or its indices as a tensor with ``weights`` beside it (e.g. module
    buffers that already live on the device). Differentiable in ``values``.
    """
    if isinstance(d, Densification):
        d, weights = torch.tensor(d.indices), torch.tensor(d.weights)
    idx = d.to(values.device)
    w = weights.to(values.device, values.dtype)
    return sum(values[..., idx[:, k], :] * w[:, k, None] for k in range(3))
