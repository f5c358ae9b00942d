"""Head template: the embedded mesh, FLAME loading without chumpy or code execution, densification."""
import functools
import os
import pickle
import sys
import types
from fractions import Fraction

import numpy as np
import pytest
import scipy.sparse
import torch

from panolam import template as T


def edges_of(faces):
    return np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])


def face_areas(v, f):
    v = v.astype(np.float64)
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)


def point_keys(d):
    """Each dense point as its sparse combination {vertex id: weight}, canonical and hashable."""
    keys = []
    for ids, ws in zip(d.indices.tolist(), d.weights.tolist()):
        combo = {}
        for i, w in zip(ids, ws):
            if w:
                combo[i] = combo.get(i, 0.0) + w
        keys.append(tuple(sorted(combo.items())))
    return keys


# -- the embedded template ------------------------------------------------------------------------

@pytest.mark.parametrize("n", T.SHIPPED_VERTICES)
def test_generation_is_deterministic_and_matches_the_shipped_file(n):
    v1, f1 = T.generate_template(n)
    v2, f2 = T.generate_template(n)
    assert np.array_equal(v1, v2) and np.array_equal(f1, f2)
    t = T.embedded_template(n)
    assert t.name == f"embedded-{n}" and t.vertices.dtype == np.float32 and t.faces.dtype == np.int64
    assert np.array_equal(t.faces, f1)
    np.testing.assert_allclose(t.vertices, v1, atol=1e-5)  # float32 field: last bits may vary by machine


@pytest.mark.parametrize("n", [4, 97, 500])
def test_vertex_count_is_exact_and_the_mesh_is_a_closed_sphere(n):
    v, f = T.generate_template(n)
    assert v.shape == (n, 3) and f.shape == (2 * n - 4, 3)
    assert set(f.ravel().tolist()) == set(range(n))
    directed = edges_of(f)
    # Every directed edge once and its reverse once: closed, manifold and consistently oriented.
    assert len({tuple(e) for e in directed.tolist()}) == len(directed)
    assert {tuple(e) for e in directed.tolist()} == {tuple(e) for e in directed[:, ::-1].tolist()}


@pytest.mark.parametrize("n", T.SHIPPED_VERTICES)
def test_template_faces_outward_without_degenerate_faces(n):
    t = T.embedded_template(n)
    v, f = t.vertices.astype(np.float64), t.faces
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    normals = np.cross(b - a, c - a)
    assert np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6 > 0.02  # signed volume, world units^3
    away = np.einsum("ij,ij->i", normals, (a + b + c) / 3 - np.asarray(T.RAY_CENTRE)) > 0
    assert away.mean() > 0.95
    areas = face_areas(v, f)
    assert areas.min() > 1e-3 * np.median(areas)
    edge = np.linalg.norm(v[edges_of(f)[:, 0]] - v[edges_of(f)[:, 1]], axis=1)
    assert edge.min() > 1e-4


@pytest.mark.parametrize("n", T.SHIPPED_VERTICES)
def test_template_is_a_whole_head_in_world_units(n):
    t = T.embedded_template(n)
    v = t.vertices
    lo, hi = v.min(0), v.max(0)
    assert (np.abs(v) < 0.48).all()  # inside the procedural generator's box
    assert 0.18 < hi[1] < 0.3  # top of the scalp
    assert lo[1] == pytest.approx(T.NECK_CUT_Y, abs=1e-4)  # the neck, down to its cap
    assert lo[2] < -0.2 and hi[2] > 0.18  # back of the head and nose tip
    assert 0.3 < hi[0] - lo[0] < 0.45 and abs(hi[0] + lo[0]) < 0.02  # ear to ear, centred
    back, top, front = v[:, 2] < -0.1, v[:, 1] > 0.1, (v[:, 2] > 0.1) & (v[:, 1] > -0.2)
    assert min(back.mean(), top.mean(), front.mean()) > 0.1
    assert t.units_per_metre == pytest.approx((hi[2] - lo[2]) / T.FLAME_DEPTH_M)
    assert 1.5 < t.units_per_metre < 2.5


def test_missing_embedded_size_names_the_script():
    with pytest.raises(T.TemplateError, match="make_head_template.py --vertices 777"):
        T.embedded_template(777)


# -- densification ----------------------------------------------------------------------------------

