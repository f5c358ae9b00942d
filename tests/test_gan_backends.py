"""GAN checkpoints: refusing bad files, and writing datasets through `datagen sample`."""
import os
import pickle

import numpy as np
import pytest
import torch

from datagen.cameras import named_views
from datagen.gans.checkpoint import CheckpointError, read_checkpoint
from datagen.generators import make_generator
from datagen.pipeline import run_sample
from datagen.dataset import Dataset
from datagen.verify import verify_dataset
from tests.conftest import all_files, gan_fixture, load_stub, repickle, tiny_spec


# -- bad input ------------------------------------------------------------------------------------------

def test_round_trip_of_the_test_pickler(persistence_module, tmp_path):
    g = load_stub(gan_fixture("eg3d", ".pkl"))
    path = tmp_path / "again.pkl"
    path.write_bytes(pickle.dumps({"G_ema": repickle(g, persistence_module._reconstruct_persistent_obj)}))
    assert read_checkpoint(path, "eg3d").kind == "eg3d"


def test_mismatched_shapes_are_named(persistence_module, tmp_path):
    g = load_stub(gan_fixture("eg3d", ".pkl"))
    dec = g.state["_modules"]["decoder"].state["_modules"]["net"].state["_modules"]["0"]
    dec.state["_parameters"]["weight"] = torch.nn.Parameter(torch.zeros(64, 31), requires_grad=False)
    path = tmp_path / "bad-shape.pkl"
    path.write_bytes(pickle.dumps({"G_ema": repickle(g, persistence_module._reconstruct_persistent_obj)}))
    with pytest.raises(CheckpointError, match=r"bad-shape.pkl: shape mismatch for decoder.net.0.weight"):
        read_checkpoint(path, "eg3d")


def test_unexpected_globals_are_refused_not_run(tmp_path):
    marker = tmp_path / "ran"

    class Evil:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps({"G_ema": Evil()}))
    with pytest.raises(CheckpointError, match=r"evil.pkl: refused to load: unexpected global (posix|os)\.system"):
        read_checkpoint(path, "eg3d")
    assert not marker.exists()


