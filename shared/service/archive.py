"""Safe unpacking of capture archives (zip, tar, tar.gz/bz2/xz) sent by users.

In: an archive file and :class:`ArchiveLimits`. Out: an :class:`ArchiveReport` (what is
inside), or a folder holding the unpacked capture.

Everything is checked before a single byte is written: member names that escape the
destination (absolute paths, ``..``, backslashes, drive letters), symbolic and hard links
and device files, the member count, the total unpacked size, the compression ratio
(decompression bombs: the whole archive's unpacked/packed ratio, and each member's, with no
exemption for small members: 4,095 members of 1 MiB of zeros are a 4 GiB bomb in a 4.6 MB zip)
and, for every image, its header's dimensions (read with Pillow from the archive stream; no
pixel is decoded). Extraction then streams each member and refuses one that grows past its
declared size, or an archive whose members together grow past the checked total (lying
headers), writes into a temporary folder and renames it into place, so a failure leaves
nothing behind.

Every problem raises :class:`~shared.core.errors.InputError` whose ``where`` is
``ARCHIVE:MEMBER`` (or the archive alone) and whose message says what is wrong.
"""

from __future__ import annotations

import io
import logging
import os
import shutil
import stat
import tarfile
import tempfile
import warnings
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import IO

from shared.core.errors import InputError
from shared.core.files import atomic_file
from shared.formats.capture import CAPTURE_FILE, IMAGE_SUFFIXES

log = logging.getLogger(__name__)

_COPY = 1 << 20
#: An archive unpacking to less than this is not held to the compression-ratio limit: a
#: capture of a few small text files compresses well and cannot hurt. The limit applies to
#: the whole archive's total, so many small members cannot pass it one by one.
_RATIO_FLOOR = 1 << 20


@dataclass(frozen=True)
class ArchiveLimits:
    """Limits on an archive: member count, total unpacked bytes, unpacked/packed ratio,
    image pixels and image side."""

    max_files: int = 4096
    max_unpacked_bytes: int = 32 << 30
    max_compression_ratio: int = 250
    max_image_pixels: int = 50_000_000
    max_image_side: int = 16384

    @classmethod
    def from_settings(cls, settings: object) -> ArchiveLimits:
        return cls(
            max_files=settings.max_archive_files,  # type: ignore[attr-defined]
            max_unpacked_bytes=settings.max_unpacked_bytes,  # type: ignore[attr-defined]
            max_compression_ratio=settings.max_compression_ratio,  # type: ignore[attr-defined]
            max_image_pixels=settings.max_image_pixels,  # type: ignore[attr-defined]
            max_image_side=settings.max_image_side,  # type: ignore[attr-defined]
        )


@dataclass(frozen=True)
class ArchiveMember:
    name: str  # normalised POSIX path inside the archive
    size: int  # declared unpacked size in bytes
    image: tuple[int, int] | None = None  # (width, height) from the header, for images


@dataclass(frozen=True)
class ArchiveReport:
    kind: str  # "zip" or "tar"
    members: tuple[ArchiveMember, ...]
    total_bytes: int
    root: str  # folder inside the archive that holds capture.json ("" for the top level)


def _safe_name(raw: str, where: str) -> str:
    """The member name as a clean relative POSIX path, or InputError if it would escape."""
    if "\x00" in raw:
        raise InputError(where, "member name contains a NUL byte")
    if "\\" in raw:
        raise InputError(where, "member name contains a backslash (path traversal is not allowed)")
    p = PurePosixPath(raw)
    if p.is_absolute() or raw.startswith("/"):
        raise InputError(where, "member has an absolute path (path traversal is not allowed)")
    if p.parts and len(p.parts[0]) == 2 and p.parts[0][1] == ":":
        raise InputError(where, "member name starts with a drive letter (path traversal is not allowed)")
    if any(part == ".." for part in p.parts):
        raise InputError(where, "member name contains '..' (path traversal is not allowed)")
    clean = "/".join(part for part in p.parts if part not in ("", "."))
    if not clean:
        raise InputError(where, "member has an empty name")
    return clean


