"""Potree 2.0 tiles: structure, every point exactly once, even sampling, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from shared.core.errors import InputError
from shared.formats.ply import read_ply, write_ply
from shared.formats.potree import open_tiles
from shared.render import _tileplan, octree
from shared.render.octree import HIERARCHY_STEP, POINT_DTYPE, build_tiles, quantise
from tests.support.clouds import synthetic_scan

# One worker builds the module's tiles once and runs every test on them.
pytestmark = pytest.mark.xdist_group("octree")

HIER = np.dtype([("type", "u1"), ("mask", "u1"), ("points", "<u4"), ("offset", "<i8"), ("size", "<i8")])


@pytest.fixture(scope="module")
def scan(tmp_path_factory) -> Path:
    """A synthetic scan plus a dense 2 mm blob, so the octree gets deep (hierarchy proxies)."""
    folder = tmp_path_factory.mktemp("octree")
    base = read_ply(synthetic_scan(folder / "base.ply", 40_000, seed=3))
    rng = np.random.default_rng(4)
    blob = rng.uniform(0, 2, (5_000, 3)).astype(np.float32) + np.array([10, 20, 900], np.float32)
    xyz = np.concatenate([base.xyz, blob])
    rgb = np.concatenate([base.rgb, rng.integers(0, 256, (5_000, 3), dtype=np.uint8)])
    normals = np.concatenate([base.normals, np.tile(np.float32([0, 0, -1]), (5_000, 1))])
    size = np.concatenate([base.size, np.full(5_000, 0.01, np.float32)])
    return write_ply(folder / "scan.ply", xyz, rgb, normals, size)


@pytest.fixture(scope="module")
def tiles(scan: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("octree_out") / "tiles"
    # Small chunks and leaves: several chunks share the upper nodes, and the tree is deep
    # enough for hierarchy proxies.
    build_tiles(scan, out, workers=1, max_chunk=6_000, max_leaf=300)
    return out


def _as_rows(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    return np.sort(a.view(np.dtype((np.void, a.dtype.itemsize * a.shape[1]))).ravel())


def test_metadata_matches_potree_2(tiles: Path) -> None:
    meta = json.loads((tiles / "metadata.json").read_text())
    assert meta["version"] == "2.0" and meta["encoding"] == "DEFAULT"
    lo, hi = np.array(meta["boundingBox"]["min"]), np.array(meta["boundingBox"]["max"])
    edge = hi - lo
    assert np.allclose(edge, edge[0])  # cubic
    assert meta["spacing"] == pytest.approx(edge[0] / 128)
    assert sum(a["size"] for a in meta["attributes"]) == POINT_DTYPE.itemsize
    for a in meta["attributes"]:
        assert a["size"] == a["numElements"] * a["elementSize"]
        assert len(a["min"]) == len(a["max"]) == a["numElements"]
    assert [a["name"] for a in meta["attributes"]] == [
        "position",
        "rgb",
        "NormalX",
        "NormalY",
        "NormalZ",
        "size",
    ]
    assert meta["hierarchy"]["stepSize"] == HIERARCHY_STEP
    hier = (tiles / "hierarchy.bin").stat().st_size
    assert hier % 22 == 0 and 0 < meta["hierarchy"]["firstChunkSize"] <= hier


def test_hierarchy_bytes_tile_octree_bin(tiles: Path) -> None:
    t = open_tiles(tiles)
    meta = t.metadata
    assert meta["hierarchy"]["depth"] == max(n.level for n in t.nodes.values())
    assert meta["hierarchy"]["depth"] > HIERARCHY_STEP  # so proxies are exercised
    recs = np.fromfile(tiles / "hierarchy.bin", HIER)
    assert (recs["type"] == 2).any()
    # PotreeConverter's chunking: the first chunk holds levels 0..stepSize, those at
    # level stepSize as proxies pointing at their own chunks.
    first = [n for n in t.nodes.values() if n.level <= HIERARCHY_STEP]
    assert meta["hierarchy"]["firstChunkSize"] == 22 * len(first)
    head = recs[: len(first)]
    assert np.all((head["type"] == 2) == np.array([n.level == HIERARCHY_STEP for n in first]))
    assert len(recs) == len(t.nodes) + int((recs["type"] == 2).sum())
    spans = sorted((n.byte_offset, n.byte_size) for n in t.nodes.values())
    pos = 0
    for off, size in spans:
        assert off == pos  # no gap, no overlap
        pos += size
    assert pos == (tiles / "octree.bin").stat().st_size
    for n in t.nodes.values():
        assert n.byte_size == n.num_points * POINT_DTYPE.itemsize
        kids = [c for c in t.nodes if len(c) == len(n.name) + 1 and c.startswith(n.name)]
        assert n.child_mask == sum(1 << int(c[-1]) for c in kids)
        assert n.node_type == (1 if not kids else 0)


def test_every_point_exactly_once(scan: Path, tiles: Path) -> None:
    t = open_tiles(tiles)
    cloud = read_ply(scan)
    assert t.points == len(cloud)
    rec = np.concatenate([t.records(n) for n in t.nodes])
    qsize = 2**31 - 1
    expected = quantise(cloud.xyz, t.offset, float(t.scale[0]), qsize)
    assert np.array_equal(_as_rows(rec["position"]), _as_rows(expected))
    # Attributes travel with their point: compare (position, colour, normal, size) rows.
    normals = np.stack([rec["NormalX"], rec["NormalY"], rec["NormalZ"]], axis=1).astype("<f4")
    got = np.concatenate(
        [rec["position"].view(np.uint8).reshape(-1, 12), rec["rgb"].view(np.uint8).reshape(-1, 6),
         normals.view(np.uint8).reshape(-1, 12), rec["size"].reshape(-1, 1).view(np.uint8)], axis=1)  # fmt: skip
    want_rgb = (cloud.rgb.astype(np.uint16) * 257).astype("<u2")
    want = np.concatenate(
        [expected.view(np.uint8).reshape(-1, 12), want_rgb.view(np.uint8).reshape(-1, 6),
         cloud.normals.astype("<f4").view(np.uint8).reshape(-1, 12),
         cloud.size.astype("<f4").reshape(-1, 1).view(np.uint8)], axis=1)  # fmt: skip
    assert np.array_equal(_as_rows(got), _as_rows(want))
    assert np.allclose(np.linalg.norm(t.read_node("r").normal, axis=1), 1, atol=1e-4)


def test_nodes_hold_their_points_and_sample_evenly(tiles: Path) -> None:
    t = open_tiles(tiles)
    step = float(t.scale[0])
    for n in t.nodes.values():
        pts = t.read_node(n.name)
        assert np.all(pts.xyz >= n.box_min - step) and np.all(pts.xyz <= n.box_max + step)
        if n.node_type == 0:  # inner node: at most one point per cell of its 128^3 grid
            cell = np.floor((pts.xyz - n.box_min) / (n.box_max - n.box_min) * 128).astype(np.int64)
            cell = np.clip(cell, 0, 127)
            keys = (cell[:, 0] * 128 + cell[:, 1]) * 128 + cell[:, 2]
            assert np.unique(keys).size >= 0.99 * keys.size
        else:
            assert n.num_points <= 300
    # The root's grid sample covers the scene: its points reach near every corner of the bounds.
    root = t.read_node("r").xyz
    cloud_lo, cloud_hi = (
        np.array(a) for a in (t.metadata["attributes"][0]["min"], t.metadata["attributes"][0]["max"])
    )
    assert np.all(np.abs(root.min(axis=0) - cloud_lo) < 0.02 * (cloud_hi - cloud_lo).max())
    assert np.all(np.abs(root.max(axis=0) - cloud_hi) < 0.02 * (cloud_hi - cloud_lo).max())


@pytest.mark.parametrize("chunks_in", ["memory", "files"])
def test_parallel_build_gives_the_same_bytes(
    scan: Path, tiles: Path, tmp_path: Path, monkeypatch, chunks_in: str
) -> None:  # fmt: skip
    """Two worker threads (each pass over the cloud split in two ranges read in several
    slices), the chunks distributed into memory or into chunk files reopened for every write,
    change no byte."""
    if chunks_in == "files":
        monkeypatch.setattr(octree, "KEEP_POINTS", 0)
    monkeypatch.setattr(_tileplan, "MAX_OPEN_FILES", 2)
    monkeypatch.setattr(_tileplan, "MIN_PART_POINTS", 1_000)
    monkeypatch.setattr(_tileplan, "READ_CHUNK", 7_000)
    out = tmp_path / "par"
    build_tiles(scan, out, workers=2, max_chunk=6_000, max_leaf=300)
    for name in ("octree.bin", "hierarchy.bin", "metadata.json"):
        assert (out / name).read_bytes() == (tiles / name).read_bytes(), name


def test_fan_out_api_matches_the_in_process_build(scan: Path, tiles: Path, tmp_path: Path) -> None:
    """plan -> chunks (any order, retried) -> merge, as the job service runs it."""
    work = tmp_path / "work"
    plan = octree.plan_tiles(scan, work, max_chunk=6_000, max_leaf=300)
    assert len(plan.chunks) > 2
    for i in reversed(range(len(plan.chunks))):
        octree.build_chunk(work, i)
    octree.build_chunk(work, 0)  # a retried task changes nothing
    octree.merge_tiles(work, tmp_path / "fan")
    for name in ("octree.bin", "hierarchy.bin", "metadata.json"):
        assert (tmp_path / "fan" / name).read_bytes() == (tiles / name).read_bytes(), name


@pytest.mark.parametrize("kind", ["empty", "nan", "inf"])
def test_bad_clouds_raise_and_leave_nothing(tmp_path: Path, kind: str) -> None:
    xyz = np.random.default_rng(0).uniform(0, 100, (500, 3)).astype(np.float32)
    if kind == "empty":
        xyz = xyz[:0]
    else:
        xyz[17, 1] = np.nan if kind == "nan" else np.inf
    src = write_ply(tmp_path / "bad.ply", xyz)
    out = tmp_path / "out" / "tiles"
    with pytest.raises(InputError) as err:
        build_tiles(src, out, workers=1)
    assert "bad.ply" in str(err.value)
    assert ("empty" if kind == "empty" else "NaN or infinite") in str(err.value)
    assert not out.exists()
    assert list((tmp_path / "out").iterdir()) == []


def test_minimal_cloud_without_attributes(tmp_path: Path) -> None:
    src = write_ply(tmp_path / "one.ply", np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]], np.float32))
    build_tiles(src, tmp_path / "t", workers=1)
    t = open_tiles(tmp_path / "t")
    pts = t.read_node("r")
    assert len(pts) == 2 and np.allclose(pts.xyz, [1, 2, 3], atol=1e-5)
    assert (pts.rgb == 255).all()
