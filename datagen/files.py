"""Files every package writes and reads: atomic writes, checksums, JSON documents with a format tag.

One home for these, used by the shard writer, the pre-flags, manifests, event logs, PLY export
and training checkpoints alike.
"""
from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Union

from .errors import DatasetError, UserError

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


def as_path(path) -> Path:
    """``path`` as a Path (itself when it is one: wrapping a Path again parses it again, which per shard
    of a 165K-subject dataset adds up)."""
    return path if isinstance(path, Path) else Path(path)


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
    path = as_path(path)
    try:
        doc = json.loads(path.read_bytes())
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
        if "header" in doc and not isinstance(header, dict):
            raise DatasetError(f"{path}: not a {fmt} {what} (field 'header' must be an object, "
                               f"not {type(header).__name__})")
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


class LockBusy(Exception):
    """The lock is held by another process."""


@contextmanager
def byte_lock(path, offset: int, blocking: bool = True):
    """Hold an exclusive POSIX record lock (``fcntl.lockf``) on one byte of ``path`` for the block.

    One lock file serves many independent locks (one byte each). POSIX locks work across the
    machines of a cluster where the shared filesystem supports them (NFS with its lock daemon,
    Lustre, GPFS); where it does not, a UserError says so. Locks end with the process, so a
    killed run never leaves one behind. Non-blocking: LockBusy when another process holds it.
    """
    path = Path(path)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.lockf(fd, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB), 1, offset, os.SEEK_SET)
        except OSError as e:
            if e.errno in (errno.EAGAIN, errno.EACCES):
                raise LockBusy(str(path)) from None
            raise UserError(f"cannot lock {path}: {e.strerror}; this filesystem does not support POSIX file locks, "
                            "so concurrent runs into one folder cannot be kept apart (use one folder per run)") from None
        yield
    finally:
        os.close(fd)


def _tuple(types) -> tuple:
    return types if isinstance(types, tuple) else (types,)
