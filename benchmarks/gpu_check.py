"""The GPU acceptance check: every GPU path of the toolkit run and measured once, in one script.

Writes ``benchmarks/reports/gpu_check.{json,md}`` (``gpu_check_dry_run.*`` with ``--dry-run``).

    python -m benchmarks.gpu_check              # on a CUDA machine (sized for under 8 min on one H100/H200)
    python -m benchmarks.gpu_check --dry-run    # the same sections at toy sizes on the CPU (~1 min, 2 cores)
    python -m benchmarks.gpu_check --sections gan_precision,gan_throughput   # some sections only

Sections (each one is timed; a failure is recorded with its error and the next section runs):

1. ``cuda_tests``: the tests marked ``cuda`` (``python -m pytest -m cuda``), skipped elsewhere.
2. ``gan_precision``: the three production-SR fixtures (``shared/fixtures/gan-sr``: 8XDC, 512 px
   from a 128 px neural render) sampled in fp32 and in fp16 on the device: PSNR of fp16 against
   fp32 and their seconds.
3. ``gan_throughput``: the released-size generators (random weights, sizes as released) at several
   memory budgets: 512 px images per second over 32-view subjects, the chunk plan, peak memory.
4. ``workers``: ``datagen sample --workers auto --device cuda`` over the visible GPUs against one
   worker: seconds and whether the two datasets are byte-identical.
5. ``training``: ``tiny`` and ``full`` (DINOv2 ViT-L/14 shape with random weights, saved and
   loaded as a Hugging Face folder) for a few optimizer steps with gsplat and with the pure-PyTorch
   rasterizer: median seconds per step and peak memory.
6. ``inference``: one reconstruction and one 512 px render of the trained models (the paper,
   A100: 0.11 s per reconstruction, 3.6 ms per render).

``--dry-run`` runs the same code on the CPU with the tiny GAN fixtures, 2 views, 64 px, two
training steps of ``tiny``; it checks the script, and its figures mean nothing for a GPU.
"""
from __future__ import annotations

import argparse
import hashlib
import importlib.util
import os
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import (REPO, REPORTS, bullets, command_line, device_sync, fmt, machine_info,
                               memory_peak, memory_start, psnr_db, reproduce, table, write_report)
from benchmarks.gan_fullsize import PROTOCOL, build
from datagen.cameras import sample_views
from datagen.generators.base import STREAM_CAMERAS, subject_rng
from datagen.generators.gan import GANConfig, GANHeads
from datagen.gans.checkpoint import read_checkpoint
from datagen.gans.kinds import KINDS

NAME = "gpu_check"
SHARED = Path(os.environ.get("PANOLAM_SHARED", REPO.parent / "shared"))
PAPER_RECONSTRUCT_S, PAPER_RENDER_MS = 0.11, 3.6  # A100, the paper
GOAL_IMAGES_PER_S = 200  # 512 px, one H100-class GPU


class Plan:
    """Sizes of one run: the GPU's, or the dry run's toy sizes on the CPU."""

    def __init__(self, dry_run: bool):
        self.dry_run = dry_run
        self.device = "cpu" if dry_run else "cuda"
        self.fixture_set = "gan" if dry_run else "gan-sr"  # the dry run's SR is the tiny 2X
        self.views = 2 if dry_run else 32
        self.precision_views = 2 if dry_run else 8
        self.resolution = 64 if dry_run else 512
        self.subjects_timed = 1 if dry_run else 2
        self.budgets_mb = (16, 64) if dry_run else (1024, 4096, 16384, 0)
        self.worker_subjects = 2 if dry_run else 16
        self.configs = ("tiny",) if dry_run else ("tiny", "full")
        self.rasterizers = ("torch",) if dry_run else ("gsplat", "torch")
        self.train_steps = 2 if dry_run else 50
        self.train_subjects = 4 if dry_run else 16


# ------------------------------------------------------------------------------------------------
# Measuring helpers


