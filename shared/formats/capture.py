"""The capture contract ``graycode-v1``: reading, validating and writing ``capture.json``.

A capture is a folder of camera images of Gray-code stripe patterns thrown by a
projector, plus an all-white and an all-black frame, described by ``capture.json``::

    {"format": "graycode-v1",
     "projector": {"width": 1024, "height": 768},
     "white": "white.png", "black": "black.png",
     "columns": [{"bit": 9, "pattern": "col_00.png", "inverse": "col_00_inv.png"}, ...],
     "rows": [...],
     "rig": "rig.json"}

Projector column ``c`` is encoded by the binary-reflected Gray code ``g = c ^ (c >> 1)``;
the entry with ``"bit": k`` lights column ``c`` iff bit ``k`` of ``g`` is 1 and its
``inverse`` lights the complement; rows likewise. Entries are listed most significant
bit first (OpenCV ``GrayCodePattern`` order). ``inverse`` may be absent, ``rows`` may be
absent or empty, the finest bits may be left out (a coarser code), ``rig`` is optional.

This module is the one place the contract is defined; the CLI, the job service and
the virtual rig all read and write captures through it.
"""

from __future__ import annotations

import math
import os
import stat
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from shared.core.errors import InputError
from shared.core.files import read_json, write_json_atomic
from shared.core.paths import confine

FORMAT = "graycode-v1"
CAPTURE_FILE = "capture.json"
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp")
#: Largest projector side we accept; real projectors stop far below this.
MAX_PROJECTOR_SIDE = 16384


def code_bits(n: int) -> int:
    """Number of Gray-code bits needed to give each of ``n`` projector columns (or rows) its own code."""
    if n < 2:
        raise ValueError(f"need at least 2 projector columns or rows, got {n}")
    return math.ceil(math.log2(n))


@dataclass(frozen=True)
class CodeImage:
    """One Gray-code bit plane: the camera image of the pattern and, if captured, of its inverse."""

    bit: int
    pattern: Path
    inverse: Path | None = None


@dataclass(frozen=True)
class Capture:
    """A validated ``graycode-v1`` capture. Paths are absolute."""

    root: Path
    projector_width: int
    projector_height: int
    white: Path
    black: Path
    columns: tuple[CodeImage, ...]
    rows: tuple[CodeImage, ...] = ()
    rig: Path | None = None
    extra: dict[str, Any] = field(default_factory=dict, compare=False)

    @property
    def column_bits(self) -> int:
        """Bits of a full column code for this projector width."""
        return code_bits(self.projector_width)

    @property
    def row_bits(self) -> int:
        """Bits of a full row code for this projector height."""
        return code_bits(self.projector_height)

    @property
    def column_lowest_bit(self) -> int:
        """Lowest column bit captured: 0 for a full code, more when the finest bits were left out."""
        return min(e.bit for e in self.columns)

    @property
    def row_lowest_bit(self) -> int | None:
        return min(e.bit for e in self.rows) if self.rows else None

    def image_paths(self) -> list[Path]:
        """Every image the capture refers to, white and black first."""
        paths = [self.white, self.black]
        for entry in (*self.columns, *self.rows):
            paths.append(entry.pattern)
            if entry.inverse is not None:
                paths.append(entry.inverse)
        return paths

    def to_json(self) -> dict[str, Any]:
        """The ``capture.json`` document. Its paths are relative to ``root``, always (that is
        how :func:`parse_capture` reads them); a file outside ``root`` is an :class:`InputError`."""
        root = Path(self.root).absolute()

        def rel(p: Path) -> str:
            try:
                return Path(p).absolute().relative_to(root).as_posix()
            except ValueError:
                raise InputError(p, f"lies outside the capture folder {root}: capture.json paths are relative to it") from None

        def entries(es: Sequence[CodeImage]) -> list[dict[str, Any]]:
            out = []
            for e in es:
                d: dict[str, Any] = {"bit": e.bit, "pattern": rel(e.pattern)}
                if e.inverse is not None:
                    d["inverse"] = rel(e.inverse)
                out.append(d)
            return out

        doc: dict[str, Any] = {
            "format": FORMAT,
            "projector": {"width": self.projector_width, "height": self.projector_height},
            "white": rel(self.white),
            "black": rel(self.black),
            "columns": entries(self.columns),
            "rows": entries(self.rows),
        }
        if self.rig is not None:
            doc["rig"] = rel(self.rig)
        doc.update({k: v for k, v in self.extra.items() if k not in doc})
        return doc


#: The keys of each object of the contract; any other is an error naming it (a misspelt
#: "inverse" silently ignored would decode without the inverse images). "simulated" holds what
#: ``graylight simulate`` wrote about the scene (free-form; readers ignore it).
_TOP_KEYS = ("format", "projector", "white", "black", "columns", "rows", "rig", "simulated")
_PROJECTOR_KEYS = ("width", "height")
_ENTRY_KEYS = ("bit", "pattern", "inverse")
#: Most code entries a list may hold: the bits of the largest projector side.
MAX_CODE_BITS = 14


