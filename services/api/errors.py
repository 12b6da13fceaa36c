"""Error answers of the API, so that every one of them is what the OpenAPI document says.

* Every 422 has FastAPI's list shape ``{"detail": [{"loc": [...], "msg": ..., "type": ...}]}``:
  pydantic's own errors, an :class:`~shared.core.errors.InputError` raised anywhere in
  ``shared/`` (its ``where`` becomes the location: ``params.preview.size`` ->
  ``["body", "params", "preview", "size"]``; a file inside a capture stays one element,
  ``["body", "scan7.zip:col_02.png"]``), and a route's ``HTTPException(422, "field: problem")``.
* A storage reference that names nothing (``capture_ref``, ``manifest``) is 404.
* Every other error is ``{"detail": "one line"}`` (:class:`services.api.models.ErrorOut`).
* A 405 names in ``Allow`` every method of every route whose path matches, not only those of
  the first route Starlette tried.
* A per-key limit refused at admission (:class:`~shared.service.usage.LimitReached`) is 429
  (running jobs, with ``Retry-After``) or 507 (stored bytes), naming the limit.
* A full data folder or database (``ENOSPC``, ``EDQUOT``, SQLite's ``database or disk is
  full``) is 507 with the reason and ``Retry-After``: space may be freed; what the request
  began to write was taken back by the store.
* No answer quotes more than :data:`~services.api.http.EXCERPT_CHARS` characters of what the
  client sent: messages and locations are cut to an excerpt (a 50 MB name is not echoed).
"""

from __future__ import annotations

import errno
import logging
import re
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from sqlalchemy.exc import OperationalError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from services.api.http import BodyInvalid, excerpt
from services.api.intake import NotInStorage
from shared.core.errors import InputError
from shared.service.usage import LimitReached

log = logging.getLogger(__name__)

#: Seconds a client refused for a full disk is told to wait (an operator or the upload
#: expiry may free space meanwhile).
DISK_FULL_RETRY_AFTER = 60
#: Longest message of an error answer: the service's own words around an excerpt of the input.
MESSAGE_CHARS = 400
#: errno values that mean the storage is full.
_FULL = (errno.ENOSPC, errno.EDQUOT)

__all__ = ["install_error_handlers", "loc_of", "validation_item"]

_DOTTED = re.compile(r"^[A-Za-z_]\w*(\.\w+)*$")


def loc_of(where: str) -> list[str | int]:
    """The location (FastAPI's ``loc``) of a problem at ``where`` (an excerpt of it when long)."""
    where = excerpt(where)
    if where == "body":
        return ["body"]
    if where.startswith("params.") and _DOTTED.match(where):  # the one nested field
        return ["body", *(int(p) if p.isdigit() else p for p in where.split("."))]
    return ["body", where]


def validation_item(where: str, problem: str, kind: str = "value_error") -> dict[str, Any]:
    return {"loc": loc_of(where), "msg": excerpt(problem, MESSAGE_CHARS), "type": kind}


def _invalid(items: list[dict[str, Any]]) -> JSONResponse:
    return JSONResponse({"detail": items}, 422)


def _routes(routes: Any) -> Any:
    """Every endpoint route, through included routers (FastAPI keeps an included router
    whole; the API includes its routers without a prefix, so their paths are the full ones)."""
    for route in routes:
        inner = getattr(route, "original_router", None)
        if inner is not None:
            yield from _routes(inner.routes)
        else:
            yield route


def _allowed(app: Any, scope: dict[str, Any]) -> list[str]:
    methods: set[str] = set()
    for route in _routes(app.router.routes):
        match, _child = route.matches(scope)
        if match != Match.NONE:
            methods |= set(getattr(route, "methods", None) or ())
    return sorted(methods)


def _loc_part(p: Any) -> str | int:
    return p if isinstance(p, int) else excerpt(str(p))


def disk_full(exc: BaseException) -> str | None:
    """The reason to give when ``exc`` says the storage is full, else None."""
    if isinstance(exc, OSError) and exc.errno in _FULL:
        return "storage full: no space left on the service's data folder; nothing of this request was kept"
    if isinstance(exc, OperationalError) and "disk is full" in str(exc.orig):
        return "storage full: the job database has no space left; nothing of this request was kept"
    return None


def install_error_handlers(app: FastAPI) -> None:
    """Register the handlers described in the module docstring on ``app``."""

    @app.exception_handler(LimitReached)
    async def _limit(_request: Request, exc: LimitReached) -> JSONResponse:
        headers = {"Retry-After": str(exc.retry_after)} if exc.retry_after else None
        return JSONResponse({"detail": str(exc)}, exc.status, headers=headers)

    async def _full(request: Request, exc: Exception) -> Response:
        reason = disk_full(exc)
        if reason is None:
            raise exc
        log.error("%s %s: %s (%s)", request.method, request.url.path, reason, exc)
        return JSONResponse({"detail": reason}, 507, headers={"Retry-After": str(DISK_FULL_RETRY_AFTER)})

    app.add_exception_handler(OSError, _full)
    app.add_exception_handler(OperationalError, _full)

    @app.exception_handler(RequestValidationError)
    async def _request_invalid(_request: Request, exc: RequestValidationError) -> JSONResponse:
        # FastAPI's own answer would carry each item's ``input``: the whole offending value.
        return _invalid([{"loc": [_loc_part(p) for p in e.get("loc", ())], "msg": excerpt(str(e.get("msg", "invalid")), MESSAGE_CHARS),
                          "type": str(e.get("type", "value_error"))} for e in exc.errors()])  # fmt: skip

    @app.exception_handler(NotInStorage)
    async def _not_in_storage(_request: Request, exc: NotInStorage) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, 404)

    @app.exception_handler(InputError)
    async def _input_error(_request: Request, exc: InputError) -> JSONResponse:
        return _invalid([validation_item(exc.where, " ".join(exc.problem.split()))])

    @app.exception_handler(BodyInvalid)
    async def _body_invalid(_request: Request, exc: BodyInvalid) -> JSONResponse:
        items = []
        for e in exc.items:
            loc = ["body", *e.get("loc", ())]
            items.append({"loc": [_loc_part(p) for p in loc], "msg": excerpt(str(e.get("msg", "invalid")), MESSAGE_CHARS),
                          "type": str(e.get("type", "value_error"))})  # fmt: skip
        return _invalid(items)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, exc: StarletteHTTPException) -> Response:
        if exc.status_code == 422 and isinstance(exc.detail, str):
            where, sep, problem = exc.detail.partition(": ")
            return _invalid([validation_item(where, problem) if sep else validation_item("body", exc.detail)])
        if exc.status_code == 405:
            allow = ", ".join(_allowed(request.app, request.scope))
            exc = StarletteHTTPException(405, exc.detail, headers={**(exc.headers or {}), "Allow": allow})
        if isinstance(exc.detail, str):
            exc = StarletteHTTPException(exc.status_code, excerpt(exc.detail, MESSAGE_CHARS), headers=exc.headers)
        return await http_exception_handler(request, exc)
