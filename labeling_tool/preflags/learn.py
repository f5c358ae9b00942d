"""Learning from reviewers: re-rank the unreviewed queue with what the verdicts so far say.

Once reviewers have given some verdicts, a small L2-regularised logistic regression is fitted on the
reviewed subjects: inputs are the pre-flag score, every detector's score and measured value
(compressed as sign * log(1 + |value|), so that a few huge z-scores do not set the scale; standardised;
a missing value as 0 with its own indicator) and the leading principal components of the frontal
thumbnails (the duplicate detector's), target "bad" (any reviewer's bad verdict). The thumbnail
components are kept only when they raise the cross-validated AUC on the reviewed subjects (with a
few hundred verdicts they mostly fit the people, not the defects). Its probability becomes the
``rank`` of each unreviewed subject, so the queue puts first what the reviewers would reject;
reviewed subjects keep their pre-flag score as rank. The fit is deterministic (Newton's method);
its cross-validated AUC on the reviewed subjects is recorded in the report.
"""
from __future__ import annotations

import numpy as np

from datagen.errors import UserError
from datagen.dataset.events import read_logs, verdicts

MIN_VERDICTS = 20         # fewer verdicts (or no bad ones, or no good ones) and nothing is learned
THUMB_COMPONENTS = 8
RIDGE = 3.0               # L2 penalty on the (standardised) weights
FOLDS = 5


def reviewed_labels(labels_dir) -> dict[str, int]:
    """{subject: 1 if any reviewer's current verdict is bad, 0 if good}; skips are not verdicts."""
    logs, _ = read_logs(labels_dir)
    out: dict[str, int] = {}
    for events in logs.values():
        for subject, e in verdicts(events).items():
            if e.action in ("good", "bad"):
                out[subject] = max(out.get(subject, 0), int(e.action == "bad"))
    return out


def feature_matrix(report: dict, thumbs: list | None = None) -> tuple[np.ndarray, list[str]]:
    """(rows in report order, column names): pre-flag score, detector scores and values, thumbnail
    components."""
    names = list(report["detectors"])
    cols = [np.array([s["score"] for s in report["subjects"]], dtype=np.float64)]
    columns = ["preflags.score"]
    for name in names:
        score = np.array([s["detectors"][name]["score"] for s in report["subjects"]], dtype=np.float64)
        value = np.array([s["detectors"][name].get("value", np.nan) for s in report["subjects"]], dtype=np.float64)
        value = np.where(np.isfinite(value), value, np.nan)
        squashed = np.nan_to_num(np.sign(value) * np.log1p(np.abs(value)), nan=0.0)
        cols += [score, squashed, np.isfinite(value).astype(float)]
        columns += [f"{name}.score", f"{name}.value", f"{name}.has_value"]
    if thumbs is not None and sum(t is not None for t in thumbs) > THUMB_COMPONENTS:
        have = np.array([t is not None for t in thumbs])
        x = np.stack([t for t in thumbs if t is not None]).astype(np.float64)
        x -= x.mean(0)
        _, _, vt = np.linalg.svd(x, full_matrices=False)
        comp = np.zeros((len(thumbs), THUMB_COMPONENTS))
        comp[have] = x @ vt[:THUMB_COMPONENTS].T
        cols += list(comp.T)
        columns += [f"thumb.pc{i}" for i in range(THUMB_COMPONENTS)]
    return np.stack(cols, 1), columns


