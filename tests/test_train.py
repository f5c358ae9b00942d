"""Training, inference and evaluation end to end on a tiny procedural dataset."""
from __future__ import annotations

import dataclasses
import errno
import io
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from datagen.errors import DatasetError, SettingError
from datagen.dataset.manifests import read_manifest
from panolam import train as train_module
from panolam.data import TrainingSamples, collate
from panolam.model import PanoLAM
from panolam.checkpoints import load_model, read_checkpoint, save_checkpoint
from panolam.config import TrainConfig, preset
from panolam.train import TrainingError, train
from datagen.pipeline import run_sample
from tests.conftest import curated_dataset, group_ended, tiny_spec
from tests.test_model import SMALL

MODEL = preset("tiny", **SMALL)
FAST = TrainConfig(steps=4, batch_size=1, views_per_sample=3, render_resolution=16, warmup_steps=2,
                   checkpoint_every=2, log_every=3, image_every=2)


@pytest.fixture(scope="module")
def curated(tmp_path_factory):
    """8 views (front/left/back/right among them) of 4 subjects; one held out for test."""
    return curated_dataset(tmp_path_factory.mktemp("curated"), subjects=4, views=8, test_count=1)


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


def test_frontal_input_policy_draws_inputs_near_the_front_and_targets_anywhere(curated):
    from datagen.cameras import FRONTAL_YAW_DEG
    data, manifest = curated
    a = TrainingSamples(data, manifest, "train", 3, 16, seed=5, input_views="frontal")
    yaws = np.array([0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 290.0, 330.0])  # frontal: views 0 and 7
    picks = [a.view_choice(g, 8, yaws) for g in range(40)]
    assert picks == [a.view_choice(g, 8, yaws) for g in range(40)]  # a pure function of (seed, g)
    assert {p[0] for p in picks} == {0, 7} and all(len(set(p)) == 3 for p in picks)
    assert {v for p in picks for v in p[1:]} == set(range(8))
    assert a.view_choice(0, 3, np.array([120.0, 180.0, 300.0]))[0] == 2  # none frontal: the nearest to the front
    item = a[3]
    assert abs((float(item.yaw_deg[0]) + 180) % 360 - 180) <= FRONTAL_YAW_DEG


def test_the_learning_rate_decays_to_its_floor_and_old_runs_keep_their_recipe():
    cfg = TrainConfig(steps=100, warmup_steps=10, lr_floor=0.1)
    factors = [train_module.lr_factor(s, cfg) for s in range(120)]
    assert factors[9] == 1.0 and abs(factors[99] - 0.1) < 1e-3 and min(factors[10:]) == pytest.approx(0.1)
    assert all(a >= b for a, b in zip(factors[9:], factors[10:]))
    old = {k: v for k, v in cfg.to_dict().items() if k not in ("input_views", "targets", "lr_floor")}
    legacy = TrainConfig.from_dict(old)  # a checkpoint written before these settings existed
    assert (legacy.input_views, legacy.targets, legacy.lr_floor) == ("any", "others", 0.0)
    assert train_module.lr_factor(99, legacy) < 1e-3 and train_module.first_target(legacy) == 1
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg


