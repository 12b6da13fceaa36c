"""The one confinement rule for every path a client names, and non-blocking bounded reads.

A submission (a capture, a scan set, a calibration session, an archive a client uploaded or a
folder it placed in storage) names files by paths inside itself: ``capture.json``'s images and
rig, ``scanset.json``'s views and rig, a preview's camera-path file, a storage reference. The
rule, applied by :func:`confine` to every one of them:

- the path is a non-empty relative string: no absolute path, no ``..`` component, no NUL, no
  backslash (a Windows separator that would mean something else on another machine);
- with every symbolic link followed, it stays inside its own folder (a link leading out is
  refused exactly like an absolute path);
- it names a regular file (or a folder where a folder is meant), never a device, FIFO or socket.

A path that leads out of the folder is refused with one text that depends only on the field and
the value the client gave, never on what lies at the target: a client cannot learn which files
exist on a worker, nor whether they parse. Inside its own folder, "not found" and "not a regular
file" are said plainly (the client made that folder).

Files are opened by :func:`open_regular` with ``O_NONBLOCK`` (opening a FIFO never waits for a
writer) and checked with ``fstat`` before a byte is read; :func:`read_bounded` reads at most a
limit (``/dev/zero`` or a huge file cannot fill the memory).
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Any, BinaryIO

from shared.core.errors import InputError

__all__ = ["confine", "open_regular", "outside_problem", "read_bounded"]

_NOUN = {"file": "file", "dir": "folder", "any": "file or folder"}


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def outside_problem(value: Any, folder: str, kind: str = "file") -> str:
    """The one problem text for a path that is malformed or leads out of ``folder``: it names
    only the value given, so it reads the same whether anything exists at the target or not."""
    return f"must be a relative path to a {_NOUN[kind]} inside the {folder}, got {_short(value)}"


def confine(
    root: str | os.PathLike[str],
    value: Any,
    *,
    where: str | os.PathLike[str],
    folder: str = "submission folder",
    kind: str = "file",
    check: bool = True,
) -> Path:
    """``root / value`` after the confinement rule (module docstring); :class:`InputError` otherwise.

    Parameters
    ----------
    root : path
        The submission's folder the path is relative to.
    value : Any
        What the client wrote (anything: a non-string is refused).
    where : str or path
        How the error names the field (``views[2].cloud``, ``capture.json: field "white"``).
    folder : str
        How the error names ``root`` ("capture folder", "scan set folder").
    kind : str
        ``"file"`` (a regular file), ``"dir"`` (a folder) or ``"any"`` (either).
    check : bool
        Also require the target to exist and be of ``kind``; without it only the syntax and the
        links are checked (for documents written before their files).

    Returns the path ``root / value`` (not resolved: messages keep the client's names).
    """
    if kind not in _NOUN:
        raise ValueError(f"kind must be one of {sorted(_NOUN)}, got {kind!r}")
    bad = InputError(where, outside_problem(value, folder, kind))
    if not isinstance(value, str) or not value or "\x00" in value or "\\" in value:
        raise bad
    rel = Path(value)
    if rel.is_absolute() or ".." in rel.parts or value.startswith("~"):
        raise bad
    base = Path(root)
    target = base / rel
    real_root = os.path.realpath(base)
    real = os.path.realpath(target)  # links followed as far as they lead, whether the end exists or not
    if os.path.commonpath([real_root, real]) != real_root:
        raise bad
    if not check:
        return target
    try:
        st = os.stat(real)
    except OSError:
        raise InputError(where, f"{_short(value)} not found in the {folder}") from None
    if kind == "dir" and not stat.S_ISDIR(st.st_mode):
        raise InputError(where, f"{_short(value)} is not a folder")
    if kind == "file" and not stat.S_ISREG(st.st_mode):
        raise InputError(where, f"{_short(value)} is not a regular file")
    if kind == "any" and not (stat.S_ISREG(st.st_mode) or stat.S_ISDIR(st.st_mode)):
        raise InputError(where, f"{_short(value)} is neither a regular file nor a folder")
    return target


def open_regular(path: str | os.PathLike[str], what: str | os.PathLike[str], *, missing: str = "file not found") -> BinaryIO:
    """Open ``path`` for reading without blocking and only if it is a regular file.

    ``O_NONBLOCK`` makes opening a FIFO return at once (instead of waiting for a writer); the
    ``fstat`` of the open descriptor (not of the name, which could change between the two) must
    say regular file. :class:`InputError` naming ``what`` with ``missing`` when there is nothing
    to open, "is not a regular file" for a folder, device, FIFO or socket.
    """
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise InputError(what, missing) from None
    except IsADirectoryError:
        raise InputError(what, "is not a regular file") from None
    except OSError as exc:
        raise InputError(what, f"cannot be opened ({exc.strerror or 'error'})") from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise InputError(what, "is not a regular file")
        if flags & getattr(os, "O_NONBLOCK", 0):
            os.set_blocking(fd, True)  # a regular file never blocks; plain reads from here on
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_bounded(path: str | os.PathLike[str], what: str | os.PathLike[str], max_bytes: int, *,
                 missing: str = "file not found") -> bytes:
    """The bytes of regular file ``path``, at most ``max_bytes`` of them; a larger file is an
    :class:`InputError` naming ``what`` ("too large"), checked by its size before reading and
    by reading one byte more than the limit (a file that grows while read)."""
    with open_regular(path, what, missing=missing) as f:
        size = os.fstat(f.fileno()).st_size
        if size > max_bytes:
            raise InputError(what, f"file of {size} bytes is too large (at most {max_bytes})")
        data = f.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise InputError(what, f"file is too large (more than {max_bytes} bytes)")
    return data
