"""The ``label-tool`` command line: auto, review, compile, stats."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from datagen.errors import OneLineParser, UserError, optional_import, run_command
from datagen.threads import add_option as add_threads_option
from datagen.shards import read_index

from .manifest import UNREVIEWED


def window_size(text: str) -> tuple[int, int]:
    """'1920x1080' -> (1920, 1080)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not WIDTHxHEIGHT, e.g. 1920x1080") from None
    if not (320 <= w <= 16384 and 240 <= h <= 16384):
        raise argparse.ArgumentTypeError(f"{text!r}: width 320..16384 and height 240..16384 pixels")
    return w, h


def build_parser() -> OneLineParser:
    p = OneLineParser(prog="label-tool", description="Curate a generated head dataset.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=OneLineParser)

    a = sub.add_parser("auto", help="score every subject with automatic pre-flags (worst first)")
    a.add_argument("dataset", help="dataset folder (datagen sample --out)")
    a.add_argument("--workers", type=int, default=1, help="processes that read and measure subjects")
    add_threads_option(a)
    a.add_argument("--learn", metavar="LABELS",
                   help="re-rank the unreviewed subjects with a classifier fitted on the verdicts in this folder of "
                        "event logs (after about 20 or more verdicts with both good and bad ones)")
    a.add_argument("--skip-incomplete", action="store_true",
                   help="score the complete shards and list the others (default: a missing, incomplete or "
                        "damaged shard is an error)")
    a.add_argument("--false-alarm-rate", type=float, metavar="R",
                   help="share of clean subjects the detectors together may flag, 0 <= R < 1 (default 0.03); the "
                        "union is calibrated to it on this dataset. 0: every detector at its own threshold, "
                        "uncalibrated")
    a.add_argument("--top", type=int, default=10, metavar="N", help="print the N worst subjects")
    a.add_argument("--quiet", action="store_true", help="no progress bar")
    a.add_argument("--shard-index", type=int, metavar="K",
                   help="array jobs: measure only the shards s with s %% N == K and write their records to a "
                        "slice file (score them all with --merge once every slice is done)")
    a.add_argument("--num-shards", type=int, metavar="N", help="array jobs: how many slices (with --shard-index)")
    a.add_argument("--merge", action="store_true",
                   help="score the whole dataset from the slice files of --shard-index/--num-shards jobs")
    a.add_argument("--out", metavar="DIR", help="folder of the slice files (default: DATASET/preflags-slices)")
    a.add_argument("--backend", default="local", choices=("local", "ray"),
                   help="local processes (--workers), or one task per shard on a Ray cluster (this process scores)")
    a.add_argument("--ray-address", metavar="ADDR",
                   help="Ray cluster to use (default: RAY_ADDRESS, else a local Ray instance)")

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
    index = read_index(path)
    items = [QueueItem(s, sh["name"]) for sh in index["shards"] for s in sh["subjects"]
             if shard_only is None or sh["name"] == shard_only]
    if shard_only is not None and not items:
        raise UserError(f"{target}: not a shard of the dataset in {path}")
    from datagen.preflags import PREFLAGS_NAME, read_preflags

    report = read_preflags(path) if (path / PREFLAGS_NAME).exists() else None
    if report is None:
        if queue != "all":
            raise UserError(f"--queue {queue} needs pre-flags: run 'label-tool auto {path}' first")
        return path, items
    scores = {r["subject"]: r for r in report["subjects"]}
    for it in items:
        r = scores.get(it.subject)
        if r:
            it.score = r["score"]
            it.flags = tuple(sorted(((k, r["detectors"][k]["score"]) for k in r["flags"]), key=lambda f: -f[1]))
    if queue in ("worst", "suspicious"):
        rank = {r["subject"]: r.get("rank", r["score"]) for r in report["subjects"]}
        items.sort(key=lambda it: -rank.get(it.subject, 0.0))
    if queue == "suspicious":
        items = [it for it in items if it.flags]
    return path, items


def _auto(args) -> int:
    from datagen.preflags import write_preflags

    optional_import("cv2", "faces")
    from .preflags import FALSE_ALARM_RATE, FLAG_AT, score_dataset

    rate = FALSE_ALARM_RATE if args.false_alarm_rate is None else args.false_alarm_rate
    if not 0 <= rate < 1:
        raise UserError(f"--false-alarm-rate must be at least 0 and below 1, not {args.false_alarm_rate:g}")
    if args.workers < 1:
        raise UserError("--workers must be at least 1")
    if args.top < 0:
        raise UserError("--top must be at least 0")
    sliced = args.shard_index is not None or args.num_shards is not None
    if sliced and (args.shard_index is None or args.num_shards is None):
        raise UserError("--shard-index and --num-shards go together")
    if (sliced or args.merge) and args.backend == "ray":
        raise UserError("--backend ray measures and scores in one run; --shard-index and --merge are for array jobs")
    if sliced and (args.merge or args.learn or args.false_alarm_rate is not None):
        given = "--merge" if args.merge else "--learn" if args.learn else "--false-alarm-rate"
        raise UserError(f"--shard-index measures one slice; {given} goes with the --merge run after every slice")
    if args.out is not None and not (sliced or args.merge):
        raise UserError("--out is the folder of slice files: only with --shard-index or --merge")
    if args.ray_address is not None and args.backend != "ray":
        raise UserError("--ray-address: only with --backend ray")
    if not args.merge:
        from datagen.faces import check_dlib
        check_dlib()
    if sliced:
        from .preflags.slices import measure_slice

        path, extracted = measure_slice(args.dataset, args.shard_index, args.num_shards, args.out, args.workers,
                                        not args.quiet, skip_incomplete=args.skip_incomplete, threads=args.threads)
        skipped = extracted["skipped_shards"]
        print(f"measured {len(extracted['records'])} subjects of slice {args.shard_index} of {args.num_shards} -> "
              f"{path}" + (f"; SKIPPED {len(skipped)} incomplete shard(s): {', '.join(skipped[:5])}"
                           if skipped else ""))
        print(f"once every slice is measured: label-tool auto {args.dataset} --merge"
              + (f" --out {args.out}" if args.out else ""))
        return 0
    if args.merge:
        from .preflags.slices import merge_slices

        report = merge_slices(args.dataset, args.out, labels=args.learn, false_alarm_rate=rate)
    elif args.backend == "ray":
        from .preflags.cluster import score_on_ray

        report = score_on_ray(args.dataset, args.ray_address, progress=not args.quiet,
                              skip_incomplete=args.skip_incomplete, labels=args.learn, false_alarm_rate=rate)
    else:
        report = score_dataset(args.dataset, progress=not args.quiet, workers=args.workers,
                               skip_incomplete=args.skip_incomplete, labels=args.learn, false_alarm_rate=rate,
                               threads=args.threads)
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
    shown = report["subjects"][: args.top]
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
    from .manifest import compile_manifest, next_version_path, write_manifest

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
    from .manifest import review_stats

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
    return run_command("label-tool", COMMANDS, build_parser().parse_args(argv), "every verdict so far is saved")


if __name__ == "__main__":
    sys.exit(main())
