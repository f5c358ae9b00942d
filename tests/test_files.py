"""Shared file formats and helpers: atomic writes, JSON documents, the index and manifest schemas."""
import errno
import json

import pytest

from datagen.errors import DatasetError, UserError
from datagen.files import atomic_write, read_json, sha256_file
from datagen.dataset.manifests import read_manifest
from datagen.dataset.shards import read_index


def test_atomic_write_replaces_whole_files_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "a.json"
    atomic_write(path, b"one")
    atomic_write(path, lambda f: f.write(b"two"))
    assert path.read_bytes() == b"two" and sorted(p.name for p in tmp_path.iterdir()) == ["a.json"]
    assert len(sha256_file(path)) == 64


def test_a_failed_write_keeps_the_old_file_removes_the_temporary_and_names_the_file(tmp_path):
    path = tmp_path / "checkpoint.pt"
    atomic_write(path, b"old")

    def disk_full(f):
        f.write(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError) as info:
        atomic_write(path, disk_full)
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(path)
    assert path.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt"]


def test_interrupted_write_removes_the_temporary(tmp_path):
    def interrupted(f):
        raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        atomic_write(tmp_path / "x", interrupted)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("text, message", [
    ("[1, 2]", "expected a JSON object, found list"),
    ("{not json", "not valid JSON"),
    ('{"format": "other/1"}', "not a panolam-heads/1 dataset index"),
])
def test_read_json_names_the_file_and_the_problem(tmp_path, text, message):
    path = tmp_path / "index.json"
    path.write_text(text)
    with pytest.raises(DatasetError, match=message) as info:
        read_json(path, "dataset index", "panolam-heads/1")
    assert str(path) in str(info.value)


def test_read_json_on_a_folder(tmp_path):
    (tmp_path / "bob.jsonl").mkdir()
    with pytest.raises(DatasetError, match="is a folder"):
        read_json(tmp_path / "bob.jsonl", "event log")


def _index(**over):
    doc = {"format": "panolam-heads/1", "settings": {}, "generator": {"name": "procedural"}, "views_per_subject": 4,
           "num_subjects": 1, "shards": [{"name": "shard-000000", "subjects": ["subj00000000"]}]}
    doc.update(over)
    return doc


@pytest.mark.parametrize("change, message", [
    ({"shards": {"name": "shard-000000"}}, "field 'shards' must be list"),
    ({"shards": [{"name": "../../etc", "subjects": []}]}, r"shards\[0\].name '../../etc' is not a shard name"),
    ({"shards": [{"name": "shard-000000"}]}, r"field 'shards\[0\].subjects' is missing"),
    ({"shards": ["shard-000000"]}, r"shards\[0\] must be an object"),
    ({"views_per_subject": "32"}, "field 'views_per_subject' must be int"),
    ({"num_subjects": True}, "field 'num_subjects' must be int, not bool"),
])
def test_structurally_wrong_index_is_one_line_naming_the_field(tmp_path, change, message):
    (tmp_path / "index.json").write_text(json.dumps(_index(**change)))
    with pytest.raises(DatasetError, match=message):
        read_index(tmp_path)


def test_index_missing_a_key(tmp_path):
    doc = _index()
    del doc["generator"]
    (tmp_path / "index.json").write_text(json.dumps(doc))
    with pytest.raises(DatasetError, match="field 'generator' is missing"):
        read_index(tmp_path)


@pytest.mark.parametrize("doc, message", [
    ({"header": "panolam-manifest/1", "subjects": []},
     r"m.json: not a panolam-manifest/1 manifest \(field 'header' must be an object, not str\)"),
    ({"header": {"format": "panolam-manifest/1"}, "subjects": [{"subject": "s", "shard": "../x",
                                                               "verdict": "accepted", "split": "train"}]},
     r"m.json: subjects\[0\].shard: '../x' is not a shard name"),
    ({"header": {"format": "panolam-manifest/1"}, "subjects": {}}, "field 'subjects' must be list"),
    ({"header": {"format": "panolam-manifest/1"}, "subjects": [{"subject": "s", "shard": "shard-000000",
                                                               "verdict": "maybe", "split": None}]},
     r"subjects\[0\].verdict must be accepted or rejected"),
    ({"header": {"format": "panolam-manifest/1"}, "subjects": [{"subject": 3}]}, r"subjects\[0\].subject' must be str"),
])
def test_structurally_wrong_manifest_is_one_line(tmp_path, doc, message):
    path = tmp_path / "m.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(UserError, match=message):
        read_manifest(path)
