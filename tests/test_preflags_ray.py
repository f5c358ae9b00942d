"""``label-tool auto --backend ray`` measures on Ray and gives the one-process report."""
from __future__ import annotations

import json
import shutil

import pytest

ray = pytest.importorskip("ray", reason="the ray backend needs the optional extra: pip install -e '.[ray]'")

from datagen.dataset.preflags import write_preflags  # noqa: E402
from labeling_tool import preflags  # noqa: E402
from labeling_tool.cli import main as label_main  # noqa: E402

pytestmark = [pytest.mark.ray]


def test_ray_backend_gives_the_one_process_report(tiny_dataset, tmp_path, capsys):
    assert not ray.is_initialized()
    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds, ignore=shutil.ignore_patterns("preflags*"))
    one = preflags.score_dataset(ds, false_alarm_rate=0.05)
    assert all("does not decode" not in s["detectors"]["empty"]["why"] for s in one["subjects"])
    assert label_main(["auto", str(ds), "--backend", "ray", "--quiet", "--top", "0", "--false-alarm-rate", "0.05"]) == 0
    assert not ray.is_initialized(), "the Ray instance started for the run was not shut down"
    on_ray = json.loads((ds / "preflags.json").read_text())
    assert on_ray["timing"]["backend"] == "ray" and on_ray["timing"]["tasks"] == 2
    assert on_ray["calibration"]["false_alarm_rate"] == 0.05
    strip = [{k: v for k, v in r.items() if k != "timing"} for r in (one, on_ray)]
    assert write_preflags(ds, strip[0], tmp_path / "a.json").read_bytes() == \
        write_preflags(ds, strip[1], tmp_path / "b.json").read_bytes()


def test_an_unreachable_cluster_is_one_line(tiny_dataset, capsys):
    assert label_main(["auto", str(tiny_dataset), "--backend", "ray", "--ray-address", "127.0.0.1:9",
                       "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "cannot reach the Ray cluster at 127.0.0.1:9" in err
