"""Triangle meshes for the virtual rig: a small Wavefront OBJ reader in numpy.

In: an ``.obj`` file (``v x y z`` vertex lines and ``f`` face lines whose entries may be
``i``, ``i/t``, ``i//n`` or ``i/t/n``, 1-based or negative = relative to the vertices read
so far; polygons are fan-triangulated). Out: :class:`TriangleMesh` with ``vertices``
(V, 3) float64 in the file's units and ``faces`` (F, 3) int32 0-based indices.
Everything else in the file (normals, texture coordinates, materials, groups) is ignored.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.core.errors import InputError


@dataclass(frozen=True)
class TriangleMesh:
    """An indexed triangle mesh.

    Attributes
    ----------
    vertices : (V, 3) float64
    faces : (F, 3) int32, 0-based indices into ``vertices``
    """

    vertices: np.ndarray
    faces: np.ndarray

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box ``(min (3,), max (3,))``."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def face_normals(self) -> np.ndarray:
        """(F, 3) float64 unit normals by the right-hand rule of each face's winding."""
        v = self.vertices
        a, b, c = v[self.faces[:, 0]], v[self.faces[:, 1]], v[self.faces[:, 2]]
        n = np.cross(b - a, c - a)
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return n / np.where(length > 0, length, 1.0)

    def transformed(self, R: np.ndarray, t: np.ndarray, scale: float = 1.0) -> TriangleMesh:
        """The mesh with vertices ``R @ (scale * v) + t``."""
        v = (scale * self.vertices) @ np.asarray(R, float).T + np.asarray(t, float)
        return TriangleMesh(vertices=v, faces=self.faces)


def parse_obj(text: str, where: str | os.PathLike[str] = "<obj>") -> TriangleMesh:
    """Parse OBJ text; polygons with more than three corners become triangle fans.

    Raises :class:`InputError` naming ``where`` and the line for malformed content, and
    when the file holds no triangle.
    """
    vertices: list[list[str]] = []
    # Per polygon: its indices as written and the number of vertices read before it (negative
    # indices count back from there).
    polys: list[tuple[list[int], int, int]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        parts = raw.split()
        if not parts:
            continue
        tag = parts[0]
        if tag == "v":
            if len(parts) < 4:
                raise InputError(f"{where}:{lineno}", "vertex line needs three coordinates")
            vertices.append(parts[1:4])
        elif tag == "f":
            if len(parts) < 4:
                raise InputError(f"{where}:{lineno}", "face line needs at least three vertices")
            try:
                idx = [int(tok.split("/", 1)[0]) for tok in parts[1:]]
            except ValueError:
                raise InputError(f"{where}:{lineno}", f"face indices are not integers: {raw.strip()!r}") from None
            polys.append((idx, len(vertices), lineno))
    if not polys:
        raise InputError(where, "OBJ file holds no faces")
    try:
        v = np.asarray(vertices, dtype=np.float64)
    except ValueError:
        raise InputError(where, "vertex coordinates are not all numbers") from None
    if not np.all(np.isfinite(v)):
        raise InputError(where, "OBJ file holds NaN or infinite vertex coordinates")
    faces: list[tuple[int, int, int]] = []
    for idx, nv, lineno in polys:
        fixed = []
        for i in idx:
            j = i - 1 if i > 0 else nv + i
            if i == 0 or not 0 <= j < nv:
                raise InputError(f"{where}:{lineno}", f"face index {i} refers to a vertex that does not exist ({nv} read so far)")
            fixed.append(j)
        for k in range(1, len(fixed) - 1):
            faces.append((fixed[0], fixed[k], fixed[k + 1]))
    return TriangleMesh(vertices=v, faces=np.asarray(faces, dtype=np.int32))


def load_obj(path: str | os.PathLike[str]) -> TriangleMesh:
    """Read a Wavefront OBJ file (see :func:`parse_obj`); a missing file is an :class:`InputError`.

    Results are cached per (path, modification time, size): scenes reload the same meshes often.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "mesh file not found")
    st = p.stat()
    return _load_cached(str(p.resolve()), st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=8)
def _load_cached(path: str, mtime_ns: int, size: int) -> TriangleMesh:
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise InputError(p, f"cannot read mesh file ({exc.strerror})") from None
    return parse_obj(text, p)
