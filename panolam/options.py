"""Command-line options generated from the configuration dataclasses: one list of settings.

A dataclass field becomes an option when its metadata holds ``help`` (see :func:`setting`): the
flag is ``--`` + the field name with dashes (or ``flag``), the value is parsed by ``parse`` (an
argparse type), and the help shows the field's default. Options default to None on the command
line, so :func:`given` tells what the user set from what the dataclass fills in. This module
imports no torch: ``panolam --help`` and usage errors answer at once.
"""
from __future__ import annotations

import argparse
import dataclasses
import math


def setting(default, help: str, *, parse=None, flag: str | None = None, nargs=None, choices=None,
            fixed: bool = False, path: bool = False):
    """A dataclass field that is also a command-line option.

    ``fixed``: set when a run starts and refused on resume (schedule, data order, objective);
    ``path``: names a file, which may have moved since (given again where it is now).
    """
    return dataclasses.field(default=default, metadata=dict(help=help, parse=parse, flag=flag, nargs=nargs,
                                                            choices=choices, fixed=fixed, path=path))


def option_fields(cls) -> list[dataclasses.Field]:
    """The fields of ``cls`` that are command-line options."""
    return [f for f in dataclasses.fields(cls) if "help" in f.metadata]


def flag(f: dataclasses.Field) -> str:
    return f.metadata["flag"] or "--" + f.name.replace("_", "-")


def fixed_fields(cls) -> tuple[str, ...]:
    return tuple(f.name for f in option_fields(cls) if f.metadata["fixed"])


def path_fields(cls) -> tuple[str, ...]:
    return tuple(f.name for f in option_fields(cls) if f.metadata["path"])


def shown(value) -> str:
    if isinstance(value, tuple):
        return " ".join(map(shown, value))
    return f"{value:g}" if isinstance(value, float) else str(value)


def add_options(parser: argparse.ArgumentParser, cls, only=None, help_suffix: str = "") -> None:
    """One option per field of ``cls`` (those named in ``only``, if given), its default in the help."""
    for f in option_fields(cls):
        if only is not None and f.name not in only:
            continue
        m = f.metadata
        text = m["help"] + help_suffix
        if f.default is not None:
            text += f" (default {shown(f.default)})"
        metavar = None if m["choices"] else flag(f)[2:].upper().replace("-", "_")
        parser.add_argument(flag(f), dest=f.name, type=m["parse"], nargs=m["nargs"], choices=m["choices"],
                            default=None, metavar=metavar, help=text)


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
