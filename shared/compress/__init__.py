"""Range compression: a quadtree codec for range images and an octree codec for point clouds.

Both write the Graylight container (:mod:`shared.formats.container`): ``.glr`` for range
images (kind ``range``), ``.glo`` for clouds (kind ``cloud``); :mod:`~shared.compress.tilenode`
codes the nodes of Potree tiles (their opt-in "GRAYLIGHT_OCTREE" encoding). The numba kernels live in
private modules (``_rans``, ``_quadtree``, ``_octree``), the functions only kernels call as
:func:`shared.core.jit.helper` (compiled once, no Python entry point, inlined by LLVM);
importing this package is cheap, its names load on first use.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = [
    "decode_cloud",
    "encode_cloud",
    "iter_cloud",
    "read_cloud_to_ply",
    "write_cloud",
    "RangeImage",
    "check_camera",
    "check_range",
    "decode_range",
    "encode_range",
    "expected_lossless",
    "load_range_npz",
    "read_range",
    "save_range_npz",
    "write_range",
    "decode_node",
    "encode_node",
]

_CLOUD = {"decode_cloud", "encode_cloud", "iter_cloud", "read_cloud_to_ply", "write_cloud"}
_HOME = {name: "shared.compress.cloud" if name in _CLOUD else "shared.compress.range" for name in __all__}
_HOME.update(decode_node="shared.compress.tilenode", encode_node="shared.compress.tilenode")
_ALIASES = {"decode_range": "read_range"}


def __getattr__(name: str) -> Any:
    # Lazy: the kernels compile (or load from numba's cache) on first use, not on import.
    if name not in _HOME:
        raise AttributeError(f"module 'shared.compress' has no attribute {name!r}")
    return getattr(importlib.import_module(_HOME[name]), _ALIASES.get(name, name))
