"""The virtual rig: physically plausible captures of analytic and mesh scenes with ground
truth, and simulated calibration sessions."""

from shared.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "ImagingParams": "simulate",
        "Truth": "truth",
        "load_truth": "truth",
        "make_rig": "rigs",
        "compute_truth": "simulate",
        "simulate_capture": "simulate",
        "simulate_named": "simulate",
        "Scene": "scenes",
        "Material": "scenes",
        "TexturedPlane": "scenes",
        "Sphere": "scenes",
        "MeshObject": "scenes",
        "build_scene": "scenes",
        "rotation_about": "scenes",
        "mesh_path": "scenes",
        "LABELS": "scenes",
        "apply_response": "response",
        "linearise": "response",
        "BoardPose": "calibration",
        "SimulatedSession": "calibration",
        "random_board_poses": "calibration",
        "simulate_session": "calibration",
        "load_simulated_session": "calibration",
    },
)
