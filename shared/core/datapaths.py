"""Where the read-only shared data lives: ``../shared/data`` beside the repository.

``GRAYLIGHT_SHARED_DATA`` overrides it. Tests and benchmarks read real captures and
meshes from there by path; nothing is copied into the repository.
"""

from __future__ import annotations

import os
from pathlib import Path


def shared_data_dir() -> Path:
    """The shared data folder (it may not exist on a machine outside the workplace)."""
    env = os.environ.get("GRAYLIGHT_SHARED_DATA")
    if env:
        return Path(env)
    # shared/core/datapaths.py: parents[2] is the repository root.
    return (Path(__file__).resolve().parents[2] / ".." / "shared" / "data").resolve()
