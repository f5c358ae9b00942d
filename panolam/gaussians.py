"""3D Gaussians: the model's output, and their export in the standard 3D Gaussian Splatting PLY layout.

Attributes are activated (the values a renderer consumes), one set of N Gaussians per object, or a
batch of B sets with a leading B on every attribute (the model's output; ``g[b]`` is one set):

* ``means``     (N, 3) world units (y up, the face looks toward +z, see :mod:`datagen.cameras`).
* ``quats``     (N, 4) rotation quaternions, wxyz, unit norm.
* ``scales``    (N, 3) standard deviations along the rotated axes, world units, > 0.
* ``opacities`` (N,)   in [0, 1].
* ``colors``    (N, 3) RGB in [0, 1].

The PLY file holds one float32 ``vertex`` element with the properties, in this order,
``x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3``:
normals are zero, opacity is stored as a logit, scales as logs, rot as wxyz and
``f_dc = (rgb - 0.5) / SH_C0`` (the degree-0 spherical-harmonic coefficient), binary little endian.
Viewers that read the reference 3DGS output (SuperSplat, antimatter15/splat, Spark) open it.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from datagen.files import atomic_write

SH_C0 = 0.28209479177387814
PLY_PROPERTIES = ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                  "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
# Opacity and scale are clamped before logit / log so that 0, 1 and 0-sized Gaussians stay finite
# on disk: an opacity of exactly 0 or 1 comes back as 1e-6 or 1 - 1e-6, a zero scale as 1e-12.
OPACITY_EPS = 1e-6
SCALE_MIN = 1e-12
SCALE_MAX = 1e30
_FIELDS = ("means", "quats", "scales", "opacities", "colors")



@dataclass
class Gaussians:
    """Activated 3D Gaussians: one set (N, ...) or a batch (B, N, ...); shapes and units in the module docstring."""

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor

    def __post_init__(self):
        lead = tuple(self.means.shape[:-1])
        expected = {"means": lead + (3,), "quats": lead + (4,), "scales": lead + (3,), "opacities": lead,
                    "colors": lead + (3,)}
        if len(lead) not in (1, 2):
            raise ValueError(f"Gaussians.means has shape {tuple(self.means.shape)}, expected (N, 3) or (B, N, 3)")
        for name, shape in expected.items():
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"Gaussians.{name} has shape {tuple(getattr(self, name).shape)}, expected {shape}")

    def __len__(self) -> int:
        """Number of Gaussians per set (N)."""
        return self.means.shape[-2]

    def __getitem__(self, b: int) -> "Gaussians":
        """Set ``b`` of a batch."""
        if self.means.dim() != 3:
            raise IndexError("indexing needs a batch of Gaussians (a leading B)")
        return Gaussians(*(getattr(self, f)[b] for f in _FIELDS))

    def to(self, *args, **kwargs) -> "Gaussians":
        """Same Gaussians with every attribute moved/cast by ``Tensor.to(*args, **kwargs)``."""
        return Gaussians(*(getattr(self, f).to(*args, **kwargs) for f in _FIELDS))

    def detach(self) -> "Gaussians":
        return Gaussians(*(getattr(self, f).detach() for f in _FIELDS))


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, OPACITY_EPS, 1.0 - OPACITY_EPS)
    return np.log(p) - np.log1p(-p)


def _unit_quats(q: np.ndarray) -> np.ndarray:
    """Normalize wxyz quaternions; a zero (or non-finite) quaternion becomes the identity."""
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    ok = np.isfinite(norm) & (norm > 0)
    identity = np.broadcast_to(np.array([1.0, 0.0, 0.0, 0.0]), q.shape)
    return np.where(ok, q / np.where(ok, norm, 1.0), identity)


def ply_vertex_table(g: Gaussians) -> np.ndarray:
    """The (N, 17) float32 table of stored values, columns in ``PLY_PROPERTIES`` order."""
    if g.means.dim() != 2:
        raise ValueError("a PLY file holds one set of Gaussians; pass g[b] of a batch")
    as64 = lambda t: t.detach().to("cpu", torch.float64).numpy()  # noqa: E731
    n = len(g)
    table = np.concatenate([
        as64(g.means),
        np.zeros((n, 3)),
        (as64(g.colors) - 0.5) / SH_C0,
        _logit(as64(g.opacities))[:, None],
        np.log(np.clip(as64(g.scales), SCALE_MIN, SCALE_MAX)),
        _unit_quats(as64(g.quats)),
    ], axis=1)
    return table.astype("<f4")


def _ply_header(n: int) -> bytes:
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    lines += [f"property float {name}" for name in PLY_PROPERTIES]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def ply_bytes(g: Gaussians) -> bytes:
    """``g`` encoded as a 3DGS PLY file."""
    return _ply_header(len(g)) + ply_vertex_table(g).tobytes()


def save_ply(path, g: Gaussians) -> Path:
    """Write ``g`` as a 3DGS PLY at ``path``, atomically (a temporary name, then a rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, ply_bytes(g))
    return path


def _read_vertices(path) -> np.ndarray:
    """The ``vertex`` element of any PLY file (ASCII or binary, either byte order, other elements and
    list properties allowed), read by plyfile, as a numpy structured array."""
    from plyfile import PlyData, PlyHeaderParseError, PlyElementParseError
    try:
        ply = PlyData.read(str(path))
    except (PlyHeaderParseError, PlyElementParseError, ValueError, EOFError) as e:
        raise ValueError(f"{path}: not a readable PLY file ({e})") from None
    if "vertex" not in ply:
        raise ValueError(f"{path}: no 'vertex' element")
    return ply["vertex"].data


def load_ply(path) -> Gaussians:
    """Read a 3DGS PLY (ours or another tool's: any PLY encoding; extra properties such as f_rest_*
    and other elements are ignored). Ours is written by :func:`ply_bytes` (a fixed layout, byte for byte).

    Returns activated float32 attributes: sigmoid opacity, exp scales, normalized quaternions and
    ``rgb = 0.5 + SH_C0 * f_dc`` clipped to [0, 1].
    """
    v = _read_vertices(path)
    missing = [p for p in PLY_PROPERTIES if p not in v.dtype.names and not p.startswith("n")]
    if missing:
        raise ValueError(f"{path}: missing PLY properties {missing}")
    col = lambda *names: np.stack([v[n].astype(np.float64) for n in names], axis=-1)  # noqa: E731
    arrays = (
        col("x", "y", "z"),
        _unit_quats(col("rot_0", "rot_1", "rot_2", "rot_3")),
        np.exp(col("scale_0", "scale_1", "scale_2")),
        0.5 * (1.0 + np.tanh(0.5 * col("opacity")[:, 0])),  # sigmoid, overflow-free
        np.clip(0.5 + SH_C0 * col("f_dc_0", "f_dc_1", "f_dc_2"), 0.0, 1.0),
    )
    return Gaussians(*(torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)) for a in arrays))
