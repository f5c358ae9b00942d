"""The detectors the pre-flags run, in report order."""
from __future__ import annotations

from .back import BlurryBack, FlatBack, Seam
from .blur import Blur
from .duplicate import Duplicate
from .empty import Empty
from .floaters import Floaters
from .haze import Haze
from .holes import Holes
from .implausible import Implausible
from .janus import Janus
from .washed_out import WashedOut

DETECTORS = (Janus(), FlatBack(), Seam(), BlurryBack(), Floaters(), Haze(), Holes(), WashedOut(), Blur(), Empty(),
             Implausible(), Duplicate())
DETECTOR_NAMES = tuple(d.name for d in DETECTORS)