def gsplat_version() -> str | None:
    if importlib.util.find_spec("gsplat") is None:
        return None
    import gsplat
    return getattr(gsplat, "__version__", "installed")


def run_command(args: list, timeout: float) -> dict:
    """A command's exit status, seconds and the tail of its output."""
    t0 = time.perf_counter()
    done = subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=timeout, cwd=REPO)
    return {"command": " ".join(str(a) for a in args), "returncode": done.returncode,
            "seconds": time.perf_counter() - t0, "tail": (done.stdout + done.stderr)[-1500:]}


def tree_digest(root: Path) -> str:
    """SHA-256 over every file's relative path and bytes under ``root``."""
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def fixture(kind: str, plan: Plan) -> Path:
    tag = "sr" if plan.fixture_set == "gan-sr" else "tiny"
    path = SHARED / "fixtures" / plan.fixture_set / kind / f"{kind}-{tag}.pkl"
    if not path.exists():
        raise FileNotFoundError(f"{path} not found (set PANOLAM_SHARED to the shared/ folder)")
    return path


def environment() -> dict:
    info = {"torch": torch.__version__, "torch_cuda": torch.version.cuda, "cuda_available": torch.cuda.is_available(),
            "gsplat": gsplat_version()}
    if torch.cuda.is_available():
        info["gpus"] = [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())]
        info["gpu_memory_gb"] = torch.cuda.get_device_properties(0).total_memory / 1e9
    return info


# ------------------------------------------------------------------------------------------------
# Sections


def cuda_tests(plan: Plan) -> dict:
    """The CUDA-only tests (marked ``cuda``); on a CPU they are all skipped."""
    result = run_command([sys.executable, "-m", "pytest", "-m", "cuda", "-q", "-p", "no:cacheprovider", "-rs",
                          "tests"], timeout=300)
    lines = [line for line in result["tail"].splitlines() if line.strip()]
    result["summary"] = lines[-1] if lines else ""
    result["ok"] = result["returncode"] in (0, 5)  # 5: none collected
    return result


def _render_subject(heads: GANHeads, index: int, views: int, resolution: int):
    cams = sample_views(PROTOCOL[heads.name], subject_rng(0, index, STREAM_CAMERAS), views)
    return heads.render(heads.sample_subject(0, index), cams, resolution)


def gan_precision(plan: Plan) -> dict:
    """fp16 against fp32 on the production-SR fixtures: PSNR of the images, seconds of each."""
    rows = {}
    for kind in KINDS:
        loaded = read_checkpoint(fixture(kind, plan), kind)
        images, seconds = {}, {}
        for precision in ("fp32", "fp16"):
            heads = GANHeads(kind, loaded, GANConfig(device=plan.device, precision=precision))
            _render_subject(heads, 0, 1, plan.resolution)  # warm-up
            device_sync(plan.device)
            t0 = time.perf_counter()
            images[precision] = _render_subject(heads, 1, plan.precision_views, plan.resolution).rgb
            seconds[precision] = time.perf_counter() - t0
        diff = images["fp16"].astype(np.float64) - images["fp32"]
        rows[kind] = {"psnr_fp16_vs_fp32_db": psnr_db(float(np.mean(diff ** 2))),
                      "max_abs_diff": float(np.abs(diff).max()), "seconds": seconds,
                      "views": plan.precision_views, "resolution": plan.resolution}
    return rows


def gan_throughput(plan: Plan) -> dict:
    """Images per second at each memory budget (released sizes on a GPU, tiny fixtures in the dry run)."""
    rows = {}
    for kind in KINDS:
        loaded = read_checkpoint(fixture(kind, plan), kind) if plan.dry_run else build(kind, plan.device).checkpoint
        for budget in plan.budgets_mb:
            heads = GANHeads(kind, loaded, GANConfig(device=plan.device, memory_budget_mb=budget))
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
        del heads, loaded
        if plan.device.startswith("cuda"):
            torch.cuda.empty_cache()
    return rows


