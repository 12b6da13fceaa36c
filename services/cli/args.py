"""Argument parsing shared by the command groups."""

from __future__ import annotations

import re

from shared.core.errors import InputError


def parse_size(text: str, where: str, *, lo: int = 0, hi: int | None = None) -> tuple[int, int]:
    """``"1024x768"`` -> ``(1024, 768)``; :class:`InputError` naming ``where`` unless both sides lie in ``lo..hi``."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text or "")
    if not m:
        raise InputError(where, f"expected WIDTHxHEIGHT such as 1024x768, got {text!r}")
    w, h = int(m.group(1)), int(m.group(2))
    if min(w, h) < lo or (hi is not None and max(w, h) > hi):
        bound = f"{lo}..{hi}" if hi is not None else f"at least {lo}"
        raise InputError(where, f"size {w}x{h} is out of range ({bound} per side)")
    return w, h
