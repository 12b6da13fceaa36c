"""``graylight merge SCANSET --out OUT [--drop-unregistered]``: the whole multi-view merge in-process.

Registers the views of a ``graylight-scanset-v1`` scan set, fuses them and meshes the result
(:func:`shared.merge.pipeline.merge_scanset`) with a progress bar on stderr (plain lines when
stderr is not a terminal), then prints where the
results are and how well the views fit. Bad input ends with a one-line error naming the view or
field and exit status 1; nothing is left half-written in OUT.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _cmd_merge(args: argparse.Namespace) -> int:
    from services.cli.progress import progress_bar
    from shared.merge.pipeline import merge_scanset

    with progress_bar("merging") as progress:  # a bar on a terminal, plain lines in a log
        report = merge_scanset(Path(args.scanset), Path(args.out), drop_unregistered=args.drop_unregistered,
                               progress=progress)
    files = report["files"]
    reg = report["registration"]
    print(f"{report['registered_views']} of {report['views']} views registered ({report['method']}), "
          f"worst fit RMS {reg['worst_rms_mm']:.3f} mm; {report['points']['merged']} merged points, "
          f"{report['mesh']['faces']} faces, in {report['seconds']['total']:.1f} s")
    if report["dropped_views"]:
        print(f"left out (registered to nothing): {', '.join(report['dropped_views'])}")
    loop = reg.get("loop_closure")
    if loop:
        print(f"loop closure (pairwise fits chained around the loop): {loop['chained_pairwise_deg']:.3f} deg, "
              f"{loop['chained_pairwise_mm']:.3f} mm")
    axis = reg.get("turntable_axis")
    if axis:
        d = axis["direction"]
        print(f"rotation axis: direction ({d[0]:.5f}, {d[1]:.5f}, {d[2]:.5f}) through "
              f"({', '.join(f'{v:.2f}' for v in axis['point_mm'])}) mm")
    for key in ("merged", "registration", "mesh_ply", "mesh_glb", "report"):
        print(f"{key + ':':<13} {files[key]}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("merge", help="register, fuse and mesh the views of a scan set",
                              description="Merge a graylight-scanset-v1 scan set into one cloud and meshes.")
    p.add_argument("scanset", help="scan set folder (with scanset.json)")
    p.add_argument("--out", required=True, help="output folder (merged.ply, registration.json, mesh.*, report.json)")
    p.add_argument("--drop-unregistered", action="store_true",
                   help="leave out, with a warning, views that register to nothing (default: an error)")
    p.set_defaults(func=_cmd_merge)


__all__ = ["register"]

if __name__ == "__main__":  # pragma: no cover
    from services.cli.main import main

    sys.exit(main())