def workers(plan: Plan, scratch: Path) -> dict:
    """``--workers auto`` over the visible GPUs against one worker: time and identical bytes."""
    common = ["datagen", "sample", "--gan", "spherehead", "--checkpoint", fixture("spherehead", plan),
              "--protocol", "360", "--subjects", plan.worker_subjects, "--views", plan.views // 4 or 1,
              "--resolution", plan.resolution, "--shard-size", 2, "--quiet", "--device", plan.device]
    one = run_command(common + ["--workers", 1, "--out", scratch / "one"], timeout=600)
    many = run_command(common + ["--workers", "2" if plan.dry_run else "auto", "--out", scratch / "many"],
                       timeout=600)
    same = (one["returncode"] == 0 and many["returncode"] == 0
            and tree_digest(scratch / "one" / "shards") == tree_digest(scratch / "many" / "shards"))
    return {"gpus": torch.cuda.device_count(), "one_worker": one, "all_workers": many, "identical_shards": same}


def _training_data(plan: Plan, scratch: Path) -> tuple[Path, Path]:
    from datagen.pipeline import JobSpec, run_sample, software_info
    from labeling_tool.manifest import compile_manifest, write_manifest
    data = scratch / "train_data"
    spec = JobSpec(out=str(data), gan="procedural", generator_options={}, protocol="360",
                   subjects=plan.train_subjects, resolution=128, views=8, seed=0, shard_size=4,
                   software=software_info())
    run_sample(spec, workers=min(8, os.cpu_count() or 1), progress=False)
    (scratch / "labels").mkdir(exist_ok=True)
    manifest = write_manifest(compile_manifest(data, scratch / "labels", test_count=2), scratch / "manifest.json")
    return data, manifest


def _random_dinov2(scratch: Path) -> Path:
    """A DINOv2 ViT-L/14 with random weights as a Hugging Face folder (what a user passes)."""
    from transformers import Dinov2Config, Dinov2Model
    folder = scratch / "dinov2-vitl14-random"
    if not folder.exists():
        torch.manual_seed(0)
        Dinov2Model(Dinov2Config(hidden_size=1024, num_hidden_layers=24, num_attention_heads=16,
                                 intermediate_size=4096, patch_size=14, image_size=518)).save_pretrained(folder)
    return folder


def training(plan: Plan, scratch: Path) -> dict:
    """A few optimizer steps per config and rasterizer: median s/step (first two steps left out), peak memory."""
    from panolam.checkpoints import read_checkpoint as read_run
    from panolam.config import TrainConfig, preset
    from panolam.train import train
    data, manifest = _training_data(plan, scratch)
    rows = {}
    for config in plan.configs:
        overrides = {"encoder_weights": str(_random_dinov2(scratch))} if config == "full" else {}
        for rasterizer in plan.rasterizers:
            key = f"{config}/{rasterizer}"
            if rasterizer == "gsplat" and gsplat_version() is None:
                rows[key] = {"skipped": "gsplat is not installed (pip install -e '.[cuda]')"}
                continue
            out = scratch / "runs" / key.replace("/", "-")
            cfg = TrainConfig(steps=plan.train_steps, warmup_steps=1, checkpoint_every=plan.train_steps,
                              rasterizer=rasterizer)
            memory_start(plan.device)
            t0 = time.perf_counter()
            train(data, manifest, preset(config, **overrides), cfg, out, device=plan.device, progress=False)
            wall = time.perf_counter() - t0
            steps = [e["seconds"] for e in read_run(out)["history"]]
            rows[key] = {"steps": len(steps), "median_step_s": statistics.median(steps[2:] or steps),
                         "wall_s": wall, "peak_mb": memory_peak(plan.device), "run": str(out)}
    return rows


