"""The object's title, collection and identifier as a submission gives them: checked once, kept verbatim.

Free text (markup, quotes and slashes are kept: JSON escapes them in the scene, HTML escaping in
the quality report, and no label ever names a file); a job's parameters are checked here too
(shared.service.params), so a job is refused at submission rather than failing at its last stage.
"""

from __future__ import annotations

from shared.core.errors import InputError

__all__ = ["LABEL_PATTERN", "MAX_LABEL_CHARS", "REFUSED_RANGES", "check_label"]

MAX_LABEL_CHARS = 500


#: Characters :func:`check_label` refuses besides surrogates, as the ranges of the API document's
#: pattern (JSON Schema, ECMA-262 syntax without the u flag, where a surrogate range would also
#: refuse every character beyond U+FFFF; a lone surrogate arrives only as a "\\ud800" escape).
REFUSED_RANGES: tuple[tuple[int, int], ...] = ((0x00, 0x1F), (0x7F, 0x9F), (0x202A, 0x202E), (0x2066, 0x2069))


def _refused(c: str) -> bool:
    o = ord(c)
    return 0xD800 <= o <= 0xDFFF or any(lo <= o <= hi for lo, hi in REFUSED_RANGES)


#: The API document's pattern for a label: the characters :func:`check_label` accepts, but lone
#: surrogates (see :data:`REFUSED_RANGES`).
LABEL_PATTERN = "^[^" + "".join(f"\\u{lo:04x}-\\u{hi:04x}" for lo, hi in REFUSED_RANGES) + "]*$"


def check_label(field: str, value: str) -> str:
    """A title, collection or identifier: any text up to :data:`MAX_LABEL_CHARS` characters (markup,
    quotes and slashes are kept and escaped where shown). Refused: control characters (C0, C1),
    surrogates, and the bidirectional embedding, override and isolate controls (U+202A-U+202E,
    U+2066-U+2069), which reorder what a reader sees of the text around them (a label that reads one
    way and sorts or matches another). Other format characters are kept because scripts need them
    (the zero-width non-joiner in Persian, the joiner in Indic scripts and emoji), and so are
    private-use characters (the Medieval Unicode Font Initiative's letters, used by archives)."""
    if len(value) > MAX_LABEL_CHARS:
        raise InputError(field, f"{len(value)} characters, at most {MAX_LABEL_CHARS}")
    bad = [c for c in value if _refused(c)]
    if bad:
        raise InputError(field, f"control character U+{ord(bad[0]):04X} is not allowed")
    return value