def test_a_time_limit_fits_the_decay_to_the_time_and_resuming_never_raises_the_rate():
    cfg = TrainConfig(steps=10_000, warmup_steps=10, lr_floor=0.1)
    now = [0.0]
    schedule = train_module.Schedule(cfg, deadline=100.0, clock=lambda: now[0])
    factors = []
    for step in range(60):  # one step a second, warm-up done after 10 s; 10,000 steps would never fit
        now[0] = float(step)
        schedule.advance(schedule.time_progress(step))
        factors.append(schedule.factor(step))
    assert factors[:10] == [train_module.lr_factor(s, cfg) for s in range(10)]
    assert schedule.decay_start == (10.0, 0.0)
    assert schedule.progress == pytest.approx(49 / 90)  # 49 of the 90 s between the decay's start and the deadline
    assert factors[-1] == pytest.approx(train_module.lr_factor(10, cfg, 49 / 90))
    assert all(a >= b for a, b in zip(factors[9:], factors[10:]))
    now[0] = 100.0
    schedule.advance(schedule.time_progress(60))
    assert schedule.factor(60) == pytest.approx(0.1)  # the floor at the deadline
    # resumed without a limit: the decay stays where it was until the steps' share passes it
    resumed = train_module.Schedule(cfg, progress=0.5)
    assert resumed.factor(20) == pytest.approx(train_module.lr_factor(20, cfg, 0.5))
    assert resumed.factor(9000) == pytest.approx(train_module.lr_factor(9000, cfg))
    # resumed with a new limit: the rest of the decay fits into it
    again = train_module.Schedule(cfg, deadline=50.0, progress=0.5, clock=lambda: now[0])
    now[0] = 0.0
    again.advance(again.time_progress(60))
    now[0] = 25.0
    again.advance(again.time_progress(61))
    assert again.progress == pytest.approx(0.75)
    # no limit: exactly the steps' schedule
    plain = train_module.Schedule(cfg)
    assert [plain.factor(s) for s in range(0, 10_000, 500)] == [train_module.lr_factor(s, cfg)
                                                               for s in range(0, 10_000, 500)]


def test_the_input_view_is_among_the_targets_unless_asked_otherwise(curated):
    data, manifest = curated
    samples = TrainingSamples(data, manifest, "train", 3, 16, seed=0, input_resolution=MODEL.image_size)
    batch = collate([samples[0]])
    torch.manual_seed(0)
    from panolam.model import PanoLAM
    model = PanoLAM(MODEL)
    for targets, rendered in (("all", 3), ("others", 2)):
        cfg = dataclasses.replace(FAST, targets=targets)
        _, parts, renders = train_module.compute_losses(model, batch, cfg, train_module.Perceptual(cfg, "cpu"))
        assert renders["dense"].shape[:2] == (1, rendered) and renders["triplane"].shape[1] == 2
        assert all(torch.isfinite(torch.as_tensor(v)).all() for v in parts.values())


def test_input_view_keeps_the_stored_detail_targets_are_resized(curated):
    from datagen.dataset.shards import decode_sample, read_fields
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
    log = (tmp_path / "a" / "train.log").read_text()
    assert "D-SSIM" in log and all(f"step {i}: loss" in log for i in (1, 2, 3, 4))  # every step, not every 3rd
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
    with pytest.raises(SettingError, match="already holds a run; pass resume to continue it or choose another out"):
        train(data, manifest, MODEL, one, tmp_path / "r", progress=False)  # the command line says --resume, --out


def test_non_finite_loss_names_step_and_subjects(curated, tmp_path, monkeypatch):
    data, manifest = curated
    real = train_module.compute_losses

    def poisoned(*a, **k):
        loss, parts, renders = real(*a, **k)
        return loss * float("nan"), parts, renders
    monkeypatch.setattr(train_module, "compute_losses", poisoned)
    with pytest.raises(TrainingError, match=r"step 0 \(subjects subj"):
        train(data, manifest, MODEL, FAST, tmp_path / "n", progress=False)


