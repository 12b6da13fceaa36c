"""Scanning: Gray codes, decoding camera pixels to projector columns and rows, triangulation,
and the single-view scan stages (ingest, decode, triangulate).

Names resolve lazily: the numba kernels load on first use."""

from shared.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "gray_encode": "graycode",
        "gray_decode": "graycode",
        "stripe_bits": "graycode",
        "pattern_image": "graycode",
        "pattern_sequence": "graycode",
        "capture_for_names": "graycode",
        "DecodeParams": "decode",
        "Decoded": "decode",
        "decode_capture": "decode",
        "decode_stack": "decode",
        "save_decoded": "decode",
        "load_decoded": "decode",
        "kernel_threads": "decode",
        "kernel_thread_scope": "decode",
        "Triangulated": "triangulate",
        "triangulate": "triangulate",
        "ingest_stage": "pipeline",
        "decode_stage": "pipeline",
        "triangulate_stage": "pipeline",
        "scan": "pipeline",
        "view_albedo": "pipeline",
        "AlbedoParams": "albedo",
        "CameraResponse": "albedo",
        "SampleAlbedo": "albedo",
        "estimate_albedo": "albedo",
        "parse_response": "albedo",
        "params_for_rig": "albedo",
        "response_for_rig": "albedo",
        "projector_geometry": "albedo",
        "smooth_normals": "albedo",
    },
)
