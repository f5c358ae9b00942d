"""The shape of a pre-flag detector: measure one subject, learn the dataset's baseline, score, explain.

A detector turns every subject into a score in [0, 1] (``FLAG_AT`` and above flags it) and a short
explanation naming the view and the number it measured. Scores only order the review queue;
nothing is ever deleted. Each detector is one class in its own module, holding its settings.

Calibration of the union (``calibrated_cut``): twelve detectors each at its own threshold add up,
so the cut of each is raised, per dataset, until the share of clean subjects the union flags is
at most ``FALSE_ALARM_RATE``. Each detector gets the tail probability ``FALSE_ALARM_RATE / K``
(K detectors; the union's share is at most the sum, whatever their dependence). Its null, the
distribution of its evidence on clean subjects, is estimated from the bulk of the dataset: above
the median, an exponential tail whose decay is the maximum-likelihood fit to the subjects between
the median and the 90th percentile, those above the 90th percentile counted as censored there
(defects, a minority, sit in the top few percent and only say "at least this far"). An exponential
tail is exact for a Laplace null and conservative for a normal one (a normal's tail is thinner);
tails heavier than exponential beyond the 90th percentile cannot be seen from the bulk and flag
more. A dataset whose bulk spreads wide gets a higher cut; one whose bulk is tight, or a point
mass (most subjects measure nothing), keeps the detector's own threshold, which is the floor.
Evidence is the ramp's measure in units of the detector's threshold (1 at its own threshold, 0
where nothing was found), so the fit is linear in what the detector measures, not in the score's
bent ramp. On synthetic nulls (12 detectors, 64 to 3000 subjects; benchmarks/reports/preflags_tuning.md)
the union flags 3.1-3.5 % of a Laplace null, 1.9-2.6 % of a Student t with 5 degrees of freedom,
1.3-1.7 % of a gamma, at most 0.1 % of a normal one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .imaging import ramp

FLAG_AT = 0.5  # a detector flags a subject when its score is at least this
FALSE_ALARM_RATE = 0.03  # share of clean subjects the union of all detectors may flag, on any dataset
NULL_QUANTILES = (0.5, 0.9)  # the null's tail starts at the first, the fit is censored at the second
MIN_SUBJECTS = 20  # fewer measured subjects and a detector keeps its own threshold (too few for a fit)


@dataclass
class Flag:
    """One detector's verdict on one subject: score in [0, 1], what it measured (``value``), why.

    ``ratio``: the saturation over the threshold of the ramp (``imaging.ramp``) that gave the score;
    None where the score is not such a ramp (the detector is then not calibrated)."""

    score: float
    why: str
    value: float | None = None
    ratio: float | None = None


def ramp_flag(m: float, t: float, sat: float, why: str, value: float | None = None) -> Flag:
    """The Flag of ``imaging.ramp(m, t, sat)`` (0.5 at the threshold ``t``, 1 at ``sat``), its ratio kept."""
    return Flag(ramp(m, t, sat), why, value, sat / t)


def evidence(score: float, ratio: float) -> float:
    """A ramp's measure in units of its threshold, from its score: 2 score below FLAG_AT, then
    linear up to ``ratio`` at a score of 1 (a saturated score reads as ``ratio``, a lower bound)."""
    if score <= FLAG_AT:
        return score / FLAG_AT
    return 1.0 + (score - FLAG_AT) / (1.0 - FLAG_AT) * (ratio - 1.0)


def calibrated_cut(levels, tail: float) -> float:
    """The evidence (units of the detector's threshold, at least 1) above which a subject of the
    dataset's null has probability ``tail``: P(x > u + y) = P(x > u) exp(-y / decay) above the
    median u, decay the censored maximum-likelihood fit (exceedances of u, capped at the 90th
    percentile c: their sum over the number below c). ``levels``: every measured subject's
    evidence. 1 with fewer than MIN_SUBJECTS levels or nothing between u and c (a point mass)."""
    x = np.asarray(levels, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size < MIN_SUBJECTS:
        return 1.0
    u, c = np.quantile(x, NULL_QUANTILES)
    above = x[x > u] - u
    events = int((above <= c - u).sum())
    if events == 0:
        return 1.0
    decay = float(np.minimum(above, c - u).sum()) / events
    return max(1.0, float(u + decay * math.log(above.size / x.size / tail)))


def recalibrated(flag: Flag, cut: float) -> float:
    """The score of ``flag`` with its threshold at evidence ``cut`` (at most the ramp's ``ratio``, so a
    saturated score stays flagged) and its saturation at ``cut * ratio``: FLAG_AT exactly at the cut.
    Unchanged for a cut of 1 or a flag that is not a ramp."""
    if flag.ratio is None or cut <= 1.0:
        return flag.score
    cut = min(cut, flag.ratio)
    return ramp(evidence(flag.score, flag.ratio), cut, cut * flag.ratio)


class Detector:
    """Base class. ``measure`` runs in the workers on one subject (a small dict, or None when it
    does not apply); ``baseline`` sees every subject's measurements; ``score`` uses both. The
    ``Settings`` dataclass of a subclass holds its thresholds. ``calibrated``: its scores are ramps
    (``ramp_flag``) whose cut the dataset's null raises (see the module docstring)."""

    name = ""
    description = ""
    calibrated = True

    @dataclass(frozen=True)
    class Settings:
        pass

    def __init__(self, settings=None):
        self.settings = settings if settings is not None else self.Settings()

    def measure(self, views) -> dict | None:
        raise NotImplementedError

    def baseline(self, measured: list) -> object:
        """Dataset statistics from every subject's measurement (None entries: not measured)."""
        return None

    def score(self, m: dict | None, base, index: int, keys: list) -> Flag:
        raise NotImplementedError

    def threshold(self):
        """The measure's threshold as reported in the report's header."""
        return None

    def header(self, cut: float = 1.0) -> dict:
        """The report header's entry; ``cut``: the calibrated threshold in units of the measure's own."""
        return {"threshold": FLAG_AT, "measure_threshold": self.threshold(), "calibrated_cut": round(cut, 4),
                "description": self.description}
