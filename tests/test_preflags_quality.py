"""The pre-flag recall benchmark's seed rules: a reported run never uses a seed settings were chosen on."""
from __future__ import annotations

import pytest

from benchmarks import preflags_quality as pq


def test_tuning_seeds_are_recognised_and_written_as_ranges():
    for seed in (0, 9, 21, 51, 6197, pq.FRESH_SEEDS_FROM - 1):
        assert pq.is_tuning_seed(seed), seed
    for seed in (pq.FRESH_SEEDS_FROM, 1656354273, 989724296):
        assert not pq.is_tuning_seed(seed), seed
    assert pq.seed_ranges((8, 0, 1, 2, 5, 7)) == "0-2, 5 and 7-8"
    assert pq.seed_ranges((5,)) == "5"
    assert pq.seed_ranges(pq.TUNING_SEEDS).endswith("and 6197")


def test_fresh_seeds_skip_tuning_seeds_and_repeats(monkeypatch):
    draws = iter([6197, 3, 123456, 123456, 2 ** 31 + 7000, 98765])  # 2**31 + 7000 wraps to 7000

    def urandom(n):
        return next(draws).to_bytes(n, "little")

    monkeypatch.setattr(pq.os, "urandom", urandom)
    assert pq.fresh_seeds(3) == [123456, 7000, 98765]


@pytest.mark.parametrize("argv, says", [
    (["--resolutions", "96", "128", "--seeds", "2000", "3000", "4000"], "--seeds: 3 seeds for 2 runs"),
    (["--resolutions", "96", "128", "--seeds", "2000", "6197"], "--seeds: 6197 is a tuning seed"),
    (["--resolutions", "96", "--seeds", "40"], "--seeds: 40 is a tuning seed"),
])
def test_seeds_given_by_hand_are_checked_before_anything_is_generated(argv, says, tmp_path, monkeypatch):
    monkeypatch.setattr(pq, "generate", lambda *a, **k: pytest.fail("generated a dataset"))
    with pytest.raises(SystemExit, match=says):
        pq.main([*argv, "--keep", str(tmp_path / "data"), "--out", str(tmp_path / "report")])
    assert not (tmp_path / "data").exists() and not list(tmp_path.iterdir())
