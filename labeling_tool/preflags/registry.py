"""The detectors the pre-flags run, in report order."""
from __future__ import annotations

from .blur import Blur
from .duplicate import Duplicate
from .empty import Empty
from .floaters import Floaters
from .holes import Holes
from .implausible import Implausible
from .janus import Janus
from .washed_out import WashedOut

DETECTORS = (Janus(), Floaters(), Holes(), WashedOut(), Blur(), Empty(), Implausible(), Duplicate())
DETECTOR_NAMES = tuple(d.name for d in DETECTORS)
