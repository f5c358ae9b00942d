"""Training, inference and evaluation end to end on a tiny procedural dataset."""
from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from datagen.manifests import read_manifest
from labeling_tool.manifest import compile_manifest, write_manifest
from panolam import train as train_module
from panolam.config import preset
from panolam.data import TrainingSamples, collate
from panolam.train import TrainConfig, TrainingError, load_model, read_checkpoint, save_checkpoint, train
from datagen.pipeline import run_sample
from tests.conftest import tiny_spec
from tests.test_model import SMALL

MODEL = preset("tiny", **SMALL)
FAST = TrainConfig(steps=4, batch_size=1, views_per_sample=3, render_resolution=16, warmup_steps=2,
                   checkpoint_every=2, log_every=1, image_every=2)


@pytest.fixture(scope="module")
def curated(tmp_path_factory):
    """8 views (front/left/back/right among them) of 4 subjects; one held out for test."""
    root = tmp_path_factory.mktemp("curated")
    data = root / "ds"
    run_sample(tiny_spec(data, subjects=4, views=8), progress=False)
    (root / "labels").mkdir()
    manifest = write_manifest(compile_manifest(data, root / "labels", test_count=1), root / "m-v1.json")
    return data, manifest


def test_sample_choice_is_a_pure_function_of_seed_and_index(curated):
    data, manifest = curated
    a = TrainingSamples(data, manifest, "train", 3, 16, seed=5)
    b = TrainingSamples(data, manifest, "train", 3, 16, seed=5)
    picks = [(a.pick(g), a.view_choice(g, 8)) for g in range(9)]
    assert picks == [(b.pick(g), b.view_choice(g, 8)) for g in range(9)]
    assert {p[0] for p in picks[:3]} == set(a.subjects)  # an epoch visits every subject once
    assert all(len(set(v)) == 3 and max(v) < 8 for _, v in picks)
    item = a[0]
    assert item.images.shape == (3, 3, 16, 16) and item.masks.shape == (3, 1, 16, 16)
    assert 0 <= float(item.images.min()) and float(item.images.max()) <= 1


def test_input_view_keeps_the_stored_detail_targets_are_resized(curated):
    from datagen.shards import decode_sample, read_fields
    data, manifest = curated
    samples = TrainingSamples(data, manifest, "train", 3, 16, seed=5, input_resolution=32)
    key, shard = samples.pick(0)
    views = samples.view_choice(0, 8)
    item = samples[0]
    assert item.inputs.shape == (3, 32, 32) and item.images.shape == (3, 3, 16, 16)
    stored = decode_sample(key, read_fields(data, shard, key), views=views[:1], depth=False)
    rgb = torch.tensor(stored.rgb[0]).float().div(255).permute(2, 0, 1)
    alpha = torch.tensor(stored.alpha[0]).float().div(255)
    expected = rgb * alpha + (1 - alpha)  # over the white background
    assert torch.allclose(item.inputs, expected, atol=1e-6)  # the stored 32 px view itself, not an upsampled target
    batch = collate([samples[0], samples[1]])
    assert batch.inputs.shape == (2, 3, 32, 32) and batch.planes is None
    assert batch.to("cpu").inputs is not None


def test_train_writes_checkpoint_logs_and_resumes_exactly(curated, tmp_path):
    data, manifest = curated
    straight = train(data, manifest, MODEL, FAST, tmp_path / "a", progress=False)
    assert np.isfinite(straight["loss"]) and straight["step"] == 4
    assert (tmp_path / "a" / "checkpoint.pt").exists() and any((tmp_path / "a" / "tb").iterdir())
    assert "D-SSIM" in (tmp_path / "a" / "train.log").read_text()
    half = dataclasses.replace(FAST, steps=2)
    train(data, manifest, MODEL, half, tmp_path / "b", progress=False)
    resumed = train(data, manifest, MODEL, FAST, tmp_path / "b", resume=True, progress=False)
    assert resumed["loss"] == pytest.approx(straight["loss"], rel=1e-5)
    sa, sb = read_checkpoint(tmp_path / "a"), read_checkpoint(tmp_path / "b")
    # Multi-threaded CPU reductions differ in the last bits from run to run (~1e-7 relative in the
    # gradient norm even between two identical runs), so "exact" is up to that noise.
    for k in sa["model"]:
        assert torch.allclose(sa["model"][k], sb["model"][k], atol=2e-5, rtol=1e-4), k
    assert [h["step"] for h in sb["history"]] == [1, 2, 3, 4]


