"""Seconds per training step of PanoLAM ``tiny`` on the CPU: the recipe before and after, side by side.

    python -m benchmarks.train_step            # about 5 minutes on 2 quiet cores
    python -m benchmarks.train_step --rounds 1 # a quicker look

Writes ``benchmarks/reports/train_step.{json,md}``. One step is what :func:`panolam.train.train`
does per batch: forward, the paper's losses over the rendered views (:func:`panolam.train.compute_losses`),
backward and Adam, on a synthetic batch of the run's shape (random images and masks at the render
resolution, 360-protocol cameras; the cost does not depend on the pixels). The variants run in
one process, interleaved round by round after a warm-up step each, so the machine's load hits
them alike; medians of ``time.perf_counter``. Stage times come from wrapping the encoder, the tri-plane tokens, the ray aggregation, the tri-plane branch's volume
render and the Gaussian renders (forward only: autograd's backward is counted in "backward + Adam").
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from benchmarks.common import REPORTS, load_average, machine_info, stage_clock, table, write_report
from datagen.cameras import sample_views
from panolam import train as train_module
from panolam.config import LEGACY_TRAINING, TrainConfig, preset
from panolam.data import Views
from panolam.model import PanoLAM

NAME = "train_step"
# name: (what it is, model overrides of the tiny preset, training settings)
VARIANTS = {
    "before": ("`tiny` as it was: K_m = 8, targets the 5 other views", {"ray_samples": 8}, dict(LEGACY_TRAINING)),
    "k2_others": ("K_m = 2 alone (targets the 5 other views)", {}, {"targets": "others"}),
    "after": ("`tiny` now: K_m = 2, the input view among the 6 targets", {}, {}),
    "after_point": ("for scale: no ray aggregation (`single_point` ablation)", {"triplane": "point"}, {}),
}
STAGES = ("encoder", "triplane_tokens", "ray_aggregation", "triplane_render", "gaussian_renders")


class Stepper:
    """One variant: its model, optimizer and a fixed synthetic batch; ``step()`` returns (seconds, stage seconds)."""

    def __init__(self, overrides: dict, settings: dict, seed: int = 0, config: str = "tiny"):
        self.cfg = TrainConfig(**settings)
        torch.manual_seed(seed)
        self.model = PanoLAM(preset(config, **overrides))
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=self.cfg.lr, betas=self.cfg.betas)
        self.perceptual = train_module.Perceptual(self.cfg, "cpu")
        b, v, r, size = self.cfg.batch_size, self.cfg.views_per_sample, self.cfg.render_resolution, self.model.cfg.image_size
        rng = np.random.default_rng(seed)
        views = [sample_views("360", rng, v) for _ in range(b)]
        cams = lambda key: torch.stack([torch.from_numpy(getattr(s, key)).float() for s in views])  # noqa: E731
        g = torch.Generator().manual_seed(seed)
        self.batch = Views("synthetic", torch.rand(b, v, 3, r, r, generator=g), torch.rand(b, v, 1, r, r, generator=g),
                           cams("cam2world"), cams("K"), torch.zeros(b, v), torch.full((b, v), 2.7), None,
                           torch.rand(b, 3, size, size, generator=g))

    def step(self) -> tuple[float, dict]:
        m = self.model
        stages = {"encoder": (m.encoder, "forward"), "triplane_tokens": (m.triplane, "forward"),
                  "ray_aggregation": (m, "aggregate_triplane"), "triplane_render": (m, "render_triplane"),
                  "gaussian_renders": (train_module, "render_views")}
        t0, c0 = time.perf_counter(), time.process_time()
        with stage_clock(stages) as seconds:
            loss, _, _ = train_module.compute_losses(m, self.batch, self.cfg, self.perceptual)
        t1 = time.perf_counter()
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        t2 = time.perf_counter()
        return t2 - t0, {**seconds, "backward_adam": t2 - t1, "cpu": time.process_time() - c0}


def interleaved(steppers: dict[str, Stepper], rounds: int) -> dict[str, list[tuple[float, dict]]]:
    """``rounds`` steps of every stepper, one of each per round after a warm-up step each, so that the machine's
    load hits them alike: name -> [Stepper.step() of each round]."""
    for s in steppers.values():
        s.step()  # warm-up
    runs = {name: [] for name in steppers}
    for _ in range(rounds):
        for name, s in steppers.items():
            runs[name].append(s.step())
    return runs


def measure(rounds: int, threads: int) -> dict:
    torch.set_num_threads(threads)
    results = {"machine": machine_info(), "rounds": rounds, "threads": threads, "load_before": load_average(), "variants": {}}
    steppers = {name: Stepper(o, s) for name, (_, o, s) in VARIANTS.items()}
    for name, rows in interleaved(steppers, rounds).items():
        what, overrides, settings = VARIANTS[name]
        results["variants"][name] = {
            "what": what, "overrides": overrides, "settings": settings, "seconds": [t for t, _ in rows],
            "median_s": statistics.median(t for t, _ in rows),
            "stages_median_s": {k: statistics.median(st[k] for _, st in rows) for k in (*STAGES, "backward_adam")},
            "cpu_median_s": statistics.median(st["cpu"] for _, st in rows)}
    results["profile_after"] = profile(steppers["after"])
    results["load_after"] = load_average()
    return results


def profile(stepper: Stepper, top: int = 10) -> dict:
    """One step under torch.profiler: the operators with the most self CPU time (ms) and the step's total."""
    from torch.profiler import ProfilerActivity, profile as torch_profile
    with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
        stepper.step()
    ops = sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)
    return {"total_ms": sum(e.self_cpu_time_total for e in ops) / 1000,
            "top": [{"op": e.key, "self_ms": e.self_cpu_time_total / 1000, "calls": e.count} for e in ops[:top]]}


