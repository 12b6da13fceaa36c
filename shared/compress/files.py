"""Files in, files out: what ``graylight compress``/``decompress`` and the ``compress`` job stage call.

:func:`compress_file` takes a scan's output folder (its ``range.npz``), a ``range.npz``, or a
PLY cloud and writes one container file; :func:`decompress_file` turns a container back into
a ``range.npz`` exactly as a scan writes it, or a PLY in the cloud contract. Both return a
small JSON-able summary. Parameters for clouds mean the same as for range images: a
``quantum`` q puts every coordinate on the grid of step q (within q/2); ``max_error`` E keeps
every coordinate within E.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from shared.compress.cloud import read_cloud_to_ply, write_cloud
from shared.compress.range import load_range_npz, read_range, save_range_npz, write_range
from shared.core.errors import InputError
from shared.formats.container import open_container
from shared.formats.ply import iter_ply_records, read_header

RANGE_FILE = "range.npz"
CLOUD_FILE = "cloud.ply"
#: The default quantum: a tenth of a good structured-light scanner's depth noise, 0.02 mm.
DEFAULT_QUANTUM_MM = 0.02
_PER_MM = {"mm": 1.0, "cm": 0.1, "m": 0.001, "um": 1000.0, "in": 1 / 25.4}


def default_quantum(units: str) -> float:
    """:data:`DEFAULT_QUANTUM_MM` in ``units``; InputError for a unit we cannot convert."""
    if units not in _PER_MM:
        raise InputError("--quantum", f"the data is in {units!r}: give --quantum or --max-error explicitly")
    return DEFAULT_QUANTUM_MM * _PER_MM[units]


def input_kind(path: str | os.PathLike[str]) -> tuple[str, Path]:
    """("range", range.npz) or ("cloud", file.ply) for a compress input; InputError otherwise."""
    p = Path(path)
    if p.is_dir():
        if (p / RANGE_FILE).is_file():
            return "range", p / RANGE_FILE
        raise InputError(p, f"folder holds no {RANGE_FILE} (give a scan's output folder, a range.npz or a PLY cloud)")
    if not p.is_file():
        raise InputError(p, "no such file or folder")
    if p.suffix.lower() == ".npz":
        return "range", p
    if p.suffix.lower() == ".ply":
        return "cloud", p
    raise InputError(p, "not a range.npz, a scan folder or a .ply cloud")


def _check_pair(quantum: float | None, max_error: float | None) -> None:
    if quantum is not None and max_error is not None:
        raise InputError("--quantum/--max-error", "give one of them, not both")
    for name, v in (("--quantum", quantum), ("--max-error", max_error)):
        if v is not None and (not math.isfinite(v) or v <= 0):
            raise InputError(name, f"must be a positive number, got {v!r}")


def compress_file(src: str | os.PathLike[str], out: str | os.PathLike[str], *, quantum: float | None = None,
                  max_error: float | None = None, effort: int = 1) -> dict[str, Any]:
    """Compress ``src`` (scan folder, range.npz or PLY) into the container ``out``.

    Range images: lossless at ``quantum`` or within ``max_error`` (default: lossless at
    :data:`DEFAULT_QUANTUM_MM` in the data's units), at the range encoder's ``effort``
    (:data:`shared.compress.range.EFFORTS`). Clouds: geometry on a grid of step ``quantum``, or
    of ``2 * max_error`` (default grid: the default quantum); ``effort`` does not apply.
    """
    _check_pair(quantum, max_error)
    kind, path = input_kind(src)
    t0 = time.perf_counter()
    if kind == "range":
        img = load_range_npz(path)
        if quantum is None and max_error is None:
            quantum = default_quantum(img.units)
        size = write_range(out, img, quantum=quantum, max_error=max_error, effort=effort)
        count = int(np.count_nonzero(~np.isnan(img.z)))
        raw = img.z.nbytes
        per = "bits_per_valid_sample"
    else:
        header = read_header(path)
        units = next((c.split(None, 1)[1] for c in header.comments if c.startswith("units ")), "mm")
        if quantum is None and max_error is None:
            quantum = default_quantum(units)
        if max_error is not None:
            # Voxel centres are within half a cell; leave room for the float32 rounding of the output.
            extent = max((float(np.abs(np.stack([r["x"], r["y"], r["z"]])).max()) for r in iter_ply_records(path) if len(r)),
                         default=1.0)
            ulp = float(np.spacing(np.float32(extent)))
            if max_error <= 2 * ulp:
                raise InputError("--max-error", f"{max_error:g} is finer than float32 can hold at {extent:g} (spacing {ulp:.3g})")
            precision = 2.0 * (max_error - ulp)
        else:
            precision = float(quantum)  # type: ignore[arg-type]
        size = write_cloud(out, path, precision)
        count = header.count
        raw = header.count * header.dtype.itemsize
        per = "bits_per_point"
    seconds = time.perf_counter() - t0
    return {
        "kind": kind,
        "input": str(path),
        "output": str(out),
        "mode": "bounded" if max_error is not None else "lossless",
        "quantum": quantum,
        "max_error": max_error,
        "bytes": size,
        "input_bytes": raw,
        "ratio": raw / size if size else None,
        per: size * 8 / max(count, 1),
        "count": count,
        "seconds": round(seconds, 4),
    }


def decompress_file(src: str | os.PathLike[str], out: str | os.PathLike[str]) -> dict[str, Any]:
    """Decode a container: a range image to ``range.npz`` (``out`` a .npz file, or a folder that
    receives ``range.npz``), a cloud to a PLY (``out`` a .ply file, or a folder for ``cloud.ply``)."""
    header, _ = open_container(src)
    out = Path(out)
    t0 = time.perf_counter()
    if header.kind == "range":
        target = out if out.suffix.lower() == ".npz" else out / RANGE_FILE
        img = read_range(src)
        save_range_npz(target, img)
        count = int(np.count_nonzero(~np.isnan(img.z)))
    else:
        target = out if out.suffix.lower() == ".ply" else out / CLOUD_FILE
        read_cloud_to_ply(src, target)
        count = int(header.meta["points"])
    return {"kind": header.kind, "input": str(src), "output": str(target), "count": count,
            "seconds": round(time.perf_counter() - t0, 4)}
