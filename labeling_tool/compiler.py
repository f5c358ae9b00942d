"""Compiling curated manifests: all reviewers' verdicts merged under a stated policy, written once.

The manifest format itself (fields, splits, versions) is described in ``datagen.dataset.manifests``.
"""
from __future__ import annotations

import hashlib
import re
from datetime import datetime, timezone
from pathlib import Path

from datagen.errors import SettingError, UserError
from datagen.files import atomic_write
from datagen.dataset.manifests import FORMAT, manifest_bytes, read_manifest
from datagen.dataset.preflags import read_queue
from datagen.dataset import Dataset

from datagen.dataset.events import is_decision, read_logs, verdicts

POLICIES = ("any-bad", "majority")
UNREVIEWED = ("accept", "reject", "reject-flagged")


def subject_hash(subject: str) -> str:
    return hashlib.sha256(subject.encode()).hexdigest()


def merge(votes: dict[str, tuple[str, tuple]], policy: str, unreviewed: str, flagged: bool = False
          ) -> tuple[str, list[str]]:
    """Decide one subject from {reviewer: (good|bad, reasons)} -> (accepted|rejected, reasons).

    ``flagged``: the pre-flags flag this subject (used for unreviewed subjects under ``reject-flagged``).
    """
    bad = {r: v for r, v in votes.items() if v[0] == "bad"}
    reasons = sorted({x for _, rs in bad.values() for x in rs})
    if not votes:
        reject = unreviewed == "reject" or (unreviewed == "reject-flagged" and flagged)
        return ("rejected" if reject else "accepted"), []
    if policy == "any-bad":
        return ("rejected" if bad else "accepted"), reasons
    # majority: strictly more bad than good votes rejects; a tie rejects (when in doubt, leave it out)
    return ("rejected" if 2 * len(bad) >= len(votes) else "accepted"), reasons


