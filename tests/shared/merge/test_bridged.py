"""The master mesh says where Poisson made surface up: vertices over a gap in the samples carry a
``bridged`` flag, kept in mesh.ply and read back by the derivatives."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from shared.derive.pipeline import load_bridged
from shared.merge.meshing import MeshParams, reconstruct_mesh, write_mesh


def test_vertices_over_a_gap_are_flagged_bridged_and_kept_in_the_ply(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    d = rng.normal(size=(60_000, 3))
    n = d / np.linalg.norm(d, axis=1, keepdims=True)
    xyz = 20.0 * n
    gap = np.abs(xyz[:, 2]) < 1.0  # a 2 mm band with no samples round the equator
    xyz, n = xyz[~gap], n[~gap]
    size = np.full(len(xyz), 0.35, np.float32)  # about the samples' spacing
    mesh, stats = reconstruct_mesh(xyz, n, np.full((len(xyz), 3), 128, np.uint8), size, MeshParams(max_depth=8))
    assert mesh.bridged is not None and len(mesh.bridged) == len(mesh.vertices)
    z = np.abs(mesh.vertices[:, 2])
    assert (z[mesh.bridged] < 1.0).all()  # nothing over measured surface is flagged
    assert mesh.bridged[z < 0.3].mean() > 0.9  # the middle of the band is
    assert stats["bridged_vertex_share"] == round(float(mesh.bridged.mean()), 5)
    write_mesh(tmp_path / "mesh.ply", mesh)
    flag = load_bridged(tmp_path / "mesh.ply", len(mesh.vertices))
    assert flag is not None and np.array_equal(flag, mesh.bridged)
    write_mesh(tmp_path / "mesh.glb", mesh)  # the GLB has no such property and is written all the same
