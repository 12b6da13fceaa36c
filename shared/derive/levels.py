"""Derivative levels: face and texture budgets, defaulting to Smithsonian Voyager's quality levels.

Voyager (``../shared/reference/voyager-svx-schema``) lists a model's derivatives by quality; the
processing recipes of Smithsonian's Cook make Thumb with about 20 k faces and 512 px maps (a GLB
under about 200 kB), Low / Medium / High with about 150 k faces and 1024 / 2048 / 4096 px maps, and
Highest with about 500 k faces and 4k-8k maps, JPEG maps at quality 59 (Thumb) and 79 (others).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from shared.core.errors import InputError
from shared.core.jsonsafe import json_integer

__all__ = ["DEFAULT_LEVELS", "LEVELS", "Level", "parse_levels"]

#: Largest texture side accepted (16384 is the most any WebGL2 implementation offers).
MAX_TEXTURE_PX = 8192
#: Face budgets outside this range make no sense for a web derivative.
MIN_FACES, MAX_FACES = 100, 5_000_000


@dataclass(frozen=True)
class Level:
    """One derivative: ``name`` (Voyager's quality), ``faces`` (face budget), ``texture_px`` (the
    side of the square maps), ``jpeg_quality`` of the maps, ``max_bytes`` (a size the GLB should
    stay under, None: no bound; a level over it is reported, not refused)."""

    name: str
    faces: int
    texture_px: int
    jpeg_quality: int = 79
    max_bytes: int | None = None

    @property
    def file_name(self) -> str:
        return f"mesh_{self.name}.glb"


LEVELS: dict[str, Level] = {
    "thumb": Level("thumb", 20_000, 512, 59, 200_000),
    "low": Level("low", 150_000, 1024),
    "medium": Level("medium", 150_000, 2048),
    "high": Level("high", 150_000, 4096),
    # 4096 px by default: an 8192 px level peaked at 3.9 GB here (the raster and four maps of 67 M
    # texels); highest:500000:8192 asks for it where the memory is there.
    "highest": Level("highest", 500_000, 4096),
}

#: The set made when none is asked for: Voyager's Thumb, Low, Medium and High (Highest, 500 k
#: faces, on request).
DEFAULT_LEVELS = ("thumb", "low", "medium", "high")


def _short_int(v: int) -> str:
    text = str(v)
    return text if len(text) <= 20 else f"an integer of {len(text)} digits"


def check_level(level: Level, where: str = "levels") -> Level:
    """Raise :class:`InputError` naming the field when a budget makes no sense."""
    if not level.name.isidentifier() or len(level.name) > 32:
        raise InputError(where, f"level name {level.name!r} must be a short identifier")
    if not MIN_FACES <= level.faces <= MAX_FACES:
        raise InputError(f"{where}.{level.name}.faces", f"must be in [{MIN_FACES}, {MAX_FACES}], got {_short_int(level.faces)}")
    px = level.texture_px
    if not 64 <= px <= MAX_TEXTURE_PX or px & (px - 1):
        raise InputError(f"{where}.{level.name}.texture_px",
                         f"must be a power of two in [64, {MAX_TEXTURE_PX}], got {_short_int(px)}")
    if not 1 <= level.jpeg_quality <= 100:
        raise InputError(f"{where}.{level.name}.jpeg_quality", f"must be in [1, 100], got {_short_int(level.jpeg_quality)}")
    return level


def _integer(item: dict[str, Any], key: str, default: int, name: Any) -> int:
    """A level object's integer field: a JSON integer, not a float int() would truncate (faces
    150.5 read as 150), an infinite one it cannot convert, a string or a bool."""
    v = item.get(key, default)
    if not json_integer(v):
        text = repr(v)
        raise InputError(f"levels.{name}.{key}", f"must be an integer, got {text if len(text) <= 40 else text[:37] + '...'}")
    return v


def parse_levels(spec: str | list | None) -> list[Level]:
    """Levels from a spec: None (the defaults), ``"thumb,low"`` (named levels), or per level
    ``NAME:FACES:PX`` (``"low:100000:2048"``), or a list of such strings or of objects
    ``{"name", "faces", "texture_px", "jpeg_quality"?, "max_bytes"?}`` (job parameters).
    A level named again replaces the earlier one. Raises :class:`InputError` naming the level and field."""
    if spec is None:
        return [LEVELS[n] for n in DEFAULT_LEVELS]
    items = [s.strip() for s in spec.split(",") if s.strip()] if isinstance(spec, str) else list(spec)
    if not items:
        raise InputError("levels", "no level named")
    if len(items) > 8:
        raise InputError("levels", f"at most 8 levels, got {len(items)}")
    out: list[Level] = []
    for item in items:
        if isinstance(item, dict):
            unknown = set(item) - {"name", "faces", "texture_px", "jpeg_quality", "max_bytes"}
            if unknown:
                raise InputError("levels", f"unknown field {sorted(unknown)[0]!r}")
            name = item.get("name")
            base = LEVELS.get(name) if isinstance(name, str) else None
            level = Level(str(name), _integer(item, "faces", base.faces if base else -1, name),
                          _integer(item, "texture_px", base.texture_px if base else -1, name),
                          _integer(item, "jpeg_quality", base.jpeg_quality if base else 79, name),
                          item.get("max_bytes", base.max_bytes if base else None))
        elif isinstance(item, str) and ":" in item:
            parts = item.split(":")
            if len(parts) != 3:
                raise InputError("levels", f"{item!r}: expected NAME:FACES:PX")
            try:
                faces, px = int(parts[1]), int(parts[2])
            except ValueError:
                raise InputError(f"levels.{parts[0]}", f"{item!r}: faces and texture size must be integers") from None
            base = LEVELS.get(parts[0])
            level = Level(parts[0], faces, px, base.jpeg_quality if base else 79, base.max_bytes if base else None)
        elif isinstance(item, str) and item in LEVELS:
            level = LEVELS[item]
        else:
            raise InputError("levels", f"unknown level {item!r}; known: {', '.join(LEVELS)} or NAME:FACES:PX")
        out.append(check_level(level))
    # A level named again replaces the earlier one, in the earlier one's place: the job service's
    # document cannot say "names unique" across names and objects, and it accepts what it allows.
    by_name = {lv.name: lv for lv in out}
    return [by_name[n] for n in dict.fromkeys(lv.name for lv in out)]
