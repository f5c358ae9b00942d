"""The panolam command line's structure: options generated from the configs, fast help, no import
cycles, `python -m panolam`; the time limit's prediction; all-or-nothing outputs of `infer`."""
from __future__ import annotations

import dataclasses
import errno
import os
import subprocess
import sys

import pytest

from panolam import cli
from panolam.config import ModelConfig, TrainConfig
from panolam.infer import write_all
from datagen.command_line import flag, option_fields, unit_interval


def _fresh(code: str) -> str:
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return r.stdout.strip()


def test_help_and_usage_errors_import_no_torch():
    assert _fresh("import sys; from panolam.cli import build_parser; build_parser().format_help(); "
                  "print('torch' in sys.modules)") == "False"
    r = subprocess.run([sys.executable, "-m", "panolam", "train", "--steps", "0"], capture_output=True, text=True)
    assert r.returncode == 2 and "--steps: must be at least 1" in r.stderr


def test_training_code_is_imported_only_by_training():
    """infer and eval load checkpoints without the trainer; the trainer does not import the command line."""
    assert _fresh("import sys, panolam.infer, panolam.evaluate, panolam.checkpoints; "
                  "print('panolam.train' in sys.modules, 'panolam.cli' in sys.modules)") == "False False"
    assert _fresh("import sys, panolam.train, panolam.launch; print('panolam.cli' in sys.modules)") == "False"


