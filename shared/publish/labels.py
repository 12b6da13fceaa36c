"""The object's title, collection and identifier as a submission gives them: checked once, kept verbatim.

Free text (markup, quotes and slashes are kept: JSON escapes them in the scene, HTML escaping in
the quality report, and no label ever names a file); a job's parameters are checked here too
(shared.service.params), so a job is refused at submission rather than failing at its last stage.
"""

from __future__ import annotations

import unicodedata

from shared.core.errors import InputError

__all__ = ["MAX_LABEL_CHARS", "check_label"]

MAX_LABEL_CHARS = 500


def check_label(field: str, value: str) -> str:
    """A title, collection or identifier: any printable text up to :data:`MAX_LABEL_CHARS` characters
    (markup, quotes and slashes are kept and escaped where shown); control characters are refused."""
    if len(value) > MAX_LABEL_CHARS:
        raise InputError(field, f"{len(value)} characters, at most {MAX_LABEL_CHARS}")
    bad = [c for c in value if unicodedata.category(c) in ("Cc", "Cf", "Cs", "Co")]
    if bad:
        raise InputError(field, f"control character U+{ord(bad[0]):04X} is not allowed")
    return value
