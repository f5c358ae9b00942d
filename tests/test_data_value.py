"""The data study (benchmarks/data_value.py): its statistics, and a whole study at toy size that
resumes without redoing finished stages."""
from __future__ import annotations

import json
import math

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
