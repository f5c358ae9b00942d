"""Text for people: sizes, counts and nested settings as the command lines print them."""
from __future__ import annotations

NOT_COUNTS = ("seed", "resolution")  # whole numbers shown without thousands separators


def byte_size(n: int) -> str:
    """A byte count for people: '25.8 MiB'."""
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n} B" if unit == "B" else f"{n:,.1f} {unit}"
        n /= 1024


def plural(n: int, word: str) -> str:
    """'1 face', '2,000 faces'."""
    return f"{n:,} {word}" + ("" if n == 1 else "s")


def readable(info: dict, indent: str = "") -> list[str]:
    """``key: value`` lines, nested dicts indented under their key, counts with thousands separators."""
    lines = []
    for k, v in info.items():
        if isinstance(v, dict):
            lines += [f"{indent}{k}:"] + readable(v, indent + "  ")
        else:
            shown = f"{v:,}" if isinstance(v, int) and not isinstance(v, bool) and k not in NOT_COUNTS else v
            lines.append(f"{indent}{k}: {shown}")
    return lines
