"""Paradata of job-service stages, and the source a scan job publishes from.

A stage's record (:func:`record_stage`) is ``.paradata.json`` in its output folder (hidden, beside
the runner's own records); the publish stage's is the job's ``paradata.json``. Upstream outputs
are artifacts that never change once stored, so a stage names them by the sha256 their producer
recorded (:attr:`shared.publish.paradata.Run.trust_recorded`) and reads none twice; the capture is
read by the stages that take nothing else (``ingest``, ``mv_plan``, ``calibrate``) and reaches the
later ones through that record.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Mapping
from datetime import datetime
from pathlib import Path
from typing import Any

from shared.core.files import write_json_atomic
from shared.publish.paradata import PARADATA_FILE, STAGE_PARADATA_FILE, Run, build_paradata, write_paradata
from shared.publish.source import DERIVATIVE_FILES, DERIVATIVES_REPORT

__all__ = ["merge_source", "record_stage", "scan_source"]


def record_stage(*, stage: str, job_id: str, kind: str, params: Mapping[str, Any], capture_dir: Path | None,
                 inputs: Mapping[str, Path], out_dir: Path, started: datetime, ended: datetime,
                 public: bool = False) -> Path:
    """Write the paradata of one job stage into ``out_dir`` (``paradata.json`` when ``public``, else
    ``.paradata.json``); ``inputs`` maps upstream stage rows to their local output folders."""
    ins: dict[str, list[Path]] = {name: [Path(p)] for name, p in sorted(inputs.items())}
    if capture_dir is not None and not inputs:
        ins["capture"] = [Path(capture_dir)]
    run = Run(stage=stage, parameters={"job": job_id, "kind": kind, **dict(params)}, inputs=ins,
              outputs={"out": [out_dir]}, started=started, ended=ended, output_root=out_dir, trust_recorded=True)
    doc = build_paradata(run)
    return write_paradata(out_dir / (PARADATA_FILE if public else STAGE_PARADATA_FILE), doc)


def scan_source(triangulate_dir: Path, capture_dir: Path, rig: Path, work: Path) -> Path:
    """A folder shaped like a ``graylight scan`` output from a scan job's stages (the cloud, a report
    from ``triangulate.json``, the stage's paradata), for :func:`shared.publish.folder.publish_folder`."""
    work.mkdir(parents=True, exist_ok=True)
    (work / "cloud.ply").symlink_to(Path(triangulate_dir).resolve() / "cloud.ply")
    tri_path = Path(triangulate_dir) / "triangulate.json"
    tri = json.loads(tri_path.read_text()) if tri_path.is_file() else {}
    report = {"capture": str(capture_dir), "rig": str(rig), "units": tri.get("units", "mm"),
              "points": tri.get("points"), "triangulate": tri.get("triangulate", {}), "decode": {}}
    write_json_atomic(work / "report.json", report)
    record = Path(triangulate_dir) / STAGE_PARADATA_FILE
    if record.is_file():
        shutil.copyfile(record, work / PARADATA_FILE)
    return work


def merge_source(merge_dir: Path, derivatives_dir: Path | None, work: Path) -> Path:
    """A folder shaped like a ``graylight merge`` output that ``graylight derivatives`` wrote into,
    from a multiview job's ``mv_merge`` output and its ``derivatives`` output (None when the job
    leaves them out: the merge's own levels are published). Files are linked, not copied."""
    work.mkdir(parents=True, exist_ok=True)
    merge_dir = Path(merge_dir).resolve()
    for p in sorted(merge_dir.iterdir()):
        if p.is_file() and not p.name.startswith("mesh_") or p.name.startswith("mesh_lod"):
            (work / p.name).symlink_to(p)
    if derivatives_dir is not None:
        for p in sorted(Path(derivatives_dir).resolve().iterdir()):
            if p.is_file() and (p.name in DERIVATIVE_FILES.values() or p.name == DERIVATIVES_REPORT):
                (work / p.name).symlink_to(p)
    return work