@functools.lru_cache(maxsize=None)
def small_mesh():
    """An irregular closed mesh: a 42-vertex template squashed unevenly, so face areas vary a lot."""
    v, f = T.generate_template(42)
    v = v * np.array([1.0, 0.3, 2.0], dtype=np.float32)
    return T.Template(v, f, "test-small", 1.0)


def reference_split(t, threshold, max_passes):
    """The literal algorithm: split sub-faces over the threshold into 4, pass after pass."""
    points, finals = set(), []
    one = Fraction(1)
    for face, area in zip(t.faces.tolist(), face_areas(t.vertices, t.faces)):
        todo = [((one, 0, 0), (0, one, 0), (0, 0, one), 0)]
        while todo:
            a, b, c, level = todo.pop()
            sub_area = area / 4 ** level
            if sub_area > threshold and level < max_passes:
                ab, bc, ca = (tuple((x + y) / 2 for x, y in zip(p, q)) for p, q in ((a, b), (b, c), (c, a)))
                todo += [(*tri, level + 1) for tri in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))]
                continue
            finals.append(sub_area)
            for p in (a, b, c):
                points.add(tuple(sorted((i, float(w)) for i, w in zip(face, p) if w)))
    return points, np.array(finals)


@pytest.mark.parametrize("threshold_scale, passes", [(1.0, 4), (0.05, 4), (0.05, 2)])
def test_area_threshold_mode_equals_the_literal_split(threshold_scale, passes):
    t = small_mesh()
    areas = face_areas(t.vertices, t.faces)
    threshold = threshold_scale * np.median(areas)
    d = T.densification(t, area_threshold=threshold, max_passes=passes)
    expected, finals = reference_split(t, threshold, passes)
    keys = point_keys(d)
    assert len(set(keys)) == len(keys)  # no duplicate points
    assert set(keys) == expected
    assert d.passes == min(passes, int(np.ceil(np.log(areas.max() / threshold) / np.log(4))))
    if (areas.max() / 4 ** passes) <= threshold:
        assert finals.max() <= threshold  # stopped with every sub-face under the threshold
    else:
        assert finals.max() > threshold  # capped by max_passes


@pytest.mark.parametrize("n, passes", [(1280, 1), (1280, 2), (642, 3)])
def test_splitting_every_face_is_trimesh_subdivision(n, passes):
    """Below every face's area the split is plain midpoint subdivision: trimesh's, point for point."""
    import trimesh
    from scipy.spatial import cKDTree
    t = T.embedded_template(n) if n in T.SHIPPED_VERTICES else T.Template(*T.generate_template(n), "test", 1.0)
    threshold = face_areas(t.vertices, t.faces).min() / 4 ** passes / 2
    d = T.densification(t, area_threshold=threshold, max_passes=passes)
    ours = T.densify(torch.from_numpy(t.vertices.astype(np.float64))[None], d)[0].numpy()
    v, f = t.vertices.astype(np.float64), t.faces
    for _ in range(passes):
        v, f = trimesh.remesh.subdivide(v, f)
    assert len(ours) == len(v) and d.passes == passes
    distance, _ = cKDTree(v).query(ours)
    assert distance.max() < 1e-6  # float32 weights


def check_points(t, d):
    V = len(t.vertices)
    assert d.indices.dtype == np.int64 and d.weights.dtype == np.float32
    assert d.indices.min() >= 0 and d.indices.max() < V
    assert (d.weights >= 0).all() and np.array_equal(d.weights.sum(1), np.ones(len(d.weights), np.float32))
    assert np.array_equal(d.indices[:V], np.repeat(np.arange(V), 3).reshape(-1, 3))
    assert np.array_equal(d.weights[:V], np.tile(np.float32([1, 0, 0]), (V, 1)))
    verts = torch.from_numpy(t.vertices.copy())[None]
    dense = T.densify(verts, d)
    assert dense.shape == (1, len(d.indices), 3) and torch.equal(dense[0, :V], verts[0])
    keys = point_keys(d)
    assert len(set(keys)) == len(keys)


@pytest.mark.parametrize("n, target", [(5023, 10000), (5023, 20000), (1280, 5000)])
def test_target_points_are_hit_closely(n, target):
    t = T.embedded_template(n)
    d = T.densification(t, target_points=target)
    assert abs(len(d.indices) - target) / target < 0.03
    check_points(t, d)
    assert T.densification(t, target_points=target) is d  # cached
    same = T.densification(t, area_threshold=d.area_threshold)  # the threshold it found gives the same points
    assert np.array_equal(same.indices, d.indices) and np.array_equal(same.weights, d.weights)


