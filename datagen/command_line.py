"""The command lines' shared machinery: one-line usage errors, options declared as dataclass fields, and
running a command so that user mistakes are one line on stderr.

Options. A dataclass field becomes an option when its metadata holds ``help`` (see :func:`setting`): the
flag is ``--`` + the field name with dashes (or ``flag``), the value is parsed by ``parse`` (an argparse
type, which checks the value's range), and the help shows the field's default. Options default to None on
the command line, so :func:`given` tells what the user set from what the dataclass fills in. Which options
go together is checked by each command in one place; the library raises
:class:`datagen.errors.SettingError` naming settings by field, and :func:`run_command` words them as flags.
No option is taken from an abbreviation of its name. This module imports no torch: ``--help`` and usage
errors answer at once.
"""
from __future__ import annotations

import argparse
import dataclasses
import difflib
import math
import os
import signal
import sys
import threading

from .errors import SettingError, UserError, os_error_line


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
        kwargs["allow_abbrev"] = False  # '--subject 2' must not run '--subjects 2'
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


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill PID``, ``timeout``, a batch scheduler) arrived: the command stops as on Ctrl-C."""


def _terminated(signum, frame):
    raise Terminated


def run_command(prog: str, commands: dict, args, interrupted: str, parser: OneLineParser | None = None) -> int:
    """Run ``commands[args.command](args)`` on the CPU threads :mod:`datagen.threads` chooses (``--threads``
    where the command has it); user mistakes become one line on stderr and exit 2, settings named by the
    flags of ``parser`` (the one that parsed ``args``), else ``--`` + their name. Ctrl-C and SIGTERM stop
    it alike (what is kept is ``interrupted``; exit 130 and 143)."""
    main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminated) if main else None
    try:
        return _run(prog, commands, args, interrupted, parser)
    finally:
        if main:
            signal.signal(signal.SIGTERM, previous)


def _run(prog: str, commands: dict, args, interrupted: str, parser: OneLineParser | None) -> int:
    from .threads import for_command
    try:
        with for_command(getattr(args, "threads", None)):
            return commands[args.command](args)
    except SettingError as e:
        chosen = None if parser is None else parser._chosen_subparser(args) or parser
        flags = {a.dest: a.option_strings[-1] for a in chosen._actions if a.option_strings} if chosen else {}
        print(f"{prog} {args.command}: error: {e.worded(lambda name: flags.get(name, flag_of(name)))}",
              file=sys.stderr)
        return 2
    except UserError as e:
        print(f"{prog} {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        print(f"{prog} {args.command}: {'terminated' if isinstance(e, Terminated) else 'interrupted'}; {interrupted}",
              file=sys.stderr)
        return 143 if isinstance(e, Terminated) else 130
    except BrokenPipeError:
        if not _stdout_closed():
            raise
        return 141  # what a shell reports for a command its reader stopped reading (SIGPIPE)
    except OSError as e:
        line = os_error_line(e)
        if line is None:
            raise
        print(f"{prog} {args.command}: error: {line}", file=sys.stderr)
        return 2


def _stdout_closed() -> bool:
    """Whether standard output's reader has gone (``datagen info | head -3``); then it is pointed at
    /dev/null, so that the interpreter's last flush does not fail on it again."""
    import select

    try:
        fd = sys.stdout.fileno()
        poll = select.poll()
        poll.register(fd, select.POLLOUT)
        gone = any(events & select.POLLERR for _, events in poll.poll(0))
    except (AttributeError, OSError, ValueError):  # no file descriptor, or no poll on this system
        return False
    if gone:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, fd)
        os.close(devnull)
    return gone


def setting(default, help: str, *, parse=None, flag: str | None = None, nargs=None, choices=None,
            fixed: bool = False, path: bool = False, metavar: str | None = None, required: bool = False):
    """A dataclass field that is also a command-line option. A boolean default makes a switch (given: True).

    ``fixed``: set when a run starts and refused on resume (schedule, data order, objective);
    ``path``: names a file, which may have moved since (given again where it is now).
    """
    return dataclasses.field(default=default, metadata=dict(help=help, parse=parse, flag=flag, nargs=nargs,
                                                            choices=choices, fixed=fixed, path=path, metavar=metavar,
                                                            required=required))


