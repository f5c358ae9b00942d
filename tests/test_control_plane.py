"""The control-plane benchmark (benchmarks/control_plane.py) at a small size: its report's entries, and
that what it builds and measures is right (the dataset verifies, the manifest holds the verdicts written)."""
from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest

from benchmarks import control_plane
from datagen.dataset.events import is_decision, read_log, verdicts
from datagen.dataset.shards import dumps, iter_tar_samples, read_index, tar_path

SUBJECTS, SLICES, SHARD_SIZE = 1200, 30, 8


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """The benchmark run once at SUBJECTS subjects: (its work folder, the report's results)."""
    base = tmp_path_factory.mktemp("control_plane")
    out, report = base / "work", base / "report"
    subprocess.run([sys.executable, "-m", "benchmarks.control_plane", "--out", str(out), "--subjects", str(SUBJECTS),
                    "--slices", str(SLICES), "--templates", "4", "--shard-size", str(SHARD_SIZE), "--report", str(report)],
                   check=True, cwd=control_plane.REPO, stdout=subprocess.DEVNULL)
    assert report.with_suffix(".md").read_text().startswith(f"# The control plane at {SUBJECTS:,} subjects")
    return out, json.loads(report.with_suffix(".json").read_text())


@pytest.mark.timeout(900)
def test_every_operation_is_measured_in_its_own_process(run):
    _, results = run
    ops = results["operations"]
    assert set(ops) == set(control_plane.OPERATIONS)
    for name, row in ops.items():
        for key in ("process_seconds", "seconds", "cpu_seconds", "peak_rss_mb"):
            assert math.isfinite(row[key]) and row[key] > 0, (name, key)
        assert row["seconds"] <= row["process_seconds"], name
        assert 10 < row["peak_rss_mb"] < control_plane.PEAK_RSS_GOAL_MB, name  # this process's, not the parent's
    assert len(results["checks"]) == 6 and results["machine"]["load_average"]


def test_the_build_scales_with_the_subjects(run):
    out, results = run
    build = results["build"]
    assert build["shards"] == -(-SUBJECTS // SHARD_SIZE)
    for events in build["events"].values():  # a verdict per subject, and a slip and its undo for a few
        assert SUBJECTS <= events <= SUBJECTS * (1 + 4 * control_plane.UNDO_RATE) + 20
    slices = sorted((out / "dataset" / "preflags-slices").glob("slice-*.json"))
    assert len(slices) == SLICES
    assert results["operations"]["merge"]["subjects"] == SUBJECTS == results["operations"]["verify"]["subjects"]


def test_the_manifest_holds_the_verdicts_in_the_logs(run):
    out, _ = run
    manifest = json.loads(control_plane.paths(out)["manifest"].read_text())
    assert manifest["header"]["counts"]["subjects"] == SUBJECTS
    logged = {}
    for reviewer in control_plane.REVIEWERS:
        events, problems = read_log(out / "labels" / f"{reviewer}.jsonl")
        assert not problems
        logged[reviewer] = {s: e.action for s, e in verdicts(events).items() if is_decision(e)}
    rejected = 0
    for row in manifest["subjects"]:
        votes = {r: v[row["subject"]] for r, v in logged.items() if row["subject"] in v}
        assert row["votes"] == votes
        rejected += row["verdict"] == "rejected"
        assert (row["verdict"] == "rejected") == ("bad" in votes.values())  # policy any-bad
    assert 0 < rejected < SUBJECTS


def test_big_subjects_are_their_templates_under_their_own_ids(run):
    out, _ = run
    templates = dict(iter_tar_samples(tar_path(out / "template", 0)))
    index = read_index(out / "dataset")
    shard = index["shards"][-1]
    for key, fields in iter_tar_samples(tar_path(out / "dataset", len(index["shards"]) - 1)):
        number = int(key.removeprefix("subj"))
        template = templates[f"subj{number % len(templates):08d}"]
        meta = json.loads(template["json"])
        assert fields["json"] == dumps(dict(meta, subject_id=key, subject_index=number))
        assert {f: b for f, b in fields.items() if f != "json"} == {f: b for f, b in template.items() if f != "json"}
    assert key == shard["subjects"][-1]
