"""HTTP plumbing of the API that is not about any resource: the request-size limit
(:class:`BodyLimit`), single byte ranges (:func:`byte_range`), and reading a body as JSON
(:func:`parse_body`) or as a multipart form (:func:`read_form`)."""

from __future__ import annotations

import errno
import re
from typing import Any, TypeVar

from fastapi import HTTPException, Request
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ValidationError
from starlette.datastructures import FormData
from starlette.types import ASGIApp, Receive, Scope, Send

from shared.core.errors import InputError
from shared.core.jsonsafe import loads_bounded

__all__ = ["EXCERPT_CHARS", "BodyLimit", "IgnoreOtherRanges", "TooLarge", "byte_range", "excerpt", "is_form", "parse_body", "read_form"]

_Body = TypeVar("_Body", bound=BaseModel)


class TooLarge(Exception):
    """A streamed request body grew past :class:`BodyLimit`'s limit."""


def _streams_bytes(scope: Scope) -> bool:
    """Whether a request carries bytes streamed to storage (a multipart form, an upload chunk)
    rather than a JSON document the API parses."""
    ctype = next((v for k, v in scope.get("headers", []) if k == b"content-type"), b"")
    if ctype.lower().startswith(b"multipart/form-data"):
        return True
    return scope.get("method") == "PATCH" and str(scope.get("path", "")).startswith("/v1/uploads/")


def _is_json(scope: Scope) -> bool:
    """Whether FastAPI or :func:`parse_body` would read the body as JSON (a JSON type, or none)."""
    ctype = next((v for k, v in scope.get("headers", []) if k == b"content-type"), b"").lower()
    return not ctype or ctype.split(b";")[0].strip().endswith((b"/json", b"+json"))


class BodyLimit:
    """ASGI middleware bounding every request body before the API holds it.

    Archives and upload chunks (multipart forms, ``PATCH /v1/uploads/{id}``) stream through,
    counted as they arrive, up to ``upload_limit`` bytes. Every other body is a JSON document:
    it is read up to ``json_limit`` bytes (413 as soon as it passes, whether it announced its
    length or not, so a 300 MB body never grows the process), and a JSON one is checked with
    :func:`shared.core.jsonsafe.loads_bounded` (nesting depth, number length, no NaN) before any
    route or FastAPI parses it: a deep document is the documented 422, never a RecursionError.
    """

    def __init__(self, app: ASGIApp, upload_limit: int, json_limit: int) -> None:
        self.app = app
        self.upload_limit = upload_limit
        self.json_limit = json_limit

    @staticmethod
    def _refusal(limit: int, what: str) -> JSONResponse:
        return JSONResponse({"detail": f"{what} larger than the limit of {limit} bytes"}, 413)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        streams = _streams_bytes(scope)
        limit, what = (self.upload_limit, "request body") if streams else (self.json_limit, "JSON request body")
        for k, v in scope.get("headers", []):
            if k == b"content-length" and v.isdigit() and int(v) > limit:
                await self._refusal(limit, what)(scope, receive, send)
                return
        if not streams:
            await self._json(scope, receive, send)
            return
        seen = 0

        async def counted() -> Any:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    raise TooLarge()
            return message

        try:
            await self.app(scope, counted, send)
        except TooLarge:
            await self._refusal(limit, what)(scope, receive, send)

    async def _json(self, scope: Scope, receive: Receive, send: Send) -> None:
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":
                return  # the client went away before its body ended
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.json_limit:
                await self._refusal(self.json_limit, "JSON request body")(scope, receive, send)
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        if body.strip() and _is_json(scope):
            try:
                loads_bounded(body, "body", max_bytes=self.json_limit)
            except InputError as exc:
                item = {"loc": ["body"], "msg": excerpt(exc.problem), "type": "value_error"}
                await JSONResponse({"detail": [item]}, 422)(scope, receive, send)
                return
        replayed = False

        async def replay() -> Any:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


#: The one Range form the API answers (a single byte range, RFC 9110 section 14.2).
SINGLE_RANGE = re.compile(r"\s*bytes=(\d*)-(\d*)\s*")


def _one_byte_range(value: str) -> bool:
    """Whether ``value`` is one well-formed byte range (``bytes=0-9``, ``bytes=5-``, ``bytes=-5``)."""
    m = SINGLE_RANGE.fullmatch(value)
    if m is None or not (m.group(1) or m.group(2)):
        return False
    return not (m.group(1) and m.group(2) and int(m.group(1)) > int(m.group(2)))


class IgnoreOtherRanges:
    """ASGI middleware: drop a ``Range`` header that is not one byte range (another unit such as
    ``items=0-9``, several ranges, or a malformed one), so the file is answered whole (200), as
    RFC 9110 asks for an unknown unit. A local store (Starlette's ``FileResponse``) and S3
    (:func:`byte_range`) then answer alike, and no answer is a ``multipart/byteranges`` the
    document does not list."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            headers = scope.get("headers", [])
            kept = [(k, v) for k, v in headers if k != b"range" or _one_byte_range(v.decode("latin-1"))]
            if len(kept) != len(headers):
                scope = {**scope, "headers": kept}
        await self.app(scope, receive, send)


#: Longest excerpt of a client's input an error answer quotes.
EXCERPT_CHARS = 200


def excerpt(text: str, limit: int = EXCERPT_CHARS) -> str:
    """``text`` on one line, cut to ``limit`` characters (with the count of those left out)."""
    one = " ".join(str(text).split())
    if len(one) <= limit:
        return one
    return f"{one[:limit]}... ({len(one) - limit} more characters)"


def byte_range(header: str | None, size: int) -> tuple[int, int] | None:
    """The (first, last) byte of a single-range ``Range`` header, None for a whole-file
    answer; HTTP 416 when the range lies outside the file. Viewers read ``octree.bin`` so."""
    if not header:
        return None
    m = SINGLE_RANGE.fullmatch(header)
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
    # Bounded before it is parsed: BodyLimit read at most its limit and checked the nesting.
    doc = loads_bounded(await request.body() or b"null", "body", max_bytes=1 << 62)
    try:
        return model.model_validate(doc)
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
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise  # the spool folder is full: 507 (services.api.errors), not a malformed form
        raise HTTPException(400, excerpt(str(exc)) or "malformed multipart form") from None
    except Exception as exc:
        raise HTTPException(400, excerpt(str(exc)) or "malformed multipart form") from None
