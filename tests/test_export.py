"""``datagen export``: the conversions, and the geometry of each format rebuilt from its files alone.

Geometry check (every format): view A's depth pixels are back-projected through A's exported camera,
projected into view B, must land on B's mask, and where B sees them (B's depth agrees) B's depth
back-projected at that spot and projected into A must return to A's pixel (median < 0.5 px).
"""
from __future__ import annotations

import json

import numpy as np
import plyfile
import pytest
import trimesh
from PIL import Image

from datagen.cameras import horizontal_fov, rays
from datagen.cli import main
from datagen.export import (
    camera_angle_x,
    colmap_pose,
    composite,
    opengl_cam2world,
    pixel_camera,
    ray_to_z_depth,
)
from datagen.pipeline import run_sample
from datagen.dataset import Dataset
from tests.conftest import tiny_spec

FLIP_YZ = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL <-> OpenCV camera axes, written out here on purpose
VISIBLE_TOLERANCE = 0.03  # world units: B's depth and the point's depth in B agree (not occluded)
SUBJECT = "subj00000000"


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """One 6-view 48 px subject, exported in every format; {format: subject folder}, and the dataset."""
    root = tmp_path_factory.mktemp("export")
    run_sample(tiny_spec(root / "ds", subjects=1, views=6, resolution=48), progress=False)
    out = {}
    for fmt in ("nerfstudio", "instant-ngp", "colmap"):
        assert main(["export", str(root / "ds"), "--format", fmt, "--out", str(root / fmt)]) == 0
        out[fmt] = root / fmt / SUBJECT
    return out, root / "ds"


# -- pure conversions --------------------------------------------------------------------------------

def test_opengl_flip_of_the_frontal_camera_is_the_identity():
    c2w = np.diag([1.0, -1.0, -1.0, 1.0])
    c2w[2, 3] = 2.7
    gl = opengl_cam2world(c2w)
    assert np.allclose(gl[:3, :3], np.eye(3)) and np.allclose(gl[:3, 3], [0, 0, 2.7])
    assert np.allclose(opengl_cam2world(gl), c2w)


def test_pixel_camera_and_angle():
    K = np.array([[4.0, 0, 0.5], [0, 4.0, 0.5], [0, 0, 1]])
    assert pixel_camera(K, 64, 32) == {"fl_x": 256.0, "fl_y": 128.0, "cx": 32.0, "cy": 16.0, "w": 64, "h": 32}
    assert camera_angle_x(K) == pytest.approx(np.radians(horizontal_fov(4.0)))


def test_colmap_pose_is_world_to_camera():
    rng = np.random.default_rng(0)
    c2w = np.eye(4)
    c2w[:3, :3] = _rotation(rng)
    c2w[:3, 3] = rng.normal(size=3)
    q, t = colmap_pose(c2w)
    assert q[0] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
    R = _quat_to_matrix(q)
    assert np.allclose(R, c2w[:3, :3].T) and np.allclose(R @ c2w[:3, 3] + t, 0)


def test_z_depth_follows_the_dataset_rays():
    K = np.array([[3.0, 0, 0.5], [0, 3.0, 0.5], [0, 0, 1]])
    _, dirs = rays(np.eye(4)[None], K[None], 8)  # camera = world: directions in camera axes
    ray_depth = np.full((8, 8), 2.5)
    assert np.allclose(ray_to_z_depth(ray_depth, K), 2.5 * dirs[0, :, 2].numpy().reshape(8, 8), atol=1e-6)
    assert ray_to_z_depth(np.zeros((8, 8)), K).max() == 0


