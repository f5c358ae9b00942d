"""Shards on disk: determinism, parallel and split runs, resume after SIGKILL, reading back, verify."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import webdataset as wds

from datagen.errors import UserError
from datagen.pipeline import run_sample
from datagen.dataset import Dataset
from datagen.dataset.shards import decode_exr, sidecar_path, tar_path
from datagen.verify import verify_dataset
from tests.conftest import all_files, group_ended, tiny_spec


def test_same_command_gives_identical_bytes(tiny_dataset, tmp_path):
    run_sample(tiny_spec(tmp_path / "again"), progress=False)
    a, b = all_files(tiny_dataset), all_files(tmp_path / "again")
    assert list(a) == list(b) and len(a) >= 5
    assert a == b


def test_layout_and_sidecars(tiny_dataset):
    names = sorted(p.name for p in Path(tiny_dataset).iterdir())
    assert names == [".datagen.lock", "index.json", "shard-000000.json", "shard-000000.tar", "shard-000001.json",
                     "shard-000001.tar", "truth"]
    side = json.loads(sidecar_path(tiny_dataset, 0).read_text())
    assert side["subjects"] == ["subj00000000", "subj00000001"] and side["files"] == 2 * (1 + 3 * 4)
    assert side["tar_bytes"] == tar_path(tiny_dataset, 0).stat().st_size
    truth = json.loads((Path(tiny_dataset) / "truth" / "shard-000000.json").read_text())
    assert set(truth) == {"subj00000000", "subj00000001"} and all("defects" in t for t in truth.values())


def test_one_worker_equals_two_workers(tmp_path):
    spec1 = tiny_spec(tmp_path / "w1", subjects=4, shard_size=1, views=2)
    spec2 = tiny_spec(tmp_path / "w2", subjects=4, shard_size=1, views=2)
    run_sample(spec1, workers=1, progress=False)
    run_sample(spec2, workers=2, progress=False)
    assert all_files(spec1.out) == all_files(spec2.out)


def test_array_job_split_equals_single_run(tiny_dataset, tmp_path):
    out = tmp_path / "split"
    run_sample(tiny_spec(out), shard_index=1, num_shards=2, progress=False)
    assert not tar_path(out, 0).exists() and tar_path(out, 1).exists()
    run_sample(tiny_spec(out), shard_index=0, num_shards=2, progress=False)
    assert all_files(out) == all_files(tiny_dataset)


def test_webdataset_reads_the_shards_unchanged(tiny_dataset):
    urls = [str(tar_path(tiny_dataset, i)) for i in range(2)]
    ds = wds.WebDataset(urls, shardshuffle=False, empty_check=False).decode("rgb8")
    samples = list(ds)
    assert [s["__key__"] for s in samples] == ["subj00000000", "subj00000001", "subj00000002"]
    s = samples[0]
    meta = s["json"]
    assert meta["subject_id"] == "subj00000000" and len(meta["views"]) == 4
    assert s["v00.png"].shape == (32, 32, 3) and s["v00.png"].dtype == np.uint8
    assert s["v03.mask.png"].shape[:2] == (32, 32)
    depth = decode_exr(s["v02.depth.exr"])
    assert depth.shape == (32, 32) and depth.dtype == np.float32 and np.isfinite(depth).all()


def test_metadata_records_provenance(tiny_dataset):
    meta = Dataset(tiny_dataset).read_subject("subj00000001").metadata
    assert meta["generator"]["name"] == "procedural" and meta["dataset_seed"] == 7
    assert meta["protocol"] == "360" and meta["resolution"] == 32 and meta["pivot"] == [0.0, 0.0, 0.0]
    assert {"version", "git_revision", "torch"} <= set(meta["software"])
    v = meta["views"][0]
    assert np.asarray(v["cam2world"]).shape == (4, 4) and np.asarray(v["intrinsics"]).shape == (3, 3)
    assert {"radius", "fov_deg", "yaw_deg", "pitch_deg"} <= set(v)
    assert "defects" not in json.dumps(meta)  # injected truth lives apart from what reviewers see
    assert "params" in meta["latent"]


def test_depth_and_mask_agree(tiny_dataset):
    s = Dataset(tiny_dataset).read_subject("subj00000002")
    for a, d in zip(s.alpha, s.depth):
        assert (d[a == 0] == 0).all()
        inside = d[a == 255]
        assert inside.size and (inside > 2.0).all() and (inside < 3.5).all()


def test_verify_passes_on_a_good_dataset(tiny_dataset):
    report = verify_dataset(tiny_dataset)
    assert report["problems"] == [] and report["complete"] == 2 and report["subjects"] == 3


def copy_dataset(src, dst):
    dst.mkdir()
    for rel, data in all_files(src).items():
        (dst / rel).parent.mkdir(parents=True, exist_ok=True)
        (dst / rel).write_bytes(data)
    return dst


def test_verify_reports_a_flipped_byte(tiny_dataset, tmp_path):
    ds = copy_dataset(tiny_dataset, tmp_path / "ds")
    tar = tar_path(ds, 1)
    data = bytearray(tar.read_bytes())
    data[len(data) // 2] ^= 0xFF
    tar.write_bytes(bytes(data))
    problems = verify_dataset(ds)["problems"]
    assert problems and all(str(tar) in p for p in problems) and "sha256" in problems[0]


def test_verify_reports_a_truncated_shard(tiny_dataset, tmp_path):
    ds = copy_dataset(tiny_dataset, tmp_path / "ds")
    tar = tar_path(ds, 0)
    tar.write_bytes(tar.read_bytes()[:5000])
    problems = verify_dataset(ds)["problems"]
    assert problems and str(tar) in problems[0]
    # Even with a sidecar rewritten to match, the truncated tar itself is reported as corrupt.
    side = json.loads(sidecar_path(ds, 0).read_text())
    from datagen.files import sha256_file

    side.update(tar_bytes=tar.stat().st_size, tar_sha256=sha256_file(tar))
    sidecar_path(ds, 0).write_text(json.dumps(side))
    problems = verify_dataset(ds)["problems"]
    assert any(str(tar) in p and ("truncated" in p or "fields" in p or "decode" in p) for p in problems)


@pytest.mark.parametrize("change", ["shift", "swap", "past_the_end"])
def test_verify_checks_every_byte_range_in_the_sidecar(tiny_dataset, tmp_path, change):
    ds = copy_dataset(tiny_dataset, tmp_path / "ds")
    path = sidecar_path(ds, 0)
    side = json.loads(path.read_text())
    a, b = list(side["offsets"])[:2]
    if change == "shift":
        side["offsets"][a][0] += 512
    elif change == "swap":
        side["offsets"][a], side["offsets"][b] = side["offsets"][b], side["offsets"][a]
    else:
        side["offsets"][b][1] = side["tar_bytes"] + 10_000
    path.write_text(json.dumps(side))
    problems = verify_dataset(ds)["problems"]
    assert problems and any("byte range" in p and (a in p or b in p) for p in problems), problems


def test_verify_tells_an_unreadable_sidecar_from_a_missing_one(tiny_dataset, tmp_path):
    ds = copy_dataset(tiny_dataset, tmp_path / "ds")
    sidecar_path(ds, 0).write_text("{broken")
    problems = verify_dataset(ds)["problems"]
    assert len(problems) == 1 and "not valid JSON" in problems[0] and str(sidecar_path(ds, 0)) in problems[0]


def test_verify_reports_a_missing_sidecar(tiny_dataset, tmp_path):
    ds = copy_dataset(tiny_dataset, tmp_path / "ds")
    sidecar_path(ds, 1).unlink()
    report = verify_dataset(ds)
    assert report["complete"] == 1
    assert len(report["problems"]) == 1 and "incomplete" in report["problems"][0]


def test_rerun_of_a_partly_done_job_without_resume_is_refused(tiny_dataset, tmp_path):
    ds = copy_dataset(tiny_dataset, tmp_path / "ds")
    (ds / "shard-000001.json").unlink()
    with pytest.raises(UserError, match="pass resume to continue, or choose another out"):
        run_sample(tiny_spec(ds), progress=False)  # the command line words them --resume, --out


def test_resuming_a_complete_dataset_with_workers_does_nothing(tiny_dataset):
    before = {p: p.stat().st_mtime_ns for p in tiny_dataset.rglob("*")}
    summary = run_sample(tiny_spec(tiny_dataset), resume=True, workers=2, progress=False)
    assert summary["shards_written"] == 0 and summary["images"] == 0
    assert {p: p.stat().st_mtime_ns for p in tiny_dataset.rglob("*")} == before


def test_other_settings_into_the_same_folder_are_refused(tiny_dataset):
    with pytest.raises(UserError, match="resolution"):
        run_sample(tiny_spec(tiny_dataset, resolution=48), resume=True, progress=False)


def test_resume_after_sigkill_loses_and_duplicates_nothing(tmp_path):
    out = tmp_path / "killed"
    args = [sys.executable, "-m", "datagen.cli", "sample", "--subjects", "6", "--shard-size", "1",
            "--resolution", "32", "--views", "4", "--seed", "7", "--out", str(out), "--quiet"]
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.time() + 120
    while time.time() < deadline and not sidecar_path(out, 1).exists():
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert sidecar_path(out, 1).exists(), "the run never completed a shard"
    complete = [i for i in range(6) if sidecar_path(out, i).exists()]
    assert len(complete) < 6, "killed too late to test anything"
    # Whatever looks complete is valid; whatever is not complete has no sidecar.
    report = verify_dataset(out)
    assert report["complete"] == len(complete)
    assert all("incomplete" in p for p in report["problems"])
    rerun = subprocess.run(args + ["--resume"], env=env, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    assert f"skipped {len(complete)} complete" in rerun.stdout
    report = verify_dataset(out)
    assert report["problems"] == [] and report["subjects"] == 6 and report["stray"] == []
    clean = tmp_path / "clean"
    subprocess.run([a if a != str(out) else str(clean) for a in args], env=env, check=True, timeout=300)
    assert all_files(out) == all_files(clean)


def test_sigterm_stops_the_workers_too_and_resume_completes(tmp_path):
    """``kill PID`` (or ``timeout``) reaches only the command: its workers must stop with it, not finish
    their queued shards into the folder the next run resumes."""
    out = tmp_path / "terminated"
    args = [sys.executable, "-m", "datagen.cli", "sample", "--subjects", "16", "--shard-size", "1", "--workers", "2",
            "--resolution", "64", "--views", "8", "--seed", "7", "--out", str(out), "--quiet"]
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)  # its own process group: every worker is in it
    deadline = time.time() + 120
    while time.time() < deadline and not any(sidecar_path(out, i).exists() for i in range(16)):
        time.sleep(0.02)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143 and err.strip() == "datagen sample: terminated; rerun with --resume to continue"
    complete = [i for i in range(16) if sidecar_path(out, i).exists()]
    assert len(complete) < 16, "terminated too late to test anything"
    assert group_ended(proc.pid, 10), "worker processes outlived the command"
    assert [i for i in range(16) if sidecar_path(out, i).exists()] == complete  # none wrote after the command ended
    rerun = subprocess.run(args + ["--resume"], env=env, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    report = verify_dataset(out)
    assert report["problems"] == [] and report["subjects"] == 16 and report["stray"] == []


# -- two runs into one folder ------------------------------------------------------------------------

SAMPLE = [sys.executable, "-m", "datagen.cli", "sample", "--subjects", "4", "--shard-size", "1", "--views", "3",
          "--seed", "7", "--quiet"]
ENV = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))


def test_a_shard_in_progress_elsewhere_is_left_alone(tmp_path):
    """Another run holds shard 0's lock: this run neither deletes its temporary tar nor writes the shard."""
    from datagen.files import byte_lock
    from datagen.pipeline import LOCK_NAME

    out = tmp_path / "ds"
    out.mkdir()
    theirs = out / ".shard-000000.tar.tmp-99999"
    theirs.write_bytes(b"half a shard")
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from datagen.files import byte_lock\n"
        f"with byte_lock({str(out / LOCK_NAME)!r}, 1):\n    print('locked', flush=True); time.sleep(60)")],
        env=ENV, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        done = subprocess.run(SAMPLE + ["--resolution", "32", "--out", str(out)], env=ENV, capture_output=True,
                              text=True, timeout=300)
        assert done.returncode == 2 and done.stderr.count("\n") == 1
        assert "shard-000000.tar is being written by another datagen run" in done.stderr
        assert theirs.read_bytes() == b"half a shard"
    finally:
        holder.kill()
        holder.wait()
    with byte_lock(out / LOCK_NAME, 1, blocking=False):  # released when its holder died
        pass


