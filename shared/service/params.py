"""Job parameters: the schema every job's ``params`` object is checked against, in one place.

``POST /v1/jobs``, ``POST /v1/batches`` and ``POST /v1/jobs/{id}/retry`` call
:func:`check_job_params` before anything is stored or queued, so a bad ``preview`` size is a
422 naming ``params.preview.size`` instead of a job that fails after decode, triangulation
and tiles have run. The stage adapters read the same checked values.

========================  =========  =============================================================
key                       kinds      meaning (mv: multiview)
========================  =========  =============================================================
``render``                scan, mv   ``false`` leaves out tiles and preview (and what follows them)
``export``                scan, mv   ``false`` leaves out the LAZ / COPC / E57 export (of the
                                     scan's cloud, or of a multiview job's merged cloud)
``drop_unregistered``     mv         ``true`` leaves out views that register to nothing
``tiles``                 scan, mv   ``{"max_chunk": 100..5e7, "max_leaf": 100..1e6,
                                     "node_codec": "plain" | "octree"}`` (octree-coded nodes: opt-in)
``preview``               scan, mv   ``{"path": "auto"|"arc"|"orbit"|"dolly", "size": [w, h],
                                     "seconds", "fps"}`` or, instead of ``path``, ``"camera":
                                     {"fov", "keyframes": [{"eye", "target"}, ...]}`` inline
                                     (:class:`shared.render.options.PreviewOptions`); never a file
                                     on the worker
``compress``              scan, mv   ``{"quantum": q}`` or ``{"max_error": e}`` (rig units, (0, 1000]; default
                                     lossless at 0.02 mm) and ``"keep_range"``: false publishes
                                     ``range.glr`` only, not the raw ``range.npz``, and deletes
                                     the raw image once ``range.glr`` is stored (default true)
``seconds``               probe      how long the self-test stage sleeps, 0..60
========================  =========  =============================================================

``rig`` and ``preview_epoch`` are set by the service itself (an uploaded rig, the nightly
re-render) and refused from clients.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from shared.core.errors import InputError
from shared.core.jsonsafe import finite_number
from shared.derive.levels import parse_levels
from shared.publish.labels import LABEL_PATTERN, MAX_LABEL_CHARS, check_label
from shared.render.camera_path import MAX_COORDINATE, MAX_INLINE_KEYFRAMES, NAMED_PATHS
from shared.render.options import MAX_FPS, MAX_HEIGHT, MAX_SECONDS, MAX_WIDTH, MIN_SIDE, PreviewOptions

__all__ = ["MAX_PARAMS_BYTES", "MAX_PROBE_SECONDS", "PARAMS", "Param", "params_schema", "SERVICE_PARAMS", "check_job_params", "compress_options",
           "tiles_options"]

#: Largest ``params`` object accepted, as JSON.
MAX_PARAMS_BYTES = 16384
#: Longest a probe stage may sleep, seconds.
MAX_PROBE_SECONDS = 60.0
#: Parameters the service sets itself; a client may not send them.
SERVICE_PARAMS = frozenset({"rig", "preview_epoch"})

_TILE_OPTIONS = ("max_chunk", "max_leaf")
#: Upper bounds of the tiling options, points: a chunk is built in one worker's memory (50 M
#: points is about 2 GB of records), a leaf is one node a viewer fetches whole. Past these a job
#: would fail late (``max_chunk`` of 1e30 raised OverflowError after the job had run).
_TILE_MAX = {"max_chunk": 50_000_000, "max_leaf": 1_000_000}
#: Largest compression step or error bound, rig units (a metre in mm): coarser is no longer a scan.
MAX_QUANTUM = 1000.0
#: ``params.tiles.node_codec``: how octree.bin stores nodes (shared.render.octree.NODE_CODECS).
_NODE_CODECS = ("plain", "octree")


def _short(value: Any) -> str:
    """``repr`` cut to a short excerpt: an error never echoes a client's whole value."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def tiles_options(value: Any, field: str = "params.tiles") -> dict[str, Any]:
    """``params.tiles`` checked: an object with integer ``max_chunk`` and/or ``max_leaf`` >= 100
    and ``node_codec`` "plain" (the default) or "octree"."""
    if value is None:
        return {}
    if not isinstance(value, Mapping) or set(value) - {*_TILE_OPTIONS, "node_codec"}:
        raise InputError(field, f"must be an object with max_chunk, max_leaf and/or node_codec, got {_short(value)}")
    for k, v in value.items():
        if k == "node_codec":
            if v not in _NODE_CODECS:
                raise InputError(f"{field}.{k}", f"must be one of {', '.join(_NODE_CODECS)}, got {_short(v)}")
            continue
        if not isinstance(v, int) or isinstance(v, bool) or not 100 <= v <= _TILE_MAX[k]:
            raise InputError(f"{field}.{k}", f"must be an integer in 100..{_TILE_MAX[k]}, got {_short(v)}")
    return dict(value)


