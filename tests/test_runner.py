"""The one runner of shard work (``datagen.runner``): same results wherever tasks run, one progress
display, errors raised where the work was asked for, settings checked once."""
from __future__ import annotations

import os

import pytest

from datagen.cli import main as datagen_main
from datagen.command_line import SilentBar
from datagen.errors import SettingError
from datagen.runner import Placement, RunOptions, run_tasks


class CountingBar(SilentBar):
    def __init__(self):
        self.n = 0

    def update(self, n=1):
        self.n += n


def square_task(job, item, device, report):
    """Reports more than its share on purpose: the bar must still count each item's units once."""
    for _ in range(item + 3):
        report(1)
    return {"value": job * item * item, "device": device, "pid": os.getpid()}


def failing_task(job, item, device, report):
    if item == 2:
        raise ValueError(f"item {item} is bad")
    return item


def run(task, items, placement, job=3):
    bar = CountingBar()
    out = dict(run_tasks(task, job, items, [i + 1 for i in items], placement, bar))
    return [out[i] for i in range(len(items))], bar.n


def test_workers_give_what_this_process_gives_and_the_bar_counts_each_unit_once():
    items = [0, 1, 2, 3, 4]
    here, counted_here = run(square_task, items, Placement())
    there, counted_there = run(square_task, items, Placement(("cpu", "cpu")))
    assert [r["value"] for r in here] == [r["value"] for r in there] == [3 * i * i for i in items]
    assert counted_here == counted_there == sum(i + 1 for i in items)
    assert {r["pid"] for r in here} == {os.getpid()}
    assert os.getpid() not in {r["pid"] for r in there}  # worker processes, not this one
    assert {r["device"] for r in there} == {"cpu"}


@pytest.mark.parametrize("devices", [("cpu",), ("cpu", "cpu")])
def test_a_task_error_is_raised_here(devices):
    with pytest.raises(ValueError, match="item 2 is bad"):
        run(failing_task, [0, 1, 2, 3], Placement(devices))


def test_no_items_runs_nothing():
    assert run(square_task, [], Placement(("cpu", "cpu"))) == ([], 0)


@pytest.mark.parametrize("kwargs, message", [
    ({"backend": "slurm"}, "{backend} 'slurm': choose local or ray"),
    ({"ray_address": "1.2.3.4:6379"}, "{ray_address}: only with {backend} ray"),
    ({"devices": ()}, "{workers} must be at least 1"),
])
def test_placement_is_checked_where_it_is_made(kwargs, message):
    with pytest.raises(SettingError) as e:
        Placement(**kwargs)
    assert e.value.template == message


def test_ray_tasks_take_one_cpu_unless_told():
    assert RunOptions(workers=2).placement() == Placement(("cpu", "cpu"))
    assert RunOptions(backend="ray").placement().threads == 1
    assert RunOptions(backend="ray").placement(4).threads == 4


def test_verify_reports_the_same_with_workers_and_in_parts(tiny_dataset, capsys):
    assert datagen_main(["verify", str(tiny_dataset), "--quiet"]) == 0
    whole = capsys.readouterr().out
    assert datagen_main(["verify", str(tiny_dataset), "--quiet", "--workers", "2"]) == 0
    assert capsys.readouterr().out == whole
    parts = []
    for k in range(2):
        assert datagen_main(["verify", str(tiny_dataset), "--quiet", "--shard-index", str(k), "--num-shards", "2"]) == 0
        parts.append(capsys.readouterr().out)
    assert "OK: 2/2 shards complete and valid, 3 subjects" in whole
    assert parts == ["OK: 1/1 shards complete and valid, 2 subjects\n", "OK: 1/1 shards complete and valid, 1 subject\n"]
    assert datagen_main(["verify", str(tiny_dataset), "--ray-address", "x:1"]) == 2
    assert capsys.readouterr().err.strip().endswith("--ray-address: only with --backend ray")


def test_a_ray_failure_that_is_not_the_tasks_own_names_the_item(monkeypatch):
    """A worker that dies (not an error of the task) is reported as the item that was lost."""
    ray = pytest.importorskip("ray", reason="the ray backend needs the optional extra")
    from contextlib import contextmanager
    from types import SimpleNamespace

    import datagen.raycluster as raycluster

    class DyingCluster:
        exceptions = ray.exceptions

        def nodes(self):
            return [{"Alive": True, "Resources": {"CPU": 2}}]

        def remote(self, **options):
            return lambda function: SimpleNamespace(remote=lambda task, job, item, *rest: item)  # ref = the item

        def wait(self, refs, num_returns=1):
            return refs[:1], refs[1:]

        def get(self, ref):
            raise ray.exceptions.WorkerCrashedError()

        def cancel(self, ref):
            pass

    @contextmanager
    def connection(address):
        yield DyingCluster()

    monkeypatch.setattr(raycluster, "ray_connection", connection)
    with pytest.raises(RuntimeError, match="^shard 7 failed on Ray \\(WorkerCrashedError\\)"):
        list(run_tasks(square_task, 1, [7, 8], [1, 1], Placement(backend="ray"), CountingBar(),
                       lambda shard: f"shard {shard}"))
