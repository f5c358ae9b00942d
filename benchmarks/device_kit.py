"""The device kit: what a GPU node with no package index needs, beside the repository, to run the GPU check.

    python -m benchmarks.device_kit --out .device-kit

The node's image (Python 3.12, torch with CUDA) already holds the packages of :data:`IMAGE`. The kit
holds the wheels of the rest of what the check uses (the core dependencies and the ``cuda`` extra,
with their own requirements, transitively: :data:`CARRY` and :data:`CARRY_GSPLAT`, downloaded for
CPython 3.12 on manylinux x86_64), the project's own wheel, the GAN fixture pickles the check reads
(``shared/``) and ``manifest.json``. gsplat's wheels lie apart (``gsplat/``): the check installs
them itself for its last, optional section, so that no earlier section builds gsplat's kernels.

Building it checks that the downloaded wheels' requirements are covered by the kit and the image;
``tests/test_device_kit.py`` checks the lists against ``pyproject.toml``.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import subprocess
import sys
import tempfile
import tomllib
import zipfile
from collections.abc import Callable, Iterable
from email.parser import Parser
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

REPO = Path(__file__).resolve().parents[1]
KIT = REPO / ".device-kit"
GSPLAT_DIR = "gsplat"
SITE = "/tmp/panolam-site"
FORMAT = "panolam-device-kit/1"
PYTHON_VERSION = "3.12"
PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64",
             "manylinux1_x86_64")
# What the check uses beyond the core: extra -> the names it needs of it (None: all of it).
CHECK_EXTRAS = {"cuda": None, "model": ("transformers", "tensorboard")}
# The Python packages of the GPU node's image (Python 3.12, torch 2.11 with CUDA 13), as listed for it.
IMAGE = frozenset(canonicalize_name(n) for n in """
absl-py accelerate aiofiles aiohappyeyeballs aiohttp aiosignal annotated-doc anyio attrs botorch build certifi
charset-normalizer chex click cloudpickle cmake colorama contourpy coverage cuda-bindings cuda-core cuda-pathfinder
cuda-toolkit cupy-cuda13x cycler cython diffrax e3nn einops equinox etils execnet filelock flatbuffers flax fonttools
formulaic frozenlist fsspec gpytorch grpcio h11 h5py hf-xet httpcore httpx huggingface-hub humanize hypothesis idna
imageio iniconfig interface-meta jax jax-cuda13-pjrt jax-cuda13-plugin jaxlib jaxtyping jinja2 joblib kiwisolver
lazy-loader lightning lightning-utilities linear-operator lineax llvmlite lxml markdown markdown-it-py markupsafe
matplotlib mdurl meson ml-dtypes mpi4py mpmath msgpack multidict multipledispatch mypy-extensions nanobind narwhals
networkx ninja numba numba-cuda numpy numpyro nvidia-cublas nvidia-cuda-cupti nvidia-cuda-nvrtc nvidia-cuda-runtime
nvidia-cudnn-cu13 nvidia-cufft nvidia-cufile nvidia-curand nvidia-cusolver nvidia-cusparse nvidia-cusparselt-cu13
nvidia-ml-py nvidia-nccl-cu13 nvidia-nvjitlink nvidia-nvshmem-cu13 nvidia-nvtx onnx onnx-ir onnxruntime onnxscript
opencv-python-headless optax opt-einsum opt-einsum-fx optimistix orbax-checkpoint packaging pandas pathspec patsy
peft pillow pip pluggy portalocker prometheus-client propcache protobuf psutil pyarrow pybind11 py-cpuinfo pygments
pyparsing pyproject-hooks pyre-extensions pytest pytest-benchmark pytest-cov pytest-mock pytest-timeout
pytest-xdist python-dateutil pytorch-lightning pyyaml regex requests rich sacrebleu safetensors scikit-build-core
scikit-image scikit-learn scipy seaborn sentencepiece sentence-transformers setuptools shellingham simplejson six
sortedcontainers statsmodels sympy tabulate tensorboard tensorboard-data-server tensorstore threadpoolctl tifffile
tiktoken timm tokenizers toolz torch torchaudio torchdiffeq torch-geometric torchmetrics torchvision tqdm
transformers treescope triton typer typing-extensions typing-inspect urllib3 uvloop wadler-lindig werkzeug wheel
wrapt xarray xxhash yarl zipp""".split())
# The wheels the kit carries: the core dependencies with their requirements, transitively, less IMAGE ...
CARRY = ("braceexpand", "openexr", "plyfile", "trimesh", "webdataset")
# ... and what CHECK_EXTRAS add to those (the gsplat/ folder).
CARRY_GSPLAT = ("gsplat",)


def project_requirements(pyproject: Path = REPO / "pyproject.toml") -> tuple[list[Requirement], list[Requirement]]:
    """(the core dependencies, what the check uses of CHECK_EXTRAS) as pyproject.toml declares them."""
    project = tomllib.loads(pyproject.read_text())["project"]
    extras = project.get("optional-dependencies", {})
    used = []
    for extra, names in CHECK_EXTRAS.items():
        declared = [Requirement(r) for r in extras.get(extra, [])]
        chosen = [r for r in declared if names is None or canonicalize_name(r.name) in names]
        if not declared or (names is not None and len(chosen) != len(names)):
            raise SystemExit(f"device_kit: pyproject.toml's extra {extra!r} lacks {names or 'its requirements'} "
                             "(CHECK_EXTRAS is out of date)")
        used += chosen
    return [Requirement(r) for r in project["dependencies"]], used


def closure(roots: Iterable[Requirement], requires: Callable[[str], list[Requirement]], environment: dict) -> set[str]:
    """The names of ``roots`` and of what they require, transitively (markers evaluated in
    ``environment``, extras left out); the image's packages are not walked into."""
    seen, todo = set(), [r for r in roots if _applies(r, environment)]
    while todo:
        name = canonicalize_name(todo.pop().name)
        if name in seen:
            continue
        seen.add(name)
        if name not in IMAGE:
            todo += [r for r in requires(name) if _applies(r, environment)]
    return seen


