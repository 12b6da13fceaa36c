"""Compile and cache every numba kernel of the pipeline ahead of use, and load them early.

numba compiles a kernel on its first call for each new signature (argument types) and keeps
the machine code in its cache (``__pycache__`` beside the module, or ``NUMBA_CACHE_DIR``);
without that cache a fresh clone's first scan or tile build spends tens of seconds
compiling. :func:`warm` runs the real stage functions on tiny inputs — a small simulated
capture of each image kind (8-bit grey, 16-bit colour, without inverses, without rows), its
scan, the one-pass and the streaming decoder, tiles of clouds with and without attributes,
preview frames with and without eye-dome lighting — so that every signature those stages
use is compiled once, at ``make setup`` (``python -m workers.warmup``) or while a Docker
image is built. A kernel's signature depends only on argument types (dtype, dimensions,
layout, tuple length), never on image or cloud sizes, which is why tiny inputs suffice.

:func:`load_cached_kernels` only loads what the cache holds, without running or compiling
anything: a job-service worker calls it when its process starts, so that no job pays for
loading machine code (a cache miss there is logged, not compiled, to keep start-up short).

It lives in ``workers/`` because it sits above every science package (it runs scan, render,
sim, merge and compress) and the worker app calls it; nothing in ``shared/`` imports it.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import hashlib
import importlib
import json
import logging
import re
import tempfile
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

from shared.core.files import write_json_atomic

log = logging.getLogger(__name__)

_SHARED = Path(__file__).resolve().parents[1] / "shared"
#: A numba kernel's decorator (numba's, or :mod:`shared.core.jit`'s ``kernel`` and ``helper``),
#: but for inline="always" functions (compiled into their callers).
_CACHED_KERNEL = re.compile(r'^@(?:(?:numba\.)?njit|kernel|helper)\b(?![^\n]*inline="always")', re.MULTILINE)

#: Modules holding numba kernels, by domain.
KERNEL_MODULES: dict[str, tuple[str, ...]] = {
    "sim": ("shared.sim.raycast",),
    "scan": ("shared.scan._decode_kernels", "shared.scan.decode", "shared.scan.triangulate", "shared.formats._png"),  # _png: frame reading
    "render": ("shared.render._octree_kernels", "shared.render.octree", "shared.render.raster", "shared.render._shading", "shared.render._neighbours",
               "shared.render._match", "shared.compress.tilenode"),  # tilenode: the tiles' octree-coded nodes
    "compress": ("shared.compress._rans", "shared.compress._tables", "shared.compress._check", "shared.compress._mask", "shared.compress._wp",
                 "shared.compress._rows", "shared.compress._ls",
                 "shared.compress._lpred", "shared.compress._levels", "shared.compress._interp", "shared.compress._quadtree",
                 "shared.compress._octree_ctx", "shared.compress._octree"),
    "merge": ("shared.merge._kernels", "shared.merge._fusion_kernels"),
    "derive": ("shared.derive._raster",),  # the texture baker's UV rasteriser
}
DOMAINS = tuple(KERNEL_MODULES)


def kernel_dispatchers(domains: Sequence[str] = DOMAINS) -> list[tuple[str, Any]]:
    """``(module.name, dispatcher)`` of every cached numba kernel (``cache=True``) defined in
    the modules of ``domains``."""
    # numba loads on demand: importing it costs half a second, which the callers pay anyway.
    from numba.core.caching import FunctionCache
    from numba.core.registry import CPUDispatcher

    out = []
    for dom in domains:
        for name in KERNEL_MODULES[dom]:
            mod: ModuleType = importlib.import_module(name)
            for attr, obj in sorted(vars(mod).items()):
                # inline="always" helpers are compiled into their callers, never on their own.
                if (isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == name
                        and obj.targetoptions.get("inline") != "always"
                        and isinstance(getattr(obj, "_cache", None), FunctionCache)):  # fmt: skip
                    out.append((f"{name}.{attr}", obj))
    return out


def uncovered_kernel_modules() -> list[str]:
    """Modules under ``shared/`` that define numba kernels but are not in :data:`KERNEL_MODULES`
    (read from the source text, nothing imported): their kernels compile on first use until a
    warm-up runs their stage."""
    listed = {m for mods in KERNEL_MODULES.values() for m in mods}
    found = []
    for path in sorted(_SHARED.rglob("*.py")):
        name = ".".join(("shared", *path.relative_to(_SHARED).with_suffix("").parts))
        if name not in listed and _CACHED_KERNEL.search(path.read_text(encoding="utf-8")):
            found.append(name)
    return found


def _module_file(name: str) -> Path | None:
    """Source file of the ``shared`` module ``name`` (a package's ``__init__.py``), or None
    when ``name`` is not a module (an attribute imported from one)."""
    parts = name.split(".")[1:]
    if not parts:
        return _SHARED / "__init__.py"
    for path in (_SHARED.joinpath(*parts).with_suffix(".py"), _SHARED.joinpath(*parts, "__init__.py")):
        if path.is_file():
            return path
    return None


def _shared_imports(name: str) -> set[str]:
    """``shared`` modules that module ``name`` imports by name (anywhere in its source)."""
    path = _module_file(name)
    out: set[str] = set()
    if path is None:
        return out
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            # "from pkg import mod" depends on mod; "from mod import name" on mod.
            subs = [f"{node.module}.{a.name}" for a in node.names]
            names = [n for n in subs if _module_file(n) is not None]
            if len(names) < len(subs):
                names.append(node.module)
        else:
            continue
        out.update(n for n in names if (n == "shared" or n.startswith("shared.")) and _module_file(n) is not None)
    return out


def kernel_dependencies(name: str) -> dict[str, str]:
    """SHA-256 of the source of every ``shared`` module that kernel module ``name`` imports,
    directly or through others (``name`` itself left out).

    numba's cache checks only the timestamp of the kernel's own file: a kernel that calls a
    numba function of another module, or reads one of its constants (frozen into the machine
    code), keeps loading the old machine code after that module changes. These digests let
    :func:`flush_stale_kernels` notice it."""
    seen: set[str] = set()
    todo = [name]
    while todo:
        for dep in _shared_imports(todo.pop()):
            if dep not in seen and dep != name:
                seen.add(dep)
                todo.append(dep)
    digests = {}
    for dep in sorted(seen):
        path = _module_file(dep)
        assert path is not None  # _shared_imports keeps modules only
        digests[dep] = hashlib.sha256(path.read_bytes()).hexdigest()
    return digests


def _manifest(name: str, dispatchers: list[Any]) -> Path:
    """Where the digests of ``name``'s dependencies at its last warm-up are kept: beside its
    kernels in numba's cache (``__pycache__`` or ``NUMBA_CACHE_DIR``), so the two go together."""
    return Path(dispatchers[0]._cache._cache_path) / f"{name}.graylight-deps.json"


def _module_kernels(domains: Sequence[str]) -> dict[str, list[Any]]:
    by_module: dict[str, list[Any]] = {}
    for qual, d in kernel_dispatchers(domains):
        by_module.setdefault(qual.rsplit(".", 1)[0], []).append(d)
    return by_module


def stale_kernel_modules(domains: Sequence[str] = DOMAINS) -> list[str]:
    """Kernel modules whose cached machine code numba would load although the ``shared``
    modules they import changed since their last warm-up (or were never recorded), or although
    a kernel module they import has kernels missing from the cache (its file touched, its
    content the same: a checkout, an edit undone): their cached code would load with the
    callees' inside it, those callees would never compile, and the warm-up's check would fail."""
    modules = _module_kernels(domains)
    # per module, whether each kernel has machine code in the cache (each index read once)
    cached = {name: [bool(cached_signatures(d)) for d in ds] for name, ds in modules.items()}
    stale = []
    for name, dispatchers in modules.items():
        try:
            recorded = json.loads(_manifest(name, dispatchers).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            recorded = None
        deps = kernel_dependencies(name)
        lost = [dep for dep in deps if dep in cached and not all(cached[dep])]
        if any(cached[name]) and (recorded != deps or lost):
            stale.append(name)
    return stale


def flush_stale_kernels(domains: Sequence[str] = DOMAINS) -> list[str]:
    """Empty numba's cache index of every kernel of :func:`stale_kernel_modules`, so that the
    warm-up compiles them again. Returns the modules flushed."""
    stale = stale_kernel_modules(domains)
    by_module = _module_kernels(domains)
    for name in stale:
        for d in by_module[name]:
            d._cache.flush()
    return stale


def record_kernel_dependencies(domains: Sequence[str] = DOMAINS) -> None:
    """Record, after a warm-up, the dependency digests :func:`flush_stale_kernels` compares."""
    for name, dispatchers in _module_kernels(domains).items():
        write_json_atomic(_manifest(name, dispatchers), kernel_dependencies(name))


def cached_signatures(dispatcher: Any) -> list[tuple]:
    """Signatures whose machine code numba's cache holds for ``dispatcher``, for this source
    file (its timestamp and bytecode) and this CPU: what a call would load instead of compile.

    Reads the cache index through numba's cache object (``_cache``, an implementation detail
    of numba 0.59-0.63, the versions pyproject allows)."""
    cache = dispatcher._cache
    codegen = dispatcher.targetctx.codegen()
    index = cache._cache_file._load_index()  # {} when missing or stale (source changed)
    return [key[0] for key in index if key == cache._index_key(key[0], codegen)]


def load_cached_kernels(domains: Sequence[str] = ("scan", "render")) -> dict[str, int]:
    """Load every cached signature of the kernels of ``domains`` into this process, without
    running a kernel (no thread pool starts) and without compiling: kernels missing from
    the cache are counted and logged. Returns ``{"loaded": n, "missing": m}`` (signatures,
    kernels)."""
    loaded = missing = 0
    for name, d in kernel_dispatchers(domains):
        sigs = cached_signatures(d)
        if not sigs:
            missing += 1
            log.warning("numba kernel %s is not in the cache: it will compile on first use (run make setup)", name)
        for sig in sigs:
            d.compile(sig)  # a cache hit: loads the machine code
            loaded += 1
    return {"loaded": loaded, "missing": missing}


def load_kernels_in_background(domains: Sequence[str] = ("scan", "render")) -> threading.Thread:
    """:func:`load_cached_kernels` in a daemon thread, for a worker process that is starting:
    its start-up is not held up (Celery gives a new pool process a few seconds to report),
    and a job that arrives meanwhile waits only for the kernel it calls (numba's compiler
    lock serialises loading). Nothing runs a kernel, so no thread pool starts."""
    thread = threading.Thread(target=load_cached_kernels, args=(tuple(domains),), name="numba-kernels", daemon=True)
    thread.start()
    return thread


@contextlib.contextmanager
def _attribute(obj: Any, name: str, value: Any) -> Iterator[None]:
    before = getattr(obj, name)
    setattr(obj, name, value)
    try:
        yield
    finally:
        setattr(obj, name, before)


# --------------------------------------------------------------------------- the workload

#: Camera and projector sizes of the warm-up captures: large enough for every code path
#: (several row bands, stripe edges), small enough to render and decode in a blink.
_CAMERA = (96, 72)
_PROJECTOR = (64, 48)


def _captures(work: Path) -> list[Path]:
    """Tiny simulated captures of every image kind the scanner reads, with rig and truth."""
    from shared.sim.scenes import mesh_path
    from shared.sim.simulate import ImagingParams, simulate_named

    kinds = [
        ("corner", {}),  # 8-bit grey, inverses, rows; planes with inter-reflection, a sphere
        ("spheres", {"bits": 16, "colour": True}),
        ("spheres", {"inverses": False}),
        ("spheres", {"bits": 16, "inverses": False, "rows": False}),
    ]
    if mesh_path("stanford-bunny").is_file():  # the demo's scene, when the shared meshes exist
        kinds.append(("bunny", {}))
    else:
        _warm_mesh_raster()
    out = []
    for i, (scene, kw) in enumerate(kinds):
        folder = work / f"capture_{i}"
        simulate_named(scene, folder, size=_CAMERA, projector=_PROJECTOR, seed=i, imaging=ImagingParams(**kw))
        out.append(folder)
    return out


def _warm_mesh_raster() -> None:
    """The mesh scenes' ray caster on one triangle, for a machine without the shared meshes
    (the bunny capture calls it otherwise): with the same argument types, so the signature
    cached is the one a mesh scene later uses, and ``make setup`` still finds every sim
    kernel compiled."""
    import numpy as np

    from shared.sim.raycast import raster_mesh, undistort_grid

    w, h = _CAMERA
    K = np.array([[100.0, 0.0, w / 2], [0.0, 100.0, h / 2], [0.0, 0.0, 1.0]])
    dist = np.zeros(5)
    rx, ry = undistort_grid(K, dist, w, h)
    zbuf = np.full((h, w), np.inf)
    tid = np.full((h, w), -1, np.int32)
    raster_mesh(np.array([[-50.0, -50.0, 500.0], [50.0, -50.0, 500.0], [0.0, 50.0, 500.0]]),
                np.array([[0, 1, 2]], np.int32), rx, ry, K, dist, zbuf, tid)  # fmt: skip


def _warm_scan(work: Path, captures: list[Path]) -> list[Path]:
    """Scan every capture (one-pass decoder, triangulation, outputs), decode them again
    through the streaming decoder, and decode in-memory stacks; returns the clouds."""
    from shared.formats.capture import load_capture
    from shared.formats.images import read_grey
    from shared.scan import decode
    from shared.scan.pipeline import scan

    clouds = []
    for k, cap in enumerate(captures):
        report = scan(cap, work / f"scan_{k}")
        clouds.append(Path(report["files"]["cloud"]))
        # The streaming path decodes axes larger than the one-pass budget (16-bit 15 MP).
        with _attribute(decode, "_ONE_PASS_BYTES", 0), _attribute(decode, "_BATCH_BYTES", 1):
            decode.decode_capture(load_capture(cap))
        c = load_capture(cap)
        white, black = read_grey(c.white), read_grey(c.black)
        cols = [(e.bit, read_grey(e.pattern), read_grey(e.inverse) if e.inverse else None) for e in c.columns]
        rows = [(e.bit, read_grey(e.pattern), read_grey(e.inverse) if e.inverse else None) for e in c.rows]
        decode.decode_stack(white, black, cols, rows, (c.projector_width, c.projector_height))
    return clouds


def _warm_render(work: Path, clouds: list[Path]) -> None:
    """Tiles of the scanned clouds (several chunks, deep nodes) and of an xyz-only cloud, in
    this process, with a pool of two threads and as the job service's per-chunk tasks; preview
    frames of the tiles; octree-coded tiles of both kinds of cloud, read back."""
    import numpy as np

    from shared.formats.ply import read_ply, write_ply
    from shared.formats.potree import open_tiles
    from shared.render.camera_path import make_path
    from shared.render.octree import build_chunk, build_tiles, merge_tiles, plan_tiles, quantise
    from shared.render.preview import frame_camera, frame_selection, load_scene, render_frames
    from shared.render.raster import Rasterizer

    # A cloud of positions only (other tools' PLYs): the tile passes carry no attributes then.
    xyz = np.ascontiguousarray(read_ply(clouds[0]).xyz)
    bare = write_ply(work / "xyz_only.ply", xyz)
    quantise(xyz, xyz.min(axis=0).astype(np.float64), 0.001, 1 << 16)
    # The job service's fan-out: plan, one task a chunk, merge (with normals estimated too).
    fan = work / "fan_out"
    fan.mkdir()
    plan = plan_tiles(bare, fan, max_chunk=500, max_leaf=100, estimate_normals=True)
    for index in range(len(plan.chunks)):
        build_chunk(fan, index)
    merge_tiles(fan, work / "tiles_fan_out")
    for k, ply in enumerate([*clouds, bare]):
        tiles = work / f"tiles_{k}"
        build_tiles(ply, tiles, workers=1 if k else 2, max_chunk=500, max_leaf=100)
        scene = load_scene(open_tiles(tiles))
        poses = make_path("orbit", scene.bounds_min, scene.bounds_max, 4)
        for edl in (0.0, 1.0):
            for _ in render_frames(scene, poses, 64, 48, edl=edl):
                pass
        rz = Rasterizer(64, 48)
        cam = frame_camera(poses[0], scene, 64, 48)
        rz.render(cam, scene.xyz, scene.colour, scene.size, *frame_selection(scene, cam, 10_000))
        rz.render(cam, scene.xyz, scene.colour, scene.size, edl=1.0)
    # Octree-coded nodes (tiles --node-codec octree): coded and decoded, with and without attributes.
    from shared.compress import tilenode

    for k, ply in enumerate([clouds[0], bare]):
        tiles = work / f"tiles_octree_{k}"
        build_tiles(ply, tiles, workers=1, max_chunk=500, max_leaf=100, node_codec="octree")
        load_scene(open_tiles(tiles, decoders=tilenode.DECODERS))


def _merged_like(work: Path, cloud: Path) -> Path:
    """``cloud`` with the merged cloud's extra fields (``view`` uint16, ``confidence`` float32)."""
    import numpy as np

    from shared.formats.ply import iter_ply_records, write_ply_records

    rec = np.concatenate(list(iter_ply_records(cloud)))
    extra = np.dtype(rec.dtype.descr + [("view", "<u2"), ("confidence", "<f4")])
    merged = np.zeros(len(rec), extra)
    for name in rec.dtype.names or ():
        merged[name] = rec[name]
    merged["view"] = np.arange(len(rec)) % 3
    merged["confidence"] = np.linspace(0.0, 1.0, len(rec), dtype=np.float32)
    return write_ply_records(work / f"{cloud.stem}_merged_like.ply", iter([merged]), len(merged), extra)


def _warm_export(work: Path, clouds: list[Path]) -> None:
    """The cloud's COPC export (its attribute look-up kernel), of a scan's cloud and of a
    merged-like one."""
    from shared.render.export import export_cloud

    for k, ply in enumerate((clouds[0], _merged_like(work, clouds[0]))):
        export_cloud(ply, work / f"export_{k}.copc.laz", "copc", workers=1, max_leaf=100)


def _compress_inputs(work: Path) -> tuple[list[Path], Path]:
    """Scan-like inputs of the compress workload, made without scanning (so that it can run
    beside the scan in a process of its own): range images as a scan writes them (``z``
    float32 with NaN holes, ``K`` and ``dist`` float64, ``units``) of a tilted plane, a sphere
    and a step edge with sub-quantum noise (one with speckled holes) and a wide view of a plane, and a cloud with every field a scan writes (xyz,
    colour, normals, size, albedo). Returns (scan folders, cloud)."""
    import numpy as np

    from shared.compress.range import RangeImage, save_range_npz

    rng = np.random.default_rng(0)
    w, h = _CAMERA
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    K = np.array([[120.0, 0.0, w / 2], [0.0, 120.0, h / 2], [0.0, 0.0, 1.0]])
    folders = []
    for k in range(3):
        z = 480.0 + 0.3 * xx - 0.2 * yy + k * 5.0
        r2 = (xx - w * 0.4) ** 2 + (yy - h * 0.5) ** 2
        z = np.where(r2 < (h * 0.3) ** 2, z - np.sqrt(np.maximum((h * 0.45) ** 2 - r2, 0.0)), z)
        z = np.where(xx > w * 0.75, z + 40.0, z) + rng.normal(0.0, 0.01 * (k + 1), z.shape)
        z[: 3 + k, :] = np.nan  # holes: a border, a shadow and scattered drop-outs
        z[h // 2 : h // 2 + 6, w // 6 : w // 6 + 10] = np.nan
        z[rng.random(z.shape) < 0.02 * k] = np.nan
        if k == 2:  # speckle, as a real capture's failed decodes: its mask coded in context
            z[:, : w // 3][rng.random((h, w // 3)) < 0.3] = np.nan
        folder = work / f"range_input_{k}"
        folder.mkdir()
        save_range_npz(folder / "range.npz", RangeImage(z.astype(np.float32), K, np.zeros(5), "mm"))
        folders.append(folder)
    # a wide view whose only holes are a silhouette's: its mask coded as runs (a small view's
    # masks all code fewer bits in context, their runs' tables weighing)
    zw = 480.0 + 0.01 * np.arange(1024)[None, :] + rng.normal(0.0, 0.02, (h, 1024))
    zw[:, :40] = np.nan
    folder = work / "range_input_wide"
    folder.mkdir()
    save_range_npz(folder / "range.npz", RangeImage(zw.astype(np.float32), K, np.zeros(5), "mm"))
    folders.append(folder)
    n = 4000
    xyz = np.column_stack([rng.uniform(-40, 40, n), rng.uniform(-30, 30, n), 480 + rng.normal(0, 3, n)])
    return folders, _scan_like_cloud(work / "cloud_input.ply", xyz, rng)


def _scan_like_cloud(path: Path, xyz: Any, rng: Any) -> Path:
    """A PLY of the points ``xyz`` (n, 3) mm with every field a scan writes, in its types:
    colour, unit normals, size, albedo and its weight (values random)."""
    import numpy as np

    from shared.formats.ply import write_ply

    n = len(xyz)
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return write_ply(path, np.asarray(xyz, np.float32), rgb=rng.integers(0, 256, (n, 3), np.uint8),
                     normals=normals.astype(np.float32), size=rng.uniform(0.1, 0.5, n).astype(np.float32),
                     comments=("generated by graylight warm-up", "units mm", "frame camera"),
                     albedo=rng.integers(0, 256, (n, 3), np.uint8), albedo_weight=rng.integers(0, 256, n, np.uint8))


def _render_inputs(work: Path) -> list[Path]:
    """Scan-like clouds for the render workload, made without scanning (so that it can run
    beside the scan in a process of its own): surfaces as a small view's scan sees them (a
    sphere's cap before a plane, a step edge, drop-outs and stray points, a few thousand points
    each), every field a scan writes, in its types."""
    import numpy as np

    rng = np.random.default_rng(1)
    clouds = []
    for k, (nx, ny) in enumerate(((80, 60), (64, 48))):
        u, v = np.meshgrid(np.linspace(-40, 40, nx), np.linspace(-30, 30, ny))
        z = 480.0 + 0.2 * u + np.where(u > 20, 15.0, 0.0)
        cap = u**2 + v**2 < (25 - 5 * k) ** 2
        z = np.where(cap, z - np.sqrt(np.maximum((30 - 5 * k) ** 2 - u**2 - v**2, 0.0)), z)
        keep = rng.random(u.shape) > 0.05  # drop-outs, as a scan's failed decodes
        xyz = np.column_stack([u[keep], v[keep], z[keep] + rng.normal(0.0, 0.05, keep.sum())])
        # stray points (a scan's flying pixels at depth edges): chunks and nodes of one point,
        # whose records numpy sees as contiguous (kernels take another signature for them)
        xyz = np.vstack([xyz, [[-90.0, -70.0, 400.0], [95.0, 60.0, 560.0], [90.0, -65.0, 420.0]]])
        clouds.append(_scan_like_cloud(work / f"render_input_{k}.ply", xyz, rng))
    return clouds


def _warm_compress_ranges(work: Path, folders: list[Path]) -> None:
    """Range images of every scan-like folder, lossless (at both encoder efforts: effort 2 runs the
    weighted predictor's kernels) and error-bounded, encoded and decoded."""
    from shared.compress.files import compress_file, decompress_file

    for k, folder in enumerate(folders):
        for name, kw in (("lossless", {}), ("lossless-effort-2", {"effort": 2}), ("bounded", {"max_error": 0.1})):
            packed = compress_file(folder, work / f"range_{k}_{name}.glr", **kw)["output"]
            decompress_file(packed, work / f"range_{k}_{name}")


def _warm_compress_clouds(work: Path, cloud: Path) -> None:
    """A cloud with and without the merged cloud's extra fields, encoded and decoded."""
    from shared.compress.files import compress_file, decompress_file

    for k, ply in enumerate((cloud, _merged_like(work, cloud))):
        packed = compress_file(ply, work / f"cloud_{k}.glo")["output"]
        decompress_file(packed, work / f"cloud_{k}.ply")


def _compress_part(part: str, work: str) -> float:
    """One part of the compress workload (``"ranges"`` or ``"clouds"``) on inputs of its own,
    in ``work``: what a process beside the other domains' runs. Returns its seconds."""
    t = time.perf_counter()
    folder = Path(work) / part
    folder.mkdir()
    folders, cloud = _compress_inputs(folder)
    if part == "ranges":
        _warm_compress_ranges(folder, folders)
    else:
        _warm_compress_clouds(folder, cloud)
    return time.perf_counter() - t


#: The compress workload's parts, each compiled in a process of its own: the range codec's
#: and the cloud codec's kernels share nothing but the rANS coder's small functions.
COMPRESS_PARTS = ("ranges", "clouds")


def _warm_merge(work: Path) -> bool:
    """An eight-view turntable merge of the bunny at 320x240, as a real turntable sees it (static
    removal, registration, fusion, meshing; four views 90 degrees apart overlap too little once
    what does not turn is left out);
    False, with a warning, where the shared meshes are missing or the merge fails (its kernels
    then compile on first use: a warm-up must not stop ``make setup``)."""
    from shared.merge.pipeline import merge_scanset
    from shared.sim.scanset import simulate_scanset
    from shared.sim.scenes import mesh_path

    if not mesh_path("stanford-bunny").is_file():
        log.warning("warm-up: no shared meshes, the merge kernels are left to compile on first use")
        return False
    try:
        folder = work / "scanset"
        simulate_scanset("bunny", folder, views=8, size=(320, 240), projector=(256, 192), seed=0)
        merge_scanset(folder, work / "merged")
    except Exception as exc:  # noqa: BLE001 - reported, and the setup goes on
        log.warning("warm-up: the merge failed (%s); its kernels compile on first use", exc)
        return False
    return True


def _warm_derive() -> None:
    """The texture baker's UV rasteriser on one triangle, with the argument types
    :func:`shared.derive.bake` passes (float32 uv, int32 faces, an int size, int32 face ids,
    float32 barycentric coordinates)."""
    import numpy as np

    from shared.derive._raster import rasterise_uv

    size = 8
    rasterise_uv(np.array([[0.1, 0.1], [0.9, 0.1], [0.5, 0.9]], np.float32), np.array([[0, 1, 2]], np.int32), size,
                 np.full((size, size), -1, np.int32), np.zeros((size, size, 3), np.float32))  # fmt: skip


#: Domains whose workload runs in the side process (:func:`warm`): their kernel modules are
#: used by nothing the other domains run (render's tiles reach the cloud codec's kernels through
#: ``tilenode``, compiled there first), and their work, about half the compile time, balances
#: sim, scan and merge's on the other core.
SIDE_DOMAINS = ("compress", "render")


def warm(domains: Sequence[str] = DOMAINS, work: Path | None = None, parallel: bool = True,
         counts: dict[str, int] | None = None) -> dict[str, float]:
    """Run the pipeline's stages on tiny inputs so that every kernel signature they use is
    compiled and cached (or loaded, when the cache already has it). Returns seconds per part;
    ``counts``, when given, receives the signatures the side process ``compiled`` and
    ``loaded`` (numba's records of that process, which this one cannot see).

    With ``parallel`` the compress and render workloads (:data:`SIDE_DOMAINS`) run at once in a
    process of their own, on inputs of their own (:func:`_compress_inputs`,
    :func:`_render_inputs`), beside sim, scan and merge in this one: numba compiles on one core
    a process. No kernel module is compiled by both processes, so their cache indexes are never
    written by two processes at once. Measured on this 2-core machine from an empty cache: the
    side process's compress and render 35.9-38.1 + 19.0-22.9 s beside sim, scan and merge's
    5.6-5.9 + 21.1-23.1 + 10.1-12.8 s, 59.0-65.5 s wall, since the scan's band kernels left
    numba's parallel loops and kernels stopped compiling numpy's allocations (the same machine,
    before: compress and render 45.6 + 29.8 s beside 6.7 + 61.2 + 12.5 s, 85.6-93.8 s wall). The
    side process is now the longer: render's kernels are still numba parallel loops."""
    seconds: dict[str, float] = {}
    sided = tuple(d for d in SIDE_DOMAINS if d in domains)
    with contextlib.ExitStack() as stack:
        if work is None:
            work = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="graylight-warmup-")))
        side = None
        if sided and parallel:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            # spawn: a fresh interpreter, not a fork of this one's numba and thread state.
            pool = stack.enter_context(ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")))
            side = pool.submit(_side_all, str(work), sided)
        if {"sim", "scan", "merge"} & set(domains):
            t = time.perf_counter()
            captures = _captures(work)
            seconds["sim"] = time.perf_counter() - t
            if "scan" in domains:
                t = time.perf_counter()
                _warm_scan(work, captures)
                seconds["scan"] = time.perf_counter() - t
        if "merge" in domains:
            t = time.perf_counter()
            if _warm_merge(work):
                seconds["merge"] = time.perf_counter() - t
        if "derive" in domains:
            t = time.perf_counter()
            _warm_derive()
            seconds["derive"] = time.perf_counter() - t
        if sided:
            part_seconds, compiled, loaded = side.result() if side is not None else _side_all(str(work), sided)
            seconds.update(part_seconds)
            if counts is not None and side is not None:
                counts.update(compiled=compiled, loaded=loaded)
    return seconds


def _side_all(work: str, domains: Sequence[str]) -> tuple[dict[str, float], int, int]:
    """The workloads of ``domains`` (of :data:`SIDE_DOMAINS`), one after the other, in this
    process: compress's parts, then render's (tiles, previews and exports of scan-like clouds).
    Returns seconds per domain and the signatures of their kernels compiled and loaded from the
    cache here."""
    seconds = {}
    if "compress" in domains:
        seconds["compress"] = sum(_compress_part(part, work) for part in COMPRESS_PARTS)
    if "render" in domains:
        t = time.perf_counter()
        folder = Path(work) / "render"
        folder.mkdir()
        clouds = _render_inputs(folder)
        _warm_render(folder, clouds)
        _warm_export(folder, clouds)
        seconds["render"] = time.perf_counter() - t
    kernels = kernel_dispatchers(domains)
    return (seconds, sum(len(d.stats.cache_misses) for _, d in kernels),
            sum(len(d.stats.cache_hits) for _, d in kernels))  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    """``python -m workers.warmup``: compile every kernel into numba's cache and say so."""
    parser = argparse.ArgumentParser(prog="python -m workers.warmup", description=__doc__.splitlines()[0])
    parser.parse_args(argv)
    t0 = time.perf_counter()
    flushed = flush_stale_kernels()
    if flushed:
        print(f"recompiling kernels whose imported modules changed: {', '.join(flushed)}")
    side: dict[str, int] = {}
    seconds = warm(counts=side)
    # A domain whose workload could not run (the merge without shared meshes) is not checked.
    ran = tuple(d for d in DOMAINS if d in seconds)
    record_kernel_dependencies(ran)
    kernels = kernel_dispatchers(ran)
    compiled = sum(len(d.stats.cache_misses) for _, d in kernels) + side.get("compiled", 0)
    loaded = sum(len(d.stats.cache_hits) for _, d in kernels) + side.get("loaded", 0)
    uncached = [name for name, d in kernels if not cached_signatures(d)]
    parts = ", ".join(f"{k} {v:.1f} s" for k, v in seconds.items())
    # compress and render ran beside the others (a process of their own): the wall time is not the sum.
    print(f"numba kernels: {len(kernels)} kernels, {compiled} signatures compiled, {loaded} loaded from the cache "
          f"in {time.perf_counter() - t0:.1f} s wall ({parts}; {' and '.join(SIDE_DOMAINS)} in a process of their own "
          "beside the others)")
    others = uncovered_kernel_modules()
    if others:
        print(f"kernel modules the warm-up does not run (they compile on first use): {', '.join(others)}")
    if uncached:
        print(f"not cached (never called by the warm-up): {', '.join(uncached)}")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
