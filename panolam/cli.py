"""The ``panolam`` command line: train on a curated manifest, reconstruct a photo, evaluate.

    panolam train --data D --manifest M --config tiny --out runs/t1 [--resume] [--nproc 2]
    panolam infer photo.jpg --ckpt runs/t1 --out head.ply [--turntable head.mp4] [--views DIR]
    panolam eval --data D --manifest M --split test --ckpt runs/t1 [--out DIR]

``python -m panolam.train`` (e.g. under ``torchrun --nproc-per-node 2``) takes the train options.
User mistakes are one line on stderr and exit status 2.
"""
from __future__ import annotations

import dataclasses
import os
import socket
import sys
from pathlib import Path

from datagen.errors import OneLineParser, UserError, run_command

CROP_SIZE = 512  # px of the head crop handed to the model (its encoder resizes to its own input size)


def _train_options(p):
    p.add_argument("--data", required=True, help="dataset directory (datagen sample --out)")
    p.add_argument("--manifest", required=True, help="curated manifest (label-tool compile)")
    p.add_argument("--config", default="tiny", help="model preset, optionally with ablations: tiny, full, tiny+no_c2f, "
                                                    "tiny+single_point, tiny+no_triplane")
    p.add_argument("--out", required=True, help="run directory (checkpoint, logs, TensorBoard)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out exactly where it stopped")
    p.add_argument("--steps", type=int)
    p.add_argument("--batch-size", type=int, help="subjects per step and process")
    p.add_argument("--render-resolution", type=int)
    p.add_argument("--lr", type=float)
    p.add_argument("--time-limit", type=float, dest="time_limit_s", help="seconds; stop with a checkpoint after this")
    p.add_argument("--checkpoint-every", type=int)
    p.add_argument("--workers", type=int, dest="num_workers", help="data loader processes")
    p.add_argument("--seed", type=int)
    p.add_argument("--lpips-backbone", help="torchvision-format AlexNet/VGG16 weights, for the LPIPS loss")
    p.add_argument("--lpips-lin", help="LPIPS linear-layer weights (alex.pth / vgg.pth)")
    p.add_argument("--encoder-weights", help="DINOv2 weights (Hugging Face folder or Meta .pth); needed by 'full'")
    p.add_argument("--template", help="a FLAME model file (default: the embedded head template)")
    p.add_argument("--spherehead", help="a SphereHead checkpoint whose frozen decoder renders the tri-plane branch")
    p.add_argument("--nproc", type=int, default=1, help="data-parallel processes on this machine")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--no-progress", action="store_true")


def build_parser() -> OneLineParser:
    parser = OneLineParser(prog="panolam", description="Train, run and evaluate the PanoLAM head reconstructor.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    _train_options(sub.add_parser("train", help="train on the accepted subjects of a manifest"))
    p = sub.add_parser("infer", help="reconstruct a head from one photo")
    p.add_argument("photo")
    p.add_argument("--ckpt", required=True, help="run directory or checkpoint file")
    p.add_argument("--out", help="Gaussians as a standard 3DGS .ply")
    p.add_argument("--turntable", help="360-degree turntable: .mp4 (H.264) or animated .gif")
    p.add_argument("--views", help="directory for front/left/back/right PNG views")
    p.add_argument("--resolution", type=int, default=256)
    p.add_argument("--frames", type=int, default=36)
    p.add_argument("--prune-opacity", type=float, default=0.02)
    p.add_argument("--pick", choices=("single", "largest"), default="single",
                   help="with several faces in the photo: refuse (single) or take the largest")
    p.add_argument("--no-crop", action="store_true", help="the photo is already framed like the training data")
    p.add_argument("--device", default="cpu")
    p = sub.add_parser("eval", help="metrics on held-out subjects (front in; front/left/back/right out)")
    p.add_argument("--data", required=True)
    p.add_argument("--manifest", required=True)
    p.add_argument("--split", default="test")
    p.add_argument("--ckpt", required=True)
    p.add_argument("--out", help="report directory (default: <ckpt>/eval-<split>)")
    p.add_argument("--limit", type=int, help="evaluate at most this many subjects")
    p.add_argument("--lpips-backbone")
    p.add_argument("--lpips-lin")
    p.add_argument("--lpips-net", default="alex", choices=("alex", "vgg"))
    p.add_argument("--no-faces", action="store_true", help="skip CSIM/APD (they need dlib)")
    p.add_argument("--device", default="cpu")
    return parser


# -- train ---------------------------------------------------------------------------------------------------
def _configs(args):
    from .config import preset
    from .train import TrainConfig, read_checkpoint
    overrides = {k: getattr(args, k) for k in ("steps", "batch_size", "render_resolution", "lr", "time_limit_s",
                                               "checkpoint_every", "num_workers", "seed")
                 if getattr(args, k, None) is not None}
    lpips = {k: v for k, v in (("lpips_backbone", args.lpips_backbone), ("lpips_lin", args.lpips_lin)) if v}
    if args.resume:
        from .config import ModelConfig
        state = read_checkpoint(args.out)
        model_cfg = ModelConfig.from_dict(state["model_config"])
        train_cfg = dataclasses.replace(TrainConfig(**{k: tuple(v) if isinstance(v, list) else v
                                                       for k, v in state["train_config"].items()}), **overrides)
        return model_cfg, train_cfg
    model_overrides = {k: v for k, v in (("encoder_weights", args.encoder_weights), ("template", args.template),
                                         ("spherehead_checkpoint", args.spherehead)) if v}
    try:
        model_cfg = preset(args.config, **model_overrides)
    except ValueError as e:
        raise UserError(str(e)) from None
    return model_cfg, TrainConfig(**overrides, **lpips)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _train_process(rank: int, world: int, port: int, args, model_cfg, train_cfg) -> None:
    import torch
    import torch.distributed as dist
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world))
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // world))
    dist.init_process_group("nccl" if args.device.startswith("cuda") else "gloo", rank=rank, world_size=world)
    try:
        _run_training(args, model_cfg, train_cfg, device=f"cuda:{rank}" if args.device.startswith("cuda") else "cpu")
    finally:
        dist.destroy_process_group()


