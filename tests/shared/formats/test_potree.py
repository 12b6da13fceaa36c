"""The Potree 2.0 reader against foreign or damaged folders: every field of ``metadata.json`` it
uses is checked by name, and a hierarchy whose nodes point outside ``octree.bin`` or whose
proxies point back at a chunk already read is refused when the folder is opened, not later as
a bare exception (or, for a proxy cycle, never: the walk expanded forever)."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from shared.compress import tilenode
from shared.core.errors import InputError
from shared.formats.ply import write_ply
from shared.formats.potree import HIERARCHY_DTYPE, open_tiles
from shared.render.octree import build_tiles
from tests.support.hostile import bare_failures


@pytest.fixture(scope="module")
def tiles(tmp_path_factory: pytest.TempPathFactory) -> Path:
    work = tmp_path_factory.mktemp("potree")
    rng = np.random.default_rng(0)
    n = 20_000
    xyz = rng.normal(0.0, 50.0, (n, 3)).astype(np.float32)
    ply = write_ply(work / "c.ply", xyz, rgb=rng.integers(0, 256, (n, 3), np.uint8))
    build_tiles(ply, work / "tiles", workers=1, max_leaf=1_000)
    return work / "tiles"


def _edited(tiles: Path, tmp_path: Path, meta: Callable[[dict], object] | None = None,
            hierarchy: Callable[[np.ndarray], None] | None = None) -> Path:
    out = tmp_path / "edited"
    shutil.copytree(tiles, out)
    if meta is not None:
        doc = json.loads((out / "metadata.json").read_text())
        doc = meta(doc) or doc
        (out / "metadata.json").write_text(json.dumps(doc))
    if hierarchy is not None:
        recs = np.fromfile(out / "hierarchy.bin", HIERARCHY_DTYPE)
        hierarchy(recs)
        recs.tofile(out / "hierarchy.bin")
    return out


def test_the_folder_as_written_reads_every_point(tiles: Path) -> None:
    t = open_tiles(tiles, decoders=tilenode.DECODERS)
    assert sum(len(t.read_node(name).xyz) for name in t.nodes) == 20_000


def _set(path: str, value: object) -> Callable[[dict], None]:
    def edit(doc: dict) -> None:
        keys = path.split(".")
        cur = doc
        for k in keys[:-1]:
            cur = cur[int(k)] if isinstance(cur, list) else cur[k]
        cur[keys[-1] if isinstance(cur, dict) else int(keys[-1])] = value
    return edit


@pytest.mark.parametrize(("edit", "message"), [
    (lambda d: [1, 2], "not a JSON object"),
    (_set("boundingBox.min", 5), '"boundingBox.min" must be a list of 3 finite numbers'),
    (_set("offset", [0, 0, 0, 0, 0]), '"offset" must be a list of 3 finite numbers'),
    (_set("scale", [0.001, 0, 0.001]), '"scale" must hold numbers in (0, 1000]'),
    (_set("hierarchy.firstChunkSize", 1.5), '"hierarchy.firstChunkSize" must be a byte count'),
    (_set("spacing", "wide"), '"spacing" must be a positive number'),
    (_set("attributes.0.name", "where"), '"attributes" must hold a position of 3 integers'),
    (_set("attributes.1.name", "position"), '"attributes[1].name" \'position\' is declared twice'),
    (_set("attributes.0.numElements", 10**6), '"attributes[0].numElements" must be an integer in 1..16'),
    (_set("attributes.0.type", "int128"), '"attributes[0].type" must be one of'),
])
def test_malformed_metadata_is_refused_by_field(tiles: Path, tmp_path: Path, edit, message: str) -> None:
    out = _edited(tiles, tmp_path, meta=edit)
    with pytest.raises(InputError) as err:
        open_tiles(out, decoders=tilenode.DECODERS)
    assert str(err.value).startswith(f"{out / 'metadata.json'}: ") and message in str(err.value), str(err.value)


def _last_node(recs: np.ndarray) -> int:
    return int(np.flatnonzero(recs["type"] != 2)[-1])


@pytest.mark.timeout(60)
@pytest.mark.parametrize(("edit", "message"), [
    # a node before octree.bin's start (seek raised a bare OSError) or past its end (a read of
    # its terabyte size raised MemoryError)
    (lambda r: r.__setitem__(_last_node(r), (1, 0, 10, -1, 10)), "its bytes -1+10 lie outside octree.bin"),
    (lambda r: r.__setitem__(_last_node(r), (1, 0, 10, 0, 1 << 40)), "lie outside octree.bin"),
    (lambda r: r["type"].__setitem__(0, 7), "node r: unknown node type 7"),
    # a proxy pointing back at the first chunk: the walk read it again and again, for ever
    (lambda r: r.__setitem__(_last_node(r), (2, 0, 0, 0, len(r) * HIERARCHY_DTYPE.itemsize)), "read twice"),
])
def test_a_hierarchy_pointing_outside_its_files_or_back_is_refused(tiles: Path, tmp_path: Path, edit,
                                                                    message: str) -> None:
    out = _edited(tiles, tmp_path, hierarchy=edit)
    with pytest.raises(InputError) as err:
        open_tiles(out, decoders=tilenode.DECODERS)
    assert str(err.value).startswith(f"{out / 'hierarchy.bin'}: ") and message in str(err.value), str(err.value)


def test_every_metadata_field_refused_by_name_not_a_bare_exception(tiles: Path, tmp_path: Path) -> None:
    """Every field of metadata.json replaced by what a careless or hostile writer sends
    (tests.support.hostile), and the folder opened and its nodes read: over a hundred bare exceptions before."""
    doc = json.loads((tiles / "metadata.json").read_text())
    out = _edited(tiles, tmp_path)

    def read(meta: object) -> None:
        (out / "metadata.json").write_text(json.dumps(meta))
        t = open_tiles(out, decoders=tilenode.DECODERS)
        for name in list(t.nodes)[:8]:
            t.read_node(name)

    assert not bare_failures(doc, read, InputError)