def fit_logistic(x: np.ndarray, y: np.ndarray, ridge: float = RIDGE, steps: int = 50):
    """(weights, bias, mean, scale) of an L2-regularised logistic regression, by Newton's method."""
    mean, scale = x.mean(0), x.std(0)
    scale = np.where(scale > 1e-12, scale, 1.0)
    z = np.column_stack([(x - mean) / scale, np.ones(len(x))])
    w = np.zeros(z.shape[1])
    penalty = np.full(z.shape[1], ridge)
    penalty[-1] = 0.0
    for _ in range(steps):
        p = 1.0 / (1.0 + np.exp(-np.clip(z @ w, -30, 30)))
        grad = z.T @ (p - y) + penalty * w
        hess = (z * (p * (1 - p))[:, None]).T @ z + np.diag(penalty + 1e-9)
        step = np.linalg.solve(hess, grad)
        w -= step
        if np.abs(step).max() < 1e-8:
            break
    return w[:-1], w[-1], mean, scale


def predict(model, x: np.ndarray) -> np.ndarray:
    w, b, mean, scale = model
    return 1.0 / (1.0 + np.exp(-np.clip(((x - mean) / scale) @ w + b, -30, 30)))


def auc(y: np.ndarray, p: np.ndarray) -> float | None:
    """Area under the ROC curve (ties count half); None without both classes."""
    pos, neg = p[y == 1], p[y == 0]
    if not len(pos) or not len(neg):
        return None
    return float(((pos[:, None] > neg[None]).sum() + 0.5 * (pos[:, None] == neg[None]).sum()) / (len(pos) * len(neg)))


def cross_validated_auc(x: np.ndarray, y: np.ndarray) -> float | None:
    folds = np.arange(len(y)) % FOLDS
    p = np.zeros(len(y))
    for k in range(FOLDS):
        train = folds != k
        if len(set(y[train])) < 2:
            return None
        p[~train] = predict(fit_logistic(x[train], y[train]), x[~train])
    return auc(y, p)


def learn_ranking(report: dict, labels: dict[str, int], thumbs: list | None = None) -> dict:
    """The report with each unreviewed subject's ``rank`` = the learned probability of "bad", reviewed
    subjects' ``rank`` = their score, and a ``learned`` summary; unchanged ranks when too little is known."""
    subjects = report["subjects"]
    reviewed = np.array([s["subject"] in labels for s in subjects])
    y_all = np.array([labels.get(s["subject"], 0) for s in subjects], dtype=np.float64)
    y = y_all[reviewed]
    for s in subjects:
        s["rank"] = s["score"]
    summary = {"verdicts": int(reviewed.sum()), "bad": int(y.sum())}
    if reviewed.sum() < MIN_VERDICTS or y.min(initial=1) == y.max(initial=0):
        report["learned"] = dict(summary, used=False,
                                 why=f"needs at least {MIN_VERDICTS} verdicts with both good and bad ones")
        return report
    x, columns = feature_matrix(report, thumbs)
    cv = cross_validated_auc(x[reviewed], y)
    if any(c.startswith("thumb.") for c in columns):
        plain = [i for i, c in enumerate(columns) if not c.startswith("thumb.")]
        cv_plain = cross_validated_auc(x[reviewed][:, plain], y)
        if cv is None or (cv_plain is not None and cv_plain >= cv):
            x, columns, cv = x[:, plain], [columns[i] for i in plain], cv_plain
    model = fit_logistic(x[reviewed], y)
    p = predict(model, x)
    for s, prob, seen in zip(subjects, p, reviewed):
        if not seen:
            s["rank"] = round(float(prob), 4)
    top = np.argsort(-np.abs(model[0]))[:5]
    report["learned"] = dict(summary, used=True, features=columns, cross_validated_auc=cv,
                             strongest=[{"feature": columns[i], "weight": round(float(model[0][i]), 3)} for i in top])
    return report


def learn_from(report: dict, labels_dir, thumbs: list | None = None) -> dict:
    """:func:`learn_ranking` with the verdicts of the event logs in ``labels_dir``."""
    labels = reviewed_labels(labels_dir)
    known = {s["subject"] for s in report["subjects"]}
    if labels and not (set(labels) & known):
        raise UserError(f"{labels_dir}: none of the reviewed subjects belongs to this dataset")
    return learn_ranking(report, labels, thumbs)
