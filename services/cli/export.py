"""``graylight export CLOUD --format laz|copc|e57|ply|las --out FILE``: a cloud in the formats
other tools read (:mod:`shared.render.export`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from shared.core.errors import InputError

FORMATS = ("laz", "copc", "e57", "ply", "las")


def _export(args: argparse.Namespace) -> int:
    from shared.render.export import export_cloud  # numba kernels: imported when the command runs

    if args.workers is not None and args.workers < 1:
        raise InputError("--workers", f"must be at least 1, got {args.workers}")
    report = export_cloud(Path(args.cloud), Path(args.out), args.format, workers=args.workers)
    extra = f", coordinate scale {report['scale']:g}" if "scale" in report else ""
    print(
        f"{report['points']} points as {args.format.upper()}, {report['bytes'] / 1e6:.1f} MB in "
        f"{report['seconds']:.1f} s{extra}"
    )
    print(f"{args.format}: {report['output']}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("export", help="write a cloud PLY as LAZ, COPC, E57, PLY or LAS")
    p.add_argument("cloud", help="cloud PLY (x, y, z and any other vertex properties)")
    p.add_argument("--format", required=True, choices=FORMATS, help="output format")
    p.add_argument("--out", required=True, help="output file (written atomically)")
    p.add_argument("--workers", type=int, default=None, help="processes building the COPC octree")
    p.set_defaults(func=_export)
