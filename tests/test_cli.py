import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from datagen.cli import main

ROOT = Path(__file__).resolve().parents[1]


def run(argv, capsys):
    """Run the CLI in-process; returns (exit code, stdout, stderr)."""
    try:
        code = main(argv)
    except SystemExit as e:  # argparse's own errors
        code = e.code
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("argv, message", [
    (["sample", "--out", "{tmp}/x", "--gan", "stylegan9"], "invalid choice: 'stylegan9'"),
    (["sample", "--out", "{tmp}/x", "--gan", "eg3d"], "needs --checkpoint PATH: EG3D checkpoints"),
    (["sample", "--out", "{tmp}/x", "--gan", "spherehead", "--checkpoint", "{tmp}/none.pkl"], "checkpoint not found"),
    (["sample", "--out", "{tmp}/x", "--gan", "eg3d", "--checkpoint", "{tmp}/afile"], "not a readable generator"),
    (["sample", "--out", "{tmp}/x", "--save-planes", "32"], "--save-planes: only for the GAN generators"),
    (["sample", "--out", "{tmp}/x", "--subject", "2"], "unrecognized arguments: --subject 2 (did you mean --subjects?)"),
    (["sample", "--out", "{tmp}/x", "--sub", "2"], "unrecognized arguments: --sub 2"),
    (["sample", "--out", "{tmp}/x", "--device", "cpu"], "--device: only for the GAN generators"),
    (["sample", "--out", "{tmp}/x", "--gan", "eg3d", "--checkpoint", "{tmp}/afile", "--truncation", "3"],
     "--truncation must be between 0 and 2"),
    (["sample", "--out", "{tmp}/x", "--shape-level", "5"], "--shape-level: only with --save-shape"),
    (["sample", "--out", "{tmp}/x", "--gan", "procedural", "--background", "own"], "white, black, grey"),
    (["sample", "--out", "{tmp}/x", "--protocol", "sideways"], "invalid choice: 'sideways'"),
    (["sample", "--out", "{tmp}/x", "--subjects", "0"], "--subjects must be at least 1"),
    (["sample", "--out", "{tmp}/x", "--subjects", "many"], "invalid int value"),
    (["sample", "--out", "{tmp}/x", "--resolution", "8"], "--resolution must be between"),
    (["sample", "--out", "{tmp}/x", "--shard-index", "2", "--num-shards", "2"], "--shard-index"),
    (["sample", "--out", "{tmp}/x", "--workers", "0"], "--workers"),
    (["sample", "--out", "{tmp}/x", "--defect-rate", "1.5"], "--defect-rate"),
    (["sample", "--out", "{tmp}/x", "--defect-types", "janus,mustache"], "--defect-types: unknown mustache"),
    (["sample", "--out", "{tmp}/x", "--defect-severity", "0.8,0.2"], "--defect-severity must be LO,HI"),
    (["sample", "--out", "{tmp}/x", "--defect-severity", "high"], "--defect-severity must be LO,HI"),
    (["sample", "--out", "{tmp}/x", "--background", "purple"], "white, black, grey"),
    (["sample", "--out", "{tmp}/x", "--truncation", "-1"], "--truncation: only for the GAN generators"),
    (["sample", "--out", "{tmp}/x", "--gan", "eg3d", "--checkpoint", "{tmp}/afile", "--truncation-cutoff", "-2"],
     "--truncation-cutoff must be at least 0"),
    (["sample", "--out", "{tmp}/afile/sub"], "cannot write"),
    (["sample", "--out", "/proc/forbidden"], "cannot write"),
    (["verify", "{tmp}/nothing-here"], "no dataset index"),
    (["preview", "{tmp}/nothing-here", "--subject", "1", "--out", "{tmp}/p.png"], "no dataset index"),
])
def test_user_mistakes_get_one_line_and_nonzero_exit(argv, message, tmp_path, capsys):
    (tmp_path / "afile").write_text("not a folder")
    code, out, err = run([a.format(tmp=tmp_path) for a in argv], capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], err
    assert "Traceback" not in err


def test_preview_unknown_subject(tiny_dataset, tmp_path, capsys):
    code, _, err = run(["preview", str(tiny_dataset), "--subject", "99", "--out", str(tmp_path / "p.png")], capsys)
    assert code == 2 and "no subject subj00000099" in err
    code, _, err = run(["preview", str(tiny_dataset), "--subject", "three", "--out", str(tmp_path / "p.png")], capsys)
    assert code == 2 and "--subject" in err


