"""Automatic pre-flags: cheap, explainable per-subject scores so reviewers see the worst subjects first.

Each detector (one module each; ``registry.DETECTORS`` lists them in report order) gives every subject
a score in [0, 1] (0.5 and above means flagged) and a short explanation naming the view and the number
it measured. Scores only order the review queue; nothing is deleted.

    janus        a face on the back of the head (face detectors, an eye-pair cascade; back against front view)
    flat_back    a flattened or truncated back of the head (depth of the back view)
    seam         a discontinuity down the back (colour, or a step in depth)
    blurry_back  a soft outline or smeared colour at the back, against the front
    floaters     silhouette parts detached from the head
    haze         semi-transparent material around the head
    holes        see-through holes in the silhouette and craters in the depth
    washed_out   a faded texture: its most saturated pixels
    blur         soft silhouette edges
    empty        (almost) empty views, subjects that do not decode
    implausible  mask area or depth far from the dataset
    duplicate    near-duplicates of another subject

    from datagen.dataset.preflags import write_preflags
    from datagen.runner import Placement
    from labeling_tool.preflags import score_dataset

    if __name__ == "__main__":  # local workers start in fresh processes, which import the calling script
        write_preflags("/data/heads", score_dataset("/data/heads", progress=True, placement=Placement(("cpu", "cpu"))))

The report format is described in ``datagen.dataset.preflags``; ``label-tool auto`` is the command line.
"""
from .detector import FALSE_ALARM_RATE, FLAG_AT, Detector, Flag
from .scoring import extract, measure_subject, score, score_dataset
from .registry import DETECTOR_NAMES, DETECTORS
from .views import SubjectViews

__all__ = ["DETECTORS", "DETECTOR_NAMES", "FALSE_ALARM_RATE", "FLAG_AT", "Detector", "Flag", "SubjectViews",
           "extract", "measure_subject", "score", "score_dataset"]