def _short(value: Any) -> str:
    """``repr`` cut to a short excerpt: an error never echoes a client's whole value."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _no_unknown(obj: dict[str, Any], known: Sequence[str], where: Path, parent: str | None) -> None:
    """:class:`InputError` naming the first key of ``obj`` that the contract does not know."""
    for k in obj:
        if k not in known:
            at = f'in "{parent}"' if parent else "at the top level"
            raise InputError(where, f'unknown field {_short(k)} {at} (allowed: {", ".join(known)})')


def _require(doc: dict[str, Any], key: str, where: Path) -> Any:
    if key not in doc:
        raise InputError(where, f'missing field "{key}"')
    return doc[key]


def _confined(root: Path, value: Any, where: Path, field_name: str) -> Path:
    """``root / value`` under the one confinement rule (:func:`shared.core.paths.confine`): relative,
    inside the capture folder with links followed. Whether the file is there is :func:`check_files`'s."""
    try:
        return confine(root, value, where=where, folder="capture folder", check=False)
    except InputError as exc:
        raise InputError(where, f'field "{field_name}" {exc.problem}') from None


def _image_path(root: Path, value: Any, where: Path, field_name: str) -> Path:
    p = _confined(root, value, where, field_name)
    if p.suffix.lower() not in IMAGE_SUFFIXES:
        raise InputError(where, f'field "{field_name}": {value!r} is not a PNG, TIFF, JPEG or BMP file name')
    return p


def _code_entries(
    root: Path, doc: dict[str, Any], key: str, nbits: int, where: Path
) -> tuple[CodeImage, ...]:
    raw = doc.get(key) or []
    if not isinstance(raw, list):
        raise InputError(where, f'field "{key}" must be a list')
    out: list[CodeImage] = []
    if len(raw) > MAX_CODE_BITS:
        raise InputError(where, f'field "{key}" lists {len(raw)} patterns (a projector of this size has {nbits} bits)')
    for i, e in enumerate(raw):
        name = f"{key}[{i}]"
        if not isinstance(e, dict):
            raise InputError(where, f'field "{name}" must be an object')
        _no_unknown(e, _ENTRY_KEYS, where, name)
        bit = _require(e, "bit", where)
        if not isinstance(bit, int) or isinstance(bit, bool) or not 0 <= bit < nbits:
            raise InputError(
                where,
                f'field "{name}.bit" is {_short(bit)}, but a projector of this size has {nbits} bits (0..{nbits - 1})',
            )
        pattern = _image_path(root, _require(e, "pattern", where), where, f"{name}.pattern")
        inverse = e.get("inverse")
        inv = _image_path(root, inverse, where, f"{name}.inverse") if inverse is not None else None
        out.append(CodeImage(bit=bit, pattern=pattern, inverse=inv))
    bits = [e.bit for e in out]
    if len(set(bits)) != len(bits):
        raise InputError(where, f'field "{key}" lists a bit more than once: {bits}')
    if out:
        expected = list(range(nbits - 1, nbits - 1 - len(out), -1))
        if bits != expected:
            raise InputError(
                where,
                f'field "{key}" has {len(out)} patterns with bits {bits}, but a projector of this size needs '
                f"bits {nbits - 1}..0 listed most significant first (the finest may be left out): expected {expected}",
            )
    return tuple(out)


def parse_capture(doc: Any, root: Path, where: Path | None = None) -> Capture:
    """Validate a ``capture.json`` document whose image paths are relative to ``root``.

    Raises :class:`InputError` naming ``where`` (default ``root/capture.json``) and the field.
    Image files are not opened here; :func:`check_files` checks that they exist.
    """
    root = Path(root).absolute()
    where = where or root / CAPTURE_FILE
    if not isinstance(doc, dict):
        raise InputError(where, "must be a JSON object")
    fmt = doc.get("format")
    if fmt != FORMAT:
        raise InputError(where, f'field "format" is {_short(fmt)}, expected "{FORMAT}"')
    _no_unknown(doc, _TOP_KEYS, where, None)
    proj = _require(doc, "projector", where)
    if not isinstance(proj, dict):
        raise InputError(where, 'field "projector" must be an object with "width" and "height"')
    _no_unknown(proj, _PROJECTOR_KEYS, where, "projector")
    w, h = proj.get("width"), proj.get("height")
    for name, v in (("width", w), ("height", h)):
        if not isinstance(v, int) or isinstance(v, bool) or not 2 <= v <= MAX_PROJECTOR_SIDE:
            raise InputError(where, f'field "projector.{name}" must be an integer in 2..{MAX_PROJECTOR_SIDE}, got {_short(v)}')
    columns = _code_entries(root, doc, "columns", code_bits(w), where)
    if not columns:
        raise InputError(where, 'field "columns" must list at least one pattern')
    rows = _code_entries(root, doc, "rows", code_bits(h), where)
    rig_value = doc.get("rig")
    rig = _confined(root, rig_value, where, "rig") if rig_value is not None else None
    simulated = doc.get("simulated")
    if simulated is not None and not isinstance(simulated, dict):
        raise InputError(where, 'field "simulated" must be an object (what graylight simulate wrote)')
    return Capture(
        root=root,
        projector_width=w,
        projector_height=h,
        white=_image_path(root, _require(doc, "white", where), where, "white"),
        black=_image_path(root, _require(doc, "black", where), where, "black"),
        columns=columns,
        rows=rows,
        rig=rig,
        extra={"simulated": simulated} if simulated is not None else {},
    )