def test_preview_writes_a_labelled_contact_sheet(tiny_dataset, tmp_path, capsys):
    out = tmp_path / "sheet.png"
    code, stdout, _ = run(["preview", str(tiny_dataset), "--subject", "1", "--out", str(out), "--columns", "2"], capsys)
    assert code == 0 and out.exists()
    im = np.asarray(Image.open(out))
    # 4 views of 32 px are upscaled to >= 160 px tiles in a 2x2 grid, with labels and a title.
    assert im.shape[1] == 2 * 160 and im.shape[0] > 2 * 160
    assert im.std() > 20  # not blank


def test_preview_on_a_full_disk_is_one_line_and_leaves_no_temporary(tiny_dataset, tmp_path, capsys, monkeypatch):
    import errno

    from PIL import Image as PILImage

    def full(self, fp, format=None, **params):
        fp.write(b"\x89PNG")
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(PILImage.Image, "save", full)
    out = tmp_path / "sheets" / "sheet.png"
    code, _, err = run(["preview", str(tiny_dataset), "--subject", "1", "--out", str(out)], capsys)
    assert code == 2 and err.strip().endswith(f"cannot write {out}: No space left on device"), err
    assert list(out.parent.iterdir()) == []


def test_preview_with_mask_and_depth(tiny_dataset, tmp_path, capsys):
    out = tmp_path / "sheet.png"
    code, _, _ = run(["preview", str(tiny_dataset), "--subject", "subj00000000", "--out", str(out), "--mask-depth"],
                     capsys)
    assert code == 0 and Image.open(out).size[0] == 4 * 3 * 160


def test_info_and_verify(tiny_dataset, capsys):
    code, out, _ = run(["info", str(tiny_dataset), "--json"], capsys)
    info = json.loads(out)
    assert code == 0 and info["subjects"] == 3 and info["shards_complete"] == 2 and info["protocol"] == "360"
    code, out, _ = run(["verify", str(tiny_dataset), "--quiet"], capsys)
    assert code == 0 and "OK: 2/2 shards" in out


def test_verify_failure_exits_nonzero(tiny_dataset, tmp_path, capsys):
    from tests.test_dataset import copy_dataset

    ds = copy_dataset(tiny_dataset, tmp_path / "ds")
    (ds / "shard-000000.json").unlink()
    code, out, _ = run(["verify", str(ds), "--quiet"], capsys)
    assert code == 1 and "FAILED" in out and "shard-000000.tar: incomplete" in out


def test_console_scripts_exist():
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-m", "panolam.cli", "--help"], capture_output=True, text=True, env=env)
    assert r.returncode == 0 and all(c in r.stdout for c in ("train", "infer", "eval"))
    r = subprocess.run([sys.executable, "-m", "labeling_tool.cli", "--help"], capture_output=True, text=True, env=env)
    assert r.returncode == 0 and "compile" in r.stdout
    r = subprocess.run([sys.executable, "-m", "datagen.cli", "--help"], capture_output=True, text=True, env=env)
    assert r.returncode == 0 and "sample" in r.stdout


