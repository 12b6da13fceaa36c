"""Octree-coded tile nodes (shared.compress.tilenode, tiles built with node_codec="octree").

Every node of octree-coded tiles decodes to exactly the records of the same node in the plain
(DEFAULT) tiles of the same cloud, as a multiset (the coded node holds them in octree order);
the hierarchy and metadata are the plain ones but for the node bytes and the encoding name.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from shared.compress import tilenode
from shared.core.errors import InputError
from shared.formats.ply import read_ply, write_ply
from shared.formats.potree import HIERARCHY_DTYPE, open_tiles
from shared.render.octree import build_chunk, build_tiles, merge_tiles, plan_tiles
from shared.render.preview import load_scene
from shared.service.params import tiles_options
from tests.support.clouds import synthetic_scan

pytestmark = pytest.mark.xdist_group("tilenode")


def _rows(rec: np.ndarray) -> np.ndarray:
    """Records as sorted rows of raw bytes (a multiset comparable with ``np.array_equal``)."""
    raw = np.ascontiguousarray(rec).view(np.uint8).reshape(len(rec), rec.dtype.itemsize)
    return raw[np.lexsort(raw.T[::-1])]


@pytest.fixture(scope="module")
def clouds(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A full scan with a dense blob and exact duplicates; the same points with nothing but x, y, z."""
    folder = tmp_path_factory.mktemp("tilenode-clouds")
    base = read_ply(synthetic_scan(folder / "base.ply", 30_000, seed=5))
    rng = np.random.default_rng(6)
    blob = rng.uniform(0, 2, (4_000, 3)).astype(np.float32) + np.array([10, 20, 900], np.float32)
    dup = np.repeat(base.xyz[:50], 4, axis=0)  # every one of these 4 times: cells with counts > 1
    xyz = np.concatenate([base.xyz, blob, dup])
    rgb = np.concatenate([base.rgb, rng.integers(0, 256, (4_000, 3), dtype=np.uint8), np.repeat(base.rgb[:50], 4, axis=0)])
    normals = np.concatenate([base.normals, rng.normal(size=(4_000, 3)).astype(np.float32), np.repeat(base.normals[:50], 4, axis=0)])
    size = np.concatenate([base.size, np.full(4_000, 0.01, np.float32), np.repeat(base.size[:50], 4, axis=0)])
    full = write_ply(folder / "full.ply", xyz, rgb, normals, size)
    bare = write_ply(folder / "bare.ply", xyz)
    return {"full": full, "bare": bare}


@pytest.fixture(scope="module")
def tile_pairs(clouds: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, Path]]:
    """Plain and octree-coded tiles of each cloud (small leaves and chunks: deep, several chunks)."""
    out = tmp_path_factory.mktemp("tilenode-tiles")
    pairs = {}
    for name, cloud in clouds.items():
        plain, coded = out / f"{name}_plain", out / f"{name}_octree"
        build_tiles(cloud, plain, workers=2, max_chunk=8_000, max_leaf=500)
        build_tiles(cloud, coded, workers=2, max_chunk=8_000, max_leaf=500, node_codec="octree")
        pairs[name] = (plain, coded)
    return pairs


@pytest.mark.parametrize("name", ["full", "bare"])
def test_every_node_decodes_to_the_plain_nodes_records(tile_pairs, name: str) -> None:
    plain_dir, coded_dir = tile_pairs[name]
    plain = open_tiles(plain_dir)
    with pytest.raises(InputError, match="encoding"):
        open_tiles(coded_dir)  # a reader without the decoder refuses: never misreads
    coded = open_tiles(coded_dir, decoders=tilenode.DECODERS)
    assert coded.encoding == tilenode.ENCODING and plain.encoding == "DEFAULT"
    assert list(coded.nodes) == list(plain.nodes)
    total = 0
    for nm, node in plain.nodes.items():
        other = coded.nodes[nm]
        assert (other.num_points, other.child_mask, other.node_type) == (node.num_points, node.child_mask, node.node_type)
        a, b = plain.records(nm), coded.records(nm)
        assert b.dtype == a.dtype and len(b) == len(a) == node.num_points
        assert np.array_equal(_rows(a), _rows(b)), f"node {nm} differs"
        total += len(a)
        # Decoded points match too (world positions, colour, normals, size), not only raw bytes.
        pa, pb = plain.read_node(nm), coded.read_node(nm)
        key_a, key_b = np.lexsort(pa.xyz.T[::-1]), np.lexsort(pb.xyz.T[::-1])
        assert np.array_equal(pa.xyz[key_a], pb.xyz[key_b]) and np.array_equal(pa.rgb[key_a], pb.rgb[key_b])
    assert total == plain.points
    # The metadata are the plain ones but for the encoding; the hierarchy but for the node bytes.
    meta_p = json.loads((plain_dir / "metadata.json").read_text())
    meta_c = json.loads((coded_dir / "metadata.json").read_text())
    assert meta_c.pop("encoding") == "GRAYLIGHT_OCTREE" and meta_p.pop("encoding") == "DEFAULT"
    assert meta_c == meta_p
    hp = np.fromfile(plain_dir / "hierarchy.bin", HIERARCHY_DTYPE)
    hc = np.fromfile(coded_dir / "hierarchy.bin", HIERARCHY_DTYPE)
    for field in ("type", "mask", "points"):
        assert np.array_equal(hp[field], hc[field])
    proxy = hp["type"] == 2
    assert proxy.any() and np.array_equal(hp[proxy][["offset", "size"]], hc[proxy][["offset", "size"]])
    # Nodes tile octree.bin breadth first, back to back, and the file is smaller.
    sizes = sum(n.byte_size for n in coded.nodes.values())
    assert sizes == (coded_dir / "octree.bin").stat().st_size < (plain_dir / "octree.bin").stat().st_size


