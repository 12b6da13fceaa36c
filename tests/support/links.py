"""Placing the shared data's files into a test's capture or scan-set folder.

A submission's paths must lie inside its own folder once symbolic links are followed
(``shared/core/paths.py``), so a folder of symlinks to ``/work/shared/data`` is refused like any
other link leading out. Hard links cost as little (the same filesystem) and are files of the
folder; across filesystems the file is copied.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path


def place_file(src: Path, dst: Path) -> Path:
    """``dst`` a hard link to ``src`` (a copy where links cannot cross filesystems); kept if present
    (a symbolic link left by an older cache is replaced)."""
    if dst.is_symlink():
        dst.unlink()
    if not dst.exists():
        try:
            os.link(src, dst)
        except OSError:
            shutil.copyfile(src, dst)
    return dst