class _Reader:
    """The same walk over a zip or a tar: (name, size, packed size, is_dir, opener)."""

    def __init__(self, path: Path, label: str) -> None:
        self.path = path
        self.label = label
        self.zip: zipfile.ZipFile | None = None
        self.tar: tarfile.TarFile | None = None
        try:
            if zipfile.is_zipfile(path):
                self.zip = zipfile.ZipFile(path)
                self.kind = "zip"
            elif tarfile.is_tarfile(path):
                self.tar = tarfile.open(path, "r:*")
                self.kind = "tar"
            else:
                raise InputError(label, "not a zip or tar archive")
        except (zipfile.BadZipFile, tarfile.TarError, EOFError, OSError) as exc:
            raise InputError(label, f"corrupt archive ({exc})") from None

    def close(self) -> None:
        if self.zip is not None:
            self.zip.close()
        if self.tar is not None:
            self.tar.close()

    def entries(self) -> Iterator[tuple[str, int, int, bool, object]]:
        try:
            if self.zip is not None:
                for info in self.zip.infolist():
                    where = f"{self.label}:{info.filename}"
                    # Unix type bits, when the creator recorded any (many tools store only permissions).
                    mode = stat.S_IFMT(info.external_attr >> 16)
                    if mode and stat.S_ISLNK(mode):
                        raise InputError(where, "member is a symbolic link (links are not allowed)")
                    if mode and not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
                        raise InputError(where, "member is not a regular file or folder")
                    if info.flag_bits & 0x1:
                        raise InputError(where, "member is encrypted")
                    yield info.filename, info.file_size, info.compress_size, info.is_dir(), info
            else:
                assert self.tar is not None
                for m in self.tar:
                    where = f"{self.label}:{m.name}"
                    if m.issym() or m.islnk():
                        raise InputError(where, "member is a link (links are not allowed)")
                    if not (m.isreg() or m.isdir()):
                        raise InputError(where, "member is a device, FIFO or other special file (not allowed)")
                    yield m.name, m.size, m.size, m.isdir(), m
        except (zipfile.BadZipFile, tarfile.TarError, EOFError, OSError) as exc:
            raise InputError(self.label, f"corrupt archive ({exc})") from None

    def open(self, handle: object) -> IO[bytes]:
        if self.zip is not None:
            return self.zip.open(handle)  # type: ignore[arg-type]
        assert self.tar is not None
        f = self.tar.extractfile(handle)  # type: ignore[arg-type]
        if f is None:
            raise InputError(self.label, f"cannot read member {getattr(handle, 'name', handle)}")
        return f


def _image_size(reader: _Reader, handle: object, where: str, limits: ArchiveLimits) -> tuple[int, int]:
    """(width, height) from an image member's header, checked against the limits."""
    from PIL import Image

    try:
        with reader.open(handle) as f:
            # Enough for PNG, JPEG (behind EXIF) and BMP headers; TIFF may keep its first
            # directory further in, so it gets the seekable stream itself.
            head = f.read(1 << 16)
            stream: IO[bytes] = io.BytesIO(head)
            if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
                stream = io.BytesIO(head + f.read(8 << 20))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                Image.MAX_IMAGE_PIXELS = None  # our own limit below applies instead
                with Image.open(stream) as img:
                    width, height = img.size
    except InputError:
        raise
    except Exception as exc:  # Pillow raises many types for a bad header
        raise InputError(where, f"not a readable image header ({type(exc).__name__}: {exc})") from None
    if width > limits.max_image_side or height > limits.max_image_side:
        raise InputError(where, f"image is {width}x{height}, a side exceeds the limit of {limits.max_image_side} pixels")
    if width * height > limits.max_image_pixels:
        raise InputError(where, f"image is {width}x{height} = {width * height} pixels, more than the limit of "
                                f"{limits.max_image_pixels}")  # fmt: skip
    return width, height


def _find_root(names: list[str], label: str, require: str | None) -> str:
    if require is None:
        tops = {n.split("/", 1)[0] for n in names}
        if len(tops) == 1 and all("/" in n for n in names):
            return next(iter(tops))
        return ""
    hits = [n for n in names if PurePosixPath(n).name == require]
    if not hits:
        raise InputError(label, f"no {require} in the archive")
    hits.sort(key=lambda n: n.count("/"))
    if len(hits) > 1 and hits[0].count("/") == hits[1].count("/"):
        raise InputError(label, f"more than one {require} at the same depth ({hits[0]}, {hits[1]}): one capture per archive")
    parent = str(PurePosixPath(hits[0]).parent)
    return "" if parent == "." else parent


