"""The dataset on disk: WebDataset-compatible tar shards, sidecars, the index, hidden truth.

A dataset folder holds::

    index.json                 the plan: settings and which subjects each shard holds
    shard-000000.tar           one tar sample per subject (key = subject id, no dots)
    shard-000000.json          sidecar, written last: counts, sha256 of the tar and truth file, and
                               each subject's byte range [start, end) in the tar (random access)
    truth/shard-000000.json    ground truth reviewers must not see (e.g. injected defects)
    .datagen.lock              empty; runs writing into the folder hold POSIX locks on its bytes
    .verified-shards.json      the shards that passed :func:`check_shards`, by the stat of their
                               tar and sidecar (readers skip re-checking them)

Fields of a subject sample ``<id>``: ``<id>.json`` (metadata and provenance), and per view i
``<id>.vII.png`` (RGB, 8-bit), ``<id>.vII.mask.png`` (alpha, 8-bit), ``<id>.vII.depth.exr``
(float32 distance along the ray, world units, 0 where alpha is 0), and ``<id>.<name>.npy`` for each
numeric array the generator records (GANs: ``z``, ``w``, optionally ``planes`` in fp16), and last,
with ``datagen sample --save-shape``, ``<id>.shape.ply`` (the head surface, ``datagen/shapes.py``).

A shard is complete only when its sidecar exists: the tar is written under a temporary name,
flushed and renamed, then the sidecar is written the same way. Tars are byte-reproducible (fixed
member order, mtime 0, no owner names).
"""
from __future__ import annotations

import functools
import hashlib
import io
import json
import os
import tarfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from ..errors import DatasetError, SettingError
from ..files import as_path, atomic_write, read_json, require, sha256_file

FORMAT = "panolam-heads/1"
INDEX_NAME = "index.json"
TRUTH_DIR = "truth"
SHAPE_FIELD = "shape.ply"  # a subject's head surface, when the dataset stores shapes


def subject_id(index: int) -> str:
    return f"subj{index:08d}"


def view_name(i: int) -> str:
    return f"v{i:02d}"


def shard_name(i: int) -> str:
    return f"shard-{i:06d}"


def shard_index(name: str) -> int:
    """Inverse of :func:`shard_name`."""
    prefix, _, number = str(name).partition("-")
    if prefix != "shard" or not number.isdigit():
        raise DatasetError(f"{name!r} is not a shard name (shard-NNNNNN)")
    return int(number)


def job_shards(num_shard_files: int, job: int, jobs: int) -> list[int]:
    """The shard numbers array job ``job`` of ``jobs`` (--shard-index K --num-shards N) handles:
    those s with s % jobs == job, of 0 .. num_shard_files - 1. A UserError when not 0 <= K < N."""
    if jobs < 1 or not 0 <= job < jobs:
        raise SettingError("{shard_index} must satisfy 0 <= shard-index < num-shards")
    return [s for s in range(num_shard_files) if s % jobs == job]


def tar_path(root, i) -> Path:
    return as_path(root) / f"{shard_name(i)}.tar"


def sidecar_path(root, i) -> Path:
    return as_path(root) / f"{shard_name(i)}.json"


def truth_path(root, i) -> Path:
    return as_path(root) / TRUTH_DIR / f"{shard_name(i)}.json"


def dumps(obj) -> bytes:
    """Canonical JSON bytes (sorted keys): identical objects give identical bytes."""
    return (json.dumps(obj, sort_keys=True, indent=1, allow_nan=False) + "\n").encode()


# ----------------------------------------------------------------------------------------------
# Encoding and decoding of fields

def encode_png(array: np.ndarray) -> bytes:
    """uint8 (H,W,3) or (H,W) -> PNG bytes (deterministic)."""
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG", compress_level=6)
    return buf.getvalue()


def encode_exr(depth: np.ndarray) -> bytes:
    """float32 (H,W) -> single-channel 'Z' EXR bytes (ZIP compression)."""
    import OpenEXR

    buf = io.BytesIO()
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Z": np.ascontiguousarray(depth, dtype=np.float32)}) as f:
        f.write(buf)
    return buf.getvalue()


