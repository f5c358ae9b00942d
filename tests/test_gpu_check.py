"""The GPU acceptance script: refuses to run without a GPU unless asked for a dry run, and its dry
run exercises every section on the CPU."""
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SCRIPT = [sys.executable, "-m", "benchmarks.gpu_check"]


def test_without_a_gpu_it_says_so_and_points_to_the_dry_run(tmp_path):
    if torch.cuda.is_available():
        pytest.skip("a GPU is here: the script would run for real")
    done = subprocess.run([*SCRIPT, "--out-dir", str(tmp_path)], capture_output=True, text=True, cwd=REPO)
    assert done.returncode == 2 and "no CUDA device here; use --dry-run" in done.stderr
    assert not list(tmp_path.iterdir())


@pytest.mark.slow
def test_the_dry_run_completes_every_section(tmp_path):
    done = subprocess.run([*SCRIPT, "--dry-run", "--out-dir", str(tmp_path)], capture_output=True, text=True,
                          timeout=900, cwd=REPO)
    assert done.returncode == 0, done.stderr[-3000:]
    results = json.loads((tmp_path / "gpu_check_dry_run.json").read_text())
    sections = ("cuda_tests", "gan_precision", "gan_throughput", "workers", "training", "inference")
    assert all("result" in results[k] for k in sections), {k: results[k].get("error") for k in sections}
    assert results["workers"]["result"]["identical_shards"]
    assert (tmp_path / "gpu_check_dry_run.md").read_text().startswith("# GPU check (dry run")
