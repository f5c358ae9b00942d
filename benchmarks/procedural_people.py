"""Do procedural heads look like different people? Identity diversity, attribute coverage and speed of
the procedural generator against earlier ones, side by side in one run.

The earlier generators are read from the project's git history (``--baseline``, default: the last
commit of the mannequin generator and the last before the sex and age cues) and imported beside
``datagen.generators.procedural``'s siblings, so the comparison needs a clone with history.

Writes ``benchmarks/reports/procedural_people.{json,md}``, a contact sheet of 32 subjects, front
and back (``procedural_people.png``), and the distribution of the identity distances per generator
(``procedural_people_distances.png``, with matplotlib).

    python -m benchmarks.procedural_people            # 40 subjects of seeds 0 and 11 for identity, 4 timed, ~8 min
    python -m benchmarks.procedural_people --quick    # 16 and 1
    python -m benchmarks.procedural_people --report-only
    python -m benchmarks.procedural_people --baseline <commit> [<commit> ...]

Sections:
1. Attribute coverage: ``sample_params`` of 1,000 seeds (no rendering): the share of each hair style,
   hair colour, skin tone bracket, sex, age bracket, facial hair, glasses and caps.
2. Identity: frontal views (yaw 0, pitch 0, radius 2.7, FOV 18.837) of N subjects of each seed from each
   generator. dlib's HOG face detector (upsampling once) on the 128 px views gives the detection
   rate; dlib's face-recognition ResNet (5-point aligned chips) on the 256 px views gives the
   Euclidean embedding distance between every pair of different subjects (dlib's same-person
   threshold is 0.6). A control: the same subject seen at yaw 0 and yaw 10 degrees.
3. Speed: the same subjects (32 views of the 360 protocol at 128 px, grid 128^3), old and new
   alternately, bake and render wall seconds (time.perf_counter), medians; torch threads as given.
"""
from __future__ import annotations

import argparse
import importlib.util
import itertools
import json
import subprocess
import tempfile
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import equator_views, load_average, machine_info, pyplot
from datagen.cameras import sample_views
from datagen.generators import procedural
from datagen.generators.base import STREAM_CAMERAS, STREAM_LATENT, subject_rng

REPORTS = Path(__file__).resolve().parent / "reports"
NAME = "procedural_people"
SEED = 0
IDENTITY_SEEDS = (0, 11)  # identity is measured on subjects of both (seed 0 was looked at while tuning the faces)
COVERAGE_SEEDS = 1000
SHEET_SUBJECTS = 32
SAME_PERSON = 0.6  # dlib's threshold on the embedding distance
# Earlier generators to compare against: the last mannequin, and the last before the face-detection fixes
# (caps high on the forehead, grey sclera, wire glasses frames).
BASELINES = ("b91c245", "c088109")
ROOT = Path(__file__).resolve().parents[1]
ATTRIBUTES = ("hair_style", "hair_colour", "skin_tone", "sex", "age_bracket", "facial_hair", "glasses", "cap",
              "makeup", "neckline", "iris")


def _git(*args) -> str:
    return subprocess.run(["git", "-C", str(ROOT), *args], check=True, capture_output=True, text=True).stdout


def generator_at(commit: str, scratch: Path):
    """The procedural generator as of ``commit`` (a module, or since the split a package under
    ``datagen/generators/procedural/``), imported beside today's modules as
    ``datagen.generators.procedural_<commit>``; a package's files are written under ``scratch``."""
    name = f"datagen.generators.procedural_{commit}"
    files = _git("ls-tree", "--name-only", commit, "datagen/generators/procedural/").split()
    if files:
        folder = scratch / f"procedural_{commit}"
        folder.mkdir(parents=True, exist_ok=True)
        for path in files:
            (folder / Path(path).name).write_text(_git("show", f"{commit}:{path}"))
        spec = importlib.util.spec_from_file_location(name, folder / "__init__.py",
                                                      submodule_search_locations=[str(folder)])
    else:
        spec = importlib.util.spec_from_loader(name, loader=None)
    module = importlib.util.module_from_spec(spec)
    module.__package__ = name if files else "datagen.generators"
    sys.modules[name] = module  # dataclasses and relative imports look their module up there
    if files:
        spec.loader.exec_module(module)
    else:
        path = "datagen/generators/procedural.py"
        exec(compile(_git("show", f"{commit}:{path}"), f"{commit}:{path}", "exec"), module.__dict__)
    return module


