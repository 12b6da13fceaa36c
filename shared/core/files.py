"""File helpers every stage shares: reading JSON inputs with clear errors, writing outputs atomically.

``atomic_file(path)`` yields a temporary path beside ``path``; when the block ends without an
exception the file is made world-readable (``mkstemp`` creates it 0600) and renamed onto
``path`` in one step, otherwise it is deleted. Readers never see a half-written output, and a
failed stage leaves nothing behind.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from shared.core.jsonsafe import read_json_bounded


@contextmanager
def atomic_file(path: str | os.PathLike[str], suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary file path in ``path``'s folder; rename it onto ``path`` on success.

    ``suffix`` matters to writers that pick a format from the name (``np.savez`` appends
    ``.npz`` unless the name ends with it; ``cv2.imwrite`` needs an image extension).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_json_atomic(path: str | os.PathLike[str], doc: Any) -> Path:
    """Write ``doc`` as indented JSON to ``path`` through :func:`atomic_file`."""
    path = Path(path)
    with atomic_file(path) as tmp:
        tmp.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return path


def read_json(path: str | os.PathLike[str], missing: str) -> Any:
    """Parse a JSON input file with bounds (:func:`shared.core.jsonsafe.read_json_bounded`: size,
    nesting depth, number length); :class:`InputError` naming the file when it is absent,
    too large, too deep or malformed (never a ``RecursionError``).

    ``missing`` is the problem to report when the file does not exist (it says what the file is for).
    Opened without blocking, regular files only: every JSON input may come from a client.
    """
    return read_json_bounded(path, str(Path(path)), missing=missing)
