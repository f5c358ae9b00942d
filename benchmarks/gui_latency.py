"""Review-GUI latency: opening a 1,000-subject shard and moving to the next subject.

Builds a valid 1,000-subject dataset quickly by rendering a few procedural subjects and repeating
their bytes under new subject ids (the GUI's cost does not depend on the picture), then opens the
review window off-screen and times: open (index + first subject shown and drawn), next subject
(key press -> textures swapped -> frame drawn), and the 3D toggle. Every frame is really drawn
(``render_window.Render()``), not deferred.

    python benchmarks/gui_latency.py [--subjects 1000] [--resolution 128] [--window 1600x900]

Writes benchmarks/reports/gui_latency.md and .json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import torch

from datagen.pipeline import JobSpec, make_index, run_sample, software_info
from datagen.files import atomic_write  # noqa: E402
from datagen.shards import INDEX_NAME, ShardWriter, dumps, iter_tar_samples, read_index, subject_id

REPORTS = Path(__file__).resolve().parent / "reports"


def build_dataset(root: Path, subjects: int, resolution: int, distinct: int = 4) -> Path:
    """A one-shard dataset of ``subjects`` subjects, repeating ``distinct`` rendered ones."""
    seed_dir = root / "seed"
    spec = JobSpec(out=str(seed_dir), subjects=distinct, resolution=resolution, shard_size=distinct,
                   software=software_info())
    run_sample(spec, progress=False)
    samples = list(iter_tar_samples(seed_dir / "shard-000000.tar"))
    out = root / "big"
    out.mkdir()
    writer = ShardWriter(out, 0)
    for i in range(subjects):
        old_key, fields = samples[i % distinct]
        key = subject_id(i)
        meta = json.loads(fields["json"])
        meta.update(subject_id=key, subject_index=i)
        members = [(f"{key}.json", dumps(meta))] + [(f"{key}.{f}", b) for f, b in fields.items() if f != "json"]
        writer.add_subject(key, members)
    writer.commit()
    big = JobSpec(out=str(out), subjects=subjects, resolution=resolution, shard_size=subjects, software=spec.software)
    atomic_write(out / INDEX_NAME, dumps(make_index(big, read_index(seed_dir)["generator"])))
    return out


def measure(dataset: Path, window, repeats: int) -> dict:
    from labeling_tool.gui import QueueItem, ReviewApp

    labels = Path(tempfile.mkdtemp())
    t0 = time.perf_counter()
    queue = [QueueItem(s, sh["name"]) for sh in read_index(dataset)["shards"] for s in sh["subjects"]]
    app = ReviewApp(dataset, queue, "bench", labels, off_screen=True, window_size=window)
    app.plotter.render_window.Render()
    open_s = time.perf_counter() - t0
    nxt, toggle = [], []
    for _ in range(repeats):
        t = time.perf_counter()
        app.press("Right")
        app.plotter.render_window.Render()
        nxt.append(time.perf_counter() - t)
    for _ in range(3):
        t = time.perf_counter()
        app.press("v")
        app.plotter.render_window.Render()
        toggle.append(time.perf_counter() - t)
        app.press("v")
    verdict = []
    for _ in range(repeats):
        t = time.perf_counter()
        app.press("g")  # verdict: log append + fsync + next subject + draw
        app.plotter.render_window.Render()
        verdict.append(time.perf_counter() - t)
    app.close()
    return {"open_s": open_s, "next_ms": [1e3 * x for x in nxt], "verdict_ms": [1e3 * x for x in verdict],
            "view3d_ms": [1e3 * x for x in toggle], "queue": len(queue)}


def report(result: dict, args) -> str:
    med = {k: statistics.median(result[k]) for k in ("next_ms", "verdict_ms", "view3d_ms")}
    lines = [
        "# Review GUI latency",
        "",
        f"Command: `python benchmarks/gui_latency.py --subjects {args.subjects} --resolution {args.resolution} "
        f"--window {args.window}`",
        f"Machine: {os.cpu_count()} cores, torch {torch.__version__} ({torch.get_num_threads()} threads), "
        f"{platform.platform()}, load average {os.getloadavg()[0]:.1f}; off-screen software OpenGL.",
        "",
        f"Dataset: one shard of {result['queue']} subjects x 32 views at {args.resolution} px.",
        "",
        "| what | median | goal |",
        "|---|---|---|",
        f"| open the shard (index, first subject decoded, first frame drawn) | {result['open_s']:.2f} s | < 2 s |",
        f"| next subject (key -> textures swapped -> frame drawn) | {med['next_ms']:.0f} ms | < 200 ms |",
        f"| verdict key (event fsynced, next subject drawn) | {med['verdict_ms']:.0f} ms | < 200 ms |",
        f"| 3D point-cloud view on | {med['view3d_ms']:.0f} ms | - |",
        "",
        f"Open goal met: {'yes' if result['open_s'] < 2 else 'no'}; next-subject goal met: "
        f"{'yes' if med['next_ms'] < 200 and med['verdict_ms'] < 200 else 'no'}.",
        f"(next subject: min {min(result['next_ms']):.0f} ms, max {max(result['next_ms']):.0f} ms over "
        f"{len(result['next_ms'])} moves)",
    ]
    return "\n".join(lines) + "\n"


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--subjects", type=int, default=1000)
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--window", default="1600x900")
    p.add_argument("--repeats", type=int, default=20)
    args = p.parse_args()
    window = tuple(int(v) for v in args.window.split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        dataset = build_dataset(Path(tmp), args.subjects, args.resolution)
        result = measure(dataset, window, args.repeats)
    result.update(args=vars(args), loadavg=os.getloadavg())
    REPORTS.mkdir(exist_ok=True)
    (REPORTS / "gui_latency.json").write_text(json.dumps(result, indent=1))
    text = report(result, args)
    (REPORTS / "gui_latency.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
