"""The ``panolam`` command line: train on a curated manifest, reconstruct a photo, evaluate.

    panolam train --data D --manifest M --config tiny --out runs/t1 [--nproc 2]
    panolam train --data D --manifest M --resume runs/t1
    panolam infer photo.jpg --ckpt runs/t1 --out head.ply [--turntable head.mp4] [--views DIR]
    panolam eval --data D --manifest M --split test --ckpt runs/t1 [--out DIR]

``python -m panolam.train`` (e.g. under ``torchrun --nproc-per-node 2``) takes the train options.
User mistakes are one line on stderr and exit status 2.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import socket
import sys
from pathlib import Path

from datagen.errors import OneLineParser, UserError, run_command

CROP_SIZE = 512  # px of the head crop handed to the model (its encoder resizes to its own input size)
DEFAULT_CONFIG = "tiny"
# Fixed when a run starts: the learning-rate schedule and the data order depend on them.
FIXED_ON_RESUME = ("steps", "batch_size", "views_per_sample", "render_resolution", "lr", "warmup_steps", "seed")
MODEL_PATHS = (("encoder_weights", "encoder_weights"), ("template", "template"), ("spherehead", "spherehead_checkpoint"))
INTERRUPTED = {"train": "the last checkpoint is kept; rerun with --resume",
               "infer": "nothing was written", "eval": "no report was written"}


def _at_least(minimum: int):
    """argparse type: an integer of at least ``minimum``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, not {value}")
        return value
    return parse


def _number(accept, requirement: str):
    """argparse type: a real number for which ``accept`` holds (``requirement`` says which, for the error)."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not accept(value):
            raise argparse.ArgumentTypeError(f"must be {requirement}, not {text}")
        return value
    return parse


_positive = _number(lambda v: v > 0, "above 0")
_opacity = _number(lambda v: 0 <= v < 1, "at least 0 and below 1")


def _check_device(device: str) -> None:
    """UserError unless ``device`` is ``cpu`` or an available ``cuda[:N]``."""
    from datagen.device import resolve_device
    if device == "auto":
        raise UserError("--device auto: name the device (cpu, cuda or cuda:N)")
    resolve_device(device)


def _model_path_options(p, where_now: bool) -> None:
    """The weight-file options: for a new run, or where a trained run's files are now."""
    now = " (where the run's file is now)" if where_now else ""
    p.add_argument("--encoder-weights", help="DINOv2 weights (Hugging Face folder or Meta .pth)" +
                                             (now or "; needed by 'full'"))
    p.add_argument("--template", help="a FLAME model file" + (now or " (default: the embedded head template)"))
    p.add_argument("--spherehead", help="a SphereHead checkpoint whose frozen decoder renders the tri-plane branch" + now)


def _train_options(p):
    from .train import TrainConfig
    d = TrainConfig()
    p.add_argument("--data", required=True, help="dataset directory (datagen sample --out)")
    p.add_argument("--manifest", required=True, help="curated manifest (label-tool compile)")
    p.add_argument("--config", help=f"model preset, optionally with ablations (default {DEFAULT_CONFIG}): tiny, full, "
                                    "tiny+no_c2f, tiny+single_point, tiny+no_triplane")
    p.add_argument("--out", help="run directory (checkpoint, logs, TensorBoard)")
    p.add_argument("--resume", nargs="?", const="", metavar="RUN",
                   help="continue the run in RUN (default: --out) exactly where it stopped")
    p.add_argument("--steps", type=_at_least(1), help=f"optimizer steps; the cosine schedule ends there "
                                                      f"(default {d.steps})")
    p.add_argument("--batch-size", type=_at_least(1), help=f"subjects per step and process (default {d.batch_size})")
    p.add_argument("--views-per-sample", type=_at_least(2),
                   help=f"N_v: 1 input + N_v - 1 targets (default {d.views_per_sample})")
    p.add_argument("--render-resolution", type=_at_least(16),
                   help=f"px of the supervised renders (default {d.render_resolution})")
    p.add_argument("--lr", type=_positive, help=f"peak learning rate (default {d.lr:g})")
    p.add_argument("--warmup-steps", type=_at_least(0), help=f"linear warm-up steps (default {d.warmup_steps})")
    p.add_argument("--time-limit", type=_positive, dest="time_limit_s",
                   help="seconds; stop with a checkpoint after this")
    p.add_argument("--checkpoint-every", type=_at_least(1), help=f"steps (default {d.checkpoint_every})")
    p.add_argument("--workers", type=_at_least(0), dest="num_workers", help="data loader processes (default 0: in process)")
    p.add_argument("--seed", type=_at_least(0), help=f"data order and initialisation (default {d.seed})")
    p.add_argument("--lpips-backbone", help="torchvision-format AlexNet/VGG16 weights, for the LPIPS loss")
    p.add_argument("--lpips-lin", help="LPIPS linear-layer weights (alex.pth / vgg.pth)")
    p.add_argument("--lpips-net", choices=("alex", "vgg"), help="LPIPS backbone (default alex)")
    _model_path_options(p, where_now=False)
    p.add_argument("--nproc", type=_at_least(1), default=1, help="data-parallel processes on this machine")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--no-progress", action="store_true")