def test_two_runs_with_different_settings_started_together(tmp_path):
    out = tmp_path / "ds"
    procs = [subprocess.Popen(SAMPLE + ["--resolution", str(r), "--out", str(out)], env=ENV, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for r in (32, 40)]
    results = [(p.wait(timeout=300), p.stderr.read()) for p in procs]
    assert sorted(rc for rc, _ in results) == [0, 2], results
    assert "already holds a dataset made with other settings (resolution)" in next(e for rc, e in results if rc)
    assert verify_dataset(out)["problems"] == []


def test_split_array_jobs_run_concurrently_into_one_folder(tmp_path):
    out = tmp_path / "ds"
    procs = [subprocess.Popen(SAMPLE + ["--resolution", "32", "--out", str(out), "--shard-index", str(k),
                                        "--num-shards", "2"], env=ENV, stderr=subprocess.PIPE, text=True)
             for k in (0, 1)]
    assert [p.wait(timeout=300) for p in procs] == [0, 0], [p.stderr.read() for p in procs]
    report = verify_dataset(out)
    assert report["problems"] == [] and report["subjects"] == 4
    single = tmp_path / "single"
    subprocess.run(SAMPLE + ["--resolution", "32", "--out", str(single)], env=ENV, check=True, timeout=300)
    assert all_files(out) == all_files(single)
