"""Time, memory and file size of a subject's shape (``datagen sample --save-shape RES``) at 256^3 and 512^3.

Writes ``benchmarks/reports/shape_speed.{json,md}`` (``shape_speed_quick.*`` with ``--quick``).

    python -m benchmarks.shape_speed                # 256^3 and 512^3 (~8 min on 2 cores)
    python -m benchmarks.shape_speed --quick        # 128^3 and 256^3 (~2 min)
    python -m benchmarks.shape_speed --report-only  # rewrite the markdown from the JSON

Subjects: a procedural head (the default generator, its 128^3 baked grid) and the shared EG3D
fixture, a tiny randomly initialised EG3D whose decoder and 256 px tri-planes have the released
model's sizes (32 -> 64 -> 33 decoder, 3 x 32 channels), so the time per grid point is the released
model's; its random density never reaches the originals' level 10, so it is meshed at level 3 and
its surface (and so the vertex count, colour time and file size) is not a head's. One run per
case, on the CPU, everything else as ``datagen sample`` does it (default memory budget). Stages:
the field on the grid (and, for the GAN, the decoder's colours at the vertices), marching cubes,
the procedural albedo at the vertices, the PLY encoding.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

from benchmarks.common import (
    REPO,
    bullets,
    load_average,
    load_note,
    measurement_header,
    peak_rss_since_reset_mb,
    report_main,
    reproduce,
    reset_peak_rss,
    run_sections,
    stage_clock,
    table,
)
from datagen import shapes
from datagen.generators import make_generator
from datagen.generators import procedural as procedural_pkg

NAME = "shape_speed"
SEED, SUBJECT = 0, 3
FIXTURE_NAME = "fixtures/gan/eg3d/eg3d-tiny.pkl"  # under $PANOLAM_SHARED, default ../shared beside the repository
FIXTURE = Path(os.environ.get("PANOLAM_SHARED", REPO.parent / "shared")) / FIXTURE_NAME
FIXTURE_LEVEL = 3.0
RESOLUTIONS = {False: (256, 512), True: (128, 256)}


def measure_case(generator, subject, res: int, level: float | None) -> dict:
    """One extraction at ``res``^3: seconds per stage, peak memory, mesh size and file sizes."""
    base = reset_peak_rss()
    stages = {"marching_cubes": (shapes, "surface_mesh"), "albedo": (procedural_pkg, "head_field")}
    start = time.perf_counter()
    with stage_clock(stages) as spent:
        mesh = shapes.extract_shape(generator, subject, res, level)
    total = time.perf_counter() - start
    t0 = time.perf_counter()
    ply = shapes.encode_mesh(mesh, "ply")
    encode = time.perf_counter() - t0
    sizes = {"ply": len(ply), "obj": len(shapes.encode_mesh(mesh, "obj")), "glb": len(shapes.encode_mesh(mesh, "glb"))}
    field = total - spent["marching_cubes"] - spent["albedo"]
    return {"resolution": res, "seconds": total + encode, "field_seconds": field,
            "marching_cubes_seconds": spent["marching_cubes"], "albedo_seconds": spent["albedo"],
            "ply_encode_seconds": encode, "peak_rss_mb_above_start": peak_rss_since_reset_mb() - base,
            "vertices": mesh.record["vertices"], "faces": mesh.record["faces"], "bytes": sizes,
            "load_average_after": load_average()}


def _warm_up() -> None:
    """Import the mesh libraries once (their first call would be counted in the first case otherwise)."""
    import numpy as np

    faces = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    tetra = shapes.Mesh(vertices=np.eye(4, 3, dtype=np.float32), faces=faces, colors=np.zeros((4, 3), np.uint8),
                        record={})
    for fmt in shapes.FORMATS:
        shapes.encode_mesh(tetra, fmt)
    ball = np.linalg.norm(np.mgrid[-1:1:8j, -1:1:8j, -1:1:8j], axis=0).astype(np.float32)
    shapes.surface_mesh(ball, 0.5, -1.0, 2 / 7, inside_above=False, what="warm-up")


def measure(quick: bool, command: str) -> dict:
    resolutions = RESOLUTIONS[quick]
    results = measurement_header("quick" if quick else "full", command,
                                 {"resolutions": list(resolutions), "seed": SEED, "subject": SUBJECT,
                                  "fixture": FIXTURE_NAME, "fixture_level": FIXTURE_LEVEL})
    cases = {"procedural": (make_generator("procedural"), None)}
    if FIXTURE.exists():
        cases["eg3d_fixture"] = (make_generator("eg3d", str(FIXTURE), {"device": "cpu"}), FIXTURE_LEVEL)

    def run_generator(name):
        generator, level = cases[name]
        t0 = time.perf_counter()
        subject = generator.sample_subject(SEED, SUBJECT)
        out = {"subject_seconds": time.perf_counter() - t0}
        for res in resolutions:
            out[str(res)] = measure_case(generator, subject, res, level)
        return out

    sections = tuple((name, f"{name} at {', '.join(f'{r}^3' for r in resolutions)}", lambda n=name: run_generator(n))
                     for name in cases)
    run_sections(results, sections, (), warm_up=_warm_up)
    return results


def _per_point(results: dict) -> str:
    """Microseconds per evaluated grid point of the GAN at its largest grid (the trim leaves fewer)."""
    if "eg3d_fixture" not in results:
        return "(not measured)"
    res = max(results["plan"]["resolutions"])
    inner = res - 2 * (shapes.TRIM_PER_256 * res // 256)
    return f"{results['eg3d_fixture'][str(res)]['field_seconds'] / inner ** 3 * 1e6:.1f} us"


def _mb(n: int) -> str:
    return f"{n / 2 ** 20:.1f}"


def render(results: dict, out_dir: Path) -> str:
    resolutions = results["plan"]["resolutions"]
    names = [k for k in ("procedural", "eg3d_fixture") if k in results]
    rows = []
    for name in names:
        for res in resolutions:
            c = results[name][str(res)]
            rows.append([name, f"{res}^3", f"{c['seconds']:.1f}", f"{c['field_seconds']:.1f}",
                         f"{c['marching_cubes_seconds']:.1f}", f"{c['albedo_seconds']:.1f}",
                         f"{c['ply_encode_seconds']:.2f}", f"{c['peak_rss_mb_above_start']:.0f}",
                         f"{c['vertices']:,}", f"{c['faces']:,}", _mb(c["bytes"]["ply"]), _mb(c["bytes"]["obj"]),
                         _mb(c["bytes"]["glb"])])
    lines = [f"# Shape extraction: time and size per subject ({results['mode']} run, {results['date_utc']})", "",
             *reproduce(results["command"]), "",
             f"Machine: {results['machine']['cpu_model']}, {results['machine']['usable_cpus']} CPUs, torch "
             f"{results['machine']['torch']} with {results['machine']['torch_threads']} threads, CPU only.",
             "", load_note(results, 2, "other work shared the CPUs, so the times are upper bounds."), "",
             *table(["subject", "grid", "total s", "field s", "marching cubes s", "albedo s", "PLY encode s",
                     "peak memory MiB", "vertices", "faces", "PLY MiB", "OBJ MiB", "GLB MiB"], rows), "",
             *bullets([
                 "total = field + marching cubes + albedo + PLY encoding; `field` is the grid (and, for the GAN, "
                 "the decoder's colours at the vertices); the subject itself (procedural bake, GAN mapping and "
                 "backbone) is not included: "
                 + ", ".join(f"{n} {results[n]['subject_seconds']:.1f} s" for n in names) + ".",
                 "peak memory: the rise of the process's resident set during the extraction (the RES^3 float32 "
                 "grid, 64 MiB at 256^3 and 512 MiB at 512^3, then marching cubes).",
                 f"The GAN's field costs {_per_point(results)} per grid point here, almost all of it the decoder and "
                 "the plane sampling (the same code the ray march runs).",
                 f"The whole run took {results['benchmark_seconds']:.0f} s.",
                 "The PLY is what `--save-shape` stores in each subject's record (binary, float32 xyz and RGBA "
                 "uchar per vertex, int32 faces); OBJ and GLB are what `datagen shape --out` writes on request.",
                 "procedural: the default generator (128^3 baked grid, trilinear); a finer grid follows that "
                 "field's surface more closely but adds no detail beyond it.",
                 f"eg3d_fixture: `shared/{results['plan']['fixture']}`, a tiny random-init EG3D (decoder and 256 px planes "
                 f"of the released sizes, so the field time per grid point is the released model's); meshed at level "
                 f"{results['plan']['fixture_level']:g} (its random density never reaches 10), so its surface and "
                 "file size are not a head's. The originals' trim leaves (RES - 2 int(30 RES / 256))^3 points to "
                 "evaluate: 196^3 = 7.5 M at 256^3, 392^3 = 60 M at 512^3.",
             ]), ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    report_main(argv, script=Path(__file__), name=NAME, doc=__doc__,
                quick_help="128^3 and 256^3 instead of 256^3 and 512^3",
                report_only_help="rewrite the markdown from the saved JSON", measure=measure, render=render)


if __name__ == "__main__":
    main()