def _run_training(args, model_cfg, train_cfg, device):
    from .train import train
    entry = train(args.data, args.manifest, model_cfg, train_cfg, args.out, resume=args.resume, device=device,
                  progress=not args.no_progress)
    return entry


def cmd_train(args) -> int:
    model_cfg, train_cfg = _configs(args)
    world_env = int(os.environ.get("WORLD_SIZE", "1"))
    if world_env > 1:  # launched by torchrun
        import torch.distributed as dist
        dist.init_process_group("nccl" if args.device.startswith("cuda") else "gloo")
        try:
            _run_training(args, model_cfg, train_cfg, args.device)
        finally:
            dist.destroy_process_group()
    elif args.nproc > 1:
        import torch.multiprocessing as mp
        mp.spawn(_train_process, args=(args.nproc, _free_port(), args, model_cfg, train_cfg), nprocs=args.nproc)
    else:
        entry = _run_training(args, model_cfg, train_cfg, args.device)
        if entry:
            print(f"step {entry['step']}: loss {entry['loss']:.4f}, PSNR {entry['psnr_dense']:.2f} dB; "
                  f"checkpoint in {args.out}")
    return 0


# -- infer ------------------------------------------------------------------------------------------------------
def cmd_infer(args) -> int:
    from . import infer
    from .faces import FaceError, load_image, prepare_photo
    from .train import load_model
    if not (args.out or args.turntable or args.views):
        raise UserError("nothing to write: give --out, --turntable and/or --views")
    model = load_model(args.ckpt, args.device)
    try:
        if args.no_crop:
            image, _ = load_image(args.photo)
        else:
            image, info = prepare_photo(args.photo, CROP_SIZE, pick=args.pick)
            print(f"face found: {info['n_faces']} in the photo, eyes {info['face_px']:.0f} px apart; head crop "
                  f"{CROP_SIZE} px")
    except (FaceError, ImportError) as e:
        raise UserError(str(e)) from None
    report = infer.run(model, image, Path(args.out) if args.out else None,
                       Path(args.turntable) if args.turntable else None, Path(args.views) if args.views else None,
                       resolution=args.resolution, frames=args.frames, prune_opacity=args.prune_opacity)
    for line in report.lines():
        print(line)
    return 0


# -- eval -------------------------------------------------------------------------------------------------------
def cmd_eval(args) -> int:
    from labeling_tool.manifest import read_manifest
    from .evaluate import evaluate, write_report
    from .train import load_model
    model = load_model(args.ckpt, args.device)
    lpips, notes = None, []
    if args.lpips_backbone or args.lpips_lin:
        from .metrics import MetricError, load_lpips
        try:
            lpips = load_lpips(args.lpips_backbone, args.lpips_lin, net=args.lpips_net).to(args.device)
        except MetricError as e:
            raise UserError(str(e)) from None
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
                     "yaw/pitch/roll difference in degrees from a 68-landmark PnP head-pose estimate.")
    result = evaluate(model, args.data, read_manifest(args.manifest), args.split, lpips=lpips, faces=faces,
                      limit=args.limit)
    out = Path(args.out) if args.out else Path(args.ckpt if Path(args.ckpt).is_dir() else Path(args.ckpt).parent) / \
        f"eval-{args.split}"
    md, _ = write_report(result, out, f"PanoLAM evaluation: {args.split} split of {args.data}", notes)
    print(md.read_text())
    return 0


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    commands = {"train": cmd_train, "infer": cmd_infer, "eval": cmd_eval}
    return run_command("panolam", commands, args, "the last checkpoint is kept; rerun with --resume")


if __name__ == "__main__":
    sys.exit(main())
