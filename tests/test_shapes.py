"""Subjects' shapes (``datagen/shapes.py``): the procedural mesh agrees with its renders, GAN fixtures
give closed meshes inside their box on the device they run on, and the commands that store, check,
summarize and write shapes.

Silhouette check: the stored mesh's triangles are rasterized through the dataset's own cameras
(pixel centres inside a projected triangle) and compared with the stored masks (alpha > 127).
"""
from __future__ import annotations

import copy
import json
import struct

import numpy as np
import plyfile
import pytest
import torch
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

from datagen.cameras import depth_points
from datagen.cli import main
from datagen.errors import DatasetError, UserError
from datagen.gans.checkpoint import read_checkpoint
from datagen.gans.kinds import KINDS
from datagen.generators import gan as gan_module
from datagen.pipeline import run_sample
from datagen.shapes import (
    Mesh,
    check_mesh,
    decode_mesh,
    encode_mesh,
    extract_shape,
    stored_shape,
)
from datagen.dataset import Dataset
from datagen.dataset.shards import SHAPE_FIELD, tar_path
from tests.conftest import gan_fixture, tiny_spec
from tests.simdev import on_device, simulated_device

SHAPE_RES = 96
FIXTURE_LEVEL = 3.0  # the fixtures' random decoders never reach the originals' level 10 (max 3.8 to 5.1)


@pytest.fixture(scope="module")
def shaped(tmp_path_factory):
    """Two procedural subjects, 6 views at 64 px, each with its shape on a 96^3 grid."""
    out = tmp_path_factory.mktemp("shapes") / "ds"
    run_sample(tiny_spec(out, subjects=2, views=6, resolution=64, shard_size=1, save_shape=SHAPE_RES), progress=False)
    return out


def run(argv, capsys):
    try:
        code = main(argv)
    except SystemExit as e:
        code = e.code
    out, err = capsys.readouterr()
    return code, out, err


# -- geometry ----------------------------------------------------------------------------------------

def silhouette(vertices, faces, cam2world, K, res):
    """Pixels (res, res) whose centre lies inside a triangle projected through an OpenCV camera
    (cam2world 4x4, K normalized); row-major, pixel (r, c) centred at (c + 0.5, r + 0.5)."""
    R, t = cam2world[:3, :3], cam2world[:3, 3]
    cam = (vertices - t) @ R
    uv = (cam[:, :2] / cam[:, 2:3] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]) * res - 0.5  # centres at integers
    tri = uv[faces]  # (T, 3, 2)
    lo, hi = np.floor(tri.min(1)).astype(int), np.ceil(tri.max(1)).astype(int)
    span = int((hi - lo).max()) + 1
    mask = np.zeros((res, res), dtype=bool)
    oy, ox = np.mgrid[0:span, 0:span]
    for first in range(0, len(tri), 20000):
        tr, lo_ = tri[first:first + 20000], lo[first:first + 20000]
        px = lo_[:, None, 0] + ox.reshape(1, -1)  # (T, span^2) candidate pixel centres
        py = lo_[:, None, 1] + oy.reshape(1, -1)
        edges = []
        for i in range(3):
            a, b = tr[:, i], tr[:, (i + 1) % 3]
            edges.append((b[:, None, 0] - a[:, None, 0]) * (py - a[:, None, 1])
                         - (b[:, None, 1] - a[:, None, 1]) * (px - a[:, None, 0]))
        e = np.stack(edges)
        inside = ((e >= 0).all(0) | (e <= 0).all(0)) & (px >= 0) & (px < res) & (py >= 0) & (py < res)
        mask[py[inside], px[inside]] = True
    return mask


def test_the_rasterizer_fills_a_square():
    """The check's own rasterizer: a square facing the camera covers the pixels it should."""
    K = np.array([[2.0, 0, 0.5], [0, 2.0, 0.5], [0, 0, 1]])
    c2w = np.eye(4)
    c2w[2, 3] = -2.0  # camera at z = -2 looking along +z at the square in the plane z = 0
    square = np.array([[-0.25, -0.25, 0], [0.25, -0.25, 0], [0.25, 0.25, 0], [-0.25, 0.25, 0]])
    got = silhouette(square, np.array([[0, 1, 2], [0, 2, 3]]), c2w, K, 16)
    want = np.zeros((16, 16), dtype=bool)
    want[4:12, 4:12] = True  # u = 0.5 + 2 * x / 2 in [0.25, 0.75]: pixel centres 4.5 ... 11.5
    np.testing.assert_array_equal(got, want)


