"""HTTP plumbing of the API that is not about any resource: the request-size limit
(:class:`BodyLimit`), single byte ranges (:func:`byte_range`), and reading a body as JSON
(:func:`parse_body`) or as a multipart form (:func:`read_form`)."""

from __future__ import annotations

import re
from typing import Any, TypeVar

from fastapi import HTTPException, Request
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ValidationError
from starlette.datastructures import FormData
from starlette.types import ASGIApp, Receive, Scope, Send

__all__ = ["BodyLimit", "TooLarge", "byte_range", "is_form", "parse_body", "read_form"]

_Body = TypeVar("_Body", bound=BaseModel)


class TooLarge(Exception):
    """A streamed request body grew past :class:`BodyLimit`'s limit."""


class BodyLimit:
    """ASGI middleware: refuse a request body larger than ``limit`` bytes with 413, whether
    it announces its length or streams chunks (counted as they arrive)."""

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app = app
        self.limit = limit

    def _refusal(self) -> JSONResponse:
        return JSONResponse({"detail": f"request body larger than the limit of {self.limit} bytes"}, 413)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        for k, v in scope.get("headers", []):
            if k == b"content-length" and v.isdigit() and int(v) > self.limit:
                await self._refusal()(scope, receive, send)
                return
        seen = 0

        async def counted() -> Any:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:
                    raise TooLarge()
            return message

        try:
            await self.app(scope, counted, send)
        except TooLarge:
            await self._refusal()(scope, receive, send)


def byte_range(header: str | None, size: int) -> tuple[int, int] | None:
    """The (first, last) byte of a single-range ``Range`` header, None for a whole-file
    answer; HTTP 416 when the range lies outside the file. Viewers read ``octree.bin`` so."""
    if not header:
        return None
    m = re.fullmatch(r"\s*bytes=(\d*)-(\d*)\s*", header)
    if m is None or (not m.group(1) and not m.group(2)):
        return None  # multi-range or malformed: answer with the whole file, as HTTP allows
    if m.group(1):
        start = int(m.group(1))
        end = min(int(m.group(2)), size - 1) if m.group(2) else size - 1
    else:
        start, end = max(size - int(m.group(2)), 0), size - 1
    if start >= size or start > end:
        raise HTTPException(416, f"range {header!r} is outside the file of {size} bytes",
                            headers={"Content-Range": f"bytes */{size}"})  # fmt: skip
    return start, end


def is_form(request: Request) -> bool:
    """Whether the request carries a multipart form (else its body is read as JSON)."""
    return request.headers.get("content-type", "").startswith("multipart/form-data")


async def parse_body(request: Request, model: type[_Body]) -> _Body:
    """The JSON body as ``model``; pydantic's errors become the API's 422 list (with ``body``
    in front of each location, as FastAPI's own validation does)."""
    try:
        return model.model_validate_json(await request.body())
    except ValidationError as exc:
        raise BodyInvalid(exc.errors(include_url=False, include_context=False)) from None


class BodyInvalid(Exception):
    """A JSON body that does not fit its model: pydantic's error list (see :mod:`services.api.errors`)."""

    def __init__(self, items: list[Any]) -> None:
        super().__init__(items)
        self.items = items


async def read_form(request: Request, max_files: int) -> FormData:
    """The multipart form of the request; 400 when it cannot be parsed."""
    try:
        return await request.form(max_files=max_files, max_fields=16, max_part_size=64 << 10)
    except TooLarge:
        raise
    except Exception as exc:
        raise HTTPException(400, " ".join(str(exc).split())[:1000] or "malformed multipart form") from None
