"""JSON from outside, parsed with bounds: size, nesting depth and number length checked first.

Python's ``json`` recurses once per nesting level (10,000 brackets raise ``RecursionError``),
converts any run of digits to an ``int`` (5,000 digits raise ``ValueError`` naming CPython's
limit) and accepts ``NaN`` and ``Infinity``, which JSON does not have. A client's document
must fail with an :class:`~shared.core.errors.InputError` that names the document, never with
one of those. :func:`loads_bounded` checks the size, then the nesting depth with a linear scan
that never recurses (strings masked out first, so brackets inside them do not count), then
parses with number hooks that refuse over-long numbers, numbers beyond float's range (``1e400``)
and the non-JSON constants.

Every JSON document a client sends goes through here: HTTP bodies and form fields, and the
files of a submission (``capture.json``, ``scanset.json``, ``rig.json``, camera paths).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from shared.core.errors import InputError
from shared.core.paths import read_bounded

__all__ = ["MAX_DEPTH", "MAX_DOCUMENT_BYTES", "MAX_NUMBER_CHARS", "finite_number", "json_depth", "json_integer",
           "loads_bounded", "read_json_bounded"]

#: Deepest nesting any Graylight document has is about 5; 64 leaves room without reaching recursion limits.
MAX_DEPTH = 64
#: Longest number literal accepted: float64 round-trips in 17 significant digits plus sign and exponent.
MAX_NUMBER_CHARS = 40
#: Default size bound of one document (a capture.json of 40 patterns is about 4 kB; a scan set of
#: hundreds of views well under 1 MiB).
MAX_DOCUMENT_BYTES = 1 << 20

_QUOTE, _BACKSLASH = 34, 92
_OPEN = np.frombuffer(b"[{", dtype=np.uint8)
_CLOSE = np.frombuffer(b"]}", dtype=np.uint8)


def json_depth(data: bytes) -> int:
    """The deepest bracket nesting of JSON text ``data`` (brackets inside strings not counted).

    Linear in the size, vectorised, never recursing and never backtracking (a regular expression
    for string literals backtracks quadratically on a client's ``"\\"\\"...`` and took 18 s on
    80 kB): a quote opens or closes a string unless an odd run of backslashes precedes it, and a
    bracket counts when an even number of such quotes precede it. Unbalanced text returns the
    depth it reaches; the parser reports the malformation itself.
    """
    a = np.frombuffer(data, dtype=np.uint8)
    n = a.size
    if n == 0:
        return 0
    idx = np.arange(n, dtype=np.int64)
    # For each position, the last index at or before it that is not a backslash.
    last_plain = np.maximum.accumulate(np.where(a != _BACKSLASH, idx, -1))
    run_before = np.zeros(n, dtype=np.int64)
    run_before[1:] = idx[:-1] - last_plain[:-1]  # backslashes just before each position
    quote = (a == _QUOTE) & (run_before % 2 == 0)
    outside = (np.cumsum(quote) % 2) == 0  # a bracket is never a quote: inclusive count is fine
    step = np.isin(a, _OPEN).astype(np.int32) - np.isin(a, _CLOSE).astype(np.int32)
    step[~outside] = 0
    return int(np.cumsum(step).max(initial=0))


def json_integer(value: Any) -> bool:
    """Whether a parsed JSON value is an integer: not a bool (an int to Python), not a float that
    ``int()`` would truncate (150.5) or fail on (infinity), not a string ``int()`` would parse."""
    return isinstance(value, int) and not isinstance(value, bool)


def finite_number(value: Any) -> bool:
    """Whether a parsed JSON value is a number (an int or a float, not a bool) of finite float
    value: an integer past float's range (``10**400``, which a library caller can pass) is not,
    where ``math.isfinite`` would raise a bare OverflowError on it."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def _number_hook(kind: type, what: str):
    def parse(text: str) -> Any:
        if len(text) > MAX_NUMBER_CHARS:
            raise InputError(what, f"a number of {len(text)} characters (at most {MAX_NUMBER_CHARS})")
        value = kind(text)
        # "1e400" is short and valid JSON, but parses to infinity: the constant refused by name
        # below, arriving as a number (validators then met int(inf), a bare OverflowError)
        if kind is float and not math.isfinite(value):
            raise InputError(what, f"{text} is beyond the range of a 64-bit float")
        return value

    return parse


def _no_constant(what: str):
    def parse(name: str) -> Any:
        raise InputError(what, f"{name} is not a JSON number")

    return parse


def loads_bounded(data: bytes | str, what: str, *, max_bytes: int = MAX_DOCUMENT_BYTES,
                  max_depth: int = MAX_DEPTH) -> Any:
    """Parse JSON text from a client with bounds; :class:`InputError` naming ``what`` on any problem.

    Parameters
    ----------
    data : bytes or str
        The document (UTF-8 when bytes).
    what : str
        How the error names the document: a file name relative to the submission, or a field.
    max_bytes : int
        Largest accepted size in bytes of the UTF-8 text.
    max_depth : int
        Deepest accepted nesting of arrays and objects.
    """
    raw = data.encode("utf-8") if isinstance(data, str) else bytes(data)
    if len(raw) > max_bytes:
        raise InputError(what, f"JSON document of {len(raw)} bytes is too large (at most {max_bytes})")
    depth = json_depth(raw)
    if depth > max_depth:
        raise InputError(what, f"JSON nested {depth} levels deep (at most {max_depth})")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(what, f"not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    try:
        return json.loads(text, parse_int=_number_hook(int, what), parse_float=_number_hook(float, what),
                          parse_constant=_no_constant(what))
    except json.JSONDecodeError as exc:
        raise InputError(what, f"malformed JSON at line {exc.lineno} column {exc.colno}: {exc.msg}") from None
    except RecursionError:  # the depth scan bounds it; kept so that no path can leak the bare name
        raise InputError(what, "JSON nested too deeply") from None


def read_json_bounded(path: str | os.PathLike[str], what: str, *, missing: str,
                      max_bytes: int = MAX_DOCUMENT_BYTES, max_depth: int = MAX_DEPTH) -> Any:
    """Read and parse a JSON file with :func:`loads_bounded`, reading at most ``max_bytes + 1`` bytes.

    ``what`` names the file in errors (relative to the submission, never an absolute worker path);
    ``missing`` is the problem reported when there is no file; a folder, device or FIFO is "not a
    regular file" (opened without blocking, :func:`shared.core.paths.read_bounded`), a larger
    file "too large" before any of it is parsed.
    """
    raw = read_bounded(Path(path), what, max_bytes, missing=missing)  # non-blocking, regular files only
    return loads_bounded(raw, what, max_bytes=max_bytes, max_depth=max_depth)