def u8(rgb) -> np.ndarray:
    return (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)


def coverage() -> dict:
    params = [procedural.sample_params(subject_rng(SEED, i, STREAM_LATENT)) for i in range(COVERAGE_SEEDS)]
    out = {}
    for key in ATTRIBUTES:
        counts = Counter(str(p[key]) for p in params)
        out[key] = {k: v / len(params) for k, v in sorted(counts.items(), key=lambda kv: -kv[1])}
    return out


class Faces:
    def __init__(self):
        import dlib

        from datagen.faces import model_file as _model_file
        self.detector = dlib.get_frontal_face_detector()
        self.shape = dlib.shape_predictor(_model_file("shape_predictor_5_face_landmarks.dat"))
        self.net = dlib.face_recognition_model_v1(_model_file("dlib_face_recognition_resnet_model_v1.dat"))

    def found(self, image) -> bool:
        return len(self.detector(image, 1)) > 0

    def embed(self, image):
        boxes = self.detector(image, 1)
        if not boxes:
            return None
        return np.asarray(self.net.compute_face_descriptor(image, self.shape(image, boxes[0])))


def identity(n: int, faces: Faces, generators: dict, seeds=IDENTITY_SEEDS) -> dict:
    """Per generator: detections and embeddings of the first ``n`` subjects of each dataset seed; the
    distances of every pair of different subjects (pooled over the seeds, and per seed)."""
    out = {}
    for label, module in generators.items():
        gen = module.ProceduralHeads(module.ProceduralConfig(defect_rate=0.0))
        found, embeddings, control, sexes, origin = 0, [], [], [], []
        for seed, i in itertools.product(seeds, range(n)):
            subject = gen.sample_subject(seed, i)
            found += faces.found(u8(gen.render(subject, equator_views((0.0,)), 128).rgb[0]))
            big = gen.render(subject, equator_views((0.0, 10.0)), 256).rgb
            e0, e1 = faces.embed(u8(big[0])), faces.embed(u8(big[1]))
            embeddings.append(e0)
            sexes.append(subject.latent["params"].get("sex"))
            origin.append(seed)
            if e0 is not None and e1 is not None:
                control.append(float(np.linalg.norm(e0 - e1)))
        kept = [(e, sex, seed) for e, sex, seed in zip(embeddings, sexes, origin) if e is not None]
        pairs = [(float(np.linalg.norm(a - b)), sa == sb, ka if ka == kb else None)
                 for (a, sa, ka), (b, sb, kb) in itertools.combinations(kept, 2)]
        out[label] = {"subjects": n * len(seeds), "seeds": list(seeds), "detected_128": found, "embedded_256": len(kept),
                      "distances": [d for d, _, _ in pairs], "same_sex": [same for _, same, _ in pairs],
                      "median_per_seed": {str(k): float(np.median([d for d, _, ks in pairs if ks == k])) for k in seeds},
                      "same_subject_yaw10": control}
    return out


def speed(n: int, generators: dict) -> dict:
    gens = {label: m.ProceduralHeads(m.ProceduralConfig()) for label, m in generators.items()}
    times = {label: [] for label in gens}
    warm = sample_views("360", subject_rng(SEED, 10_000, STREAM_CAMERAS), 4)
    for gen in gens.values():
        gen.render(gen.sample_subject(SEED, 10_000), warm, 32)
    for i in range(n):
        views = sample_views("360", subject_rng(SEED, i, STREAM_CAMERAS), 32)
        for label, gen in gens.items():  # alternately, so both see the same load
            t0 = time.perf_counter()
            subject = gen.sample_subject(SEED, i)
            t1 = time.perf_counter()
            gen.render(subject, views, 128)
            times[label].append({"bake_s": t1 - t0, "render_s": time.perf_counter() - t1, "load": load_average()})
    return times