def _switch(value: Any, field: str) -> bool:
    if not isinstance(value, bool):
        raise InputError(field, f"must be true or false, got {value!r}")
    return value


def _preview(value: Any, field: str) -> dict[str, Any]:
    if not isinstance(value, Mapping):  # from_mapping takes None for the defaults; a job's params may not
        raise InputError(field, f"must be an object of preview options, got {_short(value)}")
    PreviewOptions.from_mapping(value, prefix=f"{field}.")
    return dict(value)


def _seconds(value: Any, field: str) -> float:
    ok = finite_number(value)
    if not ok or not 0 <= value <= MAX_PROBE_SECONDS:
        raise InputError(field, f"must be a number of seconds in 0..{MAX_PROBE_SECONDS:g}, got {value!r}")
    return value


def compress_options(value: Any, field: str = "params.compress") -> dict[str, Any]:
    """``params.compress`` checked: at most one of ``quantum`` / ``max_error`` (positive numbers)
    and ``keep_range`` (true or false)."""
    if value is None:
        return {}
    if not isinstance(value, Mapping) or set(value) - {"quantum", "max_error", "keep_range"}:
        raise InputError(field, f"must be an object with quantum or max_error and keep_range, got {value!r}")
    if "quantum" in value and "max_error" in value:
        raise InputError(field, "give quantum or max_error, not both")
    for k in ("quantum", "max_error"):
        v = value.get(k)
        if k in value and (not finite_number(v) or not 0 < v <= MAX_QUANTUM):
            raise InputError(f"{field}.{k}", f"must be a positive number up to {MAX_QUANTUM:g}, got {_short(v)}")
    if "keep_range" in value and not isinstance(value["keep_range"], bool):
        raise InputError(f"{field}.keep_range", f"must be true or false, got {value['keep_range']!r}")
    return dict(value)


_POSITIVE = {"type": "number", "exclusiveMinimum": 0, "maximum": MAX_QUANTUM}
_VEC3 = {"type": "array", "items": {"type": "number", "minimum": -MAX_COORDINATE, "maximum": MAX_COORDINATE},
         "minItems": 3, "maxItems": 3}
