"""User-facing errors: the command lines print them as one line and exit non-zero."""
from __future__ import annotations

import argparse
import difflib
import errno
import importlib
import sys


class UserError(Exception):
    """A mistake in the user's input or environment, stated in one line."""


class DatasetError(UserError):
    """A problem with a dataset on disk, stated in one line naming the file."""


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


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """Appends '(default: X)' to an option's help when it has a real default its help does not state."""

    def _get_help_string(self, action):
        text = action.help or ""
        if action.default is None or action.default is False or action.default is argparse.SUPPRESS \
                or "default" in text or not action.option_strings:
            return text
        return f"{text} (default: {action.default})"


class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage errors are one line and exit 2 (no usage dump).

    Help shows each option's default; an unknown option is reported by the subcommand it was
    given to, with the closest known option as a suggestion.
    """

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", DefaultsHelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")

    def parse_args(self, args=None, namespace=None):
        ns, extra = self.parse_known_args(args, namespace)
        if extra:
            parser = self._chosen_subparser(ns) or self
            known = [o for a in parser._actions for o in a.option_strings]
            close = difflib.get_close_matches(extra[0].split("=")[0], known, n=1)
            parser.error(f"unrecognized arguments: {' '.join(extra)}" + (f" (did you mean {close[0]}?)" if close else ""))
        return ns

    def _chosen_subparser(self, ns):
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction):
                chosen = action.choices.get(getattr(ns, action.dest, None))
                return (chosen._chosen_subparser(ns) or chosen) if isinstance(chosen, OneLineParser) else chosen
        return None


def run_command(prog: str, commands: dict, args, interrupted: str) -> int:
    """Run ``commands[args.command](args)`` on the CPU threads :mod:`datagen.threads` chooses (``--threads``
    where the command has it); user mistakes become one line on stderr and exit 2."""
    from .threads import for_command
    try:
        with for_command(getattr(args, "threads", None)):
            return commands[args.command](args)
    except UserError as e:
        print(f"{prog} {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog} {args.command}: interrupted; {interrupted}", file=sys.stderr)
        return 130
    except OSError as e:
        line = os_error_line(e)
        if line is None:
            raise
        print(f"{prog} {args.command}: error: {line}", file=sys.stderr)
        return 2


def os_error_line(e: OSError) -> str | None:
    """One line for an OSError about a file (a full disk, permission denied, a read-only folder, a
    path under a regular file), naming the file; None for an OSError that names none."""
    if e.errno == errno.ENOSPC:
        return f"disk full ({e.filename or ''})"
    if not e.filename:
        return None
    return f"{e.filename}: {e.strerror or e}"
