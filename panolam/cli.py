"""The ``panolam`` command line: train on a curated manifest, reconstruct a photo, evaluate.

    panolam train --data D --manifest M --config tiny --out runs/t1 [--nproc 2]
    panolam train --data D --manifest M --resume runs/t1
    panolam infer photo.jpg --ckpt runs/t1 --out head.ply [--turntable head.mp4] [--views DIR]
    panolam eval --data D --manifest M --split test --ckpt runs/t1 [--out DIR]

``python -m panolam`` is the same command; ``torchrun --nproc-per-node 2 -m panolam train ...``
runs one training process per GPU (or CPU share). The training options are generated from
:class:`panolam.config.TrainConfig`. Heavy modules (torch, the model) are imported by the commands,
not here, so help and usage errors answer at once. User mistakes are one line on stderr and exit
status 2.
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

from datagen.device import DEVICE_HELP
from datagen.command_line import OneLineParser, run_command
from datagen.errors import UserError, optional_import
from datagen.threads import add_option as add_threads_option
from datagen.text import plural

from .config import PATH_FIELDS, ModelConfig, TrainConfig
from datagen.command_line import add_options, at_least, describe, fixed_fields, given, shown, unit_interval

CROP_SIZE = 512  # px of the head crop handed to the model (its encoder resizes to its own input size)
DEFAULT_CONFIG = "tiny"
LPIPS_FIELDS = ("lpips_backbone", "lpips_lin", "lpips_net")
FEW_TEST_SUBJECTS = 10  # below this many evaluated subjects, eval says its means are mostly noise
INTERRUPTED = {"train": "the last checkpoint is kept; rerun with --resume",
               "infer": "nothing was written", "eval": "no report was written"}


def _check_device(args) -> None:
    """Resolve ``args.device`` in place ('auto' -> cuda or cpu); UserError for one not available here."""
    from datagen.device import resolve_device
    args.device = str(resolve_device(args.device))


def _model_path_options(p, where_now: bool) -> None:
    """The weight-file options: for a new run, or where a trained run's files are now."""
    add_options(p, ModelConfig, only=PATH_FIELDS, help_suffix="; for a trained run, where its file is now"
                if where_now else "")


