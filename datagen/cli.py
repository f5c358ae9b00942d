"""The ``datagen`` command line: sample, verify, preview, export, shape, info."""
from __future__ import annotations

import argparse
import json
import sys

from .cameras import PROTOCOLS
from .errors import OneLineParser, UserError, run_command
from .threads import add_option as add_threads_option
from .text import byte_size, plural, readable
from .generators import AVAILABLE


def parse_background(text: str, allow_own: bool):
    """'own' (GANs only), white, black, grey or R,G,B in [0, 1]."""
    named = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0), "grey": (0.5, 0.5, 0.5)}
    if text == "own" and allow_own:
        return "own"
    if text in named:
        return named[text]
    try:
        rgb = tuple(float(v) for v in text.split(","))
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        choices = "own (GANs), white, black, grey" if allow_own else "white, black, grey"
        raise UserError(f"--background must be {choices} or R,G,B with values in [0, 1]")
    return rgb


def parse_workers(text: str):
    """'auto' or a whole number (checked by the pipeline)."""
    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be auto or a number, not {text!r}") from None


def build_parser() -> OneLineParser:
    p = OneLineParser(prog="datagen", description="Build multiview head datasets from head generators.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=OneLineParser)

    s = sub.add_parser("sample", help="render subjects into WebDataset shards")
    s.add_argument("--gan", default="procedural", choices=AVAILABLE, help="head generator")
    s.add_argument("--checkpoint", help="generator checkpoint file (GAN generators)")
    s.add_argument("--protocol", default="360", choices=PROTOCOLS, help="camera protocol")
    s.add_argument("--subjects", type=int, default=16, help="number of subjects")
    s.add_argument("--resolution", type=int, default=128, help="image size in pixels (square)")
    s.add_argument("--views", type=int, default=32, help="views per subject (paper: 32)")
    s.add_argument("--seed", type=int, default=0, help="dataset seed; every draw derives from (seed, subject)")
    s.add_argument("--shard-size", type=int, default=8, help="subjects per shard")
    s.add_argument("--out", required=True, help="output dataset folder")
    s.add_argument("--workers", type=parse_workers, default=1, metavar="auto|N",
                   help="worker processes on this machine: N, or auto = one per GPU on CUDA (one with --device "
                        "cuda:N), else one per CPU core up to this job's shard count. On CUDA worker k renders on "
                        "cuda:(k mod the GPU count), so more workers than GPUs share them; --device cuda:N puts all "
                        "on GPU N. With --backend ray, each task gets the CPU cores divided by N")
    s.add_argument("--backend", default="local", choices=("local", "ray"), help="run shard tasks here or on Ray")
    add_threads_option(s, "each worker process (or Ray task)")
    s.add_argument("--gpus-per-task", type=float, default=None, metavar="G",
                   help="--backend ray with CUDA: the share of one GPU each shard task asks Ray for, in (0, 1]; "
                        "0.5 runs two tasks per GPU (default 1). Each task renders on the GPU Ray gives it")
    s.add_argument("--ray-address", help="address of an existing Ray cluster (default: RAY_ADDRESS or a local one)")
    s.add_argument("--shard-index", type=int, default=0, help="this job's part K of --num-shards (array jobs)")
    s.add_argument("--num-shards", type=int, default=1, help="split the shards over N jobs; job K writes shards s with s %% N == K")
    s.add_argument("--resume", action="store_true", help="skip complete shards, redo partial ones")
    s.add_argument("--defect-rate", type=float, default=None, help="procedural: fraction of subjects with an injected defect (default 0.04)")
    s.add_argument("--defect-types", default=None, metavar="A,B",
                   help="procedural: the defect classes to draw from (default all: janus, flat_back, haze, seam, "
                        "blurry_back, hole, floaters, washed_out)")
    s.add_argument("--defect-severity", default=None, metavar="LO,HI",
                   help="procedural: severity range of injected defects, within [0, 1] (default 0.3,1)")
    s.add_argument("--background", default=None,
                   help="white, black, grey or R,G,B (procedural default white); GANs also 'own' (default)")
    s.add_argument("--truncation", type=float, default=None, help="GANs: truncation psi (default 0.7)")
    s.add_argument("--truncation-cutoff", type=int, default=None, help="GANs: truncate the first N ws (default 14)")
    s.add_argument("--save-planes", type=int, default=0, metavar="RES",
                   help="GANs: also store the plane features in fp16 at RES x RES (for distillation)")
    s.add_argument("--save-shape", type=int, default=0, metavar="RES",
                   help="also store each subject's head surface, meshed on a RES^3 grid over the generator's box, as "
                        "shape.ply in its record (binary PLY with vertex colours, world units; see datagen shape)")
    s.add_argument("--shape-level", type=float, default=None, metavar="L",
                   help="GANs with --save-shape: the raw density level of the surface (default 10, the originals')")
    s.add_argument("--device", default=None,
                   help="GANs: cpu, cuda (every GPU, see --workers), cuda:N (that GPU only; local backend) or auto "
                        "(default: cuda when available). The procedural generator runs on the CPU")
    s.add_argument("--precision", default=None, choices=("auto", "fp32", "fp16"),
                   help="GANs: 'auto' (default) runs the originals' fp16 blocks (the super-resolution of the released "
                        "checkpoints) in fp16 on CUDA and everything in fp32 on CPU; 'fp32' never uses fp16")
    s.add_argument("--clip-rays", action="store_true",
                   help="GANs: march each ray only where it crosses the generator's box and skip rays that miss it "
                        "(the originals march the whole ray range)")
    s.add_argument("--memory-budget-mb", type=float, default=None, metavar="MB",
                   help="GANs: working memory per chunk of rays / batch of super-resolved views "
                        "(default 64 on CPU, a quarter of the GPU's memory on CUDA)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")

    v = sub.add_parser("verify", help="check checksums, decoding, counts and metadata of a dataset")
    v.add_argument("dataset", help="dataset folder (datagen sample --out)")
    v.add_argument("--quiet", action="store_true", help="no progress bar")

    pv = sub.add_parser("preview", help="write a contact sheet PNG of one subject's views")
    pv.add_argument("dataset", help="dataset folder (datagen sample --out)")
    pv.add_argument("--subject", required=True, help="subject number (e.g. 3) or id (subj00000003)")
    pv.add_argument("--out", required=True, help="PNG to write")
    pv.add_argument("--columns", type=int, default=8, help="views per row")
    pv.add_argument("--mask-depth", action="store_true", help="show mask and depth beside each view")

    e = sub.add_parser("export", help="write subjects' views and cameras for nerfstudio, instant-ngp/3DGS or COLMAP")
    e.add_argument("dataset", help="dataset folder (datagen sample --out)")
    e.add_argument("--format", required=True, choices=("nerfstudio", "instant-ngp", "colmap"),
                   help="target layout: nerfstudio transforms.json, instant-ngp/Blender transforms_{train,test}.json "
                        "(3DGS train.py reads it), or COLMAP text (sparse/0)")
    e.add_argument("--subject", nargs="+", metavar="ID",
                   help="subject numbers (e.g. 3) or ids (subj00000003); default: every subject of the complete shards")
    e.add_argument("--out", required=True, help="output folder; each subject goes to OUT/<subject id>/")
    e.add_argument("--background", default="transparent", choices=("transparent", "white", "black"),
                   help="transparent: RGBA PNGs with the mask as alpha; white/black: RGB PNGs on that colour")

    sh = sub.add_parser("shape", help="write one subject's head surface as a coloured PLY, OBJ or GLB mesh")
    sh.add_argument("dataset", help="dataset folder (datagen sample --out)")
    sh.add_argument("--subject", required=True, help="subject number (e.g. 3) or id (subj00000003)")
    sh.add_argument("--out", required=True, help="mesh file to write: .ply, .obj or .glb")
    sh.add_argument("--res", type=int, default=None, metavar="RES",
                    help="grid resolution; default: the stored shape, else 256 (a shape not stored is extracted again "
                         "from the generator)")
    sh.add_argument("--level", type=float, default=None,
                    help="GANs: the raw density level of the surface (default: the stored shape's, else 10)")
    sh.add_argument("--checkpoint", help="GAN datasets: the checkpoint to extract with (default: the path the dataset "
                                         "was made from; its sha256 must be the recorded one)")
    sh.add_argument("--device", default=None, help="GAN datasets: cpu, cuda, cuda:N or auto (default)")
    sh.add_argument("--memory-budget-mb", type=float, default=None, metavar="MB",
                    help="GAN datasets: working memory per chunk of grid points (default as datagen sample's)")

    i = sub.add_parser("info", help="summarize a dataset")
    i.add_argument("dataset", help="dataset folder (datagen sample --out)")
    i.add_argument("--json", action="store_true", help="print JSON")
    return p


def _sample(args) -> int:
    from .pipeline import JobSpec, run_sample, software_info

    options = {}
    gan = args.gan != "procedural"
    if args.defect_rate is not None:
        if not 0.0 <= args.defect_rate <= 1.0:
            raise UserError("--defect-rate must be between 0 and 1")
        options["defect_rate"] = args.defect_rate
    if args.defect_types is not None:
        from .generators.procedural import DEFECT_TYPES
        kinds = [k.strip() for k in args.defect_types.split(",") if k.strip()]
        unknown = [k for k in kinds if k not in DEFECT_TYPES]
        if not kinds or unknown:
            raise UserError(f"--defect-types: unknown {', '.join(unknown) or '(none given)'}; choose from "
                            f"{', '.join(DEFECT_TYPES)}")
        options["defect_types"] = kinds
    if args.defect_severity is not None:
        try:
            lo, hi = (float(x) for x in args.defect_severity.split(","))
        except ValueError:
            lo = hi = float("nan")
        if not 0.0 <= lo <= hi <= 1.0:
            raise UserError("--defect-severity must be LO,HI with 0 <= LO <= HI <= 1")
        options["defect_severity"] = [lo, hi]
    if args.background is not None:
        bg = parse_background(args.background, allow_own=gan)
        options["background"] = bg if isinstance(bg, str) else list(bg)
    if args.truncation is not None:
        if not 0.0 <= args.truncation <= 2.0:
            raise UserError("--truncation must be between 0 and 2")
        options["truncation_psi"] = args.truncation
    if args.truncation_cutoff is not None:
        if args.truncation_cutoff < 0:
            raise UserError("--truncation-cutoff must be at least 0")
        options["truncation_cutoff"] = args.truncation_cutoff
    if args.save_planes:
        if not gan:
            raise UserError("--save-planes: the procedural generator has no planes")
        if not 8 <= args.save_planes <= 1024:
            raise UserError("--save-planes must be between 8 and 1024")
        options["save_planes"] = args.save_planes
    gan_only = {"device": args.device, "precision": args.precision, "clip_rays": args.clip_rays or None,
                "memory_budget_mb": args.memory_budget_mb}
    for key, value in gan_only.items():
        if value is not None:
            if not gan:
                raise UserError(f"--{key.replace('_', '-')}: only for the GAN generators")
            options[key] = value
    if args.memory_budget_mb is not None and not args.memory_budget_mb > 0:
        raise UserError("--memory-budget-mb must be above 0")
    spec = JobSpec(out=args.out, gan=args.gan, checkpoint=args.checkpoint, generator_options=options,
                   protocol=args.protocol, subjects=args.subjects, resolution=args.resolution, views=args.views,
                   seed=args.seed, shard_size=args.shard_size, software=software_info(), save_shape=args.save_shape,
                   shape_level=args.shape_level)
    summary = run_sample(spec, workers=args.workers, backend=args.backend, ray_address=args.ray_address,
                         gpus_per_task=args.gpus_per_task, shard_index=args.shard_index, num_shards=args.num_shards,
                         resume=args.resume, progress=not args.quiet, threads=args.threads)
    if not summary["shards_written"] and summary["shards_skipped"]:
        part = "this job's " if args.num_shards > 1 else ""
        print(f"{args.out}: complete ({part}{summary['shards_skipped']} of {plural(spec.num_shard_files, 'shard')}, "
              f"{plural(summary['subjects'], 'subject')}); nothing to do")
        return 0
    rate = summary["images"] / summary["seconds"] if summary["seconds"] > 0 else 0.0
    print(f"wrote {summary['shards_written']} shard(s), skipped {summary['shards_skipped']} complete; "
          f"{summary['images']} images in {summary['seconds']:.1f} s ({rate:.1f} img/s) -> {args.out}")
    return 0


def _verify(args) -> int:
    from .verify import verify_dataset

    report = verify_dataset(args.dataset, progress=not args.quiet)
    for line in report["problems"]:
        print(f"problem: {line}")
    for path in report["stray"]:
        print(f"note: leftover temporary file {path} (an interrupted run; --resume removes it)")
    status = "OK" if not report["problems"] else "FAILED"
    print(f"{status}: {report['complete']}/{report['shards']} shards complete and valid, {report['subjects']} subjects")
    return 0 if not report["problems"] else 1


def _preview(args) -> int:
    from .preview import write_contact_sheet

    out = write_contact_sheet(args.dataset, args.subject, args.out, args.columns, args.mask_depth)
    print(f"wrote {out}")
    return 0


def _export(args) -> int:
    from .export import check_subjects, complete_subjects, export_subject
    from .preview import parse_subject

    subjects = [parse_subject(s) for s in args.subject] if args.subject else complete_subjects(args.dataset)
    subjects = check_subjects(args.dataset, subjects)  # every one, before anything is written
    if not subjects:
        raise UserError(f"{args.dataset}: no complete shards to export (see datagen verify)")
    for key in subjects:
        done = export_subject(args.dataset, key, args.format, args.out, args.background)
        note = (f"; 3DGS's one camera_angle_x (the median) is off by up to {done['file_fov_max_px_error']:.2f} px"
                if "file_fov_max_px_error" in done else "")
        print(f"wrote {done['path']} ({args.format}, {done['views']} views{note})")
    return 0


def _shape(args) -> int:
    from .preview import parse_subject
    from .shapes import check_resolution, write_shape

    if args.res is not None:
        check_resolution(args.res, "--res")
    if args.memory_budget_mb is not None and not args.memory_budget_mb > 0:
        raise UserError("--memory-budget-mb must be above 0")
    done = write_shape(args.dataset, parse_subject(args.subject), args.out, resolution=args.res, level=args.level,
                       checkpoint=args.checkpoint, device=args.device, budget_mb=args.memory_budget_mb)
    how = "stored" if done["how"] == "stored" else f"extracted in {done['seconds']:.1f} s"
    print(f"wrote {done['path']} ({done['vertices']:,} vertices, {plural(done['faces'], 'face')}, "
          f"{done['resolution']}^3 grid, level {done['level']:g}, {how}; {byte_size(done['bytes'])})")
    return 0


def _info(args) -> int:
    from .preview import dataset_info
    from .shapes import shapes_summary

    info = dataset_info(args.dataset)
    info["shapes"] = shapes_summary(args.dataset)
    if args.json:
        print(json.dumps(info, indent=1, sort_keys=True))
    else:
        print("\n".join(readable(dict(("size", byte_size(v)) if k == "bytes" else (k, v) for k, v in info.items()))))
    return 0


COMMANDS = {"sample": _sample, "verify": _verify, "preview": _preview, "export": _export, "shape": _shape,
            "info": _info}


def main(argv=None) -> int:
    return run_command("datagen", COMMANDS, build_parser().parse_args(argv), "rerun with --resume to continue")


if __name__ == "__main__":
    sys.exit(main())
