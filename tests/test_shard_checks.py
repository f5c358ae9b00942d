"""Readers check what they read against the sidecar: a shard whose byte ranges, keys or subject names
were tampered with is refused in one line naming it by ``label-tool auto``, ``label-tool compile`` and
training's shard check, as ``datagen verify`` refuses it."""
from __future__ import annotations

import hashlib
import io
import json
import shutil
import tarfile
from pathlib import Path

import numpy as np
import pytest

import datagen.dataset.shards as shards
from datagen.errors import DatasetError
from datagen.dataset import Dataset
from datagen.dataset.shards import sidecar_path, tar_path
from datagen.verify import verify_dataset
from labeling_tool.cli import main as label_main
from panolam.data import check_subject_shards


def _rewrite_sidecar(ds, i, edit) -> None:
    path = sidecar_path(ds, i)
    side = json.loads(path.read_text())
    edit(side)
    path.write_text(json.dumps(side, indent=1, sort_keys=True) + "\n")


def _offset_digit(side) -> None:
    key = side["subjects"][-1]
    text = str(side["offsets"][key][0])
    side["offsets"][key][0] = int(str(int(text[0]) % 9 + 1) + text[1:])  # its leading digit changed


def _key_renamed(side) -> None:
    key = side["subjects"][-1]
    side["offsets"][key.replace("subj", "subx")] = side["offsets"].pop(key)


def _rename_subject(ds, i) -> str:
    """Rename the last subject of shard ``i`` in its tar and its sidecar (same length, so the byte ranges
    stay right), with the sidecar's sha256 updated: only the dataset index still has the old name."""
    tar = tar_path(ds, i)
    old = json.loads(sidecar_path(ds, i).read_text())["subjects"][-1]
    new = old[:-1] + ("9" if old[-1] != "9" else "8")
    out = io.BytesIO()
    with tarfile.open(tar, "r:") as src, tarfile.open(fileobj=out, mode="w", format=tarfile.USTAR_FORMAT) as dst:
        for m in src:
            data = src.extractfile(m).read()
            if m.name.startswith(old + "."):
                m.name = new + m.name[len(old):]
            dst.addfile(m, io.BytesIO(data))
    tar.write_bytes(out.getvalue())

    def edit(side):
        side["subjects"][-1] = new
        side["offsets"][new] = side["offsets"].pop(old)
        side["tar_bytes"] = len(out.getvalue())
        side["tar_sha256"] = hashlib.sha256(out.getvalue()).hexdigest()
    _rewrite_sidecar(ds, i, edit)
    return new


DAMAGES = ["offset_digit", "key_renamed", "subject_renamed"]


def damage(ds, kind: str, i: int = 0) -> None:
    if kind == "subject_renamed":
        _rename_subject(ds, i)
    else:
        _rewrite_sidecar(ds, i, {"offset_digit": _offset_digit, "key_renamed": _key_renamed}[kind])


@pytest.fixture
def copy(tiny_dataset, tmp_path):
    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds)
    return ds


@pytest.mark.parametrize("kind", DAMAGES)
def test_tampered_sidecars_are_refused_by_every_reader_as_by_verify(copy, tmp_path, capsys, kind):
    assert Dataset(copy).check_shards([0, 1]) == {}  # remembered as passed before the damage
    damage(copy, kind)
    assert any("shard-000000" in p for p in verify_dataset(copy)["problems"])
    problems = Dataset(copy).check_shards([0, 1])
    assert list(problems) == [0] and "shard-000000" in problems[0]
    with pytest.raises(DatasetError, match="shard-000000"):
        check_subject_shards(copy, [("subj00000000", 0)])  # what training runs before it reads
    check_subject_shards(copy, [("subj00000002", 1)])  # the other shard is still fine
    capsys.readouterr()
    labels = tmp_path / "labels"
    labels.mkdir()
    for args in (["auto", str(copy), "--quiet"],
                 ["compile", str(copy), "--labels", str(labels), "--out", str(tmp_path / "m.json")]):
        assert label_main(args) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "shard-000000" in err, (args[0], err)
    assert not (copy / "preflags.json").exists() and not (tmp_path / "m.json").exists()


