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
"""

from __future__ import annotations

import re
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from services.api.http import BodyInvalid
from services.api.intake import NotInStorage
from shared.core.errors import InputError

__all__ = ["install_error_handlers", "loc_of", "validation_item"]

_DOTTED = re.compile(r"^[A-Za-z_]\w*(\.\w+)*$")


def loc_of(where: str) -> list[str | int]:
    """The location (FastAPI's ``loc``) of a problem at ``where``."""
    if where == "body":
        return ["body"]
    if where.startswith("params.") and _DOTTED.match(where):  # the one nested field
        return ["body", *(int(p) if p.isdigit() else p for p in where.split("."))]
    return ["body", where]


def validation_item(where: str, problem: str, kind: str = "value_error") -> dict[str, Any]:
    return {"loc": loc_of(where), "msg": problem, "type": kind}


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


def install_error_handlers(app: FastAPI) -> None:
    """Register the handlers described in the module docstring on ``app``."""

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
            items.append({"loc": [p if isinstance(p, int) else str(p) for p in loc], "msg": str(e.get("msg", "invalid")),
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
        return await http_exception_handler(request, exc)
