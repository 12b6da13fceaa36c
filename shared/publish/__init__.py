"""Publishing an object the way museums do: paradata (how it was made, W3C PROV as JSON-LD), a
quality report a conservator can read (``qa.json``, ``qa.html``) and a Smithsonian Voyager scene
(``scene.svx.json`` with its derivatives), from the outputs of ``graylight scan`` and ``graylight merge``.

It reads what the domains wrote (files), so it sits above ``shared.merge`` in the layers; names
resolve lazily.
"""

from shared.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "PARADATA_FILE": "paradata", "PARADATA_FORMAT": "paradata", "Run": "paradata",
        "build_paradata": "paradata", "load_paradata": "paradata", "write_paradata": "paradata",
        "paradata_path_for": "paradata", "sha256_file": "paradata", "software": "paradata",
        "main_activity": "paradata", "rig_figures": "paradata",
        "CalibrationReport": "calibration", "calibration_report_for": "calibration",
    },
)  # fmt: skip