def test_a_second_check_reads_no_tar_and_a_changed_sidecar_is_checked_again(copy, monkeypatch):
    read, real_read = [], Path.read_bytes

    def read_bytes(path):  # the check reads a tar's bytes once: hashed, then walked
        if path.suffix == ".tar":
            read.append(path)
        return real_read(path)

    monkeypatch.setattr(Path, "read_bytes", read_bytes)
    (copy / shards.SHARD_CHECKS).unlink(missing_ok=True)
    assert Dataset(copy).check_shards([0, 1]) == {} and read == [tar_path(copy, 0), tar_path(copy, 1)]
    read.clear()
    assert Dataset(copy).check_shards([0, 1]) == {} and read == []
    damage(copy, "offset_digit", 0)
    assert list(Dataset(copy).check_shards([0, 1])) == [0] and read == [tar_path(copy, 0)]


def test_layout_of_a_good_tar_matches_its_sidecar(tiny_dataset):
    side = json.loads(sidecar_path(tiny_dataset, 0).read_text())
    runs = shards.tar_layout(tar_path(tiny_dataset, 0))
    assert [k for k, _, _ in runs] == side["subjects"]
    assert {k: [s, e] for k, s, e in runs} == side["offsets"]
    assert runs[0][1] == 0 and runs[0][2] == runs[1][1]


def _tar_runs_by_tarfile(path) -> list[tuple]:
    """The same runs from tarfile's own reading, to compare with."""
    runs = []
    with tarfile.open(path, "r:") as tar:
        for m in tar:
            end = m.offset_data + -(-m.size // 512) * 512
            key = m.name.partition(".")[0]
            if runs and runs[-1][0] == key:
                runs[-1][2] = end
            else:
                runs.append([key, m.offset, end])
    return [tuple(r) for r in runs]


def test_the_header_walk_agrees_with_tarfile_and_falls_back_to_it(tiny_dataset, tmp_path):
    for i in (0, 1):
        assert shards.tar_layout(tar_path(tiny_dataset, i)) == _tar_runs_by_tarfile(tar_path(tiny_dataset, i))
    odd = tmp_path / "odd.tar"  # a long name takes an extended header, a link another member type
    with tarfile.open(odd, "w", format=tarfile.PAX_FORMAT) as tar:
        for name, data in (("a" * 120 + ".json", b"{}"), ("b.v00.png", b"x" * 700)):
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
        link = tarfile.TarInfo("b.link")
        link.type, link.linkname = tarfile.SYMTYPE, "b.v00.png"
        tar.addfile(link)
    assert shards.tar_layout(odd) == _tar_runs_by_tarfile(odd) and [k for k, _, _ in shards.tar_layout(odd)] == \
        ["a" * 120, "b"]


def test_a_damaged_tar_header_is_named(tiny_dataset, tmp_path):
    data = bytearray(tar_path(tiny_dataset, 0).read_bytes())
    data[5] ^= 0x01  # a letter of the first member's name: its checksum no longer holds
    bad = tmp_path / "bad.tar"
    bad.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match="bad.tar: tar header at byte 0 fails its checksum"):
        shards.tar_layout(bad)
    bad.write_bytes(tar_path(tiny_dataset, 0).read_bytes()[:1500])  # cut inside the first member's data
    with pytest.raises(DatasetError, match="truncated"):
        shards.tar_layout(bad)


