"""Reading subjects for the review window: only the members asked for, by their byte ranges.

:func:`datagen.dataset.shards.read_range` copies out a subject's whole byte range (every view's image, mask
and depth); a triage page needs one image of each of 40 subjects, so this reader keeps each
subject's member table (from the tar headers in its range) and reads single members.
"""
from __future__ import annotations

import json
import tarfile
import threading
from collections import OrderedDict

import numpy as np

from datagen.cameras import angle_between
from datagen.errors import DatasetError
from datagen.dataset.shards import decode_png, read_sidecar, shard_index, tar_path

from .session import QueueItem


class SubjectReader:
    """Reads single members of a subject's tar sample (through the sidecar's byte ranges and the tar
    headers, never the whole sample). Thread-safe."""

    def __init__(self, root, cache_subjects: int = 4096):
        self.root = root
        self._sidecars: dict = {}
        self._members: OrderedDict = OrderedDict()
        self._cache_subjects = cache_subjects
        self._lock = threading.Lock()

    def _sidecar(self, shard: int) -> dict:
        with self._lock:
            side = self._sidecars.get(shard)
        if side is None:
            side = read_sidecar(self.root, shard)
            if side is None:
                raise DatasetError(f"{tar_path(self.root, shard)}: incomplete shard (no sidecar)")
            with self._lock:
                self._sidecars[shard] = side
        return side

    def members(self, item: QueueItem) -> dict:
        """{field: (offset, size)} of the subject's members in its shard."""
        with self._lock:
            if item.subject in self._members:
                self._members.move_to_end(item.subject)
                return self._members[item.subject]
        shard = shard_index(item.shard)
        path = tar_path(self.root, shard)
        try:
            start, end = self._sidecar(shard)["offsets"][item.subject]
        except KeyError:
            raise DatasetError(f"{path}: no subject {item.subject} in this shard") from None
        table = {}
        try:
            with open(path, "rb") as f:
                f.seek(start)
                with tarfile.open(fileobj=f, mode="r:") as tar:
                    for m in tar:
                        if m.offset >= end:
                            break
                        if m.isfile():
                            table[m.name.partition(".")[2]] = (m.offset_data, m.size)
        except (tarfile.TarError, EOFError, OSError) as e:
            raise DatasetError(f"{path}: corrupt subject {item.subject} ({e})") from None
        with self._lock:
            self._members[item.subject] = table
            while len(self._members) > self._cache_subjects:
                self._members.popitem(last=False)
        return table

    def read(self, item: QueueItem, fields) -> dict:
        """{field: bytes} for the fields asked for."""
        table = self.members(item)
        path = tar_path(self.root, shard_index(item.shard))
        out = {}
        try:
            with open(path, "rb") as f:
                for field in fields:
                    if field not in table:
                        raise DatasetError(f"{path}: subject {item.subject} lacks field {field}")
                    offset, size = table[field]
                    f.seek(offset)
                    out[field] = f.read(size)
        except OSError as e:
            raise DatasetError(f"{path}: cannot read subject {item.subject} ({e.strerror})") from None
        return out

    def metadata(self, item: QueueItem) -> dict:
        try:
            return json.loads(self.read(item, ["json"])["json"])
        except ValueError as e:
            raise DatasetError(f"{item.shard}: subject {item.subject} has unreadable metadata ({e})") from None


def nearest_view(views: list[dict], yaw: float) -> int:
    """Index of the view closest to ``yaw`` (degrees) on the equator."""
    d = [angle_between(v["yaw_deg"], yaw) + abs(v["pitch_deg"]) for v in views]
    return int(np.argmin(d))


def decode_image(data: bytes, where: str) -> np.ndarray:
    try:
        return decode_png(data)
    except Exception as e:  # a decoder's own error: say which subject
        raise DatasetError(f"{where}: image does not decode ({type(e).__name__}: {e})") from None
