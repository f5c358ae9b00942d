"""User-facing errors: the command lines print them as one line and exit non-zero."""
from __future__ import annotations

import argparse
import errno
import sys


class UserError(Exception):
    """A mistake in the user's input or environment, stated in one line."""


class DatasetError(UserError):
    """A problem with a dataset on disk, stated in one line naming the file."""


class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage errors are one line and exit 2 (no usage dump)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


def run_command(prog: str, commands: dict, args, interrupted: str) -> int:
    """Run ``commands[args.command](args)``; user mistakes become one line on stderr and exit 2."""
    try:
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
