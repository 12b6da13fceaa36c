"""Meshing of a fused cloud: screened Poisson, trimmed by sample density, then level-of-detail meshes.

- :func:`reconstruct_mesh`: pymeshlab's screened Poisson reconstruction (Kazhdan and Hoppe 2013)
  of the oriented points; the octree depth follows the spacing of the points Poisson gets (one
  finest cell per ``samples_per_cell`` sample sizes, or per grid step of the thinned cloud when
  that is coarser, capped by ``max_depth``). Poisson closes every hole with a smooth
  surface; the result is **trimmed** where the samples do not support it: a vertex farther than
  ``trim_factor`` local sample sizes from every sample goes, with its faces. Vertex colours are the
  nearest sample's. A kept vertex farther than ``bridge_factor`` local sample sizes from every
  sample lies on surface Poisson made up across a gap: it is **flagged bridged** (a ``bridged``
  uchar vertex property in ``mesh.ply``, 1 bridged, 0 measured), so nobody takes it for data.
- :func:`simplify_lods`: quadric decimation with ``fast-simplification`` to 1/4, 1/16, 1/64 of
  the faces, each level from the one before (colours carried over from the nearest
  full-resolution vertex).
- :func:`write_mesh`: PLY (binary, vertex colours) or binary glTF (``.glb``, ``COLOR_0``), written
  through a temporary name; readable by Blender, MeshLab and three.js.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from shared.core.errors import InputError
from shared.core.files import atomic_file
from shared.core.threads import cpu_budget

log = logging.getLogger(__name__)

__all__ = ["ColouredMesh", "MeshParams", "reconstruct_mesh", "simplify_lods", "write_mesh"]


@dataclass(frozen=True)
class MeshParams:
    """max_depth : deepest Poisson octree level. samples_per_cell : sample sizes per finest octree
    cell (sets the depth with the thinned cloud's step). samples_per_node, point_weight, iters :
    screened Poisson's own parameters (``iters``: Gauss-Seidel relaxations per octree level).
    trim_factor : a vertex farther than this many local sample sizes from every sample is trimmed.
    bridge_factor : a kept vertex farther than this many local sample sizes from every sample is
    flagged bridged (not measured).
    lods : face-count fractions of the level-of-detail meshes. max_points : a larger cloud is thinned on
    a grid to about this many points before the reconstruction. threads : Poisson's OpenMP threads
    (measured here on a busy 2-core machine, load 5-6: 2 threads took 3-10x the CPU time of 1 with
    OpenMP's default spinning, and with ``OMP_WAIT_POLICY=PASSIVE`` the same CPU and the same wall
    time as 1, 51 s: one thread it is).

    Measured on the 12-view 2048x1536 bunny turntable merge (4.2 M fused points, 0.19 mm samples,
    277 mm across with the plate, merged RMS 0.023 mm against the true surface; the issue's bound
    is a two-sided Hausdorff 95th percentile within 3x that, 0.068 mm), CPU seconds of the Poisson
    filter and the bound's ratio: depth 9 from 400 k points 37-40 s, 1.97x; depth 8 (a 1.2 mm
    cell) 13 s, 4.4x (fails); 200 k points at depth 9 38 s, 2.33x (Poisson's time follows the
    depth-9 cells on the surface, not the point count); 100 k points 12.5 s, 4.1x (the octree
    stops at depth 8 where a cell holds under ``samples_per_node`` points: fails);
    ``samples_per_node`` 4 18 s, 2.92x (too close to the bound); ``iters`` 4 instead of
    PoissonRecon's 8 35 s, 1.97x (the same surface). Hence 400 k points with ``iters`` 4 and the
    depth where a cell is the thinned cloud's step (0.73 mm here: depth 9)."""

    max_depth: int = 9
    samples_per_cell: float = 2.0
    samples_per_node: float = 1.5
    point_weight: float = 4.0
    trim_factor: float = 3.0
    bridge_factor: float = 1.5
    lods: tuple[float, ...] = (1 / 4, 1 / 16, 1 / 64)
    threads: int = 1
    max_points: int = 400_000
    iters: int = 4