def test_existing_run_needs_resume(curated, tmp_path):
    data, manifest = curated
    one = dataclasses.replace(FAST, steps=1)
    train(data, manifest, MODEL, one, tmp_path / "r", progress=False)
    with pytest.raises(Exception, match="--resume"):
        train(data, manifest, MODEL, one, tmp_path / "r", progress=False)


def test_non_finite_loss_names_step_and_subjects(curated, tmp_path, monkeypatch):
    data, manifest = curated
    real = train_module.compute_losses

    def poisoned(*a, **k):
        loss, parts, renders = real(*a, **k)
        return loss * float("nan"), parts, renders
    monkeypatch.setattr(train_module, "compute_losses", poisoned)
    with pytest.raises(TrainingError, match=r"step 0 \(subjects subj"):
        train(data, manifest, MODEL, FAST, tmp_path / "n", progress=False)


def test_non_finite_gradient_stops_before_the_update(curated, tmp_path, monkeypatch):
    data, manifest = curated
    real = train_module.compute_losses

    def poisoned(model, *a, **k):
        loss, parts, renders = real(model, *a, **k)
        p = next(model.parameters())
        return loss + torch.sqrt(p.sum() * 0), parts, renders  # the same value, a NaN gradient
    monkeypatch.setattr(train_module, "compute_losses", poisoned)
    with pytest.raises(TrainingError, match=r"non-finite gradient at step 0"):
        train(data, manifest, MODEL, FAST, tmp_path / "g", progress=False)
    assert not (tmp_path / "g" / "checkpoint.pt").exists()


def test_triplane_feature_loss_on_spherehead_planes(curated):
    from panolam.data import Views
    from panolam.model import PanoLAM
    from panolam.train import Perceptual
    data, manifest = curated
    torch.manual_seed(0)
    model = PanoLAM(MODEL)
    batch = collate([TrainingSamples(data, manifest, "train", 3, 16, 0, input_resolution=64)[g] for g in (0, 1)])
    r = MODEL.triplane_resolution
    planes = torch.randn(2, 2, 3, MODEL.triplane_channels, 2 * r, 2 * r)  # SphereHead's layout, stored larger
    batch = Views(**{**{f: getattr(batch, f) for f in batch.__dataclass_fields__}, "planes": planes})
    loss, parts, _ = train_module.compute_losses(model, batch, FAST, Perceptual(FAST, "cpu"))
    assert "planes" in parts and torch.isfinite(parts["planes"]) and parts["planes"] > 0.1
    loss.backward()
    assert model.triplane.queries.grad.abs().sum() > 0


@pytest.mark.parametrize("model, protocol, kept", [("eg3d", "frontal", False), ("spherehead", "360", True)])
def test_only_spherehead_planes_reach_training(model, protocol, kept, tmp_path):
    from datagen.shards import read_index
    from panolam.data import load_views
    from tests.conftest import gan_fixture
    data = tmp_path / model
    run_sample(tiny_spec(data, gan=model, checkpoint=str(gan_fixture(model, ".pkl")), protocol=protocol, subjects=1,
                         views=2, resolution=32, generator_options={"save_planes": 8}), progress=False)
    planes = load_views(data, read_index(data)["shards"][0]["subjects"][0], 0).planes
    if kept:  # SphereHead's (2, D, 32, R, R), in float32
        assert planes.shape[0] == 2 and planes.shape[2:] == (32, 8, 8) and planes.dtype == torch.float32
    else:  # EG3D's (3, 32, R, R): the tri-plane branch is distilled from SphereHead only
        assert planes is None


def _ddp_worker(rank, port, data, manifest, out, q):
    import os
    import torch.distributed as dist
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    torch.set_num_threads(1)
    dist.init_process_group("gloo", rank=rank, world_size=2)
    cfg = dataclasses.replace(FAST, steps=2, batch_size=1)
    train(data, manifest, MODEL, cfg, out, progress=False)
    dist.destroy_process_group()


