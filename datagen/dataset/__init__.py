"""The on-disk formats every package shares, and :class:`Dataset`, a dataset folder opened once.

- ``shards.py``: the dataset folder (index, tar shards, sidecars, hidden truth), encoding and reading.
- ``preflags.py``: pre-flag reports and the review queue made from them.
- ``events.py``: reviewers' append-only verdict logs.
- ``manifests.py``: curated manifests (which subjects are accepted, the train/test split).

Code that reads a dataset opens it once (``Dataset(root)`` reads and checks ``index.json``) and hands
the handle on; a function that also accepts a path opens it with :meth:`Dataset.of`.
"""
from __future__ import annotations

from functools import cached_property
from pathlib import Path

from ..errors import DatasetError
from ..files import sha256_file
from .shards import (INDEX_NAME, SubjectSample, check_shards, decode_sample, is_complete, read_fields, read_index,
                     shard_index, tar_path)


class Dataset:
    """A dataset folder: ``root``, its ``index`` (read and checked on opening; a DatasetError naming the file
    otherwise), and what is derived from the index, computed once on first use. The handle does not watch
    the folder: a dataset still being written is read as it was when opened."""

    def __init__(self, root):
        self.root = Path(root)
        self.index = read_index(self.root)

    @classmethod
    def of(cls, where) -> Dataset:
        """``where`` if it is a Dataset, else the dataset folder at that path, opened."""
        return where if isinstance(where, Dataset) else cls(where)

    def __repr__(self) -> str:
        return f"Dataset({str(self.root)!r})"

    @property
    def index_path(self) -> Path:
        return self.root / INDEX_NAME

    @property
    def shards(self) -> list[dict]:
        """The index's shards: {"name", "subjects"} each, in order."""
        return self.index["shards"]

    @cached_property
    def shard_numbers(self) -> list[int]:
        return [shard_index(sh["name"]) for sh in self.shards]

    @cached_property
    def shard_of(self) -> dict[str, int]:
        """{subject id: the number of the shard the index puts it in}."""
        return {key: n for n, sh in zip(self.shard_numbers, self.shards) for key in sh["subjects"]}

    @property
    def subjects(self) -> list[str]:
        """Every subject id of the index, in index order."""
        return list(self.shard_of)

    @cached_property
    def index_sha256(self) -> str:
        """sha256 of ``index.json``: what ties a manifest or a pre-flags report to this dataset."""
        return sha256_file(self.index_path)

    def shard(self, key: str) -> int:
        """The number of the shard holding subject ``key``; a DatasetError naming the index when none does."""
        try:
            return self.shard_of[key]
        except KeyError:
            raise DatasetError(f"{self.index_path}: no subject {key} in this dataset") from None

    @cached_property
    def complete_shards(self) -> list[int]:
        """The numbers of the index's shards whose sidecar and tar are in place (when first asked), in order."""
        return [n for n in self.shard_numbers if is_complete(self.root, n)]

    @cached_property
    def complete_subjects(self) -> list[str]:
        """The subject ids of :attr:`complete_shards`, in index order."""
        complete = set(self.complete_shards)
        return [key for n, sh in zip(self.shard_numbers, self.shards) if n in complete for key in sh["subjects"]]

    def check_shards(self, shards=None) -> dict[int, str]:
        """:func:`shards.check_shards` on the shards numbered ``shards`` (all of the index's when None)."""
        return check_shards(self.root, self.shard_numbers if shards is None else shards, self.index)

    def read_fields(self, key: str) -> dict:
        """Subject ``key``'s raw fields {field: bytes}, read by its byte range."""
        return read_fields(self.root, self.shard(key), key)

    def read_subject(self, key: str, views=None, depth: bool = True) -> SubjectSample:
        """Subject ``key`` decoded (all views or the view indices ``views``; depth optionally)."""
        tar = tar_path(self.root, self.shard(key))
        if not tar.exists():
            raise DatasetError(f"{tar}: shard holding {key} is missing (not generated yet?)")
        return decode_sample(key, self.read_fields(key), str(tar), views, depth)
