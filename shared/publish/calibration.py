"""The calibration evidence behind a rig, when ``graylight calibrate`` made it.

``graylight calibrate SESSION --out rig.json`` writes ``rig-report.json`` beside the rig (format
``graylight-calibration-v1``; the job stage writes ``calibration.json``). A rig with such a report
beside it, whose ``rig`` block equals the rig file's numbers, came from that session; the report's
reprojection errors per pose and its board check (the board's squares triangulated with the rig)
are the evidence the quality report shows. A rig without one (simulated, imported from OpenCV)
has no session figures, and the report says so.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shared.core.errors import InputError
from shared.core.jsonsafe import finite_number, read_json_bounded

__all__ = ["CALIBRATION_FORMAT", "CalibrationReport", "calibration_report_for"]

CALIBRATION_FORMAT = "graylight-calibration-v1"


@dataclass(frozen=True)
class CalibrationReport:
    """A calibration session's figures: ``rms_px`` per device (px), per-pose rows, the board check."""

    path: Path
    rms_px: dict[str, float]
    poses: list[dict[str, Any]]
    board_check: dict[str, Any]
    baseline: float | None
    units: str

    def summary(self) -> dict[str, Any]:
        """The figures that say how good the rig is, for paradata and the quality report."""
        used = [p for p in self.poses if p.get("used")]
        return {"report": str(self.path), "rms_px": self.rms_px, "poses_used": len(used), "poses": len(self.poses),
                "skipped": {p.get("name", "?"): p.get("reason") for p in self.poses if not p.get("used")},
                "board_square_rms_error_pct": self.board_check.get("square_rms_error_pct"),
                "board_square_size": self.board_check.get("square_size"), "baseline": self.baseline,
                "units": self.units}


def _same_rig(a: Any, b: Any, tol: float = 1e-9) -> bool:
    """Whether two rig documents hold the same numbers (a report describes this rig, not an older one)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same_rig(a[k], b[k], tol) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same_rig(x, y, tol) for x, y in zip(a, b, strict=True))
    if finite_number(a) and finite_number(b):
        return abs(float(a) - float(b)) <= tol * max(1.0, abs(float(a)))
    return a == b


def calibration_report_for(rig_path: Path) -> CalibrationReport | None:
    """The calibration report of the session that made ``rig_path`` (``<stem>-report.json`` or
    ``calibration.json`` beside it, whose rig matches), or None."""
    try:
        rig = read_json_bounded(rig_path, "rig", missing="rig file not found")
    except InputError:
        return None
    for cand in (rig_path.with_name(f"{rig_path.stem}-report.json"), rig_path.with_name("calibration.json")):
        if not cand.is_file():
            continue
        try:
            doc = read_json_bounded(cand, "calibration report", missing="not found")
        except InputError:
            continue
        if not isinstance(doc, dict) or doc.get("format") != CALIBRATION_FORMAT:
            continue
        if not _same_rig(doc.get("rig"), rig):
            continue
        rms = doc.get("rms_px") if isinstance(doc.get("rms_px"), dict) else {}
        poses = [p for p in doc.get("poses", []) if isinstance(p, dict)]
        board = doc.get("board_check") if isinstance(doc.get("board_check"), dict) else {}
        baseline = doc.get("baseline") if finite_number(doc.get("baseline")) else None
        return CalibrationReport(cand, {k: float(v) for k, v in rms.items() if finite_number(v)}, poses, board, baseline,
                                 str(doc.get("units", "mm")))
    return None
