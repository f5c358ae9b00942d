"""The shape of a pre-flag detector: measure one subject, learn the dataset's baseline, score, explain.

A detector turns every subject into a score in [0, 1] (``FLAG_AT`` and above flags it) and a short
explanation naming the view and the number it measured. Scores only order the review queue;
nothing is ever deleted. Each detector is one class in its own module, holding its settings.

Calibration of the union (``calibrated_cuts``): twelve detectors each at its own threshold add up,
so the cut of each is raised, per dataset, until the share of clean subjects the union flags is
at most ``FALSE_ALARM_RATE``; the union's share is at most the sum of the detectors' tail
probabilities, whatever their dependence, so the rate is split into shares that add up to it.

The null of a detector, the distribution of its evidence on clean subjects, is estimated from the
bulk of the dataset (``null_tail``): above the median, an exponential tail whose decay is the
maximum-likelihood fit to the subjects between the median and the 90th percentile, those above
the 90th percentile counted as censored there (its own defects, a minority, sit in the top few
percent and only say "at least this far"). The fit leaves out every subject that another detector
flags: defects of other kinds would otherwise fill the bulk (a haze defect's detached wisps on
floaters, a quarter of a dataset defective for other reasons). First the others flag at their own
thresholds, then (``NULL_ROUNDS``) at the cuts this gave: that returns to the fit the clean
subjects heavy-tailed detectors flag at their own thresholds (a quarter of a Laplace null; a fit to
the rest alone is noisier and flags more).

The shares: a detector whose null stays below its own threshold with less than an equal share
(``FALSE_ALARM_RATE / K``, K detectors), a point mass (most subjects measure nothing) or a tight
bulk, keeps its own threshold, which is the floor, and claims only its fitted tail there; the rest
of the rate is split equally among the others, each cut where its tail reaches its share.
Detectors that are not calibrated (absolute counts) and fits of fewer than ``MIN_SUBJECTS``
subjects claim an equal share. A dataset whose bulk spreads wide gets a higher cut.

An exponential tail is exact for a Laplace null and conservative for a normal one (a normal's tail
is thinner); tails heavier than exponential beyond the 90th percentile cannot be seen from the bulk
and flag more, and so does a class of defects above a tenth of the dataset (it lifts its own
detector's 90th percentile). Evidence is the ramp's measure in units of the detector's threshold
(1 at its own threshold, 0 where nothing was found), so the fit is linear in what the detector
measures, not in the score's bent ramp. The union's share on synthetic nulls (12 detectors, 64 to
3000 subjects) is in benchmarks/reports/preflags_tuning.md.
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
NULL_ROUNDS = 2  # fits of each null: without what others flag at their own thresholds, then at their cuts


@dataclass(slots=True)
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


def null_tail(levels) -> tuple[float, float, float] | None:
    """The null's tail above the median u of the finite ``levels`` (evidence): (u, decay, P(x > u)),
    P(x > u + y) = P(x > u) exp(-y / decay); decay the censored maximum-likelihood fit (exceedances
    of u capped at the 90th percentile c: their sum over the number below c), 0 for a point mass
    (nothing between u and c). None with fewer than MIN_SUBJECTS levels."""
    x = np.asarray(levels, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size < MIN_SUBJECTS:
        return None
    u, c = np.quantile(x, NULL_QUANTILES)
    above = x[x > u] - u
    events = int((above <= c - u).sum())
    decay = float(np.minimum(above, c - u).sum()) / events if events else 0.0
    return float(u), decay, above.size / x.size


def tail_beyond(fit: tuple[float, float, float], level: float) -> float:
    """P(x > ``level``) under the fitted tail ``fit`` (``null_tail``); 0 beyond a point mass, 1 below u."""
    u, decay, share = fit
    if level <= u:
        return 1.0
    return share * math.exp(-(level - u) / decay) if decay > 0 else 0.0


def calibrated_cut(levels, tail: float) -> float:
    """The evidence (units of the detector's threshold, at least 1) above which a subject of the
    null ``levels`` (every measured subject's evidence) has probability ``tail`` (``null_tail``).
    1 with fewer than MIN_SUBJECTS levels or a point mass."""
    return cut_of(null_tail(levels), tail)


def cut_of(fit: tuple[float, float, float] | None, tail: float) -> float:
    """The evidence (at least 1) where the fitted tail ``fit`` (``null_tail``) reaches ``tail``; 1 for
    no fit or a point mass."""
    if fit is None or fit[1] == 0.0:
        return 1.0
    u, decay, share = fit
    return max(1.0, u + decay * math.log(share / tail))


def calibrated_cuts(levels, own, rate: float, calibrated=None, caps=None) -> tuple[np.ndarray, np.ndarray]:
    """(cuts, shares): every detector's cut (evidence, at least 1) and its share of ``rate``, the rule
    of the module docstring. ``levels``: (subjects, detectors) evidence, NaN where not measured;
    ``own``: True where the detector flags the subject at its own threshold; ``calibrated``:
    (detectors,), False keeps the own threshold (default all True); ``caps``: the evidence from which
    a verdict no longer depends on the cut (``recalibrated``: a ramp's ``ratio``, where its score
    saturates; 0 for a score that is not a ramp; default none)."""
    x = np.asarray(levels, dtype=np.float64)
    own = np.asarray(own, dtype=bool)
    n_det = x.shape[1]
    cal = np.ones(n_det, bool) if calibrated is None else np.asarray(calibrated, dtype=bool)
    cap = np.full(x.shape, np.inf) if caps is None else np.asarray(caps, dtype=np.float64)
    measured = np.isfinite(x)
    cuts, shares = np.ones(n_det), np.full(n_det, rate / max(1, n_det))
    for _ in range(NULL_ROUNDS):
        flagged = own & ((cuts <= 1.0) | (np.where(measured, x, -np.inf) >= np.minimum(cuts, cap)))
        others = flagged.sum(axis=1, keepdims=True) - flagged
        fits = [None] * n_det
        for k in np.flatnonzero(cal):
            null = measured[:, k] & (others[:, k] == 0)
            fits[k] = null_tail(x[null if null.sum() >= MIN_SUBJECTS else measured[:, k], k])
        need = [tail_beyond(f, 1.0) if f is not None else rate / n_det for f in fits]
        budget, left = rate, sorted(range(n_det), key=lambda k: need[k])
        while left and need[left[0]] < budget / len(left):
            k = left.pop(0)
            shares[k], cuts[k] = need[k], 1.0
            budget -= need[k]
        for k in left:
            shares[k] = budget / len(left)
            cuts[k] = cut_of(fits[k], shares[k])
    return cuts, shares


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

    def header(self, cut: float = 1.0, share: float | None = None) -> dict:
        """The report header's entry; ``cut``: the calibrated threshold in units of the measure's own;
        ``share``: its part of the union's false-alarm rate (None without calibration)."""
        return {"threshold": FLAG_AT, "measure_threshold": self.threshold(), "calibrated_cut": round(cut, 4),
                "false_alarm_share": None if share is None else round(share, 6), "description": self.description}
