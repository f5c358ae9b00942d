"""The ``label-tool`` command line: auto, review, compile, stats."""
from __future__ import annotations

import argparse
import json
import signal
import sys
from dataclasses import dataclass
from pathlib import Path

from datagen.command_line import OneLineParser, add_options, at_least, given, run_command, setting, unit_interval
from datagen.errors import SettingError, UserError, optional_import
from datagen.threads import add_option as add_threads_option
from datagen.dataset import Dataset
from datagen.runner import RunOptions

from .compiler import UNREVIEWED


def window_size(text: str) -> tuple[int, int]:
    """'1920x1080' -> (1920, 1080)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not WIDTHxHEIGHT, e.g. 1920x1080") from None
    if not (320 <= w <= 16384 and 240 <= h <= 16384):
        raise argparse.ArgumentTypeError(f"{text!r}: width 320..16384 and height 240..16384 pixels")
    return w, h


@dataclass(frozen=True)
class AutoOptions(RunOptions):
    """The options of ``label-tool auto``; which go together is checked by :meth:`check`."""

    learn: str | None = setting(None, "re-rank the unreviewed subjects with a classifier fitted on the verdicts in "
                                      "this folder of event logs (after about 20 or more verdicts with both good and "
                                      "bad ones)", metavar="LABELS")
    skip_incomplete: bool = setting(False, "score the complete shards and list the others (default: a missing, "
                                           "incomplete or damaged shard is an error)")
    false_alarm_rate: float | None = setting(None, "share of clean subjects the detectors together may flag, 0 <= R "
                                                   "< 1 (default 0.03); the union is calibrated to it on this dataset. "
                                                   "0: every detector at its own threshold, uncalibrated",
                                             parse=unit_interval, metavar="R")
    top: int = setting(10, "print the N worst subjects", parse=at_least(0), metavar="N")
    quiet: bool = setting(False, "no progress bar")
    shard_index: int | None = setting(None, "array jobs: measure only the shards s with s %% N == K and write their "
                                            "records to a slice file (score them all with --merge once every slice "
                                            "is done)", parse=at_least(0), metavar="K")
    num_shards: int | None = setting(None, "array jobs: how many slices (with --shard-index)", parse=at_least(1),
                                     metavar="N")
    merge: bool = setting(False, "score the whole dataset from the slice files of --shard-index/--num-shards jobs")
    out: str | None = setting(None, "folder of the slice files (default: DATASET/preflags-slices)", metavar="DIR")

    @property
    def sliced(self) -> bool:
        return self.shard_index is not None or self.num_shards is not None

    def check(self) -> None:
        """A SettingError for options that do not go together."""
        if self.sliced and (self.shard_index is None or self.num_shards is None):
            raise SettingError("{shard_index} and {num_shards} go together")
        if (self.sliced or self.merge) and self.backend == "ray":
            raise SettingError("{backend} ray measures and scores in one run; {shard_index} and {merge} are for "
                               "array jobs")
        for name in ("merge", "learn", "false_alarm_rate"):
            if self.sliced and getattr(self, name) not in (None, False):
                raise SettingError(f"{{shard_index}} measures one slice; {{{name}}} goes with the {{merge}} run "
                                   "after every slice" if name != "merge" else
                                   "{shard_index} measures one slice; {merge} goes with the run after every slice")
        if self.out is not None and not (self.sliced or self.merge):
            raise SettingError("{out} is the folder of slice files: only with {shard_index} or {merge}")
        self.placement()  # backend and address


def build_parser() -> OneLineParser:
    p = OneLineParser(prog="label-tool", description="Curate a generated head dataset.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=OneLineParser)

    a = sub.add_parser("auto", help="score every subject with automatic pre-flags (worst first)")
    a.add_argument("dataset", help="dataset folder (datagen sample --out)")
    add_options(a, AutoOptions)
    add_threads_option(a)

    r = sub.add_parser("review", help="open the review window")
    r.add_argument("target", help="a dataset folder, or one shard-XXXXXX.tar in it")
    r.add_argument("--reviewer", required=True, help="your name; your verdicts go to its own event log")
    r.add_argument("--labels", default="labels", help="folder of reviewers' event logs (default: ./labels)")
    r.add_argument("--queue", default="all", choices=("all", "worst", "suspicious"),
                   help="all (dataset order), worst (by pre-flag score), suspicious (flagged only)")
    r.add_argument("--triage", action="store_true", help="start in triage mode (many subjects per screen)")
    r.add_argument("--columns", type=int, default=8, help="views per row in review mode")
    r.add_argument("--window-size", type=window_size, metavar="WxH",
                   help="window size in pixels (default: fit the screen; 1600x900 off-screen)")
    r.add_argument("--off-screen", action="store_true", help="no window (scripted use)")
    r.add_argument("--keys", default="", help="off-screen: keys to press, space separated, then exit")
    r.add_argument("--screenshot", help="off-screen: save a screenshot after the keys")

    c = sub.add_parser("compile", help="merge reviewers' logs into a new, versioned manifest")
    c.add_argument("dataset", help="dataset folder (datagen sample --out)")
    c.add_argument("--labels", default="labels", help="folder of reviewers' event logs (default: ./labels)")
    c.add_argument("--out", help="manifest file (default: manifests/<dataset>-v<N+1>.json)")
    c.add_argument("--policy", default="any-bad", choices=("any-bad", "majority"),
                   help="a subject several reviewers judged: rejected if any says bad (default) or most do")
    c.add_argument("--unreviewed", default="accept", choices=UNREVIEWED,
                   help="subjects nobody reviewed: accept, reject, or reject-flagged (reject those the "
                        "pre-flags of 'label-tool auto' flag)")
    c.add_argument("--test-count", type=int, default=None,
                   help="held-out test subjects (default: min(100, accepted/10); the paper holds out 100)")
    c.add_argument("--parent", help="the manifest this version revises")
    c.add_argument("--skip-incomplete", action="store_true",
                   help="reject the subjects of shards that fail the sidecar/size/sha256 check (default: an error "
                        "naming them)")

    s = sub.add_parser("stats", help="counts per reason and reviewer, agreement between reviewers")
    s.add_argument("dataset", help="dataset folder (datagen sample --out)")
    s.add_argument("--labels", default="labels", help="folder of reviewers' event logs (default: ./labels)")
    s.add_argument("--json", action="store_true", help="print JSON")
    return p


def build_queue(target: str, queue: str):
    """The review queue for a dataset or one of its shards, in dataset order or by pre-flag score."""
    from .review import QueueItem

    path = Path(target)
    shard_only = None
    if path.suffix == ".tar":
        shard_only, path = path.stem, path.parent
    dataset = Dataset(path)
    shards = [sh for sh in dataset.shards if shard_only is None or sh["name"] == shard_only]
    if shard_only is not None and not shards:
        raise UserError(f"{target}: not a shard of the dataset in {path}")
    from datagen.dataset.preflags import read_queue

    preflags = read_queue(path)
    stale = preflags is not None and preflags[0] != dataset.index_sha256
    if preflags is None or stale:
        why = "were made for another index.json: run 'label-tool auto {0}' again" if stale else \
            "are missing: run 'label-tool auto {0}' first"
        if queue != "all":
            raise UserError(f"--queue {queue} needs pre-flags; those of {path} " + why.format(path))
        if stale:
            print(f"note: pre-flags not shown; those of {path} " + why.format(path))
        return path, [QueueItem(s, sh["name"]) for sh in shards for s in sh["subjects"]]
    scores = {r[0]: r for r in preflags[1]}
    items = []
    for sh in shards:
        for s in sh["subjects"]:
            r = scores.get(s)
            items.append(QueueItem(s, sh["name"]) if r is None else QueueItem(s, sh["name"], r[1], r[3]))
    if queue in ("worst", "suspicious"):
        items.sort(key=lambda it: -scores[it.subject][2] if it.subject in scores else 0.0)
    if queue == "suspicious":
        items = [it for it in items if it.flags]
    return path, items


def _auto(args) -> int:
    from datagen.dataset.preflags import write_preflags

    optional_import("cv2", "faces")
    from .preflags import FALSE_ALARM_RATE, FLAG_AT, score_dataset

    opts = AutoOptions(**given(args, AutoOptions))
    opts.check()
    rate = FALSE_ALARM_RATE if opts.false_alarm_rate is None else opts.false_alarm_rate
    if not opts.merge:
        from datagen.faces import check_dlib
        check_dlib()
    placement = opts.placement(args.threads)
    if opts.sliced:
        from .preflags.slices import measure_slice

        path, extracted = measure_slice(args.dataset, opts.shard_index, opts.num_shards, opts.out, placement,
                                        not opts.quiet, skip_incomplete=opts.skip_incomplete)
        skipped = extracted["skipped_shards"]
        print(f"measured {len(extracted['records'])} subjects of slice {opts.shard_index} of {opts.num_shards} -> "
              f"{path}" + (f"; SKIPPED {len(skipped)} incomplete shard(s): {', '.join(skipped[:5])}"
                           if skipped else ""))
        print(f"once every slice is measured: label-tool auto {args.dataset} --merge"
              + (f" --out {opts.out}" if opts.out else ""))
        return 0
    if opts.merge:
        from .preflags.slices import merge_slices

        report = merge_slices(args.dataset, opts.out, labels=opts.learn, false_alarm_rate=rate)
    else:
        report = score_dataset(args.dataset, progress=not opts.quiet, placement=placement,
                               skip_incomplete=opts.skip_incomplete, labels=opts.learn, false_alarm_rate=rate)
    path = write_preflags(args.dataset, report)
    flagged = [r for r in report["subjects"] if r["flags"]]
    skipped = report["summary"]["skipped_shards"]
    learned = report.get("learned")
    if learned:
        cv = learned.get("cross_validated_auc")
        print(f"learned from {learned['verdicts']} verdicts ({learned['bad']} bad): " +
              (f"unreviewed subjects re-ranked (cross-validated AUC {cv:.2f})" if learned["used"] and cv is not None
               else "unreviewed subjects re-ranked" if learned["used"] else learned["why"]))
    calibrated = (f"calibrated to flag at most {rate:.1%} of clean subjects" if rate
                  else "each detector at its own threshold, uncalibrated")
    print(f"scored {len(report['subjects'])} subjects, {len(flagged)} flagged ({calibrated}) -> {path}"
          + (f"; SKIPPED {len(skipped)} incomplete shard(s): {', '.join(skipped[:5])}" if skipped else ""))
    shown = report["subjects"][: opts.top]
    if shown:
        print(f"worst first; score = the subject's highest pre-flag score, 0 to 1 (flagged from {FLAG_AT:.2f}):")
    for r in shown:
        why = "; ".join(r["detectors"][k]["why"] for k in r["flags"]) or "no flag"
        print(f"  {r['score']:.2f}  {r['subject']}  {why}")
    if shown:
        more = len(report["subjects"]) - len(shown)
        print(f"{len(shown):,} of {len(report['subjects']):,} shown" +
              (f" (--top N shows more; every score is in {path})" if more else ""))
    return 0


def _review(args) -> int:
    optional_import("pyvista", "review")
    from .review import ReviewApp

    root, items = build_queue(args.target, args.queue)
    if args.columns < 1:
        raise UserError("--columns must be at least 1")
    app = ReviewApp(root, items, args.reviewer, args.labels, off_screen=args.off_screen, columns=args.columns,
                    start_in_triage=args.triage, window_size=args.window_size)
    for problem in app.log.problems:
        print(f"note: {problem}", file=sys.stderr)
    if args.off_screen:
        for key in args.keys.split():
            if app.closed:  # Escape closed it
                break
            app.press(key)
        if args.screenshot and not app.closed:
            app.screenshot(args.screenshot)
        app.close()
    else:
        # The window's event loop runs no Python until its next event, so a handler would hold SIGTERM back
        # until then: the window ends at once, as it always did (every verdict is saved as it is given).
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        app.run()
    print(f"{args.reviewer}: {app.done}/{len(items)} reviewed; log {app.log.path}")
    if app.pending:
        print(f"{len(app.pending)} triage change(s) were not committed (nothing was written for them)")
    if app.log.failed_writes:
        raise UserError(f"{app.log.failed_writes} write(s) to the review log {app.log.path} failed (a full disk, "
                        "or its lock taken over by another window; each said which); "
                        "the verdicts saved before each are kept, those not saved must be given again")
    return 0


def _compile(args) -> int:
    from .compiler import compile_manifest, next_version_path, write_manifest

    manifest = compile_manifest(args.dataset, args.labels, args.policy, args.unreviewed, args.test_count, args.parent,
                                skip_unverified=args.skip_incomplete)
    out = Path(args.out) if args.out else next_version_path("manifests", args.dataset)
    write_manifest(manifest, out)
    h = manifest["header"]
    for problem in h["log_problems"]:
        print(f"problem: {problem}", file=sys.stderr)
    c = h["counts"]
    print(f"wrote {out}: {c['accepted']} accepted ({c['train']} train, {c['test']} test), {c['rejected']} rejected, "
          f"{c['reviewed']}/{c['subjects']} reviewed, {c['conflicts']} conflicts (policy {h['policy']}, "
          f"unreviewed {h['unreviewed']})")
    if c["unreviewed_flagged"] is None and c["unreviewed"] and h["unreviewed"] == "accept":
        print(f"note: {c['unreviewed']} subject(s) accepted without review; no current pre-flags to tell which are "
              f"suspicious (run 'label-tool auto {args.dataset}')")
    elif c["unreviewed_flagged_accepted"]:
        print(f"warning: {c['unreviewed_flagged_accepted']} flagged subject(s) accepted without review; review them "
              "(label-tool review --queue suspicious) or compile with --unreviewed reject-flagged")
    if c["unverified_shards"]:
        print(f"warning: the subjects of {len(c['unverified_shards'])} unverified shard(s) were rejected: "
              f"{', '.join(c['unverified_shards'][:5])}")
    for s in h["conflicts"][:20]:
        print(f"  conflict: {s}")
    return 0


def _stats(args) -> int:
    from .compiler import review_stats

    st = review_stats(args.dataset, args.labels)
    if args.json:
        print(json.dumps(st, indent=1, sort_keys=True))
        return 0
    for problem in st["log_problems"]:
        print(f"problem: {problem}")
    if not any(v["reviewed"] for v in st["reviewers"].values()):
        print(f"no verdicts in {args.labels} yet; review with: label-tool review {args.dataset} --reviewer NAME "
              f"--labels {args.labels}")
        return 0
    print("per reviewer:")
    for r, v in st["reviewers"].items():
        print(f"  {r}: {v['reviewed']} reviewed ({v['good']} good, {v['bad']} bad), {v['events']} events, "
              f"{v['undos']} undos")
    print("bad verdicts per reason:")
    for k, n in st["reasons"].items():
        print(f"  {k}: {n}")
    print("agreement:")
    if not st["agreement"]:
        print("  none measurable: no subject was reviewed by two reviewers")
    for a in st["agreement"]:
        print(f"  {' vs '.join(a['reviewers'])}: {a['subjects']} shared subjects, agreement {a['agreement']:.2f}, "
              f"Cohen's kappa {a['cohen_kappa']:.2f}")
    return 0


COMMANDS = {"auto": _auto, "review": _review, "compile": _compile, "stats": _stats}


def main(argv=None) -> int:
    parser = build_parser()
    return run_command("label-tool", COMMANDS, parser.parse_args(argv), "every verdict so far is saved", parser)


if __name__ == "__main__":
    sys.exit(main())
