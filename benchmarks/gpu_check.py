"""The GPU acceptance check: every GPU path of the toolkit run and measured once, within a time budget.

Sized for one call on a GPU node with a 15-minute allocation: ``--budget-s`` (default 540 s) bounds
the sections, which run in order of value; one that no longer fits in what is left is skipped, and
the report says so. The report (``benchmarks/reports/gpu_check.{json,md}``, ``gpu_check_dry_run.*``
with ``--dry-run``) is rewritten atomically after each section, so a call cut short still leaves
what it measured; its header names the GPU, driver, torch and CUDA versions.

    python -m benchmarks.gpu_check                   # on a CUDA machine
    python -m benchmarks.gpu_check --gsplat          # and, last, compile gsplat and check it
    python -m benchmarks.gpu_check --dry-run         # the same sequence at toy sizes on the CPU

Sections, in order:

1. ``cuda_vs_cpu``: the GAN samplers (released sizes, random weights, one 512 px view each, fp32)
   and the pure-PyTorch rasterizer (forward and gradients) on CUDA against the same work on the CPU.
2. ``cuda_tests``: the tests marked ``cuda`` (GAN sampling on CUDA against the CPU on the tiny
   official-format fixtures, fp32 and fp16); gsplat's parity test waits for section 8.
3. ``precision``: the released-size generators in fp16 against fp32 at 512 px: PSNR, seconds.
4. ``throughput``: 512 px images per second and peak memory of the released-size generators over
   32-view subjects, at several memory budgets (goal: 200 images/s on one H100-class GPU).
5. ``training``: ``tiny`` and ``full`` (DINOv2 ViT-L/14 shape, random weights, saved and loaded as
   a Hugging Face folder), pure-PyTorch rasterizer: median seconds per step, peak memory.
6. ``inference``: one reconstruction and one 512 px render of each trained model (the paper, A100:
   0.11 s per reconstruction, 3.6 ms per render).
7. ``workers``: ``datagen sample --workers auto`` over the visible GPUs against one worker
   (skipped with one GPU).
8. ``gsplat`` (with ``--gsplat``): installs gsplat from the device kit when it is not importable,
   compiles its kernels (minutes) and runs its parity test against the pure-PyTorch rasterizer.

``--dry-run`` runs the same code on the CPU with the tiny GAN fixtures, 64 px, two training steps
of ``tiny``; it checks the script and its report, and its figures mean nothing for a GPU.
"""
from __future__ import annotations

import argparse
import copy
import hashlib
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import (REPO, REPORTS, bullets, command_line, device_sync, fmt, machine_info, memory_peak,
                               memory_start, psnr_db, reproduce, table)
from benchmarks.gan_fullsize import PROTOCOL, build
from datagen.cameras import sample_views
from datagen.files import atomic_write
from datagen.generators.base import STREAM_CAMERAS, subject_rng
from datagen.generators.gan import GANConfig, GANHeads
from datagen.gans.checkpoint import read_checkpoint
from datagen.gans.kinds import KINDS

NAME = "gpu_check"
SHARED = Path(os.environ.get("PANOLAM_SHARED", REPO.parent / "shared"))
FIXTURE_SET, FIXTURE_TAG = "gan", "tiny"  # read by the cuda tests and the dry run; benchmarks/device_kit.py copies it
PAPER_RECONSTRUCT_S, PAPER_RENDER_MS = 0.11, 3.6  # A100, the paper
GOAL_IMAGES_PER_S = 200  # 512 px, one H100-class GPU
DEFAULT_BUDGET_S = 540


def fixture_files() -> list[Path]:
    """The GAN fixture pickles the check reads, relative to the shared/ folder."""
    return [Path("fixtures") / FIXTURE_SET / kind / f"{kind}-{FIXTURE_TAG}.pkl" for kind in KINDS]