def inspect_archive(
    path: Path, limits: ArchiveLimits, label: str | None = None, require: str | None = CAPTURE_FILE
) -> ArchiveReport:
    """Check an archive without writing anything; raises InputError naming the member and problem.

    ``label`` names the archive in messages (default: its file name); ``require`` is a
    file that must be inside (``capture.json``; None for no requirement).
    """
    path = Path(path)
    label = label or path.name
    try:
        packed = path.stat().st_size
    except OSError:
        raise InputError(label, "archive not found") from None
    if packed == 0:
        raise InputError(label, "archive is empty")
    reader = _Reader(path, label)
    try:
        members: list[ArchiveMember] = []
        seen: set[str] = set()
        total = 0
        count = 0
        images: list[tuple[str, object, int]] = []
        for raw, size, csize, is_dir, handle in reader.entries():
            where = f"{label}:{raw}"
            name = _safe_name(raw, where)
            count += 1
            if count > limits.max_files:
                raise InputError(label, f"more than {limits.max_files} members (the file-count limit, GRAYLIGHT_MAX_ARCHIVE_FILES)")
            if is_dir:
                continue
            if name in seen:
                raise InputError(where, "member appears twice in the archive")
            seen.add(name)
            total += size
            if total > limits.max_unpacked_bytes:
                raise InputError(label, f"unpacks to more than {limits.max_unpacked_bytes} bytes (the size limit, "
                                        "GRAYLIGHT_MAX_UNPACKED_BYTES)")  # fmt: skip
            if reader.kind == "zip" and size > limits.max_compression_ratio * max(csize, 1):
                # Every member, however small (the archive's total below catches many moderate ones).
                raise InputError(where, f"compression ratio {size / max(csize, 1):.0f}:1 exceeds "
                                        f"{limits.max_compression_ratio}:1 (GRAYLIGHT_MAX_COMPRESSION_RATIO; a decompression bomb?)")  # fmt: skip
            if PurePosixPath(name).suffix.lower() in IMAGE_SUFFIXES:
                images.append((name, handle, len(members)))
            members.append(ArchiveMember(name, size))
        if total > _RATIO_FLOOR and total > limits.max_compression_ratio * packed:
            raise InputError(label, f"compression ratio {total / packed:.0f}:1 exceeds "
                                    f"{limits.max_compression_ratio}:1 (GRAYLIGHT_MAX_COMPRESSION_RATIO; a decompression bomb?)")  # fmt: skip
        if not members:
            raise InputError(label, "archive holds no files")
        root = _find_root([m.name for m in members], label, require)
        for name, handle, idx in images:
            wh = _image_size(reader, handle, f"{label}:{name}", limits)
            members[idx] = ArchiveMember(name, members[idx].size, wh)
        return ArchiveReport(reader.kind, tuple(members), total, root)
    finally:
        reader.close()


def extract_archive(
    path: Path, dest: Path, limits: ArchiveLimits, label: str | None = None, require: str | None = CAPTURE_FILE
) -> Path:
    """Check, then unpack an archive into the new folder ``dest`` (atomically). Returns the
    folder holding ``require`` (``dest`` itself or its one sub-folder)."""
    path, dest = Path(path), Path(dest)
    label = label or path.name
    report = inspect_archive(path, limits, label, require)
    declared = {m.name: m.size for m in report.members}
    budget = report.total_bytes  # what the headers declared, all members together
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", dir=dest.parent))
    reader = _Reader(path, label)
    try:
        for raw, _size, _csize, is_dir, handle in reader.entries():
            name = _safe_name(raw, f"{label}:{raw}")
            target = tmp / name
            # The name was checked, but resolve once more so no later change can escape.
            if not target.resolve().is_relative_to(tmp.resolve()):
                raise InputError(f"{label}:{raw}", "member would be written outside the destination")
            if is_dir:
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            limit = declared[name]
            written = 0
            with reader.open(handle) as src, open(target, "wb") as out:
                while True:
                    block = src.read(_COPY)
                    if not block:
                        break
                    written += len(block)
                    budget -= len(block)
                    if written > limit:
                        raise InputError(f"{label}:{raw}", "member unpacks to more bytes than its header declares")
                    if budget < 0:
                        raise InputError(label, f"unpacks to more than the {report.total_bytes} bytes its headers declare")
                    out.write(block)
            os.chmod(target, 0o644)
        try:
            os.rename(tmp, dest)
        except OSError:
            if not dest.is_dir():
                raise
            # Another process unpacked the same capture first: theirs is identical.
    except (zipfile.BadZipFile, tarfile.TarError, EOFError, zlib.error) as exc:
        raise InputError(label, f"corrupt archive ({exc})") from None
    finally:
        reader.close()
        shutil.rmtree(tmp, ignore_errors=True)
    return dest / report.root if report.root else dest


def pack_folder(folder: Path, out: Path) -> Path:
    """Write ``folder``'s regular files (not links) into the zip ``out`` (stored, not deflated:
    captures are PNGs already), through a temporary name."""
    folder, out = Path(folder), Path(out)
    with atomic_file(out) as tmp, zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as z:
        for p in sorted(folder.rglob("*")):
            if p.is_file() and not p.is_symlink():
                z.write(p, p.relative_to(folder).as_posix())
    return out