def contact_sheet(path: Path, n: int = SHEET_SUBJECTS, res: int = 128) -> None:
    from PIL import Image, ImageDraw
    gen = procedural.ProceduralHeads(procedural.ProceduralConfig(defect_rate=0.0))
    cols = 8
    rows = (n + cols - 1) // cols
    sheet = Image.new("RGB", (cols * res, rows * 2 * res), "white")
    for i in range(n):
        out = gen.render(gen.sample_subject(SEED, i), equator_views((0.0, 180.0)), res)
        r, c = divmod(i, cols)
        sheet.paste(Image.fromarray(u8(out.rgb[0])), (c * res, r * 2 * res))
        sheet.paste(Image.fromarray(u8(out.rgb[1])), (c * res, r * 2 * res + res))
    draw = ImageDraw.Draw(sheet)
    for r in range(1, rows):
        draw.line([(0, r * 2 * res), (sheet.width, r * 2 * res)], fill=(200, 200, 200))
    sheet.save(path)


def plot_distances(res: dict, path: Path) -> bool:
    """Histogram of the embedding distances between different subjects, one per generator; False
    without matplotlib."""
    plt = pyplot()
    if plt is None:
        return False
    fig, ax = plt.subplots(figsize=(7, 4))
    bins = np.linspace(0.0, 1.0, 41)
    for label, r in res["identity"].items():
        d = np.asarray(r["distances"])
        ax.hist(d, bins=bins, histtype="step", linewidth=1.8, label=f"{label}: median {np.median(d):.3f}")
    ax.axvline(SAME_PERSON, color="k", linestyle="--", linewidth=1, label="dlib same-person threshold 0.6")
    ax.set_xlabel("dlib face-embedding distance between two different subjects (frontal, 256 px)")
    ax.set_ylabel("pairs")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def stats(values) -> dict:
    v = np.asarray(values, float)
    if not v.size:
        return {}
    return {k: float(f(v)) for k, f in (("median", np.median), ("p10", lambda a: np.percentile(a, 10)),
                                         ("p90", lambda a: np.percentile(a, 90)), ("min", np.min))} | {
        "share_below_0.6": float(np.mean(v < SAME_PERSON))}