class Plan:
    """Sizes of one run: the GPU's, or the dry run's toy sizes on the CPU."""

    def __init__(self, dry_run: bool, gsplat: bool = False):
        self.dry_run = dry_run
        self.device = "cpu" if dry_run else "cuda"
        self.views = 2 if dry_run else 32
        self.precision_views = 2 if dry_run else 4
        self.resolution = 64 if dry_run else 512
        self.subjects_timed = 1 if dry_run else 2
        self.budgets_mb = (0, 16) if dry_run else (0, 1024, 4096, 16384)
        self.worker_subjects = 2 if dry_run else 16
        self.configs = ("tiny",) if dry_run else ("tiny", "full")
        self.train_steps = 2 if dry_run else 30
        self.train_subjects = 4 if dry_run else 16
        self.repeats = 3 if dry_run else 10
        self.gsplat = gsplat
        self._generators = {}

    def generator(self, kind: str):
        """A CPU copy of ``kind``'s generator: the released size (random weights), or the tiny fixture
        in the dry run (GANHeads moves the generator it is given, so each caller gets its own)."""
        if kind not in self._generators:
            self._generators[kind] = (read_checkpoint(SHARED / fixture_files()[KINDS.index(kind)], kind)
                                      if self.dry_run else build(kind, "cpu").checkpoint)
        return copy.deepcopy(self._generators[kind])


class Clock:
    """The budget: seconds left in all, and for the running section (what the sections after it need
    kept back: ``reserve_s``, set before each section)."""

    def __init__(self, budget_s: float):
        self.start = time.perf_counter()
        self.budget_s = budget_s
        self.reserve_s = 0.0

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def total_left(self) -> float:
        return self.budget_s - self.elapsed()

    def left(self) -> float:
        return self.total_left() - self.reserve_s


# ------------------------------------------------------------------------------------------------
# Measuring helpers


def gsplat_version() -> str | None:
    try:
        import gsplat
    except ImportError:
        return None
    return getattr(gsplat, "__version__", "installed")


def run_command(args: list, timeout: float, env: dict | None = None) -> dict:
    """A command's exit status, seconds and the tail of its output (run from the repository root)."""
    t0 = time.perf_counter()
    try:
        done = subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=max(timeout, 1),
                              cwd=REPO, env={**os.environ, **(env or {})})
        code, out = done.returncode, done.stdout + done.stderr
    except subprocess.TimeoutExpired as e:
        code, out = None, f"{e.stdout or ''}{e.stderr or ''}\ntimed out after {timeout:.0f} s (the budget)"
    return {"command": shlex.join(str(a) for a in args), "returncode": code,
            "seconds": time.perf_counter() - t0, "tail": out[-1500:]}


def tree_digest(root: Path) -> str:
    """SHA-256 over every file's relative path and bytes under ``root``."""
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def nvidia_driver() -> str | None:
    try:
        done = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
                              capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip().splitlines()[0] if done.returncode == 0 and done.stdout.strip() else None


def environment() -> dict:
    """GPU, driver, torch, CUDA and cuDNN versions."""
    info = {"torch": torch.__version__, "torch_cuda": torch.version.cuda, "cudnn": torch.backends.cudnn.version(),
            "cuda_available": torch.cuda.is_available(), "gsplat": gsplat_version(), "driver": nvidia_driver(),
            "gpus": []}
    for i in range(torch.cuda.device_count()):
        p = torch.cuda.get_device_properties(i)
        info["gpus"].append({"name": p.name, "memory_mib": p.total_memory // 2 ** 20, "sms": p.multi_processor_count,
                             "capability": f"sm_{p.major}{p.minor}"})
    return info


def _render_subject(heads: GANHeads, index: int, views: int, resolution: int):
    cams = sample_views(PROTOCOL[heads.name], subject_rng(0, index, STREAM_CAMERAS), views)
    return heads.render(heads.sample_subject(0, index), cams, resolution)


def _compare(got: np.ndarray, want: np.ndarray) -> dict:
    diff = got.astype(np.float64) - want
    return {"psnr_db": psnr_db(float(np.mean(diff ** 2))), "max_abs_diff": float(np.abs(diff).max())}


# ------------------------------------------------------------------------------------------------
# Sections (each takes the plan, the clock and a scratch folder; returns a JSON-able result)


