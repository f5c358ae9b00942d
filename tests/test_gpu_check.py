"""The GPU acceptance script: refuses to run without a GPU unless asked for a dry run; its report is on
disk, section by section, as it goes; a section that does not fit the budget is skipped, and says so."""
import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from benchmarks import gpu_check

REPO = Path(__file__).resolve().parents[1]
SCRIPT = [sys.executable, "-m", "benchmarks.gpu_check"]


def test_without_a_gpu_it_says_so_and_points_to_the_dry_run(tmp_path):
    if torch.cuda.is_available():
        pytest.skip("a GPU is here: the script would run for real")
    done = subprocess.run([*SCRIPT, "--out-dir", str(tmp_path)], capture_output=True, text=True, cwd=REPO)
    assert done.returncode == 2 and "no CUDA device here; use --dry-run" in done.stderr
    assert not list(tmp_path.iterdir())


def run_watched(tmp_path, *args) -> tuple[int, list]:
    """The dry run in this process; after each section, what its report on disk holds then."""
    stem = tmp_path / "gpu_check_dry_run"
    seen = []

    def after_section(key):
        seen.append((key, json.loads(stem.with_suffix(".json").read_text()), stem.with_suffix(".md").read_text()))

    return gpu_check.main(["--dry-run", "--out-dir", str(tmp_path), *args], after_section=after_section), seen


def titles(keys) -> list[str]:
    return [f"## {s.title}" for s in gpu_check.SECTIONS if s.key in keys]


def test_the_report_on_disk_holds_each_section_as_it_ends(tmp_path):
    """Two sections at toy sizes, and gsplat's (not asked for): after each, the report on disk has it."""
    code, seen = run_watched(tmp_path, "--sections", "cuda_vs_cpu,precision,gsplat")
    assert code == 0 and [key for key, _, _ in seen] == ["cuda_vs_cpu", "precision", "gsplat"]
    for i, (_, report, md) in enumerate(seen):
        assert list(report["sections"]) == [k for k, _, _ in seen[:i + 1]] and not report["complete"]
        assert md.count("Not run yet.") == 2 - i and "in progress or cut short" in md
    assert "result" in seen[1][1]["sections"]["precision"]
    assert seen[2][1]["sections"]["gsplat"] == {"skipped": "not asked for: run with --gsplat", "seconds": 0.0}
    final = json.loads((tmp_path / "gpu_check_dry_run.json").read_text())
    assert final["complete"] and final["environment"]["gpus"] == [] and "driver" in final["environment"]
    md = (tmp_path / "gpu_check_dry_run.md").read_text()
    assert md.startswith("# GPU check (dry run") and "report complete" in md
    assert all(t in md for t in titles(["cuda_vs_cpu", "precision", "gsplat"]))
    assert "| eg3d | identical |" in md  # the dry run compares the CPU with itself


def test_a_section_that_does_not_fit_the_budget_is_skipped_and_named(tmp_path):
    code, seen = run_watched(tmp_path, "--budget-s", "0")
    assert code == 0 and [key for key, _, _ in seen] == list(gpu_check.KEYS)
    sections = seen[-1][1]["sections"]
    assert all(sections[k]["skipped"].startswith("does not fit the budget: 0 s left") for k in gpu_check.KEYS[:-1])
    assert sections["gsplat"]["skipped"] == "not asked for: run with --gsplat"
    assert seen[-1][2].count("Skipped: does not fit the budget") == len(gpu_check.KEYS) - 1


def test_later_sections_keep_their_time_back():
    """On a GPU a section may use the budget down to what the sections after it need."""
    plan = gpu_check.Plan(dry_run=False)
    needs = {s.key: gpu_check.needs_s(s, plan) for s in gpu_check.SECTIONS if not gpu_check.not_applicable(s, plan)}
    assert "gsplat" not in needs and sum(needs.values()) < gpu_check.DEFAULT_BUDGET_S
    assert gpu_check.not_applicable(gpu_check.SECTIONS[-1], gpu_check.Plan(False, gsplat=True)) is None


@pytest.mark.slow
def test_the_dry_run_completes_every_section_quickly(tmp_path):
    t0 = time.perf_counter()
    done = subprocess.run([*SCRIPT, "--dry-run", "--out-dir", str(tmp_path)], capture_output=True, text=True,
                          timeout=900, cwd=REPO)
    assert done.returncode == 0, done.stderr[-3000:]
    assert time.perf_counter() - t0 < 300  # 2.5 min on 2 busy cores
    results = json.loads((tmp_path / "gpu_check_dry_run.json").read_text())
    ran = [k for k in gpu_check.KEYS if k != "gsplat"]
    assert all("result" in results["sections"][k] for k in ran), {k: results["sections"][k].get("error") for k in ran}
    assert results["sections"]["workers"]["result"]["identical_shards"]
    assert results["sections"]["cuda_tests"]["result"]["ok"]
    assert all(t in (tmp_path / "gpu_check_dry_run.md").read_text() for t in titles(gpu_check.KEYS))