def compile_manifest(dataset, labels_dir, policy: str = "any-bad", unreviewed: str = "accept",
                     test_count: int | None = None, parent=None, skip_unverified: bool = False) -> dict:
    """Build the manifest dict (not written) of ``dataset`` (a Dataset or its folder); see the module docstring.

    Every shard of the index is checked first (:func:`datagen.dataset.shards.check_shards`: sidecar, size,
    sha256, subjects and byte ranges; cached): one it cannot vouch for is a UserError naming it, or
    with ``skip_unverified`` its subjects are rejected with the reason ``unverified_shard``.
    """
    if test_count is not None and test_count < 0:
        raise SettingError(f"{{test_count}} must be 0 or more, not {test_count}")
    if policy not in POLICIES:
        raise SettingError(f"{{policy}} {policy!r}: choose one of: {', '.join(POLICIES)}")
    if unreviewed not in UNREVIEWED:
        raise SettingError(f"{{unreviewed}} must be one of: {', '.join(UNREVIEWED)}")
    dataset = Dataset.of(dataset)
    index = dataset.index
    unverified = shard_problems(dataset)
    if unverified and not skip_unverified:
        first = next(iter(unverified.values()))
        raise UserError(f"{first}" + (f" (and {len(unverified) - 1} more shard(s))" if len(unverified) > 1 else "")
                        + "; its subjects cannot be vouched for (pass --skip-incomplete to reject them)")
    logs, problems = read_logs(labels_dir)
    flagged = flagged_subjects(dataset, required=unreviewed == "reject-flagged")
    # a skip is "decide later": the subject counts as unreviewed, as in the review window
    votes_of: dict[str, dict] = {}  # subject -> {reviewer: (good|bad, reasons)}, reviewers in sorted order
    for r in sorted(logs):
        for s, e in verdicts(logs[r]).items():
            if is_decision(e):
                if s in votes_of:
                    votes_of[s][r] = (e.action, e.reasons)
                else:
                    votes_of[s] = {r: (e.action, e.reasons)}
    known = {s for shard in index["shards"] for s in shard["subjects"]}
    strangers = sorted(votes_of.keys() - known)
    if strangers:
        problems.append(f"{len(strangers)} reviewed subject(s) are not in this dataset (e.g. {strangers[0]})")
    rows, conflicts, nobody = [], [], {}
    for shard in index["shards"]:
        for s in shard["subjects"]:
            votes = votes_of.get(s, nobody)
            verdict, reasons = merge(votes, policy, unreviewed, flagged is not None and s in flagged)
            if shard["name"] in unverified:
                verdict, reasons = "rejected", ["unverified_shard"]
            actions = {r: v[0] for r, v in votes.items()}
            if len(set(actions.values())) > 1:
                conflicts.append(s)
            rows.append({"subject": s, "shard": shard["name"], "verdict": verdict, "reasons": reasons,
                         "reviewers": list(votes), "votes": actions, "split": None})
    accepted = [r for r in rows if r["verdict"] == "accepted"]
    if test_count is None:
        test_count = min(100, max(1, len(accepted) // 10)) if accepted else 0

    test = {r["subject"] for r in sorted(accepted, key=lambda r: subject_hash(r["subject"]))[:test_count]}
    for r in accepted:
        r["split"] = "test" if r["subject"] in test else "train"
    unreviewed_rows = [r for r in rows if not r["reviewers"]]
    unreviewed_flagged = None if flagged is None else [r for r in unreviewed_rows if r["subject"] in flagged]
    parent_version = None
    if parent:
        parent_manifest = read_manifest(parent)
        parent_version = parent_manifest["header"]["version"]
    counts = {
        "subjects": len(rows),
        "accepted": len(accepted),
        "rejected": len(rows) - len(accepted),
        "reviewed": sum(1 for r in rows if r["reviewers"]),
        "train": sum(1 for r in accepted if r["split"] == "train"),
        "test": len(test),
        "conflicts": len(conflicts),
        "unverified_shards": sorted(unverified),
        "unreviewed": len(unreviewed_rows),
        "unreviewed_flagged": None if flagged is None else len(unreviewed_flagged),
        "unreviewed_flagged_accepted": None if flagged is None else
        sum(1 for r in unreviewed_flagged if r["verdict"] == "accepted"),
    }
    header = {
        "format": FORMAT,
        "parent_version": parent_version,
        "policy": policy,
        "unreviewed": unreviewed,
        "test_count": test_count,
        "counts": counts,
        "conflicts": conflicts,
        "reviewers": sorted(logs),
        "dataset": str(dataset.root.resolve().name),
        "dataset_index_sha256": dataset.index_sha256,
        "log_problems": problems,
    }
    return {"header": header, "subjects": rows}


def shard_problems(dataset: Dataset) -> dict[str, str]:
    """{shard name: its first problem} for the index's shards that fail :func:`datagen.dataset.shards.check_shards`."""
    problems = dataset.check_shards()
    return {sh["name"]: problems[n] for n, sh in zip(dataset.shard_numbers, dataset.shards) if n in problems}


def flagged_subjects(dataset: Dataset, required: bool) -> set[str] | None:
    """Subjects the dataset's pre-flags (``label-tool auto``) flag; None when there are none or they are
    stale (made for another index.json), or a UserError when ``required``."""
    queue = read_queue(dataset.root)
    if queue is None:
        if required:
            raise SettingError(f"{{unreviewed}} reject-flagged needs pre-flags: {dataset.root} has none (run "
                               f"'label-tool auto {dataset.root}' first)")
        return None
    made_for, rows = queue
    if made_for != dataset.index_sha256:
        if required:
            raise SettingError(f"{{unreviewed}} reject-flagged: the pre-flags of {dataset.root} were made for another "
                               f"index.json; run 'label-tool auto {dataset.root}' again")
        return None
    return {row[0] for row in rows if row[3]}


VERSION_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


def write_manifest(manifest: dict, out) -> Path:
    """Publish a manifest under ``out`` (its stem is the version); an existing file is never replaced."""
    out = Path(out)
    if out.suffix != ".json":
        raise UserError(f"{out}: manifests are JSON files; name it <name>-v<N>.json")
    if not VERSION_NAME.match(out.stem):
        raise UserError(f"{out}: the version (file name) may use letters, digits, '.', '_' and '-'")
    if out.exists():
        raise UserError(f"{out} already exists; published manifests are never edited, write a new version")
    header = dict(manifest["header"], version=out.stem,
                  created=datetime.now(timezone.utc).isoformat(timespec="seconds"))
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(out, manifest_bytes(header, manifest["subjects"]))
    except OSError as e:
        raise UserError(f"cannot write {out}: {e.strerror}") from None
    return out


def next_version_path(manifests_dir, dataset) -> Path:
    """manifests/<dataset>-v<N+1>.json after the highest existing version of that dataset."""
    name = Path(dataset).resolve().name
    found = [int(m.group(1)) for p in Path(manifests_dir).glob(f"{name}-v*.json")
             if (m := re.fullmatch(rf"{re.escape(name)}-v(\d+)", p.stem))]
    return Path(manifests_dir) / f"{name}-v{max(found, default=0) + 1}.json"


def review_stats(dataset, labels_dir) -> dict:
    """Counts per reason and per reviewer, and agreement between each pair of reviewers."""
    Dataset.of(dataset)  # a dataset folder, or a DatasetError naming what is wrong
    logs, problems = read_logs(labels_dir)
    per = {r: {s: e for s, e in verdicts(ev).items() if is_decision(e)} for r, ev in logs.items()}
    reasons: dict[str, int] = {}
    reviewers = {}
    for r, v in per.items():
        bad = [e for e in v.values() if e.action == "bad"]
        for e in bad:
            for x in e.reasons:
                reasons[x] = reasons.get(x, 0) + 1
        reviewers[r] = {"reviewed": len(v), "good": len(v) - len(bad), "bad": len(bad),
                        "events": len(logs[r]), "undos": sum(1 for e in logs[r] if e.action == "undo")}
    agreement = []
    names = sorted(per)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            both = sorted(set(per[a]) & set(per[b]))
            if not both:
                continue
            xa = [per[a][s].action == "bad" for s in both]
            xb = [per[b][s].action == "bad" for s in both]
            agree = sum(p == q for p, q in zip(xa, xb)) / len(both)
            pa, pb = sum(xa) / len(both), sum(xb) / len(both)
            chance = pa * pb + (1 - pa) * (1 - pb)
            kappa = (agree - chance) / (1 - chance) if chance < 1 else 1.0
            agreement.append({"reviewers": [a, b], "subjects": len(both), "agreement": round(agree, 4),
                              "cohen_kappa": round(kappa, 4)})
    return {"reasons": dict(sorted(reasons.items())), "reviewers": reviewers, "agreement": agreement,
            "log_problems": problems}
