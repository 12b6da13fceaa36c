"""Export speed: ``graylight export`` to LAZ and COPC against laspy writing the same points
unaided, on a 15 M-point synthetic single-view scan (:func:`tests.support.clouds.synthetic_scan`).

Ours streams the PLY (memory-mapped, 1 M points a chunk) through laspy + lazrs (LAZ), or builds
the octree with the tiles builder and compresses node by node (COPC). The peer is what a laspy
user writes by hand: the whole cloud already in memory as arrays (reading it is not timed),
one ``LasData`` with the same point format and extra bytes (normal, size), written as LAZ with
the same parallel lazrs backend. laspy cannot write COPC, and PDAL (whose writers.copc would
be the COPC peer) is neither on PyPI as a wheel with its library nor cheap to install, so the
COPC figure is set against the same LAZ peer: the price of the octree and its per-node chunks.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import laspy
import numpy as np

from shared.formats.las import coordinate_scale, las_header, las_layout
from shared.formats.ply import read_header, read_ply
from shared.render.export import export_cloud
from tests.support.clouds import synthetic_scan

POINTS = 15_000_000


def _cpu() -> float:
    s = resource.getrusage(resource.RUSAGE_SELF)
    c = resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def _timed(fn) -> tuple[float, float]:
    c0, t0 = _cpu(), time.perf_counter()
    fn()
    return time.perf_counter() - t0, _cpu() - c0


def _laspy_unaided(cloud: Path, out: Path) -> tuple[float, float]:
    """laspy writing the cloud from in-memory arrays (the read is not timed)."""
    pc = read_ply(cloud)
    xyz, rgb, normals, size = (
        np.asarray(pc.xyz),
        np.asarray(pc.rgb),
        np.asarray(pc.normals),
        np.asarray(pc.size),
    )
    lo, hi = xyz.min(axis=0).astype(np.float64), xyz.max(axis=0).astype(np.float64)

    def write() -> None:
        header = las_header(las_layout(read_header(cloud).dtype), coordinate_scale(lo, hi), lo)
        las = laspy.LasData(header)
        las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        las.red, las.green, las.blue = (rgb[:, k].astype(np.uint16) * 257 for k in range(3))
        las.return_number[:] = 1
        las.number_of_returns[:] = 1
        las.NormalX, las.NormalY, las.NormalZ = normals[:, 0], normals[:, 1], normals[:, 2]
        las.size = size
        las.write(out, laz_backend=laspy.LazBackend.LazrsParallel)

    return _timed(write)


_OURS_SCRIPT = """
import sys
from services.cli.main import main
main(["export", sys.argv[1], "--format", "laz", "--out", sys.argv[2]])
"""
_PEER_SCRIPT = """
import sys
from pathlib import Path
from tests.bench.bench_export import _laspy_unaided
_laspy_unaided(Path(sys.argv[1]), Path(sys.argv[2]))
"""
# The process's own high-water mark: VmHWM belongs to its address space since exec (a fork's
# rusage would count the parent's pages it started with).
_HWM = "\nprint([l for l in open('/proc/self/status') if l.startswith('VmHWM')][0].split()[1])\n"


def _peak_mb(script: str, *args: str) -> float:
    """Peak resident memory (MB) of ``script`` run in a fresh Python process."""
    out = subprocess.run(
        [sys.executable, "-c", script + _HWM, *args], check=True, capture_output=True, text=True
    )
    return int(out.stdout.strip().splitlines()[-1]) / 1024


def main() -> None:
    with tempfile.TemporaryDirectory(prefix="graylight-bench-export-") as tmp:
        work = Path(tmp)
        cloud = synthetic_scan(work / "scan15m.ply", POINTS, seed=9)
        n = read_header(cloud).count
        export_cloud(cloud, work / "warm.copc.laz", "copc", workers=None)  # load the kernels once
        (work / "warm.copc.laz").unlink()
        peer, peer_cpu = _laspy_unaided(cloud, work / "peer.laz")
        laz, laz_cpu = _timed(lambda: export_cloud(cloud, work / "ours.laz", "laz"))
        copc, copc_cpu = _timed(lambda: export_cloud(cloud, work / "ours.copc.laz", "copc"))
        sizes = {k: (work / k).stat().st_size / 1e6 for k in ("peer.laz", "ours.laz", "ours.copc.laz")}
        print(f"export, {n / 1e6:.1f} M-point scan (colour, normal, size), {os.cpu_count()} cores:")
        print(f"  laspy unaided LAZ (arrays in memory)  {peer:6.2f} s wall {n / peer / 1e6:5.2f} M pts/s  "
              f"{peer_cpu:6.2f} s CPU  {sizes['peer.laz']:7.1f} MB")  # fmt: skip
        print(f"  graylight export --format laz         {laz:6.2f} s wall {n / laz / 1e6:5.2f} M pts/s  "
              f"{laz_cpu:6.2f} s CPU  {sizes['ours.laz']:7.1f} MB")  # fmt: skip
        print(f"  graylight export --format copc        {copc:6.2f} s wall {n / copc / 1e6:5.2f} M pts/s  "
              f"{copc_cpu:6.2f} s CPU  {sizes['ours.copc.laz']:7.1f} MB")  # fmt: skip
        print(
            f"  ratio LAZ  {peer / laz:.2f}x wall (laspy / ours; > 1 is faster), {peer_cpu / laz_cpu:.2f}x CPU"
        )
        print(
            f"  ratio COPC {peer / copc:.2f}x wall against the same LAZ peer, {peer_cpu / copc_cpu:.2f}x CPU"
        )
        # Peak memory, each in a process of its own: ours streams, the peer holds the cloud.
        ours_mb = _peak_mb(_OURS_SCRIPT, str(cloud), str(work / "mem.laz"))
        peer_mb = _peak_mb(_PEER_SCRIPT, str(cloud), str(work / "mem_peer.laz"))
        print(f"  peak memory LAZ: ours {ours_mb:.0f} MB, laspy unaided {peer_mb:.0f} MB "
              f"(ours counts the pages of the memory-mapped {cloud.stat().st_size / 1e6:.0f} MB PLY it read, which the "
              "kernel can drop; the peer holds the cloud in arrays)")  # fmt: skip
        load = os.getloadavg()[0]
        if load > (os.cpu_count() or 1) * 0.75:
            print(f"  note: load average {load:.1f} on {os.cpu_count()} cores: other work shares the CPUs")


if __name__ == "__main__":
    main()
