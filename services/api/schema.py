"""The request bodies of ``POST /v1/jobs`` and ``POST /v1/batches`` as the OpenAPI document
states them: exactly what the intake accepts, so a client generated from the document sends
nothing the API refuses for its form.

Job parameters depend on the job's kind (:data:`shared.service.params.PARAMS`), so each body
lists every field in ``properties`` (a form's parts are known by name) and adds one ``anyOf``
branch per kind, told apart by ``kind`` (``scan`` when absent), with that kind's ``params``. What
no JSON Schema can state — that an archive is a readable capture, that a storage reference
exists — is checked at intake and answered 422 naming the file or field (``capture.zip:
col_02.png``, ``capture_ref``), or 404 for an unknown upload session.
"""

from __future__ import annotations

from typing import Any

from services.api.intake import MAX_BATCH_REFS, MAX_REF_CHARS, NAME_PATTERN
from shared.service.jobs import GRAPHS
from shared.service.params import params_schema

__all__ = ["any_params_schema", "batch_body", "job_body", "params_schema"]

_NAME = {"type": "string", "pattern": NAME_PATTERN}

def _kinds(build: Any) -> list[dict[str, Any]]:
    """One ``anyOf`` branch per kind: its ``kind`` (required but for ``scan``, the default)
    and what ``build(kind)`` adds (its ``params``, its required fields)."""
    out = []
    for kind in sorted(GRAPHS, key=lambda k: k != "scan"):
        branch = build(kind)
        branch.setdefault("properties", {})["kind"] = {"const": kind}
        if kind != "scan":
            branch["required"] = sorted({"kind", *branch.get("required", [])})
        out.append(branch)
    return out


def _with_kinds(properties: dict[str, Any], build: Any, required: list[str] | None = None,
                title: str = "") -> dict[str, Any]:  # fmt: skip
    """An object schema: every field in ``properties`` (so form parts are known by name), the
    kind-dependent rules as ``anyOf`` branches."""
    schema: dict[str, Any] = {
        "type": "object",
        "title": title,
        "properties": {"kind": {"type": "string", "enum": sorted(GRAPHS), "default": "scan"}, **properties,
                       "params": {"type": "object", "description": "job parameters (which depend on kind)"}},
        "anyOf": _kinds(build),
    }  # fmt: skip
    if required:
        schema["required"] = required
    return schema


_OPTIONAL_NAME = {"type": ["string", "null"], "pattern": NAME_PATTERN}
_REF = {"type": "string", "minLength": 1, "maxLength": MAX_REF_CHARS,
        "description": "path of an archive or capture folder, relative to the storage root"}
_UPLOAD = {"type": "string", "minLength": 1, "maxLength": MAX_REF_CHARS, "description": "a finished upload session"}


def _job_json(kind: str) -> dict[str, Any]:
    branch: dict[str, Any] = {"properties": {"params": params_schema(kind)}}
    if kind != "probe":  # a self-test reads no capture; the others name theirs
        branch["anyOf"] = [{"required": ["upload_id"], "properties": {"upload_id": _UPLOAD}},
                           {"required": ["capture_ref"], "properties": {"capture_ref": _REF}}]  # fmt: skip
    return branch


def _job_form(kind: str) -> dict[str, Any]:
    branch: dict[str, Any] = {"properties": {"params": params_schema(kind)}}
    if kind != "probe":
        branch["required"] = ["capture"]
    return branch


def job_body() -> dict[str, Any]:
    """``openapi_extra`` of ``POST /v1/jobs``: multipart (``capture`` file) or JSON."""
    form = _with_kinds({
        "capture": {"type": "string", "format": "binary", "description": "zip or tar of the capture folder (not for probe)"},
        "rig": {"type": "string", "format": "binary", "description": "rig.json to use instead of the capture's"},
        "name": _NAME,
        "batch": _NAME,
    }, _job_form, title="job (multipart)")  # fmt: skip
    body = _with_kinds({
        "name": _OPTIONAL_NAME,
        "batch": _OPTIONAL_NAME,
        "upload_id": {**_UPLOAD, "type": ["string", "null"]},
        "capture_ref": {**_REF, "type": ["string", "null"]},
    }, _job_json, title="job")  # fmt: skip
    return {
        "requestBody": {
            "required": True,
            "content": {
                "multipart/form-data": {"schema": form, "encoding": {"params": {"contentType": "application/json"}}},
                "application/json": {"schema": body},
            },
        }
    }


def _batch_params(kind: str) -> dict[str, Any]:
    return {"properties": {"params": params_schema(kind)}}


def batch_body() -> dict[str, Any]:
    """``openapi_extra`` of ``POST /v1/batches``: multipart (``captures`` files) or JSON."""
    form = _with_kinds({
        "name": _NAME,
        "captures": {"type": "array", "items": {"type": "string", "format": "binary"}, "description": "zip or tar files"},
    }, _batch_params, required=["name"], title="batch (multipart)")  # fmt: skip
    body = _with_kinds({
        "name": _NAME,
        "captures": {"type": "array", "items": {"type": "string", "maxLength": MAX_REF_CHARS}, "maxItems": MAX_BATCH_REFS,
                     "description": "storage references, one capture each"},
        "manifest": {"type": ["string", "null"], "maxLength": MAX_REF_CHARS,
                     "description": "storage reference of a text file listing one reference per line"},
    }, _batch_params, required=["name"], title="batch")  # fmt: skip
    return {
        "requestBody": {
            "required": True,
            "content": {
                "multipart/form-data": {"schema": form, "encoding": {"params": {"contentType": "application/json"}}},
                "application/json": {"schema": body},
            },
        }
    }


def any_params_schema() -> dict[str, Any]:
    """The ``params`` of a retry: valid for some kind of job (the job's own kind decides)."""
    return {"anyOf": [params_schema(k) for k in sorted(GRAPHS)]}
