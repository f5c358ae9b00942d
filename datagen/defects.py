"""The defect taxonomy: every class of failure the toolkit knows, under one name each.

A class's name is the type the procedural generator injects (``--defect-types``, the ``truth/``
records), the pre-flag detector that looks for it (``labeling_tool.preflags``) and the key the
benchmarks match the two by; its ``reason`` is what a reviewer records for it (``REVIEW_REASONS``,
the verdict log's vocabulary). Classes that are not injected are found by their detector only.
"""
from __future__ import annotations

from dataclasses import dataclass

# What a reviewer can give as the reason of a "bad" verdict (keys 1-5 of the review window), and
# the short label shown for each.
REVIEW_REASONS = ("multiple_faces", "broken_back", "artifacts", "blur", "other")
REASON_LABELS = {"multiple_faces": "faces", "broken_back": "back", "artifacts": "artifacts", "blur": "blur",
                 "other": "other"}


@dataclass(frozen=True)
class DefectClass:
    name: str       # the one spelling: injected type, detector name, benchmark key
    reason: str     # the reviewer's reason for it (one of REVIEW_REASONS)
    injected: bool  # the procedural generator can inject it
    summary: str    # what it looks like


# Injected classes first, in the order the generator draws them from (changing it changes datasets).
DEFECT_CLASSES = (
    DefectClass("janus", "multiple_faces", True, "a second face on the back of the head"),
    DefectClass("flat_back", "broken_back", True, "the back of the head cut flat"),
    DefectClass("haze", "artifacts", True, "semi-transparent wisps near the head"),
    DefectClass("seam", "broken_back", True, "a step in surface and colour down the back"),
    DefectClass("blurry_back", "blur", True, "a smeared, soft back"),
    DefectClass("holes", "broken_back", True, "a see-through hole or a crater in the head"),
    DefectClass("floaters", "artifacts", True, "detached blobs"),
    DefectClass("washed_out", "artifacts", True, "faded texture"),
    DefectClass("blur", "blur", False, "soft silhouette edges in every view"),
    DefectClass("empty", "other", False, "views with (almost) nothing in them, or a subject that does not decode"),
    DefectClass("implausible", "other", False, "a mask area or depth far from the dataset's"),
    DefectClass("duplicate", "other", False, "a near-copy of another subject"),
)
DEFECTS = {c.name: c for c in DEFECT_CLASSES}
INJECTED = tuple(c.name for c in DEFECT_CLASSES if c.injected)