def markdown(res: dict) -> str:
    lines = ["# Procedural people: identity diversity, attribute coverage, speed", "",
             f"Command: `{res['command']}` ({res['date_utc']}, {res['machine'].get('usable_cpus', '?')} CPUs, "
             f"load average {res['load_before']}, torch threads {res['threads']}). "
             "The earlier generators are `datagen/generators/procedural.py` at commits "
             f"{', '.join(res['baselines'])}.", ""]
    lines += ["## Identity (dlib)", "",
              "Frontal views (yaw 0, pitch 0): HOG face detection (upsample 1) at 128 px; ResNet embedding "
              "distance between different subjects at 256 px (dlib's same-person threshold: 0.6; higher is "
              "more different); the median also over pairs of the same sex and of different sexes, and over "
              "the pairs within each dataset seed. Control: one subject at yaw 0 against yaw 10.", "",
              "| generator | subjects | face found at 128 px | median distance | p10 | p90 | pairs below 0.6 | "
              "same sex / different sex (median) | median within each seed | same subject, yaw 0 vs 10 (median) |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for label, r in res["identity"].items():
        d, c = stats(r["distances"]), stats(r["same_subject_yaw10"])
        split = [[x for x, same in zip(r["distances"], r["same_sex"]) if same == want] for want in (True, False)]
        by_sex = " / ".join(f"{np.median(v):.3f}" for v in split) if all(split) else "n/a (no sex drawn)"
        per_seed = ", ".join(f"seed {k}: {v:.3f}" for k, v in r.get("median_per_seed", {}).items()) or "n/a"
        lines.append(f"| {label} | {r['subjects']} | {r['detected_128']}/{r['subjects']} "
                     f"({100 * r['detected_128'] / r['subjects']:.0f} %) | {d.get('median', float('nan')):.3f} | "
                     f"{d.get('p10', float('nan')):.3f} | {d.get('p90', float('nan')):.3f} | "
                     f"{100 * d.get('share_below_0.6', float('nan')):.0f} % | {by_sex} | {per_seed} | "
                     f"{c.get('median', float('nan')):.3f} |")
    if res.get("distance_plot"):
        lines += ["", f"![distances between different subjects]({res['distance_plot']})"]
    lines += ["", "## Speed (32 views, 360 protocol, 128 px, grid 128^3)", "",
              "The generators in turn on the same subjects and cameras; wall seconds, medians.", "",
              "| generator | bake s | render s | total s per subject |", "|---|---|---|---|"]
    for label, t in res["speed"].items():
        b = np.median([x["bake_s"] for x in t])
        r = np.median([x["render_s"] for x in t])
        tot = np.median([x["bake_s"] + x["render_s"] for x in t])
        lines.append(f"| {label} | {b:.2f} | {r:.2f} | {tot:.2f} |")
    loads = [x["load"] for t in res["speed"].values() for x in t if x["load"] is not None]
    if loads:
        lines.append(f"\nLoad average during the timing: {min(loads):.1f} to {max(loads):.1f} on "
                     f"{res['machine'].get('usable_cpus', '?')} CPUs (above the CPU count the figures are inflated by other work; the ratio holds).")
    lines += ["", f"## Attribute coverage ({COVERAGE_SEEDS} seeds, `sample_params` only)", ""]
    for key, shares in res["coverage"].items():
        lines.append(f"* **{key}**: " + ", ".join(f"{k} {100 * v:.1f} %" for k, v in shares.items()))
    lines += ["", "Rare on purpose: unnatural (dyed) hair (2 % of draws), and red and platinum hair (3 % each of "
              "the natural colours' draws before greying; rarer still among people). Grey and white hair come with "
              "age; facial hair only on male subjects.", "",
              "## Contact sheet", "", f"![32 subjects, front and back]({NAME}.png)", ""]
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="16 subjects for identity, 1 timed")
    ap.add_argument("--report-only", action="store_true", help="rewrite the markdown from the JSON")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--baseline", nargs="+", default=list(BASELINES), help="commits of the generators to compare against")
    args = ap.parse_args(argv)
    REPORTS.mkdir(parents=True, exist_ok=True)
    json_path = REPORTS / f"{NAME}.json"
    if args.report_only:
        res = json.loads(json_path.read_text())
    else:
        torch.set_num_threads(args.threads)
        n_id, n_speed = (16, 1) if args.quick else (40, 4)
        scratch = Path(tempfile.mkdtemp(prefix="procedural_baselines_"))  # the baselines' packages, kept while imported
        generators = {f"old ({commit})": generator_at(commit, scratch) for commit in args.baseline} | {"new": procedural}
        res = {"command": "python -m benchmarks.procedural_people" + (" --quick" if args.quick else ""),
               "baselines": args.baseline,
               "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "machine": machine_info(),
               "load_before": load_average(), "threads": args.threads}
        print("coverage ...", flush=True)
        res["coverage"] = coverage()
        print("identity ...", flush=True)
        res["identity"] = identity(n_id, Faces(), generators)
        print("speed ...", flush=True)
        res["speed"] = speed(n_speed, generators)
        print("contact sheet ...", flush=True)
        contact_sheet(REPORTS / f"{NAME}.png")
        json_path.write_text(json.dumps(res, indent=1))
    res["distance_plot"] = f"{NAME}_distances.png" if plot_distances(res, REPORTS / f"{NAME}_distances.png") else None
    (REPORTS / f"{NAME}.md").write_text(markdown(res))
    print((REPORTS / f"{NAME}.md").read_text())


if __name__ == "__main__":
    main()
