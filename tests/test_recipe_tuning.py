"""The recipe tuning benchmark (benchmarks/recipe_tuning.py): its candidates are valid `panolam
train` settings on seeds of their own, each trains for the same CPU time, and a toy study trains,
scores and compares them."""
from __future__ import annotations

import argparse
import json

import pytest

from benchmarks import data_value, recipe_tuning
from labeling_tool.compiler import VERSION_NAME
from panolam.checkpoints import read_checkpoint
from panolam.cli import _configs, build_parser


def test_candidates_are_training_options_whose_step_cost_only_their_config_sets():
    costs = {}
    for name, (_, subjects, config, options) in recipe_tuning.CANDIDATES.items():
        args = build_parser().parse_args(["train", "--data", "d", "--manifest", "m", "--out", "r", "--config", config,
                                          *options])
        args.resume = False
        model, train = _configs(args)
        assert subjects >= 48 and model.name == config, name
        assert VERSION_NAME.match(name) and VERSION_NAME.match(f"{name}-train-eval")  # its manifests' names
        shape = (model.replace(name=""), train.batch_size, train.views_per_sample, train.render_resolution)
        assert costs.setdefault(config, shape) == shape  # same config, same cost: equal steps are equal time
    for a, b in recipe_tuning.COMPARISONS:
        assert a in recipe_tuning.CANDIDATES and b in recipe_tuning.CANDIDATES
    seeds = {recipe_tuning.TUNING_HELD_OUT_SEED, recipe_tuning.TUNING_POOL_SEED}
    assert not seeds & {data_value.HELD_OUT_SEED, data_value.POOL_SEED, data_value.DEFECT_SEED}


def test_a_cheaper_config_trains_for_more_steps_in_the_same_cpu_time(tmp_path):
    args = argparse.Namespace(out=tmp_path, steps=300, arms=list(recipe_tuning.CANDIDATES))
    study = recipe_tuning.TuningStudy(args)
    (tmp_path / "step-costs.json").write_text(json.dumps({"tiny": 6.0, "tiny+cross_only": 4.5}))
    assert study.training("lr-8e-4") == (300, ["--config", "tiny", *recipe_tuning.CANDIDATES["lr-8e-4"][3]])
    steps, options = study.training("cross-only")
    assert steps == 400 and options[:2] == ["--config", "tiny+cross_only"]
    only_tiny = recipe_tuning.TuningStudy(argparse.Namespace(out=tmp_path / "b", steps=300, arms=["readme"]))
    assert only_tiny.training("readme")[0] == 300 and not (tmp_path / "b" / "step-costs.json").exists()


@pytest.mark.slow
@pytest.mark.timeout(3600)  # several minutes on 2 idle cores: 3 candidates, 3 datasets, a step-cost measurement
def test_a_toy_tuning_study_scores_and_compares_the_candidates(tmp_path, monkeypatch, toy_study_reports):
    reports = toy_study_reports
    monkeypatch.setattr(recipe_tuning, "REPORTS", reports)
    small = {a: (what, 8 if n == 48 else 12, config, options)
             for a, (what, n, config, options) in recipe_tuning.CANDIDATES.items()}
    monkeypatch.setattr(recipe_tuning, "CANDIDATES", small)
    argv = ["--out", str(tmp_path / "tuning"), "--steps", "2", "--held-out", "4",
            "--candidates", "readme", "subjects-500", "cross-only"]
    assert recipe_tuning.main([*argv, "--prepare"]) == 0  # data and step costs, nothing trained
    study = tmp_path / "tuning"
    assert {p.name for p in study.iterdir()} >= {"held-out", "pool-8", "pool-12", "step-costs.json"}
    assert not (study / "runs").exists()
    assert recipe_tuning.main(argv) == 0
    res = json.loads((reports / "recipe_tuning.json").read_text())
    assert list(res["arms"]) == ["readme", "subjects-500", "cross-only"]
    assert [r["train_subjects"] for r in res["arms"].values()] == [8, 12, 12]
    assert set(res["comparisons"]) == {"subjects-500 - readme", "cross-only - readme"}
    assert all(c["novel_psnr_fg"]["n"] == 4 for c in res["comparisons"].values())
    assert res["best"] in res["arms"] and (reports / "recipe_tuning_cross-only.png").exists()
    costs = res["step_cpu_s"]
    assert costs["tiny+cross_only"] < costs["tiny"]  # no point self-attention: a cheaper step
    cross = res["arms"]["cross-only"]
    assert cross["steps"] == cross["planned_steps"] == round(2 * costs["tiny"] / costs["tiny+cross_only"])
    trained = read_checkpoint(tmp_path / "tuning" / "runs" / "cross-only")
    assert trained["train_config"]["lr"] == 8e-4 and trained["train_config"]["lr_floor"] == 0.9
    assert trained["model_config"]["point_self_attention"] is False
    assert res["seeds"] == {"held_out": recipe_tuning.TUNING_HELD_OUT_SEED, "pool": recipe_tuning.TUNING_POOL_SEED}
