"""Curation: event logs, headless review sessions driven by keys, resume after kill -9, manifests."""
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("vtkmodules", reason="the review window needs VTK")

from labeling_tool.cli import build_queue, main as label_main  # noqa: E402
from datagen.dataset.events import Event, EventLog, Verdicts, parse_event, read_log, read_logs, verdicts  # noqa: E402
from labeling_tool.review import ReviewApp  # noqa: E402
from datagen.dataset.manifests import read_manifest  # noqa: E402
from labeling_tool.compiler import compile_manifest, subject_hash  # noqa: E402
from datagen.dataset.preflags import FORMAT as PREFLAGS_FORMAT, write_preflags  # noqa: E402
from datagen.errors import UserError  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tiny_dataset(tiny_dataset, tmp_path_factory):
    """This module's copy of the shared dataset: compiling caches its shard checks in the dataset folder."""
    return Path(shutil.copytree(tiny_dataset, tmp_path_factory.mktemp("labeling") / "ds"))


@pytest.fixture
def app_factory(tiny_dataset, tmp_path):
    apps = []

    def make(reviewer="alice", labels=None, **kw):
        _, queue = build_queue(str(tiny_dataset), "all")
        app = ReviewApp(tiny_dataset, queue, reviewer, labels or tmp_path / "labels", off_screen=True,
                        window_size=(640, 360), **kw)
        apps.append(app)
        return app
    yield make
    for a in apps:
        a.close()


def actions(labels, reviewer):
    events, problems = read_log(Path(labels) / f"{reviewer}.jsonl")
    assert problems == []
    return [(e.subject, e.action, e.reasons) for e in events]


def test_keys_produce_events(app_factory, tmp_path):
    app = app_factory()
    for k in ["g", "2", "z", "3"]:
        app.press(k)
    assert actions(tmp_path / "labels", "alice") == [
        ("subj00000000", "good", ()), ("subj00000001", "bad", ("broken_back",)),
        ("subj00000001", "undo", ()), ("subj00000001", "bad", ("artifacts",))]
    v = app.log.verdicts()
    assert v["subj00000000"].action == "good" and v["subj00000001"].reasons == ("artifacts",)
    assert app.pos == 2


def test_navigation_and_next_unreviewed(app_factory):
    app = app_factory()
    app.press("Right")
    app.press("Right")
    assert app.pos == 2
    app.press("Left")
    assert app.pos == 1
    app.press("g")  # reviews subject 1, moves to 2
    app.press("Left")
    app.press("Left")
    app.press("u")  # first subject without a verdict after position 0 -> 2
    assert app.pos == 2


def test_default_vtk_and_pyvista_keys_do_not_fire(app_factory):
    app = app_factory()
    app.press("v")
    surface = app.surface.actor
    for k in ["w", "q", "e", "f", "plus", "Up"]:  # VTK's own keys ("3": stereo) do nothing; "3" is a verdict here
        app.press(k)
    assert surface.GetProperty().GetRepresentation() == 2  # still surface, not wireframe
    assert not app.closed  # 'q' / 'e' did not close the window
    assert app.mode == "3d" and app.log.events == []


def test_screenshot_is_not_blank_and_hud_shows_state(app_factory):
    app = app_factory()
    app.press("g")
    img = app.screenshot()
    assert img.shape[:2] == (360, 640) and img.std() > 20
    status, detail = app.status_text()
    assert "subj00000001" in status and "reviewed 1, left 2" in status and "verdict: none" in detail


def test_help_and_3d_toggles(app_factory):
    app = app_factory()
    app.press("h")
    assert app.show_help and app.help_layer.visible()
    app.press("h")
    assert not app.help_layer.visible()
    app.press("v")
    assert app.mode == "3d" and app.surface.actor is not None and not app.grid_layer.visible()
    assert app.screenshot().std() > 5
    app.press("v")
    assert app.mode == "review" and app.surface.actor is None and app.grid_layer.visible()


