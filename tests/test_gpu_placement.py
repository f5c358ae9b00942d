"""Which device each worker renders on: the placement rule, its hand-off to local worker processes
and Ray tasks, and the errors for requests that cannot be met. No GPU needed: the CUDA device count
is mocked, and nothing here starts Ray or a worker process."""
from __future__ import annotations

from concurrent.futures import Future

import pytest
import torch

from datagen import pipeline, runner, threads
from datagen.command_line import SilentBar
from datagen.cli import main
from datagen.device import ray_task_device, worker_devices
from datagen.errors import UserError
from datagen.pipeline import JobSpec, on_device, run_sample
from datagen.runner import Placement, ray_task_options

from tests.conftest import tiny_spec


@pytest.fixture
def gpus(monkeypatch):
    """Pretend this machine has ``n`` CUDA devices: ``gpus(n)``."""
    def pretend(n: int) -> None:
        monkeypatch.setattr(torch.cuda, "is_available", lambda: n > 0)
        monkeypatch.setattr(torch.cuda, "device_count", lambda: n)
    return pretend


@pytest.mark.parametrize("requested, workers, want", [
    ("cuda", 2, ["cuda:0", "cuda:1"]),
    ("auto", "auto", ["cuda:0", "cuda:1"]),                 # one worker per GPU
    ("cuda", 3, ["cuda:0", "cuda:1", "cuda:0"]),            # more workers than GPUs share them
    ("cuda", 1, ["cuda:0"]),
    ("cuda:1", 3, ["cuda:1", "cuda:1", "cuda:1"]),          # pinned
    ("cuda:1", "auto", ["cuda:1"]),
    ("cpu", "auto", ["cpu"] * 5),                           # the CPU: the given CPU worker count
    ("cpu", 2, ["cpu", "cpu"]),
])
def test_worker_k_renders_on_the_gpu_k_mod_count_or_the_pinned_one(gpus, requested, workers, want):
    gpus(2)
    assert worker_devices(requested, workers, cpu_workers=5) == want


def test_without_cuda_auto_is_the_cpu_and_cuda_is_refused(gpus):
    gpus(0)
    assert worker_devices("auto", "auto", cpu_workers=3) == ["cpu"] * 3
    with pytest.raises(UserError, match="CUDA is not available"):
        worker_devices("cuda", 2, cpu_workers=3)


def test_a_gpu_index_beyond_the_count_is_refused(gpus):
    gpus(2)
    with pytest.raises(UserError, match="has 2 CUDA device"):
        worker_devices("cuda:5", 1, cpu_workers=1)


@pytest.mark.parametrize("ids, visible, want", [
    ([3], "3", "cuda:0"),                       # Ray made only the assigned GPU visible
    (["3"], "3", "cuda:0"),
    ([1], "0,1", "cuda:1"),                     # RAY_EXPERIMENTAL_NOSET_CUDA_VISIBLE_DEVICES: the node's list
    (["GPU-b"], "GPU-a, GPU-b", "cuda:1"),      # ids given as UUIDs
    ([2], None, "cuda:2"),                      # nothing set: the id is the index
])
def test_a_ray_task_renders_on_the_gpu_ray_assigned(ids, visible, want):
    assert ray_task_device(ids, visible) == want


def test_a_ray_task_without_an_assigned_gpu_fails_loudly():
    with pytest.raises(RuntimeError, match="no GPU"):
        ray_task_device([], "0")


NODES = [{"Alive": True, "Resources": {"CPU": 32.0}},
         {"Alive": True, "Resources": {"CPU": 6.0, "GPU": 2.0}},
         {"Alive": False, "Resources": {"CPU": 64.0, "GPU": 8.0}}]


def test_ray_cpu_tasks_ask_for_cpus_only_capped_at_the_largest_alive_node():
    assert ray_task_options(NODES, 16, None) == {"num_cpus": 16}
    assert ray_task_options(NODES, 48, None) == {"num_cpus": 32}


def test_ray_gpu_tasks_ask_for_their_share_of_a_gpu_and_cpus_a_gpu_node_has():
    assert ray_task_options(NODES, 16, 1) == {"num_cpus": 6, "num_gpus": 1}
    assert ray_task_options(NODES, 2, 0.5) == {"num_cpus": 2, "num_gpus": 0.5}


def test_ray_gpu_tasks_on_a_cluster_without_gpus_are_refused():
    with pytest.raises(UserError, match="no GPU"):
        ray_task_options(NODES[:1] + NODES[2:], 4, 1)


def gan_spec(out, **options) -> JobSpec:
    return JobSpec(out=str(out), gan="eg3d", checkpoint="unused.pkl", generator_options=options, subjects=8,
                   shard_size=2)


class InlinePool:
    """Stands in for ProcessPoolExecutor: 'starts' max_workers worker processes by running the
    initializer once for each and keeping the worker state it set, then runs the tasks in turn on
    those workers, each with its own state."""

    def __init__(self, max_workers, mp_context, initializer, initargs):
        self.workers = []
        for _ in range(max_workers):
            initializer(*initargs)
            self.workers.append(runner._WORKER)
        self.submitted = 0

    def submit(self, fn, *args):
        runner._WORKER = self.workers[self.submitted % len(self.workers)]
        self.submitted += 1
        future = Future()
        future.set_result(fn(*args))
        return future

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