def _train_options(p):
    p.add_argument("--data", required=True, help="dataset directory (datagen sample --out)")
    p.add_argument("--manifest", required=True, help="curated manifest (label-tool compile)")
    p.add_argument("--config", help=f"model preset, optionally with ablations (default {DEFAULT_CONFIG}): tiny, full, "
                                    "tiny+no_c2f, tiny+single_point, tiny+no_triplane, tiny+cross_only")
    p.add_argument("--out", help="run directory (checkpoint, logs, TensorBoard)")
    p.add_argument("--resume", nargs="?", const="", metavar="RUN",
                   help="continue the run in RUN (default: --out) exactly where it stopped")
    add_options(p, TrainConfig)
    _model_path_options(p, where_now=False)
    p.add_argument("--nproc", type=at_least(1), default=1,
                   help="data-parallel processes on this machine (with --device cuda, process i on GPU i)")
    p.add_argument("--device", default="cpu", help=DEVICE_HELP)
    add_threads_option(p, "each training process")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def build_parser() -> OneLineParser:
    parser = OneLineParser(prog="panolam", description="Train, run and evaluate the PanoLAM head reconstructor.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    _train_options(sub.add_parser("train", help="train on the accepted subjects of a manifest"))
    p = sub.add_parser("infer", help="reconstruct a head from one photo",
                       description="Reconstruct a head from one photo. The model was trained on heads over white: "
                                   "an RGBA PNG whose background is transparent is composited on white, as training "
                                   "images are; any other photo keeps its background.")
    p.add_argument("photo", help="the photo: JPEG or PNG (RGBA: a transparent background is made white)")
    p.add_argument("--ckpt", required=True, help="run directory or checkpoint file")
    p.add_argument("--out", help="Gaussians as a standard 3DGS .ply")
    p.add_argument("--turntable", help="360-degree turntable: .mp4 (H.264) or animated .gif")
    p.add_argument("--views", help="directory for front/left/back/right PNG views")
    p.add_argument("--resolution", type=at_least(8), default=256, help="px of the turntable and views (default 256)")
    p.add_argument("--frames", type=at_least(1), default=36, help="turntable frames (default 36)")
    p.add_argument("--prune-opacity", type=unit_interval, default=0.02,
                   help="drop Gaussians below this opacity from the outputs (default 0.02)")
    p.add_argument("--pick", choices=("single", "largest"), default="single",
                   help="with several faces in the photo: refuse (single) or take the largest")
    p.add_argument("--no-crop", action="store_true", help="the photo is already framed like the training data")
    _model_path_options(p, where_now=True)
    p.add_argument("--device", default="cpu", help=DEVICE_HELP)
    p = sub.add_parser("eval", help="metrics on held-out subjects (front in; front/left/back/right out)")
    p.add_argument("--data", required=True, help="dataset directory")
    p.add_argument("--manifest", required=True, help="curated manifest")
    p.add_argument("--split", default="test", choices=("test", "train"), help="the manifest's subjects to evaluate")
    p.add_argument("--ckpt", required=True, help="run directory or checkpoint file")
    p.add_argument("--out", help="report directory (default: <ckpt>/eval-<split>)")
    p.add_argument("--limit", type=at_least(1), help="evaluate at most this many subjects")
    p.add_argument("--resolution", type=at_least(16), help="px of the compared views (default: as stored)")
    add_options(p, TrainConfig, only=LPIPS_FIELDS)
    p.add_argument("--no-faces", action="store_true", help="skip CSIM/APD (they need dlib)")
    p.add_argument("--no-baselines", action="store_true",
                   help="skip the untrained model and the mean-colour template (each costs as much as the model)")
    p.add_argument("--gallery", type=at_least(0), metavar="N",
                   help="subjects in gallery.png: the input, the reconstruction and the truth from the front, left, "
                        "back and right (default: 8; 0: none)")
    p.add_argument("--renders", metavar="DIR",
                   help="also write each evaluated subject's reconstruction, rendered from all its stored cameras, as "
                        "a dataset in DIR (label-tool auto and review read it)")
    _model_path_options(p, where_now=True)
    p.add_argument("--device", default="cpu", help=DEVICE_HELP)
    return parser


# -- train ---------------------------------------------------------------------------------------------------
def _configs(args) -> tuple[ModelConfig, TrainConfig]:
    """The run's configs: a preset and the options given, or the checkpoint's with the changes allowed on resume."""
    from .config import preset
    paths, settings = given(args, ModelConfig, only=PATH_FIELDS), given(args, TrainConfig)
    if not args.resume:
        try:
            return preset(args.config or DEFAULT_CONFIG, **paths), TrainConfig(**settings)
        except ValueError as e:
            raise UserError(str(e)) from None
    from .checkpoints import read_checkpoint
    state = read_checkpoint(args.out)
    try:
        model_cfg = ModelConfig.from_dict(state["model_config"]).replace(**paths)
        train_cfg = TrainConfig.from_dict(state["train_config"])
    except (TypeError, ValueError) as e:
        raise UserError(f"{args.out}: its configs do not fit this version ({e})") from None
    if args.config and args.config != model_cfg.name:
        raise UserError(f"{args.out} is a {model_cfg.name!r} run; resume it without --config {args.config}")
    for k in fixed_fields(TrainConfig):
        if k in settings and settings[k] != getattr(train_cfg, k):
            raise UserError(f"{describe(TrainConfig, k, settings[k])} differs from this run's "
                            f"{shown(getattr(train_cfg, k))}: the schedule, the data order and the objective are "
                            f"fixed when a run starts (start a new --out to change them)")
    return model_cfg, dataclasses.replace(train_cfg, **settings)


def _run_directory(args) -> None:
    """Settle ``args.out`` (the run) and ``args.resume`` (a bool) from ``--out`` and ``--resume [RUN]``."""
    if args.resume:  # --resume RUN
        if args.out and Path(args.out).resolve() != Path(args.resume).resolve():
            raise UserError(f"--resume {args.resume} and --out {args.out} name two runs; give one of them")
        args.out = args.resume
    if not args.out:
        raise UserError("say where the run goes: --out RUN (or --resume RUN to continue one)")
    args.resume = args.resume is not None


def cmd_train(args) -> int:
    optional_import("tensorboard", "model")
    from . import launch
    _run_directory(args)
    _check_device(args)
    model_cfg, train_cfg = _configs(args)
    job = launch.Job(args.data, args.manifest, args.out, args.resume, args.device, model_cfg, train_cfg,
                     progress=not args.no_progress, started=args.started, threads=args.threads)
    entry = launch.run(job, args.nproc)
    if entry:
        print(f"step {entry['step']}: loss {entry['loss']:.4f}, PSNR {entry['psnr_dense']:.2f} dB; "
              f"checkpoint in {Path(args.out) / 'checkpoint.pt'}, log in {Path(args.out) / 'train.log'}")
    return 0


# -- infer ------------------------------------------------------------------------------------------------------
def cmd_infer(args) -> int:
    optional_import("cv2", "faces")
    from . import infer
    from .checkpoints import load_model
    from .photos import load_image, prepare_photo
    if not (args.out or args.turntable or args.views):
        raise UserError("nothing to write: give --out, --turntable and/or --views")
    _check_device(args)
    model = load_model(args.ckpt, args.device, **given(args, ModelConfig, only=PATH_FIELDS))
    try:
        if args.no_crop:
            image, _ = load_image(args.photo)
        else:
            image, info = prepare_photo(args.photo, CROP_SIZE, pick=args.pick)
            print(f"face found: {info['n_faces']} in the photo, eyes {info['face_px']:.0f} px apart; head crop "
                  f"{CROP_SIZE} px")
    except ImportError as e:
        raise UserError(str(e)) from None
    report = infer.run(model, image, Path(args.out) if args.out else None,
                       Path(args.turntable) if args.turntable else None, Path(args.views) if args.views else None,
                       resolution=args.resolution, frames=args.frames, prune_opacity=args.prune_opacity)
    for line in report.lines():
        print(line)
    return 0


# -- eval -------------------------------------------------------------------------------------------------------
def cmd_eval(args) -> int:
    from datagen.dataset.manifests import read_manifest
    from .checkpoints import model_from_checkpoint, read_checkpoint
    from .data import accepted_subjects
    from .evaluate import GALLERY_SUBJECTS, baselines, evaluate, write_gallery, write_report
    _check_device(args)
    manifest = read_manifest(args.manifest)
    state = read_checkpoint(args.ckpt)
    trained_on = set(state.get("data", {}).get("subjects", []))
    model = model_from_checkpoint(state, args.ckpt, args.device, **given(args, ModelConfig, only=PATH_FIELDS))
    try:
        trained = TrainConfig.from_dict(state["train_config"])
    except (TypeError, ValueError) as e:
        raise UserError(f"{args.ckpt}: its training config does not fit this version ({e})") from None
    step = state["step"]
    del state  # a copy of the weights and the optimizer's state: not needed while evaluating
    lpips, notes = None, []
    notes.append(f"Checkpoint: step {step:,} of {trained.steps:,}; trained with --input-views {trained.input_views} "
                 f"(inputs {'within +-36 deg of the front' if trained.input_views == 'frontal' else 'from any view'}) "
                 f"and --targets {trained.targets}.")
    subjects = accepted_subjects(manifest, args.split, args.data)[:args.limit]

    seen = trained_on & {key for key, _ in subjects}
    if seen:
        notes.append(f"WARNING: {len(seen)} of the evaluated subjects were training subjects of this run "
                     f"(is {args.manifest} the manifest it was trained with?)")
    if len(subjects) < FEW_TEST_SUBJECTS:
        notes.append(f"NOTE: {plural(len(subjects), args.split + ' subject')} only: these means are mostly noise, not a "
                     f"measure of the model (hold out at least {FEW_TEST_SUBJECTS} to compare runs)")
    if args.lpips_backbone or args.lpips_lin:
        from .metrics import load_lpips
        lpips = load_lpips(args.lpips_backbone, args.lpips_lin, net=args.lpips_net or TrainConfig.lpips_net)
        lpips = lpips.to(args.device)
    else:
        notes.append("LPIPS: not computed (no --lpips-backbone/--lpips-lin weights given).")
    faces = None
    if not args.no_faces:
        try:
            face_tools = optional_import("datagen.faces", "faces", "CSIM/APD")
            face_tools.check_dlib()
            faces = face_tools
        except ImportError as e:
            notes.append(f"CSIM/APD: not computed ({e}).")
    if faces is not None:
        notes.append("CSIM: cosine similarity of dlib ResNet face embeddings (not ArcFace). APD: mean absolute "
                     "yaw/pitch/roll difference in degrees from a 68-landmark PnP head-pose estimate. CSIM counts the "
                     "front views whose target has a face dlib finds (the render is read at the target's face box); "
                     "APD counts the views where a face is found in both, which blurry renders often miss.")
    options = dict(resolution=args.resolution, lpips=lpips, limit=args.limit)
    pictures = []
    result = evaluate(model, args.data, manifest, args.split, faces=faces, gallery=pictures,
                      gallery_subjects=GALLERY_SUBJECTS if args.gallery is None else args.gallery, **options)
    if not args.no_baselines:
        result["baselines"] = baselines(model, trained.seed, args.data, manifest, args.split, **options)
    out = Path(args.out) if args.out else Path(args.ckpt if Path(args.ckpt).is_dir() else Path(args.ckpt).parent) / \
        f"eval-{args.split}"
    written = []
    if pictures:
        out.mkdir(parents=True, exist_ok=True)
        written.append(write_gallery(pictures, out / "gallery.png"))
        notes.append(f"![{plural(len(pictures), 'subject')}: the input, ours and the truth from the front, left, back "
                     "and right](gallery.png)")
    if args.renders:
        from .renders import write_reconstructions
        written.append(write_reconstructions(model, args.data, subjects, args.renders))
    md, js = write_report(result, out, f"PanoLAM evaluation: {args.split} split of {args.data}", notes)
    print(md.read_text())
    print("wrote " + ", ".join(str(p) for p in [md, js, *written]))
    return 0


def main(argv=None) -> int:
    started = time.monotonic()
    parser = build_parser()
    args = parser.parse_args(argv)
    args.started = started
    commands = {"train": cmd_train, "infer": cmd_infer, "eval": cmd_eval}
    return run_command("panolam", commands, args, INTERRUPTED[args.command], parser)


if __name__ == "__main__":
    sys.exit(main())
