"""Point clouds as PLY files: the cloud contract between the scanner and the renderers.

Graylight writes binary little-endian PLY with one ``vertex`` element::

    x, y, z        float32   position in the rig's units (camera frame)
    red, green, blue  uchar  colour from the white frame
    nx, ny, nz     float32   unit normal, facing the camera
    size           float32   world-space sample size Z / f_camera (renderers size splats with it)

and, when the scan recovered it (``shared.scan.albedo``), the object's own colour beside the
shaded one: ``albedo_red, albedo_green, albedo_blue`` uchar (linear albedo, sRGB-encoded) and
``albedo_weight`` uchar (0 where no albedo could be measured). Readers that do not know these
fields ignore them.

Reading accepts any PLY whose vertex element carries at least ``x, y, z`` (binary
either endianness, or ASCII); binary files are memory-mapped, so a 15 M-point cloud
is read in chunks without loading it whole.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.core.errors import InputError
from shared.core.files import atomic_file
from shared.core.paths import open_regular

#: Field layout of the clouds Graylight writes (31 bytes per point, packed).
CLOUD_DTYPE = np.dtype(
    [
        ("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
        ("red", "u1"), ("green", "u1"), ("blue", "u1"),
        ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
        ("size", "<f4"),
    ]
)  # fmt: skip

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_NP_TO_PLY = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint", "f4": "float", "f8": "double"}

#: Points written per chunk: bounds the writer's extra memory to a few tens of MB.
CHUNK = 1 << 20


@dataclass
class PointCloud:
    """A point cloud in memory. ``xyz`` (N, 3) float32; the rest optional, N rows each."""

    xyz: np.ndarray
    rgb: np.ndarray | None = None  # (N, 3) uint8
    normals: np.ndarray | None = None  # (N, 3) float32
    size: np.ndarray | None = None  # (N,) float32
    albedo: np.ndarray | None = None  # (N, 3) uint8, sRGB-encoded linear albedo
    albedo_weight: np.ndarray | None = None  # (N,) uint8, 0 where masked

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


@dataclass(frozen=True)
class PlyHeader:
    """What a PLY header says about its vertex element."""

    fmt: str  # "binary_little_endian", "binary_big_endian" or "ascii"
    count: int
    dtype: np.dtype  # one record of the vertex element
    data_offset: int  # byte offset of the vertex data
    comments: tuple[str, ...] = ()


def _comment(text: str) -> str:
    """``text`` as one line of printable ASCII, anything else as "?": a foreign file's accented
    comment (read back as U+FFFD) failed the header's ASCII encoding with a bare
    UnicodeEncodeError, and a newline (a rig's units) would have started a header line of its own."""
    return "".join(ch if " " <= ch <= "~" else "?" for ch in str(text))


def _header_text(count: int, dtype: np.dtype, comments: tuple[str, ...]) -> bytes:
    lines = ["ply", "format binary_little_endian 1.0", *(f"comment {_comment(c)}" for c in comments),
             f"element vertex {count}"]
    for name in dtype.names or ():
        lines.append(f"property {_NP_TO_PLY[dtype[name].str[1:]]} {name}")
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def write_ply(
    path: str | os.PathLike[str],
    xyz: np.ndarray,
    rgb: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    size: np.ndarray | None = None,
    comments: tuple[str, ...] = (),
    albedo: np.ndarray | None = None,
    albedo_weight: np.ndarray | None = None,
) -> Path:
    """Write a binary little-endian PLY atomically (temporary name, then rename).

    ``xyz`` is (N, 3); ``rgb`` (N, 3) uint8, ``normals`` (N, 3), ``size`` (N,), ``albedo`` (N, 3)
    uint8 with ``albedo_weight`` (N,) uint8 are written when given. Data is converted and written in chunks of :data:`CHUNK` points.
    """
    path = Path(path)
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz must be (N, 3), got {xyz.shape}")
    n = xyz.shape[0]
    fields: list[tuple[str, str]] = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if rgb is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if size is not None:
        fields += [("size", "<f4")]
    if (albedo is None) != (albedo_weight is None):
        raise ValueError("albedo and albedo_weight go together")
    if albedo is not None:
        fields += [("albedo_red", "u1"), ("albedo_green", "u1"), ("albedo_blue", "u1"), ("albedo_weight", "u1")]
    for name, arr, shape in (("rgb", rgb, (n, 3)), ("normals", normals, (n, 3)), ("size", size, (n,)),
                             ("albedo", albedo, (n, 3)), ("albedo_weight", albedo_weight, (n,))):
        if arr is not None and np.shape(arr) != shape:
            raise ValueError(f"{name} must be {shape}, got {np.shape(arr)}")
    dtype = np.dtype(fields)
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        f.write(_header_text(n, dtype, comments))
        for start in range(0, n, CHUNK):
            sl = slice(start, min(n, start + CHUNK))
            rec = np.empty(sl.stop - sl.start, dtype=dtype)
            rec["x"], rec["y"], rec["z"] = xyz[sl, 0], xyz[sl, 1], xyz[sl, 2]
            if rgb is not None:
                rec["red"], rec["green"], rec["blue"] = rgb[sl, 0], rgb[sl, 1], rgb[sl, 2]
            if normals is not None:
                rec["nx"], rec["ny"], rec["nz"] = normals[sl, 0], normals[sl, 1], normals[sl, 2]
            if size is not None:
                rec["size"] = size[sl]
            if albedo is not None and albedo_weight is not None:
                rec["albedo_red"], rec["albedo_green"], rec["albedo_blue"] = albedo[sl, 0], albedo[sl, 1], albedo[sl, 2]
                rec["albedo_weight"] = albedo_weight[sl]
            f.write(rec.tobytes())
    return path


_END_HEADER = re.compile(rb"^end_header[ \t\r]*$", re.MULTILINE)


def read_header(path: str | os.PathLike[str]) -> PlyHeader:
    """Parse a PLY header; raises :class:`InputError` naming the file for anything we cannot read."""
    path = Path(path)
    # Without blocking, regular files only (a FIFO or device named by a client never hangs a read).
    with open_regular(path, path, missing="point cloud file not found") as f:
        head = f.read(1 << 16)
        size = os.fstat(f.fileno()).st_size
    if not head.startswith(b"ply"):
        raise InputError(path, "not a PLY file (no 'ply' magic)")
    # the line that is end_header, not those words inside a comment ("comment ... end_header")
    m = _END_HEADER.search(head)
    if m is None:
        raise InputError(path, "PLY header has no end_header within 64 KiB")
    end = m.start()
    nl = head.find(b"\n", end)
    if nl < 0:
        raise InputError(path, "PLY header is truncated")
    lines = head[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    count = None
    props: list[tuple[str, str]] = []
    comments: list[str] = []
    current = None
    seen_vertex_done = False
    for raw in lines[1:]:
        parts = raw.split()
        if not parts:
            continue
        if parts[0] == "format" and len(parts) >= 2:
            fmt = parts[1]
        elif parts[0] == "comment":
            comments.append(raw[len("comment") :].strip())
        elif parts[0] == "element" and len(parts) == 3:
            if current == "vertex":
                seen_vertex_done = True
            current = parts[1]
            if current == "vertex":
                if seen_vertex_done or count is not None:
                    raise InputError(path, "PLY has more than one vertex element")
                if not parts[2].isdigit() or len(parts[2]) > 18:
                    raise InputError(path, f"bad vertex count {parts[2][:20]!r}")
                count = int(parts[2])
            elif count is None:
                raise InputError(path, f"element {current!r} before the vertex element is not supported")
        elif parts[0] == "property" and current == "vertex":
            if parts[1] == "list":
                raise InputError(path, "list properties in the vertex element are not supported")
            if len(parts) != 3 or parts[1] not in _PLY_TYPES:
                raise InputError(path, f"unsupported PLY property line {raw!r}")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    if fmt not in ("binary_little_endian", "binary_big_endian", "ascii"):
        raise InputError(path, f"unsupported PLY format {fmt!r}")
    if count is None or count < 0:
        raise InputError(path, "PLY has no vertex element")
    names = [p[0] for p in props]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:  # numpy refuses such a record type with a bare ValueError
        raise InputError(path, f"PLY vertex property {twice[0][:40]!r} is declared more than once")
    for axis in ("x", "y", "z"):
        if axis not in names:
            raise InputError(path, f"PLY vertex element has no '{axis}' property")
    order = ">" if fmt == "binary_big_endian" else "<"
    dtype = np.dtype([(name, order + t if t[1] != "1" else t) for name, t in props])
    _check_count(path, fmt, count, dtype, size - (nl + 1))
    return PlyHeader(fmt=fmt, count=count, dtype=dtype, data_offset=nl + 1, comments=tuple(comments))


def _check_count(path: Path, fmt: str, count: int, dtype: np.dtype, data_bytes: int) -> None:
    """The header's vertex count against the bytes that follow the header, before anything is
    allocated: a binary vertex takes ``dtype.itemsize`` bytes, an ASCII one at least two a
    property (a digit and a separator). A header claiming 10^12 vertices is refused here, not
    by a failed allocation of terabytes."""
    if fmt == "ascii":
        least = 2 * len(dtype.names or ())
        if count > data_bytes // least:
            raise InputError(path, f"PLY header claims {count} vertices, but the {data_bytes} bytes after it "
                                   f"hold at most {data_bytes // least} ASCII vertices of {len(dtype.names or ())} properties")
    elif count * dtype.itemsize > data_bytes:
        raise InputError(path, f"PLY is truncated: the header claims {count} vertices of {dtype.itemsize} bytes, "
                               f"{data_bytes} bytes follow it")


def _records(path: Path, header: PlyHeader) -> np.ndarray:
    if header.fmt == "ascii":
        with open(path, "rb") as f:
            f.seek(header.data_offset)
            try:
                table = np.loadtxt(f, max_rows=header.count, ndmin=2, dtype=np.float64)
            except ValueError as exc:
                raise InputError(path, f"malformed ASCII PLY data: {exc}") from None
        if table.shape[0] != header.count or table.shape[1] < len(header.dtype.names or ()):
            raise InputError(path, f"ASCII PLY holds {table.shape[0]} vertices, header says {header.count}")
        rec = np.empty(header.count, dtype=header.dtype)
        for i, name in enumerate(header.dtype.names or ()):
            col = table[:, i]
            kind = header.dtype[name]
            if kind.kind in "iu":
                # the text is parsed as float64: 300 in a uchar wrapped to 44, -1 to 255, 1.5 to 1
                lim = np.iinfo(kind)
                with np.errstate(invalid="ignore"):
                    bad = ~np.isfinite(col) | (col != np.round(col)) | (col < lim.min) | (col > lim.max)
                if bad.any():
                    k = int(np.argmax(bad))
                    raise InputError(path, f"ASCII PLY vertex {k}: {name} is {col[k]:g}, not an integer in "
                                           f"{lim.min}..{lim.max} as its type {_NP_TO_PLY[kind.str[1:]]} holds")
            rec[name] = col
        return rec
    need = header.data_offset + header.count * header.dtype.itemsize
    have = path.stat().st_size
    if have < need:
        raise InputError(path, f"PLY is truncated: {have} bytes, the header promises {need}")
    if header.count == 0:
        return np.empty(0, dtype=header.dtype)
    return np.memmap(path, dtype=header.dtype, mode="r", offset=header.data_offset, shape=(header.count,))


def _to_cloud(rec: np.ndarray) -> PointCloud:
    names = rec.dtype.names or ()
    xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float32, copy=False)
    rgb = None
    if {"red", "green", "blue"} <= set(names):
        rgb = np.stack([rec["red"], rec["green"], rec["blue"]], axis=1)
        if rgb.dtype != np.uint8:
            rgb = np.clip(rgb, 0, 255).astype(np.uint8)
    normals = None
    if {"nx", "ny", "nz"} <= set(names):
        normals = np.stack([rec["nx"], rec["ny"], rec["nz"]], axis=1).astype(np.float32, copy=False)
    size = rec["size"].astype(np.float32, copy=False) if "size" in names else None
    albedo = albedo_weight = None
    if {"albedo_red", "albedo_green", "albedo_blue", "albedo_weight"} <= set(names):
        albedo = np.stack([rec["albedo_red"], rec["albedo_green"], rec["albedo_blue"]], axis=1)
        albedo = np.clip(albedo, 0, 255).astype(np.uint8, copy=False)
        albedo_weight = np.clip(rec["albedo_weight"], 0, 255).astype(np.uint8, copy=False)
    return PointCloud(xyz=xyz, rgb=rgb, normals=normals, size=size, albedo=albedo, albedo_weight=albedo_weight)


def read_ply(path: str | os.PathLike[str]) -> PointCloud:
    """Read a whole PLY point cloud into memory."""
    path = Path(path)
    header = read_header(path)
    return _to_cloud(np.asarray(_records(path, header)))


def iter_ply_records(path: str | os.PathLike[str], chunk: int = CHUNK) -> Iterator[np.ndarray]:
    """Yield a PLY's vertex records as they are stored (every property, the header's dtype), in
    chunks of at most ``chunk`` points (views of a memory map for binary files)."""
    path = Path(path)
    header = read_header(path)
    rec = _records(path, header)
    for start in range(0, header.count, chunk):
        yield rec[start : start + chunk]


def write_ply_records(
    path: str | os.PathLike[str],
    chunks: Iterator[np.ndarray],
    count: int,
    dtype: np.dtype,
    comments: tuple[str, ...] = (),
) -> Path:
    """Write ``count`` records of the structured ``dtype`` (PLY scalar types only), given chunk
    after chunk, as a binary little-endian PLY, atomically. Raises ValueError when the chunks
    do not add up to ``count``."""
    path = Path(path)
    out = np.dtype([(name, dtype[name].newbyteorder("<")) for name in dtype.names or ()])
    written = 0
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        f.write(_header_text(count, out, comments))
        for rec in chunks:
            f.write(np.asarray(rec).astype(out, copy=False).tobytes())
            written += len(rec)
        if written != count:
            raise ValueError(f"{written} records written, the header says {count}")
    return path


def iter_ply_chunks(path: str | os.PathLike[str], chunk: int = CHUNK) -> Iterator[PointCloud]:
    """Yield a PLY's points in chunks of at most ``chunk`` points (memory-mapped for binary files)."""
    path = Path(path)
    header = read_header(path)
    rec = _records(path, header)
    for start in range(0, header.count, chunk):
        yield _to_cloud(np.asarray(rec[start : start + chunk]))