def test_composite_removes_the_source_background():
    rgb = np.array([[[255, 255, 255], [128, 0, 128], [200, 100, 50]]], dtype=np.uint8)  # on white
    alpha = np.array([[0, 255, 128]], dtype=np.uint8)
    rgba = composite(rgb, alpha, (1.0, 1.0, 1.0), None)
    assert rgba[0, 0].tolist() == [0, 0, 0, 0] and rgba[0, 1].tolist() == [128, 0, 128, 255]
    black = composite(rgb, alpha, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    assert black[0, 0].tolist() == [0, 0, 0] and black[0, 2, 0] == round(200 - 255 * (1 - 128 / 255))


# -- readers of the exported files (nothing from datagen.export) ---------------------------------------

def _rotation(rng):
    q = rng.normal(size=4)
    return _quat_to_matrix(q / np.linalg.norm(q))


def _quat_to_matrix(q):
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _png(path):
    return np.asarray(Image.open(path))


def _opengl_views(folder, frames, image_of, depth_of, scale):
    """Per view: (OpenCV cam2world, fx, fy, cx, cy, z-depth map, alpha)."""
    return [(np.array(f["transform_matrix"]) @ FLIP_YZ, f["fl_x"], f["fl_y"], f["cx"], f["cy"],
             _png(folder / depth_of(f)) * scale, _png(folder / image_of(f))[..., 3]) for f in frames]


def read_nerfstudio(folder):
    doc = json.loads((folder / "transforms.json").read_text())
    assert doc["camera_model"] == "OPENCV" and (doc["w"], doc["h"]) == (48, 48)
    return _opengl_views(folder, doc["frames"], lambda f: f["file_path"], lambda f: f["depth_file_path"], 1e-3)


def read_instant_ngp(folder):
    docs = [json.loads((folder / f"transforms_{s}.json").read_text()) for s in ("train", "test")]
    frames = sorted(docs[0]["frames"] + docs[1]["frames"], key=lambda f: f["file_path"])
    return _opengl_views(folder, frames, lambda f: f["file_path"] + ".png", lambda f: f["depth_path"],
                         docs[0]["integer_depth_scale"])


def read_colmap(folder, dataset):
    """COLMAP cameras and images; depth from the dataset (COLMAP's sparse text has no depth field)."""
    sparse = folder / "sparse" / "0"
    cams = {int(p[0]): [float(v) for v in p[4:8]] for p in _rows(sparse / "cameras.txt")}
    sample = Dataset(dataset).read_subject(SUBJECT)
    views = []
    for head in _rows(sparse / "images.txt")[::2]:
        R, t = _quat_to_matrix([float(v) for v in head[1:5]]), np.array([float(v) for v in head[5:8]])
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = R.T, -R.T @ t
        fx, fy, cx, cy = cams[int(head[8])]
        i = int(head[9][1:3])
        u, v = np.meshgrid(np.arange(48) + 0.5, np.arange(48) + 0.5)
        z = sample.depth[i] / np.sqrt(((u - cx) / fx) ** 2 + ((v - cy) / fy) ** 2 + 1)
        views.append((c2w, fx, fy, cx, cy, z, _png(folder / "images" / head[9])[..., 3]))
    return views


def _rows(path):
    lines = [line for line in path.read_text().splitlines() if not line.startswith("#")]
    return [line.split() for line in lines]


# -- geometry ---------------------------------------------------------------------------------------

def _lift(view, rows, cols, z):
    c2w, fx, fy, cx, cy = view[:5]
    cam = np.stack([(cols + 0.5 - cx) / fx * z, (rows + 0.5 - cy) / fy * z, z], -1)
    return cam @ c2w[:3, :3].T + c2w[:3, 3]


def _project(view, points):
    c2w, fx, fy, cx, cy = view[:5]
    cam = (points - c2w[:3, 3]) @ c2w[:3, :3]
    return np.stack([fx * cam[:, 0] / cam[:, 2] + cx, fy * cam[:, 1] / cam[:, 2] + cy], -1), cam[:, 2]


def _bilinear(image, xy):
    """Bilinear samples at continuous pixel coordinates (centres at +0.5); NaN where a neighbour is 0."""
    x, y = xy[:, 0] - 0.5, xy[:, 1] - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    h, w = image.shape
    inside = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < w) & (y0 + 1 < h)
    out = np.full(len(xy), np.nan)
    x0, y0, fx, fy = x0[inside], y0[inside], (x - np.floor(x))[inside], (y - np.floor(y))[inside]
    corners = np.stack([image[y0, x0], image[y0, x0 + 1], image[y0 + 1, x0], image[y0 + 1, x0 + 1]])
    value = (corners[0] * (1 - fx) * (1 - fy) + corners[1] * fx * (1 - fy) + corners[2] * (1 - fx) * fy
             + corners[3] * fx * fy)
    out[inside] = np.where((corners > 0).all(0), value, np.nan)
    return out