def test_coded_tiles_are_several_times_smaller(tile_pairs) -> None:
    plain_dir, coded_dir = tile_pairs["full"]
    points = open_tiles(plain_dir).points
    plain_b, coded_b = ((d / "octree.bin").stat().st_size for d in (plain_dir, coded_dir))
    print(f"octree.bin {plain_b / points:.2f} -> {coded_b / points:.2f} bytes a point ({plain_b / coded_b:.2f}x)")
    # The blob's random normals cost nearly their 12 raw bytes; the scan's points far less.
    assert coded_b < 0.5 * plain_b


def test_fan_out_build_writes_the_same_coded_tiles(clouds, tile_pairs, tmp_path: Path) -> None:
    """plan_tiles(node_codec=...) + build_chunk + merge_tiles (the job service's path) gives
    the in-process build's bytes."""
    work = tmp_path / "work"
    plan = plan_tiles(clouds["full"], work, max_chunk=8_000, max_leaf=500, node_codec="octree")
    assert len(plan.chunks) > 1
    for i in range(len(plan.chunks)):
        build_chunk(work, i)
    merge_tiles(work, tmp_path / "tiles")
    _, coded = tile_pairs["full"]
    for name in ("metadata.json", "hierarchy.bin", "octree.bin"):
        assert (tmp_path / "tiles" / name).read_bytes() == (coded / name).read_bytes(), name


def test_plain_is_the_default_and_unknown_codecs_are_refused(clouds, tile_pairs, tmp_path: Path) -> None:
    plain_dir, _ = tile_pairs["full"]
    build_tiles(clouds["full"], tmp_path / "default", workers=2, max_chunk=8_000, max_leaf=500)
    for name in ("metadata.json", "hierarchy.bin", "octree.bin"):
        assert (tmp_path / "default" / name).read_bytes() == (plain_dir / name).read_bytes()
    with pytest.raises(InputError, match="node_codec"):
        build_tiles(clouds["full"], tmp_path / "bad", workers=1, node_codec="zstd")
    assert not (tmp_path / "bad").exists()


def test_preview_scene_of_coded_tiles_equals_the_plain_one(tile_pairs) -> None:
    plain_dir, coded_dir = tile_pairs["full"]
    a = load_scene(open_tiles(plain_dir))
    b = load_scene(open_tiles(coded_dir, decoders=tilenode.DECODERS))
    assert a.names == b.names and np.array_equal(a.ranges, b.ranges)
    for lo, hi in a.ranges:
        ka = np.lexsort(np.c_[a.xyz[lo:hi], a.colour[lo:hi]].T[::-1])
        kb = np.lexsort(np.c_[b.xyz[lo:hi], b.colour[lo:hi]].T[::-1])
        assert np.array_equal(a.xyz[lo:hi][ka], b.xyz[lo:hi][kb])
        assert np.array_equal(a.colour[lo:hi][ka], b.colour[lo:hi][kb])


# --------------------------------------------------------------------------- the node codec alone


def _records(n: int, rng: np.random.Generator, span: int = 2**27, eight: bool = True) -> np.ndarray:
    rec = np.zeros(n, tilenode.node_dtype(True, True, True))
    rec["position"] = rng.integers(0, span, (n, 3))
    rec["rgb"] = rng.integers(0, 256, (n, 3)) * 257 if eight else rng.integers(0, 65536, (n, 3))
    rec["normal"] = rng.normal(size=(n, 3))
    rec["size"] = rng.random(n)
    return rec