def test_triage_marks_and_commits_a_page(app_factory, tmp_path):
    app = app_factory(start_in_triage=True)
    assert app.mode == "triage" and len(app.triage.page.thumbs) == 3
    app.press("Right")
    app.press("1")          # subject 1 bad (multiple faces); the cursor stays
    assert app.triage_cursor == 1
    app.click(*app.cell_center(2))  # a click on cell 2 flips it to bad with its default reason
    assert app.pending == {"subj00000001": ("bad", ("multiple_faces",)), "subj00000002": ("bad", ("artifacts",))}
    app.click(*app.cell_center(2))  # again: the change is taken back
    assert "subj00000002" not in app.pending
    app.press("Return")
    assert actions(tmp_path / "labels", "alice") == [
        ("subj00000000", "good", ()), ("subj00000001", "bad", ("multiple_faces",)), ("subj00000002", "good", ())]


def test_reopening_resumes_where_the_reviewer_left_off(app_factory, tmp_path):
    app = app_factory()
    app.press("g")
    app.press("g")
    app.press("s")          # subject 2: decide later
    app.close()
    again = app_factory()
    assert again.pos == 2   # the skipped subject is not reviewed: the session resumes there
    again.press("s")        # skipped again (nothing written) ...
    again.close()
    assert app_factory().pos == 2
    events, _ = read_log(tmp_path / "labels" / "alice.jsonl")
    assert [e.action for e in events] == ["good", "good", "skip"]