def cuda_vs_cpu(plan: Plan, clock: Clock, scratch: Path) -> dict:
    """One fp32 view per generator and a rasterized scene with gradients, on the device against the CPU."""
    rows = {}
    for kind in KINDS:
        views = {}
        for device in ("cpu", plan.device):
            heads = GANHeads(kind, plan.generator(kind), GANConfig(device=device, precision="fp32"))
            views[device] = _render_subject(heads, 1, 1, plan.resolution)
        rows[kind] = {name: _compare(getattr(views[plan.device], name), getattr(views["cpu"], name))
                      for name in ("rgb", "alpha", "depth")}
    return {"gan": rows, "resolution": plan.resolution, "rasterizer": _rasterizer_vs_cpu(plan.device)}


def _rasterizer_vs_cpu(device: str) -> dict:
    from panolam.rasterizer import rasterize
    from tests.test_rasterizer import INPUTS, camera, loss_weights, random_scene, render
    width, height = 128, 96
    scene, (view, K) = random_scene(2000, 0, torch.float32), camera(torch.float32, width=width, height=height)
    weights = loss_weights([torch.zeros(height, width, 3), torch.zeros(height, width, 1)])
    outputs = {}
    for where in ("cpu", device):
        leaves = {k: v.to(where).detach().requires_grad_() for k, v in scene.items()}
        rgb, alpha, depth = render(rasterize, leaves, view.to(where), K.to(where), width, height, backend="torch")
        loss = (rgb * weights[0].to(where)).sum() + (alpha * weights[1].to(where)).sum()
        grads = torch.autograd.grad(loss, [leaves[k] for k in INPUTS])
        outputs[where] = [t.detach().cpu() for t in (rgb, alpha, depth, *grads)]
    ours, ref = outputs[device], outputs["cpu"]
    images = {name: _compare(a.numpy(), b.numpy())
              for name, a, b in zip(("rgb", "alpha", "depth"), ours, ref, strict=False)}
    cosines = {name: float(torch.nn.functional.cosine_similarity(a.flatten(), b.flatten(), dim=0))
               for name, a, b in zip(INPUTS, ours[3:], ref[3:], strict=True)}
    return {"gaussians": 2000, "size": [width, height], "images": images, "gradient_cosine": cosines}


def cuda_tests(plan: Plan, clock: Clock, scratch: Path, select: str = "not gsplat", env: dict | None = None) -> dict:
    """The tests marked ``cuda`` (those of ``select``), in a child pytest; on a CPU they are all skipped."""
    files = [p.relative_to(REPO) for p in sorted((REPO / "tests").glob("test_*.py"))
             if "pytest.mark.cuda" in p.read_text()]
    result = run_command([sys.executable, "-m", "pytest", "-m", "cuda", "-k", select, "-q", "-p", "no:cacheprovider",
                          "-o", "addopts=", "-rs", *files], timeout=clock.total_left(),
                         env={"PANOLAM_SHARED": str(SHARED), **(env or {})})
    lines = [line for line in result["tail"].splitlines() if line.strip()]
    result["summary"] = lines[-1] if lines else ""
    result["ok"] = result["returncode"] in (0, 5)  # 5: none collected
    return result


def precision(plan: Plan, clock: Clock, scratch: Path) -> dict:
    """fp16 against fp32: PSNR of the images, seconds of each."""
    rows = {}
    for kind in KINDS:
        images, seconds = {}, {}
        for mode in ("fp32", "fp16"):
            heads = GANHeads(kind, plan.generator(kind), GANConfig(device=plan.device, precision=mode))
            _render_subject(heads, 0, 1, plan.resolution)  # warm-up
            device_sync(plan.device)
            t0 = time.perf_counter()
            images[mode] = _render_subject(heads, 1, plan.precision_views, plan.resolution).rgb
            seconds[mode] = time.perf_counter() - t0
        rows[kind] = {**_compare(images["fp16"], images["fp32"]), "seconds": seconds,
                      "views": plan.precision_views, "resolution": plan.resolution}
    return rows