def reprojection(views, a, b):
    """(fraction of A's opaque points inside B's frame that land on B's mask, round-trip errors in px)."""
    A, B = views[a], views[b]
    rows, cols = np.nonzero((A[6] == 255) & (A[5] > 0))
    points = _lift(A, rows, cols, A[5][rows, cols])
    xy, z = _project(B, points)
    h, w = B[6].shape
    inside = (xy[:, 0] >= 0) & (xy[:, 0] < w) & (xy[:, 1] >= 0) & (xy[:, 1] < h) & (z > 0)
    pix = np.floor(xy[inside]).astype(int)
    on_mask = float(np.mean(B[6][pix[:, 1], pix[:, 0]] > 0)) if len(pix) else 0.0
    z_b = _bilinear(B[5], xy)
    seen = np.abs(z_b - z) < VISIBLE_TOLERANCE
    back = _lift(B, xy[seen, 1] - 0.5, xy[seen, 0] - 0.5, z_b[seen])
    xy_a, _ = _project(A, back)
    return on_mask, np.hypot(xy_a[:, 0] - cols[seen] - 0.5, xy_a[:, 1] - rows[seen] - 0.5)


def check_geometry(views):
    """Every pair of neighbouring views, both ways; returns the overall median error in px."""
    errors = []
    for a in range(len(views)):
        for b in ((a + 1) % len(views), (a - 1) % len(views)):
            on_mask, err = reprojection(views, a, b)
            assert on_mask > 0.97, (a, b, on_mask)
            assert len(err) > 50, (a, b, len(err))
            errors.append(err)
    median = float(np.median(np.concatenate(errors)))
    assert median < 0.5
    return median


def test_nerfstudio_geometry(exported):
    folders, _ = exported
    check_geometry(read_nerfstudio(folders["nerfstudio"]))


def test_instant_ngp_geometry_and_the_3dgs_fov_policy(exported):
    folders, _ = exported
    folder = folders["instant-ngp"]
    views = read_instant_ngp(folder)
    check_geometry(views)
    train, test = (json.loads((folder / f"transforms_{s}.json").read_text()) for s in ("train", "test"))
    assert [f["file_path"] for f in test["frames"]] == ["images/v00"] and len(train["frames"]) == 5
    frames = sorted(train["frames"] + test["frames"], key=lambda f: f["file_path"])
    angles = [f["camera_angle_x"] for f in frames]
    assert train["camera_angle_x"] == test["camera_angle_x"] == pytest.approx(np.median(angles))
    for f in frames:  # the per-frame angle and focal agree
        assert f["fl_x"] == pytest.approx(f["w"] / 2 / np.tan(f["camera_angle_x"] / 2))
    # What 3DGS does: one focal from the file's camera_angle_x, principal point at the centre.
    # The largest shift of a mask pixel that this causes is the figure export.json reports.
    shifts = []
    for (c2w, fx, fy, cx, cy, z, alpha) in views:
        f3dgs = 48 / 2 / np.tan(train["camera_angle_x"] / 2)
        rows, cols = np.nonzero(alpha > 127)
        shifts.append(np.hypot(cols + 0.5 - cx, rows + 0.5 - cy).max() * abs(f3dgs / fx - 1))
    report = json.loads((folder / "export.json").read_text())
    assert report["file_fov_max_px_error"] == pytest.approx(max(shifts)) and max(shifts) > 0


def assert_points_on_masks(points, views):
    """Depth points land on every view's mask (where they fall inside its frame)."""
    assert len(points) > 500
    for view in views:
        xy, z = _project(view, points)
        pix = np.floor(xy).astype(int)
        inside = (pix >= 0).all(1) & (pix < 48).all(1)  # the shoulders leave the frame
        assert (z > 0).all() and inside.mean() > 0.8
        assert np.mean(view[6][pix[inside, 1], pix[inside, 0]] > 0) > 0.97


def test_colmap_geometry_and_points(exported):
    folders, dataset = exported
    folder = folders["colmap"]
    views = read_colmap(folder, dataset)
    check_geometry(views)
    assert_points_on_masks(np.array([[float(v) for v in p[1:4]] for p in _rows(folder / "sparse" / "0" / "points3D.txt")]),
                           views)