def test_procedural_mesh_matches_its_renders(shaped):
    """Every stored mesh through every view against the stored masks (alpha > 127) and depth.

    The mesh is the zero level of the distance; the renderer's Laplace density (beta 0.003) makes a
    ray that grazes the surface opaque up to about 2.7 beta = 0.008 world units outside it, 0.8 px
    at 64 px, so each mask is its surface's silhouette grown by that halo (measured: IoU 0.92 with
    the bare silhouette, not one silhouette pixel outside the mask). Checked: the silhouette lies
    inside the mask; grown by one pixel it matches the mask with IoU >= 0.98 (measured 0.983 to
    0.995); the opaque pixels' depth points lie on the mesh (median distance 0.0008 to 0.0021
    world units, 90th percentile at most 0.0054: the halo again, at the silhouettes)."""
    cross = ndimage.generate_binary_structure(2, 1)
    for key in ("subj00000000", "subj00000001"):
        data, record = stored_shape(shaped, key)
        mesh = decode_mesh(data, key)
        sample = Dataset(shaped).read_subject(key)
        assert record["resolution"] == SHAPE_RES and record["level"] == 0.0
        tm = trimesh.Trimesh(mesh.vertices.astype(np.float64), mesh.faces, process=False)
        nearest = cKDTree(tm.vertices)
        for view, alpha, depth in zip(sample.metadata["views"], sample.alpha, sample.depth):
            c2w, K = np.array(view["cam2world"]), np.array(view["intrinsics"])
            sil = silhouette(tm.vertices, mesh.faces, c2w, K, 64)
            rendered = alpha > 127
            assert (sil & ~rendered).sum() <= 0.005 * sil.sum(), (key, view["name"])
            assert (sil & rendered).sum() / (sil | rendered).sum() >= 0.9  # the bare silhouette: the halo alone
            grown = ndimage.binary_dilation(sil, cross)
            iou = (grown & rendered).sum() / (grown | rendered).sum()
            assert iou >= 0.98, (key, view["name"], iou)
            rows, cols = np.nonzero(alpha > 250)
            points = depth_points(c2w, K, 64, rows, cols, depth[rows, cols])
            _, i = nearest.query(points)
            off_surface = np.abs(((points - tm.vertices[i]) * tm.vertex_normals[i]).sum(-1))
            assert np.median(off_surface) < 0.003 and np.percentile(off_surface, 90) < 0.008, (key, view["name"])


def test_procedural_mesh_is_closed_outward_and_coloured(shaped):
    data, record = stored_shape(shaped, "subj00000000")
    tm = trimesh.load(trimesh.util.wrap_as_stream(data), file_type="ply", process=False)
    assert tm.is_watertight and tm.volume > 0  # closed where the box cuts the body; normals point out
    assert np.abs(tm.vertices).max() <= record["box_half_extent"][0]
    colours = tm.visual.vertex_colors[:, :3].astype(float)
    assert colours.std(0).min() > 5  # albedo varies over the head (skin, hair, clothes)


@pytest.fixture(scope="module", params=KINDS)
def gan_heads(request):
    checkpoint = read_checkpoint(gan_fixture(request.param, ".pkl"), request.param)
    heads = gan_module.GANHeads(request.param, checkpoint, gan_module.GANConfig(device="cpu"))
    return heads, heads.sample_subject(3, 1)


def test_gan_fixture_shape_is_closed_and_inside_the_box(gan_heads):
    heads, subject = gan_heads
    mesh = extract_shape(heads, subject, 48, FIXTURE_LEVEL)
    half = heads.G.rendering_kwargs["box_warp"] / 2
    assert len(mesh.faces) > 100 and mesh.colors.shape == mesh.vertices.shape
    # The originals' trim: int(30 * 48 / 256) = 5 grid points on each side are never inside.
    assert np.abs(mesh.vertices).max() <= half - 5 * 2 * half / 47 + 1e-3
    assert trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).is_watertight
    assert check_mesh(encode_mesh(mesh), mesh.record, "x") == []
    # The colours are the decoder's at the vertices: another level moves the vertices, and the colours with them.
    other = extract_shape(heads, subject, 48, FIXTURE_LEVEL + 0.3)
    assert len(other.vertices) != len(mesh.vertices) or not np.array_equal(other.colors, mesh.colors)