def throughput(plan: Plan, clock: Clock, scratch: Path) -> dict:
    """Images per second and peak memory per generator and memory budget (0: the default), default
    budget first; a row that the last one's time says would not fit is left out, and named."""
    rows, left_out, last_s = {}, [], 0.0
    for budget in plan.budgets_mb:
        for kind in KINDS:
            if clock.left() < last_s:
                left_out.append(f"{kind}@{budget}")
                continue
            t_row = time.perf_counter()
            heads = GANHeads(kind, plan.generator(kind), GANConfig(device=plan.device, memory_budget_mb=budget))
            _render_subject(heads, 0, plan.views, plan.resolution)  # warm-up
            memory_start(plan.device)
            t0 = time.perf_counter()
            for index in range(1, 1 + plan.subjects_timed):
                _render_subject(heads, index, plan.views, plan.resolution)
            device_sync(plan.device)
            seconds = time.perf_counter() - t0
            rows[f"{kind}@{budget}"] = {"kind": kind, "budget_mb": budget, "plan": vars(heads.plan),
                                        "precision": "fp16" if heads.fp16 else "fp32",
                                        "images_per_s": plan.subjects_timed * plan.views / seconds,
                                        "peak_mb": memory_peak(plan.device)}
            del heads
            if plan.device.startswith("cuda"):
                torch.cuda.empty_cache()
            last_s = time.perf_counter() - t_row
    return {"rows": rows, "left_out": left_out}


def _training_data(plan: Plan, scratch: Path) -> tuple[Path, Path]:
    from datagen.pipeline import JobSpec, run_sample, software_info
    from labeling_tool.compiler import compile_manifest, write_manifest
    data = scratch / "train_data"
    if not data.exists():
        spec = JobSpec(out=str(data), gan="procedural", generator_options={}, protocol="360",
                       subjects=plan.train_subjects, resolution=128, views=8, seed=0, shard_size=4,
                       software=software_info())
        run_sample(spec, workers=min(8, os.cpu_count() or 1), progress=False)
        (scratch / "labels").mkdir(exist_ok=True)
        write_manifest(compile_manifest(data, scratch / "labels", test_count=2), scratch / "manifest.json")
    return data, scratch / "manifest.json"


def _random_dinov2(scratch: Path) -> Path:
    """A DINOv2 ViT-L/14 with random weights as a Hugging Face folder (what a user passes)."""
    from transformers import Dinov2Config, Dinov2Model
    folder = scratch / "dinov2-vitl14-random"
    if not folder.exists():
        torch.manual_seed(0)
        Dinov2Model(Dinov2Config(hidden_size=1024, num_hidden_layers=24, num_attention_heads=16,
                                 intermediate_size=4096, patch_size=14, image_size=518)).save_pretrained(folder)
    return folder


def train_runs(plan: Plan, clock: Clock, scratch: Path, rasterizer: str = "torch", configs=None) -> dict:
    """A few optimizer steps per config: median s/step (first two steps left out), peak memory; a
    config is left out when the time left is under the last one's."""
    from panolam.checkpoints import read_checkpoint as read_run
    from panolam.config import TrainConfig, preset
    from panolam.train import train
    data, manifest = _training_data(plan, scratch)
    rows, last_s = {}, 0.0
    for config in configs or plan.configs:
        key = f"{config}/{rasterizer}"
        if clock.left() < last_s:
            rows[key] = {"skipped": f"{max(clock.left(), 0):.0f} s of the budget left, the last took {last_s:.0f} s"}
            continue
        overrides = {"encoder_weights": str(_random_dinov2(scratch))} if config == "full" else {}
        out = scratch / "runs" / key.replace("/", "-")
        cfg = TrainConfig(steps=plan.train_steps, warmup_steps=1, checkpoint_every=plan.train_steps,
                          rasterizer=rasterizer)
        memory_start(plan.device)
        t0 = time.perf_counter()
        train(data, manifest, preset(config, **overrides), cfg, out, device=plan.device, progress=False)
        wall = last_s = time.perf_counter() - t0
        steps = [e["seconds"] for e in read_run(out)["history"]]
        rows[key] = {"steps": len(steps), "median_step_s": statistics.median(steps[2:] or steps),
                     "wall_s": wall, "peak_mb": memory_peak(plan.device), "run": str(out)}
    return rows


