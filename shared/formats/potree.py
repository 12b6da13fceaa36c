"""Reader of Potree 2.0 tiles (our :mod:`shared.render.octree` output, or PotreeConverter 2's "DEFAULT").

In: a folder with ``metadata.json``, ``hierarchy.bin`` and ``octree.bin``. Out:
:class:`PotreeTiles` — metadata, every node of the hierarchy (proxies resolved, the same walk
as Potree's ``OctreeLoader.js``) with its cubic bounding box, and per-node points decoded to
world coordinates (units of the source cloud) with colour, normal and world ``size``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shared.core.errors import InputError
from shared.core.jsonsafe import finite_number, json_integer, read_json_bounded

_TYPES = {
    "int8": "i1", "uint8": "u1", "int16": "<i2", "uint16": "<u2", "int32": "<i4", "uint32": "<u4",
    "int64": "<i8", "uint64": "<u8", "float": "<f4", "double": "<f8",
}  # fmt: skip
#: One node record of ``hierarchy.bin`` (22 bytes): type (0 normal, 1 leaf, 2 proxy for the
#: next hierarchy chunk), child mask, point count, byte offset and byte size (into
#: ``octree.bin``, or into ``hierarchy.bin`` for a proxy). The writer in
#: :mod:`shared.render.octree` and this reader share it.
HIERARCHY_DTYPE = np.dtype([("type", "u1"), ("mask", "u1"), ("points", "<u4"), ("offset", "<i8"), ("size", "<i8")])
#: Levels per hierarchy chunk (PotreeConverter's ``stepSize``).
HIERARCHY_STEP = 4


@dataclass
class PotreeNode:
    """One octree node. ``box_min``/``box_max`` are world coordinates of its cube."""

    name: str
    level: int
    num_points: int
    byte_offset: int
    byte_size: int
    child_mask: int
    node_type: int  # 0 inner, 1 leaf (after proxies are resolved)
    box_min: np.ndarray
    box_max: np.ndarray
    spacing: float


@dataclass
class NodePoints:
    """Decoded points of a node: ``xyz`` (N, 3) float64 world; ``rgb`` (N, 3) uint8;
    ``normal`` (N, 3) float32 or None; ``size`` (N,) float32 world sample size or None."""

    xyz: np.ndarray
    rgb: np.ndarray
    normal: np.ndarray | None
    size: np.ndarray | None

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


@dataclass
class PotreeTiles:
    """An opened tiles folder; ``nodes`` maps name -> node in breadth-first order."""

    root: Path
    metadata: dict
    nodes: dict[str, PotreeNode]
    point_dtype: np.dtype
    offset: np.ndarray
    scale: np.ndarray
    #: Decodes a node's bytes (bytes, record dtype, count, where) when the nodes are not
    #: Potree's plain records (the encoding's decoder given to :func:`open_tiles`).
    decoder: Callable[..., np.ndarray] | None = None

    @property
    def encoding(self) -> str:
        return str(self.metadata.get("encoding", "DEFAULT"))

    @property
    def points(self) -> int:
        return int(self.metadata["points"])

    @property
    def box_min(self) -> np.ndarray:
        return np.asarray(self.metadata["boundingBox"]["min"], np.float64)

    @property
    def box_max(self) -> np.ndarray:
        return np.asarray(self.metadata["boundingBox"]["max"], np.float64)

    def records(self, name: str) -> np.ndarray:
        """Raw records of node ``name`` as a structured array of :attr:`point_dtype`."""
        node = self.nodes[name]
        if node.byte_size == 0:
            return np.empty(0, self.point_dtype)
        with open(self.root / "octree.bin", "rb") as f:
            f.seek(node.byte_offset)
            buf = f.read(node.byte_size)
        if self.decoder is not None:
            if len(buf) != node.byte_size:
                raise InputError(self.root / "octree.bin", f"node {name} lies outside the file")
            return self.decoder(buf, self.point_dtype, node.num_points, where=f"{self.root / 'octree.bin'} node {name}")
        if len(buf) != node.byte_size or node.byte_size != node.num_points * self.point_dtype.itemsize:
            raise InputError(self.root / "octree.bin", f"node {name} bytes do not match its record")
        return np.frombuffer(buf, self.point_dtype)

    def read_node(self, name: str) -> NodePoints:
        """Decoded points of node ``name``."""
        rec = self.records(name)
        names = rec.dtype.names or ()
        xyz = rec["position"].astype(np.float64) * self.scale + self.offset
        if "rgb" in names:
            c = rec["rgb"].astype(np.uint32)
            # Potree's decoder: values above 255 are 16-bit colour.
            rgb = np.where(c > 255, c // 256, c).astype(np.uint8)
        else:
            rgb = np.full((len(rec), 3), 255, np.uint8)
        if "normal" in names:
            normal = rec["normal"].astype(np.float32)
        elif {"NormalX", "NormalY", "NormalZ"} <= set(names):
            normal = np.stack([rec["NormalX"], rec["NormalY"], rec["NormalZ"]], axis=1).astype(np.float32)
        else:
            normal = None
        size = rec["size"].astype(np.float32) if "size" in names else None
        return NodePoints(xyz=xyz, rgb=rgb, normal=normal, size=size)


def _child_box(lo: np.ndarray, hi: np.ndarray, index: int) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = lo.copy(), hi.copy()
    half = (hi - lo) / 2
    for axis, bit in ((0, 4), (1, 2), (2, 1)):
        if index & bit:
            lo[axis] += half[axis]
        else:
            hi[axis] -= half[axis]
    return lo, hi


#: Deepest level a hierarchy may reach (a node's name is "r" and a digit a level; Potree's own
#: trees stay under 20): a proxy pointing back at an earlier chunk would otherwise expand forever.
MAX_LEVELS = 32
#: Largest magnitude of an offset or bounding-box coordinate, and of a scale, in the cloud's units.
MAX_COORDINATE = 1e12
MAX_SCALE = 1e3
#: Most elements of one attribute (Potree's are 1 to 4).
MAX_ELEMENTS = 16


def _bad(meta_path: Path, field: str, problem: str) -> InputError:
    return InputError(meta_path, f'malformed Potree metadata: "{field}" {problem}')


def _vec3(meta_path: Path, value: Any, field: str) -> np.ndarray:
    if not (isinstance(value, list) and len(value) == 3 and all(finite_number(v) for v in value)):
        raise _bad(meta_path, field, "must be a list of 3 finite numbers")
    v = np.asarray(value, np.float64)
    if np.abs(v).max() > MAX_COORDINATE:
        raise _bad(meta_path, field, f"must hold numbers of magnitude at most {MAX_COORDINATE:g}")
    return v


def _metadata(meta_path: Path, decoders: Mapping[str, Any]) -> tuple[dict, np.dtype, np.ndarray, np.ndarray,
                                                                      np.ndarray, np.ndarray, int, float]:
    """``metadata.json`` read with bounds and every field the reader uses checked: (document,
    record dtype, offset, scale, box min, box max, first hierarchy chunk's size, spacing)."""
    meta = read_json_bounded(meta_path, str(meta_path), missing="not a tiles folder (no metadata.json)")
    if not isinstance(meta, dict):
        raise InputError(meta_path, "malformed Potree metadata: not a JSON object")
    if meta.get("version") != "2.0":
        raise InputError(meta_path, f"unsupported Potree version {str(meta.get('version'))[:40]!r}")
    encoding = meta.get("encoding", "DEFAULT")
    if encoding != "DEFAULT" and (not isinstance(encoding, str) or encoding not in decoders):
        raise InputError(meta_path, f"unsupported encoding {str(encoding)[:40]!r}")
    attributes = meta.get("attributes")
    if not isinstance(attributes, list) or not attributes:
        raise _bad(meta_path, "attributes", "must be a non-empty list")
    fields: list[tuple] = []
    for i, a in enumerate(attributes):
        name = a.get("name") if isinstance(a, dict) else None
        kind = a.get("type") if isinstance(a, dict) else None
        n = a.get("numElements", 1) if isinstance(a, dict) else None
        if not isinstance(name, str) or not name or len(name) > 64:
            raise _bad(meta_path, f"attributes[{i}].name", "must be a short non-empty name")
        if not isinstance(kind, str) or kind not in _TYPES:
            raise _bad(meta_path, f"attributes[{i}].type", f"must be one of {', '.join(_TYPES)}")
        if not json_integer(n) or not 1 <= n <= MAX_ELEMENTS:
            raise _bad(meta_path, f"attributes[{i}].numElements", f"must be an integer in 1..{MAX_ELEMENTS}")
        if any(f[0] == name for f in fields):
            raise _bad(meta_path, f"attributes[{i}].name", f"{name[:40]!r} is declared twice")
        fields.append((name, _TYPES[kind], (n,)) if n > 1 else (name, _TYPES[kind]))
    dtype = np.dtype(fields)
    if "position" not in dtype.names or dtype["position"].shape != (3,) or dtype["position"].base.kind not in "iu":
        raise _bad(meta_path, "attributes", "must hold a position of 3 integers")
    offset = _vec3(meta_path, meta.get("offset"), "offset")
    scale = _vec3(meta_path, meta.get("scale"), "scale")
    if not ((scale > 0) & (scale <= MAX_SCALE)).all():
        raise _bad(meta_path, "scale", f"must hold numbers in (0, {MAX_SCALE:g}]")
    box = meta.get("boundingBox")
    if not isinstance(box, dict):
        raise _bad(meta_path, "boundingBox", "must be an object with min and max")
    bmin = _vec3(meta_path, box.get("min"), "boundingBox.min")
    bmax = _vec3(meta_path, box.get("max"), "boundingBox.max")
    if not (bmax >= bmin).all():
        raise _bad(meta_path, "boundingBox", "max lies below min")
    hierarchy = meta.get("hierarchy")
    first = hierarchy.get("firstChunkSize") if isinstance(hierarchy, dict) else None
    if not json_integer(first) or first < 0:
        raise _bad(meta_path, "hierarchy.firstChunkSize", "must be a byte count")
    spacing = meta.get("spacing")
    if not finite_number(spacing) or not 0 < spacing <= MAX_COORDINATE:
        raise _bad(meta_path, "spacing", "must be a positive number")
    return meta, dtype, offset, scale, bmin, bmax, first, float(spacing)


def open_tiles(root: Path, decoders: Mapping[str, Callable[..., np.ndarray]] | None = None) -> PotreeTiles:
    """Open a Potree 2.0 folder; raises :class:`InputError` naming the file that is wrong.

    ``decoders`` maps other node encodings than "DEFAULT" to their decoders, called as
    ``decoder(bytes, record dtype, count, where=...)`` -> records (Graylight's octree-coded nodes:
    :data:`shared.compress.tilenode.DECODERS`); tiles in another encoding are refused. Every
    node's bytes lie inside ``octree.bin`` and every proxy's inside ``hierarchy.bin``, each
    hierarchy chunk read once and no deeper than :data:`MAX_LEVELS` (a foreign or damaged
    folder fails here, by name, not later in a read).
    """
    root = Path(root)
    decoders = dict(decoders or {})
    meta_path = root / "metadata.json"
    if not meta_path.is_file():
        raise InputError(root, "not a tiles folder (no metadata.json)")
    meta, dtype, offset, scale, bmin, bmax, first, spacing = _metadata(meta_path, decoders)
    hpath, opath = root / "hierarchy.bin", root / "octree.bin"
    if not hpath.is_file() or not opath.is_file():
        raise InputError(root, "tiles folder lacks hierarchy.bin or octree.bin")
    hier = np.fromfile(hpath, dtype=np.uint8)
    octree_bytes = opath.stat().st_size

    nodes: dict[str, PotreeNode] = {}
    root_node = PotreeNode("r", 0, 0, 0, 0, 0, 2, bmin, bmax, spacing)
    pending = [(root_node, 0, first)]  # proxies to expand: (node, hierarchy offset, size)
    seen: set[int] = set()  # hierarchy chunks read (by offset): a proxy may not point back
    while pending:
        start, h_off, h_size = pending.pop()
        if (h_size % HIERARCHY_DTYPE.itemsize or h_off < 0 or h_size < 0 or h_off + h_size > hier.size
                or h_off in seen):
            raise InputError(hpath, f"hierarchy chunk at {h_off}+{h_size} is out of range or read twice")
        seen.add(h_off)
        recs = np.frombuffer(hier[h_off : h_off + h_size].tobytes(), HIERARCHY_DTYPE)
        queue = [start]
        for i, r in enumerate(recs):
            if i >= len(queue):
                raise InputError(hpath, "hierarchy chunk has more records than its nodes announce")
            cur = queue[i]
            kind, off, size = int(r["type"]), int(r["offset"]), int(r["size"])
            if kind not in (0, 1, 2):
                raise InputError(hpath, f"node {cur.name}: unknown node type {kind}")
            cur.num_points = int(r["points"])
            cur.child_mask = int(r["mask"])
            if kind == 2 and cur is not start:
                cur.node_type = 2
                pending.append((cur, off, size))
                continue
            if off < 0 or size < 0 or off + size > octree_bytes:
                raise InputError(hpath, f"node {cur.name}: its bytes {off}+{size} lie outside octree.bin")
            cur.node_type = kind
            cur.byte_offset = off
            cur.byte_size = size
            nodes[cur.name] = cur
            if cur.child_mask and cur.level + 1 > MAX_LEVELS:
                raise InputError(hpath, f"node {cur.name[:40]}...: the hierarchy is deeper than {MAX_LEVELS} levels")
            for k in range(8):
                if cur.child_mask & (1 << k):
                    lo, hi = _child_box(cur.box_min, cur.box_max, k)
                    queue.append(
                        PotreeNode(cur.name + str(k), cur.level + 1, 0, 0, 0, 0, 0, lo, hi, cur.spacing / 2)
                    )
    ordered = dict(sorted(nodes.items(), key=lambda kv: (len(kv[0]), kv[0])))
    return PotreeTiles(root=root, metadata=meta, nodes=ordered, point_dtype=dtype, offset=offset, scale=scale,
                       decoder=decoders.get(meta.get("encoding", "DEFAULT")))  # fmt: skip


def tight_bounds(tiles: PotreeTiles) -> tuple[np.ndarray, np.ndarray]:
    """The points' own bounds (the position attribute's min/max), else the cubic box."""
    for a in tiles.metadata.get("attributes", []):
        if a.get("name") == "position" and len(a.get("min", [])) == 3 and len(a.get("max", [])) == 3:
            return np.asarray(a["min"], np.float64), np.asarray(a["max"], np.float64)
    return tiles.box_min, tiles.box_max
