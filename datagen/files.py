"""Files every package writes and reads: atomic writes, checksums, JSON documents with a format tag.

One home for these, used by the shard writer, the pre-flags, manifests, event logs, PLY export
and training checkpoints alike.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Callable, Union

from .errors import DatasetError

SHA_CHUNK = 1 << 20


def atomic_write(path, data: Union[bytes, Callable]) -> Path:
    """Write ``data`` (bytes, or a function that writes to a binary file object) to ``path`` atomically.

    The bytes go to a temporary name in the same folder, are flushed and fsynced, then renamed over
    ``path``: readers see the old file or the new one, never a part. On any failure (a full disk,
    an interrupt) the temporary file is removed, and an OSError names ``path``.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            if callable(data):
                data(f)
            else:
                f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as e:
        raise OSError(e.errno, e.strerror, str(path)) from None
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def sha256_file(path) -> str:
    """Hex sha256 of a file's bytes, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(SHA_CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def read_json(path, what: str, fmt: str | None = None) -> dict:
    """A JSON object from ``path``; DatasetError naming the file when it is missing, unreadable, not
    JSON, not an object, or (with ``fmt``) has another ``format`` field (or a ``header.format``)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(f"{path}: no {what} here") from None
    except IsADirectoryError:
        raise DatasetError(f"{path}: is a folder, not a {what}") from None
    except PermissionError:
        raise DatasetError(f"{path}: permission denied") from None
    except (ValueError, UnicodeDecodeError) as e:
        raise DatasetError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: not a {what} (expected a JSON object, found {type(doc).__name__})")
    if fmt is not None:
        header = doc.get("header") if "format" not in doc else doc
        found = header.get("format") if isinstance(header, dict) else None
        if found != fmt:
            raise DatasetError(f"{path}: not a {fmt} {what} (format {found!r})")
    return doc


def require(doc: dict, key: str, types, path, where: str = "") -> object:
    """``doc[key]`` if present and of ``types``; otherwise a DatasetError naming the file and field."""
    name = f"{where}.{key}" if where else key
    if key not in doc:
        raise DatasetError(f"{path}: field {name!r} is missing")
    value = doc[key]
    if not isinstance(value, types) or (isinstance(value, bool) and bool not in _tuple(types)):
        expected = " or ".join(t.__name__ for t in _tuple(types))
        raise DatasetError(f"{path}: field {name!r} must be {expected}, not {type(value).__name__}")
    return value


def _tuple(types) -> tuple:
    return types if isinstance(types, tuple) else (types,)