def test_gan_fixture_at_the_originals_level_says_there_is_no_surface(gan_heads):
    heads, subject = gan_heads
    with pytest.raises(UserError, match="never crosses level 10 .* lower --shape-level"):
        extract_shape(heads, subject, 32)


def test_gan_shape_stays_on_the_device(monkeypatch):
    """SphereHead (the rotations are device constants) on the simulated device: no host tensor in
    device math, no host sync, two copies back (the density grid and the colours), the same mesh."""
    checkpoint = read_checkpoint(gan_fixture("spherehead", ".pkl"), "spherehead")
    monkeypatch.setattr(gan_module, "resolve_device", lambda name: torch.device(name))
    expected_heads = gan_module.GANHeads("spherehead", copy.deepcopy(checkpoint), gan_module.GANConfig(device="cpu"))
    expected = extract_shape(expected_heads, expected_heads.sample_subject(3, 1), 32, FIXTURE_LEVEL)
    with simulated_device() as (device, mode):
        heads = gan_module.GANHeads("spherehead", copy.deepcopy(checkpoint), gan_module.GANConfig(device=str(device)))
        subject = heads.sample_subject(3, 1)
        assert on_device(subject.state[1])
        before = len(mode.transfers)
        mesh = extract_shape(heads, subject, 32, FIXTURE_LEVEL)
    assert mode.syncs == [] and len(mode.transfers) - before == 2
    np.testing.assert_allclose(mesh.vertices, expected.vertices, atol=1e-5)
    np.testing.assert_array_equal(mesh.faces, expected.faces)
    assert np.abs(mesh.colors.astype(int) - expected.colors).max() <= 1


def test_non_finite_fields_are_refused(gan_heads, monkeypatch):
    heads, subject = gan_heads
    field = heads.G.field

    def broken(planes):
        query = field(planes)
        return lambda points, dirs: tuple(t * float("nan") for t in query(points, dirs))
    monkeypatch.setattr(heads.G, "field", broken)
    with pytest.raises(UserError, match="NaN or Inf"):
        extract_shape(heads, subject, 16, FIXTURE_LEVEL)


def test_check_mesh_catches_bad_shapes():
    good = Mesh(vertices=np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]], np.float32), faces=np.array([[0, 1, 2]]),
                colors=np.full((3, 3), 200, np.uint8), record={})
    record = {"vertices": 3, "faces": 1, "box_half_extent": [0.5] * 3}
    assert check_mesh(encode_mesh(good), record, "s") == []
    outside = copy.deepcopy(good)
    outside.vertices[0, 1] = 0.7
    assert "outside its box" in check_mesh(encode_mesh(outside), record, "s")[0]
    assert "record says 4" in check_mesh(encode_mesh(good), {**record, "vertices": 4}, "s")[0]
    assert "does not decode" in check_mesh(encode_mesh(good)[:150], record, "s")[0]
    empty = Mesh(vertices=good.vertices, faces=np.zeros((0, 3), np.int64), colors=good.colors, record={})
    assert any("empty" in p for p in check_mesh(encode_mesh(empty), {**record, "faces": 0}, "s"))


# -- commands ------------------------------------------------------------------------------------------

def test_save_shape_through_verify_and_info(shaped, capsys):
    code, out, _ = run(["verify", str(shaped), "--quiet"], capsys)
    assert code == 0 and "OK: 2/2 shards" in out
    code, out, _ = run(["info", str(shaped), "--json"], capsys)
    shapes = json.loads(out)["shapes"]
    assert code == 0 and shapes["resolution"] == SHAPE_RES and shapes["subjects"] == 2 and shapes["level"] == 0.0
    index = json.loads((shaped / "index.json").read_text())
    assert index["settings"]["save_shape"] == SHAPE_RES
    meta = Dataset(shaped).read_subject("subj00000001").metadata
    assert meta["shape"]["member"] == SHAPE_FIELD and meta["shape"]["faces"] > 0