def inference(plan: Plan, trained: dict) -> dict:
    """Seconds per reconstruction and ms per render of each trained model (medians)."""
    from panolam.checkpoints import load_model
    from panolam.infer import reconstruct, render_set, turntable_views
    image = np.random.default_rng(0).random((512, 512, 3), dtype=np.float32)
    rows = {}
    for key, row in trained.items():
        if "run" not in row:
            continue
        model = load_model(row["run"], plan.device)
        reconstruct(model, image)  # warm-up
        seconds = [reconstruct(model, image)[1] for _ in range(plan.repeats)]
        g, _ = reconstruct(model, image)
        view = turntable_views(1)
        render_set(g, view, plan.resolution)
        renders = []
        for _ in range(plan.repeats):
            device_sync(plan.device)
            t0 = time.perf_counter()
            render_set(g, view, plan.resolution)
            device_sync(plan.device)
            renders.append(time.perf_counter() - t0)
        rows[key] = {"reconstruct_s": statistics.median(seconds), "render_ms": 1e3 * statistics.median(renders),
                     "gaussians": int(g.means.shape[0]), "render_resolution": plan.resolution}
    return rows


def workers(plan: Plan, clock: Clock, scratch: Path) -> dict:
    """``--workers auto`` over the visible GPUs against one worker: time and identical bytes."""
    common = [sys.executable, "-m", "datagen.cli", "sample", "--gan", "spherehead", "--checkpoint",
              SHARED / fixture_files()[KINDS.index("spherehead")], "--protocol", "360",
              "--subjects", plan.worker_subjects, "--views", plan.views // 4 or 1, "--resolution", plan.resolution,
              "--shard-size", 2, "--quiet", "--device", plan.device]
    one = run_command(common + ["--workers", 1, "--out", scratch / "one"], timeout=clock.total_left() / 2)
    many = run_command(common + ["--workers", "2" if plan.dry_run else "auto", "--out", scratch / "many"],
                       timeout=clock.total_left())
    same = (one["returncode"] == 0 and many["returncode"] == 0
            and tree_digest(scratch / "one" / "shards") == tree_digest(scratch / "many" / "shards"))
    return {"gpus": torch.cuda.device_count(), "one_worker": one, "all_workers": many, "identical_shards": same}


def gsplat_section(plan: Plan, clock: Clock, scratch: Path) -> dict:
    """gsplat from the device kit when it is not importable, its first rasterization (the kernel
    build) timed, then its parity test against the pure-PyTorch rasterizer."""
    from benchmarks.device_kit import GSPLAT_DIR, KIT
    env = {}
    if gsplat_version() is None:
        site = scratch / "gsplat-site"
        installed = run_command([sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps",
                                 "--target", site, *sorted((KIT / GSPLAT_DIR).glob("*.whl"))],
                                timeout=clock.total_left())
        if installed["returncode"] != 0:
            raise RuntimeError(f"gsplat is not installed and the kit's wheels did not install:\n{installed['tail']}")
        sys.path.insert(0, str(site))
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")]))
    if plan.dry_run:
        return {"gsplat": gsplat_version(), "build": "not on the CPU: gsplat's kernels are CUDA only"}
    from panolam.rasterizer import rasterize
    from tests.test_rasterizer import camera, random_scene, render
    scene = {k: v.float().cuda() for k, v in random_scene(100, 0).items()}
    view, K = camera(torch.float32)
    t0 = time.perf_counter()
    render(rasterize, scene, view.cuda(), K.cuda(), backend="gsplat")
    device_sync(plan.device)
    return {"gsplat": gsplat_version(), "first_call_s": time.perf_counter() - t0,
            "parity_test": cuda_tests(plan, clock, scratch, select="gsplat", env=env)}


@dataclass(frozen=True)
class Section:
    key: str
    title: str
    needs_s: float  # on a GPU: the least time left that makes the section worth starting
    run: Callable[[Plan, Clock, Path, dict], dict]