def option_fields(cls) -> list[dataclasses.Field]:
    """The fields of ``cls`` that are command-line options."""
    return [f for f in dataclasses.fields(cls) if "help" in f.metadata]


def flag_of(name: str) -> str:
    """The flag of the setting ``name``: ``--`` + the name with dashes."""
    return "--" + name.replace("_", "-")


def flag(f: dataclasses.Field) -> str:
    return f.metadata["flag"] or flag_of(f.name)


def fixed_fields(cls) -> tuple[str, ...]:
    return tuple(f.name for f in option_fields(cls) if f.metadata["fixed"])


def path_fields(cls) -> tuple[str, ...]:
    return tuple(f.name for f in option_fields(cls) if f.metadata["path"])


def shown(value) -> str:
    if isinstance(value, tuple):
        return " ".join(map(shown, value))
    return f"{value:g}" if isinstance(value, float) else str(value)


def add_options(parser: argparse.ArgumentParser, cls, only=None, help_prefix: str = "",
                help_suffix: str = "") -> None:
    """One option per field of ``cls`` (those named in ``only``, if given; none already in ``parser``), its
    default in the help unless the help speaks of defaults itself."""
    taken = {a.dest for a in parser._actions}
    for f in option_fields(cls):
        if (only is not None and f.name not in only) or f.name in taken:
            continue
        m = f.metadata
        text = help_prefix + m["help"] + help_suffix
        if f.default is not None and "default" not in text and not isinstance(f.default, bool):
            listed = isinstance(f.default, tuple) and not m["nargs"]  # parsed from A,B
            text += f" (default {','.join(map(shown, f.default)) if listed else shown(f.default)})"
        if isinstance(f.default, bool):
            parser.add_argument(flag(f), dest=f.name, action="store_const", const=True, default=None, help=text)
            continue
        metavar = None if m["choices"] else m["metavar"] or flag(f)[2:].upper().replace("-", "_")
        parser.add_argument(flag(f), dest=f.name, type=m["parse"], nargs=m["nargs"], choices=m["choices"],
                            default=None, metavar=metavar, required=m["required"], help=text)


def given(args: argparse.Namespace, cls, only=None) -> dict:
    """{field: value} of the options of ``cls`` set on the command line (tuples for multi-value ones)."""
    out = {}
    for f in option_fields(cls):
        value = getattr(args, f.name, None)
        if value is not None and (only is None or f.name in only):
            out[f.name] = tuple(value) if isinstance(value, list) else value
    return out


def describe(cls, name: str, value) -> str:
    """``--flag value`` of the field ``name`` of ``cls``, for messages."""
    f = next(f for f in option_fields(cls) if f.name == name)
    return f"{flag(f)} {shown(value)}"


# -- argparse types -----------------------------------------------------------------------------------------
def at_least(minimum: int):
    """An integer of at least ``minimum``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, not {value}")
        return value
    return parse


def number(accept, requirement: str):
    """A finite real number for which ``accept`` holds (``requirement`` says which, for the error)."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not math.isfinite(value) or not accept(value):
            raise argparse.ArgumentTypeError(f"must be {requirement}, not {text}")
        return value
    return parse


positive = number(lambda v: v > 0, "a finite number above 0")
non_negative = number(lambda v: v >= 0, "a finite number of at least 0")
unit_interval = number(lambda v: 0 <= v < 1, "at least 0 and below 1")


# -- progress --------------------------------------------------------------------------------------------
class SilentBar:
    """A progress bar that shows nothing (``--quiet``, or a process that is not the first)."""

    def update(self, n: int = 1):
        pass

    def set_postfix(self, **values):
        pass

    def close(self):
        pass


def progress_bar(total: int, unit: str, what: str, enabled: bool = True, initial: int = 0):
    """A progress bar on stderr counting ``total`` ``unit``s of ``what`` from ``initial``; a
    :class:`SilentBar` when not ``enabled``."""
    if not enabled:
        return SilentBar()
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, unit=unit, desc=what, dynamic_ncols=True, smoothing=0.1)