def build_parser() -> OneLineParser:
    parser = OneLineParser(prog="panolam", description="Train, run and evaluate the PanoLAM head reconstructor.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    _train_options(sub.add_parser("train", help="train on the accepted subjects of a manifest"))
    p = sub.add_parser("infer", help="reconstruct a head from one photo",
                       description="Reconstruct a head from one photo. The model was trained on heads over white: "
                                   "an RGBA PNG whose background is transparent is composited on white, as training "
                                   "images are; any other photo keeps its background.")
    p.add_argument("photo")
    p.add_argument("--ckpt", required=True, help="run directory or checkpoint file")
    p.add_argument("--out", help="Gaussians as a standard 3DGS .ply")
    p.add_argument("--turntable", help="360-degree turntable: .mp4 (H.264) or animated .gif")
    p.add_argument("--views", help="directory for front/left/back/right PNG views")
    p.add_argument("--resolution", type=_at_least(8), default=256, help="px of the turntable and views (default 256)")
    p.add_argument("--frames", type=_at_least(1), default=36, help="turntable frames (default 36)")
    p.add_argument("--prune-opacity", type=_opacity, default=0.02,
                   help="drop Gaussians below this opacity from the outputs (default 0.02)")
    p.add_argument("--pick", choices=("single", "largest"), default="single",
                   help="with several faces in the photo: refuse (single) or take the largest")
    p.add_argument("--no-crop", action="store_true", help="the photo is already framed like the training data")
    _model_path_options(p, where_now=True)
    p.add_argument("--device", default="cpu")
    p = sub.add_parser("eval", help="metrics on held-out subjects (front in; front/left/back/right out)")
    p.add_argument("--data", required=True, help="dataset directory")
    p.add_argument("--manifest", required=True, help="curated manifest")
    p.add_argument("--split", default="test", choices=("test", "train"))
    p.add_argument("--ckpt", required=True, help="run directory or checkpoint file")
    p.add_argument("--out", help="report directory (default: <ckpt>/eval-<split>)")
    p.add_argument("--limit", type=_at_least(1), help="evaluate at most this many subjects")
    p.add_argument("--resolution", type=_at_least(16), help="px of the compared views (default: as stored)")
    p.add_argument("--lpips-backbone")
    p.add_argument("--lpips-lin")
    p.add_argument("--lpips-net", default="alex", choices=("alex", "vgg"))
    p.add_argument("--no-faces", action="store_true", help="skip CSIM/APD (they need dlib)")
    _model_path_options(p, where_now=True)
    p.add_argument("--device", default="cpu")
    return parser


def _model_paths(args) -> dict:
    """ModelConfig fields for the weight files given on the command line."""
    return {field: getattr(args, option) for option, field in MODEL_PATHS if getattr(args, option)}


# -- train ---------------------------------------------------------------------------------------------------
def _configs(args):
    from .config import ModelConfig, preset
    from .train import TrainConfig, read_checkpoint
    given = {k: getattr(args, k) for k in (*FIXED_ON_RESUME, "time_limit_s", "checkpoint_every", "num_workers",
                                           "lpips_backbone", "lpips_lin", "lpips_net")
             if getattr(args, k, None) is not None}
    if not args.resume:
        try:
            return preset(args.config or DEFAULT_CONFIG, **_model_paths(args)), TrainConfig(**given)
        except ValueError as e:
            raise UserError(str(e)) from None
    state = read_checkpoint(args.out)
    model_cfg = ModelConfig.from_dict(state["model_config"]).replace(**_model_paths(args))
    if args.config and args.config != model_cfg.name:
        raise UserError(f"{args.out} is a {model_cfg.name!r} run; resume it without --config {args.config}")
    train_cfg = TrainConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in state["train_config"].items()})
    for k in FIXED_ON_RESUME:
        if k in given and given[k] != getattr(train_cfg, k):
            raise UserError(f"--{k.replace('_', '-')} {given[k]} differs from this run's {getattr(train_cfg, k)}: the "
                            f"schedule and data order are fixed when a run starts (start a new --out to change them)")
    return model_cfg, dataclasses.replace(train_cfg, **given)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _train_process(rank: int, world: int, port: int, args, model_cfg, train_cfg) -> None:
    """One of ``--nproc`` processes; a user mistake is one line and exit status 2, as in the parent."""
    import torch
    import torch.distributed as dist
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world))
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // world))
    cuda = args.device.startswith("cuda")
    if cuda:
        torch.cuda.set_device(rank)
    dist.init_process_group("nccl" if cuda else "gloo", rank=rank, world_size=world)
    try:
        _run_training(args, model_cfg, train_cfg, device=f"cuda:{rank}" if cuda else "cpu")
    except UserError as e:
        print(f"panolam train: error (process {rank}): {e}", file=sys.stderr)
        sys.exit(2)
    finally:
        dist.destroy_process_group()