@pytest.fixture
def recorded(monkeypatch):
    """Runs local workers inline and records what they are given: the device each shard's spec
    renders on, and the GPU each worker made current."""
    log = {"shards": {}, "current": [], "threads": []}

    def write_shard(spec, shard, progress=None):
        log["shards"][shard] = spec.generator_options.get("device")
        return {}

    monkeypatch.setattr(runner, "ProcessPoolExecutor", InlinePool)
    monkeypatch.setattr(runner, "_WORKER", None)
    monkeypatch.setattr(pipeline, "write_shard", write_shard)
    monkeypatch.setattr(torch.cuda, "set_device", lambda d: log["current"].append(str(d)))
    monkeypatch.setattr(torch, "set_num_threads", log["threads"].append)
    monkeypatch.setattr(threads, "usable_cpus", lambda: 8)
    monkeypatch.setattr(threads, "busy_cpus", lambda: 0)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    return log


def test_each_local_worker_renders_its_shards_on_its_own_gpu(tmp_path, recorded):
    pipeline.render_shards(gan_spec(tmp_path, device="cuda"), [0, 1, 2, 3], Placement(("cuda:0", "cuda:1")), SilentBar())
    assert recorded["current"] == ["cuda:0", "cuda:1"]  # one worker per GPU, each on its own
    assert recorded["shards"] == {0: "cuda:0", 1: "cuda:1", 2: "cuda:0", 3: "cuda:1"}
    assert recorded["threads"] == [4, 4]  # the CPU cores divided by the workers, as for CPU work


def test_a_single_worker_renders_here_on_its_device(tmp_path, recorded):
    pipeline.render_shards(gan_spec(tmp_path), [0, 1], Placement(("cuda:1",)), SilentBar())
    assert recorded["shards"] == {0: "cuda:1", 1: "cuda:1"}
    assert recorded["current"] == [] and recorded["threads"] == []  # this process is left as it is


def test_cpu_workers_stay_on_the_cpu(tmp_path, recorded):
    pipeline.render_shards(tiny_spec(tmp_path), [0, 1], Placement(("cpu", "cpu")), SilentBar())
    assert recorded["shards"] == {0: None, 1: None}  # the procedural generator takes no device
    assert recorded["current"] == []


def test_placement_changes_neither_the_recorded_settings_nor_the_procedural_spec(tmp_path):
    spec = gan_spec(tmp_path, device="cuda", truncation_psi=0.5)
    placed = on_device(spec, "cuda:1")
    assert placed.generator_options == {"device": "cuda:1", "truncation_psi": 0.5}
    assert spec.generator_options == {"device": "cuda", "truncation_psi": 0.5}  # the index is written from this
    procedural = tiny_spec(tmp_path)
    assert on_device(procedural, "cuda:1") is procedural


def test_the_index_records_neither_the_device_nor_the_memory_budget(tmp_path):
    """A dataset started on one device resumes on another: where it runs is not part of it."""
    plain = gan_spec(tmp_path, truncation_psi=0.5)
    placed = gan_spec(tmp_path, device="cuda:1", memory_budget_mb=512, truncation_psi=0.5)
    assert placed.settings() == plain.settings()
    assert placed.settings()["generator_options"] == {"truncation_psi": 0.5}


def test_auto_workers_on_the_cpu_are_the_cores_up_to_the_shard_count(tmp_path, monkeypatch):
    seen = []
    monkeypatch.setattr(pipeline, "render_shards", lambda spec, shards, placement, bar: seen.append(list(placement.devices)))
    monkeypatch.setattr(pipeline, "usable_cpus", lambda: 8)
    run_sample(tiny_spec(tmp_path / "a"), workers="auto", progress=False)  # 2 shards
    run_sample(tiny_spec(tmp_path / "b", subjects=40), workers="auto", progress=False)  # 20 shards
    assert seen == [["cpu"] * 2, ["cpu"] * 8]


@pytest.mark.parametrize("kwargs, message", [
    ({"gpus_per_task": 1}, "gpus_per_task: only for backend ray"),
    ({"backend": "ray", "gpus_per_task": 0}, "gpus_per_task must be above 0 and at most 1"),
    ({"backend": "ray", "gpus_per_task": 2}, "gpus_per_task must be above 0 and at most 1"),
    ({"backend": "ray", "gpus_per_task": 0.5, "device": "cpu"}, "the device is the CPU"),
    ({"backend": "ray", "device": "cuda:1"}, "device cuda:1 pins a GPU of this machine; with backend ray"),
    ({"workers": 0}, "workers must be auto or at least 1"),
])
def test_impossible_placements_are_refused_before_anything_is_written(gpus, tmp_path, kwargs, message):
    """(The library names settings; the command line words them as flags, tested below.)"""
    gpus(2)
    device = kwargs.pop("device", "cuda")
    with pytest.raises(UserError, match=message):
        run_sample(gan_spec(tmp_path / "out", device=device), progress=False, **kwargs)
    assert not (tmp_path / "out").exists()


def test_the_command_line_takes_auto_workers_and_reports_bad_ones_in_one_line(tmp_path, capsys):
    assert main(["sample", "--out", str(tmp_path / "x"), "--gpus-per-task", "0.5", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == ["datagen sample: error: --gpus-per-task: only for --backend ray"]
    with pytest.raises(SystemExit) as exit_:
        main(["sample", "--out", str(tmp_path / "x"), "--workers", "some"])
    assert exit_.value.code == 2
    assert capsys.readouterr().err.strip().endswith("argument --workers: must be auto or a number, not 'some'")


def test_help_documents_gpu_placement(capsys):
    with pytest.raises(SystemExit):
        main(["sample", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for words in ("--workers auto|N", "cuda:(k mod the GPU count)", "more workers than GPUs share them",
                  "--gpus-per-task G", "--device DEVICE"):
        assert words in text, words