def _applies(requirement: Requirement, environment: dict) -> bool:
    return requirement.marker is None or requirement.marker.evaluate({**environment, "extra": ""})


def target_environment(python_version: str) -> dict:
    """Marker values of CPython ``python_version`` on Linux x86_64."""
    return {"python_version": python_version, "python_full_version": f"{python_version}.0",
            "implementation_name": "cpython", "platform_python_implementation": "CPython", "sys_platform": "linux",
            "platform_system": "Linux", "platform_machine": "x86_64", "os_name": "posix"}


def wheel_requirements(wheel: Path) -> list[Requirement]:
    """The Requires-Dist lines of a wheel's METADATA."""
    with zipfile.ZipFile(wheel) as z:
        name = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
        metadata = Parser().parsestr(z.read(name).decode())
    return [Requirement(r) for r in metadata.get_all("Requires-Dist") or []]


def wheel_name(wheel: Path) -> str:
    return canonicalize_name(wheel.name.split("-")[0])


def pip(*args, cwd: Path | None = None) -> None:
    done = subprocess.run([sys.executable, "-m", "pip", *map(str, args)], capture_output=True, text=True, cwd=cwd)
    if done.returncode != 0:
        output = (done.stdout + done.stderr)[-3000:]
        raise SystemExit(f"device_kit: pip {' '.join(map(str, args[:2]))} failed:\n{output}")


def download(names: tuple, specs: dict, folder: Path, python_version: str, platforms: tuple) -> list[Path]:
    """Binary wheels of ``names`` (with pyproject's version specifiers) for the target, without their requirements."""
    folder.mkdir(parents=True, exist_ok=True)
    flags = ["--no-deps", "--only-binary=:all:", "--python-version", python_version, "--implementation", "cp",
             *(a for p in platforms for a in ("--platform", p))]
    pip("download", *flags, "-d", folder, *(str(specs.get(n, n)) for n in names))
    return sorted(w for w in folder.glob("*.whl") if wheel_name(w) in names)


def project_wheel(folder: Path) -> Path:
    """The project's wheel, built from a copy of its sources (so no build folder is left in the checkout)."""
    with tempfile.TemporaryDirectory(prefix="panolam-wheel-") as tmp:
        src = Path(tmp) / "src"
        src.mkdir()
        for name in ("pyproject.toml", "README.md"):
            shutil.copy2(REPO / name, src / name)
        for package in ("datagen", "labeling_tool", "panolam"):
            shutil.copytree(REPO / package, src / package, ignore=shutil.ignore_patterns("__pycache__"))
        pip("wheel", "--no-deps", "--no-build-isolation", "-w", folder, src)
    return next(folder.glob("panolam_toolkit-*.whl"))