def test_python_dash_m_panolam_is_the_command():
    r = subprocess.run([sys.executable, "-m", "panolam", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and all(c in r.stdout for c in ("train", "infer", "eval"))


def _example(f: dataclasses.Field):
    """A command-line value for field f that differs from its default, and the value it parses to."""
    if f.metadata["choices"]:
        value = next(c for c in f.metadata["choices"] if c != f.default)
        return [value], value
    if f.metadata["nargs"] == 2:
        return ["0.5", "0.75"], (0.5, 0.75)
    if f.metadata["parse"] is unit_interval:
        return ["0.5"], 0.5
    if f.metadata["parse"] is None:
        return ["some/file"], "some/file"
    value = (f.default or 1) + 3
    return [str(value)], value


def test_every_training_setting_is_an_option_with_its_help(capsys, monkeypatch):
    fields = option_fields(TrainConfig)
    assert {f.name for f in fields} == {f.name for f in dataclasses.fields(TrainConfig)}
    argv = ["train", "--data", "D", "--manifest", "M", "--out", "O"]
    expected = {}
    for f in fields:
        words, value = _example(f)
        argv += [flag(f), *words]
        expected[f.name] = value
    args = cli.build_parser().parse_args(argv)
    _, train_cfg = cli._configs(args)
    assert train_cfg == TrainConfig(**expected)
    monkeypatch.setenv("COLUMNS", "1000")  # no wrapping inside the help texts
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for f in fields:
        assert f"{flag(f)} " in text and " ".join(f.metadata["help"].split()) in text, f.name
    paths = [f.name for f in option_fields(ModelConfig)]
    assert paths == ["encoder_weights", "template", "spherehead_checkpoint"]


@pytest.mark.parametrize("argv, message", [
    (["--betas", "0.9", "1.5"], "--betas: must be at least 0 and below 1"),
    (["--lr", "inf"], "--lr: must be a finite number above 0"),
    (["--lambda-mask", "-1"], "--lambda-mask: must be a finite number of at least 0"),
    (["--lpips-net", "resnet"], "invalid choice"),
])
def test_bad_training_settings_are_one_line(argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        cli.build_parser().parse_args(["train", "--data", "D", "--manifest", "M", *argv])
    err = capsys.readouterr().err
    assert e.value.code == 2 and message in err and len(err.strip().splitlines()) == 1, err


def test_resume_refuses_a_change_of_the_objective_and_takes_new_file_locations(tmp_path):
    import torch
    from panolam.checkpoints import save_checkpoint
    from panolam.config import preset
    from panolam.model import PanoLAM
    from tests.test_model import SMALL
    model_cfg = preset("tiny", **SMALL)
    model = PanoLAM(model_cfg)
    opt = torch.optim.Adam(model.parameters())
    save_checkpoint(tmp_path, model, opt, torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 1.0), 0, model_cfg,
                    TrainConfig(steps=7), [])
    base = ["train", "--data", "D", "--manifest", "M", "--resume", str(tmp_path)]

    def configs(*extra):
        args = cli.build_parser().parse_args(base + list(extra))
        cli._run_directory(args)
        return cli._configs(args)

    for extra, message in ((["--lambda-mask", "2"], "--lambda-mask 2 differs from this run's 1"),
                           (["--betas", "0.8", "0.9"], "--betas 0.8 0.9 differs from this run's 0.9 0.95"),
                           (["--steps", "8"], "--steps 8 differs from this run's 7")):
        with pytest.raises(cli.UserError, match=message):
            configs(*extra)
    m, t = configs("--steps", "7", "--checkpoint-every", "3", "--template", "moved/flame.pkl")
    assert t.steps == 7 and t.checkpoint_every == 3 and m.template == "moved/flame.pkl"


def test_time_limit_stops_before_a_step_that_would_overrun(monkeypatch):
    from panolam import train as train_module
    now = [100.0]
    monkeypatch.setattr(train_module.time, "monotonic", lambda: now[0])
    clock = train_module._Clock(started=95.0, limit_s=20.0)  # the command started 5 s before the loop
    decisions = []
    for step_s in (4.0, 3.0, 3.0, 3.0):
        now[0] += step_s
        decisions.append(clock.next_step_overruns())
    # ends at 104 (+4 predicted: 108 <= 115), 107 (111), 110 (114), 113 (+4 = 117 > 115): stop after the 4th
    assert decisions == [False, False, False, True]
    now[0] = 100.0
    clock = train_module._Clock(started=100.0, limit_s=20.0)
    with clock.checkpoint():
        now[0] += 6.0  # a slow checkpoint write counts too
    now[0] += 3.0
    assert clock.next_step_overruns() is False  # a 3 s step (the write apart): 109 + 3 + 6 <= 120
    now[0] += 3.0
    assert clock.next_step_overruns() is True   # at 112: 112 + 3 + 6 > 120
    assert train_module._Clock(0.0, None).next_step_overruns() is False


# -- all-or-nothing outputs -----------------------------------------------------------------------------------
def _outputs(root):
    return {root / "head.ply": b"ply", root / "views" / "front.png": b"png", root / "views" / "back.png": b"png2"}


def test_outputs_are_all_or_nothing(tmp_path):
    write_all(_outputs(tmp_path / "ok"))
    assert sorted(p.name for p in (tmp_path / "ok").rglob("*")) == ["back.png", "front.png", "head.ply", "views"]
    # a path under a regular file: nothing of the set is left
    (tmp_path / "file").write_bytes(b"x")
    outputs = {tmp_path / "a" / "head.ply": b"ply", tmp_path / "file" / "views" / "front.png": b"png"}
    with pytest.raises(cli.UserError, match=f"cannot write {tmp_path / 'file' / 'views' / 'front.png'}"):
        write_all(outputs)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "ok"]


@pytest.mark.parametrize("error", [OSError(errno.ENOSPC, "No space left on device"),
                                   PermissionError(errno.EACCES, "Permission denied")])
def test_a_failure_on_the_last_output_is_one_line_and_removes_the_first(error, tmp_path, monkeypatch):
    """A full disk or a refused permission (as any user, root included) on back.png: nothing is left."""
    import datagen.files as files

    def refused_for_back(path, mode="r", *a, **k):
        if "back.png" in str(path):
            raise type(error)(error.errno, error.strerror, str(path))
        return open(path, mode, *a, **k)
    monkeypatch.setattr(files, "open", refused_for_back, raising=False)
    with pytest.raises(cli.UserError, match=f"cannot write .*back.png: {error.strerror}"):
        write_all(_outputs(tmp_path / "out"))
    assert not (tmp_path / "out").exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_folder_is_one_line(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        with pytest.raises(cli.UserError, match=f"cannot write {folder / 'head.ply'}: Permission denied"):
            write_all({folder / "head.ply": b"ply"})
    finally:
        folder.chmod(0o755)
    assert list(folder.iterdir()) == []


@pytest.mark.parametrize("device, message", [("cuda:x", "unknown device 'cuda:x'; use cpu, cuda, cuda:N or auto"),
                                             ("tpu", "unknown device 'tpu'")])
@pytest.mark.parametrize("command", ["train", "infer", "eval"])
def test_an_unknown_device_is_one_line(command, device, message, capsys):
    argv = {"train": ["train", "--data", "D", "--manifest", "M", "--out", "O"],
            "infer": ["infer", "photo.png", "--ckpt", "C", "--out", "h.ply"],
            "eval": ["eval", "--data", "D", "--manifest", "M", "--ckpt", "C"]}[command]
    assert cli.main(argv + ["--device", device]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"panolam {command}: error: {message}") and err.count("\n") == 1, err


@pytest.mark.parametrize("error, line", [
    (PermissionError(errno.EACCES, "Permission denied", "/runs/t1/train.log"), "/runs/t1/train.log: Permission denied"),
    (OSError(errno.ENOSPC, "No space left on device", "/runs/t1/checkpoint.pt"), "disk full (/runs/t1/checkpoint.pt)"),
    (NotADirectoryError(errno.ENOTDIR, "Not a directory", "/a/file/views"), "/a/file/views: Not a directory"),
])
def test_os_errors_naming_a_file_are_one_line(error, line, capsys):
    from types import SimpleNamespace
    from datagen.command_line import run_command

    def command(args):
        raise error
    assert run_command("panolam", {"train": command}, SimpleNamespace(command="train"), "") == 2
    assert capsys.readouterr().err == f"panolam train: error: {line}\n"
    with pytest.raises(OSError):  # an OSError about no file is a bug: its traceback stays
        run_command("panolam", {"train": lambda args: (_ for _ in ()).throw(OSError("socket"))},
                    SimpleNamespace(command="train"), "")


def test_eval_report_counts_faces_in_words_and_gives_each_note_a_paragraph(tmp_path):
    from panolam.evaluate import summarize, write_report

    result = summarize([], [], [0.1], [0.01])
    for faces, shown in ((1, "(1 face)"), (2, "(2 faces)")):
        result.update(csim_between_subjects=0.5, csim_between_subjects_faces=faces)
        md, _ = write_report(result, tmp_path, "t", ["NOTE: few subjects", "LPIPS: not computed"])
        text = md.read_text()
        assert shown in text and text.endswith("\n\nNOTE: few subjects\n\nLPIPS: not computed\n")