def markdown(results: dict, command: str) -> str:
    v = results["variants"]
    m = results["machine"]
    lines = ["# PanoLAM `tiny`: seconds per training step, before and after", "",
             f"Machine: {m['cpu_model']}, torch {m['torch']}, {results['threads']} thread(s), {m['date']}. 1-minute load average "
             f"{results['load_before']:.2f} before and {results['load_after']:.2f} after (2 cores: above ~2 other work "
             f"competed, so compare the variants' ratios, measured side by side, rather than their seconds). Batch: "
             "2 subjects x 6 views at 64 px, the model's input at 128 px; D-SSIM as the perceptual term. "
             f"{results['rounds']} interleaved rounds after a warm-up step each; medians.", "",
             "```bash", command, "```", ""]
    before, cpu = v["before"]["median_s"], v["before"]["cpu_median_s"]
    rows = [[f"{n}: {x['what']}", f"{x['median_s']:.2f}", f"{before / x['median_s']:.2f}x", f"{x['cpu_median_s']:.2f}",
             f"{cpu / x['cpu_median_s']:.2f}x", *(f"{x['stages_median_s'][k]:.2f}" for k in (*STAGES, "backward_adam"))]
            for n, x in v.items()]
    lines += table(["variant", "wall s/step", "speed-up", "CPU s/step", "CPU speed-up", *(f"{k} s" for k in STAGES),
                    "backward + Adam s"], rows)
    lines += ["", "Stage columns are forward wall times; the backward pass of every stage is in the last column. "
                  "CPU seconds (``time.process_time``, all threads) count the work done and are less sensitive "
                  "to other processes than wall time.", ""]
    prof = results.get("profile_after")
    if prof:
        lines += [f"Where the `after` step's time goes (one step under torch.profiler, {prof['total_ms']:.0f} ms of "
                  "self CPU time in all; attention is the point and tri-plane blocks, `mm`/`addmm` their "
                  "projections and MLPs, the many small elementwise calls mostly the pure-PyTorch rasterizer):", "",
                  *table(["operator", "self ms", "share", "calls"],
                         [[f"`{o['op'][:60]}`", f"{o['self_ms']:.0f}", f"{o['self_ms'] / prof['total_ms']:.0%}",
                           o["calls"]] for o in prof["top"]])]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3, help="timed steps per variant (default 3)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    args = parser.parse_args(argv)
    command = "python -m benchmarks.train_step" + "".join(
        f" --{k} {getattr(args, k)}" for k, d in (("rounds", 3), ("threads", 2)) if getattr(args, k) != d)
    results = measure(args.rounds, args.threads)
    write_report(REPORTS / NAME, results, markdown(results, command))


if __name__ == "__main__":
    main()
