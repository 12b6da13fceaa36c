"""What a ``graylight merge`` or ``graylight scan`` output folder holds, read once for publishing.

A merge output has ``registration.json`` and ``report.json`` (with ``registered_views``); a scan
output ``report.json`` (with ``decode``), ``cloud.ply`` and ``range.npz``. The model's levels are
found by name (:data:`LEVEL_FILES`, the derivatives' names first, then the merge's LODs); a scan
has no mesh, so its model is the cloud (:mod:`shared.publish.glb` writes it as a GLB of points).
An older folder lacking what publishing needs is an :class:`InputError` naming the file and the
field; blocks that only enrich the report (a quality block, fusion counts) may be absent.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from shared.core.errors import InputError
from shared.core.jsonsafe import read_json_bounded

log = logging.getLogger(__name__)

__all__ = ["DERIVATIVES_REPORT", "DERIVATIVE_FILES", "LEGACY_LOD_FILES", "QUALITIES", "Source", "read_source"]

#: Voyager's quality levels, lowest first.
QUALITIES = ("Thumb", "Low", "Medium", "High", "Highest")
#: Derivative files by quality (issue 23's textured levels; agreed in the coordination notes).
DERIVATIVE_FILES = {q: f"mesh_{q.lower()}.glb" for q in QUALITIES}
#: Without derivatives, the merge's own levels stand in (1/64, 1/16, 1/4 of the faces, the full mesh).
LEGACY_LOD_FILES = {"Thumb": "mesh_lod3.glb", "Low": "mesh_lod2.glb", "Medium": "mesh_lod1.glb", "High": "mesh.glb"}
#: The report ``graylight derivatives`` writes beside its levels (shared.derive.pipeline.REPORT_FILE).
DERIVATIVES_REPORT = "derivatives.json"
_REPORT_BYTES = 64 << 20


@dataclass
class Source:
    """A scan's or a merge's output folder: its kind (``merge`` or ``scan``), its records and model files."""

    root: Path
    kind: str
    report: dict[str, Any]
    registration: dict[str, Any] | None
    levels: dict[str, Path]  # quality -> GLB (empty for a scan: its cloud is published as points)
    cloud: Path
    paradata: Path | None
    quality: dict[str, Any] | None = None
    notes: list[str] = field(default_factory=list)
    #: ``derivatives.json`` of the textured levels (colour baked, bridged share, per level), None without.
    derivatives: dict[str, Any] | None = None


def _read(path: Path, what: str) -> dict[str, Any]:
    doc = read_json_bounded(path, what, missing=f"{what} not found", max_bytes=_REPORT_BYTES)
    if not isinstance(doc, dict):
        raise InputError(path, f"{what}: must be a JSON object")
    return doc


def read_source(root: Path) -> Source:
    """Read a merge or scan output folder; :class:`InputError` naming what is missing when it is neither."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, "not a folder (give a graylight merge or scan output folder)")
    report_path = root / "report.json"
    if not report_path.is_file():
        raise InputError(root, "no report.json: not a graylight merge or scan output folder")
    report = _read(report_path, "report.json")
    # A CLI output's paradata, or a job stage's record (the merge stage's output folder).
    paradata = next((p for p in (root / "paradata.json", root / ".paradata.json") if p.is_file()), None)
    notes: list[str] = []
    if (root / "registration.json").is_file() or "registered_views" in report:
        registration = _read(root / "registration.json", "registration.json")
        if not isinstance(registration.get("views"), list):
            raise InputError(root / "registration.json", "views: missing (an older Graylight's registration?)")
        cloud = root / "merged.ply"
        if not cloud.is_file():
            raise InputError(cloud, "the merged cloud is missing")
        levels = {q: root / n for q, n in DERIVATIVE_FILES.items() if (root / n).is_file()}
        derivatives = None
        if levels and (root / DERIVATIVES_REPORT).is_file():
            derivatives = _read(root / DERIVATIVES_REPORT, DERIVATIVES_REPORT)
            notes += [f"derivatives: {w}" for w in derivatives.get("warnings", []) if isinstance(w, str)]
        elif levels:
            notes.append(f"textured derivatives without their {DERIVATIVES_REPORT}: how they were made is not shown")
        if not levels:
            levels = {q: root / n for q, n in LEGACY_LOD_FILES.items() if (root / n).is_file()}
            if levels:
                notes.append("no textured derivatives (mesh_thumb.glb ...): the merge's own levels are published")
        if not levels:
            notes.append("no mesh in the merge output: the merged cloud is published as points")
        quality = registration.get("quality") if isinstance(registration.get("quality"), dict) else None
        quality = quality or (report.get("quality") if isinstance(report.get("quality"), dict) else None)
        if quality is None:
            notes.append("the merge wrote no quality block (an older Graylight): registration flags not shown")
        return Source(root, "merge", report, registration, levels, cloud, paradata, quality, notes, derivatives)
    if "decode" in report or (root / "cloud.ply").is_file():
        cloud = root / "cloud.ply"
        if not cloud.is_file():
            raise InputError(cloud, "the scan's cloud is missing")
        notes.append("a single view: its cloud is published as points (no mesh)")
        return Source(root, "scan", report, None, {}, cloud, paradata, None, notes)
    raise InputError(report_path, "neither a merge report (registered_views) nor a scan report (decode)")
