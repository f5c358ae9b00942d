"""The review session without a window: verdicts, undo, skips, triage pages and commits, resuming.

The last test drives the window (off-screen): verdict keys typed in the 3D view.
"""
from contextlib import ExitStack

import pytest

from datagen.errors import UserError
from datagen.dataset.events import read_log
from labeling_tool.review import QueueItem, ReviewSession

SUBJECTS = [f"subj{i:08d}" for i in range(7)]


def queue(n=len(SUBJECTS)):
    return [QueueItem(s, "shard-000000", flags=(("janus", 0.9),) if i == 1 else ()) for i, s in
            enumerate(SUBJECTS[:n])]


@pytest.fixture
def session(tmp_path):
    """Opens sessions over ``queue(n)`` (triage pages of 3 subjects); they are closed after the test."""
    with ExitStack() as opened:
        def make(reviewer="alice", n=len(SUBJECTS), triage_shape=(1, 3)):
            s = ReviewSession(queue(n), reviewer, tmp_path / "labels", triage_shape)
            opened.callback(s.close)
            return s
        yield make


def written(tmp_path, reviewer="alice"):
    events, problems = read_log(tmp_path / "labels" / f"{reviewer}.jsonl")
    assert problems == []
    return [(e.subject[-1], e.action, e.reasons) for e in events]


def test_an_empty_queue_is_one_line(tmp_path):
    with pytest.raises(UserError, match="nothing to review"):
        ReviewSession([], "alice", tmp_path / "labels")
    assert not (tmp_path / "labels").exists()


def test_a_verdict_is_written_once_and_moves_on(session, tmp_path):
    s = session(n=2)
    assert s.verdict("bad", ("blur",)) == ("saved", "saved: subj00000000 bad: blur")
    assert (s.pos, s.done) == (1, 1)
    s.pos = 0
    assert s.verdict("bad", ("blur",)) == ("warn", "subj00000000 is already bad: blur: nothing written")
    kind, message = s.verdict("good")          # the last subject: it stays, and says so
    assert kind == "saved" and message.endswith("(last subject of the queue; u finds any left)")
    assert (s.pos, s.done) == (1, 2)
    assert written(tmp_path) == [("0", "bad", ("blur",)), ("1", "good", ())]


def test_a_skip_stays_unreviewed_and_next_unreviewed_finds_it(session):
    s = session()
    s.verdict("good")
    s.verdict("skip")
    s.verdict("good")
    assert (s.pos, s.done, s.skipped) == (3, 2, 1)
    assert s.first_unreviewed(s.pos + 1) == 4
    for _ in range(4):
        s.verdict("good")
    assert s.first_unreviewed(s.pos + 1) == 1   # wraps around to the skipped subject
    assert "reviewed 6, left 1 (1 skipped)" in s.status_lines()[0]
    assert s.status_lines(view3d="the stored mesh")[0].endswith("3D view: the stored mesh")


def test_undo_cancels_the_latest_verdict_and_says_where(session, tmp_path):
    s = session()
    assert s.undo() == (("warn", "nothing to undo"), None)
    s.verdict("bad", ("other",))
    s.verdict("skip")
    notice, where = s.undo()
    assert notice == ("undo", "undone: subj00000001 skip; its verdict is now none") and where == 1
    assert (s.done, s.skipped) == (1, 0)
    s.pos = 0
    s.verdict("good")                          # replaces bad: other
    notice, where = s.undo()
    assert notice[1] == "undone: subj00000000 good; its verdict is now bad: other" and where == 0
    assert written(tmp_path)[-1] == ("0", "undo", ())


def test_triage_changes_wait_on_their_page_until_committed(session, tmp_path):
    s = session()                              # pages of 3: subjects 0-2, 3-5, 6
    s.pos = 0
    s.verdict("bad", ("blur",))                # subject 0 saved bad
    s.point_at(0)
    s.set_pending(s.cursor_item(), ("good", ()))
    s.move_cursor(1)
    s.flip(1)                                  # subject 1: bad with its pre-flag's reason
    assert s.pending == {SUBJECTS[0]: ("good", ()), SUBJECTS[1]: ("bad", ("multiple_faces",))}
    s.flip(1)                                  # again: the change is taken back
    s.set_pending(s.page_items()[2], ("good", ()))   # good for a new cell is what a commit writes anyway
    assert s.pending == {SUBJECTS[0]: ("good", ())}
    assert s.turn_page(+1) and s.triage_page == 1 and not s.turn_page(+5)
    s.set_pending(s.page_items()[0], ("bad", ("artifacts",)))
    assert s.turn_page(-1) and written(tmp_path) == [("0", "bad", ("blur",))]   # nothing written by moving
    notice = s.commit_page()
    assert notice == ("saved", "committed page 1: 0 bad, 3 good written")
    assert (s.triage_page, s.triage_cursor) == (1, 0) and s.pending == {SUBJECTS[3]: ("bad", ("artifacts",))}
    assert written(tmp_path)[1:] == [("0", "good", ()), ("1", "good", ()), ("2", "good", ())]
    assert s.done == 3


