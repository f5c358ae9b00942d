"""The defect taxonomy is the one vocabulary of the generator, the pre-flags and the review window."""
from datagen.defects import DEFECT_CLASSES, DEFECTS, INJECTED, REASON_LABELS, REVIEW_REASONS
from datagen.dataset.events import REASONS
from datagen.generators.procedural import DEFECT_TYPES
from datagen.generators.procedural.inject import APPLY, APPLY_ORDER, SAMPLE
from labeling_tool.preflags.registry import DETECTOR_NAMES
from labeling_tool.review.session import FLAG_REASON


def test_every_class_has_one_detector_of_its_name_and_a_reviewer_reason():
    assert set(DETECTOR_NAMES) == set(DEFECTS) and len(DEFECTS) == len(DEFECT_CLASSES)
    assert all(c.reason in REVIEW_REASONS for c in DEFECT_CLASSES)
    assert REASONS == REVIEW_REASONS and set(REASON_LABELS) == set(REVIEW_REASONS)
    assert FLAG_REASON == {c.name: c.reason for c in DEFECT_CLASSES}


def test_the_generator_injects_exactly_the_injected_classes_under_their_names():
    assert DEFECT_TYPES == INJECTED
    assert set(SAMPLE) == set(APPLY) == set(INJECTED)
    assert sorted(APPLY_ORDER) == sorted(INJECTED)
    assert not {"hole"} & set(DEFECTS)  # one spelling: the class is "holes" everywhere