def test_paper_threshold_on_the_paper_template():
    """2e-6 m^2 on the 5023-vertex head: about FLAME's ~94K points, every sub-face under the threshold."""
    t = T.embedded_template(5023)
    threshold = 2e-6 * t.units_per_metre ** 2
    d = T.densification(t, area_threshold=threshold)
    assert 60_000 < len(d.indices) < 130_000 and d.passes == 4
    assert face_areas(t.vertices, t.faces).max() / 4 ** d.passes <= threshold
    assert (d.weights >= 0).all() and np.allclose(d.weights.sum(1), 1)


def test_target_mode_picks_the_closest_achievable_count():
    t = small_mesh()
    areas = face_areas(t.vertices, t.faces)
    cuts = np.unique(np.concatenate([[1e-12], (areas[:, None] / 4.0 ** np.arange(3)).ravel()]))
    achievable = np.array([len(T.densification(t, area_threshold=c, max_passes=3).indices) for c in cuts])
    for target in (100, 333, 777, 1500):
        got = len(T.densification(t, target_points=target, max_passes=3).indices)
        assert got in achievable and abs(got - target) == np.abs(achievable - target).min()


def test_unreachable_targets_are_not_padded_or_truncated():
    t = small_mesh()
    assert len(T.densification(t, target_points=10).indices) == 42
    most = T.densification(t, target_points=10**6, max_passes=2)
    assert len(most.indices) == 42 + len(edges_of(t.faces)) // 2 * 3 + len(t.faces) * 3


def test_cache_tells_templates_apart():
    t = small_mesh()
    moved = T.Template(t.vertices * 2, t.faces, t.name, 1.0)  # same name, other geometry
    thr = float(np.median(face_areas(t.vertices, t.faces)))
    assert len(T.densification(moved, area_threshold=thr).indices) > len(T.densification(t, area_threshold=thr).indices)


def test_densification_arguments():
    t = small_mesh()
    for kwargs in ({}, {"area_threshold": 1e-3, "target_points": 100}, {"area_threshold": 0.0}):
        with pytest.raises(ValueError):
            T.densification(t, **kwargs)


def test_densify_gradients():
    t = small_mesh()
    d = T.densification(t, area_threshold=np.median(face_areas(t.vertices, t.faces)), max_passes=2)
    x = torch.randn(2, len(t.vertices), 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: T.densify(v, d), (x,))
    # Tensor form (module buffers) is the same map.
    idx, w = torch.from_numpy(d.indices.copy()), torch.from_numpy(d.weights.copy())
    assert torch.equal(T.densify(x, idx, w), T.densify(x, d))
    feats = torch.randn(len(t.vertices), 5)
    assert T.densify(feats, d).shape == (len(d.indices), 5)


# -- FLAME files ----------------------------------------------------------------------------------

S0, T0 = 2.0, np.array([0.01, -0.35, 0.02])  # the fake FLAME: world = S0 * metres + T0 (roughly)


def fake_flame():
    """A small head in FLAME's frame and units: the 1280 template moved to metres."""
    t = T.embedded_template(1280)
    return (t.vertices.astype(np.float64) - T0) / S0, t.faces.astype(np.uint32)


def other_arrays(v):
    return {"J_regressor": scipy.sparse.csc_matrix(np.eye(5, len(v)) / 2), "weights": np.full((len(v), 5), 0.2),
            "kintree_table": np.array([[2**32 - 1, 0, 1, 1, 1], [0, 1, 2, 3, 4]], np.uint32),
            "bs_style": "lbs", "bs_type": "lrotmin", "scale": np.float64(1.0)}


def chumpy_pickle(path, protocol):
    """A FLAME-2020-like pickle: arrays wrapped in chumpy.ch.Ch objects (state keeps 'x', as chumpy's)."""
    ch = types.ModuleType("chumpy.ch")

    class Ch:
        def __init__(self, x):
            self.x, self._dirty_vars, self._make_dense = x, {"x"}, False

    Ch.__module__, Ch.__qualname__ = "chumpy.ch", "Ch"
    ch.Ch = Ch
    sys.modules["chumpy"], sys.modules["chumpy.ch"] = types.ModuleType("chumpy"), ch
    try:
        v, f = fake_flame()
        model = {"v_template": Ch(v), "f": f, "shapedirs": Ch(np.zeros((len(v), 3, 4))),
                 "posedirs": np.zeros((len(v), 3, 36)), **other_arrays(v)}
        path.write_bytes(pickle.dumps(model, protocol=protocol))
    finally:
        del sys.modules["chumpy"], sys.modules["chumpy.ch"]
    return v, f