def test_truncated_checkpoint(tmp_path):
    data = gan_fixture("panohead", ".pkl").read_bytes()
    path = tmp_path / "cut.pkl"
    path.write_bytes(data[: len(data) // 3])
    with pytest.raises(CheckpointError, match=r"cut.pkl: not a readable generator checkpoint"):
        read_checkpoint(path, "panohead")


def test_non_generator_pickle(tmp_path):
    path = tmp_path / "dict.pkl"
    path.write_bytes(pickle.dumps({"weights": [1, 2, 3]}))
    with pytest.raises(CheckpointError, match=r"dict.pkl: no G_ema generator"):
        read_checkpoint(path)


@pytest.mark.parametrize("model, asked", [("eg3d", "spherehead"), ("spherehead", "panohead"), ("panohead", "eg3d")])
def test_checkpoint_for_another_generator(model, asked):
    with pytest.raises(CheckpointError, match=f"this is a {model} checkpoint, not {asked}"):
        read_checkpoint(gan_fixture(model, ".pkl"), asked)


def test_missing_checkpoint_says_where_it_comes_from(tmp_path):
    with pytest.raises(CheckpointError, match="not found.*github.com/lhyfst/SphereHead"):
        read_checkpoint(tmp_path / "nope.pkl", "spherehead")


# -- sampling datasets ----------------------------------------------------------------------------------

@pytest.mark.parametrize("model, protocol", [("eg3d", "frontal"), ("panohead", "360"), ("spherehead", "360")])
def test_gan_dataset_is_valid_and_reproducible(model, protocol, tmp_path):
    ckpt = str(gan_fixture(model, ".pkl"))
    spec = tiny_spec(tmp_path / "a", gan=model, checkpoint=ckpt, protocol=protocol, subjects=2, views=3,
                     resolution=64, generator_options={"save_planes": 16})
    run_sample(spec, progress=False)
    report = verify_dataset(spec.out)
    assert report["problems"] == [] and report["subjects"] == 2
    s = Dataset(spec.out).read_subject("subj00000001")
    meta = s.metadata
    assert meta["generator"]["name"] == model and len(meta["generator"]["checkpoint_sha256"]) == 64
    assert meta["truncation_psi"] == 0.7 and meta["pivot"] == ([0.0, 0.0, 0.2] if model == "eg3d" else [0.0] * 3)
    assert s.arrays["z"].shape == (512,) and s.arrays["w"].shape == (512,)
    assert s.arrays["planes"].dtype == np.float16 and s.arrays["planes"].shape[-2:] == (16, 16)
    assert s.rgb[0].shape == (64, 64, 3) and s.alpha[0].shape == (64, 64)
    assert all(np.isfinite(d).all() for d in s.depth)
    run_sample(tiny_spec(tmp_path / "b", **{k: v for k, v in spec.__dict__.items() if k != "out"}), progress=False)
    assert all_files(spec.out) == all_files(tmp_path / "b")


def test_z_is_seeded_by_dataset_seed_and_subject():
    g = make_generator("eg3d", str(gan_fixture("eg3d", ".pkl")))
    a, b, c = g.sample_subject(5, 1), g.sample_subject(5, 1), g.sample_subject(5, 2)
    np.testing.assert_array_equal(a.arrays["z"], b.arrays["z"])
    assert not np.array_equal(a.arrays["z"], c.arrays["z"])


@pytest.mark.parametrize("radius", [2.2, 2.7, 3.3])
def test_ray_range_follows_the_radius(radius):
    """At any radius the rendered head is where it is at 2.7: the mask barely changes."""
    g = make_generator("panohead", str(gan_fixture("panohead", ".pkl")), {"deterministic": True})
    s = g.sample_subject(0, 0)
    ref = g.render(s, named_views(["front"], radius=2.7), 32).alpha
    out = g.render(s, named_views(["front"], radius=radius, fov=18.83 * 2.7 / radius), 32)
    assert np.isfinite(out.rgb).all() and np.isfinite(out.depth).all()
    assert abs(out.alpha.mean() - ref.mean()) < 0.05
    inside = out.alpha > 0.5
    assert np.all(np.abs(out.depth[inside] - radius) < 0.6)


def test_solid_background_with_the_mask():
    g = make_generator("spherehead", str(gan_fixture("spherehead", ".pkl")), {"background": "white"})
    s = g.sample_subject(0, 0)
    out = g.render(s, named_views(["back"]), 32)
    expected = out.rgb * 0 + 1.0
    weight = 1 - out.alpha[..., None]
    assert np.all(out.rgb >= weight * expected - 1e-5)  # at least the background's share of white


# -- how the work is split: chunks, batches, ray clipping, devices --------------------------------------

def _views(n, protocol="360"):
    from datagen.cameras import sample_views
    from datagen.generators.base import STREAM_CAMERAS, subject_rng
    return sample_views(protocol, subject_rng(0, 0, STREAM_CAMERAS), n)


def test_chunk_plan_follows_the_memory_budget():
    from datagen.generators.gan import CHUNK_RAYS_QUANTUM, MIN_SR_BATCH, chunk_plan
    G = make_generator("eg3d", str(gan_fixture("eg3d", ".pkl"))).G
    small, large = chunk_plan(G, 16 * 2 ** 20, False), chunk_plan(G, 16 * 2 ** 30, False)
    assert small.rays % CHUNK_RAYS_QUANTUM == 0 and large.rays % CHUNK_RAYS_QUANTUM == 0
    assert small.rays < large.rays and MIN_SR_BATCH <= small.images < large.images
    assert chunk_plan(G, 16 * 2 ** 30, True).images > large.images  # fp16 activations are half the size


@pytest.mark.parametrize("n_views, size, expected", [(32, 3, 11), (7, 3, 2), (1, 4, 1), (5, 4, 1), (4, 4, 1)])
def test_super_resolution_batches_never_hold_a_lone_view(n_views, size, expected):
    from datagen.generators.gan import sr_batches
    batches = sr_batches(n_views, size)
    assert len(batches) == expected and batches[0][0] == 0 and batches[-1][1] == n_views
    assert all(a[1] == b[0] for a, b in zip(batches, batches[1:]))
    assert n_views == 1 or all(last - first >= 2 for first, last in batches)


@pytest.mark.parametrize("model", ["eg3d", "spherehead"])
def test_budget_changes_the_split_not_the_images(model):
    """Ray chunks of whole 1024s give the same bits; SR batch sizes change at most the last bits."""
    from datagen.generators.gan import ChunkPlan
    views = _views(6)
    out = {}
    for rays, images in ((1024, 6), (4096, 6), (4096, 2)):
        g = make_generator(model, str(gan_fixture(model, ".pkl")))
        g.plan = ChunkPlan(rays, images)
        out[rays, images] = g.render(g.sample_subject(0, 3), views, 64)
    small, large, split = out[1024, 6], out[4096, 6], out[4096, 2]
    for a, b in zip((small.rgb, small.alpha, small.depth), (large.rgb, large.alpha, large.depth)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(split.alpha, large.alpha)
    np.testing.assert_array_equal(split.depth, large.depth)
    assert np.abs(split.rgb - large.rgb).max() <= 2e-6


def test_memory_budget_sets_the_plan():
    plans = [make_generator("eg3d", str(gan_fixture("eg3d", ".pkl")), {"memory_budget_mb": mb}).plan
             for mb in (8, 4096)]
    assert plans[0].rays < plans[1].rays and plans[1].rays >= 4 * 1024 and plans[1].images >= 6


def test_clipped_rays_stay_inside_the_box_and_misses_are_skipped():
    from datagen.render import RenderSettings, render_rays_chunked
    origins = torch.tensor([[0.0, 0.0, 3.0], [0.0, 2.0, 3.0], [0.3, 0.0, 3.0]])
    dirs = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    seen = []

    def field(points, _dirs):
        seen.append(points.reshape(-1, 3))
        return torch.ones(*points.shape[:-1], 2), torch.full((*points.shape[:-1], 1), 10.0)

    f, depth, alpha = render_rays_chunked(field, origins, dirs, 1.0, 5.0, RenderSettings(8, 8, "none", True),
                                          box=(0.5, 0.5, 0.5))
    pts = torch.cat(seen)
    assert float(pts.abs().max()) <= 0.5 + 1e-6  # no sample outside the box
    assert alpha[1] == 0 and depth[1] == 5.0 and torch.all(f[1] == 0)  # the ray above the box is skipped
    assert alpha[0] > 0.99 and alpha[2] > 0.99
    assert 2.5 - 1e-5 <= float(depth[0]) <= 3.5


def test_box_interval_on_axis_parallel_and_missing_rays():
    from datagen.render import box_interval
    o = torch.tensor([[0.0, 0.0, 2.0], [0.5, 0.0, 2.0], [0.6, 0.0, 2.0], [0.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    near, far = box_interval(o, d, 0.5)
    assert near[0] == 1.5 and far[0] == 2.5
    assert near[1] == 1.5 and far[1] == 2.5  # grazing the face x = 0.5
    assert far[2] <= near[2]  # parallel to and outside the slab: a miss
    assert near[3] == -0.5 and far[3] == 0.5  # from inside
    assert far[4] <= 0  # the box is behind
    assert all(torch.isfinite(t).all() for t in (near[:2], far[:2]))


def test_clip_rays_option_renders_the_same_head():
    views = _views(4)
    plain = make_generator("panohead", str(gan_fixture("panohead", ".pkl")), {"deterministic": True})
    clipped = make_generator("panohead", str(gan_fixture("panohead", ".pkl")),
                             {"deterministic": True, "clip_rays": True})
    s = plain.sample_subject(0, 0)
    a, b = plain.render(s, views, 64), clipped.render(s, views, 64)
    assert clipped.describe()["config"]["clip_rays"] is True
    assert np.abs(a.alpha - b.alpha).mean() < 0.02
    assert 10 * np.log10(1 / np.mean((a.rgb - b.rgb) ** 2)) > 25


def test_precision_and_device_are_checked_and_recorded():
    from datagen.errors import UserError
    with pytest.raises(UserError, match="precision"):
        make_generator("eg3d", str(gan_fixture("eg3d", ".pkl")), {"precision": "bf16"})
    with pytest.raises(UserError, match="device"):
        make_generator("eg3d", str(gan_fixture("eg3d", ".pkl")), {"device": "cuda:x"})
    g = make_generator("eg3d", str(gan_fixture("eg3d", ".pkl")), {"device": "cpu"})
    assert g.describe()["config"]["precision"] == "fp32" and "memory_budget_mb" not in g.describe()["config"]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("model", ["eg3d", "spherehead"])
def test_cuda_renders_match_the_cpu(model):
    """On CUDA: fp32 agrees with the CPU; 'auto' runs the SR in fp16 and stays close."""
    views = _views(4)
    cpu = make_generator(model, str(gan_fixture(model, ".pkl", "gan-sr")), {"device": "cpu", "deterministic": True})
    ref = cpu.render(cpu.sample_subject(0, 1), views, 128)
    for precision, tol in (("fp32", 2e-3), ("auto", 3e-2)):
        g = make_generator(model, str(gan_fixture(model, ".pkl", "gan-sr")),
                           {"device": "cuda", "deterministic": True, "precision": precision})
        assert g.describe()["config"]["precision"] == ("fp32" if precision == "fp32" else "fp16")
        out = g.render(g.sample_subject(0, 1), views, 128)
        assert np.isfinite(out.rgb).all()
        assert np.abs(out.rgb - ref.rgb).mean() < tol and np.abs(out.alpha - ref.alpha).max() < 1e-3