_PREVIEW_SCHEMA = {
    "type": "object",
    "description": "preview video options",
    "properties": {
        "path": {"type": "string", "enum": list(NAMED_PATHS),
                 "description": "the camera path: a job names no file (keyframes go in camera)"},
        "camera": {
            "type": "object",
            "description": "keyframe camera path, inline: evenly spaced keyframes of eye and target (world units); "
                           "a keyframe whose target is its eye looks at the scene's centre",
            "properties": {
                "fov": {"type": "number", "minimum": 1, "maximum": 170, "description": "vertical field of view, degrees"},
                "keyframes": {"type": "array", "minItems": 1, "maxItems": MAX_INLINE_KEYFRAMES,
                              "items": {"type": "object", "properties": {"eye": _VEC3, "target": _VEC3},
                                        "required": ["eye", "target"], "additionalProperties": False}},
            },
            "required": ["keyframes"],
            "additionalProperties": False,
        },
        "size": {
            "type": "array",
            "description": "[width, height] in pixels, even",
            "prefixItems": [
                {"type": "integer", "minimum": MIN_SIDE, "maximum": MAX_WIDTH, "multipleOf": 2},
                {"type": "integer", "minimum": MIN_SIDE, "maximum": MAX_HEIGHT, "multipleOf": 2},
            ],
            "items": False,
            "minItems": 2,
            "maxItems": 2,
        },
        "seconds": {"type": "number", "exclusiveMinimum": 0, "maximum": MAX_SECONDS},
        "fps": {"type": "number", "minimum": 1, "maximum": MAX_FPS},
    },
    "additionalProperties": False,
}
_TILES_SCHEMA = {
    "type": ["object", "null"],
    "description": "Potree tiling options (null: the defaults)",
    "properties": {**{k: {"type": "integer", "minimum": 100, "maximum": _TILE_MAX[k]} for k in _TILE_OPTIONS},
                   "node_codec": {"type": "string", "enum": list(_NODE_CODECS)}},
    "additionalProperties": False,
}
# Two shapes (quantum, or max_error), not a "not" clause: the bodies are multipart, and
# schemathesis cannot evaluate "not" beside a binary part.
_COMPRESS_SCHEMA = {
    "description": "range compression: quantum (lossless at that step) or max_error (bounded), rig units",
    "anyOf": [
        {"type": "null"},
        *({"type": "object", "properties": {mode: _POSITIVE, "keep_range": {"type": "boolean"}}, "additionalProperties": False}
          for mode in ("quantum", "max_error")),
    ],
}


@dataclass(frozen=True)
class Param:
    """One job parameter: its check (raises :class:`InputError` naming the field) and the JSON
    Schema of its value, which the API's OpenAPI document states (``services/api/schema.py``)."""

    check: Callable[[Any, str], Any]
    schema: dict[str, Any]


_DERIVATIVE_LEVELS = ("thumb", "low", "medium", "high", "highest")
_DERIVATIVES_SCHEMA: dict[str, Any] = {
    "description": "false leaves out the textured derivatives; an object chooses them",
    "anyOf": [{"type": "boolean"}, {"type": "object", "additionalProperties": False, "properties": {
        "colour": {"enum": ["photo", "albedo", "shaded"]},
        "levels": {"type": "array", "minItems": 1, "maxItems": 5,
                   "description": "levels by name or with their budgets; a level named again replaces the earlier",
                   "items": {"anyOf": [
            {"enum": list(_DERIVATIVE_LEVELS)},
            {"type": "object", "additionalProperties": False, "required": ["name"], "properties": {
                "name": {"enum": list(_DERIVATIVE_LEVELS)},
                "faces": {"type": "integer", "minimum": 100, "maximum": 5_000_000},
                "texture_px": {"type": "integer", "enum": [64, 128, 256, 512, 1024, 2048, 4096, 8192]},
                "jpeg_quality": {"type": "integer", "minimum": 1, "maximum": 100}}}]}}}}],
}


def _derivatives(value: Any, field: str) -> Any:
    if isinstance(value, bool):
        return value
    if not isinstance(value, Mapping):
        raise InputError(field, f"must be true, false or an object (levels, colour), got {value!r}")
    unknown = set(value) - {"levels", "colour"}
    if unknown:
        raise InputError(f"{field}.{sorted(unknown)[0]}", "unknown field (accepted: levels, colour)")
    if value.get("colour", "photo") not in ("photo", "albedo", "shaded"):
        raise InputError(f"{field}.colour", f"must be photo, albedo or shaded, got {value.get('colour')!r}")
    if "levels" in value:
        levels = value["levels"]
        if not isinstance(levels, list) or not levels:
            raise InputError(f"{field}.levels", "must be a non-empty list of level names or objects")
        for item in levels:
            name = item.get("name") if isinstance(item, Mapping) else item
            if name not in _DERIVATIVE_LEVELS:
                raise InputError(f"{field}.levels", f"unknown level {name!r} (accepted: {', '.join(_DERIVATIVE_LEVELS)})")
            if isinstance(item, Mapping) and set(item) - {"name", "faces", "texture_px", "jpeg_quality"}:
                raise InputError(f"{field}.levels.{name}", "accepted fields: name, faces, texture_px, jpeg_quality")
        try:
            parse_levels(levels)
        except InputError as exc:
            raise InputError(f"{field}.{exc.where}", exc.problem) from None
    return value