SECTIONS = (
    Section("cuda_vs_cpu", "Correctness: CUDA against the CPU", 60, lambda p, c, s, r: cuda_vs_cpu(p, c, s)),
    Section("cuda_tests", "CUDA-only tests", 60, lambda p, c, s, r: cuda_tests(p, c, s)),
    Section("precision", "GAN sampling: fp16 against fp32", 45, lambda p, c, s, r: precision(p, c, s)),
    Section("throughput", "GAN sampling: throughput by memory budget", 60, lambda p, c, s, r: throughput(p, c, s)),
    Section("training", "Training steps", 90, lambda p, c, s, r: train_runs(p, c, s)),
    Section("inference", "Inference", 20,
            lambda p, c, s, r: inference(p, r["sections"].get("training", {}).get("result", {}))),
    Section("workers", "Workers over the visible GPUs", 60, lambda p, c, s, r: workers(p, c, s)),
    Section("gsplat", "gsplat: kernel build and parity", 240, lambda p, c, s, r: gsplat_section(p, c, s)),
)
KEYS = tuple(s.key for s in SECTIONS)


def not_applicable(section: Section, plan: Plan) -> str | None:
    """Why ``section`` has no place in this run, or None."""
    if section.key == "gsplat" and not plan.gsplat:
        return "not asked for: run with --gsplat"
    if section.key == "workers" and not plan.dry_run and torch.cuda.device_count() < 2:
        return f"needs two or more GPUs, {torch.cuda.device_count()} visible"
    return None


def needs_s(section: Section, plan: Plan) -> float:
    """The least time left that makes the section worth starting (any in the dry run)."""
    return 1e-9 if plan.dry_run else section.needs_s


# ------------------------------------------------------------------------------------------------
# Running and reporting


def measure(plan: Plan, command: str, budget_s: float, stem: Path, keys: tuple = KEYS,
            after_section: Callable[[str], None] | None = None) -> dict:
    """The chosen sections in order, the report at ``stem``.{json,md} rewritten after each one
    (then ``after_section(key)`` is called)."""
    clock = Clock(budget_s)
    results = {"command": command, "dry_run": plan.dry_run, "budget_s": budget_s, "planned": list(keys),
               "machine": machine_info(), "environment": environment(), "sections": {}, "complete": False}
    write_report(stem, results, clock)
    chosen = [s for s in SECTIONS if s.key in keys]
    with tempfile.TemporaryDirectory(prefix="gpu_check_") as tmp:
        for i, section in enumerate(chosen):
            clock.reserve_s = sum(needs_s(s, plan) for s in chosen[i + 1:] if not not_applicable(s, plan))
            reason = not_applicable(section, plan)
            if reason is None and clock.total_left() < needs_s(section, plan):
                reason = (f"does not fit the budget: {max(clock.total_left(), 0):.0f} s left, the section needs "
                          f"about {needs_s(section, plan):.0f} s")
            if reason:
                results["sections"][section.key] = {"skipped": reason, "seconds": 0.0}
                print(f"{section.key}: skipped ({reason})", flush=True)
            else:
                run_section(results, section, plan, clock, Path(tmp))
            write_report(stem, results, clock)
            if after_section:
                after_section(section.key)
    results["complete"] = True
    write_report(stem, results, clock)
    return results


def run_section(results: dict, section: Section, plan: Plan, clock: Clock, scratch: Path) -> None:
    """results["sections"][key] = the section's result, or the error it raised; with its seconds."""
    print(f"[{clock.elapsed():4.0f} s] {section.key} ...", flush=True)
    t0 = time.perf_counter()
    try:
        entry = {"result": section.run(plan, clock, scratch, results)}
    except Exception as e:  # a failed section is a finding: record it and go on
        entry = {"error": f"{type(e).__name__}: {e}", "traceback": traceback.format_exc()[-3000:]}
    entry["seconds"] = time.perf_counter() - t0
    results["sections"][section.key] = entry
    print(f"[{clock.elapsed():4.0f} s] {section.key}: {'failed' if 'error' in entry else 'done'} "
          f"in {entry['seconds']:.0f} s", flush=True)