@dataclass
class ColouredMesh:
    """vertices (V, 3) float64 mm, faces (F, 3) int64, colours (V, 3) uint8; bridged (V,) bool
    (surface made up across a gap, no sample near) or None when not known."""

    vertices: np.ndarray
    faces: np.ndarray
    colours: np.ndarray
    bridged: np.ndarray | None = None

    @property
    def n_faces(self) -> int:
        return int(len(self.faces))


def _compact(vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray,
             bridged: np.ndarray | None = None) -> ColouredMesh:
    used = np.zeros(len(vertices), bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used) - 1
    return ColouredMesh(vertices=vertices[used], faces=remap[faces].astype(np.int64), colours=colours[used],
                        bridged=None if bridged is None else bridged[used])


def _thin(xyz: np.ndarray, normals: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Grid means of about ``target`` points (renormalised mean normals) and the grid step (mm)."""
    extent = np.ptp(xyz, axis=0)
    step = float(np.sqrt(np.prod(np.sort(extent)[1:]) * 2.0 / target))  # a closed surface: ~2 box faces
    for _ in range(4):
        keys = np.floor((xyz - xyz.min(axis=0)) / step).astype(np.int64)
        dims = keys.max(axis=0) + 1
        flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
        uniq, inv = np.unique(flat, return_inverse=True)
        if len(uniq) <= 1.3 * target:
            break
        step *= float(np.sqrt(len(uniq) / target))
    inv = inv.ravel()
    n = len(uniq)
    counts = np.bincount(inv, minlength=n).astype(np.float64)
    out = np.stack([np.bincount(inv, weights=xyz[:, a], minlength=n) / counts for a in range(3)], axis=1)
    nrm = np.stack([np.bincount(inv, weights=normals[:, a], minlength=n) for a in range(3)], axis=1)
    length = np.linalg.norm(nrm, axis=1)
    ok = length > 1e-9
    return out[ok], nrm[ok] / length[ok, None], step


def reconstruct_mesh(xyz: np.ndarray, normals: np.ndarray, rgb: np.ndarray, size: np.ndarray,
                     params: MeshParams | None = None) -> tuple[ColouredMesh, dict]:
    """Screened Poisson surface of oriented points, trimmed by density.

    xyz (N, 3) mm, normals (N, 3) unit (outward), rgb (N, 3) uint8, size (N,) mm sample sizes.
    Returns the mesh and statistics (depth, faces before and after trimming).
    """
    import pymeshlab  # slow import (Qt and MeshLab plug-ins): only when meshing

    params = params or MeshParams()
    if len(xyz) < 100:
        raise InputError("merged cloud", f"{len(xyz)} points are too few to mesh")
    xyz = np.asarray(xyz, np.float64)
    extent = float(np.max(np.ptp(xyz, axis=0)))
    step = params.samples_per_cell * float(np.median(size))
    pxyz, pnrm = xyz, np.asarray(normals, np.float64)
    if len(xyz) > params.max_points:
        pxyz, pnrm, grid = _thin(xyz, pnrm, params.max_points)
        step = max(step, grid)
    # Poisson's bounding cube is 1.1 times the cloud's extent (its ``scale``).
    depth = int(np.clip(np.ceil(np.log2(max(extent * 1.1 / max(step, 1e-9), 2.0))), 5, params.max_depth))
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=pxyz, v_normals_matrix=pnrm))
    ms.generate_surface_reconstruction_screened_poisson(depth=depth, samplespernode=params.samples_per_node,
                                                        pointweight=params.point_weight, preclean=False,
                                                        threads=params.threads, iters=params.iters)
    m = ms.current_mesh()
    verts = np.asarray(m.vertex_matrix(), np.float64)
    faces = np.asarray(m.face_matrix(), np.int64)
    n_raw = len(faces)
    tree = cKDTree(xyz, balanced_tree=False, compact_nodes=False)  # builds in half the time, queries as fast
    d, nearest = tree.query(verts, k=1, workers=cpu_budget())
    ok = d <= params.trim_factor * np.maximum(size[nearest], 1e-6) + 0.5 * extent / (1 << depth)
    faces = faces[ok[faces].all(axis=1)]
    if len(faces) == 0:
        raise InputError("merged cloud", "the Poisson surface has no face near the samples")
    bridged = d > params.bridge_factor * np.maximum(size[nearest], 1e-6)
    mesh = _compact(verts, faces, np.asarray(rgb, np.uint8)[nearest], bridged)
    stats = {"depth": depth, "poisson_points": int(len(pxyz)), "faces_poisson": int(n_raw), "faces": mesh.n_faces,
             "vertices": int(len(mesh.vertices)), "bridged_vertex_share": round(float(bridged[np.unique(faces)].mean()), 5),
             "bridge_factor": params.bridge_factor}
    log.info("Poisson depth %d: %d faces, %d after trimming", depth, n_raw, mesh.n_faces)
    return mesh, stats


def simplify_lods(mesh: ColouredMesh, fractions: tuple[float, ...] = (1 / 4, 1 / 16, 1 / 64)) -> list[ColouredMesh]:
    """Level-of-detail meshes with about ``fraction * faces`` faces each (fast-simplification).

    ``fractions`` of the full mesh's faces, returned in their order; each level is simplified from
    the next larger one: 1.33 full-size decimations for 1/4, 1/16, 1/64 instead of 3 (measured on a
    1.2 M-face Poisson mesh: 1.9 s of CPU instead of 4.3 s, and RMS distances to the full mesh of
    0.0044 / 0.014 / 0.047 mm against 0.0044 / 0.016 / 0.053 mm from the full mesh each time).
    Colours are the nearest full-resolution vertex's.
    """
    import fast_simplification

    tree = cKDTree(mesh.vertices)
    out: list[ColouredMesh | None] = [None] * len(fractions)
    src = mesh
    for k in sorted(range(len(fractions)), key=lambda i: -fractions[i]):
        target = max(4, int(round(mesh.n_faces * fractions[k])))
        if target < src.n_faces:
            v, fc = fast_simplification.simplify(src.vertices.astype(np.float64), src.faces.astype(np.int32),
                                                 target_count=target)
        else:
            v, fc = src.vertices, src.faces
        if len(fc) == 0:
            raise InputError("mesh", f"simplification to {target} faces left nothing")
        _, idx = tree.query(v, k=1, workers=cpu_budget())
        src = _compact(np.asarray(v, np.float64), np.asarray(fc, np.int64), mesh.colours[idx])
        out[k] = src
    return [m for m in out if m is not None]


def write_mesh(path: str | os.PathLike[str], mesh: ColouredMesh) -> Path:
    """Write a mesh as ``.ply`` or ``.glb`` (by the name's suffix), atomically; a PLY keeps the
    ``bridged`` flag as a uchar vertex property when the mesh has it."""
    import trimesh

    path = Path(path)
    kind = path.suffix.lower().lstrip(".")
    if kind not in ("ply", "glb"):
        raise ValueError(f"unsupported mesh format {path.suffix!r}")
    rgba = np.concatenate([mesh.colours, np.full((len(mesh.colours), 1), 255, np.uint8)], axis=1)
    tm = trimesh.Trimesh(vertices=mesh.vertices, faces=mesh.faces, vertex_colors=rgba, process=False)
    if kind == "ply" and mesh.bridged is not None:
        tm.vertex_attributes["bridged"] = mesh.bridged.astype(np.uint8)
    with atomic_file(path, suffix=f".tmp.{kind}") as tmp:
        tm.export(tmp, file_type=kind)
    return path
