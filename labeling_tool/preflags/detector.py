"""The shape of a pre-flag detector: measure one subject, learn the dataset's baseline, score, explain.

A detector turns every subject into a score in [0, 1] (``FLAG_AT`` and above flags it) and a short
explanation naming the view and the number it measured. Scores only order the review queue;
nothing is ever deleted. Each detector is one class in its own module, holding its settings.
"""
from __future__ import annotations

from dataclasses import dataclass

FLAG_AT = 0.5  # a detector flags a subject when its score is at least this


@dataclass
class Flag:
    """One detector's verdict on one subject: score in [0, 1], what it measured (``value``), why."""

    score: float
    why: str
    value: float | None = None


class Detector:
    """Base class. ``measure`` runs in the workers on one subject (a small dict, or None when it
    does not apply); ``baseline`` sees every subject's measurements; ``score`` uses both. The
    ``Settings`` dataclass of a subclass holds its thresholds."""

    name = ""
    description = ""

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

    def header(self) -> dict:
        return {"threshold": FLAG_AT, "measure_threshold": self.threshold(), "description": self.description}
