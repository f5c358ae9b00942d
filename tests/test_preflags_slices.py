"""Pre-flags at scale: slices measured by array jobs and merged give the one-process report; a merge
refuses, in one line, slices that are missing, stale or measured with other detector settings."""
from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest

from datagen.errors import DatasetError, UserError
from datagen.dataset.preflags import write_preflags
from labeling_tool import preflags
from labeling_tool.cli import main as label_main
from labeling_tool.preflags.registry import DETECTORS
from labeling_tool.preflags.slices import decode, encode, measure_slice, merge_slices, slice_path, slices_folder


def report_bytes(root, report) -> bytes:
    """The report as written, less its timing."""
    path = write_preflags(root, {k: v for k, v in report.items() if k != "timing"}, root / "cmp.json")
    return path.read_bytes()


@pytest.fixture(scope="module")
def dataset(tiny_dataset, tmp_path_factory):
    ds = tmp_path_factory.mktemp("slices") / "ds"
    shutil.copytree(tiny_dataset, ds)
    return ds


@pytest.fixture(scope="module")
def one_process(dataset):
    return preflags.score_dataset(dataset)


@pytest.mark.parametrize("n", [2, 3])  # 3 slices of 2 shards: one slice holds none
def test_merged_slices_equal_one_process_byte_for_byte(dataset, one_process, tmp_path, n):
    out = tmp_path / "slices"
    for k in range(n):
        measure_slice(dataset, k, n, out)
    merged = merge_slices(dataset, out)
    assert merged["timing"]["slices"] == n and len(merged["subjects"]) == 3
    assert report_bytes(tmp_path, merged) == report_bytes(tmp_path, one_process)


def test_records_round_trip_with_their_types():
    record = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.float32(0.1), "c": float("nan"),
              "d": [1, (2.5, None)], "e": {0.0: 1, 45.0: True}, "f": -0.0, "g": np.int64(7)}
    back = decode(json.loads(json.dumps(encode(record))))
    assert back["a"].dtype == np.float32 and np.array_equal(back["a"], record["a"])
    assert type(back["b"]) is np.float32 and back["b"] == record["b"] and np.isnan(back["c"])
    assert back["d"] == [1, (2.5, None)] and back["e"] == {0.0: 1, 45.0: True} and type(back["g"]) is np.int64
    assert str(back["f"]) == "-0.0"


def test_a_merge_refuses_missing_stale_and_foreign_slices(dataset, tmp_path):
    ds = tmp_path / "ds"
    shutil.copytree(dataset, ds, ignore=shutil.ignore_patterns("preflags*"))
    folder = slices_folder(ds)
    with pytest.raises(UserError, match="no slices to merge"):
        merge_slices(ds)
    measure_slice(ds, 0, 2)
    with pytest.raises(UserError, match=r"slice-00001-of-00002.json: missing.*--shard-index 1 --num-shards 2"):
        merge_slices(ds)
    janus = next(d for d in DETECTORS if d.name == "janus")
    other = tuple(type(d)(dataclasses.replace(d.settings)) if d is not janus else
                  type(d)(dataclasses.replace(d.settings, **{dataclasses.fields(d.settings)[0].name: 0.123}))
                  for d in DETECTORS)
    measure_slice(ds, 1, 2, detectors=other)
    with pytest.raises(UserError, match=r"slice-00001-of-00002.json: measured with other detector settings"):
        merge_slices(ds)
    measure_slice(ds, 1, 2)
    assert len(merge_slices(ds)["subjects"]) == 3
    measure_slice(ds, 0, 3)
    with pytest.raises(UserError, match="holds slices of 2 and of 3 jobs"):
        merge_slices(ds)
    slice_path(folder, 0, 3).unlink()
    index = ds / "index.json"
    index.write_text(index.read_text() + " ")  # another index.json: the slices are stale
    with pytest.raises(UserError, match=r"slice-00000-of-00002.json: stale"):
        merge_slices(ds)
    measure_slice(ds, 0, 2), measure_slice(ds, 1, 2)
    doc = json.loads(slice_path(folder, 1, 2).read_text())
    records = doc["records"]
    doc["records"] = []  # a subject's record lost
    slice_path(folder, 1, 2).write_text(json.dumps(doc))
    with pytest.raises(DatasetError, match=r"slice-00001-of-00002.json: holds records of 0 subjects of shard-000001"):
        merge_slices(ds)
    doc["records"] = records + [["shard-000001", {"x": 1}]]
    slice_path(folder, 1, 2).write_text(json.dumps(doc))
    with pytest.raises(DatasetError, match=r"slice-00001-of-00002.json: not a readable pre-flags slice"):
        merge_slices(ds)


