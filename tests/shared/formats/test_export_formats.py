"""Exports read back by independent readers: laspy (LAZ, and its CopcReader for COPC), pye57 for
E57, plyfile for PLY; plus the LAS scale and bad input."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest
from laspy.copc import Bounds, load_octree_for_query
from plyfile import PlyData
from pye57 import E57

from shared.core.errors import InputError
from shared.formats.e57 import read_e57
from shared.formats.las import COPC_ENTRY, coordinate_scale, potree_key
from shared.render.export import export_cloud
from tests.support.clouds import ALL_FIELDS, surface_points, write_cloud

pytestmark = pytest.mark.xdist_group("export")


@pytest.fixture(scope="module")
def arrays() -> dict:
    return surface_points(240, 180, seed=5)


@pytest.fixture(scope="module")
def full(arrays: dict, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_cloud(tmp_path_factory.mktemp("export") / "full.ply", arrays, ALL_FIELDS)


def _quantised(xyz: np.ndarray, scale: float, offset: np.ndarray) -> np.ndarray:
    return np.floor((xyz.astype(np.float64) - offset) * (1.0 / scale) + 0.5).astype(np.int64)


def _rows(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a, np.int64)
    return np.sort(a.view(np.dtype((np.void, 24))).ravel())


def test_laz_keeps_every_property(full: Path, arrays: dict, tmp_path: Path) -> None:
    out = tmp_path / "cloud.laz"
    report = export_cloud(full, out, "laz")
    las = laspy.read(out)
    n = len(arrays["xyz"])
    assert las.header.version.minor == 4 and las.header.point_format.id == 7 and las.header.point_count == n
    scale = las.header.scales[0]
    assert report["scale"] == scale == coordinate_scale(arrays["xyz"].min(0), arrays["xyz"].max(0))
    xyz = np.stack([las.x, las.y, las.z], axis=1)
    assert np.abs(xyz - arrays["xyz"]).max() <= scale / 2 * 1.001
    assert np.array_equal(np.stack([las.red, las.green, las.blue], 1), arrays["rgb"].astype(np.uint16) * 257)
    assert set(las.point_format.extra_dimension_names) == {
        "NormalX",
        "NormalY",
        "NormalZ",
        "size",
        "confidence",
        "view",
    }
    normal = np.stack([las.NormalX, las.NormalY, las.NormalZ], axis=1)
    assert np.array_equal(normal, arrays["normal"])
    assert np.array_equal(las.size, arrays["size"])
    assert np.array_equal(las.confidence, arrays["confidence"])
    assert las.view.dtype == np.uint8 and np.array_equal(las.view, arrays["view"])
    assert np.all(las.return_number == 1) and np.all(las.number_of_returns == 1)
    units = [v for v in las.header.vlrs if v.user_id == "graylight"]
    assert units and units[0].record_data == b"units mm"


def test_uncompressed_las_and_colourless_cloud(arrays: dict, tmp_path: Path) -> None:
    bare = write_cloud(tmp_path / "bare.ply", arrays, ("xyz",))
    export_cloud(bare, tmp_path / "bare.las", "las")
    las = laspy.read(tmp_path / "bare.las")
    assert las.header.point_format.id == 6 and not list(las.point_format.extra_dimension_names)
    assert las.header.point_count == len(arrays["xyz"])


def test_scale_keeps_float32_precision() -> None:
    rng = np.random.default_rng(1)
    for magnitude in (0.5, 30.0, 700.0, 12_000.0):
        xyz = (rng.uniform(-1, 1, (20_000, 3)) * magnitude + [0, 0, 2 * magnitude]).astype(np.float32)
        lo, hi = xyz.min(0).astype(np.float64), xyz.max(0).astype(np.float64)
        s = coordinate_scale(lo, hi)
        m = np.abs(np.concatenate([lo, hi])).max()
        ulp = np.spacing(np.float32(m))
        assert s <= ulp  # no coordinate moves by more than half the PLY's own float32 step there
        q = _quantised(xyz, s, lo)
        assert q.max() < 2**31 - 1 and q.min() >= 0
        assert np.abs(q * s + lo - xyz).max() <= s / 2 * 1.001


def test_copc_hierarchy_reaches_every_point_once(full: Path, arrays: dict, tmp_path: Path) -> None:
    out = tmp_path / "cloud.copc.laz"
    report = export_cloud(full, out, "copc", workers=1, max_leaf=2_000)
    n = len(arrays["xyz"])
    assert report["points"] == n
    with laspy.CopcReader.open(out) as reader:
        h = reader.header
        assert h.point_count == n and h.point_format.id == 7
        scale, offset = h.scales[0], h.offsets
        assert scale == coordinate_scale(arrays["xyz"].min(0), arrays["xyz"].max(0))
        info = reader.copc_info
        nodes = load_octree_for_query(reader.source, info, reader.root_page)
        assert sum(nd.point_count for nd in nodes) == n
        assert max(nd.key.level for nd in nodes) >= 1  # a real hierarchy, not one node
        root = Bounds(info.center - info.halfsize, info.center + info.halfsize)
        seen = []
        for nd in nodes:  # every node's points lie inside the node's cube
            if nd.point_count == 0:
                continue
            pts = reader._fetch_and_decompress_points_of_nodes([nd])
            assert len(pts) == nd.point_count
            b = nd.key.bounds(root)
            xyz = np.stack([pts.X, pts.Y, pts.Z], axis=1) * scale + offset
            assert np.all(xyz >= b.mins - scale) and np.all(xyz <= b.maxs + scale), nd.key
            seen.append(np.stack([pts.X, pts.Y, pts.Z], axis=1))
        every = reader.query()
        assert len(every) == n
        levels = sum(len(reader.query(level=lv)) for lv in range(max(nd.key.level for nd in nodes) + 1))
        assert levels == n
        # Each source point exactly once: the multiset of stored integers is the source's.
        assert np.array_equal(_rows(np.concatenate(seen)), _rows(_quantised(arrays["xyz"], scale, offset)))
        # A spatial query returns exactly the points inside the box.
        lo, hi = arrays["xyz"].min(0), arrays["xyz"].max(0)
        box = Bounds(lo + (hi - lo) * 0.2, lo + (hi - lo) * 0.6)
        got = reader.spatial_query(box)
        q = _quantised(arrays["xyz"], scale, offset)
        qmin = np.round((box.mins - offset) / scale)
        qmax = np.round((box.maxs - offset) / scale)
        inside = np.all((q >= qmin) & (q <= qmax), axis=1)
        assert len(got) == int(inside.sum()) > 0
        # Attributes travel with their points: match by position.
        all_pts = reader.query()
    order_src = np.lexsort(_quantised(arrays["xyz"], scale, offset).T)
    stored = np.stack([all_pts.X, all_pts.Y, all_pts.Z], axis=1)
    order_las = np.lexsort(stored.T)
    assert np.array_equal(
        np.asarray(all_pts.red)[order_las], arrays["rgb"][order_src, 0].astype(np.uint16) * 257
    )
    assert np.array_equal(np.asarray(all_pts.NormalZ)[order_las], arrays["normal"][order_src, 2])
    assert np.array_equal(np.asarray(all_pts.size)[order_las], arrays["size"][order_src])
    # The properties the tiles do not carry come along too (looked up by position).
    assert set(all_pts.point_format.extra_dimension_names) >= {"confidence", "view"}
    assert np.array_equal(np.asarray(all_pts.confidence)[order_las], arrays["confidence"][order_src])
    assert np.array_equal(np.asarray(all_pts.view)[order_las], arrays["view"][order_src])


def test_copc_extras_of_coincident_points(tmp_path: Path) -> None:
    a = surface_points(60, 45, seed=3)
    a["xyz"][10:30] = a["xyz"][5]  # twenty-one points at one place, each with its own confidence
    cloud = write_cloud(tmp_path / "dup.ply", a, ALL_FIELDS)
    export_cloud(cloud, tmp_path / "dup.copc.laz", "copc", workers=1)
    with laspy.CopcReader.open(tmp_path / "dup.copc.laz") as r:
        pts = r.query()
        q = _quantised(a["xyz"], r.header.scales[0], r.header.offsets)
    stored = np.stack([pts.X, pts.Y, pts.Z], axis=1).astype(np.int64)
    src = np.lexsort((a["confidence"], q[:, 2], q[:, 1], q[:, 0]))
    got = np.lexsort((np.asarray(pts.confidence), stored[:, 2], stored[:, 1], stored[:, 0]))
    assert np.array_equal(q[src], stored[got])
    assert np.array_equal(a["confidence"][src], np.asarray(pts.confidence)[got])  # none lost, none doubled


def test_copc_of_a_big_tree_with_several_compression_batches(
    arrays: dict, tmp_path: Path, monkeypatch
) -> None:
    from shared.formats import las as las_mod

    monkeypatch.setattr(las_mod, "COPC_BATCH", 2_000)  # several compress_chunks calls
    cloud = write_cloud(tmp_path / "c.ply", arrays, ("xyz", "rgb", "normal", "size"))
    out = tmp_path / "c.copc.laz"
    export_cloud(cloud, out, "copc", workers=1, max_leaf=500)
    with laspy.CopcReader.open(out) as reader:
        assert len(reader.query()) == len(arrays["xyz"])
        raw = out.read_bytes()
        page = raw[reader.copc_info.hierarchy_root_offset :][: reader.copc_info.hierarchy_root_size]
        entries = [COPC_ENTRY.unpack_from(page, k) for k in range(0, len(page), COPC_ENTRY.size)]
    keys = [e[:4] for e in entries]
    assert len(set(keys)) == len(keys)
    for lv, x, y, z in keys:  # every node's parent is in the hierarchy
        assert lv == 0 or (lv - 1, x >> 1, y >> 1, z >> 1) in set(keys)


def test_potree_key_order() -> None:
    assert potree_key("r") == (0, 0, 0, 0)
    assert potree_key("r4") == (1, 1, 0, 0)  # Potree child bit 2 is x
    assert potree_key("r21") == (2, 0, 2, 1)


def test_e57_read_by_pye57(full: Path, arrays: dict, tmp_path: Path) -> None:
    out = tmp_path / "cloud.e57"
    export_cloud(full, out, "e57")
    e57 = E57(str(out))
    try:
        assert e57.scan_count == 1
        raw = e57.read_scan_raw(0, ignore_unsupported_fields=True)
    finally:
        e57.close()
    xyz = np.stack([raw["cartesianX"], raw["cartesianY"], raw["cartesianZ"]], axis=1)
    assert np.array_equal(xyz.astype(np.float32), arrays["xyz"])  # single floats: nothing rounded
    rgb = np.stack([raw["colorRed"], raw["colorGreen"], raw["colorBlue"]], axis=1)
    assert np.array_equal(rgb, arrays["rgb"])
    back = read_e57(out)
    assert back.normals is not None and np.array_equal(back.normals, arrays["normal"])


def test_e57_without_colour_or_normals(arrays: dict, tmp_path: Path) -> None:
    bare = write_cloud(tmp_path / "bare.ply", arrays, ("xyz",))
    export_cloud(bare, tmp_path / "bare.e57", "e57")
    back = read_e57(tmp_path / "bare.e57")
    assert back.rgb is None and back.normals is None and len(back) == len(arrays["xyz"])


def test_ply_export_keeps_every_property(full: Path, arrays: dict, tmp_path: Path) -> None:
    out = tmp_path / "copy.ply"
    export_cloud(full, out, "ply")
    ply = PlyData.read(str(out))
    v = ply["vertex"]
    names = [p.name for p in v.properties]
    assert names == ["x", "y", "z", "red", "green", "blue", "nx", "ny", "nz", "size", "confidence", "view"]
    assert "units mm" in ply.comments
    assert np.array_equal(np.stack([v["x"], v["y"], v["z"]], 1), arrays["xyz"])
    assert np.array_equal(v["view"], arrays["view"]) and np.array_equal(v["confidence"], arrays["confidence"])
    assert np.array_equal(np.stack([v["nx"], v["ny"], v["nz"]], 1), arrays["normal"])


@pytest.mark.parametrize("fmt", ["laz", "copc", "e57", "ply"])
def test_bad_clouds_leave_nothing(fmt: str, tmp_path: Path) -> None:
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    with pytest.raises(InputError, match="missing.ply"):
        export_cloud(tmp_path / "missing.ply", out_dir / f"x.{fmt}", fmt)
    nan = tmp_path / "nan.ply"
    a = surface_points(40, 30)
    a["xyz"][3, 1] = np.nan
    write_cloud(nan, a, ("xyz", "rgb"))
    if fmt != "ply":  # a PLY copy passes NaN through, as the source holds it
        with pytest.raises(InputError, match="NaN"):
            export_cloud(nan, out_dir / f"x.{fmt}", fmt)
    assert list(out_dir.iterdir()) == []


def test_unknown_format_is_input_error(full: Path, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="format"):
        export_cloud(full, tmp_path / "x.xyz", "xyz")


def test_copc_empty_parent_keeps_its_children_reachable(tmp_path: Path) -> None:
    from shared.formats.las import CopcNode, LasLayout, write_copc_nodes

    rng = np.random.default_rng(0)
    nodes = [CopcNode((0, 0, 0, 0), np.empty((0, 3), np.int32), None, {})]
    for x, y, z in ((0, 0, 0), (1, 0, 0), (1, 1, 1)):
        q = rng.integers(0, 500, (100, 3)).astype(np.int32) + np.array([x, y, z], np.int32) * 500
        nodes.append(CopcNode((1, x, y, z), q, None, {}))
    out = tmp_path / "e.copc.laz"
    write_copc_nodes(out, nodes, layout=LasLayout(6, ()), scale=0.01, offset=np.zeros(3), cube_min=np.zeros(3),
                     cube_size=10.0, spacing=10 / 128, points=300)  # fmt: skip
    with laspy.CopcReader.open(out) as r:
        assert len(r.query()) == 300 and len(r.query(level=0)) == 0 and len(r.query(level=1)) == 300
        assert len(r.spatial_query(Bounds(np.zeros(3), np.full(3, 5.0)))) == 100
    with pytest.raises(RuntimeError, match="300"):
        write_copc_nodes(tmp_path / "bad.copc.laz", nodes, layout=LasLayout(6, ()), scale=0.01, offset=np.zeros(3),
                         cube_min=np.zeros(3), cube_size=10.0, spacing=1.0, points=301)  # fmt: skip
    assert not (tmp_path / "bad.copc.laz").exists()