def test_info_of_a_dataset_without_shapes(tiny_dataset, capsys):
    code, out, _ = run(["info", str(tiny_dataset)], capsys)
    assert code == 0 and "shapes: none" in out.splitlines()
    assert "save_shape" not in json.loads((tiny_dataset / "index.json").read_text())["settings"]


def test_verify_flags_a_dataset_whose_shapes_are_missing(tiny_dataset, tmp_path, capsys):
    """An index that promises shapes over shards without them is caught subject by subject."""
    from tests.test_dataset import copy_dataset

    ds = copy_dataset(tiny_dataset, tmp_path / "ds")
    index = json.loads((ds / "index.json").read_text())
    index["settings"]["save_shape"] = 64
    (ds / "index.json").write_text(json.dumps(index))
    code, out, _ = run(["verify", str(ds), "--quiet"], capsys)
    assert code == 1 and f"has 13 fields, expected 14 with {SHAPE_FIELD}" in out


def test_resume_keeps_the_shape_setting(shaped, capsys):
    argv = ["sample", "--out", str(shaped), "--subjects", "2", "--views", "6", "--resolution", "64",
            "--shard-size", "1", "--seed", "7", "--quiet"]
    code, _, err = run(argv + ["--resume"], capsys)  # without --save-shape: other settings
    assert code == 2 and "other settings" in err and "save_shape" in err


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".glb"])
def test_shape_command_writes_every_format(shaped, tmp_path, capsys, suffix):
    out = tmp_path / f"head{suffix}"
    code, text, _ = run(["shape", str(shaped), "--subject", "1", "--out", str(out)], capsys)
    assert code == 0 and "stored" in text
    _, record = stored_shape(shaped, "subj00000001")
    tm = trimesh.load(out, process=False, force="mesh")
    assert len(tm.faces) == record["faces"] and len(tm.vertices) == record["vertices"]
    assert tm.visual.kind == "vertex"
    if suffix == ".ply":
        ply = plyfile.PlyData.read(str(out))
        assert ply["vertex"].count == record["vertices"] and ply["face"].count == record["faces"]
        assert {"red", "green", "blue"} <= {p.name for p in ply["vertex"].properties}


def damage_face_index(ds, key, shard, index):
    """Overwrite the first face's first vertex index of ``key``'s stored PLY, in place in its shard."""
    data, record = stored_shape(ds, key)
    tar = tar_path(ds, shard)
    raw = bytearray(tar.read_bytes())
    header = data.index(b"end_header\n") + len(b"end_header\n")
    # float32 x y z + uchar r g b a per vertex; then per face a uchar count and 3 int32 indices
    at = raw.index(data) + header + record["vertices"] * 16 + 1
    raw[at:at + 4] = struct.pack("<i", index)
    tar.write_bytes(bytes(raw))
    return record


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".glb"])
def test_shape_command_refuses_a_damaged_stored_mesh(shaped, tmp_path, capsys, suffix):
    """A face index far past the vertex count is refused in every format, the stored PLY copy too."""
    from tests.test_dataset import copy_dataset

    ds = copy_dataset(shaped, tmp_path / "ds")
    record = damage_face_index(ds, "subj00000001", 1, 4_200_280)
    out = tmp_path / f"head{suffix}"
    code, _, err = run(["shape", str(ds), "--subject", "1", "--out", str(out)], capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and not out.exists(), err
    assert f"{ds}: subj00000001: " in lines[0] and f"vertex 4,200,280 of {record['vertices']:,}" in lines[0]
    code, _, _ = run(["shape", str(ds), "--subject", "0", "--out", str(out)], capsys)
    assert code == 0 and out.exists()  # the other subject's mesh is intact


def test_decode_mesh_refuses_what_no_format_can_carry():
    mesh = Mesh(vertices=np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]], np.float32), faces=np.array([[0, 1, 2]]),
                colors=np.full((3, 3), 200, np.uint8), record={})
    assert len(decode_mesh(encode_mesh(mesh), "s").faces) == 1
    negative = copy.deepcopy(mesh)
    negative.faces[0, 2] = -1
    with pytest.raises(DatasetError, match="index vertex -1 of 3"):
        decode_mesh(encode_mesh(negative), "s")
    nan = copy.deepcopy(mesh)
    nan.vertices[1, 0] = np.nan
    with pytest.raises(DatasetError, match="NaN or Inf vertices"):
        decode_mesh(encode_mesh(nan), "s")
    with pytest.raises(DatasetError, match="does not decode.*unexpected length"):
        decode_mesh(encode_mesh(mesh) + b"\0" * 13, "s")  # one face more than its header says