def check_complete(core: list[Requirement], used: list[Requirement], wheels: dict, environment: dict) -> set[str]:
    """The image packages the kit relies on; SystemExit when the downloaded wheels need one the kit
    lacks, or the kit carries one nothing needs (CARRY and CARRY_GSPLAT are then out of date)."""
    def requires(name: str) -> list[Requirement]:
        if name not in wheels:
            raise SystemExit(f"device_kit: {name} is needed but neither carried nor in the image: add it to CARRY")
        return wheel_requirements(wheels[name])

    core_names = closure(core, requires, environment)
    all_names = closure(core + used, requires, environment)
    for found, listed, what in ((core_names - IMAGE, set(CARRY), "CARRY"),
                                (all_names - IMAGE - core_names, set(CARRY_GSPLAT), "CARRY_GSPLAT")):
        if found != listed:
            raise SystemExit(f"device_kit: {what} lists {sorted(listed)}, the requirements give {sorted(found)}")
    return all_names & IMAGE


def describe(files: Iterable[Path], root: Path) -> list[dict]:
    return [{"file": str(f.relative_to(root)), "bytes": f.stat().st_size,
             "sha256": hashlib.sha256(f.read_bytes()).hexdigest()} for f in files]


def commands(out: Path) -> tuple[str, str]:
    """The install line and the check's command line on the node, from the repository root."""
    kit = out.relative_to(REPO) if out.is_relative_to(REPO) else out
    return (f"python3 -m pip install --no-index --no-deps --target {SITE} {kit}/*.whl",
            f"PYTHONPATH={SITE} PANOLAM_SHARED=$PWD/{kit}/shared python3 -m benchmarks.gpu_check [--gsplat]")


def build_kit(out: Path, python_version: str = PYTHON_VERSION, platforms: tuple = PLATFORMS) -> dict:
    """Fill ``out`` with the kit (its former wheels, fixtures and manifest replaced); the manifest."""
    from benchmarks.gpu_check import SHARED, fixture_files
    from datagen.files import atomic_write
    out = out.resolve()
    for old in [*out.glob("*.whl"), *(out / GSPLAT_DIR).glob("*.whl")]:
        old.unlink()
    shutil.rmtree(out / "shared", ignore_errors=True)
    core, used = project_requirements()
    specs = {canonicalize_name(r.name): r for r in core + used}
    carried = download(CARRY, specs, out, python_version, platforms)
    gsplat = download(CARRY_GSPLAT, specs, out / GSPLAT_DIR, python_version, platforms)
    from_image = check_complete(core, used, {wheel_name(w): w for w in carried + gsplat},
                                target_environment(python_version))
    own = project_wheel(out)
    fixtures = []
    for rel in fixture_files():
        if not (SHARED / rel).exists():
            raise SystemExit(f"device_kit: {SHARED / rel} not found (set PANOLAM_SHARED to the shared/ folder)")
        (out / "shared" / rel).parent.mkdir(parents=True, exist_ok=True)
        fixtures.append(Path(shutil.copy2(SHARED / rel, out / "shared" / rel)))
    install, run = commands(out)
    files = describe([*carried, own, *gsplat, *fixtures], out)
    manifest = {"format": FORMAT, "python_version": python_version, "platforms": list(platforms),
                "wheels": [w.name for w in [*carried, own]], "gsplat_wheels": [w.name for w in gsplat],
                "fixtures": [str(f.relative_to(out)) for f in fixtures], "from_image": sorted(from_image),
                "files": files, "total_bytes": sum(f["bytes"] for f in files), "install": install, "run": run}
    atomic_write(out / "manifest.json", (json.dumps(manifest, indent=1) + "\n").encode())
    return manifest


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=KIT, help=f"the kit's folder (default {KIT.relative_to(REPO)})")
    parser.add_argument("--python-version", default=PYTHON_VERSION, help="the node's Python (default %(default)s)")
    parser.add_argument("--platform", action="append", dest="platforms",
                        help="a wheel platform tag, repeatable (default: manylinux x86_64 tags)")
    args = parser.parse_args(argv)
    manifest = build_kit(args.out, args.python_version, tuple(args.platforms or PLATFORMS))
    print(f"{args.out}: {len(manifest['wheels'])} wheels, {len(manifest['gsplat_wheels'])} for gsplat, "
          f"{len(manifest['fixtures'])} fixtures; {manifest['total_bytes'] / 2 ** 20:.1f} MiB in all")
    print("On the GPU node, from the repository root (the kit copied to the same place in it):")
    print(f"  {manifest['install']}")
    print(f"  {manifest['run']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