def inference(plan: Plan, trained: dict) -> dict:
    """Seconds per reconstruction and ms per 512 px render of each trained model (median of 10)."""
    from panolam.checkpoints import load_model
    from panolam.infer import reconstruct, render_set, turntable_views
    image = np.random.default_rng(0).random((512, 512, 3), dtype=np.float32)
    rows = {}
    for key, row in trained.items():
        if "run" not in row:
            continue
        model = load_model(row["run"], plan.device)
        reconstruct(model, image)  # warm-up
        seconds = [reconstruct(model, image)[1] for _ in range(3 if plan.dry_run else 10)]
        g, _ = reconstruct(model, image)
        view = turntable_views(1)
        render_set(g, view, plan.resolution)
        renders = []
        for _ in range(3 if plan.dry_run else 10):
            device_sync(plan.device)
            t0 = time.perf_counter()
            render_set(g, view, plan.resolution)
            device_sync(plan.device)
            renders.append(time.perf_counter() - t0)
        rows[key] = {"reconstruct_s": statistics.median(seconds), "render_ms": 1e3 * statistics.median(renders),
                     "gaussians": int(g.means.shape[0]), "render_resolution": plan.resolution}
    return rows


# ------------------------------------------------------------------------------------------------
# Running and reporting


def run_section(results: dict, key: str, fn) -> None:
    """results[key] = fn(), or the error it raised; with its seconds."""
    print(f"{key} ...", flush=True)
    t0 = time.perf_counter()
    try:
        results[key] = {"result": fn()}
    except Exception as e:  # a failed section is a finding: record it and go on
        results[key] = {"error": f"{type(e).__name__}: {e}", "traceback": traceback.format_exc()[-3000:]}
    results[key]["seconds"] = time.perf_counter() - t0
    print(f"{key}: {'failed' if 'error' in results[key] else 'done'} in {results[key]['seconds']:.0f} s", flush=True)


SECTIONS = ("cuda_tests", "gan_precision", "gan_throughput", "workers", "training", "inference")


def measure(plan: Plan, command: str, sections: tuple = SECTIONS) -> dict:
    """The chosen sections, in order (inference times the models that training wrote)."""
    results = {"command": command, "dry_run": plan.dry_run, "machine": machine_info(),
               "environment": environment()}
    with tempfile.TemporaryDirectory(prefix="gpu_check_") as tmp:
        scratch = Path(tmp)
        runners = {"cuda_tests": lambda: cuda_tests(plan), "gan_precision": lambda: gan_precision(plan),
                   "gan_throughput": lambda: gan_throughput(plan), "workers": lambda: workers(plan, scratch),
                   "training": lambda: training(plan, scratch),
                   "inference": lambda: inference(plan, results.get("training", {}).get("result", {}))}
        for key in sections:
            run_section(results, key, runners[key])
    return results


def _section_lines(results: dict, key: str, title: str, body) -> list[str]:
    section = results.get(key)
    if section is None:
        return []
    lines = ["", f"## {title}", "", f"Section time: {section['seconds']:.0f} s."]
    if "error" in section:
        return lines + ["", f"**Failed**: `{section['error']}`", "", "```", section["traceback"].strip(), "```"]
    return lines + [""] + body(section["result"])