def test_two_processes_match_one_process_with_the_same_global_batch(curated, tmp_path):
    import torch.multiprocessing as mp
    from panolam.cli import _free_port
    data, manifest = curated
    mp.spawn(_ddp_worker, args=(_free_port(), data, manifest, tmp_path / "ddp", None), nprocs=2)
    single = dataclasses.replace(FAST, steps=2, batch_size=2)
    train(data, manifest, MODEL, single, tmp_path / "one", progress=False)
    a, b = read_checkpoint(tmp_path / "ddp")["model"], read_checkpoint(tmp_path / "one")["model"]
    worst = max(float((a[k] - b[k]).abs().max()) for k in a)
    assert worst < 1e-4


def test_eval_and_cli_end_to_end(curated, tmp_path):
    data, manifest = curated
    run = tmp_path / "run"
    one = dataclasses.replace(FAST, steps=1)
    train(data, manifest, MODEL, one, run, progress=False)
    r = subprocess.run([sys.executable, "-m", "panolam.cli", "eval", "--data", str(data), "--manifest", str(manifest),
                        "--ckpt", str(run), "--no-faces"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    report = (run / "eval-test" / "eval.md").read_text()
    assert "| front |" in report and "| back |" in report and "1 subjects evaluated" in report
    import json
    result = json.loads((run / "eval-test" / "eval.json").read_text())
    assert 5 < result["per_view"]["all"]["psnr"] < 60 and len(result["rows"]) == 4


def test_eval_asks_the_face_tools_for_csim_on_front_views_and_apd_on_all(curated):
    """The face metrics' plumbing, with recording stand-ins for :mod:`panolam.faces` (dlib is tested there)."""
    from types import SimpleNamespace
    from panolam.evaluate import evaluate
    from panolam.model import PanoLAM
    data, manifest = curated
    calls = {"csim": [], "apd": [], "between": []}
    tools = SimpleNamespace(
        csim=lambda a, b, box_from_b: calls["csim"].append((a.shape, b.shape, box_from_b)) or 0.5,
        apd=lambda a, b: calls["apd"].append(a.shape) or 2.0,
        csim_between_subjects=lambda images: calls["between"].append(len(images)) or (0.25, len(images)))
    torch.manual_seed(0)
    r = evaluate(PanoLAM(MODEL).eval(), data, read_manifest(manifest), "test", resolution=24, faces=tools)
    assert calls["csim"] == [((24, 24, 3), (24, 24, 3), True)] and len(calls["apd"]) == 4 and calls["between"] == [1]
    assert r["per_view"]["front"]["csim"] == 0.5 and math.isnan(r["per_view"]["back"]["csim"])
    assert r["per_view"]["all"]["apd"] == 2.0 and r["per_view"]["all"]["counted"]["apd"] == 4
    assert (r["csim_between_subjects"], r["csim_between_subjects_faces"]) == (0.25, 1)


def _cli(*argv, cwd=None):
    return subprocess.run([sys.executable, "-m", "panolam.cli", *map(str, argv)], capture_output=True, text=True,
                          cwd=cwd)


def test_resume_keeps_the_schedule_the_data_and_the_manifest(curated, tmp_path):
    data, manifest = curated
    run = tmp_path / "run"
    base = ("train", "--data", data, "--manifest", manifest, "--render-resolution", "16",
            "--views-per-sample", "3", "--batch-size", "1", "--no-progress")
    first = _cli(*base, "--out", run, "--steps", "2", "--time-limit", "0.001")  # stops after its first step
    assert first.returncode == 0, first.stderr
    assert read_checkpoint(run)["step"] == 1
    for extra, message in ((("--steps", "3"), "--steps 3 differs from this run's 2"),
                           (("--config", "full"), "is a 'tiny' run"),
                           (("--steps", "0"), "must be at least 1"),
                           (("--out", tmp_path / "elsewhere"), "name two runs")):
        r = _cli(*base, "--resume", run, *extra)
        assert r.returncode == 2 and message in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    r = _cli(*base, "--resume")
    assert r.returncode == 2 and "say where the run goes" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    other = tmp_path / "other-v1.json"
    m = json.loads(Path(manifest).read_text())
    m["header"]["version"] = "other-v1"
    other.write_text(json.dumps(m))
    r = _cli(*[a if a != manifest else other for a in base], "--out", run, "--resume")
    assert r.returncode == 2 and "resume it with that manifest" in r.stderr, r.stderr
    done = _cli(*base, "--resume", run, "--steps", "2")  # the same value is fine; --resume RUN names the run
    assert done.returncode == 0, done.stderr
    assert read_checkpoint(run)["step"] == 2
    assert read_checkpoint(run)["data"]["subjects"] == [k for k, _ in TrainingSamples(
        data, manifest, "train", 3, 16, 0).subjects]
    assert not (tmp_path / "elsewhere").exists()


def test_eval_warns_when_it_scores_training_subjects(curated, tmp_path):
    data, manifest = curated
    run = tmp_path / "run"
    train(data, manifest, MODEL, dataclasses.replace(FAST, steps=1), run, progress=False)
    r = _cli("eval", "--data", data, "--manifest", manifest, "--split", "train", "--ckpt", run, "--no-faces",
             "--limit", "1")
    assert r.returncode == 0, r.stderr
    assert "1 of the evaluated subjects were training subjects" in r.stderr
    assert "WARNING" in (run / "eval-train" / "eval.md").read_text()


def test_nproc_mistakes_are_one_line_before_any_process_starts(curated, tmp_path):
    data, manifest = curated
    run = tmp_path / "run"
    train(data, manifest, MODEL, dataclasses.replace(FAST, steps=1), run, progress=False)
    r = _cli("train", "--data", data, "--manifest", manifest, "--out", run, "--nproc", "2")
    assert r.returncode == 2 and "already holds a run" in r.stderr and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("argv, message", [
    (["train", "--data", "D", "--manifest", "M", "--out", "O", "--config", "huge"], "unknown config"),
    (["eval", "--data", "D", "--manifest", "M", "--ckpt", "/nonexistent/run"], "no such manifest"),
    (["infer", "x.png", "--ckpt", "/nonexistent/run", "--out", "h.ply"], "no checkpoint"),
])
def test_cli_errors_are_one_line(argv, message, tmp_path):
    r = subprocess.run([sys.executable, "-m", "panolam.cli", *argv], capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 2 and message in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_manifest_of_another_dataset_is_refused_before_anything_is_written(curated, tmp_path, tiny_dataset):
    data, manifest = curated
    r = subprocess.run([sys.executable, "-m", "panolam.cli", "train", "--data", str(tiny_dataset), "--manifest",
                        str(manifest), "--out", str(tmp_path / "run"), "--steps", "1"], capture_output=True, text=True)
    assert r.returncode == 2 and "compiled for another dataset" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "run").exists()


def test_checkpoint_of_another_config_is_refused(tmp_path):
    from panolam.model import PanoLAM
    model = PanoLAM(MODEL)
    opt = torch.optim.Adam(model.parameters())
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 1.0)
    save_checkpoint(tmp_path, model, opt, sched, 0, MODEL, FAST, [])
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    state["model_config"]["token_dim"] = 32
    torch.save(state, tmp_path / "checkpoint.pt")
    with pytest.raises(Exception, match="does not fit config"):
        load_model(tmp_path)


@pytest.fixture(scope="module")
def untrained_run(tmp_path_factory):
    from panolam.model import PanoLAM
    run = tmp_path_factory.mktemp("untrained")
    model = PanoLAM(MODEL)
    opt = torch.optim.Adam(model.parameters())
    save_checkpoint(run, model, opt, torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 1.0), 0, MODEL, FAST, [])
    return run