def test_kill_9_mid_session_loses_and_duplicates_nothing(tiny_dataset, tmp_path):
    labels = tmp_path / "labels"
    script = (
        "import sys, time\n"
        "from labeling_tool.cli import build_queue\n"
        "from labeling_tool.review import ReviewApp\n"
        f"_, q = build_queue({str(tiny_dataset)!r}, 'all')\n"
        f"app = ReviewApp({str(tiny_dataset)!r}, q * 40, 'carol', {str(labels)!r}, off_screen=True, window_size=(320, 200))\n"
        "keys = ['g', '1', 'Right'] * 1000\n"
        "for k in keys:\n"
        "    app.press(k)\n"
        "    time.sleep(0.002)\n"
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-c", script], env=env, stderr=subprocess.DEVNULL)
    log = labels / "carol.jsonl"
    deadline = time.time() + 120
    while time.time() < deadline and (not log.exists() or log.read_bytes().count(b"\n") < 10):
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    events, problems = read_log(log)
    assert len(events) >= 10
    assert all("partial last line" in p for p in problems) and len(problems) <= 1
    assert [e.seq for e in events] == list(range(1, len(events) + 1))  # nothing lost, nothing twice
    reopened = EventLog(labels, "carol")
    nxt = reopened.append("subj00000000", "shard-000000", "good")
    reopened.close()
    assert nxt.seq == len(events) + 1
    events2, problems2 = read_log(log)
    assert [e.seq for e in events2] == list(range(1, len(events) + 2)) and len(problems2) == len(problems)


def test_corrupt_and_partial_lines_are_reported(tmp_path):
    log = EventLog(tmp_path, "dave")
    log.append("subj00000000", "shard-000000", "good")
    log.close()
    path = tmp_path / "dave.jsonl"
    with open(path, "ab") as f:
        f.write(b'{"not": "an event"}\n{"seq": 3, "action": "go')
    events, problems = read_log(path)
    assert len(events) == 1
    assert any(":2: not a valid event (missing" in p for p in problems)
    assert any(":3: partial last line" in p for p in problems)
    _, all_problems = read_logs(tmp_path)
    assert len(all_problems) == 2


def test_undo_is_an_event_and_cancels_the_latest_verdict(tmp_path):
    log = EventLog(tmp_path, "erin")
    log.append("a", "s", "good")
    log.append("b", "s", "bad", ("blur",))
    log.append("b", "s", "undo")
    log.append("a", "s", "bad", ("other",))
    v = verdicts(log.events)
    assert set(v) == {"a"} and v["a"].action == "bad"
    with pytest.raises(UserError):
        EventLog(tmp_path, "../escape")


def test_verdicts_of_a_whole_log_are_those_kept_event_by_event():
    rng = np.random.default_rng(3)
    for _ in range(200):
        events = [Event(i + 1, "t", "r", f"s{rng.integers(5)}", "shard-000000", action, ("blur",) if action == "bad"
                        else ()) for i, action in enumerate(rng.choice(["good", "bad", "skip", "undo"], rng.integers(30)))]
        kept = Verdicts(events).current
        assert list(verdicts(events).items()) == list(kept.items())


def two_reviewers(tiny_dataset, labels):
    a, b = EventLog(labels, "alice"), EventLog(labels, "bob")
    for log, calls in ((a, [("subj00000000", "good"), ("subj00000001", "bad"), ("subj00000002", "good")]),
                       (b, [("subj00000000", "good"), ("subj00000001", "good"), ("subj00000002", "bad")])):
        for s, act in calls:
            log.append(s, "shard-000000" if s != "subj00000002" else "shard-000001", act,
                       ("artifacts",) if act == "bad" else ())
        log.close()


def test_two_reviewers_policies_conflicts_and_stats(tiny_dataset, tmp_path, capsys):
    labels = tmp_path / "labels"
    two_reviewers(tiny_dataset, labels)
    m = compile_manifest(tiny_dataset, labels, "any-bad", test_count=1)
    rows = {r["subject"]: r for r in m["subjects"]}
    assert rows["subj00000000"]["verdict"] == "accepted"
    assert rows["subj00000001"]["verdict"] == "rejected" and rows["subj00000001"]["reasons"] == ["artifacts"]
    assert m["header"]["conflicts"] == ["subj00000001", "subj00000002"]
    assert m["header"]["counts"]["accepted"] == 1 and m["header"]["counts"]["test"] == 1
    maj = compile_manifest(tiny_dataset, labels, "majority", test_count=0)
    assert all(r["verdict"] == "rejected" for r in maj["subjects"] if r["subject"] != "subj00000000")  # ties reject
    code = label_main(["stats", str(tiny_dataset), "--labels", str(labels), "--json"])
    st = json.loads(capsys.readouterr().out)
    assert code == 0 and st["reviewers"]["alice"]["bad"] == 1 and st["reasons"] == {"artifacts": 2}
    assert st["agreement"][0]["subjects"] == 3 and st["agreement"][0]["agreement"] == pytest.approx(1 / 3, abs=1e-3)


def test_compile_is_deterministic_versioned_and_immutable(tiny_dataset, tmp_path, capsys):
    labels = tmp_path / "labels"
    two_reviewers(tiny_dataset, labels)
    out1, out2 = tmp_path / "m" / "demo-v1.json", tmp_path / "m" / "demo-v2.json"
    assert label_main(["compile", str(tiny_dataset), "--labels", str(labels), "--out", str(out1)]) == 0
    assert label_main(["compile", str(tiny_dataset), "--labels", str(labels), "--out", str(out2),
                       "--parent", str(out1)]) == 0
    m1, m2 = read_manifest(out1), read_manifest(out2)
    assert m1["subjects"] == m2["subjects"]
    h1, h2 = m1["header"], m2["header"]
    assert h1["version"] == "demo-v1" and h2["version"] == "demo-v2" and h2["parent_version"] == "demo-v1"
    assert {k: v for k, v in h1.items() if k not in ("version", "parent_version", "created")} == \
           {k: v for k, v in h2.items() if k not in ("version", "parent_version", "created")}
    assert len(h1["dataset_index_sha256"]) == 64
    lines = out2.read_text().splitlines()  # one subject per line, after the header
    rows = lines[lines.index(' "subjects": [') + 1:-2]
    assert [json.loads(line.rstrip(",")) for line in rows] == m2["subjects"] and lines[-2:] == [" ]", "}"]
    before = out1.read_bytes()
    capsys.readouterr()
    assert label_main(["compile", str(tiny_dataset), "--labels", str(labels), "--out", str(out1)]) == 2
    assert "never edited" in capsys.readouterr().err and out1.read_bytes() == before


@pytest.mark.parametrize("damage", ["truncate", "flip", "no_sidecar", "bad_sidecar"])
def test_compile_vouches_only_for_verified_shards(tiny_dataset, tmp_path, capsys, damage):
    import shutil
    from datagen.dataset.shards import sidecar_path, tar_path
    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds)
    tar = tar_path(ds, 1)
    if damage == "truncate":
        tar.write_bytes(tar.read_bytes()[:3000])
    elif damage == "flip":
        data = bytearray(tar.read_bytes())
        data[len(data) // 2] ^= 1
        tar.write_bytes(bytes(data))
    elif damage == "no_sidecar":
        sidecar_path(ds, 1).unlink()
    else:
        sidecar_path(ds, 1).write_text("{")
    out = tmp_path / "m" / "ds-v1.json"
    (tmp_path / "labels").mkdir()
    args = ["compile", str(ds), "--labels", str(tmp_path / "labels"), "--out", str(out)]
    assert label_main(args) == 2
    err = capsys.readouterr().err
    assert "shard-000001" in err and "--skip-incomplete" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
    assert label_main(args + ["--skip-incomplete"]) == 0
    m = read_manifest(out)
    rows = {r["subject"]: r for r in m["subjects"]}
    bad = [r for r in rows.values() if r["shard"] == "shard-000001"]
    assert bad and all(r["verdict"] == "rejected" and r["reasons"] == ["unverified_shard"] for r in bad)
    assert m["header"]["counts"]["unverified_shards"] == ["shard-000001"]
    assert "1 unverified shard(s) were rejected" in capsys.readouterr().out


def test_negative_test_count_is_refused(tiny_dataset, tmp_path, capsys):
    out = tmp_path / "m" / "demo-v1.json"
    assert label_main(["compile", str(tiny_dataset), "--labels", str(tmp_path / "none"), "--out", str(out),
                       "--test-count", "-3"]) == 2
    assert "--test-count must be 0 or more" in capsys.readouterr().err and not out.exists()


def test_test_split_is_the_smallest_hashes(tiny_dataset, tmp_path):
    labels = tmp_path / "labels"
    labels.mkdir()
    m = compile_manifest(tiny_dataset, labels, test_count=2)
    test = sorted(r["subject"] for r in m["subjects"] if r["split"] == "test")
    expected = sorted(sorted((r["subject"] for r in m["subjects"]), key=subject_hash)[:2])
    assert test == expected and m["header"]["counts"]["accepted"] == 3  # unreviewed accepted by default
    strict = compile_manifest(tiny_dataset, labels, unreviewed="reject")
    assert strict["header"]["counts"]["accepted"] == 0


def test_review_cli_off_screen_with_keys(tiny_dataset, tmp_path, capsys):
    labels, shot = tmp_path / "labels", tmp_path / "shot.png"
    tar = str(Path(tiny_dataset) / "shard-000000.tar")
    code = label_main(["review", tar, "--reviewer", "fay", "--labels", str(labels), "--off-screen",
                       "--keys", "g 4", "--screenshot", str(shot)])
    assert code == 0 and shot.exists()
    assert actions(labels, "fay") == [("subj00000000", "good", ()), ("subj00000001", "bad", ("blur",))]
    assert "2/2 reviewed" in capsys.readouterr().out
    assert label_main(["review", str(tiny_dataset), "--reviewer", "fay", "--queue", "suspicious",
                       "--labels", str(labels), "--off-screen"]) == 2 or (Path(tiny_dataset) / "preflags.json").exists()


# ------------------------------------------------------------------------------------------------
# The event-log format: one check, the same reading for review and compile


def event_line(**fields) -> str:
    d = {"seq": 1, "time": "2026-01-01T00:00:00.000+00:00", "reviewer": "alice", "subject": "subj00000000",
         "shard": "shard-000000", "action": "good", "reasons": []}
    d.update(fields)
    return json.dumps({k: v for k, v in d.items() if v != "<absent>"})


@pytest.mark.parametrize("line, message", [
    (event_line(seq=None), "seq must be a positive integer, not null"),
    (event_line(seq=True), "seq must be a positive integer"),
    (event_line(seq="3"), "seq must be a positive integer"),
    (event_line(seq=0), "seq must be a positive integer"),
    (event_line(reasons=3), "reasons must be a list"),
    (event_line(action="bad", reasons=[3]), "reasons must be a list"),
    (event_line(subject=5), "subject must be a non-empty string"),
    (event_line(time=None), "time must be a non-empty string"),
    (event_line(action="great"), "unknown action"),
    (event_line(action="bad"), "a bad verdict without a reason"),
    (event_line(action="bad", reasons=["ugly"]), "unknown reason"),
    (event_line(reasons=["blur"]), "reasons on a good event"),
    (event_line(shard="<absent>"), "missing shard"),
    ("[1, 2]", "not a JSON object"),
    (event_line(reviewer="bob"), "an event of reviewer 'bob' in the log of 'alice'"),
])
def test_parse_event_checks_every_field(line, message):
    with pytest.raises(ValueError, match=message):
        parse_event(line, "alice")
    from datagen.dataset.events import _common_event
    assert _common_event(line.encode(), "alice") is None  # the fast reader leaves every problem to parse_event


@pytest.mark.parametrize("line", [
    event_line(), event_line(action="bad", reasons=["back", "blur"]), event_line(action="skip", reasons="<absent>"),
    event_line(action="undo", seq=7), json.dumps({"seq": 2, "time": "t", "reviewer": "alice", "subject": "s",
                                                    "shard": "shard-000001", "action": "good", "extra": 1}),
    event_line() + "  ", " " + event_line(), event_line(subject="subj\u00e9"),
])
def test_the_fast_event_reader_reads_what_parse_event_reads(line):
    from datagen.dataset.events import _common_event
    fast = _common_event(line.encode(), "alice")
    assert fast is None or fast == parse_event(line, "alice")
    assert line != event_line() or fast is not None  # the form the log writes takes the fast path


def test_older_lines_without_reasons_are_read():
    assert parse_event(event_line(reasons="<absent>"), "alice").reasons == ()
    assert parse_event(event_line(reasons=None, extra="ignored"), "alice").reasons == ()


def write_troubled_logs(labels: Path) -> None:
    """alice's log with a foreign event, bad fields and a repeated number; a folder named bob.jsonl."""
    labels.mkdir(parents=True)
    lines = [event_line(seq=1, subject="subj00000000"),
             event_line(seq=2, subject="subj00000001", reviewer="bob"),       # another reviewer's event
             event_line(seq=None, subject="subj00000002"),                   # "seq": null
             event_line(seq=3, subject="subj00000002", action="bad", reasons=3),  # "reasons": 3
             event_line(seq=1, subject="subj00000002", action="bad", reasons=["blur"])]  # number repeated
    (labels / "alice.jsonl").write_text("\n".join(lines) + "\n")
    (labels / "bob.jsonl").mkdir()


def test_troubled_logs_are_read_alike_by_review_and_compile(tiny_dataset, tmp_path, capsys):
    labels = tmp_path / "labels"
    write_troubled_logs(labels)
    alice = str(labels / "alice.jsonl")
    expected = [f"{alice}:2: an event of reviewer 'bob' in the log of 'alice' (ignored)",
                f"{alice}:3: not a valid event (seq must be a positive integer, not null)",
                f"{alice}:4: not a valid event (reasons must be a list of reason names, not 3)",
                f"{alice}:5: event number 1 repeats line 1"]
    _, queue = build_queue(str(tiny_dataset), "all")
    app = ReviewApp(tiny_dataset, queue, "alice", labels, off_screen=True, window_size=(640, 360))
    review_seen = {s: e.action for s, e in app.log.verdicts().items()}
    assert app.log.problems == expected
    assert app.done == 2 and app.pos == 1  # subj00000001's verdict was bob's: alice has not reviewed it
    app.close()
    m = compile_manifest(tiny_dataset, labels)
    assert [p for p in m["header"]["log_problems"] if p.startswith(alice)] == expected
    assert any("bob.jsonl: not a file" in p for p in m["header"]["log_problems"])
    rows = {r["subject"]: r for r in m["subjects"]}
    compile_seen = {s: r["votes"]["alice"] for s, r in rows.items() if "alice" in r["votes"]}
    assert compile_seen == review_seen == {"subj00000000": "good", "subj00000002": "bad"}
    assert rows["subj00000001"]["reviewers"] == []
    out = tmp_path / "m" / "ds-v1.json"
    assert label_main(["compile", str(tiny_dataset), "--labels", str(labels), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "Traceback" not in err and f"{alice}:3:" in err and "bob.jsonl: not a file" in err
    assert label_main(["stats", str(tiny_dataset), "--labels", str(labels)]) == 0
    assert f"{alice}:4:" in capsys.readouterr().out


def test_review_refuses_a_log_that_is_a_folder(tiny_dataset, tmp_path, capsys):
    labels = tmp_path / "labels"
    write_troubled_logs(labels)
    code = label_main(["review", str(tiny_dataset), "--reviewer", "bob", "--labels", str(labels), "--off-screen"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "bob.jsonl: not a file" in err


# ------------------------------------------------------------------------------------------------
# Subjects nobody reviewed


def with_preflags(tiny_dataset, tmp_path, flagged, stale=False) -> Path:
    """A copy of the tiny dataset whose pre-flags flag ``flagged`` (janus)."""
    root = tmp_path / "ds"
    shutil.copytree(tiny_dataset, root)
    index = hashlib.sha256((root / "index.json").read_bytes()).hexdigest()
    subjects = [{"subject": f"subj0000000{i}", "score": 0.9 if f"subj0000000{i}" in flagged else 0.1,
                 "flags": ["janus"] if f"subj0000000{i}" in flagged else [],
                 "detectors": {"janus": {"score": 0.9, "why": "a face on the back"}}} for i in range(3)]
    write_preflags(root, {"format": PREFLAGS_FORMAT, "dataset_index_sha256": "0" * 64 if stale else index,
                          "subjects": subjects})
    return root


def test_compile_reports_and_can_reject_flagged_subjects_nobody_reviewed(tiny_dataset, tmp_path, capsys):
    root = with_preflags(tiny_dataset, tmp_path, flagged={"subj00000001", "subj00000002"})
    labels = tmp_path / "labels"
    log = EventLog(labels, "alice")
    log.append("subj00000002", "shard-000001", "good")  # flagged, but reviewed: the review decides
    log.close()
    m = compile_manifest(root, labels)
    c = m["header"]["counts"]
    assert (c["unreviewed"], c["unreviewed_flagged"], c["unreviewed_flagged_accepted"], c["accepted"]) == (2, 1, 1, 3)
    assert label_main(["compile", str(root), "--labels", str(labels), "--out", str(tmp_path / "m" / "a-v1.json")]) == 0
    out = capsys.readouterr().out
    assert "warning: 1 flagged subject(s) accepted without review" in out and "reject-flagged" in out
    strict = compile_manifest(root, labels, unreviewed="reject-flagged")
    verdict = {r["subject"]: r["verdict"] for r in strict["subjects"]}
    assert verdict == {"subj00000000": "accepted", "subj00000001": "rejected", "subj00000002": "accepted"}
    assert strict["header"]["counts"]["unreviewed_flagged_accepted"] == 0
    assert label_main(["compile", str(root), "--labels", str(labels), "--unreviewed", "reject-flagged",
                       "--out", str(tmp_path / "m" / "a-v2.json")]) == 0
    assert "warning" not in capsys.readouterr().out


@pytest.mark.parametrize("stale, message", [(False, "needs pre-flags"), (True, "made for another index.json")])
def test_reject_flagged_without_current_preflags_is_one_line(tiny_dataset, tmp_path, capsys, stale, message):
    root = with_preflags(tiny_dataset, tmp_path, flagged={"subj00000001"}, stale=stale)
    if not stale:
        (root / "preflags.json").unlink()
    labels = tmp_path / "labels"
    labels.mkdir()
    out = tmp_path / "m" / "a-v1.json"
    code = label_main(["compile", str(root), "--labels", str(labels), "--unreviewed", "reject-flagged",
                       "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and message in err and not out.exists()
    assert label_main(["compile", str(root), "--labels", str(labels), "--out", str(out)]) == 0
    assert "no current pre-flags" in capsys.readouterr().out


def test_auto_explains_its_columns_and_says_how_many_it_shows(tiny_dataset, tmp_path, capsys):
    from tests.test_dataset import copy_dataset

    ds = copy_dataset(tiny_dataset, tmp_path / "ds")
    assert label_main(["auto", str(ds), "--quiet", "--top", "2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1] == "worst first; score = the subject's highest pre-flag score, 0 to 1 (flagged from 0.50):"
    assert len(lines) == 5
    assert lines[-1] == f"2 of 3 shown (--top N shows more; every score is in {ds / 'preflags.json'})"
    assert label_main(["auto", str(ds), "--quiet"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "3 of 3 shown"


def test_stats_without_verdicts_says_so_in_one_line(tiny_dataset, tmp_path, capsys):
    (tmp_path / "labels").mkdir()
    assert label_main(["stats", str(tiny_dataset), "--labels", str(tmp_path / "labels")]) == 0
    assert capsys.readouterr().out == (f"no verdicts in {tmp_path / 'labels'} yet; review with: label-tool review "
                                       f"{tiny_dataset} --reviewer NAME --labels {tmp_path / 'labels'}\n")


def test_a_full_disk_is_one_line_naming_the_log_and_keeps_the_saved_verdicts(tiny_dataset, tmp_path, capsys,
                                                                              monkeypatch):
    import errno
    import datagen.dataset.events as events
    labels = tmp_path / "labels"
    real, calls = events.os.fsync, []

    def fsync(fd):  # the third write fails after its bytes went out, as a full disk fails a flush
        calls.append(fd)
        if len(calls) >= 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        real(fd)
    monkeypatch.setattr(events.os, "fsync", fsync)
    code = label_main(["review", str(tiny_dataset), "--reviewer", "gus", "--labels", str(labels), "--off-screen",
                       "--keys", "g 2 g"])
    out, err = capsys.readouterr()
    log = labels / "gus.jsonl"
    assert code == 2 and len(err.strip().splitlines()) == 1 and str(log) in err and "failed" in err
    assert "Traceback" not in out + err and "2/3 reviewed" in out
    assert actions(labels, "gus") == [("subj00000000", "good", ()), ("subj00000001", "bad", ("broken_back",))]
    assert log.read_bytes().endswith(b"\n")  # the failed line was taken back whole


def test_a_failed_write_leaves_the_session_where_it_was(app_factory, tmp_path, monkeypatch):
    import errno
    import datagen.dataset.events as events
    app = app_factory()
    app.press("g")
    monkeypatch.setattr(events.os, "fsync", lambda fd: (_ for _ in ()).throw(OSError(errno.ENOSPC, "full")))
    app.press("2")
    assert app.notice[0] == "error" and str(tmp_path / "labels" / "alice.jsonl") in app.notice[1]
    assert app.pos == 1 and app.done == 1 and app.log.seq == 1  # still on the subject whose verdict failed
    monkeypatch.undo()
    app.press("2")
    assert actions(tmp_path / "labels", "alice") == [("subj00000000", "good", ()),
                                                     ("subj00000001", "bad", ("broken_back",))]


def test_review_queue_refuses_or_hides_pre_flags_of_another_index(tiny_dataset, tmp_path, capsys):
    root = with_preflags(tiny_dataset, tmp_path, flagged={"subj00000001"}, stale=True)
    with pytest.raises(UserError, match="--queue worst needs pre-flags; those of .* were made for another index.json"):
        build_queue(str(root), "worst")
    _, items = build_queue(str(root), "all")
    assert [it.flag_pairs for it in items] == [(), (), ()] and "note: pre-flags not shown" in capsys.readouterr().out
    current = with_preflags(tiny_dataset, tmp_path / "current", flagged={"subj00000001"})
    _, items = build_queue(str(current), "worst")
    assert items[0].subject == "subj00000001" and items[0].flag_pairs == (("janus", 0.9),)


def test_compile_reads_the_flags_from_the_queue_file_while_it_is_current(tiny_dataset, tmp_path, monkeypatch):
    import datagen.dataset.preflags as report_format

    root = with_preflags(tiny_dataset, tmp_path, flagged={"subj00000001"})
    labels = tmp_path / "labels"
    labels.mkdir()
    read = []
    real = report_format.read_preflags
    monkeypatch.setattr(report_format, "read_preflags", lambda *a, **k: read.append(a) or real(*a, **k))
    verdicts = lambda: {r["subject"]: r["verdict"]  # noqa: E731
                        for r in compile_manifest(root, labels, unreviewed="reject-flagged")["subjects"]}
    want = {"subj00000000": "accepted", "subj00000001": "rejected", "subj00000002": "accepted"}
    assert verdicts() == want and read == []  # the 165K-subject report is not parsed
    queue = json.loads((root / report_format.QUEUE_NAME).read_text())
    del queue["dataset_index_sha256"]  # a queue written before it said which index it was made for
    (root / report_format.QUEUE_NAME).write_text(json.dumps(queue))
    assert verdicts() == want and len(read) == 1  # read from the report instead