def test_read_range_walks_plain_headers_and_falls_back_to_tarfile(tiny_dataset, tmp_path):
    """A subject's fields read by its byte range are the bytes tarfile extracts, from the writer's plain
    headers and from a tar with extended headers (read by tarfile); a range holding another subject
    is refused naming the file."""
    side = json.loads(sidecar_path(tiny_dataset, 0).read_text())
    with tarfile.open(tar_path(tiny_dataset, 0), "r:") as tar:
        want = {m.name.partition(".")[2]: tar.extractfile(m).read() for m in tar
                if m.name.startswith(side["subjects"][0] + ".")}
    start, end = side["offsets"][side["subjects"][0]]
    assert shards.read_range(tar_path(tiny_dataset, 0), side["subjects"][0], start, end) == want
    odd = tmp_path / "odd.tar"
    with tarfile.open(odd, "w", format=tarfile.PAX_FORMAT) as tar:
        for name, data in (("k" + "é" * 3 + ".json", b"{}"), ("k" + "é" * 3 + ".v00.png", b"x" * 700)):
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    assert shards.read_range(odd, "k" + "é" * 3, 0, odd.stat().st_size - 1024) == {"json": b"{}", "v00.png": b"x" * 700}
    with pytest.raises(DatasetError, match=f"{tar_path(tiny_dataset, 0)}: the byte range of subjX holds"):
        shards.read_range(tar_path(tiny_dataset, 0), "subjX", start, end)


def test_png_decoding_gives_pillows_pixels(tmp_path):
    """decode_png gives Pillow's pixels, shape and dtype for the grey and RGB PNGs shards hold (OpenCV
    decodes those) and for the modes only Pillow reads here (palette, grey with alpha, 16-bit)."""
    from PIL import Image

    rng = np.random.default_rng(0)
    images = [Image.fromarray(rng.integers(0, 256, (37, 23), dtype=np.uint8)),
              Image.fromarray(rng.integers(0, 256, (19, 41, 3), dtype=np.uint8)),
              Image.fromarray(rng.integers(0, 256, (19, 41, 4), dtype=np.uint8)),
              Image.fromarray(rng.integers(0, 256, (16, 16, 3), dtype=np.uint8)).convert("P"),
              Image.fromarray(rng.integers(0, 256, (16, 16, 2), dtype=np.uint8), mode="LA"),
              Image.fromarray(rng.integers(0, 65535, (9, 7), dtype=np.uint16))]
    for im in images:
        buf = io.BytesIO()
        im.save(buf, format="PNG")
        with Image.open(io.BytesIO(buf.getvalue())) as ref:
            ref.load()
            want = np.asarray(ref)
        got = shards.decode_png(buf.getvalue())
        assert got.dtype == want.dtype and got.shape == want.shape and np.array_equal(got, want), im.mode


def _with_header_field(data: bytes, at: int, value: bytes) -> bytes:
    """``data`` with bytes [at, at + len(value)) of the first header replaced, its checksum made to hold."""
    data = bytearray(data)
    data[at:at + len(value)] = value
    data[148:156] = b" " * 8
    data[148:156] = b"%06o\0 " % sum(data[:512])
    return bytes(data)


def test_other_spellings_of_header_numbers_read_as_tarfile_reads_them_and_negatives_refused(tiny_dataset, tmp_path):
    good = tar_path(tiny_dataset, 0).read_bytes()
    size = int(good[124:135], 8)
    tar = tmp_path / "odd.tar"
    for spelling in ((b"%o" % size).rjust(11) + b"\0", (b"%o" % size).ljust(11) + b" ", b"%o\0" % size + b"7" * 3):
        tar.write_bytes(_with_header_field(good, 124, spelling.ljust(12, b"\0")[:12]))
        assert shards.tar_layout(tar) == shards.tar_layout(tar_path(tiny_dataset, 0)) == _tar_runs_by_tarfile(tar)
    negative_size = _with_header_field(good, 124, b"-%010o\0" % (size + 512))  # once walked backwards
    negative_checksum = good[:148] + b"-01234\0 " + good[156:]
    for data in (negative_size, negative_checksum):
        tar.write_bytes(data)
        with pytest.raises(DatasetError, match="odd.tar: unreadable tar header at byte 0"):
            shards.tar_layout(tar)
