"""Preview options: the one place their defaults and limits are written.

The CLI (``graylight preview``), the job service's preview stage and the API's parameter
schema (:mod:`shared.service.params`) all read :data:`PREVIEW_DEFAULTS` and the limits
here. Importing this module costs nothing (no numba, no OpenCV), so the API can check a
job's ``params.preview`` before anything runs.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from shared.core.errors import InputError
from shared.core.jsonsafe import finite_number
from shared.render.camera_path import NAMED_PATHS, KeyframePath, parse_camera_doc

__all__ = ["MAX_FPS", "MAX_HEIGHT", "MAX_SECONDS", "MAX_WIDTH", "MIN_SIDE", "PREVIEW_DEFAULTS", "PreviewOptions"]

MAX_WIDTH, MAX_HEIGHT = 3840, 2160
MIN_SIDE = 16
MAX_SECONDS = 600.0
MAX_FPS = 120


@dataclass(frozen=True)
class PreviewOptions:
    """What a preview video shows and how long it runs.

    ``path``: ``"auto"`` (an arc on the scanner's side for a single-view scan, a full orbit
    for a merged model), ``"arc"``, ``"orbit"``, ``"dolly"`` or the path of a JSON keyframe file; ``size``:
    (width, height) in pixels, even, 16..3840 x 16..2160; ``seconds`` in (0, 600];
    ``fps`` frames per second in [1, 120]; ``camera``: validated keyframes
    (:func:`~shared.render.camera_path.parse_camera_doc`), which win over ``path``, their errors
    naming ``camera_where``. A job's options (:meth:`from_mapping`) name a path, never a file:
    their keyframes come inline (``params.preview.camera``).
    """

    path: str = "auto"
    size: tuple[int, int] = (1280, 720)
    seconds: float = 10.0
    fps: float = 30.0
    camera: KeyframePath | None = field(default=None, compare=False)
    camera_where: str = field(default="params.preview.camera", compare=False)

    @property
    def frames(self) -> int:
        return max(1, int(round(self.seconds * self.fps)))

    def checked(self, prefix: str = "") -> PreviewOptions:
        """These options, validated; :class:`InputError` names the field (``prefix`` + name)."""
        try:
            width, height = (int(v) for v in self.size)
            if isinstance(self.size, str | bytes) or any(isinstance(v, bool) for v in self.size):
                raise TypeError
        except (TypeError, ValueError, OverflowError):  # OverflowError: int() of an infinite float
            raise InputError(f"{prefix}size", f"must be [width, height] in pixels, got {self.size!r}") from None
        if width > MAX_WIDTH or height > MAX_HEIGHT:
            raise InputError(f"{prefix}size", f"{width}x{height} is too large (at most {MAX_WIDTH}x{MAX_HEIGHT})")
        if width < MIN_SIDE or height < MIN_SIDE:
            raise InputError(f"{prefix}size", f"{width}x{height} is too small (at least {MIN_SIDE}x{MIN_SIDE})")
        if width % 2 or height % 2:
            raise InputError(f"{prefix}size", f"{width}x{height}: H.264 needs even width and height")
        s, f = self.seconds, self.fps
        if not (finite_number(s) and 0 < s <= MAX_SECONDS):
            raise InputError(f"{prefix}seconds", f"must be in (0, {MAX_SECONDS:g}], got {s!r}")
        if not (finite_number(f) and 1 <= f <= MAX_FPS):
            raise InputError(f"{prefix}fps", f"must be in [1, {MAX_FPS}], got {f!r}")
        if not isinstance(self.path, str) or not self.path:
            raise InputError(f"{prefix}path", f"must be auto, arc, orbit, dolly or a keyframe file, got {self.path!r}")
        return replace(self, size=(width, height), seconds=float(s), fps=float(f))

    @classmethod
    def from_mapping(cls, doc: Mapping[str, Any] | None, prefix: str = "params.preview.") -> PreviewOptions:
        """Options from a JSON object (a job's ``params.preview``), validated; unknown keys
        are an error naming them."""
        if doc is None:
            return PREVIEW_DEFAULTS
        if not isinstance(doc, Mapping):
            raise InputError(prefix.rstrip("."), f"must be an object of preview options, got {doc!r}")
        known = {"path", "size", "seconds", "fps", "camera"}
        unknown = sorted(str(k)[:40] for k in set(doc) - known)
        if unknown:
            raise InputError(prefix.rstrip("."), f"unknown option(s) {unknown} (allowed: {sorted(known)})")
        path = doc.get("path", PREVIEW_DEFAULTS.path)
        if path not in NAMED_PATHS:
            # A job names no file: a path on the worker could be a FIFO, /dev/zero or another
            # tenant's file (issue 21). Keyframes travel inside the job.
            raise InputError(f"{prefix}path", f"must be one of {', '.join(NAMED_PATHS)}, got {str(path)[:40]!r} "
                                              f"(a keyframe path goes inline in {prefix}camera)")
        camera = None
        if doc.get("camera") is not None:  # it wins over path
            camera = parse_camera_doc(doc["camera"], f"{prefix}camera", inline=True)
        size = doc.get("size", PREVIEW_DEFAULTS.size)
        if isinstance(size, list):
            size = tuple(size)
        if not (isinstance(size, tuple) and len(size) == 2 and all(isinstance(v, int) and not isinstance(v, bool) for v in size)):
            raise InputError(f"{prefix}size", f"must be [width, height] in pixels, got {doc.get('size')!r}")
        return replace(PREVIEW_DEFAULTS, **{**doc, "size": size, "camera": camera,
                                            "camera_where": f"{prefix}camera"}).checked(prefix)


#: The defaults every entry point uses.
PREVIEW_DEFAULTS = PreviewOptions()