def check_flame(template, v, f):
    """Same mesh, mapped by one uniform scale and a translation onto the embedded head's place."""
    assert template.name.startswith("flame:") and len(template.name) == 18
    assert np.array_equal(template.faces, f.astype(np.int64))
    upm = template.units_per_metre
    shift = template.vertices - upm * v
    np.testing.assert_allclose(shift, np.broadcast_to(shift[0], shift.shape), atol=1e-5)
    assert upm == pytest.approx(S0, rel=0.03)
    target = T.embedded_template(5023).vertices
    lo, hi, tlo, thi = template.vertices.min(0), template.vertices.max(0), target.min(0), target.max(0)
    assert hi[1] == pytest.approx(thi[1], abs=1e-5)  # top of the head
    assert hi[2] - lo[2] == pytest.approx(thi[2] - tlo[2], abs=1e-5)  # depth
    np.testing.assert_allclose((lo + hi)[[0, 2]], (tlo + thi)[[0, 2]], atol=1e-5)


@pytest.mark.parametrize("protocol", [1, 2])
def test_load_flame_2020_chumpy_pickle_without_chumpy(tmp_path, protocol):
    path = tmp_path / "generic_model.pkl"
    v, f = chumpy_pickle(path, protocol)
    t = T.load_flame(path)
    assert "chumpy" not in sys.modules and "chumpy.ch" not in sys.modules
    check_flame(t, v, f)
    assert T.load_template(str(path), 1280).name == t.name


@pytest.mark.parametrize("protocol", [2, 4, 5])
def test_load_flame_2023_plain_pickle_and_npz(tmp_path, protocol):
    v, f = fake_flame()
    path = tmp_path / "flame2023.pkl"
    path.write_bytes(pickle.dumps({"v_template": v, "f": f, **other_arrays(v)}, protocol=protocol))
    check_flame(T.load_flame(path), v, f)
    npz = tmp_path / "flame.npz"
    np.savez(npz, v_template=v.astype(np.float32), f=f)
    check_flame(T.load_flame(npz), v.astype(np.float32).astype(np.float64), f)


class Shell:
    def __init__(self, call):
        self.call = call

    def __reduce__(self):
        return self.call


@pytest.mark.parametrize("call", ["system", "eval"])
def test_load_flame_refuses_code(tmp_path, call):
    marker = tmp_path / "ran"
    payload = (os.system, (f"touch {marker}",)) if call == "system" else \
        (eval, (f"open({str(marker)!r}, 'w').close()",))
    v, f = fake_flame()
    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps({"v_template": v, "f": f, "x": Shell(payload)}, protocol=2))
    with pytest.raises(T.TemplateError, match=r"evil\.pkl: refusing to load (posix\.system|__builtin__\.eval)"):
        T.load_flame(path)
    assert not marker.exists()


def test_load_flame_clear_errors(tmp_path):
    with pytest.raises(T.TemplateError, match="cannot read FLAME model .*nothere.pkl"):
        T.load_flame(tmp_path / "nothere.pkl")
    garbage = tmp_path / "garbage.pkl"
    garbage.write_bytes(b"\x00not a pickle at all")
    with pytest.raises(T.TemplateError, match="garbage.pkl: not a FLAME model pickle"):
        T.load_flame(garbage)
    v, f = fake_flame()
    cases = {"no_template.pkl": {"f": f}, "flat.pkl": {"v_template": v[:, :2], "f": f},
             "float_faces.pkl": {"v_template": v, "f": f.astype(float)},
             "out_of_range.pkl": {"v_template": v[:10], "f": f}, "list.pkl": [v, f]}
    for name, content in cases.items():
        path = tmp_path / name
        path.write_bytes(pickle.dumps(content, protocol=2))
        with pytest.raises(T.TemplateError, match=name):
            T.load_flame(path)
    npz = tmp_path / "bad.npz"
    np.savez(npz, v=v)
    with pytest.raises(T.TemplateError, match="bad.npz: a FLAME model needs 'v_template' and 'f'"):
        T.load_flame(npz)
