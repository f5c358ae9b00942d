"""The recipe benchmark (benchmarks/panolam_recipe.py): its report shows the commands that ran."""
from __future__ import annotations

import argparse
import json

from benchmarks import panolam_recipe
from benchmarks.common import REPORTS


def test_the_report_shows_the_training_options_that_were_passed():
    res = json.loads((REPORTS / "panolam_recipe.json").read_text())
    res.pop("train_options", None)
    plain = panolam_recipe.markdown(res)
    assert f"--time-limit {res['time_limit_s']}\n" in plain  # a report from before the option: the command as it ran
    res.update(subjects=60, test_count=12, train_options="--lr-floor 0.5")
    text = panolam_recipe.markdown(res)
    assert "datagen sample --out data --subjects 60 " in text and "--test-count 12 " in text
    assert f"--time-limit {res['time_limit_s']} --lr-floor 0.5\n" in text


def test_a_dataset_begun_earlier_is_resumed_not_taken_as_it_is(tmp_path, monkeypatch):
    ran = []
    monkeypatch.setattr(panolam_recipe, "run", lambda command, *argv, cwd: ran.append((command, *argv)))
    monkeypatch.setattr(panolam_recipe, "collect", lambda out, args: {})
    args = argparse.Namespace(out=tmp_path, subjects=8, test_count=2, seed=3, time_limit=1, steps=None,
                              train_options="")
    panolam_recipe.measure(args)
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "index.json").write_text("{}")  # an interrupted generation leaves the index first
    panolam_recipe.measure(args)
    first, second = (r for r in ran if r[:2] == ("datagen", "sample"))
    assert "--resume" not in first and "--resume" in second


def test_the_report_of_a_finished_run_names_the_settings_it_ran_with(tmp_path, monkeypatch):
    monkeypatch.setattr(panolam_recipe, "run", lambda command, *argv, cwd: None)
    ran_with = argparse.Namespace(out=tmp_path, subjects=8, test_count=2, seed=3, time_limit=60, steps=None,
                                  train_options="--lr-floor 0.5")
    real_collect = panolam_recipe.collect
    monkeypatch.setattr(panolam_recipe, "collect", lambda out, args: {})
    panolam_recipe.measure(ran_with)
    run = tmp_path / "runs" / "r1"
    (run / "eval-test").mkdir(parents=True)
    view = {m: 10.0 for m in ("psnr", "psnr_fg", "ssim", "ssim_fg")}
    scores = {"per_view": {"all": view, "novel": view}}
    (run / "eval-test" / "eval.json").write_text(json.dumps(
        {**scores, "baselines": {"untrained": scores}, "subjects": 2, "reconstruct_s_median": 0.1}))
    (run / "train.log").write_text("step 1: loss 1, PSNR 12.00 dB\nstep 2: loss 1, PSNR 13.00 dB\n")
    today = argparse.Namespace(out=tmp_path, subjects=548, test_count=48, seed=61043, time_limit=1200, steps=None,
                               train_options="--lr-floor 0.9")  # --report-only with other defaults
    res = real_collect(tmp_path, today)
    assert (res["seed"], res["subjects"], res["test_count"], res["time_limit_s"], res["train_options"]) == \
        (3, 8, 2, 60, "--lr-floor 0.5")
    assert res["steps_done"] == 2 and res["train_psnr_last_200"] == 12.5
    assert "training batches scored 12.50 dB over the last 200 steps" in panolam_recipe.markdown(
        {**res, "figures": {**res["figures"], "baseline: mean colour template": res["figures"]["baseline: untrained"]}})
