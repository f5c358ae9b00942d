"""The Ray backend runs the same shard tasks as the local one and must give the same bytes."""
from __future__ import annotations

from pathlib import Path

import pytest

ray = pytest.importorskip("ray", reason="the ray backend needs the optional extra: pip install -e '.[ray]'")

from datagen.pipeline import JobSpec, run_sample, software_info  # noqa: E402

pytestmark = [pytest.mark.ray]


def tiny_job(out: Path) -> JobSpec:
    return JobSpec(out=str(out), gan="procedural", generator_options={"grid_resolution": 48}, protocol="360",
                   subjects=3, resolution=32, views=3, seed=7, shard_size=2, software=software_info())


def files(root: Path) -> dict[str, bytes]:
    """{relative path: bytes} of every file under root, hidden ones included."""
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture
def no_ray():
    """Start from a process without Ray, and leave none behind whatever the test does."""
    assert not ray.is_initialized(), "Ray is already initialized in this process"
    yield
    if ray.is_initialized():
        ray.shutdown()


def test_ray_backend_writes_the_same_bytes_as_local(tmp_path, no_ray):
    # Two tasks side by side with one thread each on Ray; one process with the default threads locally.
    on_ray = run_sample(tiny_job(tmp_path / "ray"), backend="ray", workers=2, progress=False)
    local = run_sample(tiny_job(tmp_path / "local"), backend="local", workers=1, progress=False)
    assert on_ray["shards_written"] == local["shards_written"] == 2
    assert not ray.is_initialized(), "the Ray instance started for the run was not shut down"

    got, want = files(tmp_path / "ray"), files(tmp_path / "local")
    assert want, "the local run wrote no files"
    assert sorted(got) == sorted(want)
    assert {"index.json", "shard-000000.tar", "shard-000001.json", "truth/shard-000001.json"} <= set(want)
    different = [name for name in want if got[name] != want[name]]
    assert not different, f"files differ between the ray and local backends: {different}"


def test_a_failing_shard_task_raises_its_own_error_and_leaves_the_users_ray_running(tmp_path, no_ray):
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)  # the user's own Ray
    out = tmp_path / "broken"
    out.mkdir()
    (out / "truth").write_text("a file where the truth folder belongs")
    with pytest.raises(OSError) as caught:
        run_sample(tiny_job(out), backend="ray", workers=2, progress=False)
    # The task's own error, with Ray's record of the remote traceback chained to it.
    assert isinstance(caught.value.__cause__, ray.exceptions.RayTaskError)
    assert ray.is_initialized(), "run_sample shut down a Ray it did not start"
    assert not list(out.glob("shard-*")), "a failed shard task left a shard behind"
    ray.shutdown()