@pytest.mark.parametrize("args, message", [
    (["--shard-index", "0"], "--shard-index and --num-shards go together"),
    (["--shard-index", "2", "--num-shards", "2"], "0 <= shard-index < num-shards"),
    (["--shard-index", "0", "--num-shards", "2", "--merge"], "--merge goes with"),
    (["--merge", "--backend", "ray"], "--backend ray measures and scores in one run"),
    (["--out", "x"], "--out is the folder of slice files"),
    (["--merge"], "no slices to merge"),
    (["--false-alarm-rate", "1"], "--false-alarm-rate: must be at least 0 and below 1, not 1"),
    (["--work", "2"], "unrecognized arguments: --work 2 (did you mean --workers?)"),
    (["--ray-address", "a:1"], "--ray-address: only with --backend ray"),
    (["--false-alarm-rate", "-0.01"], "--false-alarm-rate: must be at least 0"),
    (["--shard-index", "0", "--num-shards", "2", "--false-alarm-rate", "0.1"], "--false-alarm-rate goes with the --merge"),
])
def test_auto_slice_options_are_checked_in_one_line(dataset, tmp_path, capsys, args, message):
    ds = tmp_path / "ds"
    shutil.copytree(dataset, ds, ignore=shutil.ignore_patterns("preflags*"))
    try:
        code = label_main(["auto", str(ds), "--quiet"] + args)
    except SystemExit as e:  # a value argparse refuses
        code = e.code
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and message in err


def test_auto_cli_slices_then_merge(dataset, one_process, tmp_path, capsys):
    ds = tmp_path / "ds"
    shutil.copytree(dataset, ds, ignore=shutil.ignore_patterns("preflags*"))
    out = tmp_path / "shared" / "slices"
    for k in range(2):
        assert label_main(["auto", str(ds), "--quiet", "--shard-index", str(k), "--num-shards", "2",
                           "--out", str(out)]) == 0
    assert not (ds / "preflags.json").exists() and "--merge --out" in capsys.readouterr().out
    assert label_main(["auto", str(ds), "--merge", "--out", str(out), "--top", "0"]) == 0
    merged = json.loads((ds / "preflags.json").read_text())
    assert report_bytes(tmp_path, merged) == report_bytes(tmp_path, one_process)


def test_the_false_alarm_rate_reaches_every_way_of_scoring(dataset, tmp_path, capsys):
    ds = tmp_path / "ds"
    shutil.copytree(dataset, ds, ignore=shutil.ignore_patterns("preflags*"))
    assert label_main(["auto", str(ds), "--quiet", "--top", "0", "--false-alarm-rate", "0.1"]) == 0
    assert "calibrated to flag at most 10.0% of clean subjects" in capsys.readouterr().out
    one = json.loads((ds / "preflags.json").read_text())
    assert one["calibration"]["false_alarm_rate"] == 0.1
    for k in range(2):
        assert label_main(["auto", str(ds), "--quiet", "--shard-index", str(k), "--num-shards", "2"]) == 0
    assert label_main(["auto", str(ds), "--merge", "--top", "0", "--false-alarm-rate", "0.1"]) == 0
    merged = json.loads((ds / "preflags.json").read_text())
    assert report_bytes(tmp_path, merged) == report_bytes(tmp_path, one)
    assert label_main(["auto", str(ds), "--merge", "--top", "0", "--false-alarm-rate", "0"]) == 0
    assert "each detector at its own threshold, uncalibrated" in capsys.readouterr().out
    assert json.loads((ds / "preflags.json").read_text())["calibration"]["false_alarm_rate"] == 0