def write_report(stem: Path, results: dict, clock: Clock) -> None:
    """``stem``.json and ``stem``.md, each replaced atomically."""
    results["elapsed_s"] = clock.elapsed()
    stem.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(stem.with_suffix(".json"), (json.dumps(results, indent=1) + "\n").encode())
    atomic_write(stem.with_suffix(".md"), markdown(results).encode())


def _section_lines(section: dict | None, title: str, body) -> list[str]:
    if section is None:
        return ["", f"## {title}", "", "Not run yet."]
    if "skipped" in section:
        return ["", f"## {title}", "", f"Skipped: {section['skipped']}."]
    lines = ["", f"## {title}", "", f"Section time: {section['seconds']:.0f} s."]
    if "error" in section:
        return lines + ["", f"**Failed**: `{section['error']}`", "", "```", section["traceback"].strip(), "```"]
    return lines + [""] + body(section["result"])


def _db(value: float | None) -> str:
    return "identical" if value is None else f"{value:.1f} dB"


def _header(results: dict) -> list[str]:
    env, m = results["environment"], results["machine"]
    gpus = "; ".join(f"{g['name']} ({g['memory_mib']} MiB, {g['sms']} SMs, {g['capability']})" for g in env["gpus"])
    done = [k for k in results["planned"] if k in results["sections"]]
    state = ("complete" if results["complete"] else
             f"**in progress or cut short**: {len(done)} of {len(results['planned'])} sections written")
    return [f"# GPU check{' (dry run on the CPU: the figures mean nothing for a GPU)' if results['dry_run'] else ''}",
            "", f"- GPU: {gpus or 'none (CPU only)'}; driver {env['driver'] or 'unknown'}",
            (f"- torch {env['torch']}, CUDA {env['torch_cuda']}, cuDNN {env['cudnn']}, Python {m['python']}, "
             f"gsplat {env['gsplat'] or 'not installed'}"),
            (f"- {m['date']}, revision {m['git_revision']}, {m['cpu_count']} CPUs ({m['cpu_model']}), load average "
             f"{m['load_average'][0]:.2f} at the start"),
            f"- Budget {results['budget_s']:.0f} s, {results['elapsed_s']:.0f} s used; report {state}.",
            "", "Peak memory: torch's CUDA allocator on a GPU, the process's resident set on a CPU.", ""
            ] + reproduce(results["command"])


