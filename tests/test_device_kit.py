"""The device kit: its wheel lists follow pyproject.toml, and a kit built for this interpreter, installed
with no index onto torch and the GPU image's packages alone, runs the GPU check's dry run."""
import json
import os
import subprocess
import sys
import zipfile
from importlib import metadata
from pathlib import Path

import pytest
from packaging.requirements import Requirement

from benchmarks import device_kit as kit

REPO = Path(__file__).resolve().parents[1]


def installed_requirements(name: str) -> list[Requirement]:
    """Requirements of an installed distribution (none known when it is not installed here)."""
    try:
        return [Requirement(r) for r in metadata.requires(name) or []]
    except metadata.PackageNotFoundError:
        return []


def test_carried_wheels_follow_pyproject():
    """CARRY is the core's requirement closure less the image; CARRY_GSPLAT what the check's extras add
    (their own requirements are checked against the downloaded wheels when a kit is built)."""
    core, used = kit.project_requirements()
    env = kit.target_environment(f"{sys.version_info.major}.{sys.version_info.minor}")
    core_names = kit.closure(core, installed_requirements, env)
    assert core_names - kit.IMAGE == set(kit.CARRY)
    assert kit.closure(core + used, installed_requirements, env) - kit.IMAGE - core_names == set(kit.CARRY_GSPLAT)
    assert not (set(kit.CARRY) | set(kit.CARRY_GSPLAT)) & kit.IMAGE
    assert "torch" in {r.name for r in core} and "torch" in kit.IMAGE


def test_a_requirement_outside_the_kit_and_the_image_stops_the_build(tmp_path):
    wheel = tmp_path / "webdataset-9.0-py3-none-any.whl"
    with zipfile.ZipFile(wheel, "w") as z:
        z.writestr("webdataset-9.0.dist-info/METADATA",
                   "Metadata-Version: 2.1\nName: webdataset\nRequires-Dist: numpy\nRequires-Dist: lmdb\n"
                   "Requires-Dist: mkdocs; extra == 'dev'\nRequires-Dist: old; python_version < '3.8'\n")
    assert [str(r) for r in kit.wheel_requirements(wheel)][:2] == ["numpy", "lmdb"]
    with pytest.raises(SystemExit, match="lmdb is needed but neither carried nor in the image"):
        kit.check_complete([Requirement("webdataset")], [], {"webdataset": wheel}, kit.target_environment("3.12"))


@pytest.mark.slow
def test_the_kit_alone_runs_the_dry_run_on_a_bare_interpreter(tmp_path):
    """Built for this Python, the kit and the image's packages (not transformers: only the GPU-sized
    run's 'full' config reads it) are all a fresh venv beside torch needs for the whole dry run."""
    python = f"{sys.version_info.major}.{sys.version_info.minor}"
    run = lambda *args, **kw: subprocess.run([str(a) for a in args], capture_output=True, text=True, **kw)  # noqa: E731
    built = run(sys.executable, "-m", "benchmarks.device_kit", "--out", tmp_path / "kit", "--python-version", python,
                cwd=REPO)
    assert built.returncode == 0, built.stderr[-3000:]
    manifest = json.loads((tmp_path / "kit" / "manifest.json").read_text())
    assert manifest["total_bytes"] < 30 * 2 ** 20
    venv = tmp_path / "venv"
    assert run(sys.executable, "-m", "venv", venv).returncode == 0
    py = venv / "bin" / "python"
    image = [n for n in manifest["from_image"] if n not in ("torch", "transformers")]
    done = run(py, "-m", "pip", "install", "-q", "torch==2.13.0", *image, "pytest")
    assert done.returncode == 0, done.stderr[-3000:]
    site = tmp_path / "site"
    done = run(py, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--target", site,
               *sorted((tmp_path / "kit").glob("*.whl")))
    assert done.returncode == 0, done.stderr[-3000:]
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH")}
    env.update(PYTHONPATH=str(site), PANOLAM_SHARED=str(tmp_path / "kit" / "shared"), OMP_NUM_THREADS="1")
    # The project's wheel on its own (away from the checkout): its packages, data and entry point.
    code = ("import datagen.cli, labeling_tool.compiler, panolam.train; from importlib.resources import files; "
            "assert (files('panolam') / 'assets' / 'head_template_1280.npz').is_file(); print(datagen.__file__)")
    done = run(py, "-c", code, cwd=tmp_path, env=env)
    assert done.returncode == 0 and done.stdout.startswith(str(site)), done.stderr[-3000:]
    assert run(site / "bin" / "datagen", "--help", env=env).returncode == 0
    done = run(py, "-m", "benchmarks.gpu_check", "--dry-run", "--out-dir", tmp_path / "report", cwd=REPO, env=env,
               timeout=900)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    report = json.loads((tmp_path / "report" / "gpu_check_dry_run.json").read_text())
    assert report["complete"] and report["machine"]["python"].startswith(python)
    assert all("result" in report["sections"][k] for k in report["planned"] if k != "gsplat"), report["sections"]
