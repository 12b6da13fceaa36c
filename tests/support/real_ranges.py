"""Range images of the five real captures in ``procam-kamino410``, scanned once per test session.

The five captures are the poses of a calibration session, so the rig is the one our own
calibrator makes from them (``calibrate_session``: reprojection RMS 0.20 / 0.15 px); each
capture is then scanned with it, as ``graylight calibrate`` + ``graylight scan`` would.
(The authors' ``calibration_result.xml`` is no use here: with its projector model every
pixel fails the triangulation's geometry check.) Frames are linked, not copied.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from shared.core.datapaths import shared_data_dir
from shared.formats.capture import numbered_frames, opencv_order_capture, write_capture
from tests.support.links import place_file

REAL = shared_data_dir() / "procam-kamino410"
CAPTURES = [f"capture_{k}" for k in range(5)]
BOARD = {"kind": "chessboard", "inner_corners": [9, 7], "square_size": 75.0}


def available() -> bool:
    return all((REAL / c).is_dir() for c in CAPTURES)


def scan_real_ranges(work: Path) -> dict[str, Path]:
    """Calibrate the session, scan every capture into ``work/<capture>/scan``; their
    ``range.npz`` by capture name."""
    # Slow imports (numba kernels, OpenCV calibration): only when the scans are made.
    from shared.calib.session import calibrate_session
    from shared.scan.pipeline import scan

    session = work / "session"
    session.mkdir(parents=True, exist_ok=True)
    (session / "board.json").write_text(json.dumps(BOARD), encoding="utf-8")
    for k, name in enumerate(CAPTURES):
        cap = session / f"pose_{k:02d}"
        cap.mkdir(exist_ok=True)
        for p in numbered_frames(REAL / name):
            place_file(p, cap / p.name)  # not a symlink: a capture's files lie inside its folder
        write_capture(opencv_order_capture(cap, numbered_frames(cap), 1024, 768))
    calibrate_session(session, work / "calibration")
    rig = work / "calibration" / "rig.json"
    out: dict[str, Path] = {}
    for k, name in enumerate(CAPTURES):
        scan(session / f"pose_{k:02d}", work / name, rig=rig)
        out[name] = work / name / "range.npz"
    return out


def valid_fraction(path: Path) -> float:
    with np.load(path) as d:
        return float(np.mean(~np.isnan(d["z"])))