@pytest.mark.parametrize(
    "case", ["empty", "one", "same point", "16-bit colour", "wide", "positions only", "negative zero and nan"]
)
def test_node_round_trip_edge_cases(case: str) -> None:
    rng = np.random.default_rng(11)
    rec = _records({"empty": 0, "one": 1}.get(case, 2000), rng)
    if case == "same point":
        rec["position"] = [123, -7, 2**30]
    elif case == "16-bit colour":
        rec = _records(2000, rng, eight=False)
    elif case == "wide":
        rec["position"][:, 0] = rng.integers(-(2**31), 2**31 - 1, len(rec))
        rec["position"][:2, 0] = [-(2**31), 2**31 - 1]  # the whole int32 range on one axis
    elif case == "positions only":
        rec = np.array(rec[["position"]]).astype(tilenode.node_dtype(False, False, False))
    elif case == "negative zero and nan":
        rec["normal"][::3] = -0.0
        rec["size"][::5] = np.nan
        rec["size"][1::5] = np.float32(np.frombuffer(np.uint32(0x7FC00123).tobytes(), np.float32)[0])
    data = tilenode.encode_node(rec)
    out = tilenode.decode_node(data, rec.dtype, len(rec))
    assert out.dtype == rec.dtype and np.array_equal(_rows(out), _rows(rec))


def test_decoded_order_is_the_octree_order() -> None:
    """Points come back sorted by their cells (Morton order, x the high bit): what the viewer
    relies on to read attributes in step with the positions."""
    rng = np.random.default_rng(2)
    rec = _records(3000, rng, span=1 << 12)
    out = tilenode.decode_node(tilenode.encode_node(rec), rec.dtype)
    p = out["position"].astype(np.int64) - out["position"].min(axis=0)
    code = np.zeros(len(p), np.int64)
    for bit in range(12):
        for axis, shift in ((0, 2), (1, 1), (2, 0)):
            code |= ((p[:, axis] >> bit) & 1) << (3 * bit + shift)
    assert np.all(np.diff(code) >= 0)


def test_bad_nodes_are_clear_errors() -> None:
    rng = np.random.default_rng(3)
    rec = _records(500, rng)
    data = tilenode.encode_node(rec)
    assert len(tilenode.decode_node(b"", rec.dtype, 0)) == 0  # an empty node has no bytes, as in plain tiles
    with pytest.raises(InputError, match="truncated"):
        tilenode.decode_node(b"", rec.dtype, 5)
    with pytest.raises(InputError, match="truncated"):
        tilenode.decode_node(data[:8], rec.dtype)
    with pytest.raises(InputError, match="magic"):
        tilenode.decode_node(b"XXXX" + data[4:], rec.dtype)
    with pytest.raises(InputError, match="hierarchy says"):
        tilenode.decode_node(data, rec.dtype, 499)
    with pytest.raises(InputError, match="its streams"):
        tilenode.decode_node(data[:-20], rec.dtype)  # raw planes cut short
    with pytest.raises(InputError, match="truncated"):
        tilenode.decode_node(data[:100], rec.dtype)  # the zlib stream cut short
    with pytest.raises(InputError, match="attributes"):
        tilenode.decode_node(data, tilenode.node_dtype(True, False, True))
    with pytest.raises(InputError, match="cannot be octree-coded"):
        tilenode.encode_node(np.zeros(3, [("position", "<i4", (3,)), ("intensity", "<u2")]))
    # A flipped byte anywhere (head, zlib stream or raw planes): a check or a checksum refuses it.
    zlen = tilenode._HEAD.unpack_from(data)[3]
    assert tilenode._HEAD.size + zlen < len(data) - 500  # the random normals' low bytes went raw
    for at in [*range(0, 20), *range(20, len(data), max(1, len(data) // 60))]:
        bad = bytearray(data)
        bad[at] ^= 0x5A
        with pytest.raises(InputError):
            tilenode.decode_node(bytes(bad), rec.dtype)


def test_tiles_parameter_checks_the_codec() -> None:
    assert tiles_options({"node_codec": "octree", "max_leaf": 500}) == {"node_codec": "octree", "max_leaf": 500}
    with pytest.raises(InputError, match=r"params\.tiles\.node_codec"):
        tiles_options({"node_codec": "brotli"})
    with pytest.raises(InputError, match=r"params\.tiles\.node_codec"):
        tiles_options({"node_codec": ["octree"]})


def test_cli_tiles_node_codec(clouds, tmp_path: Path, capsys) -> None:
    from services.cli.main import main

    assert main(["tiles", str(clouds["bare"]), "--out", str(tmp_path / "t"), "--workers", "1", "--node-codec", "octree"]) == 0
    assert json.loads((tmp_path / "t" / "metadata.json").read_text())["encoding"] == "GRAYLIGHT_OCTREE"
    assert "tiles:" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["tiles", str(clouds["bare"]), "--out", str(tmp_path / "u"), "--node-codec", "lzma"])
    assert not (tmp_path / "u").exists()