def decode_png(data: bytes) -> np.ndarray:
    """A PNG's pixels as Pillow reads them (uint8 (h,w) grey, (h,w,3) RGB, ...). The 8-bit grey and RGB
    PNGs the shards hold are decoded by OpenCV where it is installed (the same pixels, about 1.6x faster),
    those within Pillow's pixel limit (``Image.MAX_IMAGE_PIXELS``, read from the header); Pillow decodes
    everything else and refuses larger images."""
    cv2 = _opencv()
    if cv2 is not None and data[:8] == _PNG_SIGNATURE and data[12:16] == b"IHDR" and data[24] == 8 \
            and data[25] in (0, 2) and int.from_bytes(data[16:20], "big") * int.from_bytes(data[20:24], "big") \
            <= (Image.MAX_IMAGE_PIXELS or 0):
        pixels = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if pixels is not None:
            return pixels if pixels.ndim == 2 else cv2.cvtColor(pixels, cv2.COLOR_BGR2RGB)
    with Image.open(io.BytesIO(data)) as im:
        im.load()
        return np.asarray(im)


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@functools.lru_cache(maxsize=None)
def _opencv():
    """OpenCV's module where installed (the ``faces`` extra), else None."""
    try:
        import cv2
    except ImportError:
        return None
    return cv2


def decode_exr(data: bytes) -> np.ndarray:
    import OpenEXR

    with OpenEXR.File(io.BytesIO(data)) as f:
        return np.array(f.channels()["Z"].pixels, dtype=np.float32)