def _run_training(args, model_cfg, train_cfg, device):
    from .train import train
    return train(args.data, args.manifest, model_cfg, train_cfg, args.out, resume=args.resume, device=device,
                 progress=not args.no_progress)


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
    _run_directory(args)
    _check_device(args.device)
    model_cfg, train_cfg = _configs(args)
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:  # launched by torchrun: one process per GPU (or CPU share)
        import torch
        import torch.distributed as dist
        device = args.device
        if device.startswith("cuda"):
            device = f"cuda:{int(os.environ.get('LOCAL_RANK', '0'))}"
            torch.cuda.set_device(device)
        dist.init_process_group("nccl" if device.startswith("cuda") else "gloo")
        try:
            _run_training(args, model_cfg, train_cfg, device)
        finally:
            dist.destroy_process_group()
    elif args.nproc > 1:
        import torch.multiprocessing as mp
        from .train import check_start
        # Each process checks again as it starts; checking here first makes a mistake one line, not one per process.
        check_start(args.data, args.manifest, model_cfg, train_cfg, args.out, args.resume)
        try:
            mp.spawn(_train_process, args=(args.nproc, _free_port(), args, model_cfg, train_cfg), nprocs=args.nproc)
        except mp.ProcessExitedException as e:
            if e.exit_code == 2:  # the process has said why
                return 2
            raise
    else:
        entry = _run_training(args, model_cfg, train_cfg, args.device)
        if entry:
            print(f"step {entry['step']}: loss {entry['loss']:.4f}, PSNR {entry['psnr_dense']:.2f} dB; "
                  f"checkpoint in {args.out}")
    return 0


# -- infer ------------------------------------------------------------------------------------------------------
def cmd_infer(args) -> int:
    from . import infer
    from .faces import load_image, prepare_photo
    from .train import load_model
    if not (args.out or args.turntable or args.views):
        raise UserError("nothing to write: give --out, --turntable and/or --views")
    _check_device(args.device)
    model = load_model(args.ckpt, args.device, **_model_paths(args))
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
    from datagen.manifests import read_manifest
    from .data import accepted_subjects
    from .evaluate import evaluate, write_report
    from .train import model_from_checkpoint, read_checkpoint
    _check_device(args.device)
    manifest = read_manifest(args.manifest)
    state = read_checkpoint(args.ckpt)
    trained_on = set(state.get("data", {}).get("subjects", []))
    model = model_from_checkpoint(state, args.ckpt, args.device, **_model_paths(args))
    del state  # a copy of the weights and the optimizer's state: not needed while evaluating
    lpips, notes = None, []
    seen = trained_on & {key for key, _ in accepted_subjects(manifest, args.split, args.data)[:args.limit]}
    if seen:
        warning = (f"WARNING: {len(seen)} of the evaluated subjects were training subjects of this run "
                   f"(is {args.manifest} the manifest it was trained with?)")
        print(warning, file=sys.stderr)
        notes.append(warning)
    if args.lpips_backbone or args.lpips_lin:
        from .metrics import load_lpips
        lpips = load_lpips(args.lpips_backbone, args.lpips_lin, net=args.lpips_net).to(args.device)
    else:
        notes.append("LPIPS: not computed (no --lpips-backbone/--lpips-lin weights given).")
    faces = None
    if not args.no_faces:
        from . import faces as face_tools
        try:
            face_tools.check_dlib()
            faces = face_tools
        except ImportError as e:
            notes.append(f"CSIM/APD: not computed ({e}).")
    if faces is not None:
        notes.append("CSIM: cosine similarity of dlib ResNet face embeddings (not ArcFace). APD: mean absolute "
                     "yaw/pitch/roll difference in degrees from a 68-landmark PnP head-pose estimate. CSIM counts the "
                     "front views whose target has a face dlib finds (the render is read at the target's face box); "
                     "APD counts the views where a face is found in both, which blurry renders often miss.")
    result = evaluate(model, args.data, manifest, args.split, resolution=args.resolution,
                      lpips=lpips, faces=faces, limit=args.limit)
    out = Path(args.out) if args.out else Path(args.ckpt if Path(args.ckpt).is_dir() else Path(args.ckpt).parent) / \
        f"eval-{args.split}"
    md, _ = write_report(result, out, f"PanoLAM evaluation: {args.split} split of {args.data}", notes)
    print(md.read_text())
    return 0


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    commands = {"train": cmd_train, "infer": cmd_infer, "eval": cmd_eval}
    return run_command("panolam", commands, args, INTERRUPTED[args.command])


if __name__ == "__main__":
    sys.exit(main())
