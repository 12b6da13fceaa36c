"""Calibration of camera and projector from board sessions (Moreno-Taubin local homographies,
stereo refinement) and the calibration stage."""

from shared.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "Board": "board",
        "Detection": "board",
        "parse_board": "board",
        "load_board": "board",
        "detect_board": "board",
        "calibrate_camera": "calibrate",
        "calibrate_rig": "calibrate",
        "projector_corners": "calibrate",
        "triangulate_corners": "calibrate",
        "CameraCalibration": "calibrate",
        "RigCalibration": "calibrate",
        "Session": "session",
        "SessionResult": "session",
        "load_session": "session",
        "run_session": "session",
        "write_outputs": "session",
        "write_opencv_yaml": "session",
        "calibrate_camera_images": "session",
        "calibrate_session": "session",
    },
)
