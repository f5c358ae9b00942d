"""The review window and the session behind it: a person looks at generated heads and types verdicts.

:mod:`.session` (the queue, verdicts, undo, triage pages and commits; no window) is imported here
at once; the window's names (pyvista) are imported when first asked for, so that the session and
the queue's items need neither pyvista nor VTK.
"""
from importlib import import_module

from .session import FLAG_REASON, QueueItem, ReviewSession

_LAZY = {"ReviewApp": "app", "Window": "window", "fit_window": "window", "BACKGROUND": "layout", "COLORS": "layout",
         "HELP": "layout", "Layout": "layout", "Prefetcher": "prefetch", "polydata": "surface",
         "surface_actor": "surface", "surface_mesh": "surface"}
__all__ = ["FLAG_REASON", "QueueItem", "ReviewSession", *_LAZY]


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(import_module(f".{_LAZY[name]}", __name__), name)
