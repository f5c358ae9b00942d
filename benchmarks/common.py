"""What every benchmark script shares: machine description, memory readings, child processes, command line,
report files and markdown pieces."""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

from datagen.cameras import ViewSet
from datagen.pipeline import software_info
from datagen.threads import usable_cpus

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
REPORTS = HERE / "reports"


# ------------------------------------------------------------------------------------------------
# The machine and its load


def machine_info() -> dict:
    """CPU, software versions, torch threads, git revision, load average and date of a measurement."""
    cpu = {}  # the first processor's /proc/cpuinfo fields
    for line in Path("/proc/cpuinfo").read_text().splitlines() if Path("/proc/cpuinfo").exists() else []:
        key, _, value = line.partition(":")
        if not key.strip():
            break
        cpu.setdefault(key.strip(), value.strip())
    usable = usable_cpus()
    return {"cpu_model": cpu.get("model name") or platform.processor() or "unknown",
            # hosts sold under one name differ: the family/model and the vector instructions torch uses tell them apart
            "cpu_family_model": f"family {cpu['cpu family']} model {cpu['model']}" if "cpu family" in cpu else None,
            "cpu_capability": torch.backends.cpu.get_cpu_capability(), "cpu_count": os.cpu_count(),
            "usable_cpus": usable, "platform": platform.platform(), "python": platform.python_version(),
            "numpy": np.__version__, "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
            "torch_interop_threads": torch.get_num_interop_threads(),
            "git_revision": software_info()["git_revision"], "load_average": list(os.getloadavg()),
            "nice": os.nice(0),
            "date": datetime.now(timezone.utc).isoformat(timespec="seconds")}


def injected_defects(root: Path) -> dict[str, list[str]]:
    """subject -> the defect types injected into it, from a dataset's hidden ``truth/`` (only benchmarks read it)."""
    truth = {}
    for f in sorted((root / "truth").glob("*.json")):
        for key, val in json.loads(f.read_text()).items():
            truth[key] = [d["type"] for d in val.get("defects", [])]
    return truth


def equator_views(yaw) -> ViewSet:
    """Views at these yaws (degrees) on the equator at radius 2.7 and FOV 18.837 (EG3D's), looking at the origin."""
    n = len(yaw)
    return ViewSet("equator", np.asarray(yaw, float), np.zeros(n), np.full(n, 2.7), np.full(n, 18.837), (0.0, 0.0, 0.0))


def load_average() -> float | None:
    """1-minute load average (None where the platform has none)."""
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else None


def rss_mb() -> float:
    """Current resident set size (MiB), from /proc/self/statm."""
    return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20


def reset_peak_rss() -> float:
    """Reset this process's peak resident set size to its current one (Linux clear_refs); returns that, MiB."""
    Path("/proc/self/clear_refs").write_text("5")
    return rss_mb()


