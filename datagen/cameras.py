"""Cameras: the one home of the project's camera conventions.

World: y up, the face looks toward +z, the head sits at the origin (about 1 unit tall).
Extrinsics: OpenCV cam2world 4x4 (camera +x right, +y down, +z forward), float64.
Intrinsics: normalized by image size, ``[[f, 0, 0.5], [0, f, 0.5], [0, 0, 1]]``; pixel K is that
times the resolution. FOV follows EG3D's convention ``f = 1 / (tan(fov / 2) * 1.414)`` (18.837 deg
gives f = 4.2634; EG3D's scripts hard-code 4.2647).

Angles: ``yaw`` in degrees, 0 = frontal camera on +z, 90 = camera on +x, 180 = back of the head.
``pitch`` in degrees is the camera's elevation above the horizontal plane (positive = camera above
the head, looking down). Cameras sit on a sphere of the given radius around the origin and look at
a pivot: EG3D (0, 0, 0.2), PanoHead/SphereHead (0, 0, 0). docs/conventions.md collects these.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import torch

EG3D_FOCAL_SCALE = 1.414
EG3D_FOCAL = 4.2647  # the focal EG3D's scripts hard-code for FFHQ (normalized units)
EG3D_FOV_DEG = 18.837
EG3D_RADIUS = 2.7
EG3D_PIVOT = (0.0, 0.0, 0.2)
HEAD360_PIVOT = (0.0, 0.0, 0.0)
# EG3D renders rays from 2.25 to 3.3 at radius 2.7: the range moves with the radius.
RAY_START_BEFORE_ORIGIN = 0.45
RAY_END_BEYOND_ORIGIN = 0.6


def fov_to_focal(fov_deg):
    """EG3D's FOV (degrees) -> normalized focal length."""
    return 1.0 / (np.tan(np.radians(fov_deg) / 2.0) * EG3D_FOCAL_SCALE)


def focal_to_fov(focal):
    """Normalized focal length -> EG3D's FOV in degrees (inverse of :func:`fov_to_focal`)."""
    return np.degrees(2.0 * np.arctan(1.0 / (np.asarray(focal, dtype=np.float64) * EG3D_FOCAL_SCALE)))


def horizontal_fov(focal):
    """The true horizontal FOV (degrees) of a square image with normalized focal ``focal``."""
    return np.degrees(2.0 * np.arctan(0.5 / np.asarray(focal, dtype=np.float64)))


def intrinsics(focal) -> np.ndarray:
    """Normalized 3x3 intrinsics for one focal, or (N, 3, 3) for an array of focals."""
    f = np.asarray(focal, dtype=np.float64)
    K = np.zeros(f.shape + (3, 3))
    K[..., 0, 0] = f
    K[..., 1, 1] = f
    K[..., 0, 2] = 0.5
    K[..., 1, 2] = 0.5
    K[..., 2, 2] = 1.0
    return K


def pixel_intrinsics(K_norm, width: int, height: int):
    """Normalized intrinsics -> pixel intrinsics (works on numpy arrays and torch tensors)."""
    scale = K_norm.new_tensor([width, height, 1.0]) if _is_tensor(K_norm) else np.array([width, height, 1.0])
    return K_norm * scale[..., :, None]


