"""Installs by role: with every extra's modules missing, as on an install of the core alone, the core
commands run, and each command that needs an extra stops with one line naming it."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from functools import cache
from importlib import metadata
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from datagen.errors import NotInstalled, UserError, optional_import

tomllib = pytest.importorskip("tomllib")

ROOT = Path(__file__).resolve().parents[1]

# Runs the commands in argv[2] (JSON: [[module, *args], ...]) one after the other, each as ``python -m module args``
# would, as if the top-level modules in argv[1] (JSON) were not installed; prints [[exit status, stderr], ...].
RUN_WITHOUT = """
import contextlib, importlib.machinery, io, json, runpy, sys, traceback

missing = set(json.loads(sys.argv[1]))


class Missing:
    def find_spec(self, name, path=None, target=None):
        return importlib.machinery.ModuleSpec(name, self) if name.partition(".")[0] in missing else None

    def create_module(self, spec):
        return None

    def exec_module(self, module):
        raise ModuleNotFoundError(f"No module named {module.__name__!r}", name=module.__name__)


for name in [m for m in sys.modules if m.partition(".")[0] in missing]:
    del sys.modules[name]
sys.meta_path.insert(0, Missing())
results = []
for command in json.loads(sys.argv[2]):
    sys.argv, err = list(command), io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        try:
            runpy.run_module(command[0], run_name="__main__", alter_sys=True)
            code = 0
        except SystemExit as e:
            code = 0 if e.code is None else e.code if isinstance(e.code, int) else 1
        except BaseException:
            traceback.print_exc()
            code = 1
    results.append([code, err.getvalue()])
print(json.dumps(results))
"""


def _closure(requirements: list[str], extra: str = "") -> set[str]:
    """Canonical names of the distributions these requirements pull in, transitively (installed ones
    are followed; a missing one is named only)."""
    found, seen, todo = set(), set(), [(Requirement(r), extra) for r in requirements]
    while todo:
        req, ex = todo.pop()
        name = canonicalize_name(req.name)
        if (req.marker and not req.marker.evaluate({"extra": ex})) or (name, frozenset(req.extras)) in seen:
            continue
        seen.add((name, frozenset(req.extras)))
        found.add(name)
        try:
            deps = metadata.requires(req.name) or []
        except metadata.PackageNotFoundError:
            continue
        todo += [(Requirement(d), e) for d in deps for e in ("", *req.extras)]
    return found


def _top_level(dist_names: set[str]) -> set[str]:
    """Top-level modules the installed distributions put in site-packages (their RECORDs; top_level.txt can be
    incomplete); a distribution that is not installed: its name as a module."""
    found = set()
    for name in dist_names:
        try:
            files = metadata.distribution(name).files or []
        except metadata.PackageNotFoundError:
            found.add(name.replace("-", "_"))
            continue
        found |= {f.parts[0].split(".")[0] for f in files if (len(f.parts) > 1 or f.suffix in (".py", ".so", ".pyd"))
                  and not f.parts[0].endswith((".dist-info", ".data"))}
    return found - {"", "__pycache__"}


@cache
def _modules_by_role() -> tuple[set[str], dict[str, set[str]]]:
    """(core's distributions, {extra: top-level modules that only that extra brings}) from pyproject.toml."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = _closure(project["dependencies"])
    core_modules = _top_level(core)
    return core, {extra: _top_level(_closure(reqs) - core) - core_modules
                  for extra, reqs in project["optional-dependencies"].items() if extra != "all"}


# Core commands (all must succeed), then, for each command that needs an extra, that extra and the command.
CORE = [
    ("datagen.cli", "sample", "--subjects", "2", "--views", "4", "--resolution", "32", "--out", "ds", "--quiet"),
    ("datagen.cli", "verify", "ds"),
    ("labeling_tool.cli", "compile", "ds", "--labels", "labels", "--out", "m.json"),
]
NEEDS = [
    ("review", "labeling_tool.cli", "review", "ds", "--reviewer", "t", "--labels", "labels", "--off-screen"),
    ("faces", "labeling_tool.cli", "auto", "ds", "--quiet"),
    ("model", "panolam.cli", "train", "--data", "ds", "--manifest", "m.json", "--out", "run", "--steps", "1"),
    ("faces", "panolam.cli", "infer", "photo.png", "--ckpt", "run", "--out", "head.ply"),
    ("ray", "datagen.cli", "sample", "--subjects", "1", "--out", "ray-ds", "--backend", "ray", "--quiet"),
]


@pytest.fixture(scope="module")
def core_install(tmp_path_factory) -> list[tuple[int, str]]:
    """(exit status, stderr) of CORE and then of NEEDS' commands, run in one process in a fresh folder with every
    extra's modules missing, as on an install of the core alone."""
    cwd = tmp_path_factory.mktemp("core")
    (cwd / "labels").mkdir()
    missing = set().union(*_modules_by_role()[1].values())
    env = dict(os.environ, OMP_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    commands = json.dumps(CORE + [n[1:] for n in NEEDS])
    r = subprocess.run([sys.executable, "-c", RUN_WITHOUT, json.dumps(sorted(missing)), commands], cwd=cwd, env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.splitlines()[-1])


def test_extra_modules_are_known():
    core, by_role = _modules_by_role()
    assert {"torch", "numpy", "pillow", "openexr"} <= core and not core & {"vtk", "dlib-bin", "transformers", "av"}
    for extra, module in (("review", "pyvista"), ("review", "vtkmodules"), ("faces", "dlib"), ("faces", "cv2"),
                          ("faces", "face_recognition_models"), ("model", "transformers"), ("model", "tensorboard"),
                          ("model", "av"), ("photos", "OpenImageIO"), ("ray", "ray"), ("cuda", "gsplat")):
        assert module in by_role[extra], (extra, module)


def test_core_commands_run_without_the_extras(core_install):
    for command, (code, err) in zip(CORE, core_install[:len(CORE)], strict=True):
        assert code == 0, f"{' '.join(command)}: {err[-2000:]}"


@pytest.mark.parametrize("case", range(len(NEEDS)), ids=[" ".join(n[:3]) for n in NEEDS])
def test_command_without_its_extra_names_it(core_install, case):
    extra = NEEDS[case][0]
    code, err = core_install[len(CORE) + case]
    lines = err.splitlines()
    assert code != 0 and len(lines) == 1, err[-2000:]
    assert f"needs the '{extra}' extra" in lines[0] and f"pip install 'panolam-toolkit[{extra}]'" in lines[0]


def test_optional_import():
    assert optional_import("json", "model", "x") is json
    with pytest.raises(NotInstalled, match=r"^reading X needs the 'photos' extra \(No module named 'no_such_mod'\): "
                                           r"pip install 'panolam-toolkit\[photos\]'$") as e:
        optional_import("no_such_mod", "photos", "reading X")
    assert isinstance(e.value, UserError) and isinstance(e.value, ImportError)