def peak_rss_since_reset_mb() -> float:
    """Peak resident set size (VmHWM, MiB) since the last :func:`reset_peak_rss`."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return peak_rss_mb()


def device_sync(device: str) -> None:
    """Wait for the device's queued work (CUDA), so that a clock reading after it is the work's."""
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def memory_start(device: str) -> float:
    """Reset the peak-memory reading of ``device`` (CUDA: torch's allocator; CPU: this process's
    resident set); the memory in use now, MiB."""
    if device.startswith("cuda"):
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        return torch.cuda.memory_allocated() / 2 ** 20
    return reset_peak_rss()


def memory_peak(device: str) -> float:
    """Peak memory since :func:`memory_start`, MiB."""
    return torch.cuda.max_memory_allocated() / 2 ** 20 if device.startswith("cuda") else peak_rss_since_reset_mb()


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far (MiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux


# ------------------------------------------------------------------------------------------------
# Measuring


def median(values) -> float:
    return float(statistics.median(values))


def psnr_db(mse: float) -> float | None:
    """PSNR in dB of a mean squared error of values in [0, 1]; None when the images are identical."""
    return 10.0 * float(np.log10(1.0 / mse)) if mse > 0 else None


@contextmanager
def stage_clock(stages: dict):
    """Accumulate wall seconds spent in callables while the block runs.

    ``stages``: {stage name: (owner, attribute name)}; each ``owner.attribute`` (a module's function
    or an object's method) is wrapped for the duration of the block. Yields {stage: seconds}.
    """
    totals = dict.fromkeys(stages, 0.0)
    originals = {name: getattr(owner, attr) for name, (owner, attr) in stages.items()}

    def timed(name, fn):
        def wrapper(*args, **kwargs):
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                totals[name] += time.perf_counter() - start
        return wrapper

    for name, (owner, attr) in stages.items():
        setattr(owner, attr, timed(name, originals[name]))
    try:
        yield totals
    finally:
        for name, (owner, attr) in stages.items():
            if isinstance(owner, type) or not hasattr(type(owner), attr):
                setattr(owner, attr, originals[name])
            else:
                delattr(owner, attr)  # an instance's wrapped method: the class's shows again


def run_child(script: Path, config: dict, env: dict | None = None) -> dict:
    """Run the benchmark ``script`` with ``--child JSON`` in a fresh process (a clean peak-memory reading);
    its last stdout line is JSON."""
    command = [sys.executable, "-m", module_name(script), "--child", json.dumps(config)]
    done = subprocess.run(command, capture_output=True, text=True, env={**os.environ, **(env or {})}, cwd=REPO)
    if done.returncode != 0:
        raise RuntimeError(f"{script.name} child {config} failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def measurement_header(mode: str, command: str, plan: dict) -> dict:
    """The fields a sectioned report opens with; ``load_average`` gets an entry per section."""
    return {"mode": mode, "command": command, "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "machine": machine_info(), "load_average": {"before": load_average()}, "plan": plan}


def run_sections(results: dict, sections: tuple, args: tuple, warm_up: Callable[[], None]) -> None:
    """Warm up, then ``results[key] = fn(*args)`` for each (key, title, fn) of ``sections``.

    Prints progress, records the load average after each section and the seconds of it all
    (warm-up included) as ``benchmark_seconds``.
    """
    start = time.perf_counter()
    warm_up()
    for key, title, fn in sections:
        t0 = time.perf_counter()
        print(f"[{time.perf_counter() - start:6.0f} s] {title} ...", flush=True)
        results[key] = fn(*args)
        results["load_average"][key] = load_average()
        print(f"           done in {time.perf_counter() - t0:.0f} s", flush=True)
    results["benchmark_seconds"] = time.perf_counter() - start


# ------------------------------------------------------------------------------------------------
# Command line and report files


def benchmark_parser(doc: str, quick_help: str, report_only_help: str) -> argparse.ArgumentParser:
    """A parser with the --quick and --report-only flags; its description is the first paragraph of ``doc``."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help=quick_help)
    parser.add_argument("--report-only", action="store_true", help=report_only_help)
    return parser


def add_work_folder(parser: argparse.ArgumentParser, name: str, what: str) -> None:
    """``--work``: where ``what`` (default: /tmp/panolam-``name``)."""
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / f"panolam-{name}",
                        help=f"where {what} (default: a folder in /tmp)")


def report_stem(name: str, quick: bool) -> Path:
    """The report's path without suffix: REPORTS/``name``, ``_quick`` for a quick run."""
    return REPORTS / (f"{name}_quick" if quick else name)


def module_name(script: Path) -> str:
    """``benchmarks.NAME`` of a benchmark script's path."""
    return f"{HERE.name}.{Path(script).stem}"


def command_line(script: Path, argv: list[str] | None) -> str:
    """The command that reproduces this run, from the repository root."""
    return " ".join(["python", "-m", module_name(script), *(argv if argv is not None else sys.argv[1:])])


