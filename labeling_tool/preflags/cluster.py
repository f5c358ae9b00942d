"""``label-tool auto --backend ray``: one Ray task per shard measures its subjects, this process scores.

The shards are checked and planned here (index, sidecars: the dataset folder must be shared with
the cluster's nodes, at the same path); each task reads and measures one shard's subjects with the
registry's detectors and returns their records, so the report equals a one-process run's apart
from its ``timing``.
"""
from __future__ import annotations

import time
from contextlib import closing

from datagen.command_line import progress_bar
from datagen.raycluster import ray_connection, ray_results
from datagen.shards import index_sha256

from .detector import FALSE_ALARM_RATE
from .scoring import finish, measure, plan
from .registry import DETECTORS


def _measure_shard(tasks: list) -> list:
    """Ray task: the (shard, record) pairs of one shard's planned subjects, in order."""
    return [measure(t + (DETECTORS,)) for t in tasks]


def score_on_ray(root, address: str | None = None, progress: bool = False, skip_incomplete: bool = False,
                 labels=None, false_alarm_rate: float | None = FALSE_ALARM_RATE) -> dict:
    """The report of the dataset at ``root`` measured by Ray tasks (see the module docstring);
    ``address`` as :func:`datagen.raycluster.ray_connection` takes it, ``labels`` and
    ``false_alarm_rate`` as in :func:`scoring.score_dataset`."""
    t0 = time.perf_counter()
    tasks, skipped = plan(root, skip_incomplete)
    by_shard: dict[str, list] = {}
    for t in tasks:
        by_shard.setdefault(t[0], []).append(t)
    bar = progress_bar(len(tasks), "subj", "preflags", progress)
    results: dict[str, list] = {}
    with ray_connection(address) as ray:
        remote = ray.remote(num_cpus=1)(_measure_shard)
        pending = {remote.remote(group): shard for shard, group in by_shard.items()}
        try:
            with closing(ray_results(ray, pending, "measuring {}")) as finished:
                for shard, records in finished:
                    results[shard] = records
                    bar.update(len(records))
        finally:
            bar.close()
    extracted = {"index_sha256": index_sha256(root), "records": [p for s in by_shard for p in results[s]],
                 "skipped_shards": skipped, "seconds": time.perf_counter() - t0}
    return finish(extracted, t0, {"backend": "ray", "tasks": len(by_shard)}, DETECTORS, labels, false_alarm_rate)