def test_non_finite_gradient_stops_before_anything_is_saved(curated, tmp_path, monkeypatch):
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
    from datagen.dataset.shards import read_index
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
    from panolam.launch import free_port
    data, manifest = curated
    mp.spawn(_ddp_worker, args=(free_port(), data, manifest, tmp_path / "ddp", None), nprocs=2)
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
    r = subprocess.run([sys.executable, "-m", "panolam", "eval", "--data", str(data), "--manifest", str(manifest),
                        "--ckpt", str(run), "--no-faces"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    report = (run / "eval-test" / "eval.md").read_text()
    assert "| front |" in report and "| back |" in report and "| novel |" in report and "1 subject evaluated" in report
    assert "| baseline: untrained |" in report and "| baseline: mean colour template |" in report
    assert "trained with --input-views frontal" in report and "--targets all" in report
    assert "NOTE: 1 test subject only" in report
    assert "](gallery.png)" in report and str(run / "eval-test" / "gallery.png") in r.stdout
    import json
    result = json.loads((run / "eval-test" / "eval.json").read_text())
    assert 5 < result["per_view"]["all"]["psnr"] < 60 and len(result["rows"]) == 4
    for r in (result, *result["baselines"].values()):
        assert 0 < r["per_view"]["novel"]["psnr_fg"] < r["per_view"]["all"]["psnr"]  # the background is the easy part
        assert r["per_view"]["novel"]["counted"]["psnr_fg"] == 3 and 0 < r["per_view"]["all"]["ssim_fg"] < 1


def test_eval_gallery_shows_the_input_renders_and_truth(curated, tmp_path):
    """One row per subject: the input tile is the model's input, the truth tiles are the stored views."""
    from PIL import Image

    from panolam.data import accepted_subjects
    from panolam.evaluate import GALLERY_TILE, evaluate, write_gallery
    data, manifest = curated
    model = PanoLAM(MODEL).eval()
    pictures = []
    evaluate(model, data, read_manifest(manifest), "train", resolution=32, gallery=pictures, gallery_subjects=2)
    keys = [k for k, _ in accepted_subjects(read_manifest(manifest), "train", data)]
    assert [p[0] for p in pictures] == keys[:2]
    key, photo, renders, targets = pictures[0]
    assert photo.shape == (MODEL.image_size, MODEL.image_size, 3) and renders.shape == targets.shape == (4, 32, 32, 3)
    assert renders.dtype == targets.dtype == np.uint8 and not np.array_equal(renders, targets)
    sheet = np.asarray(Image.open(write_gallery(pictures, tmp_path / "g.png")))
    tile = GALLERY_TILE  # 32 px enlarged 4x
    assert sheet.shape[0] > 2 * tile and sheet.shape[1] > 9 * tile
    row = sheet[sheet.shape[0] - 18 - tile: sheet.shape[0] - 18]  # the last row's tiles
    last = row[:, -tile:]  # truth, right view, enlarged by nearest neighbour
    np.testing.assert_array_equal(last[::4, ::4], pictures[1][3][3])


def test_eval_asks_the_face_tools_for_csim_on_front_views_and_apd_on_all(curated):
    """The face metrics' plumbing, with recording stand-ins for :mod:`datagen.faces` (dlib is tested there)."""
    from types import SimpleNamespace
    from panolam.data import accepted_subjects, load_views
    from panolam.evaluate import evaluate
    from panolam.model import PanoLAM
    data, manifest = curated
    calls = {"csim": [], "apd": [], "between": []}
    tools = SimpleNamespace(
        csim=lambda a, b, box_from_b: calls["csim"].append((a.shape, b.shape, box_from_b)) or 0.5,
        apd=lambda a, b, focal: calls["apd"].append((a.shape, round(focal, 3))) or 2.0,
        csim_between_subjects=lambda images: calls["between"].append(len(images)) or (0.25, len(images)))
    torch.manual_seed(0)
    r = evaluate(PanoLAM(MODEL).eval(), data, read_manifest(manifest), "test", resolution=24, faces=tools)
    assert calls["csim"] == [((24, 24, 3), (24, 24, 3), True)] and calls["between"] == [1]
    key, shard = accepted_subjects(read_manifest(manifest), "test", data)[0]
    focals = [round(float(K[0, 0]), 3) for K in load_views(data, key, shard).K]
    assert len(calls["apd"]) == 4 and all(shape == (24, 24, 3) and f in focals for shape, f in calls["apd"])
    assert r["per_view"]["front"]["csim"] == 0.5 and math.isnan(r["per_view"]["back"]["csim"])
    assert r["per_view"]["all"]["apd"] == 2.0 and r["per_view"]["all"]["counted"]["apd"] == 4
    assert (r["csim_between_subjects"], r["csim_between_subjects_faces"]) == (0.25, 1)


def _cli(*argv, cwd=None):
    return subprocess.run([sys.executable, "-m", "panolam", *map(str, argv)], capture_output=True, text=True,
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
    assert "1 of the evaluated subjects were training subjects" in r.stdout and not r.stderr
    assert "WARNING" in (run / "eval-train" / "eval.md").read_text()


def test_nproc_mistakes_are_one_line_before_any_process_starts(curated, tmp_path):
    data, manifest = curated
    run = tmp_path / "run"
    train(data, manifest, MODEL, dataclasses.replace(FAST, steps=1), run, progress=False)
    r = _cli("train", "--data", data, "--manifest", manifest, "--out", run, "--nproc", "2")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert "already holds a run; pass --resume to continue it or choose another --out" in r.stderr


def test_sigterm_stops_every_training_process_and_the_run_resumes(curated, tmp_path):
    data, manifest = curated
    run = tmp_path / "run"
    base = [sys.executable, "-m", "panolam", "train", "--data", str(data), "--manifest", str(manifest), "--steps",
            "1000", "--render-resolution", "16", "--views-per-sample", "3", "--batch-size", "1", "--no-progress",
            "--checkpoint-every", "1", "--nproc", "2"]
    proc = subprocess.Popen([*base, "--out", str(run)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)  # its own process group: both training processes are in it
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None and not (run / "checkpoint.pt").exists():
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    assert err.strip().splitlines()[-1] == "panolam train: terminated; the last checkpoint is kept; rerun with --resume"
    assert group_ended(proc.pid, 20), "a training process outlived the command"
    step = read_checkpoint(run)["step"]
    resumed = subprocess.run([*base[:-2], "--time-limit", "0.001", "--resume", str(run)],  # one more step
                             capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    assert read_checkpoint(run)["step"] == step + 1


@pytest.mark.parametrize("argv, message", [
    (["train", "--data", "D", "--manifest", "M", "--out", "O", "--config", "huge"], "unknown config"),
    (["eval", "--data", "D", "--manifest", "M", "--ckpt", "/nonexistent/run"], "M: no "),  # the manifest, named
    (["infer", "x.png", "--ckpt", "/nonexistent/run", "--out", "h.ply"], "no checkpoint"),
])
def test_cli_errors_are_one_line(argv, message, tmp_path):
    r = subprocess.run([sys.executable, "-m", "panolam", *argv], capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 2 and message in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_manifest_of_another_dataset_is_refused_before_anything_is_written(curated, tmp_path, tiny_dataset):
    data, manifest = curated
    r = subprocess.run([sys.executable, "-m", "panolam", "train", "--data", str(tiny_dataset), "--manifest",
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
    return subprocess.run([sys.executable, "-m", "panolam", "infer", *map(str, argv)], capture_output=True,
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


def test_a_learning_rate_too_large_for_float32_stops_before_anything_is_saved(curated, tmp_path):
    data, manifest = curated
    huge = dataclasses.replace(FAST, lr=1e38, warmup_steps=0)
    with pytest.raises(TrainingError, match=r"non-finite update at step 0 \(learning rate 1e\+38\)"):
        train(data, manifest, MODEL, huge, tmp_path / "lr", progress=False)
    assert not (tmp_path / "lr" / "checkpoint.pt").exists()


class _FullDisk(io.FileIO):
    """A file on a full disk: every write fails as the kernel's would."""

    def write(self, data):
        raise OSError(errno.ENOSPC, "No space left on device")


@pytest.mark.parametrize("module, name", [("datagen.files", "checkpoint.pt"), ("panolam.train", "train.log")])
def test_a_full_disk_is_one_line_naming_the_file_and_leaves_no_temporary(curated, tmp_path, monkeypatch, capsys,
                                                                       module, name):
    """The checkpoint (written atomically) and the log (appended): each write fails as on a full disk."""
    import builtins
    import importlib
    from panolam.cli import main
    data, manifest = curated

    def opener(path, mode="r", *args, **kwargs):
        if name in Path(path).name and mode[0] in "wa":
            return _FullDisk(path, mode[0] + "b")
        return builtins.open(path, mode, *args, **kwargs)
    monkeypatch.setattr(importlib.import_module(module), "open", opener, raising=False)
    run = tmp_path / "run"
    code = main(["train", "--data", str(data), "--manifest", str(manifest), "--out", str(run), "--steps", "1",
                 "--views-per-sample", "3", "--render-resolution", "16", "--batch-size", "1", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and err.strip() == f"panolam train: error: disk full ({run / name})", err
    assert "checkpoint.pt" not in [p.name for p in run.iterdir()]
    assert not [p.name for p in run.iterdir() if p.name.startswith(".")]  # no .checkpoint.pt.tmp


@pytest.fixture
def damaged(curated, tmp_path):
    """A copy of the curated dataset; returns it, the manifest, and a training subject's shard and key."""
    import shutil
    from datagen.dataset.shards import tar_path
    data, manifest = curated
    copy = tmp_path / "copy"
    shutil.copytree(data, copy)
    key, shard = TrainingSamples(copy, manifest, "train", 3, 16, 0).subjects[0]
    return copy, manifest, tar_path(copy, shard), key


def test_training_checks_its_shards_first_and_remembers_those_that_passed(damaged, monkeypatch):
    import datagen.dataset.shards as shards
    data, manifest, tar, _ = damaged
    (data / shards.SHARD_CHECKS).unlink(missing_ok=True)  # as remembered by the copied dataset
    read, real_read = [], Path.read_bytes

    def read_bytes(path):  # a shard's check reads its tar once (hashed, then walked)
        if path.suffix == ".tar":
            read.append(path)
        return real_read(path)

    monkeypatch.setattr(Path, "read_bytes", read_bytes)
    TrainingSamples(data, manifest, "train", 3, 16, 0)
    assert tar in read and (data / shards.SHARD_CHECKS).exists()
    read.clear()
    TrainingSamples(data, manifest, "train", 3, 16, 0)
    assert read == []  # the second time costs a stat per shard (and the index's hash)
    blob = bytearray(tar.read_bytes())
    blob[700] ^= 0xFF  # one flipped bit pattern, same size: only the hash can tell
    st = tar.stat()
    tar.write_bytes(bytes(blob))
    os.utime(tar, ns=(st.st_atime_ns, st.st_mtime_ns))  # even with its mtime put back
    with pytest.raises(DatasetError, match=f"{tar}: sha256 differs from the sidecar"):
        TrainingSamples(data, manifest, "train", 3, 16, 0)
    tar.unlink()
    with pytest.raises(DatasetError, match=f"{tar}: missing although its sidecar exists"):
        TrainingSamples(data, manifest, "train", 3, 16, 0)


def test_a_view_that_does_not_decode_names_the_shard_and_the_subject(damaged):
    """A shard whose sidecar vouches for a broken image (written broken): decoding says where."""
    import tarfile
    from datagen.files import sha256_file
    from datagen.dataset.shards import read_sidecar, sidecar_path
    data, manifest, tar, key = damaged
    with tarfile.open(tar) as t:
        members = [(m, t.extractfile(m).read()) for m in t]
    with tarfile.open(tar, "w", format=tarfile.USTAR_FORMAT) as t:
        for m, blob in members:
            if m.name.startswith(key) and m.name.endswith(".png"):
                blob = blob[:20] + bytes(len(blob) - 20)  # the header survives, the pixels do not
            t.addfile(m, io.BytesIO(blob))
    shard = int(tar.stem.split("-")[1])
    side = read_sidecar(data, shard)
    side.update(tar_bytes=tar.stat().st_size, tar_sha256=sha256_file(tar))
    sidecar_path(data, shard).write_text(json.dumps(side))
    samples = TrainingSamples(data, manifest, "train", 3, 16, 0)
    g = next(g for g in range(8) if samples.pick(g)[0] == key)
    with pytest.raises(DatasetError, match=f"{tar}: subject {key} does not decode") as e:
        samples[g]
    assert "\n" not in str(e.value)
