"""The recipe tuning benchmark (benchmarks/recipe_tuning.py): its candidates are valid `panolam
train` settings on seeds of their own, and a toy study trains, scores and compares them."""
from __future__ import annotations

import json

import pytest

from benchmarks import data_value, recipe_tuning
from panolam.checkpoints import read_checkpoint
from panolam.cli import _configs, build_parser


def test_candidates_are_training_options_that_differ_only_in_what_a_step_does_not_cost():
    costs = set()
    for name, (_, subjects, options) in recipe_tuning.CANDIDATES.items():
        args = build_parser().parse_args(["train", "--data", "d", "--manifest", "m", "--out", "r", *options])
        args.resume = False
        model, train = _configs(args)
        assert subjects >= 48, name
        costs.add((model, train.batch_size, train.views_per_sample, train.render_resolution))
    assert len(costs) == 1  # equal steps are equal time
    for a, b in recipe_tuning.COMPARISONS:
        assert a in recipe_tuning.CANDIDATES and b in recipe_tuning.CANDIDATES
    seeds = {recipe_tuning.TUNING_HELD_OUT_SEED, recipe_tuning.TUNING_POOL_SEED}
    assert not seeds & {data_value.HELD_OUT_SEED, data_value.POOL_SEED, data_value.DEFECT_SEED}


@pytest.mark.slow
@pytest.mark.timeout(3600)  # a few minutes on 2 idle cores: 3 candidates, 3 datasets
def test_a_toy_tuning_study_scores_and_compares_the_candidates(tmp_path, monkeypatch, toy_study_reports):
    reports = toy_study_reports
    monkeypatch.setattr(recipe_tuning, "REPORTS", reports)
    small = {a: (what, 8 if n == 48 else 12, options) for a, (what, n, options) in recipe_tuning.CANDIDATES.items()}
    monkeypatch.setattr(recipe_tuning, "CANDIDATES", small)
    argv = ["--out", str(tmp_path / "tuning"), "--steps", "2", "--held-out", "4",
            "--candidates", "readme", "subjects-500", "lr-8e-4"]
    assert recipe_tuning.main(argv) == 0
    res = json.loads((reports / "recipe_tuning.json").read_text())
    assert list(res["arms"]) == ["readme", "subjects-500", "lr-8e-4"]
    assert [r["train_subjects"] for r in res["arms"].values()] == [8, 12, 12]
    assert set(res["comparisons"]) == {"subjects-500 - readme", "lr-8e-4 - readme"}
    assert all(c["novel_psnr_fg"]["n"] == 4 for c in res["comparisons"].values())
    assert res["best"] in res["arms"] and (reports / "recipe_tuning_lr-8e-4.png").exists()
    trained = read_checkpoint(tmp_path / "tuning" / "runs" / "lr-8e-4")["train_config"]
    assert trained["lr"] == 8e-4 and trained["lr_floor"] == 0.9 and trained["steps"] == 2
    assert res["seeds"] == {"held_out": recipe_tuning.TUNING_HELD_OUT_SEED, "pool": recipe_tuning.TUNING_POOL_SEED}
