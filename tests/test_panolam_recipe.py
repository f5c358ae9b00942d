"""The recipe benchmark (benchmarks/panolam_recipe.py): its report shows the commands that ran."""
from __future__ import annotations

import json

from benchmarks import panolam_recipe
from benchmarks.common import REPORTS


def test_the_report_shows_the_training_options_that_were_passed():
    res = json.loads((REPORTS / "panolam_recipe.json").read_text())
    plain = panolam_recipe.markdown(res)
    assert "--time-limit 1200\n" in plain  # a report from before the option: the command as it ran
    res.update(subjects=548, test_count=48, train_options="--lr-floor 0.9")
    text = panolam_recipe.markdown(res)
    assert "datagen sample --out data --subjects 548 " in text and "--test-count 48 " in text
    assert "--time-limit 1200 --lr-floor 0.9\n" in text