def test_instant_ngp_points_read_back_with_plyfile_and_trimesh(exported):
    folders, _ = exported
    path = folders["instant-ngp"] / "points3d.ply"
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    assert {"x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"} <= set(vertex.data.dtype.names)  # 3DGS's fetchPly
    points = np.stack([vertex["x"], vertex["y"], vertex["z"]], -1).astype(np.float64)
    assert np.allclose(trimesh.load(str(path)).vertices, points)
    assert_points_on_masks(points, read_instant_ngp(folders["instant-ngp"]))


def test_colmap_reads_back_with_pycolmap(exported):
    pycolmap = pytest.importorskip("pycolmap")
    folders, _ = exported
    rec = pycolmap.Reconstruction()
    rec.read_text(str(folders["colmap"] / "sparse" / "0"))
    assert rec.num_images() == 6 and rec.num_points3D() > 500
    rec.update_point_3d_errors()  # each point against its observation in images.txt
    assert rec.compute_mean_reprojection_error() < 1e-3


def test_a_wrong_axis_convention_fails_the_geometry_check(exported):
    folders, _ = exported
    views = [(c2w @ FLIP_YZ, *rest) for c2w, *rest in read_nerfstudio(folders["nerfstudio"])]  # OpenGL read as OpenCV
    with pytest.raises(AssertionError):
        check_geometry(views)


def test_background_and_subject_selection(exported, tmp_path, capsys):
    _, dataset = exported
    assert main(["export", str(dataset), "--format", "nerfstudio", "--subject", "0", "--background", "white",
                 "--out", str(tmp_path)]) == 0
    image = _png(tmp_path / SUBJECT / "images" / "v00.png")
    assert image.shape == (48, 48, 3) and image[0, 0].tolist() == [255, 255, 255]
    assert sorted(p.name for p in tmp_path.iterdir()) == [SUBJECT]  # no temporary folder left
    assert main(["export", str(dataset), "--format", "colmap", "--subject", "5", "--out", str(tmp_path)]) == 2
    assert "no subject subj00000005" in capsys.readouterr().err


def test_a_failed_export_leaves_the_earlier_one(exported, tmp_path, monkeypatch, capsys):
    from datagen import export

    _, dataset = exported
    args = ["export", str(dataset), "--format", "colmap", "--out", str(tmp_path)]
    assert main(args) == 0
    before = (tmp_path / SUBJECT / "sparse" / "0" / "images.txt").read_bytes()
    calls = []

    def full_disk(path, data):
        calls.append(path)
        if len(calls) > 3:
            raise OSError(28, "No space left on device", str(path))
        return real(path, data)

    real = export.atomic_write
    monkeypatch.setattr(export, "atomic_write", full_disk)
    assert main(args + ["--background", "black"]) == 2
    assert "disk full" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == [SUBJECT]  # nothing temporary left
    assert (tmp_path / SUBJECT / "sparse" / "0" / "images.txt").read_bytes() == before
    assert _png(tmp_path / SUBJECT / "images" / "v00.png").shape[-1] == 4  # still the first (RGBA) export


def test_every_subject_is_checked_before_anything_is_written(tiny_dataset, tmp_path, capsys):
    """A missing id, or a subject of an incomplete shard, after a good one: nothing is written."""
    from datagen.dataset.shards import sidecar_path
    from tests.test_dataset import copy_dataset

    out = tmp_path / "out"
    assert main(["export", str(tiny_dataset), "--format", "colmap", "--subject", "0", "99", "--out", str(out)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "no subject subj00000099" in lines[0] and "nothing was exported" in lines[0]
    assert not out.exists()
    ds = copy_dataset(tiny_dataset, tmp_path / "ds")
    sidecar_path(ds, 1).unlink()  # shard 1 (subject 2) is no longer complete
    assert main(["export", str(ds), "--format", "nerfstudio", "--subject", "0", "1", "2", "--out", str(out)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "shard-000001.tar: the shard holding subj00000002 is not complete" in lines[0]
    assert not out.exists()
    assert main(["export", str(ds), "--format", "nerfstudio", "--subject", "1", "0", "1", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["subj00000000", "subj00000001"]
