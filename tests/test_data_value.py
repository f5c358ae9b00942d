"""The data study (benchmarks/data_value.py): its statistics, and a whole study at toy size that
resumes without redoing finished stages."""
from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
from scipy import stats

from benchmarks import data_value


def test_paired_differences_have_students_interval():
    rng = np.random.default_rng(3)
    a = {f"s{i}": float(v) for i, v in enumerate(rng.normal(20, 2, 40))}
    b = {k: v - 1.0 + float(rng.normal(0, 0.5)) for k, v in a.items()}
    b["only in b"] = 0.0
    got = data_value.paired(a, b)
    d = np.array([a[k] - b[k] for k in a])
    lo, hi = stats.ttest_1samp(d, 0.0).confidence_interval(0.95)
    assert got["n"] == 40 and math.isclose(got["mean"], d.mean())
    assert np.allclose(got["ci95"], [lo, hi])
    assert math.isnan(data_value.paired({"x": 1.0}, {"x": 0.5})["ci95"][0])  # one subject: no interval


def test_step_lines_are_read_with_and_without_the_data_time(tmp_path):
    (tmp_path / "train.log").write_text(
        "perceptual loss: D-SSIM\n"
        "step 1: loss 0.9000, PSNR 12.50 dB, lr 4.00e-06, 2.31 s/step\n"
        "step 2: loss 0.8000, PSNR 13.25 dB, lr 8.00e-06, 2.10 s/step, 0.041 s data\n"
        "step 2: loss 0.8000, PSNR 13.25 dB; checkpoint in x, log in y\n")
    rows = data_value._log_steps(tmp_path)
    assert [r["step"] for r in rows] == [1, 2] and rows[1]["psnr"] == 13.25 and rows[1]["data_s"] == 0.041
    assert math.isnan(rows[0]["data_s"]) and data_value._steps_done(tmp_path) == 2


def test_arms_of_the_last_report_are_carried_when_the_folder_lost_them(tmp_path):
    machine = {"cpu_model": "AMD EPYC", "cpu_family_model": "family 23 model 1", "cpu_capability": "AVX2",
               "git_revision": "069367a (from an archive)", "date": "2026-12-07T00:00:15+00:00"}
    old = {"machine": machine, "seeds": {"held_out": 1}, "settings": {"steps": 10, "batch_size": 2},
           "arms": {"a": {"psnr": 1.0}, "b": {"psnr": 2.0}, "gone": {"psnr": 3.0}}}
    report = tmp_path / "study.json"
    report.write_text(json.dumps(old))
    assert data_value.previous_report(report, {"steps": 10}, {"held_out": 1}) == old
    assert data_value.previous_report(report, {"steps": 20}, {"held_out": 1}) is None  # other settings: not one study
    assert data_value.previous_report(report, {"steps": 10}, {"held_out": 2}) is None
    assert data_value.previous_report(tmp_path / "none.json", {"steps": 10}, {"held_out": 1}) is None
    here = {"host": "AMD EPYC (family 26 model 2, AVX512), revision 5df2a21", "from_step": 0}
    arms = data_value.carry({"b": {"psnr": 5.0, "hosts": [here]}}, ["b", "a", "new"], old)
    assert list(arms) == ["b", "a"] and arms["b"] == {"psnr": 5.0, "hosts": [here]}  # the folder's own wins
    assert arms["a"]["psnr"] == 1.0 and arms["a"]["carried_from"] == machine["date"]
    assert "hosts" not in arms["a"] and data_value.carry({}, ["a"], None) == {}
    assert data_value.host_label(machine) == "AMD EPYC (family 23 model 1, AVX2), revision 069367a"
    lines = data_value.trained_on(arms)
    assert lines[0] == "Trained on AMD EPYC (family 26 model 2, AVX512), revision 5df2a21: b; hosts not recorded: a."
    assert machine["date"] in lines[1] and lines[1].endswith(": a.")


@pytest.mark.slow
@pytest.mark.timeout(3600)  # about 5 minutes on 2 idle cores: 6 arms, 4 datasets
def test_a_toy_study_runs_every_arm_and_resumes(tmp_path, monkeypatch, toy_study_reports):
    reports = toy_study_reports
    monkeypatch.setattr(data_value, "REPORTS", reports)
    argv = ["--out", str(tmp_path / "study"), "--steps", "2", "--scale", "8", "16", "--held-out", "4",
            "--curation-subjects", "16"]
    assert data_value.main(argv) == 0
    res = json.loads((reports / "data_value.json").read_text())
    assert set(res["arms"]) == {"scale-8", "scale-16", "curation-as-is", "curation-auto", "curation-truth",
                                "curation-random"}
    c = res["curation"]
    arms = res["arms"]
    assert arms["curation-as-is"]["train_subjects"] == 16
    assert arms["curation-truth"]["train_subjects"] == 16 - c["defective"]
    assert arms["curation-auto"]["train_subjects"] == arms["curation-random"]["train_subjects"] == 16 - c["flagged"]
    trained = c["training"]
    assert {a: t["subjects"] for a, t in trained.items()} == {a: r["train_subjects"] for a, r in arms.items()
                                                              if a.startswith("curation-")}
    assert trained["curation-as-is"]["defective"] == c["defective"] and trained["curation-truth"]["defective"] == 0
    assert trained["curation-auto"]["defective"] == c["defective"] - c["flagged_defective"]
    assert sum(trained["curation-as-is"]["defect_types"].values()) >= c["defective"]
    assert all(r["steps"] == 2 and r["defects"]["subjects"] == 4 for r in arms.values())
    assert "scale-16 - scale-8" in res["comparisons"]
    assert (reports / "data_value_scale.png").exists() and (reports / "data_value_scale-8.png").exists()
    stamp = {p: p.stat().st_mtime_ns for p in (tmp_path / "study" / "runs").rglob("*") if p.is_file()}
    assert data_value.main(argv) == 0  # all done: nothing is trained or evaluated again
    assert stamp == {p: p.stat().st_mtime_ns for p in (tmp_path / "study" / "runs").rglob("*") if p.is_file()}
    assert all(r["hosts"] == [{"host": data_value.host_label(data_value.machine_info()), "from_step": 0}]
               for r in arms.values())
    shutil.rmtree(tmp_path / "study" / "runs" / "curation-truth")  # a folder that lost an arm keeps it from the report
    (tmp_path / "study" / "manifests" / "curation-truth.json").unlink()
    before = json.loads((reports / "data_value.json").read_text())
    assert data_value.main([*argv, "--report-only"]) == 0
    again = json.loads((reports / "data_value.json").read_text())
    assert again["arms"]["curation-truth"] == dict(arms["curation-truth"], carried_from=before["machine"]["date"])
    assert again["curation"] == c and again["comparisons"] == res["comparisons"]
    assert "From the report of" in (reports / "data_value.md").read_text()