def markdown(results: dict) -> str:
    env, m = results["environment"], results["machine"]
    where = ", ".join(env.get("gpus", [])) or "no GPU (CPU only)"
    lines = [f"# GPU check{' (dry run on the CPU: the figures mean nothing for a GPU)' if results['dry_run'] else ''}",
             "", f"Date {m['date']}, revision {m['git_revision']}, on {where}; torch {env['torch']} "
                 f"(CUDA {env['torch_cuda']}), gsplat {env['gsplat'] or 'not installed'}; load average "
                 f"{m['load_average'][0]:.2f} at the start. Peak memory: torch's CUDA allocator on a GPU, the "
                 f"process's resident set on a CPU.", ""] + reproduce(results["command"])

    def tests(r):
        return [f"`{r['command']}` -> exit {r['returncode']}: {r['summary']}"]

    def precision(r):
        return table(["model", "views", "px", "PSNR fp16 vs fp32 (dB)", "max abs diff", "s fp32", "s fp16"],
                     [[k, v["views"], v["resolution"], fmt(v["psnr_fp16_vs_fp32_db"], 1), f"{v['max_abs_diff']:.4f}",
                       fmt(v["seconds"]["fp32"]), fmt(v["seconds"]["fp16"])] for k, v in r.items()])

    def throughput(r):
        rows = [[v["kind"], v["budget_mb"] or "default", v["precision"], v["plan"]["rays"], v["plan"]["images"],
                 fmt(v["images_per_s"], 1), fmt(v["peak_mb"], 0)] for v in r.values()]
        return table(["model", "budget MiB", "precision", "rays/chunk", "views/SR batch", "images/s", "peak MiB"],
                     rows) + ["", f"Goal: >= {GOAL_IMAGES_PER_S} images/s at 512 px on one H100-class GPU."]

    def worker_lines(r):
        return bullets([f"GPUs visible: {r['gpus']}",
                        f"one worker: exit {r['one_worker']['returncode']}, {r['one_worker']['seconds']:.1f} s",
                        f"all workers: exit {r['all_workers']['returncode']}, {r['all_workers']['seconds']:.1f} s",
                        f"shards byte-identical: {r['identical_shards']}"])

    def train_lines(r):
        rows = [[k, v.get("skipped", v.get("steps")), fmt(v.get("median_step_s"), 3) if "steps" in v else "",
                 fmt(v["peak_mb"], 0) if "peak_mb" in v else ""] for k, v in r.items()]
        return table(["config/rasterizer", "steps", "median s/step", "peak MiB"], rows)

    def infer_lines(r):
        rows = [[k, v["gaussians"], fmt(v["reconstruct_s"], 3), fmt(v["render_ms"], 1), v["render_resolution"]]
                for k, v in r.items()]
        return table(["model", "Gaussians", "s/reconstruction", "ms/render", "render px"], rows) + [
            "", f"Paper (A100): {PAPER_RECONSTRUCT_S} s per reconstruction, {PAPER_RENDER_MS} ms per render."]

    for key, title, body in (("cuda_tests", "CUDA-only tests", tests),
                             ("gan_precision", "GAN sampling: fp16 against fp32", precision),
                             ("gan_throughput", "GAN sampling: throughput by memory budget", throughput),
                             ("workers", "Workers over the visible GPUs", worker_lines),
                             ("training", "Training steps", train_lines),
                             ("inference", "Inference", infer_lines)):
        lines += _section_lines(results, key, title, body)
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dry-run", action="store_true", help="toy sizes on the CPU: checks the script only")
    parser.add_argument("--out-dir", type=Path, default=REPORTS, help="where the report goes")
    parser.add_argument("--sections", default=",".join(SECTIONS),
                        help=f"comma-separated, in order (default all: {','.join(SECTIONS)}); inference needs training")
    args = parser.parse_args(argv)
    sections = tuple(s for s in args.sections.split(",") if s)
    unknown = [s for s in sections if s not in SECTIONS]
    if unknown:
        parser.error(f"unknown section(s) {', '.join(unknown)}; choose from {', '.join(SECTIONS)}")
    if not args.dry_run and not torch.cuda.is_available():
        print("gpu_check: no CUDA device here; use --dry-run to check the script on the CPU", file=sys.stderr)
        return 2
    results = measure(Plan(args.dry_run), command_line(Path(__file__), argv), sections)
    write_report(args.out_dir / (f"{NAME}_dry_run" if args.dry_run else NAME), results, markdown(results))
    failed = [k for k, v in results.items() if isinstance(v, dict) and "error" in v]
    if failed:
        print(f"gpu_check: sections failed: {', '.join(failed)} (see the report)", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