def test_disk_full_is_one_line_and_leaves_nothing_complete(tmp_path, capsys, monkeypatch):
    import errno

    import datagen.pipeline as pipeline

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pipeline, "encode_subject", full)
    out = tmp_path / "full"
    code, _, err = run(["sample", "--out", str(out), "--subjects", "2", "--resolution", "16", "--views", "1",
                        "--quiet"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "disk full" in err and "--resume" in err
    assert sorted(p.name for p in out.iterdir()) == [".datagen.lock", "index.json"]  # no shard, no temporary


@pytest.fixture
def fast_cli(monkeypatch):
    """`datagen sample` with the tests' fast procedural grid (tiny_spec's), so its arguments below name tiny_dataset."""
    import datagen.cli as cli
    from tests.conftest import FAST_PROCEDURAL

    monkeypatch.setattr(cli, "generator_options", lambda args, given=cli.generator_options: {
        **FAST_PROCEDURAL, **given(args)})
    return ["sample", "--protocol", "360", "--subjects", "3", "--resolution", "32", "--views", "4", "--seed", "7",
            "--shard-size", "2", "--quiet", "--out"]


def test_rerunning_a_complete_job_says_so_and_writes_nothing(tiny_dataset, fast_cli, capsys):
    before = {p: p.stat().st_mtime_ns for p in tiny_dataset.rglob("*")}
    code, out, err = run(fast_cli + [str(tiny_dataset)], capsys)
    assert (code, out, err) == (0, f"{tiny_dataset}: complete (2 of 2 shards, 3 subjects); nothing to do\n", "")
    code, out, _ = run(fast_cli + [str(tiny_dataset), "--shard-index", "1", "--num-shards", "2"], capsys)
    assert code == 0 and "complete (this job's 1 of 2 shards, 1 subject)" in out
    assert {p: p.stat().st_mtime_ns for p in tiny_dataset.rglob("*")} == before


def test_rerunning_another_or_a_partly_done_job_is_refused(tiny_dataset, fast_cli, tmp_path, capsys):
    from tests.test_dataset import copy_dataset

    code, _, err = run(fast_cli + [str(tiny_dataset), "--seed", "8"], capsys)
    assert code == 2 and "already holds a dataset made with other settings (seed)" in err
    partly = copy_dataset(tiny_dataset, tmp_path / "ds")
    (partly / "shard-000001.json").unlink()
    code, _, err = run(fast_cli + [str(partly)], capsys)
    assert code == 2 and "already has 1 complete shard(s) of this job; pass --resume" in err


def test_info_prints_readable_lines(tiny_dataset, capsys):
    from datagen.text import byte_size, readable

    code, out, _ = run(["info", str(tiny_dataset)], capsys)
    lines = out.splitlines()
    assert code == 0 and "subjects: 3" in lines and "shards_complete: 2" in lines and "{" not in out
    assert any(line.startswith("size: ") and line.endswith(" KiB") for line in lines)
    assert lines[lines.index("software:") + 1].startswith("  ")
    assert [byte_size(n) for n in (512, 27023360, 3 << 30)] == ["512 B", "25.8 MiB", "3.0 GiB"]
    assert readable({"subjects": 12345, "seed": 1000, "software": {"torch": "2.13.0"}}) == \
        ["subjects: 12,345", "seed: 1000", "software:", "  torch: 2.13.0"]


def _cli_parsers():
    from labeling_tool.cli import build_parser as label_tool
    from panolam.cli import build_parser as panolam

    from datagen.cli import build_parser as datagen
    return {"datagen": datagen, "label-tool": label_tool, "panolam": panolam}


@pytest.mark.parametrize("command", ["datagen", "label-tool", "panolam"])
def test_every_option_of_every_subcommand_has_help(command):
    import argparse

    parser = _cli_parsers()[command]()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    missing = [f"{name} {a.option_strings[0] if a.option_strings else a.dest}"
               for name, sub in commands.items() for a in sub._actions if not a.help]
    assert missing == []


def test_the_library_names_settings_and_the_command_line_names_flags(tmp_path, capsys):
    from datagen.errors import SettingError
    from datagen.generators.settings import GANConfig, ProceduralConfig
    from datagen.job import JobSpec

    with pytest.raises(SettingError) as bad:
        JobSpec(out=str(tmp_path), shard_size=0).check()
    assert str(bad.value) == "shard_size must be at least 1"
    with pytest.raises(SettingError, match=r"^defect_severity must be LO,HI"):
        ProceduralConfig(defect_severity=(0.9, 0.1))
    with pytest.raises(SettingError, match=r"^truncation_psi must be between 0 and 2"):
        GANConfig(truncation_psi=3.0)
    # The command line words the same errors with its own flags (--truncation for truncation_psi).
    code, _, err = run(["sample", "--out", str(tmp_path / "x"), "--shard-size", "0"], capsys)
    assert code == 2 and err.strip() == "datagen sample: error: --shard-size must be at least 1"
    assert not (tmp_path / "x").exists()


def test_generator_settings_given_on_the_command_line_reach_the_generator(monkeypatch, tmp_path):
    from datagen import pipeline

    seen = []
    monkeypatch.setattr(pipeline, "run_sample", lambda spec, **kw: seen.append(spec) or
                        {"shards_written": 1, "shards_skipped": 0, "subjects": 1, "images": 1, "seconds": 1.0})
    assert main(["sample", "--out", str(tmp_path / "x"), "--subjects", "3", "--defect-types", "janus,haze",
                 "--defect-severity", "0.2,0.5", "--background", "grey", "--quiet"]) == 0
    spec = seen[0]
    assert (spec.subjects, spec.resolution) == (3, 128)
    assert spec.generator_options == {"defect_types": ("janus", "haze"), "defect_severity": (0.2, 0.5),
                                      "background": (0.5, 0.5, 0.5)}


def test_a_reader_that_stops_reading_gets_no_traceback(tiny_dataset):
    """``datagen verify DIR | head -0``: the output has nowhere to go; the command ends as SIGPIPE would."""
    proc = subprocess.Popen([sys.executable, "-m", "datagen.cli", "verify", str(tiny_dataset), "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # the reader is gone before the command writes its verdict
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141 and "Traceback" not in err, err