def markdown(results: dict) -> str:
    def correctness(r):
        gan = table(["model", "rgb PSNR (dB)", "rgb max diff", "alpha max diff", "depth max diff"],
                    [[k, fmt(v["rgb"]["psnr_db"], 1), f"{v['rgb']['max_abs_diff']:.2e}",
                      f"{v['alpha']['max_abs_diff']:.2e}", f"{v['depth']['max_abs_diff']:.2e}"]
                     for k, v in r["gan"].items()])
        ras = r["rasterizer"]
        return ([f"GAN samplers, one {r['resolution']} px view, fp32:", ""] + gan + [
            "", f"Pure-PyTorch rasterizer, {ras['gaussians']} Gaussians at {ras['size'][0]}x{ras['size'][1]} px:", ""]
            + bullets([f"{k}: PSNR {_db(v['psnr_db'])}, max diff {v['max_abs_diff']:.2e}"
                       for k, v in ras["images"].items()]
                      + ["gradient cosine: " + ", ".join(f"{k} {v:.6f}" for k, v in ras["gradient_cosine"].items())]))

    def tests(r):
        return [f"`{r['command']}` -> exit {r['returncode']}: {r['summary']}"]

    def fp16(r):
        return table(["model", "views", "px", "PSNR fp16 vs fp32 (dB)", "max abs diff", "s fp32", "s fp16"],
                     [[k, v["views"], v["resolution"], fmt(v["psnr_db"], 1), f"{v['max_abs_diff']:.4f}",
                       fmt(v["seconds"]["fp32"]), fmt(v["seconds"]["fp16"])] for k, v in r.items()])

    def speed(r):
        rows = [[v["kind"], v["budget_mb"] or "default", v["precision"], v["plan"]["rays"], v["plan"]["images"],
                 fmt(v["images_per_s"], 1), fmt(v["peak_mb"], 0)] for v in r["rows"].values()]
        left = [f"Left out at the budget: {', '.join(r['left_out'])}."] if r["left_out"] else []
        return table(["model", "budget MiB", "precision", "rays/chunk", "views/SR batch", "images/s", "peak MiB"],
                     rows) + ["", f"Goal: >= {GOAL_IMAGES_PER_S} images/s at 512 px on one H100-class GPU."] + left

    def train_lines(r):
        rows = [[k, v.get("skipped", v.get("steps")), fmt(v.get("median_step_s"), 3) if "steps" in v else "",
                 fmt(1 / v["median_step_s"], 2) if "steps" in v else "", fmt(v["peak_mb"], 0) if "peak_mb" in v else ""]
                for k, v in r.items()]
        return table(["config/rasterizer", "steps", "median s/step", "steps/s", "peak MiB"], rows)

    def infer_lines(r):
        rows = [[k, v["gaussians"], fmt(v["reconstruct_s"], 3), fmt(v["render_ms"], 1), v["render_resolution"]]
                for k, v in r.items()]
        return table(["model", "Gaussians", "s/reconstruction", "ms/render", "render px"], rows) + [
            "", f"Paper (A100): {PAPER_RECONSTRUCT_S} s per reconstruction, {PAPER_RENDER_MS} ms per render."]

    def worker_lines(r):
        return bullets([f"GPUs visible: {r['gpus']}",
                        f"one worker: exit {r['one_worker']['returncode']}, {r['one_worker']['seconds']:.1f} s",
                        f"all workers: exit {r['all_workers']['returncode']}, {r['all_workers']['seconds']:.1f} s",
                        f"shards byte-identical: {r['identical_shards']}"])

    def gsplat_lines(r):
        lines = [f"gsplat {r['gsplat']}"]
        if "first_call_s" in r:
            lines += [f"first rasterization (kernel build): {r['first_call_s']:.0f} s",
                      f"parity test: exit {r['parity_test']['returncode']}: {r['parity_test']['summary']}"]
        else:
            lines.append(r["build"])
        return bullets(lines)

    bodies = {"cuda_vs_cpu": correctness, "cuda_tests": tests, "precision": fp16, "throughput": speed,
              "training": train_lines, "inference": infer_lines, "workers": worker_lines, "gsplat": gsplat_lines}
    lines = _header(results)
    for section in SECTIONS:
        if section.key in results["planned"]:
            lines += _section_lines(results["sections"].get(section.key), section.title, bodies[section.key])
    return "\n".join(lines) + "\n"


def main(argv=None, after_section=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dry-run", action="store_true", help="toy sizes on the CPU: checks the script only")
    parser.add_argument("--budget-s", type=float, default=DEFAULT_BUDGET_S,
                        help=f"seconds for all sections (default {DEFAULT_BUDGET_S}); one that does not fit is skipped")
    parser.add_argument("--gsplat", action="store_true", help="last, install (from the device kit) and compile gsplat")
    parser.add_argument("--out-dir", type=Path, default=REPORTS, help="where the report goes")
    parser.add_argument("--sections", default=",".join(KEYS), help=f"comma-separated subset of {','.join(KEYS)}")
    args = parser.parse_args(argv)
    keys = tuple(s for s in args.sections.split(",") if s)
    unknown = [s for s in keys if s not in KEYS]
    if unknown:
        parser.error(f"unknown section(s) {', '.join(unknown)}; choose from {', '.join(KEYS)}")
    if not args.dry_run and not torch.cuda.is_available():
        print("gpu_check: no CUDA device here; use --dry-run to check the script on the CPU", file=sys.stderr)
        return 2
    stem = args.out_dir / (f"{NAME}_dry_run" if args.dry_run else NAME)
    results = measure(Plan(args.dry_run, args.gsplat), command_line(Path(__file__), argv), args.budget_s, stem, keys,
                      after_section)
    print(f"wrote {stem}.md")
    failed = [k for k, v in results["sections"].items() if "error" in v]
    if failed:
        print(f"gpu_check: sections failed: {', '.join(failed)} (see the report)", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