def _infer(*argv, cwd):
    return subprocess.run([sys.executable, "-m", "panolam.cli", "infer", *map(str, argv)], capture_output=True,
                          text=True, cwd=cwd)


def test_infer_on_a_real_portrait(untrained_run, tmp_path):
    skimage_data = pytest.importorskip("skimage.data", reason="scikit-image ships the test portrait")
    pytest.importorskip("dlib", reason="face detection needs dlib (dlib-bin)")
    from PIL import Image
    from panolam.gaussians import load_ply
    Image.fromarray(skimage_data.astronaut()).save(tmp_path / "astronaut.png")
    r = _infer("astronaut.png", "--ckpt", untrained_run, "--out", "head.ply", "--turntable", "turn.gif",
               "--views", "views", "--resolution", "32", "--frames", "4", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "face found: 1" in r.stdout and "kept" in r.stdout
    g = load_ply(tmp_path / "head.ply")
    assert 0 < len(g) <= 2100 and torch.isfinite(g.means).all()
    gif = Image.open(tmp_path / "turn.gif")
    assert gif.n_frames == 4 and gif.size == (32, 32)
    assert sorted(p.name for p in (tmp_path / "views").iterdir()) == ["back.png", "front.png", "left.png", "right.png"]
    assert not list(tmp_path.rglob(".*tmp*"))


@pytest.mark.parametrize("make, message", [
    (lambda p: __import__("PIL.Image").Image.new("RGB", (200, 200), "white").save(p), "no face found"),
    (lambda p: p.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 40), "cannot read image"),
])
def test_infer_bad_photos_exit_cleanly(untrained_run, tmp_path, make, message):
    pytest.importorskip("dlib", reason="face detection needs dlib (dlib-bin)")
    make(tmp_path / "bad.png")
    r = _infer("bad.png", "--ckpt", untrained_run, "--out", "head.ply", cwd=tmp_path)
    assert r.returncode == 2 and message in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not (tmp_path / "head.ply").exists()