def _label(value: Any, field: str) -> str:
    if not isinstance(value, str):
        raise InputError(field, f"must be a string, got {_short(value)}")
    return check_label(field, value)


def _label_param(description: str) -> Param:
    """The object's title, collection or identifier, shown in its Voyager scene and quality report."""
    # The pattern is check_label's own refusal (shared.publish.labels.REFUSED_RANGES), so the
    # document and the check agree on every character a client can send.
    return Param(_label, {"type": "string", "maxLength": MAX_LABEL_CHARS, "pattern": LABEL_PATTERN,
                          "description": description + "; text without control characters or bidirectional overrides"})


#: The object as the museum names it (shared.publish.folder.ObjectMeta), for scan and multiview jobs.
_OBJECT_PARAMS: dict[str, Param] = {
    "title": _label_param("the object's title in its published scene and quality report (default: the job)"),
    "collection": _label_param("the collection the object belongs to"),
    "identifier": _label_param("the object's accession number or identifier (default: the job id)"),
}


def _bool(description: str) -> Param:
    return Param(_switch, {"type": "boolean", "description": description})


#: What each job kind accepts, the one table the intake and the OpenAPI document read.
PARAMS: dict[str, dict[str, Param]] = {
    "scan": {
        "render": _bool("false leaves out tiles and preview"),
        "export": _bool("false leaves out the LAZ / COPC / E57 export"),
        "tiles": Param(lambda v, f: tiles_options(v, f), _TILES_SCHEMA),
        "preview": Param(_preview, _PREVIEW_SCHEMA),
        "compress": Param(lambda v, f: compress_options(v, f), _COMPRESS_SCHEMA),
        **_OBJECT_PARAMS,
    },
    "calibrate": {},
    "multiview": {
        "render": _bool("false leaves out tiles and preview of the merged cloud"),
        "export": _bool("false leaves out the LAZ / COPC / E57 export of the merged cloud"),
        "drop_unregistered": _bool("true leaves out, with a warning, views that register to nothing"),
        "derivatives": Param(_derivatives, _DERIVATIVES_SCHEMA),
        "tiles": Param(lambda v, f: tiles_options(v, f), _TILES_SCHEMA),
        "preview": Param(_preview, _PREVIEW_SCHEMA),
        "compress": Param(lambda v, f: compress_options(v, f), _COMPRESS_SCHEMA),
        **_OBJECT_PARAMS,
    },
    "probe": {"seconds": Param(_seconds, {"type": "number", "minimum": 0, "maximum": MAX_PROBE_SECONDS})},
}


def params_schema(kind: str) -> dict[str, Any]:
    """The JSON Schema of a ``kind`` job's ``params`` object."""
    props = {k: p.schema for k, p in PARAMS.get(kind, {}).items()}
    return {"type": "object", "properties": props, "additionalProperties": False}


def check_job_params(kind: str, params: Any, *, allow_service: bool = False) -> dict[str, Any]:
    """``params`` of a ``kind`` job, checked against :data:`PARAMS`; :class:`InputError`
    names the field (``params.preview.size``). ``allow_service`` lets the service's own keys
    (``rig``, ``preview_epoch``) through, for parameters read back from the job store."""
    if not isinstance(params, Mapping):
        raise InputError("params", f"must be a JSON object, got {type(params).__name__}")
    if len(json.dumps(params, default=str)) > MAX_PARAMS_BYTES:
        raise InputError("params", f"larger than {MAX_PARAMS_BYTES // 1024} KiB")
    accepted = PARAMS.get(kind, {})
    out: dict[str, Any] = {}
    for key, value in params.items():
        field = f"params.{key}"
        if key in SERVICE_PARAMS:
            if not allow_service:
                hint = "upload a rig in the multipart field 'rig' instead" if key == "rig" else "set by the service"
                raise InputError(field, hint)
            out[key] = value
        elif key in accepted:
            accepted[key].check(value, field)
            out[key] = value
        else:
            allowed = ", ".join(sorted(accepted)) or "none"
            raise InputError(field, f"unknown parameter for a {kind} job (accepted: {allowed})")
    return out