def to_uint8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(np.asarray(x, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)


def encode_npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
    return buf.getvalue()


def decode_npy(data: bytes) -> np.ndarray:
    return np.load(io.BytesIO(data), allow_pickle=False)


def encode_subject(metadata: dict, rgb: np.ndarray, alpha: np.ndarray, depth: np.ndarray,
                   arrays: dict | None = None, shape: bytes | None = None) -> list[tuple[str, bytes]]:
    """One subject's tar members in order: metadata json, arrays (sorted by name), per view rgb, mask,
    depth, then the shape's PLY bytes when given."""
    key = metadata["subject_id"]
    members = [(f"{key}.json", dumps(metadata))]
    members += [(f"{key}.{name}.npy", encode_npy(arrays[name])) for name in sorted(arrays or {})]
    for i in range(rgb.shape[0]):
        v = view_name(i)
        members.append((f"{key}.{v}.png", encode_png(to_uint8(rgb[i]))))
        members.append((f"{key}.{v}.mask.png", encode_png(to_uint8(alpha[i]))))
        members.append((f"{key}.{v}.depth.exr", encode_exr(depth[i])))
    if shape is not None:
        members.append((f"{key}.{SHAPE_FIELD}", shape))
    return members


# ----------------------------------------------------------------------------------------------
# Writing a shard

# Not webdataset's TarWriter: headers can match, but it sorts each sample's fields by name, not encode_subject's order
class ShardWriter:
    """Writes one shard: members go to a temporary tar; :meth:`commit` publishes tar, truth, sidecar.

    Nothing under the final names exists until commit; an interrupted writer leaves only a
    temporary file that the next run removes.
    """

    def __init__(self, root, index: int):
        self.root = Path(root)
        self.index = index
        self.final = tar_path(root, index)
        self.tmp = self.final.with_name(f".{self.final.name}.tmp-{os.getpid()}")
        self._file = open(self.tmp, "wb")
        self._tar = tarfile.open(fileobj=self._file, mode="w", format=tarfile.USTAR_FORMAT)
        self.subjects: list[str] = []
        self.offsets: dict[str, list[int]] = {}
        self.truth: dict = {}
        self.n_files = 0

    def add_subject(self, key: str, members: list[tuple[str, bytes]], truth: dict | None = None) -> None:
        start = self._tar.offset
        for name, data in members:
            info = tarfile.TarInfo(name)
            info.size = len(data)
            info.mtime = 0
            info.mode = 0o644
            info.uid = info.gid = 0
            info.uname = info.gname = ""
            self._tar.addfile(info, io.BytesIO(data))
        self.subjects.append(key)
        self.offsets[key] = [start, self._tar.offset]
        self.n_files += len(members)
        if truth is not None:
            self.truth[key] = truth

    def commit(self, extra: dict | None = None) -> dict:
        self._tar.close()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        os.replace(self.tmp, self.final)
        sidecar = {
            "format": FORMAT,
            "shard": shard_name(self.index),
            "tar": self.final.name,
            "tar_bytes": self.final.stat().st_size,
            "tar_sha256": sha256_file(self.final),
            "subjects": self.subjects,
            "offsets": self.offsets,
            "files": self.n_files,
        }
        if self.truth:
            truth_file = truth_path(self.root, self.index)
            truth_file.parent.mkdir(exist_ok=True)
            data = dumps(self.truth)
            atomic_write(truth_file, data)
            sidecar["truth_sha256"] = hashlib.sha256(data).hexdigest()
        sidecar.update(extra or {})
        atomic_write(sidecar_path(self.root, self.index), dumps(sidecar))
        return sidecar

    def abort(self) -> None:
        try:
            self._tar.close()
            self._file.close()
        finally:
            self.tmp.unlink(missing_ok=True)


def remove_partial(root, index: int) -> None:
    """Remove whatever an interrupted run left of shard ``index`` (temporary files, a tar without sidecar)."""
    root = Path(root)
    name = shard_name(index)
    for p in root.glob(f".{name}.*tmp-*"):
        p.unlink(missing_ok=True)
    for p in (root / TRUTH_DIR).glob(f".{name}.*tmp-*"):
        p.unlink(missing_ok=True)
    if not sidecar_path(root, index).exists():
        tar_path(root, index).unlink(missing_ok=True)
        truth_path(root, index).unlink(missing_ok=True)


def read_sidecar(root, index: int, strict: bool = False) -> dict | None:
    """The shard's sidecar, or None when the shard is not complete (no sidecar, or it is unreadable).

    ``strict``: a sidecar that exists but cannot be read, is not JSON, or lacks its fields raises a
    DatasetError saying so (None still means there is none).
    """
    path = sidecar_path(root, index)
    try:
        side = read_json(path, "shard sidecar", FORMAT)
        require(side, "tar_bytes", int, path)
        require(side, "tar_sha256", str, path)
        require(side, "subjects", list, path)
        for key, span in require(side, "offsets", dict, path).items():
            if not (isinstance(span, list) and len(span) == 2 and all(isinstance(v, int) for v in span)
                    and 0 <= span[0] < span[1]):
                raise DatasetError(f"{path}: byte range of {key} is {span!r}, not [start, end)")
    except DatasetError:
        if strict and path.exists():
            raise
        return None
    return side


def is_complete(root, index: int) -> bool:
    """Fast completeness check: a readable sidecar whose tar exists with the recorded size."""
    side = read_sidecar(root, index)
    tar = tar_path(root, index)
    return bool(side) and tar.exists() and tar.stat().st_size == side.get("tar_bytes")


# ----------------------------------------------------------------------------------------------
# Reading

def read_index(root) -> dict:
    """A dataset's index.json, its structure checked; a DatasetError naming the file and field otherwise."""
    path = Path(root) / INDEX_NAME
    if not path.exists():
        raise DatasetError(f"{path}: no dataset index here (is this a dataset folder made by 'datagen sample'?)")
    index = read_json(path, "dataset index", FORMAT)
    for key, types in (("settings", dict), ("generator", dict), ("views_per_subject", int), ("num_subjects", int)):
        require(index, key, types, path)
    for i, shard in enumerate(require(index, "shards", list, path)):
        where = f"shards[{i}]"
        if not isinstance(shard, dict):
            raise DatasetError(f"{path}: {where} must be an object")
        name = require(shard, "name", str, path, where)
        try:
            shard_index(name)
        except DatasetError:
            raise DatasetError(f"{path}: {where}.name {name!r} is not a shard name (shard-NNNNNN)") from None
        if not all(isinstance(s, str) for s in require(shard, "subjects", list, path, where)):
            raise DatasetError(f"{path}: {where}.subjects must be a list of subject ids")
    return index


def index_sha256(root) -> str:
    """sha256 of a dataset's index.json: what ties a manifest or a pre-flags report to its dataset."""
    return sha256_file(Path(root) / INDEX_NAME)


@dataclass
class SubjectSample:
    """A subject read back: metadata, per view rgb (H,W,3) uint8, alpha (H,W) uint8, depth (H,W) float32
    (the decoded views, in the order asked for; depth empty when not asked for), and the generator's
    arrays by name."""

    key: str
    metadata: dict
    rgb: list
    alpha: list
    depth: list
    arrays: dict


def iter_tar_samples(path, wanted=None):
    """Group a shard's members into per-subject dicts {field: bytes}, in order; errors name the file.

    ``wanted(field, fields_so_far)`` may skip fields (their bytes are not read).
    """
    path = Path(path)
    try:
        with tarfile.open(path, "r:") as tar:
            current, fields = None, {}
            for member in tar:
                if not member.isfile():
                    continue
                key, _, field = member.name.partition(".")
                if key != current and current is not None:
                    yield current, fields
                    fields = {}
                current = key
                if wanted is None or wanted(field, fields):
                    fields[field] = tar.extractfile(member).read()
            if current is not None:
                yield current, fields
    except (tarfile.TarError, EOFError, OSError) as e:
        raise DatasetError(f"{path}: corrupt or truncated shard ({e})") from None


def read_fields(root, shard: int, key: str) -> dict:
    """One subject's raw fields {field: bytes}, read by its byte range from the sidecar (no scan)."""
    side = read_sidecar(root, shard)
    path = tar_path(root, shard)
    if side is None:
        raise DatasetError(f"{path}: incomplete shard (no sidecar)")
    try:
        start, end = side["offsets"][key]
    except KeyError:
        raise DatasetError(f"{path}: no subject {key} in this shard") from None
    return read_range(path, key, start, end)


def read_range(path, key: str, start: int, end: int, wanted=None) -> dict:
    """The fields {field: bytes} of subject ``key`` stored at bytes [start, end) of the tar ``path``.

    ``wanted(field, fields_so_far)`` may skip fields (their bytes are not copied out). A range that
    runs past the file or holds another subject is a DatasetError naming the file.
    """
    try:
        with open(path, "rb") as f:
            f.seek(start)
            blob = f.read(end - start)
        if len(blob) != end - start:
            raise DatasetError(f"{path}: the byte range of {key} [{start}, {end}) runs past the end of the tar")
        members = [m for m in tar_members(blob, path) if m[4]]  # its files
        others = sorted({name.partition(".")[0] for name, *_ in members} - {key})
        if others or not members:
            raise DatasetError(f"{path}: the byte range of {key} holds {others[:1] or 'no subject'}, not {key}")
        fields = {}
        for name, _, first, last, _ in members:
            field = name.partition(".")[2]
            if wanted is None or wanted(field, fields):
                fields[field] = blob[first:last]
        return fields
    except (tarfile.TarError, EOFError, OSError) as e:
        raise DatasetError(f"{path}: corrupt subject {key} ({e})") from None


def decode_sample(key: str, fields: dict, where="", views=None, depth: bool = True) -> SubjectSample:
    """Decode a subject's raw fields: all views, or only the view indices ``views``; depth optionally."""
    try:
        meta = json.loads(fields["json"])
        views = range(len(meta["views"])) if views is None else views
        rgb = [decode_png(fields[f"{view_name(i)}.png"]) for i in views]
        alpha = [decode_png(fields[f"{view_name(i)}.mask.png"]) for i in views]
        depths = [decode_exr(fields[f"{view_name(i)}.depth.exr"]) for i in views] if depth else []
        arrays = {name: decode_npy(fields[f"{name}.npy"]) for name in meta.get("arrays", {})}
    except KeyError as e:
        raise DatasetError(f"{where}: subject {key} lacks field {e}") from None
    except Exception as e:  # a decoder's own error: report which file and subject
        raise DatasetError(f"{where}: subject {key} does not decode ({type(e).__name__}: {e})") from None
    return SubjectSample(key, meta, rgb, alpha, depths, arrays)


# ----------------------------------------------------------------------------------------------
# The check readers run before they rely on shards (pre-flags, manifest compilation, training)

SHARD_CHECKS = ".verified-shards.json"  # in the dataset folder: the shards that passed check_shards
_CHECKS = "size+sha256+layout/1"  # what a remembered pass vouches for


def tar_layout(path, data: bytes | None = None) -> list[tuple[str, int, int]]:
    """(subject, start, end) of each run of members sharing a key, in tar order, from the member
    headers alone: the byte range [start, end) a writer records, from the first member's header to the
    end of the last member's 512-byte-padded data (members as :func:`tar_members` reads them).
    ``data``: the tar's bytes when they are already read."""
    data = Path(path).read_bytes() if data is None else data
    try:
        walked = _ustar_walk(data, path)
        if walked is not None:
            names, starts, ends = walked
            keys = [name.partition(b".")[0] for name in names]
        else:
            members = _tarfile_members(data)
            keys = [m[0].partition(".")[0] for m in members]
            starts, ends = [m[1] for m in members], [m[3] for m in members]
    except (tarfile.TarError, EOFError, OSError) as e:
        raise DatasetError(f"{path}: corrupt or truncated shard ({e})") from None
    firsts = [i for i, (before, key) in enumerate(zip([None, *keys], keys)) if key != before]
    return [(_text(keys[first]), starts[first], -(-ends[last - 1] // BLOCK) * BLOCK)
            for first, last in zip(firsts, [*firsts[1:], len(keys)])]


BLOCK = tarfile.BLOCKSIZE


def tar_members(data: bytes, path) -> list[tuple[str, int, int, int, bool]]:
    """(name, header offset, data offset, end of data, whether a plain file) of each member of the tar
    bytes ``data`` (a shard, or a subject's byte range of one) from ``path``. Plain ustar headers (what
    :class:`ShardWriter` writes) are walked here; a tar with other members (extended headers, links)
    is read with tarfile, whose errors the caller reports."""
    walked = _ustar_walk(data, path)
    if walked is None:
        return _tarfile_members(data)
    return [(_text(name), start, start + BLOCK, end, True) for name, start, end in zip(*walked)]


def _tarfile_members(data: bytes) -> list[tuple[str, int, int, int, bool]]:
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:") as tar:
        return [(m.name, m.offset, m.offset_data, m.offset_data + m.size, m.isfile()) for m in tar]


def _text(name: bytes | str) -> str:
    return name.decode("utf-8", "replace") if isinstance(name, bytes) else name


def _octal(field: bytes) -> int:
    """A numeric header field as tarfile reads it (to the first NUL, spaces stripped); ValueError when it
    is not a number of 0 or more."""
    value = int(field.split(b"\0", 1)[0].strip() or b"0", 8)
    if value < 0:
        raise ValueError(f"negative number {value}")
    return value


_ZERO_BLOCK = bytes(BLOCK)
_SIZE_DIGITS = 8.0 ** np.arange(10, -1, -1)
_CHECKSUM_DIGITS = (8 ** np.arange(5, -1, -1)).astype(np.float32)
_CHECKSUM_WEIGHTS = np.ones(BLOCK, np.float32)  # a header's bytes summed, its checksum field counted as 8 spaces
_CHECKSUM_WEIGHTS[148:156] = 0
_OCTAL_DIGITS = np.array([0xF8F8F8F8, 0xF8F8F8F8, 0xFFF8F8F8], np.uint32)  # a byte '0'..'7' keeps 0x30
_ZEROS = np.array([0x30303030, 0x30303030, 0x00303030], np.uint32)  # ... and the field's last byte is NUL
_FILE_TYPE = np.isin(np.arange(256), (0, 48))  # by byte value: the type flag of a plain file (NUL or '0')
_WRITTEN_CHECKSUM = (0xFFFF_F8F8_F8F8_F8F8, 0x2000_3030_3030_3030)  # mask, value: 6 octal digits, NUL, space


def _ustar_walk(data: bytes, path) -> tuple[list[bytes], list[int], list[int]] | None:
    """(names, header offsets, ends of data) of the members of the tar bytes ``data`` when every member
    is a plain file with a plain header, else None. A header that cannot be read (a size or checksum
    that is not a number of 0 or more) or whose checksum fails is a DatasetError naming the first such
    header. Every 512-byte block is first read as the writer spells a file's header (numpy: 11 octal
    digits of size, then NUL); the walk from header to header looks those sizes up and reads any other
    spelling as tarfile does. The checksums and names of the headers it walked are read together."""
    n = len(data)
    blocks = np.frombuffer(data, np.uint8, n // BLOCK * BLOCK).reshape(-1, BLOCK)
    words = np.ascontiguousarray(blocks[:, 124:136]).view("<u4")  # the size field as three little-endian words
    spelled = ((words & _OCTAL_DIGITS) == _ZEROS).all(axis=1) & _FILE_TYPE[blocks[:, 156]]  # 11 digits, NUL
    fast = np.where(spelled, (blocks[:, 124:135] - np.uint8(48)).astype(np.float64) @ _SIZE_DIGITS, -1)
    fast = fast.astype(np.int64).tolist()
    heads, sizes, b, problem, other_member = [], [], 0, None, False
    while b < len(fast):
        size = fast[b]
        if size < 0 or (b + 1) * BLOCK + size > n:  # another spelling, the end blocks, or past the end
            o = b * BLOCK
            if data[o:o + BLOCK] == _ZERO_BLOCK:
                break
            if not _FILE_TYPE[data[o + 156]] or data[o + 124] & 0x80:
                other_member = True
                break
            try:
                size = _octal(data[o + 124:o + 136])
            except ValueError:
                problem = f"unreadable tar header at byte {o}"
                break
        heads.append(b)
        sizes.append(size)
        if (b + 1) * BLOCK + size > n:
            problem = "truncated (a member runs past the end of the file)"
            break
        b += 1 + -(-size // BLOCK)
    else:
        if b * BLOCK < n:
            problem = "truncated (a header runs past the end of the file)"
    headers = blocks[heads]
    _check_headers(headers, heads, path)  # a failing checksum before the problem is the first to report
    if other_member:
        return None
    if problem:
        raise DatasetError(f"{path}: {problem}")
    names = [x.split(b"\0", 1)[0] for x in np.ascontiguousarray(headers[:, :100]).view("S100").ravel().tolist()]
    for k in np.flatnonzero(headers[:, 345]):  # a ustar header's prefix before the name
        if headers[k, 257:262].tobytes() == b"ustar":
            names[k] = headers[k, 345:500].tobytes().split(b"\0", 1)[0] + b"/" + names[k]
    return names, [b * BLOCK for b in heads], [(b + 1) * BLOCK + size for b, size in zip(heads, sizes)]


def _check_headers(headers: np.ndarray, blocks: list[int], path) -> None:
    """DatasetError naming the first of ``headers`` (rows of 512 bytes, at the block numbers ``blocks``)
    whose checksum field cannot be read or differs from the sum of its bytes (the field counted as spaces)."""
    total = headers.astype(np.float32) @ _CHECKSUM_WEIGHTS + 8 * 32  # exact: below 512 * 255 < 2 ** 24
    field = headers[:, 148:156]
    mask, value = _WRITTEN_CHECKSUM  # the field as the writer spells it, read as one little-endian word
    written = (np.ascontiguousarray(field).view("<u8").ravel() & np.uint64(mask)) == np.uint64(value)
    stored = np.where(written, (field[:, :6] - np.uint8(48)).astype(np.float32) @ _CHECKSUM_DIGITS, -1)
    for k in np.flatnonzero(~written):  # any other spelling, as tarfile reads it
        try:
            stored[k] = _octal(field[k].tobytes())
        except ValueError:
            stored[k] = -1
    bad = np.flatnonzero(stored != total)
    if bad.size:
        what = "unreadable tar header at byte {}" if stored[bad[0]] < 0 else "tar header at byte {} fails its checksum"
        raise DatasetError(f"{path}: " + what.format(blocks[bad[0]] * BLOCK))


def _first_difference(got: list, want: list, where: str) -> str:
    for i, (a, b) in enumerate(zip(got, want)):
        if a != b:
            return f"{a} as subject {i} where {where} has {b}"
    return f"{len(got)} subjects where {where} has {len(want)}"


def layout_problem(root, i: int, side: dict, subjects: list, data: bytes | None = None) -> str | None:
    """The first way shard ``i``'s sidecar disagrees with the dataset index (``subjects``: the ids the
    index lists for it) or with its tar's member headers (each subject's key and byte range), as one
    line naming the file; None when they agree. ``data``: the tar's bytes when they are already read."""
    tar, side_path = tar_path(root, i), sidecar_path(root, i)
    if side["subjects"] != subjects:
        return f"{side_path}: lists {_first_difference(side['subjects'], subjects, 'the dataset index')}"
    runs = tar_layout(tar, data)
    keys = [k for k, _, _ in runs]
    if keys != subjects:
        return f"{tar}: holds {_first_difference(keys, subjects, 'its sidecar')}"
    offsets = side["offsets"]
    stray = sorted(set(offsets) - set(keys))
    if stray:
        return f"{side_path}: a byte range for {stray[0]}, which the shard does not hold"
    for key, start, end in runs:
        if offsets.get(key) != [start, end]:
            return (f"{side_path}: byte range of {key} is {offsets.get(key)}, the tar holds it at "
                    f"[{start}, {end})")
    return None


def check_shards(root, shards, index: dict) -> dict[int, str]:
    """{shard number: its first problem, one line naming the file} for the shards numbered ``shards``
    of a dataset that fail the check a reader needs before it trusts them; empty when all pass.

    Checked: the sidecar is there and readable, the tar has the size and sha256 it records, the
    sidecar lists the subjects the dataset's ``index`` lists, and every subject's
    byte range is where the tar's member headers put it (images are not decoded; ``datagen verify``
    checks everything). A shard that passed is remembered in ``root/.verified-shards.json`` with the
    size, inode, mtime and ctime of its tar and sidecar; while those stay the same it is not hashed
    or walked again, so a second check costs a few ``stat`` calls (a write that restores the mtime
    still changes the ctime). A dataset folder that cannot be written is checked in full every time.
    """
    root = Path(root)
    listed = {shard_index(sh["name"]): sh["subjects"] for sh in index["shards"]}
    cache_path = root / SHARD_CHECKS
    try:
        cache = json.loads(cache_path.read_text())
    except (OSError, ValueError):
        cache = {}
    cache = cache if isinstance(cache, dict) else {}
    problems, passed = {}, {}
    for i in sorted(set(shards)):
        tar, side_path = tar_path(root, i), sidecar_path(root, i)
        try:
            side = read_sidecar(root, i, strict=True)
        except DatasetError as e:
            problems[i] = f"{e} (datagen verify {root} tells more)"
            continue
        if side is None:
            problems[i] = f"{tar}: incomplete (no sidecar {side_path.name})"
            continue
        try:
            tar_stamp = _stat_stamp(tar)
        except FileNotFoundError:
            problems[i] = f"{tar}: missing although its sidecar exists"
            continue
        if i not in listed:
            problems[i] = f"{tar}: not a shard of the dataset index"
            continue
        if side["subjects"] != listed[i]:
            problems[i] = layout_problem(root, i, side, listed[i])
            continue
        stamp = [tar_stamp, _stat_stamp(side_path), side["tar_sha256"], _CHECKS]
        if cache.get(tar.name) == stamp:
            passed[tar.name] = stamp
        elif tar_stamp[0] != side["tar_bytes"]:
            problems[i] = f"{tar}: size {tar_stamp[0]} differs from the sidecar's {side['tar_bytes']}"
        else:
            data = tar.read_bytes()  # hashed, then walked
            if hashlib.sha256(data).hexdigest() != side["tar_sha256"]:
                problems[i] = f"{tar}: sha256 differs from the sidecar (corrupted)"
            else:
                problem = layout_problem(root, i, side, listed[i], data)
                if problem:
                    problems[i] = problem
                else:
                    passed[tar.name] = stamp
    if any(cache.get(name) != stamp for name, stamp in passed.items()):
        try:
            atomic_write(cache_path, json.dumps({**cache, **passed}, sort_keys=True).encode())
        except OSError:
            pass  # a read-only dataset: nothing remembered, the next check hashes again
    return problems


def _stat_stamp(path: Path) -> list[int]:
    st = path.stat()
    return [st.st_size, st.st_ino, st.st_mtime_ns, st.st_ctime_ns]