def test_shape_command_extracts_what_is_not_stored(tiny_dataset, tmp_path, capsys):
    """A dataset without shapes: the subject is sampled again from the index and meshed."""
    out = tmp_path / "s.ply"
    code, text, _ = run(["shape", str(tiny_dataset), "--subject", "subj00000002", "--res", "32", "--out", str(out)],
                        capsys)
    assert code == 0 and "extracted" in text and "32^3" in text
    mesh = decode_mesh(out.read_bytes(), str(out))
    assert len(mesh.faces) > 0 and np.abs(mesh.vertices).max() <= 0.48


def test_gan_dataset_with_shapes(tmp_path, capsys):
    """sample --save-shape on a GAN fixture, verify, then shape: the stored mesh, and one extracted
    again from the recorded checkpoint (whose sha256 must match)."""
    ckpt = str(gan_fixture("eg3d", ".pkl"))
    ds = tmp_path / "ds"
    argv = ["sample", "--gan", "eg3d", "--checkpoint", ckpt, "--protocol", "frontal", "--subjects", "1", "--views",
            "2", "--resolution", "32", "--out", str(ds), "--save-shape", "32", "--shape-level", "3", "--quiet"]
    code, _, err = run(argv, capsys)
    assert code == 0, err
    code, out, _ = run(["verify", str(ds), "--quiet"], capsys)
    assert code == 0 and "OK: 1/1 shards" in out
    _, record = stored_shape(ds, "subj00000000")
    assert record["level"] == 3.0 and record["trim_points"] == 3 and record["colour"] == "decoder raw RGB"
    code, out, _ = run(["shape", str(ds), "--subject", "0", "--res", "24", "--level", "3.2",
                        "--out", str(tmp_path / "a.glb"), "--device", "cpu"], capsys)
    assert code == 0 and "extracted" in out and "level 3.2" in out
    other = tmp_path / "other.pkl"
    other.write_bytes(gan_fixture("panohead", ".pkl").read_bytes())
    code, _, err = run(["shape", str(ds), "--subject", "0", "--res", "24", "--checkpoint", str(other),
                        "--out", str(tmp_path / "b.ply")], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and not (tmp_path / "b.ply").exists()


@pytest.mark.parametrize("argv, message", [
    (["shape", "{ds}", "--subject", "9", "--out", "{tmp}/a.ply"], "no subject subj00000009"),
    (["shape", "{ds}", "--subject", "me", "--out", "{tmp}/a.ply"], "--subject must be a subject number or id"),
    (["shape", "{ds}", "--subject", "1", "--out", "{tmp}/a.stl"], "must end in .ply, .obj or .glb"),
    (["shape", "{ds}", "--subject", "1", "--res", "4", "--out", "{tmp}/a.ply"], "--res must be between"),
    (["shape", "{ds}", "--subject", "1", "--device", "cpu", "--out", "{tmp}/a.ply"], "only for GAN datasets"),
    (["shape", "{tmp}/none", "--subject", "1", "--out", "{tmp}/a.ply"], "no dataset index"),
    (["sample", "--out", "{tmp}/x", "--save-shape", "8"], "--save-shape must be between"),
    (["sample", "--out", "{tmp}/x", "--save-shape", "64", "--shape-level", "5"], "only for the GAN generators"),
])
def test_shape_mistakes_get_one_line(tiny_dataset, tmp_path, capsys, argv, message):
    code, _, err = run([a.format(ds=tiny_dataset, tmp=tmp_path) for a in argv], capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and message in lines[0], err
    assert not (tmp_path / "a.ply").exists() and not (tmp_path / "a.stl").exists()