def camera_directions(K_norm, resolution: int, rows, cols) -> np.ndarray:
    """Camera-space ray directions (N, 3) with z = 1 through the centres of pixels (rows, cols) of a
    square ``resolution`` px image: ((col + 0.5) / R, (row + 0.5) / R) in normalized coordinates,
    OpenCV axes, normalized intrinsics with skew (the convention of :func:`rays`)."""
    u, v = (np.asarray(cols) + 0.5) / resolution, (np.asarray(rows) + 0.5) / resolution
    fx, fy, cx, cy, sk = K_norm[0, 0], K_norm[1, 1], K_norm[0, 2], K_norm[1, 2], K_norm[0, 1]
    x = (u - cx + cy * sk / fy - sk * v / fy) / fx
    y = (v - cy) / fy
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def depth_points(cam2world: np.ndarray, K_norm: np.ndarray, resolution: int, rows, cols, depth) -> np.ndarray:
    """World points (N, 3) at pixels (rows, cols) of a view whose ``depth`` (N,) is the distance
    along the unit ray from the camera centre (the datasets' depth)."""
    d = camera_directions(K_norm, resolution, rows, cols) @ cam2world[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return cam2world[:3, 3] + np.asarray(depth)[..., None] * d


def angle_between(a_deg, b_deg=0.0):
    """The smaller angle between directions ``a_deg`` and ``b_deg`` (degrees, any turns), in [0, 180]."""
    return np.abs((np.asarray(a_deg, dtype=np.float64) - b_deg + 180.0) % 360.0 - 180.0)


def camera_position(yaw_deg, pitch_deg, radius) -> np.ndarray:
    """Camera centres (..., 3) on a sphere around the origin, from yaw/pitch in degrees."""
    yaw = np.radians(np.asarray(yaw_deg, dtype=np.float64))
    pitch = np.radians(np.asarray(pitch_deg, dtype=np.float64))
    r = np.asarray(radius, dtype=np.float64)
    return np.stack(
        [r * np.cos(pitch) * np.sin(yaw), r * np.sin(pitch), r * np.cos(pitch) * np.cos(yaw)], axis=-1
    )


def look_at(position, target=(0.0, 0.0, 0.0)) -> np.ndarray:
    """OpenCV cam2world (..., 4, 4) for cameras at ``position`` looking at ``target``, world y up.

    Pole-safe: when the viewing direction is (anti)parallel to the world up axis, the camera's
    right axis is taken as world +x, continuing the frontal orientation.
    """
    position = np.asarray(position, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - position
    forward = forward / np.maximum(np.linalg.norm(forward, axis=-1, keepdims=True), 1e-12)
    up = np.broadcast_to(np.array([0.0, 1.0, 0.0]), forward.shape)
    right = np.cross(forward, up)
    norm = np.linalg.norm(right, axis=-1, keepdims=True)
    degenerate = norm < 1e-6
    # At a pole forward = (0, +-1, 0); crossing with (0, 0, forward_y) gives +x.
    pole_up = np.zeros_like(forward)
    pole_up[..., 2] = np.sign(forward[..., 1]) + (forward[..., 1] == 0)
    right = np.where(degenerate, np.cross(forward, pole_up), right)
    right = right / np.maximum(np.linalg.norm(right, axis=-1, keepdims=True), 1e-12)
    down = np.cross(forward, right)
    c2w = np.zeros(forward.shape[:-1] + (4, 4))
    c2w[..., :3, 0] = right
    c2w[..., :3, 1] = down
    c2w[..., :3, 2] = forward
    c2w[..., :3, 3] = position
    c2w[..., 3, 3] = 1.0
    return c2w


def eg3d_lookat_pose(h, v, radius=EG3D_RADIUS, pivot=EG3D_PIVOT) -> np.ndarray:
    """EG3D's ``LookAtPoseSampler.sample(h, v, pivot, radius)`` without jitter (h, v in radians).

    EG3D parameterises elevation through ``phi = arccos(1 - 2 v / pi)``; h = v = pi/2 is frontal.
    """
    v = np.clip(np.asarray(v, dtype=np.float64), 1e-5, math.pi - 1e-5)
    h = np.asarray(h, dtype=np.float64)
    phi = np.arccos(1.0 - 2.0 * v / math.pi)
    pos = radius * np.stack(
        [np.sin(phi) * np.cos(math.pi - h), np.cos(phi), np.sin(phi) * np.sin(math.pi - h)], axis=-1
    )
    return look_at(pos, pivot)


def conditioning_vector(cam2world, K_norm) -> np.ndarray:
    """GAN conditioning c (..., 25): cam2world row-major ++ normalized K row-major."""
    cam2world = np.asarray(cam2world, dtype=np.float64)
    K_norm = np.asarray(K_norm, dtype=np.float64)
    lead = cam2world.shape[:-2]
    return np.concatenate([cam2world.reshape(lead + (16,)), K_norm.reshape(lead + (9,))], axis=-1)


def _is_tensor(x) -> bool:
    """A torch tensor (subclasses too), without importing torch for numpy callers (command-line
    help stays fast)."""
    return any(c.__module__.split(".")[0] == "torch" for c in type(x).__mro__)


def ray_range(radius):
    """EG3D's ray range (near, far) as distances along the ray, moved with the camera radius.

    ``radius``: floats or arrays (float64 numpy out), or a tensor (same dtype and device out).
    """
    r = radius if _is_tensor(radius) else np.asarray(radius, dtype=np.float64)
    return r - RAY_START_BEFORE_ORIGIN, r + RAY_END_BEYOND_ORIGIN


def rays(cam2world: torch.Tensor, K_norm: torch.Tensor, resolution: int):
    """Ray origins and unit directions (V, R*R, 3) through pixel centres, row-major pixels.

    Pixel (row, col) has normalized coordinates u = col/R + 0.5/R, v = row/R + 0.5/R. The
    arithmetic follows EG3D's ray sampler operation by operation (lift to camera space, transform
    the point with the full cam2world, subtract the centre, normalize), so GAN renders reproduce
    the originals to float32 rounding. Computed on the device of ``cam2world`` (arrays: the CPU).
    """
    import torch

    cam2world = torch.as_tensor(cam2world, dtype=torch.float32)
    K_norm = torch.as_tensor(K_norm, dtype=torch.float32, device=cam2world.device)
    V, M = cam2world.shape[0], resolution ** 2
    idx = torch.arange(resolution, dtype=torch.float32, device=cam2world.device)
    uv = torch.stack(torch.meshgrid(idx, idx, indexing="ij")) * (1.0 / resolution) + (0.5 / resolution)
    uv = uv.flip(0).reshape(2, -1).transpose(1, 0).unsqueeze(0).repeat(V, 1, 1)
    x_cam, y_cam = uv[:, :, 0], uv[:, :, 1]
    z_cam = torch.ones((V, M), device=cam2world.device)
    fx, fy = K_norm[:, 0, 0, None], K_norm[:, 1, 1, None]
    cx, cy, sk = K_norm[:, 0, 2, None], K_norm[:, 1, 2, None], K_norm[:, 0, 1, None]
    x_lift = (x_cam - cx + cy * sk / fy - sk * y_cam / fy) / fx * z_cam
    y_lift = (y_cam - cy) / fy * z_cam
    cam_points = torch.stack((x_lift, y_lift, z_cam, torch.ones_like(z_cam)), dim=-1)
    world = torch.bmm(cam2world, cam_points.permute(0, 2, 1)).permute(0, 2, 1)[:, :, :3]
    centre = cam2world[:, :3, 3]
    dirs = torch.nn.functional.normalize(world - centre[:, None, :], dim=2)
    origins = centre.unsqueeze(1).repeat(1, M, 1)
    return origins, dirs


# --------------------------------------------------------------------------------------------
# Sampling protocols (paper appendix)

PROTOCOLS = ("frontal", "360")
VIEWS_PER_SUBJECT = 32
RADIUS_MEAN, RADIUS_STD = 2.7, 0.1
FOV_MEAN, FOV_STD = 18.83, 1.0
FRONTAL_YAW_DEG, FRONTAL_PITCH_DEG = 36.0, 26.0
EQUATORIAL_VIEWS = 8
RANDOM_PITCH_DEG = 26.0  # pitch range of the random 360 views (the paper gives none; frontal's is used)
CLIP_SIGMAS = 4.0  # radius and FOV draws are clipped to +-4 sigma so no draw is absurd


@dataclass(frozen=True)
class ViewSet:
    """The cameras of one subject. Angles in degrees; cam2world (V,4,4); K normalized (V,3,3)."""

    protocol: str
    yaw: np.ndarray
    pitch: np.ndarray
    radius: np.ndarray
    fov: np.ndarray
    pivot: tuple

    @property
    def focal(self) -> np.ndarray:
        return fov_to_focal(self.fov)

    @property
    def K(self) -> np.ndarray:
        return intrinsics(self.focal)

    @property
    def cam2world(self) -> np.ndarray:
        return look_at(camera_position(self.yaw, self.pitch, self.radius), self.pivot)

    def __len__(self) -> int:
        return len(self.yaw)

    def subset(self, index) -> "ViewSet":
        index = np.atleast_1d(index)
        return ViewSet(self.protocol, self.yaw[index], self.pitch[index], self.radius[index],
                       self.fov[index], self.pivot)

    def to_records(self) -> list[dict]:
        """Per-view JSON-ready camera records."""
        c2w, K = self.cam2world, self.K
        return [
            {
                "yaw_deg": float(self.yaw[i]),
                "pitch_deg": float(self.pitch[i]),
                "radius": float(self.radius[i]),
                "fov_deg": float(self.fov[i]),
                "cam2world": c2w[i].tolist(),
                "intrinsics": K[i].tolist(),
            }
            for i in range(len(self))
        ]

    @classmethod
    def from_records(cls, records: list[dict], protocol: str, pivot) -> "ViewSet":
        col = lambda k: np.array([r[k] for r in records], dtype=np.float64)  # noqa: E731
        return cls(protocol, col("yaw_deg"), col("pitch_deg"), col("radius"), col("fov_deg"), tuple(pivot))


def protocol_pivot(protocol: str) -> tuple:
    if protocol not in PROTOCOLS:
        raise ValueError(f"unknown protocol {protocol!r}; choose one of {', '.join(PROTOCOLS)}")
    return EG3D_PIVOT if protocol == "frontal" else HEAD360_PIVOT


def _clipped_normal(rng: np.random.Generator, mean: float, std: float, n: int) -> np.ndarray:
    return np.clip(rng.normal(mean, std, n), mean - CLIP_SIGMAS * std, mean + CLIP_SIGMAS * std)


def sample_views(protocol: str, rng: np.random.Generator, n_views: int = VIEWS_PER_SUBJECT) -> ViewSet:
    """Draw one subject's cameras for ``protocol`` ('frontal' or '360') from ``rng``.

    frontal: yaw ~ U(-36, 36), pitch ~ U(-26, 26). 360: 8 equatorial views at yaw 0, 45, ..., 315
    (pitch 0) then random views with yaw ~ U(0, 360), pitch ~ U(-26, 26). Both: radius ~ N(2.7, 0.1),
    FOV ~ N(18.83, 1) deg, clipped to +-4 sigma.
    """
    pivot = protocol_pivot(protocol)
    if n_views < 1:
        raise ValueError("n_views must be >= 1")
    if protocol == "frontal":
        yaw = rng.uniform(-FRONTAL_YAW_DEG, FRONTAL_YAW_DEG, n_views)
        pitch = rng.uniform(-FRONTAL_PITCH_DEG, FRONTAL_PITCH_DEG, n_views)
    else:
        n_eq = min(EQUATORIAL_VIEWS, n_views)
        n_rand = n_views - n_eq
        yaw = np.concatenate([np.arange(n_eq) * (360.0 / EQUATORIAL_VIEWS), rng.uniform(0.0, 360.0, n_rand)])
        pitch = np.concatenate([np.zeros(n_eq), rng.uniform(-RANDOM_PITCH_DEG, RANDOM_PITCH_DEG, n_rand)])
    radius = _clipped_normal(rng, RADIUS_MEAN, RADIUS_STD, n_views)
    fov = _clipped_normal(rng, FOV_MEAN, FOV_STD, n_views)
    return ViewSet(protocol, yaw, pitch, radius, fov, pivot)


def named_views(names, radius=RADIUS_MEAN, fov=FOV_MEAN, pivot=HEAD360_PIVOT) -> ViewSet:
    """Fixed views by name ('front', 'left', 'right', 'back', 'top', 'bottom'), e.g. for evaluation.

    'left' is the subject's left side (camera on +x).
    """
    table = {"front": (0, 0), "left": (90, 0), "back": (180, 0), "right": (270, 0), "top": (0, 90), "bottom": (0, -90)}
    yaw, pitch = zip(*(table[n] for n in names))
    n = len(names)
    return ViewSet("named", np.array(yaw, float), np.array(pitch, float), np.full(n, float(radius)),
                   np.full(n, float(fov)), tuple(pivot))