def check_files(capture: Capture) -> None:
    """Raise :class:`InputError` naming the first image file that is missing, not a regular file
    (a FIFO or device would block or never end a read) or empty."""
    for p in capture.image_paths():
        try:
            st = p.stat()
        except OSError:
            raise InputError(p, "image file is missing") from None
        if not stat.S_ISREG(st.st_mode):
            raise InputError(p, "image is not a regular file")
        if st.st_size == 0:
            raise InputError(p, "image file is empty")


def load_capture(path: str | os.PathLike[str], check: bool = True) -> Capture:
    """Read and validate a capture from its folder or its ``capture.json``.

    With ``check`` (the default) every image file must exist and be non-empty.
    """
    p = Path(path)
    if p.is_dir():
        p = p / CAPTURE_FILE
    doc = read_json(p, "capture description not found (a capture folder needs a capture.json)")
    capture = parse_capture(doc, p.parent, where=p)
    if check:
        check_files(capture)
    return capture


def write_capture(capture: Capture, path: str | os.PathLike[str] | None = None) -> Path:
    """Write ``capture.json`` (into ``capture.root`` unless ``path`` says otherwise); returns its path."""
    out = Path(path) if path is not None else capture.root / CAPTURE_FILE
    if out.is_dir():
        out = out / CAPTURE_FILE
    write_json_atomic(out, capture.to_json())
    return out


def opencv_order_capture(
    root: Path,
    frames: Sequence[Path],
    projector_width: int,
    projector_height: int,
    white_index: int | None = None,
    black_index: int | None = None,
    rig: Path | None = None,
) -> Capture:
    """Describe frames in OpenCV ``GrayCodePattern`` order as a capture.

    OpenCV's order is: every column bit (most significant first), each pattern followed
    by its inverse, then the rows likewise, then white, then black. ``white_index`` and
    ``black_index`` default to the two frames after the patterns.
    """
    cb, rb = code_bits(projector_width), code_bits(projector_height)
    n_patterns = 2 * (cb + rb)
    white_index = n_patterns if white_index is None else white_index
    black_index = n_patterns + 1 if black_index is None else black_index
    needed = max(n_patterns, white_index + 1, black_index + 1)
    if len(frames) < needed:
        raise InputError(
            root,
            f"{len(frames)} frames, but a {projector_width}x{projector_height} projector in OpenCV order needs "
            f"{n_patterns} pattern frames plus white and black ({needed} in all)",
        )
    # Absolute, so that capture.json (relative to the capture folder) comes out right whatever
    # the working directory: `import-sequence c0` must not write "c0/graycode_40.png".
    frames = [Path(f).absolute() for f in frames]
    rig = Path(rig).absolute() if rig is not None else None
    pattern_frames = [f for i, f in enumerate(frames) if i not in (white_index, black_index)][:n_patterns]
    cols = tuple(
        CodeImage(bit=cb - 1 - k, pattern=pattern_frames[2 * k], inverse=pattern_frames[2 * k + 1]) for k in range(cb)
    )
    rows = tuple(
        CodeImage(bit=rb - 1 - k, pattern=pattern_frames[2 * (cb + k)], inverse=pattern_frames[2 * (cb + k) + 1])
        for k in range(rb)
    )
    return Capture(
        root=Path(root).absolute(),
        projector_width=projector_width,
        projector_height=projector_height,
        white=frames[white_index],
        black=frames[black_index],
        columns=cols,
        rows=rows,
        rig=rig,
    )


def numbered_frames(folder: Path) -> list[Path]:
    """Image files of ``folder`` sorted by the number in their name (``graycode_07.png`` before ``graycode_10.png``)."""
    import re

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "not a folder")
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    if not files:
        raise InputError(folder, "no PNG, TIFF, JPEG or BMP images in this folder")

    def key(p: Path) -> tuple[int, str]:
        nums = re.findall(r"\d+", p.stem)
        return (int(nums[-1]) if nums else -1, p.name)

    keyed = sorted(files, key=key)
    numbers = [key(p)[0] for p in keyed]
    if -1 in numbers or len(set(numbers)) != len(numbers):
        raise InputError(folder, "frame file names must each carry a distinct number (e.g. graycode_00.png)")
    return keyed