def test_infer_writes_an_mp4_turntable_and_refuses_unknown_formats(untrained_run, tmp_path):
    import av
    from PIL import Image
    Image.fromarray(np.full((64, 64, 3), 128, np.uint8)).save(tmp_path / "framed.png")
    r = _infer("framed.png", "--ckpt", untrained_run, "--no-crop", "--turntable", "t.mp4", "--resolution", "33",
               "--frames", "5", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    with av.open(str(tmp_path / "t.mp4")) as video:
        frames = [f.to_ndarray(format="rgb24") for f in video.decode(video=0)]
    assert len(frames) == 5 and frames[0].shape == (34, 34, 3)  # odd sizes padded for yuv420p
    assert frames[0].mean() > 100  # the head over the white background, not an empty video
    r = _infer("framed.png", "--ckpt", untrained_run, "--no-crop", "--turntable", "t.avi", cwd=tmp_path)
    assert r.returncode == 2 and ".mp4" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_infer_prunes_faint_gaussians_and_reports_what_it_costs(untrained_run, tmp_path):
    import re
    from PIL import Image
    from panolam.gaussians import load_ply
    Image.fromarray(np.full((64, 64, 3), 128, np.uint8)).save(tmp_path / "framed.png")
    common = ("framed.png", "--ckpt", untrained_run, "--no-crop", "--resolution", "24", "--frames", "2")
    r = _infer(*common, "--out", "all.ply", "--prune-opacity", "0", cwd=tmp_path)
    assert r.returncode == 0 and "kept all" in r.stdout, r.stderr
    opacity = load_ply(tmp_path / "all.ply").opacities
    threshold = float(opacity.median())
    r = _infer(*common, "--out", "some.ply", "--prune-opacity", f"{threshold:.6f}", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    kept, of, db = re.search(r"kept (\d+) of (\d+) Gaussians; .* at ([\d.]+) dB PSNR", r.stdout).groups()
    assert int(of) == len(opacity) and 0 < int(kept) < len(opacity)
    assert len(load_ply(tmp_path / "some.ply")) == int(kept) and 0 < float(db) < 100
    above_all = float(opacity.max()) + 1e-4
    assert above_all < 1
    r = _infer(*common, "--out", "none.ply", "--prune-opacity", f"{above_all:.6f}", cwd=tmp_path)
    assert r.returncode == 2 and "removes every Gaussian" in r.stderr and not (tmp_path / "none.ply").exists()
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
