"""The ``datagen`` command line: sample, verify, preview, export, shape, info."""
from __future__ import annotations

import json
import sys

from .command_line import OneLineParser, add_options, given, run_command
from .errors import SettingError, UserError
from .threads import add_option as add_threads_option
from .text import byte_size, plural, readable
from .generators.settings import GANConfig, ProceduralConfig
from .dataset import Dataset
from .job import JobSpec, SampleOptions
from .verify import VerifyOptions


def build_parser() -> OneLineParser:
    p = OneLineParser(prog="datagen", description="Build multiview head datasets from head generators.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=OneLineParser)

    s = sub.add_parser("sample", help="render subjects into WebDataset shards")
    add_options(s, JobSpec)
    add_options(s, SampleOptions, only=("workers", "backend"))
    add_threads_option(s, "each worker process (or Ray task)")
    add_options(s, SampleOptions)
    add_options(s, ProceduralConfig, only=("background",))
    add_options(s, ProceduralConfig, help_prefix="procedural: ")
    add_options(s, GANConfig, help_prefix="GANs: ")

    v = sub.add_parser("verify", help="check checksums, decoding, counts and metadata of a dataset")
    v.add_argument("dataset", help="dataset folder (datagen sample --out)")
    add_options(v, VerifyOptions)
    add_threads_option(v, "each worker process (or Ray task)")

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


def generator_options(args) -> dict:
    """The generator settings given on the command line, for the chosen generator; a SettingError for one
    that only the other kind of generator has."""
    mine, other = (ProceduralConfig, GANConfig) if (args.gan or JobSpec.gan) == "procedural" \
        else (GANConfig, ProceduralConfig)
    options = given(args, mine)
    for name in given(args, other):
        if name not in options:
            raise SettingError(f"{{{name}}}: only for the " +
                               ("GAN generators" if other is GANConfig else "procedural generator"))
    return options


def _sample(args) -> int:
    from .pipeline import run_sample, software_info

    spec = JobSpec(**given(args, JobSpec), generator_options=generator_options(args), software=software_info())
    opts = SampleOptions(**given(args, SampleOptions))
    summary = run_sample(spec, workers=opts.workers, backend=opts.backend, ray_address=opts.ray_address,
                         gpus_per_task=opts.gpus_per_task, shard_index=opts.shard_index, num_shards=opts.num_shards,
                         resume=opts.resume, progress=not opts.quiet, threads=args.threads)
    if not summary["shards_written"] and summary["shards_skipped"]:
        part = "this job's " if opts.num_shards > 1 else ""
        print(f"{args.out}: complete ({part}{summary['shards_skipped']} of {plural(spec.num_shard_files, 'shard')}, "
              f"{plural(summary['subjects'], 'subject')}); nothing to do")
        return 0
    rate = summary["images"] / summary["seconds"] if summary["seconds"] > 0 else 0.0
    print(f"wrote {summary['shards_written']} shard(s), skipped {summary['shards_skipped']} complete; "
          f"{summary['images']} images in {summary['seconds']:.1f} s ({rate:.1f} img/s) -> {args.out}")
    return 0


def _verify(args) -> int:
    from .dataset.shards import job_shards
    from .verify import verify_dataset

    opts = VerifyOptions(**given(args, VerifyOptions))
    dataset = Dataset(args.dataset)
    shards = None
    if opts.num_shards > 1 or opts.shard_index:
        mine = set(job_shards(max(dataset.shard_numbers, default=-1) + 1, opts.shard_index, opts.num_shards))
        shards = [n for n in dataset.shard_numbers if n in mine]
    report = verify_dataset(dataset, not opts.quiet, opts.placement(args.threads), shards)
    for line in report["problems"]:
        print(f"problem: {line}")
    for path in report["stray"]:
        print(f"note: leftover temporary file {path} (an interrupted run; --resume removes it)")
    status = "OK" if not report["problems"] else "FAILED"
    print(f"{status}: {report['complete']}/{report['shards']} shards complete and valid, {plural(report['subjects'], 'subject')}")
    return 0 if not report["problems"] else 1


def _preview(args) -> int:
    from .preview import write_contact_sheet

    out = write_contact_sheet(args.dataset, args.subject, args.out, args.columns, args.mask_depth)
    print(f"wrote {out}")
    return 0


def _export(args) -> int:
    from .export import check_subjects, export_subject
    from .preview import parse_subject

    dataset = Dataset(args.dataset)
    subjects = [parse_subject(s) for s in args.subject] if args.subject else dataset.complete_subjects
    subjects = check_subjects(dataset, subjects)  # every one, before anything is written
    if not subjects:
        raise UserError(f"{args.dataset}: no complete shards to export (see datagen verify)")
    for key in subjects:
        done = export_subject(dataset, key, args.format, args.out, args.background)
        note = (f"; 3DGS's one camera_angle_x (the median) is off by up to {done['file_fov_max_px_error']:.2f} px"
                if "file_fov_max_px_error" in done else "")
        print(f"wrote {done['path']} ({args.format}, {done['views']} views{note})")
    return 0


def _shape(args) -> int:
    from .preview import parse_subject
    from .shapes import check_resolution, write_shape

    if args.res is not None:
        check_resolution(args.res, "res")
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

    dataset = Dataset(args.dataset)
    info = dataset_info(dataset)
    info["shapes"] = shapes_summary(dataset)
    if args.json:
        print(json.dumps(info, indent=1, sort_keys=True))
    else:
        print("\n".join(readable(dict(("size", byte_size(v)) if k == "bytes" else (k, v) for k, v in info.items()))))
    return 0


COMMANDS = {"sample": _sample, "verify": _verify, "preview": _preview, "export": _export, "shape": _shape,
            "info": _info}


def main(argv=None) -> int:
    parser = build_parser()
    return run_command("datagen", COMMANDS, parser.parse_args(argv), "rerun with --resume to continue", parser)


if __name__ == "__main__":
    sys.exit(main())
