"""Multi-view scanning: register, fuse and mesh the views of a scan set (``graylight-scanset-v1``).

Base types live in :mod:`shared.merge.views` (:class:`ViewCloud`, one view's points and range
image); the algorithms in :mod:`shared.merge.registration`, :mod:`shared.merge.fusion` and
:mod:`shared.merge.meshing`; :mod:`shared.merge.pipeline` runs the whole merge (``graylight merge``).
Names are imported lazily: numba kernels and Open3D load slowly.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "ViewCloud": "views", "load_view": "views", "load_views": "views", "crop_to_roi": "views",
    "estimate_normals": "views", "view_from_scan_outputs": "views",
    "Registration": "registration", "RegistrationParams": "registration", "register_views": "registration",
    "axis_from_poses": "registration", "pose_error": "registration",
    "FusionParams": "fusion", "FusedCloud": "fusion", "fuse_views": "fusion",
    "MeshParams": "meshing", "reconstruct_mesh": "meshing", "simplify_lods": "meshing", "write_mesh": "meshing",
    "merge_scanset": "pipeline",
}  # fmt: skip

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"shared.merge.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'shared.merge' has no attribute {name!r}")
