"""What every benchmark script shares: machine description, memory readings, child processes, reports."""
from __future__ import annotations

import json
import os
import platform
import resource
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
REPORTS = HERE / "reports"


def machine_info() -> dict:
    models = [line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
              if line.startswith("model name")] if Path("/proc/cpuinfo").exists() else []
    try:
        revision = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                  cwd=HERE).stdout.strip()
    except OSError:
        revision = "unknown"
    return {"cpu_model": models[0] if models else platform.processor(), "cpu_count": os.cpu_count(),
            "platform": platform.platform(), "python": platform.python_version(), "torch": torch.__version__,
            "torch_threads": torch.get_num_threads(), "git_revision": revision or "unknown",
            "load_average": list(os.getloadavg()), "date": datetime.now(timezone.utc).isoformat(timespec="seconds")}


def rss_mb() -> float:
    """Current resident set size (MiB), from /proc/self/statm."""
    return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far (MiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux


def run_child(script: Path, config: dict, env: dict | None = None) -> dict:
    """Run ``script --child JSON`` in a fresh process (a clean peak-memory reading); its last stdout line is JSON."""
    command = [sys.executable, str(script), "--child", json.dumps(config)]
    done = subprocess.run(command, capture_output=True, text=True, env={**os.environ, **(env or {})})
    if done.returncode != 0:
        raise RuntimeError(f"{script.name} child {config} failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def write_report(stem: Path, results: dict, markdown: str) -> None:
    """``stem``.json and ``stem``.md (plots are written beside them by the caller)."""
    stem.parent.mkdir(parents=True, exist_ok=True)
    stem.with_suffix(".json").write_text(json.dumps(results, indent=1) + "\n")
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