def report_name(name: str, quick: bool) -> str:
    """The stem of a report's files: ``name``, or ``name``_quick for a --quick run."""
    return f"{name}_quick" if quick else name


def write_json(path: Path, results: dict) -> None:
    """``results`` at ``path``, indented, making its folder if needed."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=1) + "\n")


def load_or_measure(json_path: Path, report_only: bool, measure: Callable[[], dict]) -> dict:
    """The results saved at ``json_path`` with --report-only; otherwise ``measure()``'s, saved there first."""
    if report_only:
        return json.loads(json_path.read_text())
    results = measure()
    write_json(json_path, results)
    return results


def report_main(argv: list[str] | None, *, script: Path, name: str, doc: str, quick_help: str,
                report_only_help: str, measure: Callable[[bool, str], dict],
                render: Callable[[dict, Path], str]) -> None:
    """main() of a script with --quick, --report-only and --out-dir.

    ``measure(quick, command)`` gives the results (or --report-only reads the saved JSON);
    ``render(results, out_dir)`` writes the plots and returns the markdown.
    """
    parser = benchmark_parser(doc, quick_help, report_only_help)
    parser.add_argument("--out-dir", type=Path, default=REPORTS, help="where the report goes")
    args = parser.parse_args(argv)
    json_path = args.out_dir / f"{report_name(name, args.quick)}.json"
    results = load_or_measure(json_path, args.report_only, lambda: measure(args.quick, command_line(script, argv)))
    md_path = json_path.with_suffix(".md")
    md_path.write_text(render(results, args.out_dir))
    print(f"wrote {json_path}, {md_path}")


def write_report(stem: Path, results: dict, markdown: str) -> None:
    """``stem``.json and ``stem``.md (plots are written beside them by the caller)."""
    write_json(stem.with_suffix(".json"), results)
    stem.with_suffix(".md").write_text(markdown)
    print(f"wrote {stem}.md")


def pyplot():
    """matplotlib.pyplot with a file-only backend, or None when matplotlib is not installed."""
    try:
        import matplotlib
    except ImportError:
        return None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


# ------------------------------------------------------------------------------------------------
# Markdown


def fmt(value, digits=2) -> str:
    """``value`` with ``digits`` decimals; "identical" for None (an error of zero)."""
    return "identical" if value is None else f"{value:.{digits}f}"


def table(headers: list[str], rows: list[list]) -> list[str]:
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    return lines + ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]


def bullets(lines: list[str]) -> list[str]:
    return [f"- {line}" for line in lines]


def reproduce(command: str) -> list[str]:
    """Markdown lines giving the command that reproduces a report."""
    return ["Reproduce from the repository root:", "", "```bash", command, "```"]


def load_note(results: dict, run_cpus: int, busy_verdict: str) -> str:
    """The 1-minute load average around a sectioned run, and whether other work competed for the CPUs.

    ``run_cpus``: how many CPUs the run itself keeps busy; ``busy_verdict``: the sentence for a busy machine.
    """
    load = results["load_average"]
    if load["before"] is None:
        return "Load average: not available on this platform."
    cpus = results["machine"]["usable_cpus"]
    during = {k: v for k, v in load.items() if k != "before"}
    busy = load["before"] > 0.5 * cpus or max(during.values()) > cpus + 1.0
    nice = results["machine"].get("nice", 0)
    priority = (f" The run had scheduling priority (nice {nice}) over that other work (nice 0), so it got the "
                "CPUs first; times are still somewhat inflated (caches, memory bandwidth)." if busy and nice < 0 else "")
    return (f"1-minute load average {load['before']:.2f} before the run and "
            + ", ".join(f"{v:.2f} after {k}" for k, v in during.items())
            + f" (this run alone keeps about {run_cpus} busy): "
            + (busy_verdict if busy else "the machine was otherwise idle.") + priority)
