"""User-facing errors: the command lines print them as one line and exit non-zero."""
from __future__ import annotations

import errno
import importlib


class UserError(Exception):
    """A mistake in the user's input or environment, stated in one line."""


class DatasetError(UserError):
    """A problem with a dataset on disk, stated in one line naming the file."""


class SettingError(UserError):
    """A setting's value, or a combination of settings, that cannot be used. The message names settings as
    ``{field_name}``: the library shows the field's name, a command line its flag (``--field-name``)."""

    def __init__(self, template: str):
        self.template = template
        super().__init__(self.worded(lambda name: name))

    def worded(self, name_of) -> str:
        """The message with each ``{setting}`` written as ``name_of(setting)`` (as it is, should a file name in
        it hold braces)."""
        try:
            return self.template.format_map(_Named(name_of))
        except (ValueError, IndexError, AttributeError):
            return self.template


class _Named(dict):
    def __init__(self, name_of):
        super().__init__()
        self.name_of = name_of

    def __missing__(self, key: str) -> str:
        return self.name_of(key)


class NotInstalled(UserError, ImportError):
    """An optional library, or a file it ships, is missing; the one line says what to install."""


def missing_extra(extra: str, what: str, why) -> NotInstalled:
    """The error for ``what`` run without the optional dependencies ``extra`` (pyproject.toml), with the pip line."""
    return NotInstalled(f"{what} needs the '{extra}' extra ({why}): pip install 'panolam-toolkit[{extra}]'")


def optional_import(module: str, extra: str, what: str = "this command"):
    """``module``, imported; :func:`missing_extra` when it cannot be (not installed, or broken)."""
    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise missing_extra(extra, what, e) from None


def os_error_line(e: OSError) -> str | None:
    """One line for an OSError about a file (a full disk, permission denied, a read-only folder, a
    path under a regular file), naming the file; None for an OSError that names none."""
    if e.errno == errno.ENOSPC:
        return f"disk full ({e.filename or ''})"
    if not e.filename:
        return None
    return f"{e.filename}: {e.strerror or e}"