def test_a_commit_keeps_saved_verdicts_and_skips(session, tmp_path):
    s = session(n=3)
    s.verdict("bad", ("blur",))
    s.verdict("skip")
    s.point_at(0)
    assert s.commit_page() == ("saved", "committed page 1: 0 bad, 1 good written, 1 kept their saved verdict, "
                                        "1 skipped left unreviewed (u finds them) (last page)")
    assert s.commit_page() == ("warn", "page 1: nothing to commit (every cell has its verdict and none was "
                                       "changed); nothing written")
    assert written(tmp_path) == [("0", "bad", ("blur",)), ("1", "skip", ()), ("2", "good", ())]
    assert "here: 2 reviewed, 1 skipped, 0 changed" in s.triage_lines(0.0)[0]


def test_a_session_resumes_from_its_log(session, tmp_path):
    s = session()
    for _ in range(3):
        s.verdict("good")
    s.pos = 4
    s.verdict("skip")
    s.close()
    again = session()
    assert (again.pos, again.done, again.skipped) == (3, 3, 1)
    log = tmp_path / "labels" / "alice.jsonl"
    assert again.resume_notice() == ("saved", f"resumed: 4 verdicts from {log} (3 of 7 in this queue reviewed)")
    bob = session(reviewer="bob")             # another reviewer's log is another session
    assert bob.pos == 0 and bob.resume_notice() == ("saved", f"new log {log.with_name('bob.jsonl')}: 0 of 7 reviewed")


def test_a_restart_after_a_cut_line_says_what_it_recovered(session, tmp_path):
    """A crash mid-write leaves a cut last line: the reopened session names it, once dropped, with
    the verdicts it resumes from; reopened again, the line (now closed) still reads as a cut write."""
    s = session()
    s.verdict("good")
    s.verdict("bad", ("blur",))
    s.close()
    log = tmp_path / "labels" / "alice.jsonl"
    with open(log, "ab") as f:
        f.write(b'{"action": "good", "reason')      # the write a crash cut short
    again = session()
    assert again.log.problems == [f"{log}:3: partial last line, dropped"]
    assert again.resume_notice() == ("warn", f"resumed: 2 verdicts from {log} (2 of 7 in this queue reviewed); "
                                             "line 3: partial last line, dropped")
    again.verdict("skip")
    again.close()
    third = session()
    assert third.log.problems == [f"{log}:3: partial line (a write cut short, closed by a later session), dropped"]
    assert (third.done, third.skipped, third.pos) == (2, 1, 2)


def test_log_problems_show_the_first_and_count_the_rest(session, tmp_path):
    log = tmp_path / "labels" / "alice.jsonl"
    log.parent.mkdir()
    good = '{{"seq": {}, "time": "t", "reviewer": "alice", "subject": "{}", "shard": "shard-000000", "action": "good"}}'
    log.write_text("\n".join([good.format(1, SUBJECTS[0]), good.format(1, SUBJECTS[1]),
                              good.format("null", SUBJECTS[2]), good.format(2, SUBJECTS[3])]) + "\n")
    kind, message = session().resume_notice()
    assert kind == "warn" and message == (f"resumed: 3 verdicts from {log} (3 of 7 in this queue reviewed); "
                                          "line 2: event number 1 repeats line 1; 1 more log problem (listed on "
                                          "the terminal)")


def test_next_unreviewed_says_when_none_is_left_and_stays(session):
    s = session(n=3)
    s.verdict("good")
    s.pos = 0
    assert s.next_unreviewed() is None and s.pos == 1
    s.verdict("good")
    assert s.pos == 2 and s.next_unreviewed() == ("warn", f"{SUBJECTS[2]} (shown) is the only unreviewed "
                                                          "subject left")
    s.verdict("bad", ("other",))
    s.pos = 1
    assert s.next_unreviewed() == ("warn", "all 3 subjects of this queue are reviewed: no unreviewed subject left")
    assert s.pos == 1


def test_verdict_keys_work_in_the_3d_view(tiny_dataset, tmp_path):
    """2 in the 3D view saves a broken back for the subject shown and brings the next subject's views."""
    pytest.importorskip("vtkmodules", reason="the review window needs VTK")
    from labeling_tool.cli import build_queue
    from labeling_tool.review import ReviewApp

    _, items = build_queue(str(tiny_dataset), "all")
    app = ReviewApp(tiny_dataset, items, "alice", tmp_path / "labels", off_screen=True, window_size=(480, 320))
    try:
        for key, subject in (("2", "0"), ("s", "1")):
            app.press("v")
            assert app.mode == "3d"
            app.press(key)
            assert app.mode == "review" and app.surface.actor is None and app.notice[0] == "saved"
        app.press("v")
        app.press("g")                         # the last subject: it stays in 3D and says so
        assert app.mode == "3d" and "last subject" in app.notice[1]
        assert written(tmp_path) == [("0", "bad", ("broken_back",)), ("1", "skip", ()), ("2", "good", ())]
    finally:
        app.close()
